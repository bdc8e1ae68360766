//! The robot protocol (`dbc/mecanum_robot.dbc`): every message, its extremes and reserved
//! values, the rejections, and the DBC's value-table names.

use embedded_can::{ExtendedId, Frame, Id};
use firmware::CanFrame;
use firmware::protocol::robot::{
    self, Fault, HeadingSource, Heartbeat, ImuYawRate, ModeRequest, OdomPosition, OdomVelocity,
    RobotState, Status, StatusCounters, TwistCmd,
};
use firmware::protocol::{DecodeError, ErrorKind};

use crate::{assert_close, frame, sid};

#[test]
fn robot_estop() {
    let f = frame(0x300, &[0xE5]);
    assert_eq!(robot::Command::decode(&f), Ok(robot::Command::Estop));
    assert_eq!(robot::Command::Estop.to_can_frame(), f);
    assert_eq!(
        robot::Command::decode(&frame(0x300, &[0xE4])),
        Err(DecodeError::OutOfRange {
            field: "magic",
            value: 0xE4
        })
    );
}

#[test]
fn robot_twist() {
    // vx 500 mm/s = 0x01F4, vy -250 = 0xFF06, wz 1000 mrad/s = 0x03E8, seq 7, reserved 0.
    let f = frame(0x301, &[0xF4, 0x01, 0x06, 0xFF, 0xE8, 0x03, 0x07, 0x00]);
    let twist = TwistCmd {
        vx: 0.5,
        vy: -0.25,
        wz: 1.0,
        seq: 7,
    };
    assert_eq!(robot::Command::decode(&f), Ok(robot::Command::Twist(twist)));
    assert_eq!(robot::Command::Twist(twist).to_can_frame(), f);
    // The reserved byte is ignored on receipt.
    let g = frame(0x301, &[0xF4, 0x01, 0x06, 0xFF, 0xE8, 0x03, 0x07, 0x55]);
    assert_eq!(robot::Command::decode(&g), Ok(robot::Command::Twist(twist)));
}

#[test]
fn robot_twist_extremes_and_reserved_raw() {
    // ±32767 are the limits; -32768 (0x8000) is reserved and rejected.
    let f = frame(0x301, &[0xFF, 0x7F, 0x01, 0x80, 0x00, 0x00, 0x00, 0x00]);
    match robot::Command::decode(&f).unwrap() {
        robot::Command::Twist(t) => {
            assert_close(t.vx, 32.767, 1e-6);
            assert_close(t.vy, -32.767, 1e-6);
        }
        other => panic!("{other:?}"),
    }
    for offset in [0, 2, 4] {
        let mut data = [0u8; 8];
        data[offset + 1] = 0x80;
        let err = robot::Command::decode(&frame(0x301, &data)).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::OutOfRange);
        assert!(matches!(err, DecodeError::OutOfRange { value: -32768, .. }));
    }
    // Encoding saturates symmetrically and maps NaN to 0.
    let t = TwistCmd {
        vx: 1e9,
        vy: f32::NEG_INFINITY,
        wz: f32::NAN,
        seq: 0,
    };
    assert_eq!(
        robot::Command::Twist(t).to_can_frame(),
        frame(0x301, &[0xFF, 0x7F, 0x01, 0x80, 0x00, 0x00, 0x00, 0x00])
    );
}

#[test]
fn robot_mode_and_status_request() {
    for (raw, req) in [
        (0u8, ModeRequest::Disable),
        (1, ModeRequest::Enable),
        (2, ModeRequest::Reset),
    ] {
        let f = frame(0x302, &[raw]);
        assert_eq!(robot::Command::decode(&f), Ok(robot::Command::Mode(req)));
        assert_eq!(robot::Command::Mode(req).to_can_frame(), f);
    }
    assert_eq!(
        robot::Command::decode(&frame(0x302, &[3])),
        Err(DecodeError::OutOfRange {
            field: "request",
            value: 3
        })
    );
    let f = frame(0x303, &[]);
    assert_eq!(
        robot::Command::decode(&f),
        Ok(robot::Command::StatusRequest)
    );
    assert_eq!(robot::Command::StatusRequest.to_can_frame(), f);
    assert_eq!(
        robot::Command::decode(&frame(0x303, &[0])),
        Err(DecodeError::WrongDlc {
            id: 0x303,
            expected: 0,
            got: 1
        })
    );
}

#[test]
fn robot_imu_yaw_rate() {
    // 0.5 rad/s = 0x3F000000 little-endian, seq 7, reserved 0.
    let f = frame(0x304, &[0x00, 0x00, 0x00, 0x3F, 0x07, 0, 0, 0]);
    let g = robot::Command::ImuYawRate(ImuYawRate {
        yaw_rate: 0.5,
        seq: 7,
    });
    assert_eq!(robot::Command::decode(&f), Ok(g));
    assert_eq!(g.to_can_frame(), f);
    // Clockwise: -1.5 rad/s = 0xBFC00000; reserved bytes are ignored on receipt.
    let f = frame(0x304, &[0x00, 0x00, 0xC0, 0xBF, 0xFF, 0xAA, 0xBB, 0xCC]);
    assert_eq!(
        robot::Command::decode(&f),
        Ok(robot::Command::ImuYawRate(ImuYawRate {
            yaw_rate: -1.5,
            seq: 255
        }))
    );
    // ±35 rad/s is the edge of the range; a hair beyond is out of range (raw = the bits).
    let at_edge = 35.0f32.to_le_bytes();
    let beyond = 35.000_004f32;
    assert!(
        robot::Command::decode(&frame(
            0x304,
            &[at_edge[0], at_edge[1], at_edge[2], at_edge[3], 0, 0, 0, 0]
        ))
        .is_ok()
    );
    let b = beyond.to_le_bytes();
    assert_eq!(
        robot::Command::decode(&frame(0x304, &[b[0], b[1], b[2], b[3], 0, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "yaw_rate",
            value: i64::from(beyond.to_bits())
        })
    );
    // NaN and infinities are non-finite, with their bits.
    for bits in [0x7FC0_0000u32, 0x7F80_0000, 0xFF80_0000] {
        let b = bits.to_le_bytes();
        assert_eq!(
            robot::Command::decode(&frame(0x304, &[b[0], b[1], b[2], b[3], 1, 0, 0, 0])),
            Err(DecodeError::NonFinite {
                field: "yaw_rate",
                bits
            })
        );
    }
    assert_eq!(
        robot::Command::decode(&frame(0x304, &[0; 7])),
        Err(DecodeError::WrongDlc {
            id: 0x304,
            expected: 8,
            got: 7
        })
    );
    // The encoder never sends what the decoder refuses: NaN as 0, beyond ±35 saturated.
    for (rate, sent) in [
        (f32::NAN, 0.0),
        (f32::INFINITY, 35.0),
        (-1e9, -35.0),
        (-0.0, -0.0),
    ] {
        let g = robot::Command::ImuYawRate(ImuYawRate {
            yaw_rate: rate,
            seq: 1,
        });
        let Ok(robot::Command::ImuYawRate(back)) = robot::Command::decode(&g.to_can_frame()) else {
            panic!("{rate} did not round-trip");
        };
        assert_eq!(back.yaw_rate.to_bits(), f32::to_bits(sent), "{rate}");
    }
}

#[test]
fn robot_odom_position() {
    // x 1.0 m = 10000 = 0x00002710, y -2.5 m = -25000 = 0xFFFF9E58.
    let f = frame(0x310, &[0x10, 0x27, 0x00, 0x00, 0x58, 0x9E, 0xFF, 0xFF]);
    let o = OdomPosition { x: 1.0, y: -2.5 };
    assert_eq!(
        robot::Telemetry::decode(&f),
        Ok(robot::Telemetry::OdomPosition(o))
    );
    assert_eq!(robot::Telemetry::OdomPosition(o).to_can_frame(), f);
}

#[test]
fn robot_odom_velocity() {
    // heading 1.2345 rad = 12345 = 0x3039, vx -0.001 = 0xFFFF, vy 32.767 = 0x7FFF,
    // wz -32.767 = 0x8001.
    let f = frame(0x311, &[0x39, 0x30, 0xFF, 0xFF, 0xFF, 0x7F, 0x01, 0x80]);
    let robot::Telemetry::OdomVelocity(o) = robot::Telemetry::decode(&f).unwrap() else {
        panic!("not odometry velocity");
    };
    assert_close(o.heading, 1.2345, 1e-6);
    assert_close(o.vx, -0.001, 1e-9);
    assert_close(o.vy, 32.767, 1e-6);
    assert_close(o.wz, -32.767, 1e-6);
    let sent = OdomVelocity {
        heading: 1.2345,
        vx: -0.001,
        vy: 32.767,
        wz: -32.767,
    };
    assert_eq!(robot::Telemetry::OdomVelocity(sent).to_can_frame(), f);
    // Headings are wrapped into -π..π when encoded: 2π + 1.2345 sends 1.2345.
    let wrapped = OdomVelocity {
        heading: 1.2345 + core::f32::consts::TAU,
        ..sent
    };
    assert_eq!(robot::Telemetry::OdomVelocity(wrapped).to_can_frame(), f);
    // Raw ±31416 (just over π) decode and re-encode unchanged.
    for data in [
        [0xB8u8, 0x7A, 0, 0, 0, 0, 0, 0],
        [0x48, 0x85, 0, 0, 0, 0, 0, 0],
    ] {
        let m = robot::Telemetry::decode(&frame(0x311, &data)).unwrap();
        assert_eq!(m.to_can_frame(), frame(0x311, &data));
    }
    // |heading| > π (raw 31417 = 0x7AB9) is rejected.
    assert_eq!(
        robot::Telemetry::decode(&frame(0x311, &[0xB9, 0x7A, 0, 0, 0, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "heading",
            value: 31417
        })
    );
}

#[test]
fn robot_status() {
    // state 1, fault 0, rx_errors 0x0102, unknown_ids 3, motors 0b1111, seq 0x80.
    let f = frame(0x312, &[0x01, 0x00, 0x02, 0x01, 0x03, 0x00, 0x0F, 0x80]);
    let s = Status {
        state: RobotState::Enabled,
        fault: Fault::None,
        rx_errors: 0x0102,
        unknown_ids: 3,
        motors_online: 0x0F,
        heading_source: HeadingSource::Wheels,
        seq: 0x80,
    };
    assert_eq!(
        robot::Telemetry::decode(&f),
        Ok(robot::Telemetry::Status(s))
    );
    assert_eq!(robot::Telemetry::Status(s).to_can_frame(), f);
    // heading_source shares byte 6 with motors_online: its high nibble.
    for (nibble, source) in [
        (0x10u8, HeadingSource::Gyro),
        (0x20, HeadingSource::WheelsGyroSilent),
    ] {
        let f = frame(
            0x312,
            &[0x01, 0x00, 0x02, 0x01, 0x03, 0x00, nibble | 0x0B, 0x80],
        );
        let s = Status {
            motors_online: 0x0B,
            heading_source: source,
            ..s
        };
        assert_eq!(
            robot::Telemetry::decode(&f),
            Ok(robot::Telemetry::Status(s))
        );
        assert_eq!(robot::Telemetry::Status(s).to_can_frame(), f);
    }
    // Bits 4-7 of motors_online are not encoded (they would be heading_source).
    let wide = Status {
        motors_online: 0xFF,
        ..s
    };
    assert_eq!(robot::Telemetry::Status(wide).to_can_frame(), f);
    let faults = [
        Fault::None,
        Fault::MotorStale,
        Fault::MotorMissing,
        Fault::DriveError,
        Fault::Watchdog,
        Fault::Config,
        Fault::EncoderStuck,
        Fault::WheelRunaway,
        Fault::WheelFight,
        Fault::DriveSilent,
        Fault::DriveRebooted,
        Fault::DriveSetup,
        Fault::DriveTransition,
        Fault::DriveNmt,
    ];
    for (raw, fault) in faults.into_iter().enumerate() {
        let f = frame(0x312, &[2, raw as u8, 0, 0, 0, 0, 0, 0]);
        let robot::Telemetry::Status(s) = robot::Telemetry::decode(&f).unwrap() else {
            panic!()
        };
        assert_eq!((s.state, s.fault), (RobotState::Fault, fault));
    }
    for (data, field, value) in [
        ([5u8, 0, 0, 0, 0, 0, 0, 0], "state", 5),
        ([0, 14, 0, 0, 0, 0, 0, 0], "fault", 14),
        ([0, 0, 0, 0, 0, 0, 0x3F, 0], "heading_source", 3),
        ([0, 0, 0, 0, 0, 0, 0xF0, 0], "heading_source", 15),
    ] {
        assert_eq!(
            robot::Telemetry::decode(&frame(0x312, &data)),
            Err(DecodeError::OutOfRange { field, value })
        );
    }
}

#[test]
fn robot_status_counters() {
    // repeated_seq 0x0102, wrong_dlc 3, out_of_range 0xFFFF, non_finite 0x8000.
    let f = frame(0x313, &[0x02, 0x01, 0x03, 0x00, 0xFF, 0xFF, 0x00, 0x80]);
    let c = StatusCounters {
        repeated_seq: 0x0102,
        wrong_dlc: 3,
        out_of_range: 0xFFFF,
        non_finite: 0x8000,
    };
    assert_eq!(
        robot::Telemetry::decode(&f),
        Ok(robot::Telemetry::StatusCounters(c))
    );
    assert_eq!(robot::Telemetry::StatusCounters(c).to_can_frame(), f);
    assert_eq!(
        robot::decode(&f),
        Ok(robot::Message::Telemetry(robot::Telemetry::StatusCounters(
            c
        )))
    );
    // Robot -> host only, 8 bytes only.
    assert_eq!(
        robot::Command::decode(&f),
        Err(DecodeError::UnknownId {
            id: Id::Standard(sid(0x313))
        })
    );
    assert_eq!(
        robot::Telemetry::decode(&frame(0x313, &[0; 6])),
        Err(DecodeError::WrongDlc {
            id: 0x313,
            expected: 8,
            got: 6
        })
    );
}

#[test]
fn robot_heartbeat() {
    // uptime 0x12345678 ms, state 3 (e-stop), protocol version 8, configuration 0xC0DE.
    let f = frame(0x31F, &[0x78, 0x56, 0x34, 0x12, 0x03, 0x08, 0xDE, 0xC0]);
    assert_eq!(robot::PROTOCOL_VERSION, 8);
    let h = Heartbeat {
        uptime_ms: 0x1234_5678,
        state: RobotState::Estop,
        protocol_version: robot::PROTOCOL_VERSION,
        config_id: 0xC0DE,
    };
    assert_eq!(
        robot::Telemetry::decode(&f),
        Ok(robot::Telemetry::Heartbeat(h))
    );
    assert_eq!(robot::Telemetry::Heartbeat(h).to_can_frame(), f);
}

#[test]
fn robot_wheel_test() {
    use robot::{TestOutcome, WheelTest, WheelTestResult};
    // Wheel 2 (RL), speed -3.5 rad/s = raw -3500 = 0xF254, 1500 ms = 0x05DC.
    let f = frame(0x305, &[0x02, 0x54, 0xF2, 0xDC, 0x05, 0x00, 0x00, 0x00]);
    let t = WheelTest {
        wheel: 2,
        speed: -3.5,
        duration_ms: 1500,
    };
    assert_eq!(robot::Command::decode(&f), Ok(robot::Command::WheelTest(t)));
    assert_eq!(robot::Command::WheelTest(t).to_can_frame(), f);
    for (data, field, value) in [
        ([4u8, 0x54, 0xF2, 0xDC, 0x05, 0, 0, 0], "wheel", 4),
        // 10.001 rad/s.
        ([0, 0x11, 0x27, 0xDC, 0x05, 0, 0, 0], "speed", 10_001),
        ([0, 0x54, 0xF2, 0x00, 0x00, 0, 0, 0], "duration_ms", 0),
        ([0, 0x54, 0xF2, 0xB9, 0x0B, 0, 0, 0], "duration_ms", 3001),
    ] {
        assert_eq!(
            robot::Command::decode(&frame(0x305, &data)),
            Err(DecodeError::OutOfRange { field, value }),
            "{field}"
        );
    }
    // Wheel 1, FAULT, angle -1.234 rad = raw -1234 = 0xFB2E, peak 3.99 A = raw 399 = 0x018F.
    let f = frame(0x314, &[0x01, 0x02, 0x2E, 0xFB, 0x8F, 0x01, 0x00, 0x00]);
    let r = WheelTestResult {
        wheel: 1,
        outcome: TestOutcome::Fault,
        angle: -1.234,
        peak_current: 3.99,
    };
    assert_eq!(
        robot::Telemetry::decode(&f),
        Ok(robot::Telemetry::WheelTestResult(r))
    );
    assert_eq!(robot::Telemetry::WheelTestResult(r).to_can_frame(), f);
    assert_eq!(
        robot::Telemetry::decode(&frame(0x314, &[0, 4, 0, 0, 0, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "outcome",
            value: 4
        })
    );
}

#[test]
fn robot_pod_counts_and_odom_slip() {
    // Counts 1, 65535 and 0x8000 (wrapping u16s), seq 9.
    let f = frame(0x306, &[0x01, 0x00, 0xFF, 0xFF, 0x00, 0x80, 0x09, 0x00]);
    let c = robot::PodCounts {
        counts: [1, 0xFFFF, 0x8000],
        seq: 9,
    };
    assert_eq!(robot::Command::decode(&f), Ok(robot::Command::PodCounts(c)));
    assert_eq!(robot::Command::PodCounts(c).to_can_frame(), f);
    // vx 0.012 m/s, vy -0.345 m/s, wz 0.2 rad/s, source 2 (PODS3) in byte 6's low nibble.
    let f = frame(0x315, &[0x0C, 0x00, 0xA7, 0xFE, 0xC8, 0x00, 0x02, 0x00]);
    let s = robot::OdomSlip {
        vx: 0.012,
        vy: -0.345,
        wz: 0.2,
        source: robot::OdometrySource::Pods3,
    };
    assert_eq!(robot::Telemetry::OdomSlip(s).to_can_frame(), f);
    let robot::Telemetry::OdomSlip(back) = robot::Telemetry::decode(&f).unwrap() else {
        panic!("not ODOM_SLIP");
    };
    assert_eq!(back.source, robot::OdometrySource::Pods3);
    assert!((back.vy + 0.345).abs() < 1e-6 && (back.wz - 0.2).abs() < 1e-6);
    // Source 4 is reserved.
    assert!(matches!(
        robot::Telemetry::decode(&frame(0x315, &[0, 0, 0, 0, 0, 0, 0x04, 0])),
        Err(DecodeError::OutOfRange {
            field: "source",
            value: 4
        })
    ));
}

#[test]
fn robot_rejections() {
    // Wrong DLC, remote, extended, unknown, wrong direction.
    assert_eq!(
        robot::Command::decode(&frame(0x301, &[0; 7])),
        Err(DecodeError::WrongDlc {
            id: 0x301,
            expected: 8,
            got: 7
        })
    );
    assert_eq!(
        robot::Command::decode(&CanFrame::remote(sid(0x301), 8)),
        Err(DecodeError::Remote { id: 0x301 })
    );
    let ext = <CanFrame as Frame>::new(ExtendedId::new(0x301).unwrap(), &[0; 8]).unwrap();
    assert_eq!(
        robot::decode(&ext),
        Err(DecodeError::ExtendedId { id: 0x301 })
    );
    for id in [0x307, 0x31E, 0x123] {
        assert_eq!(
            robot::decode(&frame(id, &[0; 8])),
            Err(DecodeError::UnknownId {
                id: Id::Standard(sid(id))
            })
        );
    }
    assert!(matches!(
        robot::Telemetry::decode(&frame(0x301, &[0; 8])),
        Err(DecodeError::UnknownId { .. })
    ));
    assert!(robot::in_block(0x300) && robot::in_block(0x31F) && !robot::in_block(0x320));
}

/// Every state, fault, heading source, outcome and mode request is named as the DBC's value
/// table names it: logs and printouts use these names (`as_str`, `Display`).
#[test]
fn names_are_the_dbc_value_tables() {
    use robot::{HeadingSource, ModeRequest, TestOutcome};
    let dbc = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../dbc/mecanum_robot.dbc"
    ))
    .unwrap();
    // `VAL_ <id> <signal> 0 "NAME" 1 "NAME" ... ;` as (raw, name) pairs.
    let table = |id: u32, signal: &str| -> Vec<(u8, String)> {
        let head = format!("VAL_ {id} {signal} ");
        let line = dbc.lines().find(|l| l.starts_with(&head)).unwrap();
        let parts: Vec<&str> = line[head.len()..]
            .trim_end_matches(" ;")
            .split('"')
            .collect();
        parts
            .chunks(2)
            .filter(|c| c.len() == 2)
            .map(|c| (c[0].trim().parse().unwrap(), c[1].to_string()))
            .collect()
    };
    let check = |id, signal, names: &dyn Fn(u8) -> Option<&'static str>| {
        let t = table(id, signal);
        assert!(!t.is_empty(), "{signal}");
        for (raw, name) in t {
            assert_eq!(names(raw), Some(name.as_str()), "{signal} {raw}");
        }
    };
    check(786, "state", &|r| {
        RobotState::from_raw(r).map(RobotState::as_str)
    });
    check(799, "state", &|r| {
        RobotState::from_raw(r).map(RobotState::as_str)
    });
    check(786, "fault", &|r| Fault::from_raw(r).map(Fault::as_str));
    check(786, "heading_source", &|r| {
        HeadingSource::from_raw(r).map(HeadingSource::as_str)
    });
    check(788, "outcome", &|r| {
        TestOutcome::from_raw(r).map(TestOutcome::as_str)
    });
    check(770, "request", &|r| {
        ModeRequest::from_raw(r).map(ModeRequest::as_str)
    });
    assert_eq!(
        format!("{} {}", RobotState::WheelTest, Fault::WheelFight),
        "WHEEL_TEST WHEEL_FIGHT"
    );
}
