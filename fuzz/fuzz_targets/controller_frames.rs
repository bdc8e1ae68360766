//! The control core under any sequence of frames and steps: `Controller::on_frame` and
//! `Controller::step` with non-decreasing times (as the adapters guarantee), for the DJI and
//! the ODrive example configurations. The core must never panic, and every frame it sends
//! must decode with the project's own codecs.
#![no_main]

use arbitrary::Arbitrary;
use firmware::config::{Config, Drive};
use firmware::control::{Controller, Instant, Outbox};
use firmware::protocol::robot::{self, ModeRequest, TwistCmd};
use firmware::protocol::{canopen, dji, odrive};
use libfuzzer_sys::fuzz_target;
use mecanum_fuzz::FrameInput;

/// One event. Besides raw frames, well-formed messages are offered directly so that the
/// fuzzer reaches the enabled, driving states without having to guess their encodings.
#[derive(Arbitrary, Debug)]
enum Op {
    /// Any frame, received now.
    Frame(FrameInput),
    /// A twist command (any floats: the encoder saturates them).
    Twist { vx: f32, vy: f32, wz: f32, seq: u8 },
    /// Enable / disable / reset.
    Mode(u8),
    /// E-stop.
    Estop,
    /// `STATUS_REQ`.
    StatusRequest,
    /// `IMU_YAW_RATE` (any float: the encoder saturates it).
    Imu { yaw_rate: f32, seq: u8 },
    /// DJI feedback from ESC `esc` (1..=8).
    DjiFeedback {
        esc: u8,
        angle: u16,
        speed: i16,
        current: i16,
        temp: u8,
    },
    /// ODrive encoder estimates from node `node` (0..=63).
    OdriveEstimates { node: u8, pos: f32, vel: f32 },
    /// ODrive heartbeat.
    OdriveHeartbeat { node: u8, error: u32, state: u8 },
    /// Advance time by `us` microseconds (0 allowed), then step.
    Step { us: u32 },
    /// Advance by many periods without stepping (a stalled loop), then step.
    Stall { ms: u16 },
    /// `shutdown()`.
    Shutdown,
}

/// The example configuration fuzzed.
#[derive(Arbitrary, Debug)]
enum Example {
    Dji,
    Odrive,
    Cia402,
}

#[derive(Arbitrary, Debug)]
struct Input {
    drive: Example,
    /// `[odometry] heading_source = "gyro"`.
    gyro: bool,
    start_us: u32,
    ops: Vec<Op>,
}

fn check_outbox(config: &Config, out: &Outbox) {
    for f in out {
        let ok = robot::Telemetry::decode(f).is_ok()
            || match config.drive {
                Drive::Dji { model, .. } => dji::CurrentCommand::decode(f, model).is_ok(),
                Drive::Odrive { .. } => odrive::Command::decode(f).is_ok(),
                Drive::Cia402(_) => canopen::decode(f).is_ok(),
            };
        assert!(ok, "the core sent a frame its own codecs reject: {f}");
    }
}

fuzz_target!(|input: Input| {
    let mut config = match input.drive {
        Example::Dji => Config::dji_m3508_example(),
        Example::Odrive => Config::odrive_example(),
        Example::Cia402 => Config::cia402_example(),
    };
    if input.gyro {
        config.odometry.heading_source = firmware::config::HeadingMode::Gyro;
    }
    let mut ctl = Controller::new(&config).expect("example configurations are valid");
    let mut now = u64::from(input.start_us);
    for op in input.ops.iter().take(2_000) {
        let frame = match op {
            Op::Frame(f) => f.build(),
            Op::Twist { vx, vy, wz, seq } => Some(
                robot::Command::Twist(TwistCmd {
                    vx: *vx,
                    vy: *vy,
                    wz: *wz,
                    seq: *seq,
                })
                .to_can_frame(),
            ),
            Op::Mode(m) => Some(
                robot::Command::Mode(ModeRequest::from_raw(m % 3).expect("0..=2")).to_can_frame(),
            ),
            Op::Estop => Some(robot::Command::Estop.to_can_frame()),
            Op::StatusRequest => Some(robot::Command::StatusRequest.to_can_frame()),
            Op::Imu { yaw_rate, seq } => Some(
                robot::Command::ImuYawRate(robot::ImuYawRate {
                    yaw_rate: *yaw_rate,
                    seq: *seq,
                })
                .to_can_frame(),
            ),
            Op::DjiFeedback {
                esc,
                angle,
                speed,
                current,
                temp,
            } => dji::EscId::new(esc % 8 + 1).map(|esc| {
                dji::Feedback {
                    model: dji::EscModel::C620,
                    esc,
                    rotor_angle: *angle,
                    rotor_speed_rpm: *speed,
                    torque_current: *current,
                    temperature_c: *temp,
                }
                .to_can_frame()
            }),
            Op::OdriveEstimates { node, pos, vel } => odrive::NodeId::new(node % 64).map(|n| {
                odrive::Feedback::EncoderEstimates {
                    pos: *pos,
                    vel: *vel,
                }
                .to_can_frame(n)
            }),
            Op::OdriveHeartbeat { node, error, state } => {
                let n = odrive::NodeId::new(node % 64);
                let s = odrive::AxisState::from_raw(u32::from(*state % 14));
                n.zip(s).map(|(n, s)| {
                    odrive::Feedback::Heartbeat(odrive::Heartbeat {
                        axis_error: *error,
                        axis_state: s,
                        procedure_result: 0,
                        trajectory_done: false,
                    })
                    .to_can_frame(n)
                })
            }
            Op::Step { us } => {
                now = now.saturating_add(u64::from(*us));
                let out = ctl.step(Instant::from_micros(now));
                check_outbox(&config, &out);
                None
            }
            Op::Stall { ms } => {
                now = now.saturating_add(u64::from(*ms) * 1000);
                let out = ctl.step(Instant::from_micros(now));
                check_outbox(&config, &out);
                None
            }
            Op::Shutdown => {
                let out = ctl.shutdown();
                check_outbox(&config, &out);
                None
            }
        };
        if let Some(frame) = frame {
            ctl.on_frame(Instant::from_micros(now), &frame);
        }
    }
    // A last step a control period later, and a snapshot.
    now = now.saturating_add(ctl.period_micros());
    let out = ctl.step(Instant::from_micros(now));
    check_outbox(&config, &out);
    let _ = ctl.snapshot();
});
