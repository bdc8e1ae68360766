//! The control core: a deterministic, fixed-step state machine from received frames and the
//! time to frames to send. Its specification (states, faults and their latencies, the watches,
//! the wheel test, the command watchdog, the gyro heading) is `docs/control.md`.
//!
//! ```text
//! on_frame ─► decode (typed; errors counted) ─► command.rs (robot commands)
//!                                            ├► params.rs (parameter requests, kept)
//!                                            └► dji.rs │ odrive.rs │ cia402/ (drives)
//! step(now) ─► params.rs (the request kept served: a change in force from here)
//!           ─► health.rs (missing / stale / drive error, the drive's watches → fault)
//!           ─► command.rs (watchdog, acceleration limits), wheel_test.rs
//!           ─► odometry.rs (wheel increments, the gyro's rotation → SE(2) pose)
//!           ─► inverse kinematics ─► desaturation
//!           ─► dji.rs (current_loop.rs: velocity PI → currents) │ odrive.rs (setpoints)
//!              │ cia402/ (setup, enable, cycle; watch)
//!           ─► telemetry.rs (odometry, status, heartbeat at their rates)
//! ```
//!
//! One file a concern, one file a drive protocol: a new protocol is a variant of
//! `DriveState`'s and a file beside `dji.rs`, and nothing else in the core matches on the
//! drive. [`Controller`]'s fields are private to this module; each file adds the methods of
//! its concern.
//!
//! The core reads no clock and allocates nothing: time comes in as [`Instant`], frames go out
//! through a fixed-capacity [`Outbox`]. The same inputs give the same frames, bit for bit, on
//! every target.

mod cia402;
mod command;
mod current_loop;
mod dji;
mod health;
mod odometry;
mod odrive;
mod params;
mod pods;
mod telemetry;
mod time;
mod wheel_test;

use embedded_can::Frame;
use kinematics::{ChassisVelocity, MecanumKinematics, Odometry, Pose2, WheelSpeeds};

pub use self::cia402::{
    CANOPEN_NMT_GRACE_US, CANOPEN_SDO_TIMEOUT_US, CIA402_RESET_GRACE_US,
    CIA402_TRANSITION_TIMEOUT_US, DriveIssue,
};
pub use self::current_loop::{
    FIGHT_COMBINED_MIN, FIGHT_CURRENT_FRACTION, FIGHT_WINDOW_US, RUNAWAY_GROWTH, RUNAWAY_MIN_SPEED,
    RUNAWAY_SATURATION, RUNAWAY_WINDOW_US,
};
pub use self::dji::{
    ENCODER_STUCK_BAND_COUNTS, ENCODER_STUCK_DRAGGED_US, ENCODER_STUCK_MIN_CURRENT,
    ENCODER_STUCK_MIN_ROTOR_RPM, ENCODER_STUCK_SPINNING_US,
};
pub use self::odometry::{GYRO_BIAS_MAX_SAMPLES, STANDSTILL_WHEEL_SPEED};
pub use self::odrive::{ODRIVE_CLEAR_GRACE_US, ODRIVE_MAX_JUMP_FACTOR, ODRIVE_STATE_GRACE_US};
pub use self::params::{
    INFO, INFO_INDEX, LOAD_SIGNATURE, RESTORE, SAVE_SIGNATURE, STORE, SaveOutcome,
};
pub use self::pods::SLIP_TIME_CONSTANT_S;
pub use self::telemetry::Snapshot;
pub use self::time::Instant;
pub use self::wheel_test::WHEEL_TEST_CURRENT_FRACTION;
pub use crate::protocol::robot::{Fault, HeadingSource, OdometrySource};

use self::current_loop::WatchInputs;
use self::telemetry::Due;
use self::time::Every;
use crate::config::{Config, ConfigError, Drive};
use crate::frame::CanFrame;
use crate::protocol::robot::{self, Command, RobotState, TestOutcome, WheelTestResult};
use crate::protocol::{DecodeError, RxErrorCounters};

/// Most frames one [`Controller::step`] can emit: two DJI command frames, or for four ODrive
/// axes `Clear_Errors` (after a reset), three state commands (after an enable) and a velocity
/// setpoint each (16), or for four CiA 402 nodes an SDO request, NMT start and RPDO1 each,
/// SYNC and the master's heartbeat (14); plus odometry (2, and the slip with pods: 3), status,
/// status counters and heartbeat (3), a wheel test's result (1) and the parameter service's
/// response (1).
pub const OUTBOX_CAPACITY: usize = 28;

/// The frames one step emits, in the order they should be sent.
pub type Outbox = heapless::Vec<CanFrame, OUTBOX_CAPACITY>;

/// Why [`Controller::new`] refused a configuration.
pub type Error = ConfigError;

/// What the core knows of one wheel, whatever drives it.
#[derive(Debug, Clone, Copy)]
struct Wheel {
    /// -1 where the motor is mirrored (`drive.inverted`), else 1.
    sign: f32,
    /// Time of the last feedback frame that counts for staleness.
    last_seen: Option<Instant>,
    /// Wheel angle accumulated since the last step, rad (robot-forward positive).
    pending: f32,
    /// Wheel angle since the start, rad (robot-forward positive): what the encoders say the
    /// wheel turned, in f32 (its resolution coarsens as it grows: 8 mrad at 65,536 rad).
    angle: f32,
    /// Latest wheel speed, rad/s (robot-forward positive).
    speed: f32,
}

/// The wheel of each drive id (DJI ESC id, ODrive node id): its index, or 4 and above for an
/// id that no wheel has (so that `wheels.get(i)` is the one check).
#[derive(Debug, Clone)]
struct WheelOf([u8; 64]);

impl WheelOf {
    #[inline]
    fn get(&self, id: u8) -> usize {
        usize::from(self.0.get(usize::from(id)).copied().unwrap_or(u8::MAX))
    }
}

/// The drive protocol's own state, and the one place the core tells the drives apart.
#[derive(Debug, Clone)]
#[allow(
    clippy::large_enum_variant,
    reason = "one per controller, never moved after construction; boxing needs a heap"
)]
enum DriveState {
    Dji(dji::Dji),
    Odrive(odrive::Odrive),
    Cia402(cia402::Cia402),
}

impl DriveState {
    /// A feedback frame (any frame outside the robot's own ids).
    #[inline]
    fn on_frame<F: Frame>(
        &mut self,
        now: Instant,
        frame: &F,
        wheel_of: &WheelOf,
        wheels: &mut [Wheel; 4],
    ) -> Result<(), DecodeError> {
        match self {
            Self::Dji(d) => d.on_frame(now, frame, wheel_of, wheels),
            Self::Odrive(o) => o.on_frame(now, frame, wheel_of, wheels),
            Self::Cia402(c) => c.on_frame(now, frame, wheels),
        }
    }

    /// Motion stopped; the robot is now in `state` (`Enabled`: it stays enabled, at zero).
    fn halt(&mut self, state: RobotState) {
        match self {
            Self::Dji(d) => d.current.reset(),
            Self::Odrive(o) if state != RobotState::Enabled => o.request_idle(),
            Self::Odrive(_) => {}
            Self::Cia402(c) => c.halt(state),
        }
    }

    /// An enable (`only` `None`) or a wheel test of wheel `only`.
    fn request_closed_loop(&mut self, now: Instant, only: Option<u8>) {
        match self {
            Self::Dji(_) => {}
            Self::Odrive(o) => o.request_closed_loop(now, only),
            Self::Cia402(c) => c.request_enable(only),
        }
    }

    /// A reset from `Fault` or `Estop`.
    fn clear_errors(&mut self, now: Instant) {
        match self {
            Self::Dji(_) => {}
            Self::Odrive(o) => o.clear_errors(now),
            Self::Cia402(c) => c.clear_errors(now),
        }
    }

    /// A step begins at `now`.
    fn step_started(&mut self, now: Instant) {
        match self {
            Self::Dji(_) => {}
            Self::Odrive(o) => o.step_started(now),
            Self::Cia402(c) => c.step_started(now),
        }
    }

    /// The fault wheel `i`'s drive reports of its own (`Fault::None` if none).
    #[inline]
    fn wheel_fault(&self, i: usize, enabled: bool) -> Fault {
        match self {
            Self::Dji(_) => Fault::None,
            Self::Odrive(o) if o.wheel_fault(i, enabled) => Fault::DriveError,
            Self::Odrive(_) => Fault::None,
            Self::Cia402(c) => c.wheel_fault(i),
        }
    }

    /// Wheel `i`'s drive is being configured: no feedback is expected from it yet.
    #[inline]
    fn wheel_configuring(&self, i: usize) -> bool {
        match self {
            Self::Cia402(c) => c.wheel_configuring(i),
            Self::Dji(_) | Self::Odrive(_) => false,
        }
    }
}

/// The drive controller. See the [module documentation](self) and `docs/control.md`.
#[derive(Debug, Clone)]
pub struct Controller {
    config: Config,
    /// [`Config::id`], sent in every `HEARTBEAT`.
    config_id: u16,
    kin: MecanumKinematics<f32, 4>,
    /// Seconds per control period.
    dt: f32,
    /// Expected feedback period of the motors, µs (staleness reference).
    feedback_period_us: u64,
    wheel_of: WheelOf,
    wheels: [Wheel; 4],
    drive: DriveState,
    /// Odometry frames are due on this step (every `control_hz / odometry_hz` steps).
    odom_clock: Every,
    /// Status and heartbeat frames are due (every `control_hz / status_hz` steps).
    status_clock: Every,
    /// Velocity setpoints (ODrive) or the SYNC cycle (CiA 402) are due (every
    /// `control_hz / setpoint_hz` steps).
    setpoint_clock: Every,

    state: RobotState,
    fault: Fault,
    /// Time of the last valid twist command accepted while enabled (watchdog).
    last_command: Option<Instant>,
    /// `seq` of the last twist accepted since the last enable or reset; `None`: the next
    /// twist is accepted whatever its `seq`.
    last_seq: Option<u8>,
    /// Twists not applied because their `seq` equalled `last_seq` (saturating).
    repeated_seq: u32,
    /// The twist being followed: zero, or a twist that passed `check_twist` (`on_command`
    /// relies on this to take a twist with the same values without checking it again).
    target: ChassisVelocity<f32>,
    commanded: ChassisVelocity<f32>,
    /// Watchdog expired: ramping down, then disable.
    stopping: bool,
    /// Bit i set when wheel i's motor reported within its staleness window at the last step.
    online: u8,
    /// The wheel test running (state `WheelTest`).
    test: Option<wheel_test::TestRun>,
    /// A wheel test's result, sent at the next step.
    test_result: Option<WheelTestResult>,

    odometry: Odometry<f32>,
    measured: ChassisVelocity<f32>,
    setpoints: WheelSpeeds<f32, 4>,
    /// Currents commanded at the last step, A (zero for velocity-mode drives).
    currents: [f32; 4],
    rx_errors: RxErrorCounters,
    gyro: odometry::Gyro,
    pods: pods::Pods,

    /// Odometry and status frames due while the robot held its block (CiA 402: a drive's
    /// RPDO2 may be on), sent at the first step it may speak again.
    held: Due,

    boot: Option<Instant>,
    steps: u64,
    status_requested: bool,
    status_seq: u8,

    /// The parameter service's node id (`params.rs`).
    param_node: u8,
    /// A parameter request received, served at the next step's start.
    param_request: Option<crate::protocol::canopen::SdoRequest>,
    /// The configuration this controller was made with: what a restore puts back.
    builtin: Config,
    /// The saved set (object 0x2100).
    saved: params::SavedSet,
    /// A save or restore being stored by the edge.
    saving: params::Saving,
}

impl Controller {
    /// A controller for a validated configuration, disabled, at pose zero.
    ///
    /// # Errors
    /// The first [`ConfigError`] of [`Config::validate`].
    pub fn new(config: &Config) -> Result<Self, Error> {
        config.validate()?;
        let kin = config.kinematics().map_err(|_| ConfigError {
            field: "geometry",
            value: f64::NAN,
            expected: "a valid layout",
        })?;
        let t = &config.timing;
        let period_us = 1_000_000 / u64::from(t.control_hz);
        let (ids, inverted, feedback_period_us, drive) = match config.drive {
            Drive::Dji {
                model,
                gear_ratio,
                inverted,
                esc_ids,
            } => (
                esc_ids,
                inverted,
                dji::FEEDBACK_PERIOD_US,
                DriveState::Dji(dji::Dji::new(model, gear_ratio, esc_ids, period_us)?),
            ),
            Drive::Odrive {
                node_ids,
                gear_ratio,
                inverted,
                vel_ramp,
            } => (
                node_ids,
                inverted,
                odrive::FEEDBACK_PERIOD_US,
                DriveState::Odrive(odrive::Odrive::new(
                    node_ids,
                    gear_ratio,
                    vel_ramp,
                    config.limits.max_wheel_speed,
                )),
            ),
            Drive::Cia402(ref drive) => (
                drive.node_ids,
                drive.inverted,
                1_000_000 / u64::from(t.setpoint_hz),
                DriveState::Cia402(cia402::Cia402::new(drive, t.control_hz, t.setpoint_hz)),
            ),
        };
        // Ids are validated (in range, one per wheel), so every wheel lands in the table
        // (CiA 402 drives keep their own map: a node may drive two wheels).
        let mut wheel_of = [u8::MAX; 64];
        for (wheel, id) in (0u8..).zip(ids) {
            if let Some(w) = wheel_of.get_mut(usize::from(id)) {
                *w = wheel;
            }
        }
        Ok(Self {
            config: *config,
            config_id: config.id(),
            kin,
            dt: 1.0 / t.control_hz as f32,
            feedback_period_us,
            wheel_of: WheelOf(wheel_of),
            wheels: inverted.map(|i| Wheel {
                sign: if i { -1.0 } else { 1.0 },
                last_seen: None,
                pending: 0.0,
                angle: 0.0,
                speed: 0.0,
            }),
            drive,
            odom_clock: Every::new(t.control_hz / t.odometry_hz),
            status_clock: Every::new(t.control_hz / t.status_hz),
            setpoint_clock: Every::new(t.control_hz / t.setpoint_hz),
            state: RobotState::Disabled,
            fault: Fault::None,
            last_command: None,
            last_seq: None,
            repeated_seq: 0,
            target: ChassisVelocity::default(),
            commanded: ChassisVelocity::default(),
            stopping: false,
            online: 0,
            test: None,
            test_result: None,
            odometry: Odometry::new(Pose2::default()),
            measured: ChassisVelocity::default(),
            setpoints: WheelSpeeds::zero(),
            currents: [0.0; 4],
            rx_errors: RxErrorCounters::new(),
            gyro: odometry::Gyro::default(),
            pods: pods::Pods::new(&config.odometry),
            held: Due::default(),
            boot: None,
            steps: 0,
            status_requested: false,
            status_seq: 0,
            param_node: crate::params::service_node(config),
            param_request: None,
            builtin: *config,
            saved: params::SavedSet {
                builtin_id: config.id(),
                id: config.id(),
                seq: 0,
            },
            saving: params::Saving::Idle,
        })
    }

    /// The configuration in force.
    #[must_use]
    pub const fn config(&self) -> &Config {
        &self.config
    }

    /// The configuration's id ([`Config::id`]), as `HEARTBEAT.config_id` sends it.
    #[must_use]
    pub const fn config_id(&self) -> u16 {
        self.config_id
    }

    /// The control period, s.
    #[must_use]
    pub const fn period(&self) -> f32 {
        self.dt
    }

    /// The control period, µs.
    #[must_use]
    pub const fn period_micros(&self) -> u64 {
        1_000_000 / self.config.timing.control_hz as u64
    }

    /// Current state.
    #[must_use]
    pub const fn state(&self) -> RobotState {
        self.state
    }

    /// Current fault (or the last watchdog stop's reason).
    #[must_use]
    pub const fn fault(&self) -> Fault {
        self.fault
    }

    /// The odometry pose.
    #[must_use]
    pub fn pose(&self) -> Pose2<f32> {
        self.odometry.pose()
    }

    /// Where the odometry's heading came from at the last step.
    #[must_use]
    pub const fn heading_source(&self) -> HeadingSource {
        self.gyro.source
    }

    /// Sets the odometry pose (e.g. from a localisation fix).
    pub fn set_pose(&mut self, pose: Pose2<f32>) {
        self.odometry.set_pose(pose);
    }

    /// Takes one received frame. Call for every frame between two steps, in arrival order.
    pub fn on_frame<F: Frame>(&mut self, now: Instant, frame: &F) {
        if let Err(e) = self.dispatch(now, frame) {
            self.rx_errors.record(&e);
        }
    }

    #[inline]
    fn dispatch<F: Frame>(&mut self, now: Instant, frame: &F) -> Result<(), DecodeError> {
        let raw_id = match frame.id() {
            embedded_can::Id::Standard(id) => id.as_raw(),
            embedded_can::Id::Extended(id) => {
                return Err(DecodeError::ExtendedId { id: id.as_raw() });
            }
        };
        if (robot::layout::ID_FIRST..=robot::layout::ID_LAST).contains(&raw_id) {
            let cmd = Command::decode(frame)?;
            self.on_command(now, cmd)
        } else if self.is_param_request(raw_id) {
            self.on_param_frame(frame)
        } else {
            self.drive
                .on_frame(now, frame, &self.wheel_of, &mut self.wheels)
        }
    }

    /// Runs one control period at time `now` and returns the frames to send.
    ///
    /// Call it once per period (`1 / timing.control_hz`) with a monotonic `now`; frames
    /// received since the previous call must have been passed to [`on_frame`](Self::on_frame).
    /// A loop that keeps its outbox calls [`step_into`](Self::step_into) instead: the outbox
    /// is [`OUTBOX_CAPACITY`] frames, and moving it out of a call that is not inlined copies all of it.
    #[inline]
    pub fn step(&mut self, now: Instant) -> Outbox {
        // Inlined into the caller, so the frames are written straight into the caller's
        // outbox instead of being copied out of this function's frame.
        let mut out = Outbox::new();
        self.step_into(now, &mut out);
        out
    }

    /// [`step`](Self::step), writing the frames to send into `out` (emptied first): for a
    /// loop that keeps one outbox from period to period.
    pub fn step_into(&mut self, now: Instant, out: &mut Outbox) {
        out.clear();
        // A parameter change takes effect here, at the step's start, for the whole step.
        let param_response = self.serve_param();
        let boot = *self.boot.get_or_insert(now);
        self.drive.step_started(now);
        self.check_motors(now, boot);
        self.run_watchdog(now);
        self.time_test(now);
        self.ramp();
        self.update_gyro(now);
        self.update_pods(now);
        self.integrate_odometry();
        // One tick of every rate divider per step, whether or not its frames go out.
        let due = Due {
            odom: self.odom_clock.tick(),
            status: self.status_clock.tick(),
        };
        let setpoint_due = self.setpoint_clock.tick();

        // The wheels driven (bit i: wheel i) and their setpoints.
        let test = self.test.filter(|_| self.state == RobotState::WheelTest);
        let mask = if self.state == RobotState::Enabled {
            self.setpoints = self
                .kin
                .inverse(self.commanded)
                .desaturate(self.config.limits.max_wheel_speed);
            0b1111
        } else if let Some(t) = test {
            let mut sp = [0.0; 4];
            sp[usize::from(t.wheel)] = t.speed;
            self.setpoints = WheelSpeeds(sp);
            1 << t.wheel
        } else {
            self.setpoints = WheelSpeeds::zero();
            0
        };
        self.emit_drive(out, mask, setpoint_due);
        self.note_test_current();
        self.emit_robot_block(out, now, boot, due);
        if let Some(frame) = param_response {
            push(out, frame);
        }
        self.steps += 1;
    }

    /// The drive's frames for this step: the wheels in `mask` driven towards their setpoints
    /// (current drives), the setpoints sent (`setpoints_due` and a wheel driven: ODrive), the
    /// cycle run (`setpoints_due`, driven or not: CiA 402).
    fn emit_drive(&mut self, out: &mut Outbox, mask: u8, setpoints_due: bool) {
        let max = self.current_limit();
        match &mut self.drive {
            DriveState::Dji(d) => {
                self.currents = d.emit(
                    out,
                    &self.wheels,
                    self.setpoints,
                    &self.config.gains,
                    mask,
                    max,
                    self.dt,
                );
            }
            DriveState::Odrive(o) => {
                self.currents = [0.0; 4];
                o.emit(
                    out,
                    &self.wheels,
                    self.setpoints,
                    mask != 0 && setpoints_due,
                );
            }
            DriveState::Cia402(c) => {
                self.currents = [0.0; 4];
                c.emit(out, &mut self.wheels, self.setpoints, setpoints_due);
            }
        }
    }

    /// The robot's own frames (`0x300..=0x31F`) of this step. With CiA 402 drives, while
    /// some drive being brought up may have its RPDO2 (`0x300 + node`) on, the robot holds
    /// them all (the due ones go out at the first step it may speak; its first `HEARTBEAT`
    /// tells a host the block is safe), and in any state a frame with an id that is such
    /// an RPDO2 is not sent (`docs/protocol.md`, "The RPDO2 window").
    fn emit_robot_block(&mut self, out: &mut Outbox, now: Instant, boot: Instant, due: Due) {
        let DriveState::Cia402(c) = &self.drive else {
            self.emit_telemetry(out, now, boot, due);
            return;
        };
        let faulted = matches!(self.state, RobotState::Fault | RobotState::Estop);
        if c.rpdo2_pending(faulted) {
            self.held = self.held.or(due);
            return;
        }
        let due = due.or(core::mem::take(&mut self.held));
        let first = out.len();
        self.emit_telemetry(out, now, boot, due);
        if let DriveState::Cia402(c) = &self.drive {
            let mut i = 0;
            out.retain(|f| {
                i += 1;
                let id = match f.id() {
                    embedded_can::Id::Standard(id) => id.as_raw(),
                    embedded_can::Id::Extended(_) => return true,
                };
                i <= first || !c.is_open_rpdo2(id)
            });
        }
    }

    /// The drive's own watches for this step, on the currents and setpoints of the previous
    /// step (the ones the motors are acting on) and the latest measured speeds.
    fn watch_drive(&mut self, now: Instant) -> Fault {
        let limit = self.current_limit();
        match &mut self.drive {
            DriveState::Dji(d) => d.watch(
                now,
                &WatchInputs {
                    kin: &self.kin,
                    currents: self.currents,
                    setpoints: self.setpoints.0,
                    speeds: self.wheels.map(|w| w.speed),
                    limit,
                    max_current: self.config.limits.max_current,
                    commanded: self.commanded,
                    enabled: self.state == RobotState::Enabled,
                },
            ),
            DriveState::Odrive(_) | DriveState::Cia402(_) => Fault::None,
        }
    }

    /// What the latest CiA 402 fault was, with what the bus said (the node, the object and
    /// the abort code, the last statusword): for logs. `None` for other drives.
    #[must_use]
    pub const fn drive_issue(&self) -> Option<DriveIssue> {
        match &self.drive {
            DriveState::Cia402(c) => c.issue(),
            DriveState::Dji(_) | DriveState::Odrive(_) => None,
        }
    }

    /// EMCY frames received from CiA 402 drives since the start (saturating; 0 for other
    /// drives).
    #[must_use]
    pub const fn drive_emcy_count(&self) -> u32 {
        match &self.drive {
            DriveState::Cia402(c) => c.emcy_count(),
            DriveState::Dji(_) | DriveState::Odrive(_) => 0,
        }
    }

    /// Disables the drive and returns the frames that leave the motors safe: zero current for
    /// DJI ESCs; zero velocity and the idle state for ODrive axes; for CiA 402 nodes SYNC and
    /// shutdown with zero targets. For a runner that is about
    /// to exit (SIGINT/SIGTERM): send these, then stop.
    pub fn shutdown(&mut self) -> Outbox {
        if matches!(self.state, RobotState::Enabled | RobotState::WheelTest) {
            self.end_test(TestOutcome::Stopped);
            self.state = RobotState::Disabled;
        }
        // Not enabled now, so the halt asks an ODrive for idle, a CiA 402 drive for shutdown.
        self.halt();
        self.setpoints = WheelSpeeds::zero();
        let mut out = Outbox::new();
        // A CiA 402 cycle now (the shutdown and zero targets); nothing due for the others.
        let cia402 = matches!(self.drive, DriveState::Cia402(_));
        self.emit_drive(&mut out, 0, cia402);
        out
    }
}

fn push(out: &mut Outbox, frame: CanFrame) {
    // OUTBOX_CAPACITY covers the largest step; a full outbox drops the frame rather than panic.
    let _ = out.push(frame);
}

fn unknown<F: Frame>(frame: &F) -> DecodeError {
    DecodeError::UnknownId { id: frame.id() }
}
