//! DJI C620 / C610 (`dbc/dji_c620.dbc`): ESC ids, current commands and feedback.

use firmware::protocol::DecodeError;
use firmware::protocol::dji::{self, EscGroup, EscId, EscModel};

use crate::{assert_close, frame, sid};

#[test]
fn esc_id_range() {
    assert_eq!(EscId::new(0), None);
    assert_eq!(EscId::new(9), None);
    let e = EscId::new(6).unwrap();
    assert_eq!((e.group(), e.slot()), (EscGroup::Esc5To8, 1));
    assert_eq!(e.feedback_id(), sid(0x206));
    assert!(dji::is_dji_id(0x1FF) && dji::is_dji_id(0x208) && !dji::is_dji_id(0x209));
}

#[test]
fn dji_current_command() {
    // raw 1000 = 0x03E8, -1000 = 0xFC18, 16384 = 0x4000, -16384 = 0xC000, big-endian.
    let data = [0x03, 0xE8, 0xFC, 0x18, 0x40, 0x00, 0xC0, 0x00];
    let c = dji::CurrentCommand {
        model: EscModel::C620,
        group: EscGroup::Esc1To4,
        raw: [1000, -1000, 16384, -16384],
    };
    let f = frame(0x200, &data);
    assert_eq!(dji::CurrentCommand::decode(&f, EscModel::C620), Ok(c));
    assert_eq!(c.to_can_frame(), f);
    assert_eq!(c.amps(), [1.220_703_1, -1.220_703_1, 20.0, -20.0]);
    let high = dji::CurrentCommand {
        group: EscGroup::Esc5To8,
        ..c
    };
    assert_eq!(high.to_can_frame(), frame(0x1FF, &data));
    // From amperes: rounded and clamped to ±20 A.
    let from_amps = dji::CurrentCommand::from_amps(
        EscModel::C620,
        EscGroup::Esc1To4,
        [1.2207031, -1.2207031, 25.0, f32::NEG_INFINITY],
    );
    assert_eq!(from_amps, c);
    // C610: ±10000 raw = ±10 A; 16384 is out of range for it.
    assert_eq!(
        dji::CurrentCommand::decode(&f, EscModel::C610),
        Err(DecodeError::OutOfRange {
            field: "current_3",
            value: 16384
        })
    );
    let c610 = dji::CurrentCommand::from_amps(
        EscModel::C610,
        EscGroup::Esc5To8,
        [10.0, -10.0, 0.001, 11.0],
    );
    assert_eq!(c610.raw, [10000, -10000, 1, 10000]);
    assert_eq!(
        c610.to_can_frame(),
        frame(0x1FF, &[0x27, 0x10, 0xD8, 0xF0, 0x00, 0x01, 0x27, 0x10])
    );
    // Encoding clamps raw values beyond the model's limit.
    let over = dji::CurrentCommand {
        model: EscModel::C620,
        group: EscGroup::Esc1To4,
        raw: [i16::MAX, i16::MIN, 0, 0],
    };
    assert_eq!(
        over.to_can_frame(),
        frame(0x200, &[0x40, 0x00, 0xC0, 0x00, 0, 0, 0, 0])
    );
}

#[test]
fn dji_feedback() {
    // angle 8191 = 0x1FFF, speed 1000 rpm = 0x03E8, current -1000 = 0xFC18, 37 °C, unused.
    let f = frame(0x203, &[0x1F, 0xFF, 0x03, 0xE8, 0xFC, 0x18, 0x25, 0x00]);
    let fb = dji::Feedback {
        model: EscModel::C620,
        esc: EscId::new(3).unwrap(),
        rotor_angle: 8191,
        rotor_speed_rpm: 1000,
        torque_current: -1000,
        temperature_c: 37,
    };
    assert_eq!(dji::Feedback::decode(&f, EscModel::C620), Ok(fb));
    assert_eq!(fb.to_can_frame(), f);
    assert_close(fb.rotor_speed_rad_s(), 104.719_76, 1e-4);
    assert_close(
        fb.rotor_angle_rad(),
        core::f32::consts::TAU * 8191.0 / 8192.0,
        1e-6,
    );
    assert_close(fb.current_amps(), -1.220_703_1, 1e-6);
    assert_eq!(
        dji::decode(&f, EscModel::C620),
        Ok(dji::Message::Feedback(fb))
    );
    // Angle 8192 is rejected.
    assert_eq!(
        dji::Feedback::decode(
            &frame(0x203, &[0x20, 0x00, 0, 0, 0, 0, 0, 0]),
            EscModel::C620
        ),
        Err(DecodeError::OutOfRange {
            field: "rotor_angle",
            value: 8192
        })
    );
    // Unknown id, wrong DLC.
    assert!(matches!(
        dji::decode(&frame(0x209, &[0; 8]), EscModel::C620),
        Err(DecodeError::UnknownId { .. })
    ));
    assert_eq!(
        dji::decode(&frame(0x201, &[0; 6]), EscModel::C620),
        Err(DecodeError::WrongDlc {
            id: 0x201,
            expected: 8,
            got: 6
        })
    );
}
