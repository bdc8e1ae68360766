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
//! CiA 402: the nodes are the firmware crate's drive double (`protocol::canopen::drive`, the
//! simulator's), answering the next millisecond, as drives without the option codes
//! 0x605B / 0x605C. The core resets both nodes at 0 ms and configures them by SDO (37
//! transfers a node, one a step), so the enable at 10 ms waits in the enable sequence until
//! the nodes are started (NMT start at 38 ms, SYNC from 40 ms) and runs it from there:
//! enable operation at 56 ms, targets from the SYNC at 64 ms. The disable, the watchdog's
//! stop and the reset send shutdown (the torque goes at once), the e-stop and the stale fault
//! a quick stop (it ends once the wheels rest). Wheel 2's lost feedback is node 2's TPDO1
//! (its statusword and first axis); its TPDO2 still comes.
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
use firmware::protocol::canopen::drive::{
    Axes, AxisCommand, Drives402, Options as CoOptions, Timing,
};
use firmware::protocol::canopen::{self, Message, NodeId as CoNode};
use firmware::protocol::dji::{self, EscId, EscModel};
use firmware::protocol::odrive::{self, AxisState, NodeId};
use firmware::protocol::robot::{self, Command, ModeRequest, TwistCmd};
use firmware::{CanFrame, Config, Controller, Instant, StreamHash};
use kinematics::{MecanumKinematics, PodGeometry, Twist2, WheelSpeeds};

/// Control steps of the full scenario (3 s at 1 kHz).
pub const STEPS: u32 = 3000;

/// The control period, µs (the example configurations run at 1 kHz).
pub const PERIOD_US: u64 = 1000;

/// Nanoseconds a millisecond: the CiA 402 nodes' clock.
const NS_PER_MS: u64 = 1_000_000;

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
/// ODrive's; a quick stop or a slow down decelerates with a 50 ms time constant, otherwise
/// (no torque) the axis coasts.
const CO_QUICK_STOP: f32 = 20.0;

/// A CiA 402 axis slower than this is at rest (a quick stop or a slow down ends), motor rpm:
/// about the simulator's 0.1 rad/s.
const CO_REST_RPM: f32 = 1.0;

/// The scenario's CiA 402 drives have no shutdown and disable operation option codes
/// (0x605B, 0x605C): the master's writes are refused (no failure: the drive keeps its own
/// behaviour), and a shutdown takes the torque at once.
const OPTIONS_402: CoOptions = CoOptions {
    lacks_option_codes: true,
    quick_stop_stays: false,
    self_starting: false,
};

/// The CiA 402 side of the plant: the firmware crate's drive double
/// (`firmware::protocol::canopen::drive`), answering the next millisecond, and what each
/// wheel's node asks of it.
#[derive(Clone, Debug)]
struct Canopen {
    drives: Drives402,
    /// Each wheel's command from its node.
    command: [AxisCommand; 4],
    /// Motor rpm per raw unit of target and of actual velocity.
    target_rpm: f32,
    actual_rpm: f32,
    /// The node of wheel 2, whose TPDO1 (statusword and first axis) the stale-motor part of
    /// the script drops.
    stale_node: Option<CoNode>,
}

impl Canopen {
    fn new(config: &Config) -> Option<Self> {
        let Drive::Cia402(Cia402Drive {
            node_ids,
            target_rpm_per_unit,
            actual_rpm_per_unit,
            ..
        }) = config.drive
        else {
            return None;
        };
        Some(Self {
            drives: Drives402::new(config, Timing::NEXT_MS, OPTIONS_402),
            command: [AxisCommand::Off; 4],
            target_rpm: target_rpm_per_unit,
            actual_rpm: actual_rpm_per_unit,
            stale_node: CoNode::new(node_ids[2]),
        })
    }

    /// The drives and the plant's axes as they see them.
    fn split<'a>(&'a mut self, axes: &'a mut [Axis; 4]) -> (&'a mut Drives402, CoAxes<'a>) {
        let view = CoAxes {
            axes,
            command: &mut self.command,
            target_rpm: self.target_rpm,
            actual_rpm: self.actual_rpm,
        };
        (&mut self.drives, view)
    }
}

/// The plant's axes as the CiA 402 nodes see them, by wheel.
struct CoAxes<'a> {
    axes: &'a mut [Axis; 4],
    command: &'a mut [AxisCommand; 4],
    target_rpm: f32,
    actual_rpm: f32,
}

impl Axes for CoAxes<'_> {
    fn command(&mut self, wheel: usize, command: AxisCommand) {
        if let (Some(c), Some(a)) = (self.command.get_mut(wheel), self.axes.get_mut(wheel)) {
            *c = command;
            if let AxisCommand::Velocity(target) = command {
                a.cmd = target as f32 * self.target_rpm;
            }
        }
    }

    fn velocity(&self, wheel: usize) -> i32 {
        // Saturating, truncating: the drive's own rounding.
        self.axes
            .get(wheel)
            .map_or(0, |a| (a.speed / self.actual_rpm) as i32)
    }

    fn at_rest(&self, wheel: usize) -> bool {
        self.axes
            .get(wheel)
            .is_none_or(|a| a.speed.abs() < CO_REST_RPM)
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

/// Frames one step can feed the controller (4 estimates + 4 heartbeats, 4 DJI feedbacks, or
/// what two CiA 402 nodes owe: their TPDOs, answers, heartbeats and boot-ups).
type Inbox = [Option<CanFrame>; 12];

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
        *inbox = [None; 12];
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
                // What the nodes owe by now, in time order, but wheel 2's node's TPDO1 while
                // its feedback is cut.
                let stale = co.stale_node.filter(|_| dropped(self.setup, ms, 2));
                let (drives, mut axes) = co.split(&mut self.axes);
                let mut slots = inbox.iter_mut();
                drives.feedback(u64::from(ms) * NS_PER_MS, &mut axes, |_, f| {
                    if stale.is_some_and(|node| {
                        matches!(canopen::decode(&f), Ok(Message::Tpdo1 { node: n, .. }) if n == node)
                    }) {
                        return;
                    }
                    match slots.next() {
                        Some(slot) => *slot = Some(f),
                        None => panic!("more CiA 402 frames in one step than the inbox holds"),
                    }
                });
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

    /// CiA 402: takes one frame of the master (the nodes answer the next step).
    fn receive_canopen(&mut self, frame: &CanFrame) {
        let t_ns = u64::from(self.ms) * NS_PER_MS;
        let Some(co) = self.canopen.as_mut() else {
            return;
        };
        let (drives, mut axes) = co.split(&mut self.axes);
        drives.on_frame(t_ns, frame, &mut axes);
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
            for (a, command) in self.axes.iter_mut().zip(co.command) {
                // Motor rpm; a drive without torque coasts.
                a.speed += match command {
                    AxisCommand::Velocity(_) => (a.cmd - a.speed) * (OD_K * dt),
                    AxisCommand::QuickStop | AxisCommand::SlowDown => {
                        -a.speed * (CO_QUICK_STOP * dt)
                    }
                    AxisCommand::Off => -a.speed * (OD_COAST * dt),
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
    let mut inbox: Inbox = [None; 12];
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
