//! The control core: a deterministic, fixed-step state machine from received frames and the
//! time to frames to send.
//!
//! # One period
//!
//! ```text
//! on_frame ─► decode (typed; errors counted) ─► robot commands │ motor feedback (encoders, speeds)
//! step(now) ─► motor health (missing / stale / drive error / stuck encoder → fault)
//!           ─► command watchdog (expired → stop ramp → disable, latched)
//!           ─► acceleration limits ─► inverse kinematics ─► desaturation
//!           ─► per-wheel velocity PI (current drives) │ velocity setpoints (ODrive)
//!           ─► odometry (encoder increments → forward kinematics → SE(2) exp; the rotation
//!              from the gyro, less its bias, when configured and alive)
//!           ─► frames: motor commands every period, odometry / status (+ counters) / heartbeat
//!              at their rates
//! ```
//!
//! # States
//!
//! | state | motors | leaves on |
//! |---|---|---|
//! | `Disabled` | no torque | `MODE_CMD enable` → `Enabled` |
//! | `Enabled` | driven | `disable`, watchdog stop completed → `Disabled`; fault → `Fault`; e-stop → `Estop` |
//! | `Fault` | no torque | `MODE_CMD reset` → `Disabled` |
//! | `Estop` | no torque | `MODE_CMD reset` → `Disabled` |
//!
//! # Faults
//!
//! Checked at every step, in this order (the first that applies is reported); each one moves
//! `Disabled`, `Enabled` or `WheelTest` to `Fault` with no torque, latched until `MODE_CMD reset` (which
//! faults again at the next step if the cause is still there).
//!
//! | fault | condition | latency |
//! |---|---|---|
//! | `MotorMissing` | a motor never reported, `timing.boot_timeout_ms` after the first step | the next step |
//! | `MotorStale` | a motor's last feedback is older than `timing.stale_periods` feedback periods (DJI 1 ms, ODrive estimates 10 ms) | ≤ that + one control period after its last frame |
//! | `DriveError` | an ODrive heartbeat or `Get_Error` reports a nonzero axis error, or (while enabled) an axis state other than closed loop | the next step |
//! | `EncoderStuck` | see below (DJI only) | [`ENCODER_STUCK_SPINNING_US`] / [`ENCODER_STUCK_DRAGGED_US`] after the signature appears |
//! | `WheelRunaway` | see below (current drives: DJI) | [`RUNAWAY_WINDOW_US`] after the current saturates |
//! | `WheelFight` | see below (current drives: DJI) | [`FIGHT_WINDOW_US`] after the wheels start pushing against each other |
//!
//! An ODrive keeps reporting an axis error until it is told to clear it, so for ODrive
//! drives `MODE_CMD reset` also sends `Clear_Errors` to every node at the next step; error
//! bits in heartbeats received before that, or within [`ODRIVE_CLEAR_GRACE_US`] after it,
//! are ignored as stale. A cause that is still there is reported again by the next heartbeat
//! and faults again.
//!
//! `Watchdog` is not a fault state but the reason a watchdog stop gives (below); `Config`
//! is for runners that refuse a configuration.
//!
//! A motor is *online* (`STATUS.motors_online`, [`Snapshot::motors_online`]) while its last
//! feedback is within the `MotorStale` window. Feedback values are checked before they are
//! used: the codecs reject malformed frames and non-finite numbers, and an ODrive position
//! estimate that jumped further than the wheel can turn ([`ODRIVE_MAX_JUMP_FACTOR`]) becomes
//! the new reference instead of moving the odometry. Every rejected frame is counted by kind.
//! A frame stamped earlier than one already taken never moves a time mark (watchdog,
//! staleness) back.
//!
//! ## Stuck encoder (DJI)
//!
//! A C620/C610 whose feedback keeps arriving but whose rotor angle stays within
//! [`ENCODER_STUCK_BAND_COUNTS`] counts of where it last moved is *still*. A still rotor is
//! a stuck encoder when, at every step for a window,
//!
//! 1. **spinning**: it reports a rotor speed of at least [`ENCODER_STUCK_MIN_ROTOR_RPM`]
//!    (a rotor at 100 rpm moves 13.7 counts per millisecond, so a still angle contradicts
//!    the speed in the same frame). Window [`ENCODER_STUCK_SPINNING_US`]. This is also what
//!    an ESC or gateway that repeats one stale frame looks like.
//! 2. **dragged**: its commanded current is at least [`ENCODER_STUCK_MIN_CURRENT`] of
//!    `limits.max_current` *and* the other three wheels imply
//!    ([`MecanumKinematics::implied_by_others`]) that it turns at least as fast as rule 1's
//!    speed. Window [`ENCODER_STUCK_DRAGGED_US`], longer because the evidence is indirect.
//!    This covers an encoder that reads zero speed too.
//!
//! A wheel that is genuinely blocked while the others stand (the robot against a wall) is not
//! flagged: it reports no speed and nothing implies that it turns. A wheel locked on its own
//! while the chassis drags it over the ground looks exactly like rule 2 and is reported as
//! `EncoderStuck`; either way the drive cannot follow its setpoint and stopping is right.
//! The detector reads only feedback frames, the currents the core itself commanded and
//! `now`: no clock, no heap. ODrive axes are not watched here: the ODrive runs its own
//! velocity loop on the same encoder and reports encoder and spin-out failures in its axis
//! error, which becomes `DriveError`.
//!
//! ## Wheel runaway (current drives)
//!
//! While the core runs a wheel's velocity loop (`Enabled`, or that wheel in `WheelTest`), a
//! wheel is *saturated* when the current commanded at the previous step is at least
//! [`RUNAWAY_SATURATION`] of the limit in force (`limits.max_current`; a quarter of it in a
//! wheel test) and pushes towards the setpoint. A wheel saturated at every step for
//! [`RUNAWAY_WINDOW_US`] (and for as many steps as the window spans, so that a loop that
//! stalls does not judge on one late look) is a *runaway* when, at the end of that window
//! or any later step of the same interval,
//!
//! 1. it turns against its setpoint, at least [`RUNAWAY_MIN_SPEED`] the other way, or
//! 2. its speed has moved at least [`RUNAWAY_GROWTH`] the other way than its current pushes
//!    since the interval began (dragged away from its setpoint).
//!
//! That is a drive that cannot follow its setpoint with everything the loop can give: a
//! sign error between a drive's current and its own encoder (positive feedback) runs the
//! wheel away at full current. Normal driving stays far from saturation: the acceleration
//! limits ask for a few amperes. A wheel held still at full current (blocked against a
//! wall) does not move away and is not a runaway.
//!
//! ## Wheels that fight (current drives)
//!
//! A motor mounted the other way than `drive.inverted` says does not run away: the sign is
//! applied to its current and to its encoder alike, so its loop stays stable and its
//! encoder follows the setpoint while the wheel really turns backwards, scrubbing on the
//! ground against the three others (measured in the simulator: no current near saturation,
//! the robot still making 80 % of a commanded forward leg). What shows is the currents:
//! every torque pattern that moves or holds the body lies in the range of the kinematics
//! (`J`), and a wheel pushing against the others adds a part outside it, the part the
//! forward kinematics cannot explain (their residual, the same one that measures slip in
//! wheel speeds). While `Enabled`, when the residual of the currents commanded at the
//! previous step has an RMS of at least [`FIGHT_CURRENT_FRACTION`] of `limits.max_current`
//! at every step for [`FIGHT_WINDOW_US`] (and as many steps as it spans), the core faults
//! `WheelFight`. The watch rests while the commanded twist strafes and turns at once
//! (both at least [`FIGHT_COMBINED_MIN`]), and after that until the residual has dropped
//! below the threshold (the loops' integrators hold the pushing for a while): there the
//! rollers' drag makes a right robot's wheels push against each other as well, so a
//! flipped motor on a robot that only ever strafes and turns at once is caught at its
//! first other motion after a stop. Measured on the simulated robot (sustained over
//! 60 steps): a right wiring gives 0.00 A in any translation, 0.16 A in a spin on the spot,
//! but 0.6-0.7 A in a moderate strafe-and-turn and 2.2 A in 1 m/s strafe with 2 rad/s
//! turn; a single flipped motor gives 1.9-4.9 A in every motion, and crosses the threshold
//! within about 0.3 s of a twist from rest (the hostsim crate's `tests/miswiring.rs`). A
//! real robot's uneven loads leave some residual of their own: if it faults `WheelFight`
//! with a right wiring (the bring-up check says so), that is the figure to measure. Drives swapped between wheels are not
//! seen this way: every encoder and every current stays consistent with some body motion
//! (a swap of FL and RR, with the right side mirrored, turns forward into a rigid strafe; a
//! swap of FL and FR fights in a pattern that the currents see as a forward push), so the
//! bring-up check (`WHEEL_TEST`, someone watching the wheels) is what finds those.
//! Velocity-mode drives (ODrive) run their own loop and report a spin-out in their axis
//! error (`DriveError`).
//!
//! # Wheel test
//!
//! A `WHEEL_TEST` received while `Disabled` drives that one wheel at its speed for its
//! duration (state `WheelTest`): current drives run the velocity loop of that wheel alone,
//! limited to [`WHEEL_TEST_CURRENT_FRACTION`] of `limits.max_current`, the other wheels get
//! no current; an ODrive gets closed loop and the setpoint on that axis only. The motor
//! health checks and the runaway watch run as when enabled; the command watchdog does not
//! (the duration bounds the test). It ends at the first step at or after its duration
//! (`DONE`), on `MODE_CMD disable` or `ESTOP` (`STOPPED`), or by a fault (`FAULT`), back to
//! `Disabled` (or `Estop`, `Fault`); `MODE_CMD enable` is ignored meanwhile. In any other
//! state it is refused (`REFUSED`). The next step sends one `WHEEL_TEST_RESULT` with how far
//! the wheel's encoder turned and the peak current.
//!
//! # Command watchdog
//!
//! Only a valid `TWIST_CMD` received while enabled, whose `seq` differs from the last accepted
//! twist's, feeds the watchdog: status requests, mode commands, rejected twists and repeated
//! ones never do. After an enable the robot holds still until a twist command arrives *after*
//! the enable (a fresh command), so a stale setpoint can never restart motion. When the
//! watchdog expires the commanded twist ramps to zero at
//! [`Limits::stop_linear_decel`](crate::config::Limits) and the state then drops to `Disabled`
//! with fault reason `Watchdog` reported: motion resumes only after an explicit enable and a
//! fresh command.
//!
//! `TWIST_CMD.seq` is an alive counter ([`robot`]): a twist whose `seq` equals the last
//! accepted one's is a *repeat* (a host, a USB adapter or a gateway that resends one frame
//! forever) and is neither applied nor fed to the watchdog, so a sender stuck on one frame
//! stops the robot exactly as silence does: the watchdog fires one
//! `timing.command_timeout_ms` after the last accepted twist and the stop ramp follows. Any
//! other `seq` is accepted (255 → 0 is an increment; the host may skip values). Repeats are
//! counted ([`Snapshot::repeated_seq`], `STATUS_COUNTERS.repeated_seq`) in every state, so
//! a sender that keeps repeating after the stop still shows; they are not rejected frames
//! (`rx_errors`). The last accepted `seq` is forgotten at an enable and at a reset: the
//! first twist after either is accepted whatever its `seq` (after a watchdog stop the robot
//! is disabled, and only an enable lets it move again). A repeat is judged after the
//! limits, so a twist beyond them is an `OutOfRange` rejection whatever its `seq`.
//!
//! # Gyro heading
//!
//! With `odometry.heading_source = "gyro"` ([`HeadingMode::Gyro`]) each step's rotation comes
//! from the gyro, as WPILib's odometry takes a gyro angle in every update: the latest yaw rate
//! of an `IMU_YAW_RATE` frame, less the estimated bias, times the step's period. The
//! translation still comes from the wheels (forward kinematics of the step's increments), and
//! the step moves the pose along the SE(2) arc of that displacement as without a gyro. The
//! measured yaw rate (`ODOM_VELOCITY.wz`) is the gyro's, less the bias, too.
//!
//! The gyro is *alive* while its last valid frame is at most `odometry.gyro_timeout_ms` old.
//! While it is not (silent, unplugged, every frame rejected, or not heard yet) the wheels give
//! the rotation again and `STATUS.heading_source` says `WHEELS_GYRO_SILENT`
//! ([`HeadingSource::WheelsGyroSilent`]): a warning, not a fault. The robot keeps its state
//! and keeps driving; the first valid frame after the silence makes the gyro the source again.
//! `IMU_YAW_RATE.seq` is an alive counter like `TWIST_CMD.seq`: a frame that repeats the last
//! accepted `seq` is not used (so a node stuck on one frame goes silent), and is counted in
//! `repeated_seq`, after a silence too. Malformed frames (wrong DLC, NaN or
//! infinite, beyond ±35 rad/s) are rejected and counted by kind like every other frame.
//!
//! **Bias.** A MEMS gyro reads a small rate when still (its bias, 0.1 °/s is common: 6° of
//! heading a minute). The core learns it while the robot *stands still*: no motion commanded
//! (not enabled, or a zero target and a zero commanded twist) and every wheel online with a
//! speed below [`STANDSTILL_WHEEL_SPEED`], for longer than `odometry.gyro_standstill_ms` (the
//! chassis settles first). Each valid frame received then is a sample of the bias: the
//! estimate is their running mean, which becomes an exponential average over the last
//! [`GYRO_BIAS_MAX_SAMPLES`] once it has that many (10 s of a 200 Hz gyro), so a bias that
//! drifts with temperature is followed across standstills. It starts at zero, and is not
//! learned with `odometry.gyro_bias_estimation = false` (a gyro that removes its own bias).
//! With `heading_source = "wheels"`, the default, `IMU_YAW_RATE` frames are decoded and
//! counted but not used, `STATUS.heading_source` is always `WHEELS`, and every frame the core
//! sends is what it sent before the gyro existed.
//!
//! # Determinism
//!
//! The core reads no clock and allocates nothing: time comes in as [`Instant`], frames go out
//! through a fixed-capacity [`Outbox`]. The same inputs give the same frames, bit for bit, on
//! every target.

use embedded_can::Frame;
use kinematics::{
    ChassisVelocity, Encoder, EncoderConfig, MecanumKinematics, Odometry, Pose2, Real, WheelDeltas,
    WheelSpeeds,
};

use crate::config::{Config, ConfigError, Drive, Gains, HeadingMode, Limits};
use crate::frame::CanFrame;
use crate::protocol::dji::{self, CurrentCommand, EscGroup, EscId, EscModel};
use crate::protocol::odrive::{self, AxisState, ControlMode, InputMode, NodeId};
use crate::protocol::robot::{
    self, Command, ImuYawRate, ModeRequest, RobotState, TestOutcome, TwistCmd, WheelTest,
    WheelTestResult,
};
use crate::protocol::{DecodeError, RxErrorCounters};

pub use crate::protocol::robot::{Fault, HeadingSource};

/// Stuck-encoder band: a rotor angle within this many counts (of 8192 per rotor turn) of
/// where the rotor last moved counts as not moving.
pub const ENCODER_STUCK_BAND_COUNTS: u16 = 2;
/// Rotor speed (rpm, motor side, either sign) above which a still angle is a contradiction.
pub const ENCODER_STUCK_MIN_ROTOR_RPM: f32 = 100.0;
/// How long a still rotor must report speed before `EncoderStuck` (rule 1), µs.
pub const ENCODER_STUCK_SPINNING_US: u64 = 10_000;
/// How long a still rotor must be driven while the other wheels move before `EncoderStuck`
/// (rule 2), µs.
pub const ENCODER_STUCK_DRAGGED_US: u64 = 50_000;
/// Fraction of `limits.max_current` that counts as driven hard (rule 2).
pub const ENCODER_STUCK_MIN_CURRENT: f32 = 0.25;
/// ODrive: a position estimate that moved more than this many times what
/// `limits.max_wheel_speed` allows since the previous one (plus one estimate period) is not
/// integrated into the odometry (a drive reboot restarting its count, a corrupt value); it
/// becomes the new reference and is counted as an out-of-range frame.
pub const ODRIVE_MAX_JUMP_FACTOR: f32 = 2.0;
/// ODrive: heartbeats received until this long after the step that asked for closed loop
/// (after an enable) may predate the request: their axis state is not judged, µs. One and a
/// half heartbeat periods, so that a stalled runner or drive does not turn an old heartbeat
/// into a fault. A later heartbeat of an enabled robot that reports another state is a
/// `DriveError`.
pub const ODRIVE_STATE_GRACE_US: u64 = 150_000;
/// ODrive: after a reset, heartbeat and `Get_Error` frames received until this long after the
/// next step sent `Clear_Errors` may predate the clearing: their error bits are ignored, µs.
/// One and a half heartbeat periods, as [`ODRIVE_STATE_GRACE_US`]; a cause that persists
/// shows in the first heartbeat after it.
pub const ODRIVE_CLEAR_GRACE_US: u64 = 150_000;

/// Wheel runaway: a current at least this fraction of the limit in force is saturated.
pub const RUNAWAY_SATURATION: f32 = 0.95;
/// Wheel runaway: how long a wheel's current must stay saturated towards its setpoint before
/// its speed is judged, µs.
pub const RUNAWAY_WINDOW_US: u64 = 60_000;
/// Wheel runaway: a wheel turning against its setpoint at least this fast (rad/s at the
/// wheel) is turning the other way.
pub const RUNAWAY_MIN_SPEED: f32 = 1.0;
/// Wheel runaway: a wheel whose speed moved at least this much (rad/s) the other way than
/// its current pushes, since its current saturated, moves away from its setpoint.
pub const RUNAWAY_GROWTH: f32 = 2.0;
/// Wheels that fight: a residual of the currents (the part no body motion explains) with
/// an RMS at least this fraction of `limits.max_current` is a fight (0.8 A of 16 A).
pub const FIGHT_CURRENT_FRACTION: f32 = 0.05;
/// Wheels that fight: the watch rests while the commanded twist strafes and turns at once,
/// at least this fast each (m/s and rad/s), where the rollers' drag makes a right robot's
/// wheels push against each other too.
pub const FIGHT_COMBINED_MIN: f32 = 0.02;
/// Wheels that fight: how long the residual must stay above its threshold, µs.
pub const FIGHT_WINDOW_US: u64 = 60_000;
/// Wheel test: the current limit is this fraction of `limits.max_current` (current drives).
pub const WHEEL_TEST_CURRENT_FRACTION: f32 = 0.25;

/// A wheel turning slower than this (either way) is at rest for the gyro's bias estimate,
/// rad/s: 3.8 mm/s at the rim of a 76 mm wheel.
pub const STANDSTILL_WHEEL_SPEED: f32 = 0.05;
/// The gyro's bias estimate is the running mean of its standstill readings up to this many,
/// then an exponential average with this weight (see
/// [the module documentation](self#gyro-heading)).
pub const GYRO_BIAS_MAX_SAMPLES: u32 = 2000;

/// A point in time, microseconds since an arbitrary epoch; monotonic. The core never reads a
/// clock: the adapter (runner, board, simulator) passes it in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct Instant(u64);

impl Instant {
    /// From microseconds.
    #[must_use]
    pub const fn from_micros(us: u64) -> Self {
        Self(us)
    }

    /// From milliseconds.
    #[must_use]
    pub const fn from_millis(ms: u64) -> Self {
        Self(ms * 1000)
    }

    /// Microseconds since the epoch.
    #[must_use]
    pub const fn as_micros(self) -> u64 {
        self.0
    }

    /// Microseconds from `earlier` to `self`, zero if `earlier` is later.
    #[must_use]
    pub const fn micros_since(self, earlier: Self) -> u64 {
        self.0.saturating_sub(earlier.0)
    }
}

/// Most frames one [`Controller::step`] can emit: two DJI command frames, or for four ODrive
/// axes `Clear_Errors` (after a reset), three state commands (after an enable) and a velocity
/// setpoint each; plus odometry (2), status, status counters and heartbeat (3), and a wheel
/// test's result (1).
pub const OUTBOX_CAPACITY: usize = 26;

/// The frames one step emits, in the order they should be sent.
pub type Outbox = heapless::Vec<CanFrame, OUTBOX_CAPACITY>;

/// Why [`Controller::new`] refused a configuration.
pub type Error = ConfigError;

/// What one wheel's motor has told us.
#[derive(Debug, Clone, Copy)]
struct Motor {
    /// Time of the last feedback frame that counts for staleness.
    last_seen: Option<Instant>,
    /// DJI: rotor angle integrator. Unused for ODrive.
    encoder: Encoder<f32>,
    /// ODrive: last position estimate, motor turns.
    last_pos: Option<f32>,
    /// Wheel angle accumulated since the last step, rad (robot-forward positive).
    pending: f32,
    /// Wheel angle since the start, rad (robot-forward positive): what the encoders say the
    /// wheel turned, in f32 (its resolution coarsens as it grows: 8 mrad at 65,536 rad).
    angle: f32,
    /// Latest wheel speed, rad/s (robot-forward positive).
    speed: f32,
    /// ODrive: latest heartbeat.
    axis_error: u32,
    axis_state: Option<AxisState>,
    /// Velocity PI integrator, A.
    integral: f32,
    /// DJI: stuck-encoder watch.
    watch: StuckWatch,
    /// Current drives: runaway watch.
    runaway: RunawayWatch,
}

/// Runaway watch of one current-driven wheel (see the [module documentation](self)).
#[derive(Debug, Clone, Copy, Default)]
struct RunawayWatch {
    /// First step of the running interval of saturated current towards the setpoint.
    since: Option<Instant>,
    /// The wheel's speed at that step, rad/s.
    speed0: f32,
    /// Steps in the interval so far.
    steps: u32,
}

impl RunawayWatch {
    /// Updates the interval for this step (`push`: the sign of the saturated current, 0 when
    /// it is not saturated towards the setpoint); `true` once it has lasted
    /// [`RUNAWAY_WINDOW_US`] and the wheel turns against its setpoint or has moved away from
    /// it since the interval began.
    #[inline]
    fn judge(&mut self, now: Instant, push: f32, setpoint: f32, speed: f32, steps: u32) -> bool {
        if push == 0.0 {
            self.since = None;
            return false;
        }
        let since = match self.since {
            Some(t) => t,
            None => {
                self.since = Some(now);
                self.speed0 = speed;
                self.steps = 0;
                now
            }
        };
        self.steps = self.steps.saturating_add(1);
        if now.micros_since(since) < RUNAWAY_WINDOW_US || self.steps <= steps {
            return false;
        }
        let against = setpoint * speed < 0.0 && speed.abs() >= RUNAWAY_MIN_SPEED;
        let away = (speed - self.speed0) * push <= -RUNAWAY_GROWTH;
        against || away
    }
}

/// A running wheel test (`WHEEL_TEST`).
#[derive(Debug, Clone, Copy)]
struct TestRun {
    wheel: u8,
    /// Wheel speed setpoint, rad/s.
    speed: f32,
    /// It ends at the first step at or after this.
    until: Instant,
    /// The wheel's angle when it began, rad.
    start_angle: f32,
    /// The current of largest magnitude commanded so far, A (signed).
    peak_current: f32,
}
/// Stuck-encoder watch of one DJI motor (see the [module documentation](self)).
#[derive(Debug, Clone, Copy, Default)]
struct StuckWatch {
    /// Rotor angle, raw counts, where the rotor was last seen to move.
    anchor: Option<u16>,
    /// A feedback frame after the one that set `anchor` stayed within the band.
    still: bool,
    /// First step of the running interval of rule 1 (still and reporting speed).
    spinning_since: Option<Instant>,
    /// First step of the running interval of rule 2 (still, driven, the others move).
    dragged_since: Option<Instant>,
}

impl StuckWatch {
    #[inline]
    fn on_angle(&mut self, raw: u16, counts_per_turn: u16) {
        match self.anchor {
            Some(a) if circular_distance(raw, a, counts_per_turn) <= ENCODER_STUCK_BAND_COUNTS => {
                self.still = true;
            }
            _ => {
                self.anchor = Some(raw);
                self.still = false;
            }
        }
    }

    /// Updates both intervals for this step; `true` once either has lasted its window.
    fn judge(&mut self, now: Instant, spinning: bool, dragged: bool) -> bool {
        let since = |flag: bool, start: Option<Instant>| flag.then(|| start.unwrap_or(now));
        self.spinning_since = since(self.still && spinning, self.spinning_since);
        self.dragged_since = since(self.still && dragged, self.dragged_since);
        self.spinning_since
            .is_some_and(|t| now.micros_since(t) >= ENCODER_STUCK_SPINNING_US)
            || self
                .dragged_since
                .is_some_and(|t| now.micros_since(t) >= ENCODER_STUCK_DRAGGED_US)
    }
}

/// A rate divider: due on the first tick and then on every `period`-th one, like
/// `steps % period == 0` for a step counter starting at 0, without a division per step.
#[derive(Debug, Clone, Copy)]
struct Every {
    period: u32,
    /// Ticks left before the next due one.
    left: u32,
}

impl Every {
    /// A divider with `period >= 1` (a 0 is treated as 1: due on every tick).
    const fn new(period: u32) -> Self {
        Self {
            period: if period == 0 { 1 } else { period },
            left: 0,
        }
    }

    /// Advances by one tick; `true` when this tick is due.
    #[inline]
    fn tick(&mut self) -> bool {
        let due = self.left == 0;
        self.left = if due { self.period - 1 } else { self.left - 1 };
        due
    }
}

/// The gyro (`IMU_YAW_RATE`), its bias estimate and the standstill that feeds it (see
/// [the module documentation](self#gyro-heading)).
#[derive(Debug, Clone, Copy, Default)]
struct Gyro {
    /// Latest accepted yaw rate, bias included, rad/s.
    rate: f32,
    /// Arrival of the latest accepted frame (never moved back).
    last_at: Option<Instant>,
    /// `seq` of the latest accepted frame; `None`: the next is accepted whatever its `seq`.
    last_seq: Option<u8>,
    /// Bias estimate, rad/s.
    bias: f32,
    /// Readings in the estimate, at most [`GYRO_BIAS_MAX_SAMPLES`].
    samples: u32,
    /// Since when the robot stands still, as of the last step; `None` while it does not.
    still_since: Option<Instant>,
    /// The heading source of the last step.
    source: HeadingSource,
}

/// Distance between two readings of a counter that wraps at `modulus`, the short way round.
#[inline]
fn circular_distance(a: u16, b: u16, modulus: u16) -> u16 {
    let d = a.abs_diff(b) % modulus;
    d.min(modulus - d)
}

/// Snapshot of the controller for logs and tests.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Snapshot {
    /// State.
    pub state: RobotState,
    /// Current fault, or the reason of the last watchdog stop.
    pub fault: Fault,
    /// Odometry pose.
    pub pose: Pose2<f32>,
    /// Body velocity measured by the wheels (forward kinematics).
    pub measured: ChassisVelocity<f32>,
    /// Body velocity being commanded after acceleration limits.
    pub commanded: ChassisVelocity<f32>,
    /// Wheel speed setpoints, rad/s.
    pub wheel_setpoints: WheelSpeeds<f32, 4>,
    /// Measured wheel speeds, rad/s.
    pub wheel_speeds: WheelSpeeds<f32, 4>,
    /// Wheel angles since the start, rad (robot-forward positive), as the odometry
    /// integrated them (f32: about 8 mrad resolution at 65,536 rad).
    pub wheel_angles: [f32; 4],
    /// Motor currents commanded, A (current-mode drives; zero otherwise).
    pub currents: [f32; 4],
    /// Bit i set when wheel i's motor is online: its last feedback was within the
    /// staleness window at the last step.
    pub motors_online: u8,
    /// Rejected frames by kind.
    pub rx_errors: RxErrorCounters,
    /// `TWIST_CMD`s not applied because their `seq` repeated the last accepted one's
    /// (saturating; see the [module documentation](self#command-watchdog)). Not rejected
    /// frames: they decode, so `rx_errors` does not count them. Repeated `IMU_YAW_RATE`
    /// frames are counted here too.
    pub repeated_seq: u32,
    /// Where the odometry's heading came from at the last step.
    pub heading_source: HeadingSource,
    /// The gyro's estimated bias, rad/s (0 until learned, and without a gyro).
    pub gyro_bias: f32,
    /// Standstill readings in the gyro's bias estimate (at most [`GYRO_BIAS_MAX_SAMPLES`]).
    pub gyro_bias_samples: u32,
    /// Steps run.
    pub steps: u64,
}

/// The drive controller. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct Controller {
    config: Config,
    /// [`Config::id`], sent in every `HEARTBEAT`.
    config_id: u16,
    kin: MecanumKinematics<f32, 4>,
    /// Per-wheel sign: -1 where the motor is mirrored.
    sign: [f32; 4],
    /// Seconds per control period.
    dt: f32,
    /// Expected feedback period of the motors, µs (staleness reference).
    feedback_period_us: u64,
    /// DJI: wheel speed (rad/s) of [`ENCODER_STUCK_MIN_ROTOR_RPM`]; `None` for drives whose
    /// encoders are not watched.
    stuck_speed: Option<f32>,
    /// The wheel of each drive id (DJI ESC id, ODrive node id); `None` for ids no wheel has.
    wheel_of: [Option<u8>; 64],
    /// DJI: the wheel whose current goes into each slot of the two command frames
    /// (ESC 1-4, ESC 5-8); `None` for an ESC that no wheel has.
    dji_slots: [[Option<u8>; 4]; 2],
    /// Odometry frames are due on this step (every `control_hz / odometry_hz` steps).
    odom_clock: Every,
    /// Status and heartbeat frames are due (every `control_hz / status_hz` steps).
    status_clock: Every,
    /// ODrive velocity setpoints are due (every `control_hz / setpoint_hz` steps).
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
    /// ODrive: state requests owed to the drives (sent on the next step).
    axis_request: Option<AxisState>,
    /// ODrive: `Clear_Errors` owed to the drives (after a reset; sent on the next step).
    clear_errors: bool,
    /// ODrive: when `Clear_Errors` was last sent.
    errors_cleared_at: Option<Instant>,
    /// ODrive: when closed loop was last requested.
    closed_loop_at: Option<Instant>,
    /// ODrive: the most a position estimate may move per µs since the previous one, motor
    /// turns ([`ODRIVE_MAX_JUMP_FACTOR`]).
    max_turns_per_us: f32,
    /// Bit i set when wheel i's motor reported within its staleness window at the last step.
    online: u8,
    /// Current drives: since when the currents' residual has been above its threshold, and
    /// for how many steps.
    fight_since: Option<(Instant, u32)>,
    /// Current drives: the fight watch rests (a strafe-and-turn, until the residual is below
    /// its threshold again).
    fight_rest: bool,
    /// The wheel test running (state `WheelTest`).
    test: Option<TestRun>,
    /// A wheel test's result, sent at the next step.
    test_result: Option<WheelTestResult>,
    /// ODrive: the one node an axis state request goes to (a wheel test); `None`: every node.
    axis_only: Option<u8>,

    motors: [Motor; 4],
    odometry: Odometry<f32>,
    measured: ChassisVelocity<f32>,
    setpoints: WheelSpeeds<f32, 4>,
    currents: [f32; 4],
    rx_errors: RxErrorCounters,
    gyro: Gyro,

    boot: Option<Instant>,
    steps: u64,
    status_requested: bool,
    status_seq: u8,
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
        let (inverted, feedback_period_us, encoder_cfg, stuck_speed) = match config.drive {
            Drive::Dji {
                model,
                gear_ratio,
                inverted,
                ..
            } => {
                let mut e = match model {
                    EscModel::C620 => EncoderConfig::dji_m3508(false),
                    EscModel::C610 => EncoderConfig::dji_m2006(false),
                };
                e.gear_ratio = gear_ratio;
                let rpm_to_wheel = core::f32::consts::TAU / 60.0 / gear_ratio;
                // DJI ESCs send feedback every millisecond.
                let stuck = ENCODER_STUCK_MIN_ROTOR_RPM * rpm_to_wheel;
                (inverted, 1_000, e, Some(stuck))
            }
            Drive::Odrive { inverted, .. } => {
                // Encoder estimates every 10 ms (ODrive default); the encoder is unused.
                (inverted, 10_000, EncoderConfig::dji_m3508(false), None)
            }
        };
        let encoder = Encoder::new(&encoder_cfg).map_err(|_| ConfigError {
            field: "drive.gear_ratio",
            value: f64::from(encoder_cfg.gear_ratio),
            expected: "a finite number > 0",
        })?;
        // Ids are validated (in range, one per wheel), so every wheel lands in the tables.
        let mut wheel_of = [None; 64];
        let mut dji_slots = [[None; 4]; 2];
        let ids = match config.drive {
            Drive::Dji { esc_ids, .. } => esc_ids,
            Drive::Odrive { node_ids, .. } => node_ids,
        };
        for (wheel, id) in (0u8..).zip(ids) {
            if let Some(w) = wheel_of.get_mut(usize::from(id)) {
                *w = Some(wheel);
            }
            if let (Drive::Dji { .. }, Some(esc)) = (config.drive, EscId::new(id)) {
                let group = usize::from(esc.group() == EscGroup::Esc5To8);
                dji_slots[group][esc.slot()] = Some(wheel);
            }
        }
        let motor = Motor {
            last_seen: None,
            encoder,
            last_pos: None,
            pending: 0.0,
            angle: 0.0,
            speed: 0.0,
            axis_error: 0,
            axis_state: None,
            integral: 0.0,
            watch: StuckWatch::default(),
            runaway: RunawayWatch::default(),
        };
        Ok(Self {
            config: *config,
            kin,
            sign: inverted.map(|i| if i { -1.0 } else { 1.0 }),
            dt: 1.0 / t.control_hz as f32,
            feedback_period_us,
            stuck_speed,
            wheel_of,
            dji_slots,
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
            axis_request: None,
            clear_errors: false,
            errors_cleared_at: None,
            closed_loop_at: None,
            max_turns_per_us: match config.drive {
                Drive::Odrive { gear_ratio, .. } => {
                    ODRIVE_MAX_JUMP_FACTOR * config.limits.max_wheel_speed * gear_ratio
                        / core::f32::consts::TAU
                        * 1e-6
                }
                Drive::Dji { .. } => 0.0,
            },
            online: 0,
            fight_since: None,
            fight_rest: false,
            test: None,
            test_result: None,
            axis_only: None,
            motors: [motor; 4],
            odometry: Odometry::new(Pose2::default()),
            measured: ChassisVelocity::default(),
            setpoints: WheelSpeeds::zero(),
            currents: [0.0; 4],
            rx_errors: RxErrorCounters::new(),
            gyro: Gyro::default(),
            boot: None,
            steps: 0,
            status_requested: false,
            status_seq: 0,
            config_id: config.id(),
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

    /// Everything a log or a test wants to see.
    #[must_use]
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            state: self.state,
            fault: self.fault,
            pose: self.odometry.pose(),
            measured: self.measured,
            commanded: self.commanded,
            wheel_setpoints: self.setpoints,
            wheel_speeds: WheelSpeeds(self.motors.map(|m| m.speed)),
            wheel_angles: self.motors.map(|m| m.angle),
            currents: self.currents,
            motors_online: self.online,
            rx_errors: self.rx_errors,
            repeated_seq: self.repeated_seq,
            heading_source: self.gyro.source,
            gyro_bias: self.gyro.bias,
            gyro_bias_samples: self.gyro.samples,
            steps: self.steps,
        }
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
        } else {
            match self.config.drive {
                Drive::Dji { model, .. } => self.on_dji(now, frame, model),
                Drive::Odrive { .. } => self.on_odrive(now, frame),
            }
        }
    }

    #[inline]
    fn on_command(&mut self, now: Instant, cmd: Command) -> Result<(), DecodeError> {
        match cmd {
            Command::Estop => {
                self.end_test(TestOutcome::Stopped);
                self.state = RobotState::Estop;
                self.halt();
            }
            Command::Twist(t) => {
                let v = ChassisVelocity::new(t.vx, t.vy, t.wz);
                // `target` only ever holds zero or a twist that passed `check_twist` under
                // the same (fixed) limits, so a twist equal to it passes too: a stream that
                // holds one setpoint skips the check.
                let v = if v == self.target {
                    v
                } else {
                    self.check_twist(t)?
                };
                if self.last_seq == Some(t.seq) {
                    // The same frame again (a stuck host, adapter or gateway): not a command.
                    self.repeated_seq = self.repeated_seq.saturating_add(1);
                } else if self.state == RobotState::Enabled && !self.stopping {
                    self.target = v;
                    self.last_seq = Some(t.seq);
                    // A frame stamped before the last one does not move the mark back.
                    self.last_command = Some(self.last_command.map_or(now, |t| t.max(now)));
                }
            }
            Command::Mode(ModeRequest::Enable) => {
                if self.state == RobotState::Disabled {
                    self.state = RobotState::Enabled;
                    self.fault = Fault::None;
                    self.halt();
                    // A new session: its first twist is accepted whatever its seq.
                    self.last_seq = None;
                    self.request_closed_loop(now, None);
                }
            }
            Command::Mode(ModeRequest::Disable) => {
                if matches!(self.state, RobotState::Enabled | RobotState::WheelTest) {
                    self.end_test(TestOutcome::Stopped);
                    self.state = RobotState::Disabled;
                    self.halt();
                }
            }
            Command::Mode(ModeRequest::Reset) => {
                if matches!(self.state, RobotState::Fault | RobotState::Estop) {
                    self.state = RobotState::Disabled;
                    self.fault = Fault::None;
                    self.halt();
                    self.last_seq = None;
                    // An ODrive reports its errors until told to clear them.
                    if matches!(self.config.drive, Drive::Odrive { .. }) {
                        self.clear_errors = true;
                        // Error bits received from now until the clear goes out predate it.
                        self.errors_cleared_at = Some(now);
                        for m in &mut self.motors {
                            m.axis_error = 0;
                        }
                    }
                }
            }
            Command::StatusRequest => self.status_requested = true,
            Command::ImuYawRate(g) => self.on_gyro(now, g),
            Command::WheelTest(t) => self.start_test(now, t),
        }
        Ok(())
    }

    /// Starts a wheel test if the robot is disabled; otherwise refuses it (a
    /// `WHEEL_TEST_RESULT` `REFUSED` at the next step).
    fn start_test(&mut self, now: Instant, t: WheelTest) {
        // The codec refuses wheels above 3; the core does not index past them either way.
        let wheel = t.wheel.min(3);
        if self.state != RobotState::Disabled {
            self.test_result = Some(WheelTestResult {
                wheel: t.wheel,
                outcome: TestOutcome::Refused,
                angle: 0.0,
                peak_current: 0.0,
            });
            return;
        }
        self.state = RobotState::WheelTest;
        self.fault = Fault::None;
        self.halt();
        let max = self.config.limits.max_wheel_speed;
        self.test = Some(TestRun {
            wheel,
            speed: symmetric_limit(t.speed, max),
            until: Instant::from_micros(
                now.as_micros()
                    .saturating_add(u64::from(t.duration_ms) * 1000),
            ),
            start_angle: self.motors[usize::from(wheel)].angle,
            peak_current: 0.0,
        });
        // ODrive: closed loop on the tested axis only; the others stay idle.
        self.request_closed_loop(now, Some(wheel));
    }

    /// ODrive: asks for closed loop (with velocity mode) at the next step, on every axis
    /// (`only` `None`: an enable) or on wheel `only`'s alone (a wheel test). Axis states
    /// reported from now until the request goes out predate it. Nothing for current drives.
    fn request_closed_loop(&mut self, now: Instant, only: Option<u8>) {
        self.axis_request = self.odrive_axis(AxisState::ClosedLoopControl);
        self.axis_only = only;
        self.closed_loop_at = Some(now);
        for m in &mut self.motors {
            m.axis_state = None;
        }
    }

    /// The current limit in force, A: `limits.max_current` while enabled, a quarter of it in
    /// a wheel test, none otherwise (no wheel is driven).
    fn current_limit(&self) -> f32 {
        let max = self.config.limits.max_current;
        match self.state {
            RobotState::Enabled => max,
            RobotState::WheelTest => WHEEL_TEST_CURRENT_FRACTION * max,
            _ => 0.0,
        }
    }

    /// Ends the running wheel test, if any, with `outcome` (its result goes out at the next
    /// step). The caller sets the state.
    fn end_test(&mut self, outcome: TestOutcome) {
        if let Some(t) = self.test.take() {
            let wheel = usize::from(t.wheel);
            self.test_result = Some(WheelTestResult {
                wheel: t.wheel,
                outcome,
                angle: self.motors[wheel].angle + self.motors[wheel].pending - t.start_angle,
                peak_current: t.peak_current,
            });
        }
    }

    /// Takes a valid `IMU_YAW_RATE`: the gyro's latest rate, and a bias sample while the
    /// robot has stood still long enough (since before the last step, and still now).
    fn on_gyro(&mut self, now: Instant, g: ImuYawRate) {
        // Still standing still now: no twist accepted and no wheel turning since the step.
        let still = self.standing_still();
        let o = &self.config.odometry;
        let gyro = &mut self.gyro;
        if gyro.last_seq == Some(g.seq) {
            // The same frame again (a stuck node or gateway): not a sign of life.
            self.repeated_seq = self.repeated_seq.saturating_add(1);
            return;
        }
        gyro.last_seq = Some(g.seq);
        gyro.rate = g.yaw_rate;
        // A frame stamped before the last one does not move the mark back.
        gyro.last_at = Some(gyro.last_at.map_or(now, |t| t.max(now)));
        let settle_us = u64::from(o.gyro_standstill_ms) * 1000;
        let settled = still
            && gyro
                .still_since
                .is_some_and(|t| now.micros_since(t) >= settle_us);
        if settled && o.gyro_bias_estimation && o.heading_source == HeadingMode::Gyro {
            gyro.samples = (gyro.samples + 1).min(GYRO_BIAS_MAX_SAMPLES);
            gyro.bias += (g.yaw_rate - gyro.bias) / gyro.samples as f32;
        }
    }

    /// Rejects twists beyond the configured limits (the decoder already rejected the rest).
    #[inline]
    fn check_twist(&self, t: TwistCmd) -> Result<ChassisVelocity<f32>, DecodeError> {
        let l = &self.config.limits;
        let speed = (t.vx * t.vx + t.vy * t.vy).sqrt_libm();
        for (field, v) in [("vx", t.vx), ("vy", t.vy), ("wz", t.wz)] {
            if !v.is_finite() {
                return Err(DecodeError::NonFinite {
                    field,
                    bits: v.to_bits(),
                });
            }
        }
        if speed > l.max_linear_speed {
            return Err(DecodeError::OutOfRange {
                field: "vx,vy",
                value: (speed * 1000.0) as i64,
            });
        }
        if t.wz.abs() > l.max_angular_speed {
            return Err(DecodeError::OutOfRange {
                field: "wz",
                value: (t.wz * 1000.0) as i64,
            });
        }
        Ok(ChassisVelocity::new(t.vx, t.vy, t.wz))
    }

    /// Drops every motion target and the watchdog; the motors get zero on the next step.
    fn halt(&mut self) {
        self.target = ChassisVelocity::default();
        self.commanded = ChassisVelocity::default();
        self.last_command = None;
        self.stopping = false;
        for m in &mut self.motors {
            m.integral = 0.0;
        }
        if self.state != RobotState::Enabled {
            self.axis_request = self.odrive_axis(AxisState::Idle);
            self.axis_only = None;
        }
    }

    fn odrive_axis(&self, s: AxisState) -> Option<AxisState> {
        matches!(self.config.drive, Drive::Odrive { .. }).then_some(s)
    }

    #[inline]
    fn on_dji<F: Frame>(
        &mut self,
        now: Instant,
        frame: &F,
        model: EscModel,
    ) -> Result<(), DecodeError> {
        let Drive::Dji { gear_ratio, .. } = self.config.drive else {
            return Ok(());
        };
        let fb = dji::Feedback::decode(frame, model)?;
        let Some((sign, m)) = self.wheel(fb.esc.get()) else {
            return Err(unknown(frame));
        };
        // The decoder has checked the angle range, so the encoder accepts it.
        let counts = m.encoder.update(u32::from(fb.rotor_angle)).unwrap_or(0);
        m.watch.on_angle(fb.rotor_angle, dji::layout::ANGLE_COUNTS);
        m.pending += sign * m.encoder.counts_to_radians(counts);
        m.speed = sign * fb.rotor_speed_rad_s() / gear_ratio;
        m.last_seen = Some(m.last_seen.map_or(now, |t| t.max(now)));
        Ok(())
    }

    fn on_odrive<F: Frame>(&mut self, now: Instant, frame: &F) -> Result<(), DecodeError> {
        let Drive::Odrive { gear_ratio, .. } = self.config.drive else {
            return Ok(());
        };
        if odrive::is_request(frame) {
            // Another host polling a drive (odrivetool, a logger): not feedback, not an error.
            return Ok(());
        }
        let fb = odrive::Feedback::decode(frame)?;
        // Error bits from before the last `Clear_Errors` (see ODRIVE_CLEAR_GRACE_US).
        let errors_stale = self
            .errors_cleared_at
            .is_some_and(|t| now.micros_since(t) <= ODRIVE_CLEAR_GRACE_US);
        let state_stale = self
            .closed_loop_at
            .is_some_and(|t| now.micros_since(t) <= ODRIVE_STATE_GRACE_US);
        let (max_turns_per_us, estimate_period_us) =
            (self.max_turns_per_us, self.feedback_period_us);
        let Some((sign, m)) = self.wheel(fb.node.get()) else {
            return Err(unknown(frame));
        };
        match fb.msg {
            odrive::Feedback::Heartbeat(hb) => {
                m.axis_error = if errors_stale { 0 } else { hb.axis_error };
                if !state_stale {
                    m.axis_state = Some(hb.axis_state);
                }
            }
            odrive::Feedback::EncoderEstimates { pos, vel } => {
                let turns_to_rad = core::f32::consts::TAU / gear_ratio;
                let jump = m.last_pos.zip(m.last_seen).map(|(last, seen)| {
                    let elapsed_us = now.micros_since(seen).saturating_add(estimate_period_us);
                    (pos - last, max_turns_per_us * elapsed_us as f32)
                });
                m.last_pos = Some(pos);
                m.speed = sign * vel * turns_to_rad;
                m.last_seen = Some(m.last_seen.map_or(now, |t| t.max(now)));
                if let Some((delta, max)) = jump {
                    // An infinite difference (finite estimates far apart) fails too.
                    if !delta.is_finite() || delta.abs() > max {
                        return Err(DecodeError::OutOfRange {
                            field: "pos_estimate",
                            value: delta as i64,
                        });
                    }
                    m.pending += sign * delta * turns_to_rad;
                }
            }
            odrive::Feedback::Error { active_errors, .. } => {
                if !errors_stale {
                    m.axis_error |= active_errors;
                }
            }
        }
        Ok(())
    }

    /// The mounting sign and the motor state of the wheel driven by drive id `id` (DJI ESC
    /// id, ODrive node id); `None` if no wheel has that id.
    #[inline]
    fn wheel(&mut self, id: u8) -> Option<(f32, &mut Motor)> {
        let wheel = usize::from(self.wheel_of.get(usize::from(id)).copied().flatten()?);
        Some((*self.sign.get(wheel)?, self.motors.get_mut(wheel)?))
    }

    /// Runs one control period at time `now` and returns the frames to send.
    ///
    /// Call it once per period (`1 / timing.control_hz`) with a monotonic `now`; frames
    /// received since the previous call must have been passed to [`on_frame`](Self::on_frame).
    /// A loop that keeps its outbox calls [`step_into`](Self::step_into) instead: the outbox
    /// is 26 frames, and moving it out of a call that is not inlined copies all of it.
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
        let boot = *self.boot.get_or_insert(now);
        // Sent by this step (emit_odrive).
        if self.clear_errors {
            self.errors_cleared_at = Some(now);
        }
        if self.axis_request == Some(AxisState::ClosedLoopControl) {
            self.closed_loop_at = Some(now);
        }
        self.check_motors(now, boot);
        self.run_watchdog(now);
        if let Some(t) = self.test
            && now >= t.until
        {
            self.end_test(TestOutcome::Done);
            self.state = RobotState::Disabled;
            self.halt();
        }
        self.ramp();
        self.update_gyro(now);
        self.integrate_odometry();
        // One tick of every rate divider per step, whether or not its frames go out.
        let odom_due = self.odom_clock.tick();
        let status_due = self.status_clock.tick();
        let setpoint_due = self.setpoint_clock.tick();

        let enabled = self.state == RobotState::Enabled;
        let test = self.test.filter(|_| self.state == RobotState::WheelTest);
        // The wheels driven (bit i: wheel i).
        let mask = if enabled {
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
        match self.config.drive {
            Drive::Dji { model, .. } => self.emit_dji(out, model, mask, self.current_limit()),
            Drive::Odrive {
                node_ids,
                gear_ratio,
                vel_ramp,
                ..
            } => self.emit_odrive(
                out,
                node_ids,
                gear_ratio,
                vel_ramp,
                mask != 0 && setpoint_due,
            ),
        }
        if let Some(t) = &mut self.test {
            let i = self.currents[usize::from(t.wheel)];
            if i.abs() > t.peak_current.abs() {
                t.peak_current = i;
            }
        }
        self.emit_telemetry(out, now, boot, odom_due, status_due);
        self.steps += 1;
    }

    /// Disables the drive and returns the frames that leave the motors safe: zero current for
    /// DJI ESCs; zero velocity and the idle state for ODrive axes. For a runner that is about
    /// to exit (SIGINT/SIGTERM): send these, then stop.
    pub fn shutdown(&mut self) -> Outbox {
        if matches!(self.state, RobotState::Enabled | RobotState::WheelTest) {
            self.end_test(TestOutcome::Stopped);
            self.state = RobotState::Disabled;
        }
        self.halt();
        self.axis_request = self.odrive_axis(AxisState::Idle);
        self.setpoints = WheelSpeeds::zero();
        let mut out = Outbox::new();
        match self.config.drive {
            Drive::Dji { model, .. } => self.emit_dji(&mut out, model, 0, 0.0),
            Drive::Odrive {
                node_ids,
                gear_ratio,
                vel_ramp,
                ..
            } => self.emit_odrive(&mut out, node_ids, gear_ratio, vel_ramp, false),
        }
        out
    }

    fn check_motors(&mut self, now: Instant, boot: Instant) {
        let t = &self.config.timing;
        let stale_us = self.feedback_period_us * u64::from(t.stale_periods);
        let boot_us = u64::from(t.boot_timeout_ms) * 1000;
        // One pass: each motor's freshness (online bit, staleness) and the first fault found
        // in wheel order.
        let mut online = 0u8;
        let mut fault = Fault::None;
        let enabled = self.state == RobotState::Enabled;
        for (i, m) in self.motors.iter().enumerate() {
            let fresh = m.last_seen.is_some_and(|t| now.micros_since(t) <= stale_us);
            online |= u8::from(fresh) << i;
            if fault != Fault::None {
                continue;
            }
            // ODrive: an enabled robot's axes must be in closed loop (once they could be).
            let left_closed_loop = enabled
                && m.axis_state
                    .is_some_and(|s| s != AxisState::ClosedLoopControl);
            fault = match m.last_seen {
                None if now.micros_since(boot) > boot_us => Fault::MotorMissing,
                Some(_) if !fresh => Fault::MotorStale,
                _ if m.axis_error != 0 || left_closed_loop => Fault::DriveError,
                _ => Fault::None,
            };
        }
        self.online = online;
        if self.watch_encoders(now) && fault == Fault::None {
            fault = Fault::EncoderStuck;
        }
        if self.watch_runaway(now) && fault == Fault::None {
            fault = Fault::WheelRunaway;
        }
        if self.watch_fight(now) && fault == Fault::None {
            fault = Fault::WheelFight;
        }
        if fault != Fault::None
            && matches!(
                self.state,
                RobotState::Disabled | RobotState::Enabled | RobotState::WheelTest
            )
        {
            self.end_test(TestOutcome::Fault);
            self.state = RobotState::Fault;
            self.fault = fault;
            self.halt();
        }
    }

    /// The wheel-fight watch for this step (see the [module documentation](self)); `true`
    /// once the currents of the previous step and those before it have had a residual above
    /// the threshold for [`FIGHT_WINDOW_US`].
    fn watch_fight(&mut self, now: Instant) -> bool {
        let c = self.commanded;
        let combined = c.vy.abs() >= FIGHT_COMBINED_MIN && c.wz.abs() >= FIGHT_COMBINED_MIN;
        let watching =
            matches!(self.config.drive, Drive::Dji { .. }) && self.state == RobotState::Enabled;
        let threshold = FIGHT_CURRENT_FRACTION * self.config.limits.max_current;
        let above = watching && {
            let (_, residual) = self.kin.forward_with_residual(&WheelSpeeds(self.currents));
            residual.rms() >= threshold
        };
        // A strafe-and-turn rests the watch; the loops' integrators hold its pushing for a
        // while after it, so the watch wakes only once the residual has been below the
        // threshold again.
        self.fight_rest = combined || (self.fight_rest && above);
        let fighting = above && !self.fight_rest;
        if !fighting {
            self.fight_since = None;
            return false;
        }
        let steps = self.window_steps(FIGHT_WINDOW_US);
        let (since, n) = self.fight_since.get_or_insert((now, 0));
        *n = n.saturating_add(1);
        now.micros_since(*since) >= FIGHT_WINDOW_US && *n > steps
    }

    /// How many control steps a watch window of `window_us` spans: a watch fires only after
    /// its window has passed *and* the core has seen that many steps of it, so a loop that
    /// stalls (a late runner, an overrun) does not judge a wheel on one late look.
    fn window_steps(&self, window_us: u64) -> u32 {
        u32::try_from(window_us / self.period_micros().max(1)).unwrap_or(u32::MAX)
    }

    /// Runs every current-driven wheel's runaway watch for this step; `true` if one has
    /// fired. The currents and setpoints are those of the previous step (the ones the motors
    /// are acting on), the speeds the latest measured.
    fn watch_runaway(&mut self, now: Instant) -> bool {
        let limit = match self.config.drive {
            Drive::Dji { .. } => self.current_limit(),
            Drive::Odrive { .. } => 0.0,
        };
        let threshold = RUNAWAY_SATURATION * limit;
        let steps = self.window_steps(RUNAWAY_WINDOW_US);
        let mut runaway = false;
        for (i, m) in self.motors.iter_mut().enumerate() {
            let (current, setpoint) = (self.currents[i], self.setpoints.0[i]);
            // Saturated, and pushing towards the setpoint.
            let saturated =
                limit > 0.0 && current.abs() >= threshold && current * (setpoint - m.speed) > 0.0;
            let push = if saturated { current.signum() } else { 0.0 };
            runaway |= m.runaway.judge(now, push, setpoint, m.speed, steps);
        }
        runaway
    }

    /// Runs every DJI motor's stuck-encoder watch for this step; `true` if one has fired.
    /// The currents are those of the previous step (the ones the motors are acting on).
    fn watch_encoders(&mut self, now: Instant) -> bool {
        let Some(min_speed) = self.stuck_speed else {
            return false;
        };
        if !self.motors.iter().any(|m| m.watch.still) {
            // The common case: every rotor moved. No interval runs (what `judge` would
            // conclude for each), and the least-squares fit is not needed.
            for m in &mut self.motors {
                m.watch.spinning_since = None;
                m.watch.dragged_since = None;
            }
            return false;
        }
        let min_current = ENCODER_STUCK_MIN_CURRENT * self.config.limits.max_current;
        let driven: [bool; 4] = core::array::from_fn(|i| {
            self.motors[i].watch.still && self.currents[i].abs() >= min_current
        });
        // The least-squares fit is only worth its cost when some still wheel is driven.
        let implied = if driven.contains(&true) {
            self.kin
                .implied_by_others(&WheelSpeeds(self.motors.map(|m| m.speed)))
        } else {
            [None; 4]
        };
        let mut stuck = false;
        for (i, m) in self.motors.iter_mut().enumerate() {
            let spinning = m.speed.abs() >= min_speed;
            let dragged = driven[i] && implied[i].is_some_and(|w| w.abs() >= min_speed);
            stuck |= m.watch.judge(now, spinning, dragged);
        }
        stuck
    }

    fn run_watchdog(&mut self, now: Instant) {
        if self.state != RobotState::Enabled || self.stopping {
            return;
        }
        let timeout_us = u64::from(self.config.timing.command_timeout_ms) * 1000;
        if let Some(last) = self.last_command
            && now.micros_since(last) > timeout_us
        {
            self.stopping = true;
            self.fault = Fault::Watchdog;
            self.target = ChassisVelocity::default();
        }
    }

    /// Moves the commanded twist towards the target within the acceleration limits (the stop
    /// deceleration while the watchdog stop runs), and completes a watchdog stop.
    fn ramp(&mut self) {
        if self.state != RobotState::Enabled {
            self.commanded = ChassisVelocity::default();
            return;
        }
        let l: &Limits = &self.config.limits;
        let (lin, ang) = if self.stopping {
            (l.stop_linear_decel, l.stop_angular_decel)
        } else {
            (l.max_linear_accel, l.max_angular_accel)
        };
        let (dvx, dvy) = (
            self.target.vx - self.commanded.vx,
            self.target.vy - self.commanded.vy,
        );
        // At the target already (the common case): the same zero without the square root.
        let dv = if dvx == 0.0 && dvy == 0.0 {
            0.0
        } else {
            (dvx * dvx + dvy * dvy).sqrt_libm()
        };
        let max_dv = lin * self.dt;
        if dv <= max_dv {
            self.commanded.vx = self.target.vx;
            self.commanded.vy = self.target.vy;
        } else {
            let k = max_dv / dv;
            self.commanded.vx += dvx * k;
            self.commanded.vy += dvy * k;
        }
        let dw = self.target.wz - self.commanded.wz;
        let max_dw = ang * self.dt;
        self.commanded.wz = if dw.abs() <= max_dw {
            self.target.wz
        } else {
            self.commanded.wz + max_dw.copysign(dw)
        };
        if self.stopping && self.commanded == ChassisVelocity::default() {
            // Stop complete: disable, keep `Watchdog` as the reason until the next enable.
            self.state = RobotState::Disabled;
            self.stopping = false;
            self.last_command = None;
            self.axis_request = self.odrive_axis(AxisState::Idle);
        }
    }

    /// With a gyro configured: whether it is alive (the heading source of this step), and
    /// whether the robot stands still (for the bias estimate).
    fn update_gyro(&mut self, now: Instant) {
        let o = &self.config.odometry;
        if o.heading_source == HeadingMode::Wheels {
            return;
        }
        let timeout_us = u64::from(o.gyro_timeout_ms) * 1000;
        let alive = self
            .gyro
            .last_at
            .is_some_and(|t| now.micros_since(t) <= timeout_us);
        // `last_seq` is kept through a silence: a node stuck on one frame stays silent. A
        // restarted node loses at most its first frame (if its `seq` happens to repeat).
        self.gyro.source = if alive {
            HeadingSource::Gyro
        } else {
            HeadingSource::WheelsGyroSilent
        };
        self.gyro.still_since = if self.online == 0b1111 && self.standing_still() {
            Some(self.gyro.still_since.unwrap_or(now))
        } else {
            None
        };
    }

    /// No motion commanded (not enabled, or a zero target and a zero commanded twist) and
    /// every wheel's latest speed below [`STANDSTILL_WHEEL_SPEED`].
    fn standing_still(&self) -> bool {
        let zero = ChassisVelocity::default();
        let commanded =
            self.state == RobotState::Enabled && (self.target != zero || self.commanded != zero);
        !commanded
            && self
                .motors
                .iter()
                .all(|m| m.speed.abs() <= STANDSTILL_WHEEL_SPEED)
    }

    fn integrate_odometry(&mut self) {
        let deltas = WheelDeltas(self.motors.map(|m| m.pending));
        for m in &mut self.motors {
            m.angle += m.pending;
            m.pending = 0.0;
        }
        self.measured = self.kin.forward(&WheelSpeeds(self.motors.map(|m| m.speed)));
        if self.gyro.source == HeadingSource::Gyro {
            // The wheels' translation, the gyro's rotation.
            let rate = self.gyro.rate - self.gyro.bias;
            let mut step = self.kin.displacement(&deltas);
            step.dtheta = rate * self.dt;
            self.odometry.apply(step);
            self.measured.wz = rate;
        } else {
            self.odometry.update(&self.kin, &deltas);
        }
    }

    /// DJI: the velocity PI of the wheels in `mask` (bit i: wheel i; the others get no
    /// current) with the current limit `max`, and the command frames.
    fn emit_dji(&mut self, out: &mut Outbox, model: EscModel, mask: u8, max: f32) {
        let mut integral = self.motors.map(|m| m.integral);
        self.currents = if mask != 0 {
            let speed = self.motors.map(|m| m.speed);
            let g = &self.config.gains;
            let mut c = pi_step(&mut integral, self.setpoints.0, speed, g, max, self.dt);
            if mask != 0b1111 {
                for i in 0..4 {
                    if mask & (1 << i) == 0 {
                        c[i] = 0.0;
                        integral[i] = 0.0;
                    }
                }
            }
            c
        } else {
            integral = [0.0; 4];
            [0.0; 4]
        };
        for (m, i) in self.motors.iter_mut().zip(integral) {
            m.integral = i;
        }
        // Raw current of each wheel's ESC.
        let mut raw = [0i16; 4];
        for (wheel, r) in raw.iter_mut().enumerate() {
            *r = model.amps_to_raw(self.sign[wheel] * self.currents[wheel]);
        }
        for (group, slots) in [EscGroup::Esc1To4, EscGroup::Esc5To8]
            .into_iter()
            .zip(self.dji_slots)
        {
            if slots.iter().any(Option::is_some) {
                let cmd = CurrentCommand {
                    model,
                    group,
                    raw: slots.map(|w| {
                        w.and_then(|w| raw.get(usize::from(w)).copied())
                            .unwrap_or(0)
                    }),
                };
                push(out, cmd.to_can_frame());
            }
        }
    }

    fn emit_odrive(
        &mut self,
        out: &mut Outbox,
        node_ids: [u8; 4],
        gear_ratio: f32,
        vel_ramp: bool,
        setpoints_due: bool,
    ) {
        self.currents = [0.0; 4];
        let nodes = node_ids.map(NodeId::new);
        if core::mem::take(&mut self.clear_errors) {
            let clear = odrive::Command::ClearErrors { identify: false };
            for node in nodes.iter().flatten() {
                push(out, clear.to_can_frame(*node));
            }
        }
        if let Some(state) = self.axis_request.take() {
            let only = self.axis_only.map(usize::from);
            let addressed = nodes
                .iter()
                .enumerate()
                .filter(|(wheel, _)| only.is_none_or(|w| w == *wheel))
                .filter_map(|(_, node)| node.as_ref());
            for node in addressed {
                if state == AxisState::ClosedLoopControl {
                    let mode = odrive::Command::SetControllerMode {
                        control_mode: ControlMode::VelocityControl,
                        input_mode: if vel_ramp {
                            InputMode::VelRamp
                        } else {
                            InputMode::Passthrough
                        },
                    };
                    push(out, mode.to_can_frame(*node));
                }
                push(
                    out,
                    odrive::Command::SetInputVel {
                        vel: 0.0,
                        torque_ff: 0.0,
                    }
                    .to_can_frame(*node),
                );
                push(
                    out,
                    odrive::Command::SetAxisState(state).to_can_frame(*node),
                );
            }
        }
        if setpoints_due {
            let rad_to_turns = gear_ratio / core::f32::consts::TAU;
            for (wheel, node) in nodes.iter().enumerate() {
                if let Some(node) = node {
                    let vel = self.sign[wheel] * self.setpoints.0[wheel] * rad_to_turns;
                    let cmd = odrive::Command::SetInputVel {
                        vel,
                        torque_ff: 0.0,
                    };
                    push(out, cmd.to_can_frame(*node));
                }
            }
        }
    }

    fn emit_telemetry(
        &mut self,
        out: &mut Outbox,
        now: Instant,
        boot: Instant,
        odom_due: bool,
        status_due: bool,
    ) {
        if odom_due {
            let p = self.odometry.pose();
            push(
                out,
                robot::Telemetry::OdomPosition(robot::OdomPosition { x: p.x, y: p.y })
                    .to_can_frame(),
            );
            push(
                out,
                robot::Telemetry::OdomVelocity(robot::OdomVelocity {
                    heading: p.heading,
                    vx: self.measured.vx,
                    vy: self.measured.vy,
                    wz: self.measured.wz,
                })
                .to_can_frame(),
            );
        }
        if status_due || self.status_requested {
            self.status_requested = false;
            let e = &self.rx_errors;
            let sat = |n: u32| u16::try_from(n).unwrap_or(u16::MAX);
            push(
                out,
                robot::Telemetry::Status(robot::Status {
                    state: self.state,
                    fault: self.fault,
                    rx_errors: sat(e.total().saturating_sub(e.unknown_id)),
                    unknown_ids: sat(e.unknown_id),
                    motors_online: self.online,
                    heading_source: self.gyro.source,
                    seq: self.status_seq,
                })
                .to_can_frame(),
            );
            self.status_seq = self.status_seq.wrapping_add(1);
            // Right after STATUS, which has no room left for them.
            push(
                out,
                robot::Telemetry::StatusCounters(robot::StatusCounters {
                    repeated_seq: sat(self.repeated_seq),
                    wrong_dlc: sat(e.wrong_dlc),
                    out_of_range: sat(e.out_of_range),
                    non_finite: sat(e.non_finite),
                })
                .to_can_frame(),
            );
        }
        if let Some(r) = self.test_result.take() {
            push(out, robot::Telemetry::WheelTestResult(r).to_can_frame());
        }
        if status_due {
            let uptime_ms = now.micros_since(boot) / 1000;
            push(
                out,
                robot::Telemetry::Heartbeat(robot::Heartbeat {
                    // Wraps after 49.7 days, as the DBC says (a host checks that it advances).
                    uptime_ms: uptime_ms as u32,
                    state: self.state,
                    protocol_version: robot::PROTOCOL_VERSION,
                    config_id: self.config_id,
                })
                .to_can_frame(),
            );
        }
    }
}

/// One step of the four wheels' velocity PI with conditional integration (anti-windup): a
/// wheel's integrator only moves when its output is not saturated, or when the error would
/// pull it back out of saturation. Returns the currents; the wheels are independent (written
/// as one loop so that the compiler can run them side by side).
fn pi_step(
    integral: &mut [f32; 4],
    setpoint: [f32; 4],
    speed: [f32; 4],
    g: &Gains,
    max: f32,
    dt: f32,
) -> [f32; 4] {
    let mut current = [0.0; 4];
    for i in 0..4 {
        let error = setpoint[i] - speed[i];
        let proportional = g.kv * setpoint[i] + g.kp * error;
        let increment = g.ki * error * dt;
        let unclamped = proportional + integral[i] + increment;
        // `&` and a select rather than `&&` and a branch: the same values, and no branch
        // per wheel.
        let saturated_same_way = (unclamped.abs() > max) & ((unclamped > 0.0) == (error > 0.0));
        let moved = symmetric_limit(integral[i] + increment, max);
        integral[i] = if saturated_same_way {
            integral[i]
        } else {
            moved
        };
        current[i] = symmetric_limit(proportional + integral[i], max);
    }
    current
}

/// `x` limited to `[-max, max]`. Not `f32::clamp`: its check of the bounds formats floats in
/// its panic message, which costs the MCU image about 19 KB of formatting code.
fn symmetric_limit(x: f32, max: f32) -> f32 {
    x.max(-max).min(max)
}

fn push(out: &mut Outbox, frame: CanFrame) {
    // OUTBOX_CAPACITY covers the largest step; a full outbox drops the frame rather than panic.
    let _ = out.push(frame);
}

fn unknown<F: Frame>(frame: &F) -> DecodeError {
    DecodeError::UnknownId { id: frame.id() }
}
