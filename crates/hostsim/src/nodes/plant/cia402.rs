//! A CiA 402 drive's axis in profile velocity mode: a hub motor under a velocity loop with a
//! torque limit, powered only in operation enabled (or while a quick stop brings it to rest).
//!
//! The motor and its loop are the [`OdriveAxis`] model's (a velocity loop with an integrator,
//! a torque limit and friction), with a hub motor's parameters ([`Cia402Params`]); its ODrive
//! feedback schedule is not used. The CANopen side (NMT, SDO, PDOs, heartbeats, the 402 state
//! machine) is the firmware crate's drive double (`firmware::protocol::canopen::drive`), whose
//! commands the adapter, `crate::nodes::drives::canopen`, applies to this axis.

use firmware::protocol::odrive::AxisState;

use super::error::ParamError;
use super::odrive::{OdriveAxis, OdriveParams};
use super::{Drive, Shaft};

/// A hub-motor axis's parameters (motor side).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cia402Params {
    /// Motor turns per wheel turn (1: a hub motor).
    pub gear_ratio: f64,
    /// Rotor inertia, kg·m² (an 8-inch hub motor's rotor).
    pub rotor_inertia: f64,
    /// Velocity loop gain, N·m per rev/s.
    pub vel_gain: f64,
    /// Velocity loop integrator gain, N·m per rev.
    pub vel_integrator_gain: f64,
    /// Torque limit, N·m.
    pub torque_limit: f64,
    /// Velocity limit, rev/s.
    pub vel_limit: f64,
    /// Coulomb friction, N·m.
    pub coulomb_friction: f64,
    /// Viscous friction, N·m·s/rad.
    pub viscous_friction: f64,
}

impl Default for Cia402Params {
    fn default() -> Self {
        Self {
            gear_ratio: 1.0,
            rotor_inertia: 2.0e-3,
            // A loop time constant of about 10 ms on the example's 40 kg body, as the ODrive
            // model's on its 12 kg one: the body's share of inertia per wheel is ~0.1 kg·m².
            vel_gain: 60.0,
            vel_integrator_gain: 120.0,
            torque_limit: 20.0,
            vel_limit: 6.0,
            coulomb_friction: 0.05,
            viscous_friction: 1.0e-3,
        }
    }
}

/// One axis of a CiA 402 drive.
#[derive(Debug, Clone, PartialEq)]
pub struct Cia402Axis {
    motor: OdriveAxis,
}

impl Cia402Axis {
    /// An axis without power.
    ///
    /// # Errors
    /// [`ParamError`] for the first parameter out of range.
    pub fn new(p: Cia402Params) -> Result<Self, ParamError> {
        let motor = OdriveAxis::new(OdriveParams {
            gear_ratio: p.gear_ratio,
            rotor_inertia: p.rotor_inertia,
            vel_gain: p.vel_gain,
            vel_integrator_gain: p.vel_integrator_gain,
            torque_limit: p.torque_limit,
            vel_limit: p.vel_limit,
            coulomb_friction: p.coulomb_friction,
            viscous_friction: p.viscous_friction,
            watchdog_timeout: None,
            ..OdriveParams::default()
        })?;
        Ok(Self { motor })
    }

    /// Powers the loop (operation enabled, or a quick stop under way) or not.
    pub fn set_powered(&mut self, powered: bool) {
        let state = if powered {
            AxisState::ClosedLoopControl
        } else {
            AxisState::Idle
        };
        if self.motor.axis_state() != state {
            self.motor.set_axis_state(state);
        }
    }

    /// Whether the loop is powered.
    #[must_use]
    pub fn powered(&self) -> bool {
        self.motor.axis_state() == AxisState::ClosedLoopControl
    }

    /// The velocity target, rev/s (motor side).
    pub fn set_target(&mut self, rev_s: f64) {
        self.motor.set_input_vel(rev_s, 0.0);
    }
}

impl Drive for Cia402Axis {
    type Feedback = ();

    fn gear_ratio(&self) -> f64 {
        self.motor.gear_ratio()
    }

    fn reflected_inertia(&self) -> f64 {
        self.motor.reflected_inertia()
    }

    fn advance(&mut self, h: f64, motor: Shaft) -> f64 {
        self.motor.advance(h, motor)
    }

    /// The drive's frames are the adapter's: SYNC-triggered and SDO answers.
    fn next_feedback_ns(&self) -> u64 {
        u64::MAX
    }

    fn emit_feedback(&mut self, _now_ns: u64, _motor: Shaft, _out: &mut Vec<()>) {}
}
