//! One control period of the core on the host.
//!
//! - `control_step_4_wheels_dji`: four DJI feedback frames decoded and integrated, watchdog
//!   and limits, inverse kinematics, desaturation, four PI loops, the current frame encoded,
//!   odometry (and, every 10th / 100th step, the telemetry frames).
//! - `control_step_4_wheels_odrive`: the same period with ODrive drives at their default
//!   rates: encoder estimates of the four axes every 10th step, heartbeats every 100th, and
//!   velocity setpoints to the four axes every 5th step (no velocity loop in the core).

use core::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant, Outbox};
use firmware::protocol::dji::{EscId, EscModel, Feedback};
use firmware::protocol::odrive::{self, AxisState, NodeId};
use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};

fn feedback(esc: u8, angle: u16, rpm: i16) -> CanFrame {
    Feedback {
        model: EscModel::C620,
        esc: EscId::new(esc).unwrap(),
        rotor_angle: angle,
        rotor_speed_rpm: rpm,
        torque_current: 1200,
        temperature_c: 35,
    }
    .to_can_frame()
}

/// A controller on `config` that has seen `first` (one message of each motor) at t = 0,
/// stepped once and enabled; and the twist frames the benches keep sending, one per `seq`
/// (a host increments it: the same frame again would not feed the watchdog).
fn enabled(config: &Config, first: &[CanFrame]) -> (Controller, [CanFrame; 256]) {
    let mut ctl = Controller::new(config).unwrap();
    let t0 = Instant::from_micros(0);
    for frame in first {
        ctl.on_frame(t0, frame);
    }
    ctl.step(t0);
    ctl.on_frame(t0, &Command::Mode(ModeRequest::Enable).to_can_frame());
    let twists = core::array::from_fn(|seq| {
        Command::Twist(TwistCmd {
            vx: 0.8,
            vy: -0.3,
            wz: 0.5,
            seq: seq as u8,
        })
        .to_can_frame()
    });
    (ctl, twists)
}

fn bench(c: &mut Criterion) {
    let first: Vec<CanFrame> = (1..=4).map(|esc| feedback(esc, 0, 0)).collect();
    let (mut ctl, twists) = enabled(&Config::dji_m3508_example(), &first);
    let mut t = 0u64;
    let mut angle = [0u16; 4];
    let rpm = [2400i16, -2600, 2100, -2300];
    let mut out = Outbox::new();
    c.bench_function("control_step_4_wheels_dji", |b| {
        b.iter(|| {
            t += 1000;
            let now = Instant::from_micros(t);
            // Keep the watchdog fed without a per-iteration branch cost worth measuring.
            ctl.on_frame(now, &twists[(t / 1000) as u8 as usize]);
            for w in 0..4 {
                angle[w] = (angle[w] + (rpm[w].unsigned_abs() / 8)) % 8192;
                ctl.on_frame(now, &feedback(w as u8 + 1, angle[w], rpm[w]));
            }
            ctl.step_into(now, &mut out);
            black_box(&out);
        })
    });
}

fn estimates(node: u8, pos: f32, vel: f32) -> CanFrame {
    odrive::Feedback::EncoderEstimates { pos, vel }.to_can_frame(NodeId::new(node).unwrap())
}

fn heartbeat(node: u8) -> CanFrame {
    odrive::Feedback::Heartbeat(odrive::Heartbeat {
        axis_error: 0,
        axis_state: AxisState::ClosedLoopControl,
        procedure_result: 0,
        trajectory_done: false,
    })
    .to_can_frame(NodeId::new(node).unwrap())
}

fn bench_odrive(c: &mut Criterion) {
    let first: Vec<CanFrame> = (0..4)
        .flat_map(|node| [heartbeat(node), estimates(node, 0.0, 0.0)])
        .collect();
    let (mut ctl, twists) = enabled(&Config::odrive_example(), &first);
    let mut t = 0u64;
    let mut step = 0u64;
    let mut pos = [0f32; 4];
    let vel = [2.5f32, -2.7, 2.2, -2.4];
    let mut out = Outbox::new();
    c.bench_function("control_step_4_wheels_odrive", |b| {
        b.iter(|| {
            t += 1000;
            step += 1;
            let now = Instant::from_micros(t);
            ctl.on_frame(now, &twists[step as u8 as usize]);
            if step.is_multiple_of(10) {
                for w in 0..4 {
                    pos[w] += vel[w] * 0.01;
                    ctl.on_frame(now, &estimates(w as u8, pos[w], vel[w]));
                }
            }
            if step.is_multiple_of(100) {
                for w in 0..4 {
                    ctl.on_frame(now, &heartbeat(w as u8));
                }
            }
            ctl.step_into(now, &mut out);
            black_box(&out);
        })
    });
}

criterion_group!(benches, bench, bench_odrive);
criterion_main!(benches);
