//! A fixed, deterministic scenario for the firmware control core: scripted host commands, a
//! scripted plant answering the motor commands, 3,000 control steps at 1 kHz, for the DJI, the
//! ODrive and the CiA 402 example configurations, and the DJI one with its odometry from three
//! tracking pods. It reports the outbound frame stream as text: a rolling FNV-1a 64 hash
//! (`firmware::StreamHash`), checkpoints every 100 steps, every n-th frame, and the final
//! state.
//!
//! The same code runs on the host (`xtarget-host`) and on an emulated Cortex-M4
//! (`board-qemu-m4`); `scripts/xtarget.sh` compares the two reports line by line. Everything
//! here is deterministic on both targets: integer arithmetic, IEEE `+ - * /` on `f32`
//! (Rust never contracts them into fused multiply-adds), saturating float-to-int casts, and
//! libm for the one transcendental function the script uses.
//!
//! # One step (time `t = k` ms)
//!
//! ```text
//! plant ─► feedback frames ─► ctl.on_frame(t, ·)      (DJI: 4 every ms; ODrive: every 10 ms;
//!                                                      CiA 402: the nodes' answers, TPDOs
//!                                                      the ms after each SYNC, heartbeats)
//! script ─► host commands  ─► ctl.on_frame(t, ·)      (enable, twists, e-stop, reset, junk)
//! ctl.step(t) ─► outbox ─► hash, report ─► plant (applies the commands, integrates 1 ms)
//! ```
//!
//! # Script (ms)
//!
//! | when | what |
//! |---|---|
//! | 5, 1380, 2760 | status requests (the watchdog stop and the stale fault show in the stream) |
//! | 10 | enable |
//! | 20..1200 | twists every 20 ms: straight, then with rotation, then a circle (`sinf`/`cosf`) |
//! | ~1280 | the command watchdog expires: stop ramp, then disabled |
//! | 1400 | enable; twists with rotation from 1410 |
//! | 1500 | rejected frames: a twist over the speed limit, a short twist, an unknown id, an extended id |
//! | 1900 | e-stop (twists keep coming until 2000 and are ignored) |
//! | 2100, 2110 | reset, enable; twists 2120..2600 with a sinusoidal yaw rate |
//! | 2600 | disable |
//! | 2700 | wheel 2's feedback stops (DJI 10 ms, ODrive 50 ms, CiA 402 20 ms): stale motor fault |
//! | 2800, 2850 | reset, enable; twists 2860..3000 |
//!
//! CiA 402: the core resets both nodes at 0 ms and configures them by SDO (34 transfers a
//! node, one a step), so the enable at 10 ms waits in the enable sequence until the nodes are
//! started (NMT start at 35 ms, SYNC from 36 ms) and runs it from there: operation enabled at
//! 57 ms, targets from the SYNC at 60 ms. The disable, the watchdog's stop and the reset send
//! shutdown, the e-stop and the stale fault a quick stop. Wheel 2's
//! lost feedback is node 2's TPDO1 (its statusword and first axis); its TPDO2 still comes.
//!
//! Pods: the DJI setup with `odometry.source = "pods3"` (the layout of
//! `config/dji_m3508_pods3.toml`). A pod node sends `POD_COUNTS` every 5 ms from the body
//! motion the plant's wheels imply (forward kinematics) plus a sideways slide of 5 % of the
//! forward speed that no wheel sees; it is silent from 2300 to 2400 ms (the wheels take over,
//! then the pods again), and repeats one frame at 1000 ms (not used, counted).

#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

use core::f32::consts::TAU;
use core::fmt::{self, Write};

use embedded_can::{ExtendedId, Frame, StandardId};
use firmware::config::{Cia402Drive, Drive, OdometryMode, PodConfig, Pods};
use firmware::protocol::canopen::{
    self, DriveState402, Message, NmtCommand, NmtState, NodeId as CoNode, SdoRequest, SdoResponse,
};
use firmware::protocol::dji::{self, EscId, EscModel};
use firmware::protocol::odrive::{self, AxisState, NodeId};
use firmware::protocol::robot::{self, Command, ModeRequest, TwistCmd};
use firmware::{CanFrame, Config, Controller, Instant, StreamHash};
use kinematics::{MecanumKinematics, PodGeometry, Twist2, WheelSpeeds};

/// Control steps of the full scenario (3 s at 1 kHz).
pub const STEPS: u32 = 3000;

/// The control period, µs (the example configurations run at 1 kHz).
pub const PERIOD_US: u64 = 1000;

/// Checkpoint lines (`ck`) every this many steps.
pub const CHECKPOINT_EVERY: u32 = 100;

/// Which example configuration to run.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Setup {
    /// `Config::dji_m3508_example()`: four C620 ESCs, current control.
    Dji,
    /// `Config::odrive_example()`: four ODrive axes, velocity setpoints.
    Odrive,
    /// `Config::cia402_example()`: two dual-axis CiA 402 nodes, profile velocity mode, a
    /// 250 Hz SYNC cycle; the core is their CANopen master.
    Cia402,
    /// The DJI example with its odometry from three tracking pods (`POD_COUNTS`).
    Pods,
}

impl Setup {
    /// All four, in report order.
    pub const ALL: [Self; 4] = [Self::Dji, Self::Odrive, Self::Cia402, Self::Pods];

    /// Short name used in the report.
    #[must_use]
    pub const fn name(self) -> &'static str {
        match self {
            Self::Dji => "dji",
            Self::Odrive => "odrive",
            Self::Cia402 => "cia402",
            Self::Pods => "pods",
        }
    }

    /// The configuration.
    #[must_use]
    pub fn config(self) -> Config {
        match self {
            Self::Dji => Config::dji_m3508_example(),
            Self::Odrive => Config::odrive_example(),
            Self::Cia402 => Config::cia402_example(),
            Self::Pods => {
                let pod = |x, y, direction_deg| PodConfig {
                    x,
                    y,
                    direction_deg,
                    radius: 0.024,
                    counts_per_turn: 2000,
                };
                let mut c = Config::dji_m3508_example();
                c.odometry.source = OdometryMode::Pods3;
                c.odometry.pods = Pods::new(&[
                    pod(0.0, 0.11, 0.0),
                    pod(0.0, -0.11, 0.0),
                    pod(0.12, 0.0, 90.0),
                ])
                .unwrap_or_default();
                c
            }
        }
    }
}

/// Hooks around the control core's work in each step (the frames passed to `on_frame` and
/// the `step` call): the Cortex-M4 build puts instruction-count markers here.
pub trait Probe {
    /// Before the first `on_frame` of step `step`.
    fn core_begin(&mut self, _setup: Setup, _step: u32) {}
    /// After `step` returned.
    fn core_end(&mut self, _setup: Setup, _step: u32) {}
}

/// A [`Probe`] that does nothing.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoProbe;

impl Probe for NoProbe {}

/// What to run and how much to print.
#[derive(Clone, Copy, Debug)]
pub struct Options {
    /// Steps to run (the script is defined for [`STEPS`]).
    pub steps: u32,
    /// Print every n-th outbound frame (frame index 0, n, 2n, ...); 0 prints none.
    pub frame_every: u32,
    /// Print `ck` lines every [`CHECKPOINT_EVERY`] steps.
    pub checkpoints: bool,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            steps: STEPS,
            frame_every: 100,
            checkpoints: true,
        }
    }
}

/// The outcome of one run.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Digest {
    /// Outbound frames.
    pub frames: u64,
    /// [`StreamHash`] of the outbound frames, each with its time in µs (`run_all`'s: of the
    /// setups' hashes, each as 8 bytes LE).
    pub hash: u64,
}

/// xorshift32: the plant's encoder jitter. Integer only.
#[derive(Clone, Copy, Debug)]
struct Rng(u32);

impl Rng {
    fn next(&mut self) -> u32 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        self.0 = x;
        x
    }
}

/// DJI rotor model (motor side): `dω/dt = A·i − C·ω`. Steady state at the C620's 16 A limit:
/// 960 rad/s (9,170 rpm); time constant 50 ms.
const DJI_A: f32 = 1200.0;
const DJI_C: f32 = 20.0;
const DJI_COUNTS: f32 = 8192.0;

/// ODrive axis model: the drive's own velocity loop as a first-order lag (1/40 s); coasting
/// with a 0.5 s time constant when not in closed loop.
const OD_K: f32 = 40.0;
const OD_COAST: f32 = 2.0;

/// CiA 402 axis model: the drive's profile velocity loop as the same first-order lag as the
/// ODrive's; a quick stop decelerates with a 50 ms time constant, otherwise the axis coasts.
const CO_QUICK_STOP: f32 = 20.0;

/// The device type a CiA 402 drive reports (object 0x1000): profile 402, servo drive.
const DEVICE_TYPE_402: u32 = 0x0002_0192;

/// Frames one scripted CiA 402 node can owe the next step (an SDO answer or a boot-up, and
/// the two TPDOs of a SYNC).
const NODE_PENDING: usize = 3;

/// One scripted CiA 402 node: it answers the master's NMT, SDO, SYNC and RPDOs the next
/// millisecond and runs the 402 state machine (the codec's drive side,
/// `DriveState402::on_controlword`) on each controlword: the firmware's test double in
/// `crates/firmware/tests/control/canopen_bus.rs`, without heap and fault injection.
#[derive(Clone, Copy, Debug)]
struct Node402 {
    id: CoNode,
    operational: bool,
    state: DriveState402,
    mode: i8,
    last_controlword: u16,
    pending: [Option<CanFrame>; NODE_PENDING],
}

impl Node402 {
    fn new(id: CoNode) -> Self {
        Self {
            id,
            operational: false,
            state: DriveState402::SwitchOnDisabled,
            mode: 0,
            last_controlword: 0,
            pending: [None; NODE_PENDING],
        }
    }

    fn owe(&mut self, frame: CanFrame) {
        if let Some(slot) = self.pending.iter_mut().find(|p| p.is_none()) {
            *slot = Some(frame);
        }
    }

    /// A boot-up: pre-operational, switch on disabled, the mode forgotten.
    fn reboot(&mut self) {
        self.operational = false;
        self.state = DriveState402::SwitchOnDisabled;
        self.mode = 0;
        self.pending = [None; NODE_PENDING];
        self.owe(
            Message::Heartbeat {
                node: self.id,
                state: NmtState::BootUp,
            }
            .to_can_frame(),
        );
    }

    fn sdo(&mut self, request: SdoRequest) {
        let (index, sub) = request.object();
        let response = match request {
            SdoRequest::Upload { .. } if (index, sub) == (0x1000, 0) => SdoResponse::Uploaded {
                index,
                sub,
                value: DEVICE_TYPE_402,
                size: 4,
            },
            // The mode of operation display shows the mode written at once.
            SdoRequest::Upload { .. } if (index, sub) == (0x6061, 0) => SdoResponse::Uploaded {
                index,
                sub,
                value: u32::from(self.mode as u8),
                size: 1,
            },
            SdoRequest::Download { value, .. } => {
                if (index, sub) == (0x6060, 0) {
                    self.mode = value as i8;
                }
                SdoResponse::Downloaded { index, sub }
            }
            _ => SdoResponse::Abort {
                index,
                sub,
                code: 0x0602_0000,
            },
        };
        self.owe(
            Message::SdoResponse {
                node: self.id,
                response,
            }
            .to_can_frame(),
        );
    }

    /// The CiA 402 state machine, on each controlword received.
    fn control(&mut self, cw: u16) {
        self.state = self
            .state
            .on_controlword(cw, self.last_controlword, self.mode == 3);
        self.last_controlword = cw;
    }
}

/// The CiA 402 side of the plant: the nodes and each wheel's place on them.
#[derive(Clone, Copy, Debug)]
struct Canopen {
    /// The nodes, in the order they first appear in `node_ids` (the example has two).
    nodes: [Option<Node402>; 2],
    /// Each wheel's node (index into `nodes`) and axis slot (0: sub-index 0 or 1; 1: 2).
    wheel_node: [(usize, usize); 4],
    /// Motor rpm per raw unit of target and of actual velocity.
    target_rpm: f32,
    actual_rpm: f32,
}

impl Canopen {
    fn new(config: &Config) -> Option<Self> {
        let Drive::Cia402(Cia402Drive {
            node_ids,
            axes,
            target_rpm_per_unit,
            actual_rpm_per_unit,
            ..
        }) = config.drive
        else {
            return None;
        };
        let mut nodes: [Option<Node402>; 2] = [None; 2];
        let mut wheel_node = [(0, 0); 4];
        for ((slot, &id), &axis) in wheel_node.iter_mut().zip(&node_ids).zip(&axes) {
            let index = nodes
                .iter()
                .position(|n| n.is_some_and(|n| n.id.get() == id))
                .or_else(|| {
                    let free = nodes.iter().position(Option::is_none)?;
                    let node = nodes.get_mut(free)?;
                    *node = Some(Node402::new(CoNode::new(id)?));
                    Some(free)
                });
            let Some(index) = index else {
                panic!("the scenario's CiA 402 plant takes at most two nodes");
            };
            *slot = (index, usize::from(axis == 2));
        }
        Some(Self {
            nodes,
            wheel_node,
            target_rpm: target_rpm_per_unit,
            actual_rpm: actual_rpm_per_unit,
        })
    }

    /// A target (raw) of axis `(node index, slot)` into its wheel's command, motor rpm.
    fn set_target(&self, axes: &mut [Axis; 4], axis: (usize, usize), target: i32) {
        for (a, &w) in axes.iter_mut().zip(&self.wheel_node) {
            if w == axis {
                a.cmd = target as f32 * self.target_rpm;
            }
        }
    }

    fn node(&mut self, id: CoNode) -> Option<(usize, &mut Node402)> {
        self.nodes
            .iter_mut()
            .enumerate()
            .find_map(|(i, n)| n.as_mut().filter(|n| n.id == id).map(|n| (i, n)))
    }
}

#[derive(Clone, Copy, Debug)]
struct Axis {
    /// DJI: rotor speed, rad/s. ODrive: velocity, rev/s (motor side).
    speed: f32,
    /// DJI: rotor angle, counts in [0, 8192). ODrive: position, rev.
    pos: f32,
    /// DJI: commanded current, A, and its raw value. ODrive: velocity setpoint, rev/s.
    cmd: f32,
    raw: i16,
    state: AxisState,
}

/// The pods setup's pod node: the pods' travel from the body motion the wheels imply, plus
/// a slide they do not see.
#[derive(Debug)]
struct PodNode {
    kin: MecanumKinematics<f32, 4>,
    /// Rotor rad/s to wheel rad/s, robot-forward positive, per wheel.
    wheel_per_rotor: [f32; 4],
    pods: [PodGeometry<f32>; 3],
    metres_per_count: [f32; 3],
    /// Each pod's travel, m.
    travel: [f32; 3],
    /// The last frame sent (repeated once, to be counted and not used).
    last: robot::PodCounts,
}

impl PodNode {
    /// Sideways slide, of the forward speed: what the pods see and the wheels do not.
    const SLIDE: f32 = 0.05;

    fn new(config: &Config) -> Option<Self> {
        let Drive::Dji {
            gear_ratio,
            inverted,
            ..
        } = config.drive
        else {
            return None;
        };
        let list = config.odometry.pods.as_slice();
        if list.len() != 3 {
            return None;
        }
        let kin = config.kinematics().ok()?;
        let pod = |i: usize| list[i];
        Some(Self {
            kin,
            wheel_per_rotor: inverted.map(|inv| if inv { -1.0 } else { 1.0 } / gear_ratio),
            pods: [0, 1, 2].map(|i| pod(i).geometry()),
            metres_per_count: [0, 1, 2].map(|i| pod(i).metres_per_count()),
            travel: [0.0; 3],
            last: robot::PodCounts::default(),
        })
    }

    /// The body moved for `dt` s with the wheels at `rotor` rad/s.
    fn advance(&mut self, rotor: [f32; 4], dt: f32) {
        let mut w = [0.0; 4];
        for ((w, r), k) in w.iter_mut().zip(rotor).zip(self.wheel_per_rotor) {
            *w = r * k;
        }
        let v = self.kin.forward(&WheelSpeeds(w));
        let twist = Twist2 {
            dx: v.vx * dt,
            dy: (v.vy + Self::SLIDE * v.vx) * dt,
            dtheta: v.wz * dt,
        };
        for (t, p) in self.travel.iter_mut().zip(&self.pods) {
            *t += p.arc(twist);
        }
    }

    /// `POD_COUNTS` at `ms` (every 5 ms; none from 2300 to 2400 ms; at 1000 ms the previous
    /// frame again).
    fn frame(&mut self, ms: u32) -> Option<CanFrame> {
        if !ms.is_multiple_of(5) || (2300..2400).contains(&ms) {
            return None;
        }
        if ms != 1000 {
            let mut counts = [0u16; 3];
            for ((c, t), m) in counts
                .iter_mut()
                .zip(self.travel)
                .zip(self.metres_per_count)
            {
                // An encoder's count, wrapping as a 16-bit timer does.
                *c = libm::floorf(t / m) as i32 as u16;
            }
            self.last = robot::PodCounts {
                counts,
                seq: self.last.seq.wrapping_add(1),
            };
        }
        Some(Command::PodCounts(self.last).to_can_frame())
    }
}

/// The scripted plant: four motors that answer the controller's frames.
#[derive(Debug)]
struct Plant {
    setup: Setup,
    axes: [Axis; 4],
    rng: Rng,
    /// CiA 402: the nodes (`None` for the other setups).
    canopen: Option<Canopen>,
    /// The pods setup: the pod node (`None` for the other setups).
    pods: Option<PodNode>,
    /// The step of the last `feedback` call, ms.
    ms: u32,
}

/// Frames one step can feed the controller (4 estimates + 4 heartbeats, or 4 DJI feedbacks).
type Inbox = [Option<CanFrame>; 8];

impl Plant {
    fn new(setup: Setup, config: &Config) -> Self {
        let axis = Axis {
            speed: 0.0,
            pos: 0.0,
            cmd: 0.0,
            raw: 0,
            state: AxisState::Idle,
        };
        let mut axes = [axis; 4];
        // Different starting angles so the encoders do not move in lockstep.
        for (i, a) in axes.iter_mut().enumerate() {
            a.pos = match setup {
                Setup::Dji | Setup::Pods => 1000.0 * i as f32 + 17.0,
                Setup::Odrive => 0.25 * i as f32 - 0.3,
                Setup::Cia402 => 0.0,
            };
        }
        Self {
            setup,
            axes,
            rng: Rng(0x1234_5678),
            canopen: Canopen::new(config),
            pods: PodNode::new(config),
            ms: 0,
        }
    }

    fn feedback(&mut self, ms: u32, inbox: &mut Inbox) {
        *inbox = [None; 8];
        self.ms = ms;
        if let Some(p) = &mut self.pods {
            inbox[4] = p.frame(ms);
        }
        match self.setup {
            Setup::Dji | Setup::Pods => {
                for (i, a) in self.axes.iter().enumerate() {
                    // Up to ±1 count of jitter; the rng advances even when the frame is lost.
                    let jitter = (self.rng.next() % 3) as i32 - 1;
                    if dropped(self.setup, ms, i) {
                        continue;
                    }
                    let Some(esc) = EscId::new(i as u8 + 1) else {
                        continue;
                    };
                    let angle = (a.pos as i32 + jitter).rem_euclid(DJI_COUNTS as i32) as u16;
                    let fb = dji::Feedback {
                        model: EscModel::C620,
                        esc,
                        rotor_angle: angle,
                        rotor_speed_rpm: (a.speed * (60.0 / TAU)) as i16,
                        torque_current: a.raw,
                        temperature_c: 30 + (ms / 500) as u8,
                    };
                    inbox[i] = Some(fb.to_can_frame());
                }
            }
            Setup::Odrive => {
                for (i, a) in self.axes.iter().enumerate() {
                    if dropped(self.setup, ms, i) {
                        continue;
                    }
                    let Some(node) = NodeId::new(i as u8) else {
                        continue;
                    };
                    // Estimates every 10 ms, heartbeats every 100 ms (ODrive defaults), offset
                    // per node like drives that booted at different times.
                    let phase = ms + i as u32 * 3;
                    if phase.is_multiple_of(10) {
                        let est = odrive::Feedback::EncoderEstimates {
                            pos: a.pos,
                            vel: a.speed,
                        };
                        inbox[i] = Some(est.to_can_frame(node));
                    }
                    if phase.is_multiple_of(100) {
                        let hb = odrive::Feedback::Heartbeat(odrive::Heartbeat {
                            axis_error: 0,
                            axis_state: a.state,
                            procedure_result: 0,
                            trajectory_done: true,
                        });
                        inbox[4 + i] = Some(hb.to_can_frame(node));
                    }
                }
            }
            Setup::Cia402 => {
                let Some(co) = self.canopen.as_mut() else {
                    return;
                };
                // What each node owes from the last step, then its heartbeat (50 ms, offset
                // per node).
                let mut slots = inbox.iter_mut();
                for (i, n) in co.nodes.iter_mut().enumerate() {
                    let Some(n) = n else { continue };
                    let owed = core::mem::replace(&mut n.pending, [None; NODE_PENDING]);
                    let heartbeat = (ms > 0 && (ms + 7 * i as u32).is_multiple_of(50)).then(|| {
                        let state = if n.operational {
                            NmtState::Operational
                        } else {
                            NmtState::PreOperational
                        };
                        Message::Heartbeat { node: n.id, state }.to_can_frame()
                    });
                    for f in owed.into_iter().chain([heartbeat]).flatten() {
                        if let Some(slot) = slots.next() {
                            *slot = Some(f);
                        }
                    }
                }
            }
        }
    }

    /// Takes one frame the controller sent.
    fn receive(&mut self, frame: &CanFrame) {
        match self.setup {
            Setup::Dji | Setup::Pods => {
                if let Ok(cmd) = dji::CurrentCommand::decode(frame, EscModel::C620) {
                    let first = usize::from(cmd.group.first_esc()) - 1;
                    for (slot, &raw) in cmd.raw.iter().enumerate() {
                        if let Some(a) = self.axes.get_mut(first + slot) {
                            a.raw = raw;
                            a.cmd = EscModel::C620.raw_to_amps(raw);
                        }
                    }
                }
            }
            Setup::Odrive => {
                if let Ok(odrive::Addressed { node, msg }) = odrive::Command::decode(frame) {
                    let Some(a) = self.axes.get_mut(usize::from(node.get())) else {
                        return;
                    };
                    match msg {
                        odrive::Command::SetInputVel { vel, .. } => a.cmd = vel,
                        odrive::Command::SetAxisState(s) => {
                            a.state = s;
                            if s != AxisState::ClosedLoopControl {
                                a.cmd = 0.0;
                            }
                        }
                        _ => {}
                    }
                }
            }
            Setup::Cia402 => self.receive_canopen(frame),
        }
    }

    /// CiA 402: takes one frame of the master (frames of the next step are owed by the nodes).
    fn receive_canopen(&mut self, frame: &CanFrame) {
        let ms = self.ms;
        let Some(co) = self.canopen.as_mut() else {
            return;
        };
        let Ok(msg) = canopen::decode(frame) else {
            return;
        };
        match msg {
            Message::Nmt { command, node } => {
                for n in co.nodes.iter_mut().flatten() {
                    if node.is_some_and(|id| id != n.id) {
                        continue;
                    }
                    match command {
                        NmtCommand::Start => n.operational = true,
                        NmtCommand::Stop | NmtCommand::EnterPreOperational => {
                            n.operational = false;
                        }
                        NmtCommand::ResetNode | NmtCommand::ResetCommunication => n.reboot(),
                    }
                }
            }
            Message::SdoRequest { node, request } => {
                if let Some((_, n)) = co.node(node) {
                    n.sdo(request);
                }
            }
            Message::Sync { .. } => {
                // Each operational node's TPDO1 (statusword, first axis) and TPDO2 (second
                // axis), delivered the next step: synchronous TPDOs, sampled at the SYNC, so
                // before the RPDOs that follow it in the outbox.
                for (index, n) in co.nodes.iter_mut().enumerate() {
                    let Some(n) = n.as_mut().filter(|n| n.operational) else {
                        continue;
                    };
                    let mut actual = [0i32; 2];
                    let mut first_wheel = None;
                    for (w, (a, &(i, slot))) in self.axes.iter().zip(&co.wheel_node).enumerate() {
                        if i == index
                            && let Some(v) = actual.get_mut(slot)
                        {
                            // Saturating, truncating: the drive's own rounding.
                            *v = (a.speed / co.actual_rpm) as i32;
                            if slot == 0 {
                                first_wheel = Some(w);
                            }
                        }
                    }
                    let [v1, v2] = actual;
                    if !first_wheel.is_some_and(|w| dropped(self.setup, ms + 1, w)) {
                        n.owe(
                            Message::Tpdo1 {
                                node: n.id,
                                statusword: n.state.statusword(),
                                velocity: v1,
                            }
                            .to_can_frame(),
                        );
                    }
                    n.owe(
                        Message::Tpdo2 {
                            node: n.id,
                            velocity: v2,
                        }
                        .to_can_frame(),
                    );
                }
            }
            Message::Rpdo1 {
                node,
                controlword,
                target,
            } => {
                if let Some((index, n)) = co.node(node) {
                    n.control(controlword);
                    co.set_target(&mut self.axes, (index, 0), target);
                }
            }
            Message::Rpdo3 { node, target } => {
                if let Some((index, _)) = co.node(node) {
                    co.set_target(&mut self.axes, (index, 1), target);
                }
            }
            _ => {}
        }
    }

    /// Integrates one period, `dt` s.
    fn advance(&mut self, dt: f32) {
        if let Some(p) = &mut self.pods {
            p.advance(self.axes.map(|a| a.speed), dt);
        }
        for a in &mut self.axes {
            match self.setup {
                Setup::Dji | Setup::Pods => {
                    a.speed += dt * (DJI_A * a.cmd - DJI_C * a.speed);
                    a.pos += a.speed * dt * (DJI_COUNTS / TAU);
                    while a.pos >= DJI_COUNTS {
                        a.pos -= DJI_COUNTS;
                    }
                    while a.pos < 0.0 {
                        a.pos += DJI_COUNTS;
                    }
                }
                Setup::Odrive => {
                    if a.state == AxisState::ClosedLoopControl {
                        a.speed += (a.cmd - a.speed) * (OD_K * dt);
                    } else {
                        a.speed -= a.speed * (OD_COAST * dt);
                    }
                    a.pos += a.speed * dt;
                }
                Setup::Cia402 => {}
            }
        }
        if let Some(co) = &self.canopen {
            for (a, &(i, _)) in self.axes.iter_mut().zip(&co.wheel_node) {
                let state = co.nodes.get(i).copied().flatten().map(|n| n.state);
                // Motor rpm; a drive not enabled has no torque and coasts.
                a.speed += match state {
                    Some(DriveState402::OperationEnabled) => (a.cmd - a.speed) * (OD_K * dt),
                    Some(DriveState402::QuickStopActive) => -a.speed * (CO_QUICK_STOP * dt),
                    _ => -a.speed * (OD_COAST * dt),
                };
                a.pos += a.speed * (dt / 60.0);
            }
        }
    }
}

/// Wheel `i`'s feedback is missing at `ms` (the stale-motor part of the script).
fn dropped(setup: Setup, ms: u32, i: usize) -> bool {
    let len = match setup {
        Setup::Dji | Setup::Pods => 10,
        Setup::Odrive => 50,
        Setup::Cia402 => 20,
    };
    i == 2 && (2700..2700 + len).contains(&ms)
}

fn twist_frame(vx: f32, vy: f32, wz: f32, seq: u8) -> CanFrame {
    Command::Twist(TwistCmd { vx, vy, wz, seq }).to_can_frame()
}

/// The host's frames at `ms` (see the script in the crate documentation).
fn host_commands(ms: u32, seq: &mut u8, out: &mut [Option<CanFrame>; 6]) {
    *out = [None; 6];
    let mut n = 0;
    let mut put = |f: CanFrame| {
        if let Some(slot) = out.get_mut(n) {
            *slot = Some(f);
            n += 1;
        }
    };
    match ms {
        5 | 1380 | 2760 => put(Command::StatusRequest.to_can_frame()),
        10 | 1400 | 2110 | 2850 => put(Command::Mode(ModeRequest::Enable).to_can_frame()),
        1900 => put(Command::Estop.to_can_frame()),
        2100 | 2800 => put(Command::Mode(ModeRequest::Reset).to_can_frame()),
        2600 => put(Command::Mode(ModeRequest::Disable).to_can_frame()),
        1500 => {
            // Rejected: over max_linear_speed, a 7-byte twist, an unknown id, an extended id.
            put(twist_frame(3.5, 0.0, 0.0, 0));
            let twist = robot::layout::TWIST_CMD.id;
            if let Some(id) = StandardId::new(twist) {
                put(CanFrame::standard(id, &[0; 7])
                    .unwrap_or_else(|| twist_frame(0.0, 0.0, 0.0, 0)));
            }
            if let Some(id) = StandardId::new(0x123) {
                put(CanFrame::standard(id, &[1, 2, 3])
                    .unwrap_or_else(|| twist_frame(0.0, 0.0, 0.0, 0)));
            }
            if let Some(id) = ExtendedId::new(0x0123_4567)
                && let Some(f) = CanFrame::new(id, &[0xAA; 8])
            {
                put(f);
            }
            put(twist_frame(-0.4, 0.6, 3.0, *seq));
            *seq = seq.wrapping_add(1);
        }
        _ => {}
    }
    if ms.is_multiple_of(20) && ms != 1500 {
        let t = ms as f32 * 0.001;
        let twist = match ms {
            20..100 => Some((0.8, 0.0, 0.0)),
            100..800 => Some((0.5, 0.3, 1.5)),
            800..1200 => {
                let (s, c) = libm::sincosf(4.0 * t);
                Some((0.6 * c, 0.6 * s, -2.0))
            }
            1410..1900 => Some((-0.4, 0.6, 3.0)),
            1900..2000 => Some((1.0, 0.0, 0.0)),
            2120..2600 => Some((0.3, -0.2, 2.5 * libm::sinf(10.0 * t))),
            2860..3000 => Some((0.7, 0.7, -1.0)),
            _ => None,
        };
        if let Some((vx, vy, wz)) = twist {
            put(twist_frame(vx, vy, wz, *seq));
            *seq = seq.wrapping_add(1);
        }
    }
}

/// Hex of an `f32`'s bits, for the report (exact, unlike a decimal rendering).
struct Bits(f32);

impl fmt::Display for Bits {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:08x}", self.0.to_bits())
    }
}

/// Runs the scenario for `setup` and writes its report to `out`:
///
/// ```text
/// begin <setup> steps=<n>
/// f <setup> <frame index> <t_us> <candump>          every `frame_every`-th frame
/// ck <setup> step=<k> frames=<n> hash=<16 hex>      after every 100th step
/// end <setup> frames=<n> hash=<16 hex> state=<s> fault=<f> pose=<x>,<y>,<heading bits> rx_errors=<n>
/// ```
///
/// # Errors
/// Only those of `out`.
///
/// # Panics
/// If the example configuration is rejected (a bug in the firmware crate).
pub fn run<W: Write, P: Probe>(
    setup: Setup,
    opts: &Options,
    out: &mut W,
    probe: &mut P,
) -> Result<Digest, fmt::Error> {
    let config = setup.config();
    let mut ctl = match Controller::new(&config) {
        Ok(ctl) => ctl,
        Err(e) => panic!("example configuration rejected: {}", e.field),
    };
    let dt = ctl.period();
    let name = setup.name();
    let mut plant = Plant::new(setup, &config);
    let mut hash = StreamHash::new();
    let mut frames = 0u64;
    let mut seq = 0u8;
    let mut inbox: Inbox = [None; 8];
    let mut cmds = [None; 6];
    writeln!(out, "begin {name} steps={}", opts.steps)?;
    for k in 0..opts.steps {
        let now = Instant::from_micros(u64::from(k) * PERIOD_US);
        plant.feedback(k, &mut inbox);
        host_commands(k, &mut seq, &mut cmds);

        probe.core_begin(setup, k);
        for f in inbox.iter().chain(cmds.iter()).flatten() {
            ctl.on_frame(now, f);
        }
        let outbox = ctl.step(now);
        probe.core_end(setup, k);

        for f in &outbox {
            hash.add(now.as_micros(), f);
            if opts.frame_every != 0 && frames.is_multiple_of(u64::from(opts.frame_every)) {
                writeln!(out, "f {name} {frames} {} {f}", now.as_micros())?;
            }
            frames += 1;
            plant.receive(f);
        }
        plant.advance(dt);
        if opts.checkpoints && (k + 1).is_multiple_of(CHECKPOINT_EVERY) {
            writeln!(
                out,
                "ck {name} step={} frames={frames} hash={:016x}",
                k + 1,
                hash.value()
            )?;
        }
    }
    let s = ctl.snapshot();
    writeln!(
        out,
        "end {name} frames={frames} hash={:016x} state={:?} fault={:?} pose={},{},{} rx_errors={}",
        hash.value(),
        s.state,
        s.fault,
        Bits(s.pose.x),
        Bits(s.pose.y),
        Bits(s.pose.heading),
        s.rx_errors.total(),
    )?;
    Ok(Digest {
        frames,
        hash: hash.value(),
    })
}

/// Runs every setup ([`Setup::ALL`]) and ends with a `total` line: the frames of all and the
/// hash of their hashes.
///
/// # Errors
/// Only those of `out`.
pub fn run_all<W: Write, P: Probe>(
    opts: &Options,
    out: &mut W,
    probe: &mut P,
) -> Result<Digest, fmt::Error> {
    let mut total = Digest { frames: 0, hash: 0 };
    let mut h = StreamHash::new();
    for setup in Setup::ALL {
        let d = run(setup, opts, out, probe)?;
        total.frames += d.frames;
        h.write(&d.hash.to_le_bytes());
    }
    total.hash = h.value();
    writeln!(
        out,
        "total frames={} hash={:016x}",
        total.frames, total.hash
    )?;
    Ok(total)
}
