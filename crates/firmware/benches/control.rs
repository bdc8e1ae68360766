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
//!   actual velocities) come in; the nodes' heartbeats every 50th step. A compact scripted
//!   bus (below) brings the nodes there; the measured loop then feeds frames built in advance.

use core::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant, Outbox};
use firmware::protocol::canopen::{
    self, DriveState402, Message, NmtCommand, NmtState, NodeId as CoNode, SdoRequest, SdoResponse,
};
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

/// One scripted CiA 402 node: the master's NMT, SDO, SYNC and RPDOs answered the next step
/// (a compact form of `tests/control/canopen_bus.rs`, which a bench cannot import; the
/// codec's drive-side state machine).
struct Node402 {
    id: CoNode,
    operational: bool,
    state: DriveState402,
    last_controlword: u16,
    mode: i8,
    /// Targets of axes 1 and 2, raw (rpm).
    targets: [i32; 2],
}

impl Node402 {
    fn control(&mut self, cw: u16) {
        self.state = self
            .state
            .on_controlword(cw, self.last_controlword, self.mode == 3);
        self.last_controlword = cw;
    }

    /// TPDO1 and TPDO2: the statusword and the actual velocities (0.1 rpm: the targets x 10
    /// once operation enabled).
    fn tpdos(&self) -> [CanFrame; 2] {
        let moving = self.state == DriveState402::OperationEnabled;
        let actual = self.targets.map(|t| if moving { t * 10 } else { 0 });
        [
            Message::Tpdo1 {
                node: self.id,
                statusword: self.state.statusword(),
                velocity: actual[0],
            }
            .to_can_frame(),
            Message::Tpdo2 {
                node: self.id,
                velocity: actual[1],
            }
            .to_can_frame(),
        ]
    }
}

fn heartbeat_402(node: CoNode, state: NmtState) -> CanFrame {
    Message::Heartbeat { node, state }.to_can_frame()
}

/// The nodes of the example and the frames they owe the next step.
struct Bus402 {
    nodes: Vec<Node402>,
    pending: Vec<CanFrame>,
}

impl Bus402 {
    fn new() -> Self {
        let node = |id| Node402 {
            id: CoNode::new(id).unwrap(),
            operational: false,
            state: DriveState402::SwitchOnDisabled,
            last_controlword: 0,
            mode: 0,
            targets: [0; 2],
        };
        Self {
            nodes: vec![node(1), node(2)],
            pending: Vec::new(),
        }
    }

    /// The frames of step `k` (1 ms each): what the nodes owe, and their heartbeats (50 ms).
    fn feed(&mut self, k: u64) -> Vec<CanFrame> {
        let mut out = std::mem::take(&mut self.pending);
        if k > 0 && k.is_multiple_of(50) {
            for n in &self.nodes {
                let state = if n.operational {
                    NmtState::Operational
                } else {
                    NmtState::PreOperational
                };
                out.push(heartbeat_402(n.id, state));
            }
        }
        out
    }

    /// Takes the master's frames of one step.
    fn take(&mut self, frames: &Outbox) {
        for f in frames {
            let Ok(msg) = canopen::decode(f) else {
                continue;
            };
            let node = msg.node();
            match msg {
                Message::Nmt { command, .. } => {
                    for n in &mut self.nodes {
                        if node.is_some_and(|id| id != n.id) {
                            continue;
                        }
                        match command {
                            NmtCommand::Start => n.operational = true,
                            NmtCommand::ResetNode | NmtCommand::ResetCommunication => {
                                n.operational = false;
                                n.state = DriveState402::SwitchOnDisabled;
                                n.mode = 0;
                                self.pending.push(heartbeat_402(n.id, NmtState::BootUp));
                            }
                            _ => n.operational = false,
                        }
                    }
                    continue;
                }
                Message::Sync { .. } => {
                    for n in self.nodes.iter().filter(|n| n.operational) {
                        self.pending.extend(n.tpdos());
                    }
                    continue;
                }
                _ => {}
            }
            let Some(n) = self.nodes.iter_mut().find(|n| Some(n.id) == node) else {
                continue;
            };
            match msg {
                Message::SdoRequest { request, .. } => {
                    let (index, sub) = request.object();
                    let response = match request {
                        SdoRequest::Upload { .. } if (index, sub) == (0x1000, 0) => {
                            SdoResponse::Uploaded {
                                index,
                                sub,
                                value: 0x0002_0192,
                                size: 4,
                            }
                        }
                        SdoRequest::Download { value, .. } => {
                            if (index, sub) == (0x6060, 0) {
                                n.mode = value as i8;
                            }
                            SdoResponse::Downloaded { index, sub }
                        }
                        _ => SdoResponse::Abort {
                            index,
                            sub,
                            code: 0x0602_0000,
                        },
                    };
                    self.pending.push(
                        Message::SdoResponse {
                            node: n.id,
                            response,
                        }
                        .to_can_frame(),
                    );
                }
                Message::Rpdo1 {
                    controlword,
                    target,
                    ..
                } => {
                    n.control(controlword);
                    n.targets[0] = target;
                }
                Message::Rpdo3 { target, .. } => n.targets[1] = target,
                _ => {}
            }
        }
    }
}

fn bench_cia402(c: &mut Criterion) {
    let config = Config::cia402_example();
    let mut ctl = Controller::new(&config).unwrap();
    let mut bus = Bus402::new();
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
    let mut run = |ctl: &mut Controller, k: &mut u64, drive: bool| {
        let now = Instant::from_micros(*k * 1000);
        for f in bus.feed(*k) {
            ctl.on_frame(now, &f);
        }
        if drive {
            ctl.on_frame(now, &twists[*k as u8 as usize]);
        }
        ctl.step_into(now, &mut out);
        if out
            .iter()
            .any(|f| matches!(canopen::decode(f), Ok(Message::Sync { .. })))
        {
            last_sync = Some(*k);
        }
        bus.take(&out);
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
        bus.nodes
            .iter()
            .all(|n| n.state == DriveState402::OperationEnabled)
    );
    assert!(bus.nodes.iter().all(|n| n.targets != [0, 0]), "driving");
    let last_sync = last_sync.expect("SYNC is sent");
    // From here on the frames of each step come from a table of 100 steps (the TPDOs every
    // 4th, the step after SYNC; the heartbeats every 50th): the nodes answer as above, with
    // the targets of the settled ramp.
    let tpdos: Vec<CanFrame> = bus.nodes.iter().flat_map(Node402::tpdos).collect();
    let schedule: Vec<Vec<CanFrame>> = (0..100u64)
        .map(|i| {
            let mut frames = Vec::new();
            if (i + 100 - (last_sync + 1) % 100).is_multiple_of(4) {
                frames.extend(&tpdos);
            }
            if i.is_multiple_of(50) {
                frames.extend(
                    bus.nodes
                        .iter()
                        .map(|n| heartbeat_402(n.id, NmtState::Operational)),
                );
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
