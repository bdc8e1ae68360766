//! Properties of every codec: decode(encode(x)) == x (within half an LSB for scaled fields,
//! exactly otherwise); encoders always produce frames their decoders accept, whatever the input;
//! decoders never panic, and what they accept re-encodes to an equivalent message.

use core::f32::consts::PI;

use embedded_can::{ExtendedId, Frame, StandardId};
use firmware::CanFrame;
use firmware::protocol::dji::{self, EscGroup, EscId, EscModel};
use firmware::protocol::odrive::{self, AxisState, ControlMode, InputMode, NodeId};
use firmware::protocol::robot::{
    self, Fault, HeadingSource, Heartbeat, ImuYawRate, ModeRequest, OdomPosition, OdomVelocity,
    RobotState, Status, StatusCounters, TwistCmd,
};
use proptest::prelude::*;

/// Half an LSB plus the f32 rounding of the value itself.
fn tol(lsb: f32, value: f32) -> f32 {
    0.5 * lsb * (1.0 + 1e-6) + value.abs() * f32::EPSILON
}

fn close(got: f32, want: f32, lsb: f32) -> bool {
    (got - want).abs() <= tol(lsb, want)
}

const AXIS_STATES: [AxisState; 15] = [
    AxisState::Undefined,
    AxisState::Idle,
    AxisState::StartupSequence,
    AxisState::FullCalibrationSequence,
    AxisState::MotorCalibration,
    AxisState::SensorlessControl,
    AxisState::EncoderIndexSearch,
    AxisState::EncoderOffsetCalibration,
    AxisState::ClosedLoopControl,
    AxisState::LockinSpin,
    AxisState::EncoderDirFind,
    AxisState::Homing,
    AxisState::EncoderHallPolarityCalibration,
    AxisState::EncoderHallPhaseCalibration,
    AxisState::AnticoggingCalibration,
];

fn axis_state() -> impl Strategy<Value = AxisState> {
    (0..15usize).prop_map(|i| AXIS_STATES[i])
}

fn robot_state() -> impl Strategy<Value = RobotState> {
    (0u8..4).prop_map(|r| RobotState::from_raw(r).unwrap())
}

fn finite_f32() -> impl Strategy<Value = f32> {
    prop::num::f32::NORMAL | prop::num::f32::SUBNORMAL | prop::num::f32::ZERO
}

fn any_f32() -> impl Strategy<Value = f32> {
    prop::num::f32::ANY
}

fn node() -> impl Strategy<Value = NodeId> {
    (0u8..=63).prop_map(|n| NodeId::new(n).unwrap())
}

fn model() -> impl Strategy<Value = EscModel> {
    prop_oneof![Just(EscModel::C620), Just(EscModel::C610)]
}

/// Any classic frame: standard or extended id, data or remote, DLC 0..=8.
fn any_frame() -> impl Strategy<Value = CanFrame> {
    let id = prop_oneof![
        4 => (0u16..0x800).prop_map(|r| embedded_can::Id::Standard(StandardId::new(r).unwrap())),
        1 => (0u32..0x2000_0000).prop_map(|r| embedded_can::Id::Extended(ExtendedId::new(r).unwrap())),
    ];
    (id, any::<bool>(), prop::collection::vec(any::<u8>(), 0..=8)).prop_map(|(id, remote, data)| {
        if remote {
            <CanFrame as Frame>::new_remote(id, data.len()).unwrap()
        } else {
            <CanFrame as Frame>::new(id, &data).unwrap()
        }
    })
}

/// Frames concentrated on the ids the codecs know, to reach deep into the decoders.
fn known_id_frame() -> impl Strategy<Value = CanFrame> {
    let id = prop_oneof![0x300u16..=0x31F, 0x1FFu16..=0x208, 0u16..0x80];
    (id, prop::collection::vec(any::<u8>(), 0..=8), any::<bool>()).prop_map(|(id, data, remote)| {
        let id = StandardId::new(id).unwrap();
        if remote {
            CanFrame::remote(id, data.len() as u8)
        } else {
            CanFrame::standard(id, &data).unwrap()
        }
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    // -------------------------------------------------------------------- robot protocol

    #[test]
    fn robot_twist_round_trip(vx in -32.767f32..=32.767, vy in -32.767f32..=32.767,
                              wz in -32.767f32..=32.767, seq in any::<u8>()) {
        let t = TwistCmd { vx, vy, wz, seq };
        let Ok(robot::Command::Twist(d)) = robot::Command::decode(&robot::Command::Twist(t).to_can_frame()) else {
            panic!("twist did not decode");
        };
        prop_assert!(close(d.vx, vx, 0.001), "{} vs {}", d.vx, vx);
        prop_assert!(close(d.vy, vy, 0.001));
        prop_assert!(close(d.wz, wz, 0.001));
        prop_assert_eq!(d.seq, seq);
    }

    #[test]
    fn robot_odom_round_trip(x in -214_748.0f32..214_748.0, y in -214_748.0f32..214_748.0,
                             heading in -PI..=PI, vx in -32.767f32..=32.767,
                             vy in -32.767f32..=32.767, wz in -32.767f32..=32.767) {
        let p = robot::Telemetry::OdomPosition(OdomPosition { x, y });
        let Ok(robot::Telemetry::OdomPosition(d)) = robot::Telemetry::decode(&p.to_can_frame()) else {
            panic!("position did not decode");
        };
        prop_assert!(close(d.x, x, 0.0001), "{} vs {}", d.x, x);
        prop_assert!(close(d.y, y, 0.0001));
        let v = robot::Telemetry::OdomVelocity(OdomVelocity { heading, vx, vy, wz });
        let Ok(robot::Telemetry::OdomVelocity(d)) = robot::Telemetry::decode(&v.to_can_frame()) else {
            panic!("velocity did not decode");
        };
        prop_assert!(close(d.heading, heading, 0.0001));
        prop_assert!(close(d.vx, vx, 0.001));
        prop_assert!(close(d.vy, vy, 0.001));
        prop_assert!(close(d.wz, wz, 0.001));
    }

    #[test]
    fn robot_status_heartbeat_mode_round_trip(state in robot_state(), fault in 0u8..7,
            rx_errors in any::<u16>(), unknown_ids in any::<u16>(), motors in 0u8..16,
            seq in any::<u8>(), uptime_ms in any::<u32>(), version in any::<u8>(), mode in 0u8..3,
            heading in 0u8..3) {
        let s = robot::Telemetry::Status(Status {
            state, fault: Fault::from_raw(fault).unwrap(), rx_errors, unknown_ids,
            motors_online: motors, heading_source: HeadingSource::from_raw(heading).unwrap(), seq,
        });
        prop_assert_eq!(robot::Telemetry::decode(&s.to_can_frame()), Ok(s));
        let c = robot::Telemetry::StatusCounters(StatusCounters {
            repeated_seq: rx_errors, wrong_dlc: unknown_ids, out_of_range: rx_errors ^ 0x5A5A,
            non_finite: u16::from(seq) << 8 | u16::from(motors),
        });
        prop_assert_eq!(robot::Telemetry::decode(&c.to_can_frame()), Ok(c));
        let h = robot::Telemetry::Heartbeat(Heartbeat {
            uptime_ms, state, protocol_version: version, config_id: rx_errors ^ unknown_ids,
        });
        prop_assert_eq!(robot::Telemetry::decode(&h.to_can_frame()), Ok(h));
        let m = robot::Command::Mode(ModeRequest::from_raw(mode).unwrap());
        prop_assert_eq!(robot::Command::decode(&m.to_can_frame()), Ok(m));
        prop_assert_eq!(robot::decode(&robot::Command::Estop.to_can_frame()),
                        Ok(robot::Message::Command(robot::Command::Estop)));
    }

    /// Encoders are total: any float, NaN and infinities included, gives a frame the
    /// decoder accepts (saturated, NaN as 0).
    #[test]
    fn robot_encoders_always_decodable(a in any_f32(), b in any_f32(), c in any_f32(), d in any_f32()) {
        let gyro = robot::Command::ImuYawRate(ImuYawRate { yaw_rate: a, seq: 3 });
        let Ok(robot::Command::ImuYawRate(g)) = robot::Command::decode(&gyro.to_can_frame()) else {
            panic!("yaw rate {a} did not decode");
        };
        if a.is_finite() && a.abs() <= 35.0 { prop_assert_eq!(g.yaw_rate.to_bits(), a.to_bits()); }
        let twist = robot::Command::Twist(TwistCmd { vx: a, vy: b, wz: c, seq: 0 });
        let Ok(robot::Command::Twist(t)) = robot::Command::decode(&twist.to_can_frame()) else {
            panic!("twist from {a} {b} {c} did not decode");
        };
        if a.is_nan() { prop_assert_eq!(t.vx, 0.0); }
        if a.is_finite() && a.abs() <= 32.767 { prop_assert!(close(t.vx, a, 0.001)); }
        if a > 32.767 { prop_assert!(close(t.vx, 32.767, 0.001)); }
        let pos = robot::Telemetry::OdomPosition(OdomPosition { x: a, y: b });
        prop_assert!(robot::Telemetry::decode(&pos.to_can_frame()).is_ok());
        let vel = robot::Telemetry::OdomVelocity(OdomVelocity { heading: a, vx: b, vy: c, wz: d });
        let Ok(robot::Telemetry::OdomVelocity(v)) = robot::Telemetry::decode(&vel.to_can_frame()) else {
            panic!("velocity from {a} did not decode");
        };
        prop_assert!(v.heading.abs() <= PI + 1e-4);
    }

    // -------------------------------------------------------------------- ODrive

    #[test]
    fn odrive_commands_round_trip(node in node(), state in axis_state(), control in 0u32..4,
                                  input in 0u32..9, vel in finite_f32(), torque_ff in finite_f32(),
                                  identify in any::<bool>()) {
        let cmds = [
            odrive::Command::Estop,
            odrive::Command::GetError,
            odrive::Command::GetHeartbeat,
            odrive::Command::GetEncoderEstimates,
            odrive::Command::SetAxisState(state),
            odrive::Command::SetControllerMode {
                control_mode: ControlMode::from_raw(control).unwrap(),
                input_mode: InputMode::from_raw(input).unwrap(),
            },
            odrive::Command::SetInputVel { vel, torque_ff },
            odrive::Command::ClearErrors { identify },
        ];
        for c in cmds {
            let f = c.to_can_frame(node);
            prop_assert_eq!(odrive::Command::decode(&f), Ok(odrive::Addressed { node, msg: c }));
            prop_assert_eq!(odrive::decode(&f), Ok(odrive::Message::Command(odrive::Addressed { node, msg: c })));
        }
    }

    #[test]
    fn odrive_feedback_round_trip(node in node(), axis_error in any::<u32>(), state in axis_state(),
                                  procedure_result in any::<u8>(), done in any::<bool>(),
                                  active in any::<u32>(), disarm in any::<u32>(),
                                  pos in finite_f32(), vel in finite_f32()) {
        let fbs = [
            odrive::Feedback::Heartbeat(odrive::Heartbeat {
                axis_error, axis_state: state, procedure_result, trajectory_done: done,
            }),
            odrive::Feedback::Error { active_errors: active, disarm_reason: disarm },
            odrive::Feedback::EncoderEstimates { pos, vel },
        ];
        for fb in fbs {
            let f = fb.to_can_frame(node);
            prop_assert_eq!(odrive::Feedback::decode(&f), Ok(odrive::Addressed { node, msg: fb }));
            prop_assert_eq!(odrive::decode(&f), Ok(odrive::Message::Feedback(odrive::Addressed { node, msg: fb })));
        }
    }

    #[test]
    fn odrive_encoders_never_send_non_finite(node in node(), a in any_f32(), b in any_f32()) {
        let f = odrive::Command::SetInputVel { vel: a, torque_ff: b }.to_can_frame(node);
        prop_assert!(odrive::Command::decode(&f).is_ok());
        let f = odrive::Feedback::EncoderEstimates { pos: a, vel: b }.to_can_frame(node);
        prop_assert!(odrive::Feedback::decode(&f).is_ok());
    }

    // -------------------------------------------------------------------- DJI

    #[test]
    fn dji_round_trip(model in model(), high in any::<bool>(), raw in prop::array::uniform4(-16384i16..=16384),
                      esc in 1u8..=8, angle in 0u16..8192, speed in any::<i16>(),
                      current in -16384i16..=16384, temp in any::<u8>()) {
        let lim = model.raw_limit();
        let group = if high { EscGroup::Esc5To8 } else { EscGroup::Esc1To4 };
        let c = dji::CurrentCommand { model, group, raw: raw.map(|r| r.clamp(-lim, lim)) };
        prop_assert_eq!(dji::CurrentCommand::decode(&c.to_can_frame(), model), Ok(c));
        prop_assert_eq!(dji::decode(&c.to_can_frame(), model), Ok(dji::Message::Command(c)));
        let fb = dji::Feedback {
            model, esc: EscId::new(esc).unwrap(), rotor_angle: angle, rotor_speed_rpm: speed,
            torque_current: current.clamp(-lim, lim), temperature_c: temp,
        };
        prop_assert_eq!(dji::Feedback::decode(&fb.to_can_frame(), model), Ok(fb));
        prop_assert_eq!(dji::decode(&fb.to_can_frame(), model), Ok(dji::Message::Feedback(fb)));
    }

    #[test]
    fn dji_amps_round_trip(model in model(), amps in prop::array::uniform4(-20.0f32..=20.0)) {
        let c = dji::CurrentCommand::from_amps(model, EscGroup::Esc1To4, amps);
        let d = dji::CurrentCommand::decode(&c.to_can_frame(), model).unwrap();
        let max = model.max_amps();
        for (got, want) in d.amps().into_iter().zip(amps) {
            prop_assert!(close(got, want.clamp(-max, max), model.amps_per_lsb()), "{} vs {}", got, want);
        }
    }

    // -------------------------------------------------------------------- every decoder

    /// No input makes a decoder panic; what a decoder accepts re-encodes to a frame that
    /// decodes to the same message.
    #[test]
    fn decoders_never_panic_and_are_stable(frame in prop_oneof![any_frame(), known_id_frame()]) {
        if let Ok(m) = robot::decode(&frame) {
            prop_assert_eq!(robot::decode(&m.to_can_frame()), Ok(m));
        }
        if let Ok(m) = odrive::decode(&frame) {
            prop_assert_eq!(odrive::decode(&m.to_can_frame()), Ok(m));
        }
        for model in [EscModel::C620, EscModel::C610] {
            if let Ok(m) = dji::decode(&frame, model) {
                prop_assert_eq!(dji::decode(&m.to_can_frame(), model), Ok(m));
            }
        }
        let _ = robot::Command::decode(&frame);
        let _ = robot::Telemetry::decode(&frame);
        let _ = odrive::Command::decode(&frame);
        let _ = odrive::Feedback::decode(&frame);
        let _ = dji::Feedback::decode(&frame, EscModel::C620);
        let _ = dji::CurrentCommand::decode(&frame, EscModel::C610);
        if let Some(f) = CanFrame::from_frame(&frame) {
            prop_assert_eq!(f, frame);
        }
    }
}
