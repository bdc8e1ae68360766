//! `[plant]`: the simulated robot where it differs from the drive configuration, a
//! miswiring included.

use firmware::Config;
use serde::Deserialize;

use crate::nodes::plant::{ChassisParams, ParamError};

/// The simulated robot where it differs from the drive configuration (a scenario's `[plant]`
/// table): its true wheel radius, wheel positions and roller drag. `None` keeps the value the
/// configuration (geometry) or the plant's defaults (roller drag, [`ChassisParams`]) give.
#[derive(Debug, Clone, PartialEq, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct PlantSpec {
    /// True wheel radius, m, in `(0, 1]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wheel_radius: Option<f64>,
    /// True distance from the centre to the wheels along x, m, in `(0, 5]` (standard layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lx: Option<f64>,
    /// True distance from the centre to the wheels along y, m, in `(0, 5]` (standard layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ly: Option<f64>,
    /// Roller drag `ε` ([`ChassisParams::roller_drag`]) in `[0, 1)`: a pure strafe settles at
    /// `(1 − ε)/(1 + ε)` of the command (default 1/7: 75 %).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roller_drag: Option<f64>,
    /// True mass of the robot, kg, in `(0, 1000]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mass_kg: Option<f64>,
    /// Wheels (indices 0..=3: FL, FR, RL, RR) whose motor is mounted the other way than the
    /// configuration's `drive.inverted` says: a miswired robot.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub flip: Vec<usize>,
    /// Pairs of wheels whose drives answer to each other's ids (`drive.esc_ids` or
    /// `drive.node_ids`): drives wired to the wrong wheels. Applied in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub swap: Vec<[usize; 2]>,
    /// The robot on blocks, wheels off the ground (the bring-up check): no wheel touches the
    /// ground, the body stays where it is.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub lifted: bool,
}

impl PlantSpec {
    /// `true` if it changes nothing.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// The robot of the DJI example configuration, every value given: lx 0.20 m, ly 0.18 m,
    /// wheel radius 0.076 m (as the configuration's `f32` values), roller drag 1/7 (the
    /// built-in `calibration` scenario's, so that `--config` changes only what the firmware
    /// believes).
    #[must_use]
    pub fn dji_m3508_example() -> Self {
        let c = ChassisParams::from_config(&Config::dji_m3508_example());
        let w = c.wheels[0];
        Self {
            wheel_radius: Some(w.radius),
            lx: Some(w.x),
            ly: Some(w.y),
            roller_drag: Some(c.roller_drag),
            ..Self::default()
        }
    }

    /// The first value out of its range: its field as a scenario file names it, the value and
    /// what is expected.
    #[must_use]
    pub fn first_invalid(&self) -> Option<(&'static str, f64, &'static str)> {
        let length = |v: f64, max: f64| v > 0.0 && v <= max;
        [
            (
                "plant.wheel_radius",
                self.wheel_radius,
                length(self.wheel_radius.unwrap_or(1.0), 1.0),
                "a radius in (0, 1] m",
            ),
            (
                "plant.lx",
                self.lx,
                length(self.lx.unwrap_or(1.0), 5.0),
                "a distance in (0, 5] m",
            ),
            (
                "plant.ly",
                self.ly,
                length(self.ly.unwrap_or(1.0), 5.0),
                "a distance in (0, 5] m",
            ),
            (
                "plant.roller_drag",
                self.roller_drag,
                (0.0..1.0).contains(&self.roller_drag.unwrap_or(0.0)),
                "a roller drag in [0, 1)",
            ),
            (
                "plant.mass_kg",
                self.mass_kg,
                length(self.mass_kg.unwrap_or(1.0), 1000.0),
                "a mass in (0, 1000] kg",
            ),
        ]
        .into_iter()
        .find_map(|(field, value, ok, expected)| Some((field, value?, expected)).filter(|_| !ok))
        .or_else(|| self.invalid_wiring())
    }

    /// The first wiring entry that is not acceptable, as [`Self::first_invalid`] names it.
    #[allow(clippy::cast_precision_loss)] // wheel indices
    fn invalid_wiring(&self) -> Option<(&'static str, f64, &'static str)> {
        const WHEEL: &str = "a wheel index 0..=3 (FL, FR, RL, RR)";
        for (k, &w) in self.flip.iter().enumerate() {
            if w > 3 {
                return Some(("plant.flip", w as f64, WHEEL));
            }
            if self.flip[..k].contains(&w) {
                return Some(("plant.flip", w as f64, "each wheel at most once"));
            }
        }
        for &[a, b] in &self.swap {
            if let Some(w) = [a, b].into_iter().find(|&w| w > 3) {
                return Some(("plant.swap", w as f64, WHEEL));
            }
            if a == b {
                return Some(("plant.swap", a as f64, "two different wheels"));
            }
        }
        None
    }

    /// The drive ids of the plant's wheels (its ESC or node id per wheel), given the
    /// configured ones: `configured` with [`Self::swap`] applied.
    #[must_use]
    pub fn wired_ids<T: Copy>(&self, configured: [T; 4]) -> [T; 4] {
        let mut ids = configured;
        for &[a, b] in &self.swap {
            if a < 4 && b < 4 {
                ids.swap(a, b);
            }
        }
        ids
    }

    /// How the plant's motors are mounted, given the configured `drive.inverted`: with
    /// [`Self::flip`] applied.
    #[must_use]
    pub fn wired_inverted(&self, configured: [bool; 4]) -> [bool; 4] {
        let mut inverted = configured;
        for &w in &self.flip {
            if let Some(i) = inverted.get_mut(w) {
                *i = !*i;
            }
        }
        inverted
    }

    /// Applies the values to a chassis built from a configuration.
    ///
    /// # Errors
    /// [`ParamError`] naming a value out of its range ([`Self::first_invalid`]), or `plant.lx`
    /// or `plant.ly` if the chassis is not the standard layout (wheels at `(±lx, ±ly)`).
    pub fn apply(&self, chassis: &mut ChassisParams) -> Result<(), ParamError> {
        if let Some((field, value, expected)) = self.first_invalid() {
            return Err(ParamError::new(field, value, expected));
        }
        let standard = {
            let w = &chassis.wheels;
            w.iter()
                .all(|g| g.x.abs() == w[0].x.abs() && g.y.abs() == w[0].y.abs())
        };
        for (field, value) in [("plant.lx", self.lx), ("plant.ly", self.ly)] {
            if let (Some(v), false) = (value, standard) {
                return Err(ParamError::new(
                    field,
                    v,
                    "a configuration with the standard layout (wheels at ±lx, ±ly)",
                ));
            }
        }
        for w in &mut chassis.wheels {
            if let Some(r) = self.wheel_radius {
                w.radius = r;
            }
            if let Some(lx) = self.lx {
                w.x = lx.copysign(w.x);
            }
            if let Some(ly) = self.ly {
                w.y = ly.copysign(w.y);
            }
        }
        if let Some(eps) = self.roller_drag {
            chassis.roller_drag = eps;
        }
        if let Some(m) = self.mass_kg {
            chassis.mass = m;
        }
        Ok(())
    }
}
