//! Frames the core rejects, counts by kind, and never acts on.

use crate::rig::*;

/// `frame` with its data replaced: `edit` gets the 8-byte buffer, `dlc` sets the length.
fn tampered(frame: CanFrame, dlc: u8, edit: impl FnOnce(&mut [u8; 8])) -> CanFrame {
    let mut data = [0u8; 8];
    let src = embedded_can::Frame::data(&frame);
    data[..src.len()].copy_from_slice(src);
    edit(&mut data);
    let id = embedded_can::Frame::id(&frame);
    let embedded_can::Id::Standard(id) = id else {
        panic!("standard ids only")
    };
    CanFrame::from_buffer(id, data, dlc)
}

#[test]
fn rejected_commands_are_counted_and_never_feed_the_watchdog() {
    let twist = |vx| {
        Command::Twist(TwistCmd {
            vx,
            vy: 0.0,
            wz: 0.0,
            seq: 1,
        })
    };
    // Faster than limits.max_linear_speed (3 m/s): rejected by the core.
    let too_fast = twist(5.0).to_can_frame();
    // vx raw = -32768, reserved as invalid: rejected by the decoder.
    let reserved = tampered(twist(0.1).to_can_frame(), 8, |d| {
        d[0] = 0x00;
        d[1] = 0x80;
    });
    // Wrong DLC.
    let short = tampered(twist(0.1).to_can_frame(), 5, |_| {});

    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.enable();
    rig.twist(0.3, 0.0, 0.0);
    let t_cmd = rig.now_us;
    let mut zero_at = None;
    for _ in 0..300 {
        rig.raw(too_fast);
        rig.raw(reserved);
        rig.raw(short);
        let t = rig.now_us;
        let out = rig.tick();
        if odrive_vels(&rig.config, &out).is_some_and(all_zero) {
            zero_at.get_or_insert(t);
        }
    }
    let dt = zero_at.expect("watchdog stopped the robot") - t_cmd;
    assert!(dt <= 110_000, "invalid commands kept it alive: {dt} us");
    rig.send(Command::StatusRequest);
    rig.tick();
    let snap = rig.ctl.snapshot();
    assert_eq!(snap.rx_errors.out_of_range, 600);
    assert_eq!(snap.rx_errors.wrong_dlc, 300);
    let status = rig.status();
    assert_eq!(status.rx_errors, 900);
    assert_eq!(status.unknown_ids, 0);
}

/// A frame as a driver that reports the DLC register unchanged gives it (embassy-stm32 0.6):
/// a classic frame may carry DLC 9-15, and `data()` slices the 8-byte buffer by the DLC.
struct RawDlcFrame {
    id: embedded_can::Id,
    dlc: usize,
    data: [u8; 8],
}

impl embedded_can::Frame for RawDlcFrame {
    fn new(_: impl Into<embedded_can::Id>, _: &[u8]) -> Option<Self> {
        None
    }
    fn new_remote(_: impl Into<embedded_can::Id>, _: usize) -> Option<Self> {
        None
    }
    fn is_extended(&self) -> bool {
        false
    }
    fn is_remote_frame(&self) -> bool {
        false
    }
    fn id(&self) -> embedded_can::Id {
        self.id
    }
    fn dlc(&self) -> usize {
        self.dlc
    }
    fn data(&self) -> &[u8] {
        &self.data[..self.dlc]
    }
}

#[test]
fn a_dlc_above_8_is_a_wrong_dlc_not_a_panic() {
    for (mut rig, ids) in [
        (Rig::dji(), [0x201u16, 0x301, 0x300]),
        (Rig::odrive(), [0x009, 0x001, 0x301]),
    ] {
        rig.run_ms(5);
        let before = rig.ctl.snapshot().rx_errors.wrong_dlc;
        for id in ids {
            for dlc in 9..=15 {
                let frame = RawDlcFrame {
                    id: embedded_can::StandardId::new(id).unwrap().into(),
                    dlc,
                    data: [0; 8],
                };
                rig.ctl.on_frame(rig.now(), &frame);
                assert_eq!(CanFrame::from_frame(&frame), None);
            }
        }
        assert_eq!(rig.ctl.snapshot().rx_errors.wrong_dlc - before, 3 * 7);
    }
}

#[test]
fn non_finite_feedback_is_rejected_and_counted() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    let node = NodeId::new(0).unwrap();
    let est = odrive::Feedback::EncoderEstimates { pos: 1.0, vel: 0.0 }.to_can_frame(node);
    let f = tampered(est, 8, |d| d[0..4].copy_from_slice(&f32::NAN.to_le_bytes()));
    let pose_before = rig.ctl.pose();
    rig.raw(f);
    rig.run_ms(1);
    assert_eq!(rig.ctl.snapshot().rx_errors.non_finite, 1);
    assert_eq!(rig.ctl.pose(), pose_before);
}

#[test]
fn another_hosts_odrive_requests_are_neither_feedback_nor_errors() {
    let mut rig = odrive_driving();
    let pose_before = rig.ctl.pose();
    let before = rig.ctl.snapshot().rx_errors;
    let node = NodeId::new(0).unwrap();
    // An odrivetool-style poll of every message the core reads, as RTR and as empty frames.
    for cmd in [
        odrive::Command::GetHeartbeat,
        odrive::Command::GetError,
        odrive::Command::GetEncoderEstimates,
    ] {
        let rtr = cmd.to_can_frame(node);
        rig.raw(rtr);
        rig.raw(tampered(rtr, 0, |_| {}));
    }
    rig.run_ms(1);
    let snap = rig.ctl.snapshot();
    assert_eq!(snap.rx_errors, before, "requests counted as errors");
    assert_eq!(snap.state, RobotState::Enabled);
    // The pose moved by the step's driving only, not by a request read as estimates.
    assert!((rig.ctl.pose().x - pose_before.x).abs() < 1e-3);
}

#[test]
fn unknown_ids_are_counted_separately() {
    let mut rig = Rig::dji();
    rig.run_ms(2);
    for id in [0x123u16, 0x7FF, 0x209] {
        rig.raw(CanFrame::from_buffer(
            embedded_can::StandardId::new(id).unwrap(),
            [0; 8],
            8,
        ));
    }
    rig.send(Command::StatusRequest);
    rig.tick();
    let s = rig.status();
    assert_eq!((s.unknown_ids, s.rx_errors), (3, 0));
    assert_eq!(s.motors_online, 0b1111);
}
