//! `golden`: frames built by the encoders, each with the values given and the values read
//! back, for the Python tests to decode with cantools and the DBC files.

use std::io::{self, Write};

use drivelog::candump;
use embedded_can::Frame as _;
use firmware::protocol::dji::{self, EscGroup, EscId, EscModel};
use firmware::protocol::odrive::{
    self, Addressed, AxisState, Command as OC, ControlMode, Feedback as OF, InputMode, NodeId,
};
use firmware::protocol::robot::{
    self, Command as RC, Fault, HeadingSource, ModeRequest, RobotState, Telemetry as RT,
};

use crate::canopen;
use crate::json::{Decoded, Num, decode_error_json};
use crate::message::{AnyMessage, route};

/// Prints each golden frame: its candump text, the encoder's input and the fields read back.
pub(crate) fn run() -> io::Result<()> {
    let mut out = io::BufWriter::new(io::stdout().lock());
    for (msg, input) in golden_set() {
        let frame = msg.to_can_frame();
        let line = match route(&frame, msg.routing()) {
            Ok(decoded) => decoded
                .fields()
                .json(frame.id(), Some((&candump::format_frame(&frame), &input))),
            // A golden frame the decoder rejects is a bug; print it so the tests fail loudly.
            Err(e) => decode_error_json(frame.id(), &e),
        };
        writeln!(out, "{line}")?;
    }
    out.flush()
}

/// The golden messages, each with the values given to its encoder: the message's own
/// fields, but for the DJI current commands the amps before rounding to raw values (and for
/// CANopen SDO frames the command byte the encoder chose).
fn golden_set() -> Vec<(AnyMessage, Decoded)> {
    let mut v = robot_commands();
    v.extend(robot_telemetry());
    v.extend(wheel_tests());
    v.extend(modes_and_statuses());
    v.extend(odrive_messages());
    v.extend(canopen::golden_set().into_iter().map(AnyMessage::Canopen));
    v.extend(dji_feedback());
    let mut golden: Vec<(AnyMessage, Decoded)> = v
        .into_iter()
        .map(|msg| {
            let input = msg.fields();
            (msg, input)
        })
        .collect();
    golden.extend(dji_commands());
    golden
}

/// The robot protocol's commands (but the wheel tests and the mode requests).
fn robot_commands() -> Vec<AnyMessage> {
    vec![
        AnyMessage::Robot(robot::Message::Command(RC::Estop)),
        AnyMessage::Robot(robot::Message::Command(RC::Twist(robot::TwistCmd {
            vx: 0.5,
            vy: -0.25,
            wz: 1.0,
            seq: 7,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::Twist(robot::TwistCmd {
            vx: 32.767,
            vy: -32.767,
            wz: 0.0004,
            seq: 255,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::Twist(robot::TwistCmd {
            vx: -1.2345,
            vy: 2.0,
            wz: -2.50137,
            seq: 0,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::StatusRequest)),
        AnyMessage::Robot(robot::Message::Command(RC::ImuYawRate(robot::ImuYawRate {
            yaw_rate: 0.001_745_329_3,
            seq: 0,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::ImuYawRate(robot::ImuYawRate {
            yaw_rate: -34.906_586,
            seq: 255,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::ImuYawRate(robot::ImuYawRate {
            yaw_rate: 35.0,
            seq: 17,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::PodCounts(robot::PodCounts {
            counts: [0, 65535, 32768],
            seq: 0,
        }))),
        AnyMessage::Robot(robot::Message::Command(RC::PodCounts(robot::PodCounts {
            counts: [1234, 40000, 0],
            seq: 255,
        }))),
    ]
}

/// The robot protocol's telemetry (but the wheel test results and the status).
fn robot_telemetry() -> Vec<AnyMessage> {
    vec![
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomSlip(robot::OdomSlip {
            vx: 0.012,
            vy: -0.345,
            wz: 0.2,
            source: robot::OdometrySource::Pods3,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomSlip(robot::OdomSlip {
            vx: -32.767,
            vy: 32.767,
            wz: -0.001,
            source: robot::OdometrySource::WheelsPodsSilent,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomSlip(robot::OdomSlip {
            vx: 0.0,
            vy: 0.0,
            wz: 0.0,
            source: robot::OdometrySource::Pods2Gyro,
        }))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomPosition(
            robot::OdomPosition {
                x: 12.3456,
                y: -0.0001,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomPosition(
            robot::OdomPosition {
                x: -150_000.0,
                y: 200_000.0,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomVelocity(
            robot::OdomVelocity {
                heading: 3.1234,
                vx: 0.1,
                vy: -0.2,
                wz: 0.3,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::OdomVelocity(
            robot::OdomVelocity {
                heading: -1.2345,
                vx: -32.767,
                vy: 32.767,
                wz: -0.001,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::StatusCounters(
            robot::StatusCounters {
                repeated_seq: 65535,
                wrong_dlc: 0,
                out_of_range: 513,
                non_finite: 7,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::StatusCounters(
            robot::StatusCounters {
                repeated_seq: 258,
                wrong_dlc: 65535,
                out_of_range: 0,
                non_finite: 1,
            },
        ))),
        AnyMessage::Robot(robot::Message::Telemetry(RT::Heartbeat(robot::Heartbeat {
            uptime_ms: 4_000_000_000,
            state: RobotState::Enabled,
            protocol_version: robot::PROTOCOL_VERSION,
            config_id: 0xBEEF,
        }))),
    ]
}

/// WHEEL_TEST commands and their results.
fn wheel_tests() -> Vec<AnyMessage> {
    let mut v = Vec::new();
    for (wheel, speed, duration_ms) in [(0, 3.0, 1000), (3, -10.0, 3000), (1, 0.001, 1)] {
        v.push(AnyMessage::Robot(robot::Message::Command(RC::WheelTest(
            robot::WheelTest {
                wheel,
                speed,
                duration_ms,
            },
        ))));
    }
    for (wheel, outcome, angle, peak_current) in [
        (0, robot::TestOutcome::Done, 2.5, 3.99),
        (1, robot::TestOutcome::Stopped, -0.5, -4.0),
        (2, robot::TestOutcome::Fault, 32.767, 300.0),
        (3, robot::TestOutcome::Refused, 0.0, 0.0),
    ] {
        v.push(AnyMessage::Robot(robot::Message::Telemetry(
            RT::WheelTestResult(robot::WheelTestResult {
                wheel,
                outcome,
                angle,
                peak_current,
            }),
        )));
    }
    v
}

/// Every mode request, and STATUS with every state, fault and heading source.
fn modes_and_statuses() -> Vec<AnyMessage> {
    let mut v = Vec::new();
    for request in [
        ModeRequest::Disable,
        ModeRequest::Enable,
        ModeRequest::Reset,
    ] {
        v.push(AnyMessage::Robot(robot::Message::Command(RC::Mode(
            request,
        ))));
    }
    for (state, fault, heading_source) in [
        (RobotState::Disabled, Fault::None, HeadingSource::Wheels),
        (RobotState::Fault, Fault::MotorStale, HeadingSource::Wheels),
        (RobotState::Fault, Fault::MotorMissing, HeadingSource::Gyro),
        (RobotState::Fault, Fault::DriveError, HeadingSource::Wheels),
        (RobotState::Disabled, Fault::Watchdog, HeadingSource::Wheels),
        (RobotState::Fault, Fault::Config, HeadingSource::Wheels),
        (
            RobotState::Fault,
            Fault::EncoderStuck,
            HeadingSource::Wheels,
        ),
        (RobotState::Estop, Fault::None, HeadingSource::Wheels),
        (
            RobotState::Fault,
            Fault::WheelRunaway,
            HeadingSource::Wheels,
        ),
        (RobotState::Fault, Fault::WheelFight, HeadingSource::Wheels),
        (RobotState::WheelTest, Fault::None, HeadingSource::Wheels),
        (
            RobotState::Enabled,
            Fault::None,
            HeadingSource::WheelsGyroSilent,
        ),
        (RobotState::Enabled, Fault::None, HeadingSource::Gyro),
        (RobotState::Fault, Fault::DriveSilent, HeadingSource::Wheels),
        (
            RobotState::Fault,
            Fault::DriveRebooted,
            HeadingSource::Wheels,
        ),
        (RobotState::Fault, Fault::DriveSetup, HeadingSource::Gyro),
        (
            RobotState::Fault,
            Fault::DriveTransition,
            HeadingSource::Wheels,
        ),
        (RobotState::Fault, Fault::DriveNmt, HeadingSource::Wheels),
    ] {
        v.push(AnyMessage::Robot(robot::Message::Telemetry(RT::Status(
            robot::Status {
                state,
                fault,
                rx_errors: 65535,
                unknown_ids: 513,
                motors_online: 0b1011,
                heading_source,
                seq: 42,
            },
        ))));
    }
    v
}

/// Every ODrive message for nodes 0-3.
fn odrive_messages() -> Vec<AnyMessage> {
    let node = |n| NodeId::new(n).unwrap_or(NodeId::new(0).unwrap_or_else(|| unreachable!()));
    let mut v = Vec::new();
    for n in 0..=3 {
        let cmd =
            |msg| AnyMessage::Odrive(odrive::Message::Command(Addressed { node: node(n), msg }));
        let fb =
            |msg| AnyMessage::Odrive(odrive::Message::Feedback(Addressed { node: node(n), msg }));
        v.extend([
            cmd(OC::Estop),
            cmd(OC::GetError),
            cmd(OC::GetHeartbeat),
            cmd(OC::GetEncoderEstimates),
            cmd(OC::SetAxisState(AxisState::ClosedLoopControl)),
            cmd(OC::SetAxisState(AxisState::Idle)),
            cmd(OC::SetControllerMode {
                control_mode: ControlMode::VelocityControl,
                input_mode: InputMode::VelRamp,
            }),
            cmd(OC::SetControllerMode {
                control_mode: ControlMode::VelocityControl,
                input_mode: InputMode::Passthrough,
            }),
            cmd(OC::SetInputVel {
                vel: 12.5 * f32::from(n) - 3.25,
                torque_ff: 0.1,
            }),
            cmd(OC::ClearErrors { identify: n == 1 }),
            fb(OF::Heartbeat(odrive::Heartbeat {
                axis_error: 0x0100_0000,
                axis_state: AxisState::ClosedLoopControl,
                procedure_result: 3 + n,
                trajectory_done: true,
            })),
            fb(OF::Error {
                active_errors: 0x0000_1000,
                disarm_reason: 0x8000_0001,
            }),
            fb(OF::EncoderEstimates {
                pos: -1234.5678,
                vel: 1.0e-3 * f32::from(n),
            }),
        ]);
    }
    v
}

/// DJI feedback from ESCs 1-8.
fn dji_feedback() -> Vec<AnyMessage> {
    let esc = |n| EscId::new(n).unwrap_or_else(|| unreachable!("ESC ids 1..=8"));
    let mut v = Vec::new();
    for n in 1..=8u8 {
        v.push(AnyMessage::Dji(dji::Message::Feedback(dji::Feedback {
            model: EscModel::C620,
            esc: esc(n),
            rotor_angle: 1023 * u16::from(n),
            rotor_speed_rpm: 1000 - 700 * i16::from(n),
            torque_current: -2000 * i16::from(n),
            temperature_c: 20 + 5 * n,
        })));
    }
    v
}

/// DJI current commands, with the amps given (before rounding to raw values) as the input.
fn dji_commands() -> Vec<(AnyMessage, Decoded)> {
    let mut golden = Vec::new();
    // The last set is exact ties (k + 1/2 LSB, binary fractions): nearest even raw value.
    let lsb = EscModel::C620.amps_per_lsb();
    for (group, amps) in [
        (EscGroup::Esc1To4, [20.0, -20.0, 1.5, -0.0006]),
        (EscGroup::Esc5To8, [20.0, -20.0, 1.5, -0.0006]),
        (
            EscGroup::Esc1To4,
            [2.5 * lsb, -2.5 * lsb, 1.5 * lsb, -3.5 * lsb],
        ),
    ] {
        let msg = AnyMessage::Dji(dji::Message::Command(dji::CurrentCommand::from_amps(
            EscModel::C620,
            group,
            amps,
        )));
        let mut input = msg.fields();
        input.fields = group
            .fields()
            .iter()
            .zip(amps)
            .map(|(field, a)| (field.name, Num::Float(a)))
            .collect();
        golden.push((msg, input));
    }
    golden
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_golden_frame_decodes() {
        for (msg, _) in golden_set() {
            let frame = msg.to_can_frame();
            assert!(
                route(&frame, msg.routing()).is_ok(),
                "{}",
                candump::format_frame(&frame)
            );
        }
    }
}
