//! `[[actions]]`: what the host does, and when.

use firmware::params::{self, Param};
use serde::Deserialize;

use super::Invalid;
use crate::scenario::ScenarioError;

/// What the host does at a moment.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Action {
    /// When, s of simulated time.
    pub at_s: f64,
    /// Send `MODE_CMD enable`.
    #[serde(default)]
    pub enable: bool,
    /// Send `MODE_CMD disable`.
    #[serde(default)]
    pub disable: bool,
    /// Send `MODE_CMD reset`.
    #[serde(default)]
    pub reset: bool,
    /// Send `ESTOP`.
    #[serde(default)]
    pub estop: bool,
    /// Send a `STATUS_REQ`.
    #[serde(default)]
    pub status_request: bool,
    /// New twist setpoint `[vx, vy, wz]` (m/s, m/s, rad/s), streamed from now on.
    #[serde(default)]
    pub twist: Option<[f32; 3]>,
    /// Stop streaming twist commands (the setpoint is kept for a later `resume`).
    #[serde(default)]
    pub silence: bool,
    /// Resume streaming.
    #[serde(default)]
    pub resume: bool,
    /// Send a `WHEEL_TEST` (the bring-up check; a disabled robot runs it).
    #[serde(default)]
    pub wheel_test: Option<WheelTestSpec>,
    /// Set a parameter over CAN (an SDO download to the robot's parameter service; the robot
    /// may refuse it): `set = { param = "gains.kp", value = 1.5 }`.
    #[serde(default)]
    pub set: Option<ParamSet>,
    /// Save the parameters in force (`"save"`, `0x1010`) or restore the built-in set
    /// (`"restore"`, `0x1011`) over CAN; the robot answers once its flash has stored it.
    #[serde(default)]
    pub store: Option<StoreCommand>,
}

/// A save or a restore of the robot's parameters (CiA 301 `0x1010`, `0x1011`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StoreCommand {
    /// Save the parameters in force.
    Save,
    /// Put the built-in set in force and save it.
    Restore,
}

/// A parameter write as a scenario writes it.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamSet {
    /// The parameter, by its name (`mecanum-codec params` lists them).
    pub param: ParamName,
    /// The value, in the parameter's unit (a whole number for an integer type).
    pub value: f64,
}

/// A parameter of `firmware::params::PARAMS`, named in a scenario.
#[derive(Debug, Clone, Copy)]
pub struct ParamName(pub &'static Param);

impl PartialEq for ParamName {
    fn eq(&self, other: &Self) -> bool {
        self.0.name == other.0.name
    }
}

impl<'de> Deserialize<'de> for ParamName {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        params::find(&name).map(Self).ok_or_else(|| {
            serde::de::Error::custom(format!(
                "no parameter {name:?} (`mecanum-codec params` lists them)"
            ))
        })
    }
}

/// A `WHEEL_TEST` as a scenario writes it: `wheel_test = { wheel = 0, speed = 3.0,
/// duration_ms = 1000 }`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WheelTestSpec {
    /// The wheel, 0..=3 (FL, FR, RL, RR).
    pub wheel: u8,
    /// Wheel speed setpoint, rad/s, robot-forward positive, `|speed| <= 10`.
    pub speed: f32,
    /// How long, ms, 1..=3000.
    pub duration_ms: u16,
}

impl Action {
    /// An action at `at_s` that does nothing yet; set one field.
    #[must_use]
    pub const fn at(at_s: f64) -> Self {
        Self {
            at_s,
            enable: false,
            disable: false,
            reset: false,
            estop: false,
            status_request: false,
            twist: None,
            silence: false,
            resume: false,
            wheel_test: None,
            set: None,
            store: None,
        }
    }

    /// A twist setpoint at `at_s`.
    #[must_use]
    pub const fn twist(at_s: f64, vx: f32, vy: f32, wz: f32) -> Self {
        let mut a = Self::at(at_s);
        a.twist = Some([vx, vy, wz]);
        a
    }
}

/// Checks every action of a file whose run lasts `duration_s`.
pub(super) fn check(
    actions: &[Action],
    duration_s: f64,
    invalid: &Invalid<'_>,
) -> Result<(), ScenarioError> {
    for (i, a) in actions.iter().enumerate() {
        if !(a.at_s.is_finite() && a.at_s >= 0.0) {
            return Err(invalid.at(
                &format!("actions[{i}].at_s"),
                a.at_s.to_string(),
                "a time >= 0 s",
            ));
        }
        if a.at_s >= duration_s {
            return Err(invalid.at(
                &format!("actions[{i}].at_s"),
                a.at_s.to_string(),
                "a time before duration_s (a later action would never happen)",
            ));
        }
        let does = |set: bool, what: &'static str| set.then_some(what);
        let commands: Vec<&str> = [
            does(a.enable, "enable"),
            does(a.disable, "disable"),
            does(a.reset, "reset"),
            does(a.estop, "estop"),
            does(a.status_request, "status_request"),
            does(a.twist.is_some(), "twist"),
            does(a.silence, "silence"),
            does(a.resume, "resume"),
            does(a.wheel_test.is_some(), "wheel_test"),
            does(a.set.is_some(), "set"),
            does(a.store.is_some(), "store"),
        ]
        .into_iter()
        .flatten()
        .collect();
        let contradicts = |x, y| commands.contains(&x) && commands.contains(&y);
        if commands.is_empty()
            || contradicts("enable", "disable")
            || contradicts("silence", "resume")
        {
            return Err(invalid.at(
                &format!("actions[{i}]"),
                format!("{{{}}}", commands.join(", ")),
                "at least one of enable, disable, reset, estop, status_request, twist, \
                 silence, resume, wheel_test, set, store, and not both enable and disable or \
                 silence and resume",
            ));
        }
        if let Some(t) = a.twist
            && t.iter().any(|v| !v.is_finite())
        {
            return Err(invalid.at(
                &format!("actions[{i}].twist"),
                format!("{t:?}"),
                "finite numbers",
            ));
        }
        if let Some(s) = a.set
            && s.param.0.ty.from_f64(s.value).is_none()
        {
            return Err(invalid.at(
                &format!("actions[{i}].set.value"),
                s.value.to_string(),
                "a value the parameter's type holds (a whole number for an integer type, \
                 0 or 1 for a flag)",
            ));
        }
        if let Some(t) = a.wheel_test {
            // The protocol's ranges (WHEEL_TEST in the robot DBC): the codec would clamp.
            for (field, value, ok, expected) in [
                (
                    "wheel",
                    f64::from(t.wheel),
                    t.wheel <= 3,
                    "a wheel index 0..=3",
                ),
                (
                    "speed",
                    f64::from(t.speed),
                    t.speed.is_finite() && t.speed.abs() <= 10.0,
                    "a wheel speed in [-10, 10] rad/s",
                ),
                (
                    "duration_ms",
                    f64::from(t.duration_ms),
                    (1..=3000).contains(&t.duration_ms),
                    "1 to 3000 ms",
                ),
            ] {
                if !ok {
                    return Err(invalid.at(
                        &format!("actions[{i}].wheel_test.{field}"),
                        value.to_string(),
                        expected,
                    ));
                }
            }
        }
    }
    Ok(())
}
