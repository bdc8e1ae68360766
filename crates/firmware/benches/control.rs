//! One control period of the core on the host.
//!
//! - `control_step_4_wheels_dji`: four DJI feedback frames decoded and integrated, watchdog
//!   and limits, inverse kinematics, desaturation, four PI loops, the current frame encoded,
//!   odometry (and, every 10th / 100th step, the telemetry frames).
//! - `control_step_4_wheels_odrive`: the same period with ODrive drives at their default
//!   rates: encoder estimates of the four axes every 10th step, heartbeats every 100th, and
//!   velocity setpoints to the four axes every 5th step (no velocity loop in the core).
//! - `control_step_4_wheels_cia402`: the CiA 402 example (two dual-axis nodes, a 250 Hz
//!   SYNC cycle), the nodes configured, started and operation enabled: every 4th step SYNC
//!   and the four RPDOs go out, the step after it the four TPDOs (statusword 0x0237 and the
//!   actual velocities) come in; the nodes' heartbeats every 50th step. The firmware crate's
//!   drive double (`protocol::canopen::drive`) brings the nodes there; the measured loop then
//!   feeds their last TPDOs and heartbeats from a table built in advance.

use core::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant, Outbox};
use firmware::protocol::canopen::drive::{Axes, AxisCommand, Drives402, Options, Timing};
use firmware::protocol::canopen::{self, DriveState402, Message};
use firmware::protocol::dji::{EscId, EscModel, Feedback};
use firmware::protocol::odrive::{self, AxisState, NodeId};
use firmware::protocol::robot::{Command, Fault, ModeRequest, RobotState, TwistCmd};

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

/// The bench's axes: each follows its target at once (0.1 rpm units: the target in rpm x 10).
struct Follow([i32; 4]);

impl Axes for Follow {
    fn command(&mut self, wheel: usize, command: AxisCommand) {
        self.0[wheel] = match command {
            AxisCommand::Velocity(target) => target * 10,
            _ => 0,
        };
    }

    fn velocity(&self, wheel: usize) -> i32 {
        self.0[wheel]
    }

    fn at_rest(&self, wheel: usize) -> bool {
        self.0[wheel] == 0
    }
}

fn bench_cia402(c: &mut Criterion) {
    let config = Config::cia402_example();
    let mut ctl = Controller::new(&config).unwrap();
    // The firmware crate's drive double, answering the next step; heartbeats on the
    // multiples of their period (50 ms).
    let timing = Timing {
        heartbeat_aligned: true,
        ..Timing::NEXT_MS
    };
    let mut bus = Drives402::new(&config, timing, Options::default());
    let mut axes = Follow([0; 4]);
    let twists: [CanFrame; 256] = core::array::from_fn(|seq| {
        Command::Twist(TwistCmd {
            vx: 0.8,
            vy: -0.3,
            wz: 0.5,
            seq: seq as u8,
        })
        .to_can_frame()
    });
    let mut out = Outbox::new();
    // The set-up, scripted: configuration and start (~37 ms), the enable sequence (~18 ms),
    // then driving until the ramp has settled (0.8 m/s at 4 m/s²: 0.2 s).
    let mut k = 0u64;
    let mut last_sync = None;
    // The nodes' last TPDOs and heartbeats, for the measured loop's schedule.
    let (mut tpdos, mut beats) = (Vec::new(), Vec::new());
    let mut run = |ctl: &mut Controller, k: &mut u64, drive: bool| {
        let now = Instant::from_micros(*k * 1000);
        let mut fed = Vec::new();
        bus.feedback(*k * 1_000_000, &mut axes, |_, f| fed.push(f));
        for f in &fed {
            ctl.on_frame(now, f);
        }
        let is = |f: &CanFrame, heartbeat: bool| match canopen::decode(f) {
            Ok(Message::Tpdo1 { .. } | Message::Tpdo2 { .. }) => !heartbeat,
            Ok(Message::Heartbeat { .. }) => heartbeat,
            _ => false,
        };
        for (list, heartbeat) in [(&mut tpdos, false), (&mut beats, true)] {
            if fed.iter().any(|f| is(f, heartbeat)) {
                *list = fed.iter().filter(|f| is(f, heartbeat)).copied().collect();
            }
        }
        if drive {
            ctl.on_frame(now, &twists[*k as u8 as usize]);
        }
        ctl.step_into(now, &mut out);
        for f in &out {
            if matches!(canopen::decode(f), Ok(Message::Sync { .. })) {
                last_sync = Some(*k);
            }
            bus.on_frame(*k * 1_000_000, f, &mut axes);
        }
        *k += 1;
    };
    while ctl.snapshot().motors_online != 0b1111 {
        assert!(k < 200, "the nodes are configured and report");
        run(&mut ctl, &mut k, false);
    }
    ctl.on_frame(
        Instant::from_micros(k * 1000),
        &Command::Mode(ModeRequest::Enable).to_can_frame(),
    );
    let enabled_at = k;
    while k < enabled_at + 400 {
        run(&mut ctl, &mut k, true);
    }
    assert!(
        bus.nodes()
            .iter()
            .all(|n| n.state() == DriveState402::OperationEnabled)
    );
    assert!(axes.0.iter().all(|v| *v != 0), "driving");
    assert_eq!(tpdos.len(), 4, "TPDO1 and TPDO2 of each node");
    assert_eq!(beats.len(), 2, "a heartbeat of each node");
    let last_sync = last_sync.expect("SYNC is sent");
    // From here on the frames of each step come from a table of 100 steps (the TPDOs every
    // 4th, the step after SYNC; the heartbeats every 50th): the nodes' last ones, with the
    // targets of the settled ramp.
    let schedule: Vec<Vec<CanFrame>> = (0..100u64)
        .map(|i| {
            let mut frames = Vec::new();
            if (i + 100 - (last_sync + 1) % 100).is_multiple_of(4) {
                frames.extend(&tpdos);
            }
            if i.is_multiple_of(50) {
                frames.extend(&beats);
            }
            frames
        })
        .collect();
    c.bench_function("control_step_4_wheels_cia402", |b| {
        b.iter(|| {
            let now = Instant::from_micros(k * 1000);
            ctl.on_frame(now, &twists[k as u8 as usize]);
            for f in &schedule[(k % 100) as usize] {
                ctl.on_frame(now, f);
            }
            ctl.step_into(now, &mut out);
            black_box(&out);
            k += 1;
        })
    });
    // Still driving: nothing went stale, no node left operation enabled, every frame taken.
    let s = ctl.snapshot();
    assert_eq!((s.state, s.fault), (RobotState::Enabled, Fault::None));
    assert_eq!(s.motors_online, 0b1111);
    assert_eq!(s.rx_errors.total(), 0);
    assert!(s.wheel_speeds.0.iter().all(|w| w.abs() > 1.0), "{s:?}");
}

criterion_group!(benches, bench, bench_odrive, bench_cia402);
criterion_main!(benches);
