//! The parameter service (`docs/protocol.md`, "Parameters"): reads, a write in force from the
//! next step with the heartbeat's config id, refusals on the wire, and gains changed while
//! driving without a step in the current.

use firmware::control::{INFO_INDEX, LOAD_SIGNATURE, RESTORE, SAVE_SIGNATURE, STORE};
use firmware::protocol::canopen::{self, Message, SdoRequest, SdoResponse};
use firmware::protocol::robot::{PROTOCOL_VERSION, Telemetry};
use firmware::storage::{Layout, RECORD_BYTES, RamFlash, Store};
use kinematics::ChassisVelocity;

use crate::rig::*;

fn request(rig: &mut Rig, request: SdoRequest) {
    let node = canopen::NodeId::new(rig.ctl.param_node()).unwrap();
    rig.raw(Message::SdoRequest { node, request }.to_can_frame());
}

/// The service's response in a step's frames.
fn response(rig: &Rig, out: &Outbox) -> Option<SdoResponse> {
    out.iter().find_map(|f| match canopen::decode(f) {
        Ok(Message::SdoResponse { node, response }) if node.get() == rig.ctl.param_node() => {
            Some(response)
        }
        _ => None,
    })
}

/// One request, served at the next step: its response.
fn ask(rig: &mut Rig, r: SdoRequest) -> SdoResponse {
    request(rig, r);
    let out = rig.tick();
    response(rig, &out).expect("answered at the next step")
}

fn write(index: u16, sub: u8, value: u32, size: u8) -> SdoRequest {
    SdoRequest::Download {
        index,
        sub,
        value,
        size,
    }
}

fn abort_of(r: SdoResponse) -> u32 {
    match r {
        SdoResponse::Abort { code, .. } => code,
        other => panic!("not refused: {other:?}"),
    }
}

#[test]
fn reads_give_the_values_in_force_and_the_identity() {
    let mut rig = Rig::dji();
    assert_eq!(rig.ctl.param_node(), 127);
    let read = |rig: &mut Rig, index, sub| ask(rig, SdoRequest::Upload { index, sub });
    let kp = rig.config.gains.kp.to_bits();
    assert_eq!(
        read(&mut rig, 0x2002, 1),
        SdoResponse::Uploaded {
            index: 0x2002,
            sub: 1,
            value: kp,
            size: 4
        }
    );
    assert_eq!(
        read(&mut rig, 0x1018, 3),
        SdoResponse::Uploaded {
            index: 0x1018,
            sub: 3,
            value: u32::from(PROTOCOL_VERSION),
            size: 4
        }
    );
    assert_eq!(
        read(&mut rig, 0x2002, 0),
        SdoResponse::Uploaded {
            index: 0x2002,
            sub: 0,
            value: 3,
            size: 1
        }
    );
    assert_eq!(abort_of(read(&mut rig, 0x3000, 1)), 0x0602_0000);
    assert_eq!(abort_of(read(&mut rig, 0x2002, 9)), 0x0609_0011);
    // The general layout's wheels are not in a standard-layout configuration.
    assert_eq!(abort_of(read(&mut rig, 0x2010, 1)), 0x0609_0011);
    // With CiA 402 drives the service is their master's node.
    let cia402 = Rig::new(Config::cia402_example());
    let Drive::Cia402(d) = cia402.config.drive else {
        unreachable!()
    };
    assert_eq!(cia402.ctl.param_node(), d.master_node);
}

#[test]
fn a_write_is_in_force_from_the_next_step_and_the_heartbeat_sends_its_id() {
    let mut rig = Rig::dji();
    let before = rig.ctl.config_id();
    request(&mut rig, write(0x2003, 5, 250, 4)); // timing.command_timeout_ms
    assert_eq!(
        rig.ctl.config().timing.command_timeout_ms,
        100,
        "not before the step"
    );
    let out = rig.tick();
    assert_eq!(
        response(&rig, &out),
        Some(SdoResponse::Downloaded {
            index: 0x2003,
            sub: 5
        })
    );
    assert_eq!(rig.ctl.config().timing.command_timeout_ms, 250);
    let mut want = rig.config;
    want.timing.command_timeout_ms = 250;
    assert_eq!(rig.ctl.config_id(), want.id());
    assert_ne!(want.id(), before);
    // The next HEARTBEAT (10 Hz) carries the new id.
    let heartbeat = |out: &Outbox| {
        out.iter().find_map(|f| match Telemetry::decode(f) {
            Ok(Telemetry::Heartbeat(h)) => Some(h.config_id),
            _ => None,
        })
    };
    let sent = (0..200).find_map(|_| heartbeat(&rig.tick()));
    assert_eq!(sent, Some(want.id()));
}

#[test]
fn refusals_go_out_with_their_abort_code_and_change_nothing() {
    let mut rig = Rig::dji();
    rig.enable();
    rig.twist(0.3, 0.0, 0.0);
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    let config = *rig.ctl.config();
    let cases = [
        (write(0x2000, 1, 0.3f32.to_bits(), 4), 0x0800_0022), // geometry.lx while enabled
        (write(0x2002, 1, 150f32.to_bits(), 4), 0x0609_0031), // gains.kp above 100
        (write(0x2002, 2, (-1f32).to_bits(), 4), 0x0609_0032), // gains.ki below 0
        (write(0x2002, 1, f32::NAN.to_bits(), 4), 0x0609_0030), // NaN
        (write(0x2001, 8, 25f32.to_bits(), 4), 0x0609_0030),  // above the C620's 20 A
        (write(0x2005, 1, 1, 1), 0x0601_0002),                // drive.protocol
        (write(0x2002, 1, 2, 2), 0x0607_0010),                // a REAL32 in 2 bytes
        (write(0x1018, 3, 9, 4), 0x0601_0002),                // the identity
        (write(0x3000, 1, 0, 4), 0x0602_0000),                // no such object
    ];
    for (r, code) in cases {
        rig.twist(0.3, 0.0, 0.0);
        assert_eq!(abort_of(ask(&mut rig, r)), code, "{r:?}");
    }
    assert_eq!(*rig.ctl.config(), config);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

/// A gain set while the robot drives: the current at the step it takes effect is the one the
/// old gains would have commanded (within 0.02 A), where a bare switch would have stepped by
/// `Δkp · error` (over 0.5 A here); and the new gain is the one in force afterwards.
#[test]
fn a_gain_changed_while_driving_does_not_step_the_current() {
    let mut rig = Rig::dji();
    let kin = rig.config.kinematics().unwrap();
    let signs = match rig.config.drive {
        Drive::Dji { inverted, .. } => inverted.map(|i| if i { -1.0 } else { 1.0 }),
        _ => unreachable!(),
    };
    rig.enable();
    for _ in 0..300 {
        rig.twist(0.4, 0.0, 0.0);
        // The wheels lag their setpoints by 15 %: an error the proportional term acts on.
        let wheels = kin.inverse(ChassisVelocity::new(0.4, 0.0, 0.0)).0;
        rig.speed = core::array::from_fn(|i| signs[i] * wheels[i] * 0.85);
        rig.run_ms(1);
    }
    let error = kin.inverse(ChassisVelocity::new(0.4, 0.0, 0.0)).0[0] * 0.15;
    let (old_kp, new_kp) = (rig.config.gains.kp, 2.0 * rig.config.gains.kp);
    assert!(
        (new_kp - old_kp) * error > 0.5,
        "the test needs an error to act on: {error}"
    );
    let mut twin = Rig::new(rig.config);
    twin.ctl = rig.ctl.clone();
    (twin.now_us, twin.rotor, twin.speed, twin.seq) = (rig.now_us, rig.rotor, rig.speed, rig.seq);
    request(&mut rig, write(0x2002, 1, new_kp.to_bits(), 4));
    let (out, twin_out) = (rig.tick(), twin.tick());
    let (with, without) = (
        dji_currents(&out).unwrap(),
        dji_currents(&twin_out).unwrap(),
    );
    for i in 0..4 {
        assert!(
            (with[i] - without[i]).abs() < 0.02,
            "wheel {i}: {} A against {} A",
            with[i],
            without[i]
        );
    }
    assert_eq!(rig.ctl.config().gains.kp, new_kp);
}

/// Steps until the response to a save or restore, the store on `flash` serving the core after
/// every step as a board does (three words a step): the response and the steps it took.
fn until_answered(rig: &mut Rig, store: &mut Store, flash: &mut RamFlash) -> (SdoResponse, u32) {
    for steps in 1..=200 {
        let out = rig.tick();
        if let Some(r) = response(rig, &out) {
            return (r, steps);
        }
        store.serve(&mut rig.ctl, flash, 3);
    }
    panic!("no response in 200 steps");
}

const LAYOUT: Layout = Layout {
    starts: [0x4000, 0x8000],
    sector_bytes: 0x4000,
};

#[test]
fn a_save_is_answered_once_stored_and_a_new_controller_boots_it() {
    let mut rig = Rig::dji();
    let mut flash = RamFlash::new(0xC000);
    let (mut store, found) = Store::mount(&mut flash, LAYOUT, &rig.config).unwrap();
    assert_eq!(found.saved, None);
    let kp = 1.5f32;
    assert!(matches!(
        ask(&mut rig, write(0x2002, 1, kp.to_bits(), 4)),
        SdoResponse::Downloaded { .. }
    ));
    request(&mut rig, write(STORE, 1, SAVE_SIGNATURE, 4));
    let (r, steps) = until_answered(&mut rig, &mut store, &mut flash);
    assert_eq!(
        r,
        SdoResponse::Downloaded {
            index: STORE,
            sub: 1
        }
    );
    // Served at the first step, 72 words at 3 after each step from it (24 steps), answered
    // at the step after the last: 25 periods, 25 ms at 1 kHz.
    assert_eq!(steps, 25);
    assert!(steps <= 30, "a save acknowledged within 30 ms");
    let info = |rig: &mut Rig, sub| match ask(
        rig,
        SdoRequest::Upload {
            index: INFO_INDEX,
            sub,
        },
    ) {
        SdoResponse::Uploaded { value, .. } => value,
        other => panic!("{other:?}"),
    };
    let running = u32::from(rig.ctl.config_id());
    assert_eq!(info(&mut rig, 1), running);
    assert_eq!(info(&mut rig, 2), u32::from(rig.config.id()));
    assert_eq!((info(&mut rig, 3), info(&mut rig, 4)), (running, 1));

    // A boot on that flash runs the saved set.
    let (_, found) = Store::mount(&mut flash, LAYOUT, &rig.config).unwrap();
    let saved = found.saved.expect("saved");
    assert_eq!(saved.config.gains.kp, kp);
    let booted = Controller::new(&rig.config)
        .unwrap()
        .with_saved(&saved.config, saved.seq)
        .unwrap();
    assert_eq!(u32::from(booted.config_id()), running);
    assert_eq!(booted.builtin_id(), rig.config.id());
}

#[test]
fn save_and_restore_refusals_name_their_rule() {
    let mut rig = Rig::dji();
    let mut flash = RamFlash::new(0xC000);
    let (mut store, _) = Store::mount(&mut flash, LAYOUT, &rig.config).unwrap();
    // Without the signature, another sub-index, another size.
    assert_eq!(
        abort_of(ask(&mut rig, write(STORE, 1, LOAD_SIGNATURE, 4))),
        0x0800_0020
    );
    assert_eq!(
        abort_of(ask(&mut rig, write(RESTORE, 1, SAVE_SIGNATURE, 4))),
        0x0800_0020
    );
    assert_eq!(
        abort_of(ask(&mut rig, write(STORE, 2, SAVE_SIGNATURE, 4))),
        0x0609_0011
    );
    assert_eq!(
        abort_of(ask(&mut rig, write(STORE, 1, 0x73, 1))),
        0x0607_0010
    );
    // A second save while one is stored.
    request(&mut rig, write(STORE, 1, SAVE_SIGNATURE, 4));
    rig.tick();
    store.serve(&mut rig.ctl, &mut flash, 3);
    assert_eq!(
        abort_of(ask(&mut rig, write(STORE, 1, SAVE_SIGNATURE, 4))),
        0x0800_0022
    );
    let (r, _) = until_answered(&mut rig, &mut store, &mut flash);
    assert!(matches!(r, SdoResponse::Downloaded { .. }));
    // A restore while driving.
    rig.enable();
    assert_eq!(
        abort_of(ask(&mut rig, write(RESTORE, 1, LOAD_SIGNATURE, 4))),
        0x0800_0022
    );
}

#[test]
fn a_restore_puts_the_built_in_set_in_force_and_saves_it() {
    let mut rig = Rig::dji();
    let mut flash = RamFlash::new(0xC000);
    let (mut store, _) = Store::mount(&mut flash, LAYOUT, &rig.config).unwrap();
    let builtin = rig.ctl.config_id();
    ask(&mut rig, write(0x2002, 1, 2.0f32.to_bits(), 4));
    assert_ne!(rig.ctl.config_id(), builtin);
    request(&mut rig, write(RESTORE, 1, LOAD_SIGNATURE, 4));
    let (r, _) = until_answered(&mut rig, &mut store, &mut flash);
    assert_eq!(
        r,
        SdoResponse::Downloaded {
            index: RESTORE,
            sub: 1
        }
    );
    assert_eq!(rig.ctl.config_id(), builtin);
    let (_, found) = Store::mount(&mut flash, LAYOUT, &rig.config).unwrap();
    assert_eq!(found.saved.map(|s| s.config.id()), Some(builtin));
}

#[test]
fn a_full_store_refuses_the_save_at_the_next_step() {
    let mut rig = Rig::dji();
    // Room for one record in each sector.
    let layout = Layout {
        starts: [0, RECORD_BYTES as u32],
        sector_bytes: RECORD_BYTES as u32,
    };
    let mut flash = RamFlash::new(2 * RECORD_BYTES);
    let (mut store, _) = Store::mount(&mut flash, layout, &rig.config).unwrap();
    for _ in 0..2 {
        request(&mut rig, write(STORE, 1, SAVE_SIGNATURE, 4));
        assert!(matches!(
            until_answered(&mut rig, &mut store, &mut flash).0,
            SdoResponse::Downloaded { .. }
        ));
    }
    request(&mut rig, write(STORE, 1, SAVE_SIGNATURE, 4));
    let (r, steps) = until_answered(&mut rig, &mut store, &mut flash);
    assert_eq!((abort_of(r), steps), (0x0800_0020, 2));
}
