//! The simulated plant: four motor drives on a mecanum chassis, in simulated time.
//!
//! The plant is sans-IO and deterministic: no clock, no randomness, `f64` throughout. It
//! advances only when told to ([`Plant::step`]), and two plants given the same calls produce
//! the same bits. It does not speak CAN: each drive model takes typed commands (a current
//! setpoint, an ODrive command) and produces typed feedback; the adapter that owns the
//! simulated bus turns them into frames with the firmware crate's codecs
//! ([`DjiFeedback::to_firmware`], [`OdriveFeedback::to_firmware`]).
//!
//! - [`chassis`]: the rigid body on mecanum rollers, friction-limited slip, the physics of
//!   slower strafing (as FTC mecanum tutorials report) and the contact-point ripple (Gfrerrer 2008,
//!   eq. 11).
//! - [`dji`]: C620 ESC + M3508 gear motor (current in, 1 kHz feedback with a 13-bit rotor
//!   angle).
//! - [`odrive`]: an ODrive axis (velocity loop, watchdog, 10 ms encoder estimates, 100 ms
//!   heartbeat).
//! - [`cia402`]: a CiA 402 drive's hub-motor axis (the CANopen node around it is the
//!   adapter's, `crate::nodes::drives::canopen`).
//!
//! Wheel order is FL, FR, RL, RR ([`Wheel`]). How the drives' mounting signs and gear ratios
//! couple them to the wheels, when feedback is due ([`Plant::take_feedback`]) and what the
//! faults ([`Plant::set_faults_at`]) do: `docs/simulator.md`, section "Plant".

pub mod chassis;
pub mod cia402;
pub mod dji;
pub mod error;
pub mod odrive;
mod spec;

use kinematics::{ChassisVelocity, Pose2};

pub use chassis::{Chassis, ChassisParams, ChassisState, Contact, Ripple, WheelInput};
pub use cia402::{Cia402Axis, Cia402Params};
pub use dji::{C620Params, DjiDrive, DjiFeedback, M3508Params};
pub use error::ParamError;
pub use odrive::{OdriveAxis, OdriveFeedback, OdriveParams};
pub use spec::PlantSpec;

/// Number of wheels.
pub const WHEELS: usize = 4;

/// A wheel, in the project's order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Wheel {
    /// Front left (index 0).
    FrontLeft = 0,
    /// Front right (index 1).
    FrontRight = 1,
    /// Rear left (index 2).
    RearLeft = 2,
    /// Rear right (index 3).
    RearRight = 3,
}

impl Wheel {
    /// All wheels in order FL, FR, RL, RR.
    pub const ALL: [Self; WHEELS] = [
        Self::FrontLeft,
        Self::FrontRight,
        Self::RearLeft,
        Self::RearRight,
    ];

    /// The index in every wheel array.
    #[must_use]
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The wheel at `index`, if any.
    #[must_use]
    pub const fn from_index(index: usize) -> Option<Self> {
        match index {
            0 => Some(Self::FrontLeft),
            1 => Some(Self::FrontRight),
            2 => Some(Self::RearLeft),
            3 => Some(Self::RearRight),
            _ => None,
        }
    }
}

/// A shaft's angle and speed.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Shaft {
    /// Angle, rad, not wrapped.
    pub angle: f64,
    /// Speed, rad/s.
    pub speed: f64,
}

/// A motor drive model: what the plant needs from a C620 + M3508, an ODrive axis, ….
///
/// Commands are the concrete type's own methods; this trait is the plant's side.
pub trait Drive {
    /// One feedback message.
    type Feedback: Clone + core::fmt::Debug + PartialEq;

    /// Motor turns per wheel turn.
    fn gear_ratio(&self) -> f64;

    /// Rotor inertia seen at the wheel (`J_rotor · G²`), kg·m².
    fn reflected_inertia(&self) -> f64;

    /// Advances the drive's internal state by `h` seconds with its motor shaft at `motor`
    /// (motor side, the motor's own sign); returns the torque at the wheel side of the gear,
    /// N·m, in the motor's positive sense.
    fn advance(&mut self, h: f64, motor: Shaft) -> f64;

    /// The time (ns) at which the next feedback is due.
    fn next_feedback_ns(&self) -> u64;

    /// Appends the feedback due at `now_ns` (nothing if none is due), reporting `motor`, and
    /// moves the schedule past `now_ns`.
    fn emit_feedback(&mut self, now_ns: u64, motor: Shaft, out: &mut Vec<Self::Feedback>);
}

/// Feedback from one wheel's drive, stamped with the simulated time it is due.
#[derive(Debug, Clone, PartialEq)]
pub struct Timed<F> {
    /// Simulated time, ns.
    pub time_ns: u64,
    /// The wheel whose drive sent it.
    pub wheel: Wheel,
    /// The message.
    pub feedback: F,
}

#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Faults {
    stuck: Option<Shaft>,
    offline: bool,
}

/// A chassis on four drives of one kind (see the [module docs](self) and `docs/simulator.md`,
/// section "Plant").
#[derive(Debug, Clone, PartialEq)]
pub struct Plant<D: Drive> {
    chassis: Chassis,
    drives: [D; WHEELS],
    sign: [f64; WHEELS],
    gear: [f64; WHEELS],
    now_ns: u64,
    substep_ns: u64,
    faults: [Faults; WHEELS],
    /// Faults to set once the clock reaches the time: `(at_ns, stuck, offline)`.
    pending_faults: Option<(u64, [bool; WHEELS], [bool; WHEELS])>,
    outbox: Vec<Timed<D::Feedback>>,
    scratch: Vec<D::Feedback>,
}

impl Plant<DjiDrive> {
    /// The chassis of `firmware::Config::dji_m3508_example()`: default [`ChassisParams`]
    /// (20 kg, lx 0.20, ly 0.18, r 0.076), four default C620 + M3508, right side inverted.
    ///
    /// # Errors
    /// Never with these defaults; the type is that of [`Plant::new`].
    pub fn dji_m3508_example() -> Result<Self, ParamError> {
        Self::new(
            ChassisParams::default(),
            core::array::from_fn(|_| DjiDrive::default()),
            [false, true, false, true],
        )
    }

    /// The plant for a DJI configuration: its geometry (default mass, inertia and contact),
    /// its gear ratio and mounting signs, default C620 + M3508 otherwise.
    ///
    /// # Errors
    /// [`ParamError`] if the configuration is not a C620 one (field `"drive"`), or its
    /// geometry or gear ratio is refused.
    pub fn dji_from_config(config: &firmware::Config) -> Result<Self, ParamError> {
        use firmware::config::Drive as D;
        use firmware::protocol::dji::EscModel;
        let D::Dji {
            model: EscModel::C620,
            gear_ratio,
            inverted,
            ..
        } = config.drive
        else {
            return Err(ParamError::new("drive", f64::NAN, "a DJI C620 drive"));
        };
        let motor = M3508Params {
            gear_ratio: f64::from(gear_ratio),
            ..M3508Params::default()
        };
        let drive = DjiDrive::new(motor, C620Params::default())?;
        Self::new(
            ChassisParams::from_config(config),
            core::array::from_fn(|_| drive.clone()),
            inverted,
        )
    }
}

impl Plant<OdriveAxis> {
    /// The plant for an ODrive configuration: its geometry with the body of
    /// [`Plant::odrive_example`], its gear ratio and mounting signs, default axes otherwise.
    ///
    /// # Errors
    /// [`ParamError`] if the configuration is not an ODrive one (field `"drive"`), or its
    /// geometry or gear ratio is refused.
    pub fn odrive_from_config(config: &firmware::Config) -> Result<Self, ParamError> {
        use firmware::config::Drive as D;
        let D::Odrive {
            gear_ratio,
            inverted,
            ..
        } = config.drive
        else {
            return Err(ParamError::new("drive", f64::NAN, "an ODrive drive"));
        };
        let axis = OdriveAxis::new(OdriveParams {
            gear_ratio: f64::from(gear_ratio),
            ..OdriveParams::default()
        })?;
        let mut chassis = ChassisParams::from_config(config);
        chassis.mass = 12.0;
        chassis.yaw_inertia = 0.28;
        chassis.wheel_inertia = [4.5e-4; WHEELS];
        Self::new(chassis, core::array::from_fn(|_| axis.clone()), inverted)
    }

    /// The chassis of `firmware::Config::odrive_example()`: lx 0.15, ly 0.125, r 0.05, a
    /// 12 kg body, four default ODrive axes (5:1), right side inverted.
    ///
    /// # Errors
    /// Never with these defaults; the type is that of [`Plant::new`].
    pub fn odrive_example() -> Result<Self, ParamError> {
        let mut chassis = ChassisParams::standard(0.15, 0.125, 0.05);
        chassis.mass = 12.0;
        // A 0.40 m x 0.35 m box of 12 kg.
        chassis.yaw_inertia = 0.28;
        // A 100 mm mecanum wheel of ~0.3 kg.
        chassis.wheel_inertia = [4.5e-4; WHEELS];
        Self::new(
            chassis,
            core::array::from_fn(|_| OdriveAxis::default()),
            [false, true, false, true],
        )
    }
}

impl Plant<Cia402Axis> {
    /// The plant for a CiA 402 configuration: its geometry with a 40 kg body, its gear ratio
    /// and mounting signs, hub-motor axes ([`Cia402Params`]).
    ///
    /// # Errors
    /// [`ParamError`] if the configuration is not a CiA 402 one (field `"drive"`), or its
    /// geometry or gear ratio is refused.
    pub fn cia402_from_config(config: &firmware::Config) -> Result<Self, ParamError> {
        use firmware::config::Drive as D;
        let D::Cia402(drive) = config.drive else {
            return Err(ParamError::new("drive", f64::NAN, "a CiA 402 drive"));
        };
        let axis = Cia402Axis::new(Cia402Params {
            gear_ratio: f64::from(drive.gear_ratio),
            ..Cia402Params::default()
        })?;
        let mut chassis = ChassisParams::from_config(config);
        // A 0.6 m x 0.5 m AGV of 40 kg on 200 mm wheels of 1.5 kg.
        chassis.mass = 40.0;
        chassis.yaw_inertia = 2.0;
        chassis.wheel_inertia = [7.5e-3; WHEELS];
        Self::new(
            chassis,
            core::array::from_fn(|_| axis.clone()),
            drive.inverted,
        )
    }
}

impl<D: Drive> Plant<D> {
    /// A plant at rest at the origin at time 0. `chassis.wheel_inertia` is the wheels' own;
    /// each drive's reflected rotor inertia is added to it.
    ///
    /// # Errors
    /// [`ParamError`] for the first chassis parameter out of range, or a drive whose gear
    /// ratio or reflected inertia is not a finite positive (resp. non-negative) number.
    pub fn new(
        mut chassis: ChassisParams,
        drives: [D; WHEELS],
        inverted: [bool; WHEELS],
    ) -> Result<Self, ParamError> {
        let mut gear = [1.0; WHEELS];
        for (i, d) in drives.iter().enumerate() {
            gear[i] = error::positive("drive.gear_ratio", d.gear_ratio()).map_err(|e| e.at(i))?;
            let j = error::non_negative("drive.reflected_inertia", d.reflected_inertia())
                .map_err(|e| e.at(i))?;
            chassis.wheel_inertia[i] += j;
        }
        let chassis = Chassis::new(chassis)?;
        let mut plant = Self {
            chassis,
            drives,
            sign: inverted.map(|i| if i { -1.0 } else { 1.0 }),
            gear,
            now_ns: 0,
            substep_ns: 0,
            faults: [Faults::default(); WHEELS],
            pending_faults: None,
            outbox: Vec::new(),
            scratch: Vec::new(),
        };
        plant.substep_ns = substep_ns(plant.chassis.substep());
        Ok(plant)
    }

    /// The same plant with its chassis parameters changed by `adjust`: a robot whose true
    /// geometry or rollers differ from what its configuration says (a scenario's `[plant]`
    /// table). Call it on a plant just built: the chassis starts again at rest at the origin.
    /// The wheel inertias `adjust` sees include the drives' reflected rotor inertia.
    ///
    /// # Errors
    /// The error of `adjust`, or [`ParamError`] for the first changed parameter out of range.
    pub fn with_chassis(
        mut self,
        adjust: impl FnOnce(&mut ChassisParams) -> Result<(), ParamError>,
    ) -> Result<Self, ParamError> {
        let mut params = *self.chassis.params();
        adjust(&mut params)?;
        self.chassis = Chassis::new(params)?;
        self.substep_ns = substep_ns(self.chassis.substep());
        Ok(self)
    }

    /// Simulated time, ns since the start.
    #[must_use]
    pub const fn time_ns(&self) -> u64 {
        self.now_ns
    }

    /// Simulated time, s.
    #[must_use]
    pub fn time(&self) -> f64 {
        // Exact below 2^53 ns (104 days).
        #[allow(clippy::cast_precision_loss)]
        let t = self.now_ns as f64 * 1e-9;
        t
    }

    /// The integration substep, ns.
    #[must_use]
    pub const fn substep_ns(&self) -> u64 {
        self.substep_ns
    }

    /// The chassis (ground truth, contacts, parameters).
    #[must_use]
    pub const fn chassis(&self) -> &Chassis {
        &self.chassis
    }

    /// Ground-truth chassis state.
    #[must_use]
    pub const fn state(&self) -> &ChassisState {
        self.chassis.state()
    }

    /// Ground-truth world pose.
    #[must_use]
    pub const fn pose(&self) -> Pose2<f64> {
        self.chassis.state().pose
    }

    /// Ground-truth body velocity.
    #[must_use]
    pub const fn velocity(&self) -> ChassisVelocity<f64> {
        self.chassis.state().velocity
    }

    /// One wheel's drive.
    #[must_use]
    pub const fn drive(&self, wheel: Wheel) -> &D {
        &self.drives[wheel.index()]
    }

    /// One wheel's drive, to command it.
    pub const fn drive_mut(&mut self, wheel: Wheel) -> &mut D {
        &mut self.drives[wheel.index()]
    }

    /// The same plant with its motors mounted as `inverted` says (`true`: mirrored), e.g.
    /// the other way than its configuration says (a miswired robot).
    #[must_use]
    pub fn with_inverted(mut self, inverted: [bool; WHEELS]) -> Self {
        self.sign = inverted.map(|i| if i { -1.0 } else { 1.0 });
        self
    }

    /// `true` where the drive is mounted mirrored.
    #[must_use]
    pub fn inverted(&self) -> [bool; WHEELS] {
        self.sign.map(|s| s < 0.0)
    }

    /// The true motor shaft of `wheel` (motor side, the motor's sign): `s · G · wheel`.
    #[must_use]
    pub fn shaft(&self, wheel: Wheel) -> Shaft {
        let i = wheel.index();
        let k = self.sign[i] * self.gear[i];
        let st = self.chassis.state();
        Shaft {
            angle: k * st.wheel_angle[i],
            speed: k * st.wheel_speed[i],
        }
    }

    /// The motor shaft as the drive reports it (frozen while the encoder is stuck).
    #[must_use]
    pub fn reported_shaft(&self, wheel: Wheel) -> Shaft {
        self.faults[wheel.index()]
            .stuck
            .unwrap_or_else(|| self.shaft(wheel))
    }

    /// Freezes (or releases) the reported angle and speed of `wheel`'s motor.
    pub fn set_stuck_encoder(&mut self, wheel: Wheel, stuck: bool) {
        let snapshot = self.shaft(wheel);
        let f = &mut self.faults[wheel.index()];
        f.stuck = match (stuck, f.stuck) {
            (true, Some(s)) => Some(s),
            (true, None) => Some(snapshot),
            (false, _) => None,
        };
    }

    /// Turns `wheel`'s drive off: no feedback at all and no torque, the wheel coasts (and the
    /// adapter must not deliver commands to it).
    pub fn set_offline(&mut self, wheel: Wheel, offline: bool) {
        self.faults[wheel.index()].offline = offline;
    }

    /// Sets every wheel's stuck encoder and offline drive ([`Self::set_stuck_encoder`],
    /// [`Self::set_offline`]) from `at_ns` on, at once if the plant's clock is already there:
    /// the motion before `at_ns` does not feel them, the feedback due at `at_ns` does. A later
    /// call replaces a setting that is still pending.
    pub fn set_faults_at(&mut self, at_ns: u64, stuck: [bool; WHEELS], offline: [bool; WHEELS]) {
        self.pending_faults = Some((at_ns, stuck, offline));
        self.apply_due_faults();
    }

    fn apply_due_faults(&mut self) {
        if let Some((at_ns, stuck, offline)) = self.pending_faults
            && at_ns <= self.now_ns
        {
            self.pending_faults = None;
            for w in Wheel::ALL {
                self.set_stuck_encoder(w, stuck[w.index()]);
                self.set_offline(w, offline[w.index()]);
            }
        }
    }

    /// Whether `wheel`'s drive is off the bus.
    #[must_use]
    pub const fn is_offline(&self, wheel: Wheel) -> bool {
        self.faults[wheel.index()].offline
    }

    /// Whether `wheel`'s encoder is stuck.
    #[must_use]
    pub const fn is_stuck(&self, wheel: Wheel) -> bool {
        self.faults[wheel.index()].stuck.is_some()
    }

    /// Changes the ground's friction coefficient for every wheel.
    ///
    /// # Errors
    /// [`ParamError`] unless `mu` is finite and `> 0`.
    pub fn set_friction(&mut self, mu: f64) -> Result<(), ParamError> {
        self.chassis.set_friction(mu)?;
        self.substep_ns = substep_ns(self.chassis.substep());
        Ok(())
    }

    /// Replaces the chassis state (start pose, initial velocity). Wheel angles and speeds are
    /// the chassis's; drive internals are not touched.
    ///
    /// # Errors
    /// [`ParamError`] if a value is not finite.
    pub fn set_state(&mut self, state: ChassisState) -> Result<(), ParamError> {
        self.chassis.set_state(state)
    }

    /// The feedback queued since the last call, in time order (then wheel order).
    pub fn take_feedback(&mut self) -> Vec<Timed<D::Feedback>> {
        core::mem::take(&mut self.outbox)
    }

    /// [`Self::take_feedback`] without giving up the queue's buffer: for a caller that
    /// collects feedback every step.
    pub fn drain_feedback(&mut self) -> impl Iterator<Item = Timed<D::Feedback>> + '_ {
        self.outbox.drain(..)
    }

    /// Advances by `dt` seconds (rounded to the nanosecond).
    ///
    /// # Errors
    /// [`ParamError`] if `dt` is negative, not finite or longer than a day; nothing happens.
    pub fn step(&mut self, dt: f64) -> Result<(), ParamError> {
        error::non_negative("dt", dt)?;
        if dt > 86_400.0 {
            return Err(ParamError::new("dt", dt, "at most one day per step"));
        }
        // In range: 0 <= dt * 1e9 <= 8.64e13.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let ns = round(dt * 1e9) as u64;
        self.advance_ns(ns);
        Ok(())
    }

    /// When the next feedback of any drive is due, ns of the plant's time.
    #[must_use]
    pub fn next_feedback_ns(&self) -> u64 {
        self.drives
            .iter()
            .map(Drive::next_feedback_ns)
            .min()
            .unwrap_or(u64::MAX)
    }

    /// Advances by `dt_ns` nanoseconds.
    pub fn advance_ns(&mut self, dt_ns: u64) {
        let end = self.now_ns.saturating_add(dt_ns);
        loop {
            self.apply_due_faults();
            self.emit_due();
            if self.now_ns >= end {
                break;
            }
            let faults_ns = self.pending_faults.map_or(end, |(at_ns, ..)| at_ns);
            let next = self.next_feedback_ns().min(end).min(faults_ns);
            let h_ns = self.substep_ns.min(next.saturating_sub(self.now_ns)).max(1);
            self.substep(h_ns);
            self.now_ns += h_ns;
        }
    }

    fn substep(&mut self, h_ns: u64) {
        // h_ns <= substep_ns, far below 2^53.
        #[allow(clippy::cast_precision_loss)]
        let h = h_ns as f64 * 1e-9;
        let mut inputs = [WheelInput::Torque(0.0); WHEELS];
        for w in Wheel::ALL {
            let i = w.index();
            let motor = self.shaft(w);
            let tau = self.drives[i].advance(h, motor);
            // An offline drive is off (no power, or shut down): its wheel coasts.
            let tau = if self.faults[i].offline { 0.0 } else { tau };
            inputs[i] = WheelInput::Torque(self.sign[i] * tau);
        }
        self.chassis.advance(h, &inputs);
    }

    fn emit_due(&mut self) {
        for w in Wheel::ALL {
            let i = w.index();
            if self.drives[i].next_feedback_ns() > self.now_ns {
                continue;
            }
            let motor = self.reported_shaft(w);
            self.scratch.clear();
            self.drives[i].emit_feedback(self.now_ns, motor, &mut self.scratch);
            if self.faults[i].offline {
                continue;
            }
            for feedback in self.scratch.drain(..) {
                self.outbox.push(Timed {
                    time_ns: self.now_ns,
                    wheel: w,
                    feedback,
                });
            }
        }
    }
}

/// The largest divisor of 1 ms not above `substep` seconds (at least 1 ns).
/// `x.trunc()` by an integer conversion (the baseline x86-64 target makes a libm call of
/// `trunc`, `round` and `floor`), for `|x| < 2⁵²`, where it is exact; `None` for larger,
/// infinite and NaN inputs (already integral, or NaN).
fn trunc_exact(x: f64) -> Option<f64> {
    const EXACT: f64 = 4_503_599_627_370_496.0; // 2^52
    // Below 2^52 the truncation fits an i64 and converts back exactly; above, `as`
    // saturates and the value is dropped.
    #[allow(clippy::cast_possible_truncation, clippy::cast_precision_loss)]
    (x.abs() < EXACT).then_some(x as i64 as f64)
}

/// `x.round()` (half away from zero) without the libm call: the truncation, then the
/// fraction, which is exact below 2⁵².
pub(crate) fn round(x: f64) -> f64 {
    let Some(t) = trunc_exact(x) else { return x };
    let frac = x - t;
    if frac >= 0.5 {
        t + 1.0
    } else if frac <= -0.5 {
        t - 1.0
    } else {
        t
    }
}

/// `x.floor()` without the libm call, on the same terms as [`round`].
pub(crate) fn floor(x: f64) -> f64 {
    let Some(t) = trunc_exact(x) else { return x };
    if t > x { t - 1.0 } else { t }
}

fn substep_ns(substep: f64) -> u64 {
    const MS: u64 = 1_000_000;
    // substep is in (0, 0.01] (validated), so this is in [0, 1e7].
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let limit = (substep * 1e9).floor() as u64;
    let mut n = MS.div_ceil(limit.max(1));
    while !MS.is_multiple_of(n) {
        n += 1;
    }
    MS / n
}

#[cfg(test)]
mod tests {
    #[test]
    fn round_and_floor_match_std() {
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            0.499_999_999_999_999_94,
            -0.499_999_999_999_999_94,
            4_503_599_627_370_495.5,
            4_503_599_627_370_497.0,
            -9.0e18,
            1.0e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut x = 0.123_f64;
        for _ in 0..100_000 {
            x = (x * 7.3 + 0.37) % 70_000.0 - 35_000.0;
            values.push(x);
            values.push((x * 2.0).round() / 2.0);
        }
        for v in values {
            assert_eq!(super::round(v), v.round(), "{v:e}");
            assert_eq!(super::floor(v), v.floor(), "{v:e}");
        }
        assert!(super::round(f64::NAN).is_nan());
        assert!(super::floor(f64::NAN).is_nan());
    }
}
