//! The simulated plant against the references and against itself: strafe loss (as FTC mecanum
//! tutorials report), the wheel patterns of Tlale and de Villiers, Table I, sign conventions
//! against the kinematics crate, energy, motor limits, the 13-bit rotor angle, the ODrive watchdog
//! and velocity loop, determinism.
//!
//! By concern: `chassis` (the chassis against the references: strafe, Table I, signs, energy,
//! ripple), `dji` (the M3508 and its C620: current, rotor angle, faults), `odrive` (its
//! watchdog and velocity loop), `setup` (parameters refused, plants from the example
//! configurations, determinism, cost).

use hostsim::nodes::plant::{DjiDrive, Plant, WHEELS, Wheel};
use kinematics::MecanumKinematics;

#[path = "plant/chassis.rs"]
mod chassis;
#[path = "plant/dji.rs"]
mod dji;
#[path = "plant/odrive.rs"]
mod odrive;
#[path = "plant/setup.rs"]
mod setup;

/// Standard layout of `firmware::Config::dji_m3508_example()`.
const LX: f64 = 0.20;
const LY: f64 = 0.18;
const R: f64 = 0.076;

fn kin() -> MecanumKinematics<f64, 4> {
    MecanumKinematics::standard(LX, LY, R).expect("valid layout")
}

/// A test-local wheel velocity PI on the C620 current, run at 1 kHz on the true wheel speed:
/// the "ideal velocity loop" the references' claims assume.
struct WheelPi {
    integral: [f64; WHEELS],
}

impl WheelPi {
    const KP: f64 = 3.0; // A per rad/s
    const KI: f64 = 60.0; // A per rad

    fn new() -> Self {
        Self {
            integral: [0.0; WHEELS],
        }
    }

    /// One control period: wheel setpoints (rad/s, positive forward) to currents.
    fn control(&mut self, plant: &mut Plant<DjiDrive>, setpoints: &[f64; WHEELS], dt: f64) {
        let inverted = plant.inverted();
        for w in Wheel::ALL {
            let i = w.index();
            let speed = plant.state().wheel_speed[i];
            let err = setpoints[i] - speed;
            self.integral[i] += err * dt;
            let amps = (Self::KP * err + Self::KI * self.integral[i]).clamp(-20.0, 20.0);
            let sign = if inverted[i] { -1.0 } else { 1.0 };
            plant.drive_mut(w).set_current_amps(sign * amps);
        }
    }
}
