//! DJI RoboMaster C620 ESC with an M3508 gear motor: a current-mode drive.
//!
//! # Model
//!
//! The firmware sends a current setpoint (raw `−16384..16384` ↔ `−20..20 A` for the C620).
//! The ESC's own current loop is a first-order lag toward the setpoint, clamped to the ESC's
//! limit and to what the bus voltage can push against the back-EMF:
//!
//! ```text
//! i ← i + (clamp(i_cmd, ±i_max) − i) (1 − e^(−h/τ_i))
//! i ∈ [(−V_bus − k_e ω) / R, (V_bus − k_e ω) / R]          (voltage limit)
//! τ_out = K_t i − τ_c ω / sqrt(ω² + ω_s²) − b ω            (at the gearbox output)
//! ```
//!
//! with `ω` the output shaft speed. `K_t ≈ 0.3 N·m/A` is the datasheet's figure *at the
//! gearbox output*; `k_e = V_bus / ω_nl` comes from the datasheet's no-load speed (482 rpm at
//! the output at 24 V), so the available current and torque fall to zero at the no-load
//! speed; the two constants are taken independently from the datasheet and `k_e` is used only
//! for that limit. The gearbox is 3591/187 (≈ 19.2) rotor turns per output turn; the rotor's
//! inertia times the gear ratio squared is added to the wheel's spin inertia by the plant.
//!
//! Winding temperature follows a one-node thermal model `C dT/dt = i² R − (T − T_amb)/R_th`.
//!
//! # Feedback
//!
//! A [`DjiFeedback`] every `feedback_period_ns` (1 ms, the C620 default), the fields of the
//! 0x201.. frame: the rotor angle (13 bits, one *rotor* turn, wraps), the rotor speed in rpm
//! (rotor side, signed), the current (same scale as the command) and the temperature.

use firmware::protocol::dji::{EscId, EscModel, Feedback};

use super::error::{ParamError, finite, non_negative, positive};
use super::{Drive, Shaft};

/// Counts per rotor turn of the C620's angle field (13 bits).
pub const ROTOR_COUNTS: u16 = 8192;

/// The M3508 gear motor (P19 gearbox). Torque constant and friction at the gearbox output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct M3508Params {
    /// Rotor turns per output turn (3591/187).
    pub gear_ratio: f64,
    /// Torque constant at the gearbox output, N·m/A (datasheet: 0.3).
    pub torque_constant: f64,
    /// Output no-load speed at the ESC's bus voltage, rpm (datasheet: 482 at 24 V).
    pub no_load_speed_rpm: f64,
    /// Winding resistance, Ω (datasheet phase resistance 0.194).
    pub resistance: f64,
    /// Rotor inertia, kg·m² (estimate; the plant adds `rotor_inertia · gear_ratio²` at the
    /// wheel).
    pub rotor_inertia: f64,
    /// Coulomb friction at the output (gearbox, seals), N·m.
    pub coulomb_friction: f64,
    /// Speed below which the Coulomb friction is smoothed to zero, rad/s at the output.
    pub friction_smoothing: f64,
    /// Viscous friction at the output, N·m·s/rad.
    pub viscous_friction: f64,
    /// Thermal resistance winding to ambient, K/W.
    pub thermal_resistance: f64,
    /// Thermal capacity of the winding, J/K.
    pub thermal_capacity: f64,
    /// Ambient (and initial) temperature, °C.
    pub ambient_c: f64,
}

impl Default for M3508Params {
    fn default() -> Self {
        Self {
            gear_ratio: 3591.0 / 187.0,
            torque_constant: 0.3,
            no_load_speed_rpm: 482.0,
            resistance: 0.194,
            rotor_inertia: 1.5e-5,
            coulomb_friction: 0.05,
            friction_smoothing: 0.5,
            viscous_friction: 1.0e-3,
            thermal_resistance: 1.5,
            thermal_capacity: 150.0,
            ambient_c: 25.0,
        }
    }
}

/// The C620 ESC.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct C620Params {
    /// Current limit, A (20).
    pub max_current: f64,
    /// Time constant of the ESC's current loop, s (≈ 1 ms).
    pub current_time_constant: f64,
    /// Bus voltage, V (24).
    pub bus_voltage: f64,
    /// Feedback period, ns (1 ms: 1 kHz).
    pub feedback_period_ns: u64,
}

impl Default for C620Params {
    fn default() -> Self {
        Self {
            max_current: 20.0,
            current_time_constant: 1.0e-3,
            bus_voltage: 24.0,
            feedback_period_ns: 1_000_000,
        }
    }
}

/// The contents of one C620 feedback frame (0x200 + ESC id).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DjiFeedback {
    /// Rotor angle, 0..8191 over one rotor turn.
    pub rotor_angle: u16,
    /// Rotor speed, rpm (rotor side, signed).
    pub rotor_speed_rpm: i16,
    /// Torque current, raw (C620: ±16384 ↔ ±20 A).
    pub torque_current: i16,
    /// Temperature, °C.
    pub temperature_c: u8,
}

impl DjiFeedback {
    /// The firmware codec's message for ESC `esc` (encode it with `to_can_frame`).
    #[must_use]
    pub const fn to_firmware(self, esc: EscId) -> Feedback {
        Feedback {
            model: EscModel::C620,
            esc,
            rotor_angle: self.rotor_angle,
            rotor_speed_rpm: self.rotor_speed_rpm,
            torque_current: self.torque_current,
            temperature_c: self.temperature_c,
        }
    }
}

/// A C620 ESC driving an M3508 (see the [module docs](self)).
#[derive(Debug, Clone, PartialEq)]
pub struct DjiDrive {
    motor: M3508Params,
    esc: C620Params,
    /// Back-EMF constant at the output, V·s/rad.
    ke: f64,
    command: f64,
    current: f64,
    temperature: f64,
    next_feedback_ns: u64,
    /// The current loop's factor `1 − e^(−h/τ_i)` per step length.
    lag: LagCache,
}

/// The current loop's factor `1 − e^(−h/τ_i)` for the step lengths seen so far.
///
/// The lockstep loop splits each period at the delivery of the current command, so a run
/// steps the drives with a few hundred lengths, whole microseconds, over and over (284 in the
/// 60 s square), and the `exp` behind each new step was a tenth of a run's time. Direct-mapped
/// on the length in µs. A cache, not state: an entry is the same `exp` of the same `h`, so it
/// never changes a result, and drives compare equal whatever it holds. `τ_i` is fixed when
/// the drive is built.
#[derive(Clone)]
struct LagCache([(f64, f64); LAG_SLOTS]);

const LAG_SLOTS: usize = 64;

impl LagCache {
    /// Every slot holds `h = 0`, whose factor is 0.
    const fn new() -> Self {
        Self([(0.0, 0.0); LAG_SLOTS])
    }

    /// `1 − e^(−h/τ)`, `tau` being the drive's fixed `τ_i`.
    fn factor(&mut self, h: f64, tau: f64) -> f64 {
        // Only picks the slot: saturating, and any value will do for a NaN or a huge step.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let slot = &mut self.0[(h * 1e6) as usize % LAG_SLOTS];
        if slot.0 != h {
            *slot = (h, 1.0 - libm::exp(-h / tau));
        }
        slot.1
    }
}

impl PartialEq for LagCache {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl core::fmt::Debug for LagCache {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("LagCache")
    }
}

impl Default for DjiDrive {
    fn default() -> Self {
        // The defaults are valid (checked by a test).
        Self::build(M3508Params::default(), C620Params::default())
    }
}

impl DjiDrive {
    /// Raw current units per ampere on the C620 scale.
    pub const RAW_PER_AMP: f64 = 16384.0 / 20.0;

    /// A drive at rest, zero current, first feedback one period after time 0.
    ///
    /// # Errors
    /// [`ParamError`] for the first parameter out of range.
    pub fn new(motor: M3508Params, esc: C620Params) -> Result<Self, ParamError> {
        positive("m3508.gear_ratio", motor.gear_ratio)?;
        positive("m3508.torque_constant", motor.torque_constant)?;
        positive("m3508.no_load_speed_rpm", motor.no_load_speed_rpm)?;
        positive("m3508.resistance", motor.resistance)?;
        non_negative("m3508.rotor_inertia", motor.rotor_inertia)?;
        non_negative("m3508.coulomb_friction", motor.coulomb_friction)?;
        positive("m3508.friction_smoothing", motor.friction_smoothing)?;
        non_negative("m3508.viscous_friction", motor.viscous_friction)?;
        positive("m3508.thermal_resistance", motor.thermal_resistance)?;
        positive("m3508.thermal_capacity", motor.thermal_capacity)?;
        finite("m3508.ambient_c", motor.ambient_c)?;
        positive("c620.max_current", esc.max_current)?;
        positive("c620.current_time_constant", esc.current_time_constant)?;
        positive("c620.bus_voltage", esc.bus_voltage)?;
        if esc.feedback_period_ns == 0 {
            return Err(ParamError::new(
                "c620.feedback_period_ns",
                0.0,
                "a period > 0",
            ));
        }
        Ok(Self::build(motor, esc))
    }

    fn build(motor: M3508Params, esc: C620Params) -> Self {
        let no_load = motor.no_load_speed_rpm * core::f64::consts::TAU / 60.0;
        Self {
            motor,
            esc,
            ke: esc.bus_voltage / no_load,
            command: 0.0,
            current: 0.0,
            temperature: motor.ambient_c,
            next_feedback_ns: esc.feedback_period_ns,
            lag: LagCache::new(),
        }
    }

    /// The motor parameters.
    #[must_use]
    pub const fn motor(&self) -> &M3508Params {
        &self.motor
    }

    /// The ESC parameters.
    #[must_use]
    pub const fn esc(&self) -> &C620Params {
        &self.esc
    }

    /// Sets the current setpoint from the command frame's raw value (±16384 ↔ ±20 A; larger
    /// values are clamped by the ESC).
    pub fn set_current_raw(&mut self, raw: i16) {
        self.command = f64::from(raw) / Self::RAW_PER_AMP;
    }

    /// Sets the current setpoint in amperes; NaN is ignored (the ESC keeps the last setpoint).
    pub fn set_current_amps(&mut self, amps: f64) {
        if !amps.is_nan() {
            self.command = amps;
        }
    }

    /// The current setpoint, A (before the ESC's clamp).
    #[must_use]
    pub const fn current_command(&self) -> f64 {
        self.command
    }

    /// The winding current, A.
    #[must_use]
    pub const fn current(&self) -> f64 {
        self.current
    }

    /// Winding temperature, °C.
    #[must_use]
    pub const fn temperature(&self) -> f64 {
        self.temperature
    }

    /// The output torque at output speed `omega` (rad/s) with the present current, N·m.
    #[must_use]
    pub fn output_torque(&self, omega: f64) -> f64 {
        let m = &self.motor;
        let smoothing = m.friction_smoothing;
        let friction = m.coulomb_friction * omega / (omega * omega + smoothing * smoothing).sqrt()
            + m.viscous_friction * omega;
        m.torque_constant * self.current - friction
    }

    /// The feedback frame for rotor shaft state `rotor` (rad, rad/s, rotor side).
    #[must_use]
    pub fn feedback_for(&self, rotor: Shaft) -> DjiFeedback {
        let counts = f64::from(ROTOR_COUNTS);
        let turns = rotor.angle * (1.0 / core::f64::consts::TAU);
        let turn = turns - super::floor(turns);
        // `turn` is in [0, 1], so this truncation is the floor, in [0, 8192]; `min` covers a
        // fraction that rounds up to one full turn.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let angle = ((turn * counts) as u16).min(ROTOR_COUNTS - 1);
        let rpm = rotor.speed * (60.0 / core::f64::consts::TAU);
        let raw = self.current * Self::RAW_PER_AMP;
        DjiFeedback {
            rotor_angle: angle,
            rotor_speed_rpm: saturate_i16(rpm),
            torque_current: saturate_i16(raw.clamp(-16384.0, 16384.0)),
            // Saturating float-to-int conversion, rounded.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            temperature_c: super::round(self.temperature).clamp(0.0, 255.0) as u8,
        }
    }
}

/// Rounds and saturates to `i16` (NaN gives 0).
fn saturate_i16(x: f64) -> i16 {
    // `as` saturates and maps NaN to 0.
    #[allow(clippy::cast_possible_truncation)]
    let v = super::round(x) as i16;
    v
}

impl Drive for DjiDrive {
    type Feedback = DjiFeedback;

    fn gear_ratio(&self) -> f64 {
        self.motor.gear_ratio
    }

    fn reflected_inertia(&self) -> f64 {
        self.motor.rotor_inertia * self.motor.gear_ratio * self.motor.gear_ratio
    }

    fn advance(&mut self, h: f64, rotor: Shaft) -> f64 {
        let omega = rotor.speed / self.motor.gear_ratio;
        let target = self
            .command
            .clamp(-self.esc.max_current, self.esc.max_current);
        let alpha = self.lag.factor(h, self.esc.current_time_constant);
        let mut i = self.current + (target - self.current) * alpha;
        let emf = self.ke * omega;
        let lo = (-self.esc.bus_voltage - emf) / self.motor.resistance;
        let hi = (self.esc.bus_voltage - emf) / self.motor.resistance;
        // lo < hi: the bus voltage is positive.
        i = i.clamp(lo, hi);
        self.current = i;
        let m = &self.motor;
        let heat = i * i * m.resistance - (self.temperature - m.ambient_c) / m.thermal_resistance;
        self.temperature += h * heat / m.thermal_capacity;
        self.output_torque(omega)
    }

    fn next_feedback_ns(&self) -> u64 {
        self.next_feedback_ns
    }

    fn emit_feedback(&mut self, now_ns: u64, rotor: Shaft, out: &mut Vec<DjiFeedback>) {
        if now_ns < self.next_feedback_ns {
            return;
        }
        out.push(self.feedback_for(rotor));
        let period = self.esc.feedback_period_ns;
        // Next multiple of the period after `now`: a late poll does not burst.
        self.next_feedback_ns = (now_ns / period + 1) * period;
    }
}
