//! The drive configuration: geometry, motor protocol and ids, per-wheel mounting, limits,
//! gains and rates.
//!
//! One plain-data [`Config`] serves every target. On the host it is read from TOML (feature
//! `serde` derives `Deserialize`; the `std` feature adds `Config::from_toml_str`); on the MCU
//! it is built in code. Either way [`Config::validate`] checks it before a
//! [`Controller`](crate::control::Controller) accepts it, and every error names the field and
//! the value that is wrong ([`ConfigError`]).
//!
//! Wheel arrays are in the order FL, FR, RL, RR. Units are SI unless a name says otherwise
//! (`_ms`, `_hz`).
//!
//! The optional effectiveness factors of [`Geometry`] (slip) and the `[odometry]` section
//! ([`OdometryConfig`], heading from a gyro) are specified in `docs/protocol.md`, section
//! "Configuration file".

use core::fmt;

use kinematics::{Effectiveness, GeometryError, MecanumKinematics, WheelGeometry};

use crate::protocol::dji::{EscId, EscModel};
use crate::protocol::odrive::NodeId;
use crate::protocol::robot;

mod cia402;
mod encoding;
mod pods;
#[cfg(feature = "serde")]
mod tagged;
pub use cia402::{Cia402Drive, defaults as cia402_defaults};
pub use encoding::ENCODED_LEN;
pub use pods::{OdometryMode, PODS_MAX, PodConfig, Pods};
pub(crate) use pods::{PodSolve, localizer as pod_localizer};

/// The whole drive configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct Config {
    /// Wheel layout.
    pub geometry: Geometry,
    /// Motor controllers on the bus.
    pub drive: Drive,
    /// Speed, acceleration and current limits.
    #[cfg_attr(feature = "serde", serde(default))]
    pub limits: Limits,
    /// Wheel velocity loop gains (current-mode drives only).
    #[cfg_attr(feature = "serde", serde(default))]
    pub gains: Gains,
    /// Loop, telemetry and timeout timing.
    #[cfg_attr(feature = "serde", serde(default))]
    pub timing: Timing,
    /// Where the odometry's heading comes from: the wheels, or a gyro (see `docs/protocol.md`,
    /// section "Heading from a gyro"). Left out of the TOML at its defaults.
    #[cfg_attr(
        feature = "serde",
        serde(default, skip_serializing_if = "OdometryConfig::is_default")
    )]
    pub odometry: OdometryConfig,
}

/// Wheel layout.
///
/// In TOML, a table with `layout = "standard"` or `"general"` and that layout's keys.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
#[cfg_attr(feature = "serde", serde(tag = "layout", rename_all = "snake_case"))]
pub enum Geometry {
    /// Four wheels at `(±lx, ±ly)`, 45° rollers pointing to the centre seen from above.
    Standard {
        /// Distance from the centre to the wheel centres along x, m.
        lx: f32,
        /// Distance from the centre to the wheel centres along y, m.
        ly: f32,
        /// Wheel radius, m.
        wheel_radius: f32,
        /// Fraction of the wheel-implied forward (x) motion the robot makes, in `(0, 1.5]`
        /// (see `docs/protocol.md`, section "Effectiveness (slip)").
        #[cfg_attr(feature = "serde", serde(skip_serializing_if = "unit::is_one"))]
        forward_effectiveness: f32,
        /// Fraction of the wheel-implied lateral (y) motion the robot makes, in `(0, 1.5]`.
        #[cfg_attr(feature = "serde", serde(skip_serializing_if = "unit::is_one"))]
        lateral_effectiveness: f32,
        /// Fraction of the wheel-implied yaw motion the robot makes, in `(0, 1.5]`.
        #[cfg_attr(feature = "serde", serde(skip_serializing_if = "unit::is_one"))]
        yaw_effectiveness: f32,
    },
    /// Any four wheels, each given by its own geometry (FL, FR, RL, RR).
    General {
        /// Per-wheel geometry.
        wheels: [WheelConfig; 4],
        /// Fraction of the wheel-implied forward (x) motion the robot makes, in `(0, 1.5]`
        /// (see `docs/protocol.md`, section "Effectiveness (slip)").
        #[cfg_attr(feature = "serde", serde(skip_serializing_if = "unit::is_one"))]
        forward_effectiveness: f32,
        /// Fraction of the wheel-implied lateral (y) motion the robot makes, in `(0, 1.5]`.
        #[cfg_attr(feature = "serde", serde(skip_serializing_if = "unit::is_one"))]
        lateral_effectiveness: f32,
        /// Fraction of the wheel-implied yaw motion the robot makes, in `(0, 1.5]`.
        #[cfg_attr(feature = "serde", serde(skip_serializing_if = "unit::is_one"))]
        yaw_effectiveness: f32,
    },
}

impl Geometry {
    /// The effectiveness factors (forward, lateral, yaw) of either layout.
    #[must_use]
    pub const fn effectiveness(&self) -> Effectiveness<f32> {
        match *self {
            Self::Standard {
                forward_effectiveness,
                lateral_effectiveness,
                yaw_effectiveness,
                ..
            }
            | Self::General {
                forward_effectiveness,
                lateral_effectiveness,
                yaw_effectiveness,
                ..
            } => Effectiveness::new(
                forward_effectiveness,
                lateral_effectiveness,
                yaw_effectiveness,
            ),
        }
    }
}

/// The effectiveness keys' default and when they are left out of the TOML.
#[cfg(feature = "serde")]
mod unit {
    pub const fn one() -> f32 {
        1.0
    }

    // A bit test, so that only exactly 1.0 is left out (what reads back as the default).
    pub const fn is_one(value: &f32) -> bool {
        value.to_bits() == 1.0f32.to_bits()
    }
}

/// One wheel of a [`Geometry::General`] layout (see [`WheelGeometry`]).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct WheelConfig {
    /// Wheel centre x, m.
    pub x: f32,
    /// Wheel centre y, m.
    pub y: f32,
    /// Axle angle from the body x axis, rad (π/2 for a wheel rolling forward).
    pub axle_angle: f32,
    /// Roller angle to the axle, rad.
    pub roller_angle: f32,
    /// Radius, m.
    pub radius: f32,
}

/// The motor controllers and how each wheel is wired to one.
///
/// In TOML, a table with `protocol = "dji"`, `"odrive"` or `"cia402"` and that protocol's keys.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
#[cfg_attr(feature = "serde", serde(tag = "protocol", rename_all = "snake_case"))]
pub enum Drive {
    /// DJI C620/C610 current-mode ESCs; the firmware runs the wheel velocity loop.
    Dji {
        /// ESC model.
        #[cfg_attr(
            feature = "serde",
            serde(serialize_with = "esc_model_serde::serialize")
        )]
        model: EscModel,
        /// ESC id (1..=8) of each wheel.
        esc_ids: [u8; 4],
        /// Rotor turns per wheel turn (3591/187 for the M3508; 36 for the M2006).
        gear_ratio: f32,
        /// `true` where a positive motor current rolls the robot backward (mirrored side).
        inverted: [bool; 4],
    },
    /// ODrive (CAN Simple) velocity-mode drives; the drive runs the velocity loop.
    Odrive {
        /// Node id (0..=63) of each wheel's axis.
        node_ids: [u8; 4],
        /// Motor turns per wheel turn (1 for direct drive).
        gear_ratio: f32,
        /// `true` where a positive motor velocity rolls the robot backward.
        inverted: [bool; 4],
        /// Use the drive's velocity ramp input mode (else passthrough). Default `false`.
        vel_ramp: bool,
    },
    /// CANopen CiA 402 drives in profile velocity mode; the drive runs the velocity loop and
    /// the core is the CANopen master (`docs/protocol.md`, section "CANopen CiA 402").
    Cia402(Cia402Drive),
}

#[cfg(feature = "serde")]
mod esc_model_serde {
    use crate::protocol::dji::EscModel;

    pub fn serialize<S: serde::Serializer>(m: &EscModel, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(match m {
            EscModel::C620 => "c620",
            EscModel::C610 => "c610",
        })
    }

    /// `drive.model`, read.
    pub struct Model(pub EscModel);

    impl<'de> serde::Deserialize<'de> for Model {
        fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            deserialize(d).map(Model)
        }
    }

    fn deserialize<'de, D: serde::Deserializer<'de>>(d: D) -> Result<EscModel, D::Error> {
        struct V;
        impl serde::de::Visitor<'_> for V {
            type Value = EscModel;
            fn expecting(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
                f.write_str("\"c620\" or \"c610\"")
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<EscModel, E> {
                match v {
                    "c620" | "C620" => Ok(EscModel::C620),
                    "c610" | "C610" => Ok(EscModel::C610),
                    _ => Err(E::invalid_value(serde::de::Unexpected::Str(v), &self)),
                }
            }
        }
        d.deserialize_str(V)
    }
}

/// Limits on what the controller commands.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct Limits {
    /// Largest accepted linear speed command `|(vx, vy)|`, m/s; larger commands are rejected.
    pub max_linear_speed: f32,
    /// Largest accepted yaw rate command `|wz|`, rad/s.
    pub max_angular_speed: f32,
    /// Linear acceleration limit of the commanded body velocity, m/s².
    pub max_linear_accel: f32,
    /// Yaw acceleration limit, rad/s².
    pub max_angular_accel: f32,
    /// Linear deceleration after the command watchdog expires, m/s² (`inf`: stop at once).
    pub stop_linear_decel: f32,
    /// Yaw deceleration after the command watchdog expires, rad/s² (`inf`: stop at once).
    pub stop_angular_decel: f32,
    /// Largest wheel speed the drive can hold, rad/s: wheel setpoints are desaturated to it.
    pub max_wheel_speed: f32,
    /// Largest motor current the velocity loop may command, A (current-mode drives).
    pub max_current: f32,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_linear_speed: 3.0,
            max_angular_speed: 6.0,
            max_linear_accel: 4.0,
            max_angular_accel: 12.0,
            stop_linear_decel: 8.0,
            stop_angular_decel: 24.0,
            // M3508 no-load ~482 rpm at the output shaft: 50 rad/s; keep margin for the loop.
            max_wheel_speed: 45.0,
            max_current: 16.0,
        }
    }
}

/// Wheel velocity PI (current-mode drives). Output current, A, from wheel speed error, rad/s.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct Gains {
    /// Proportional gain, A per rad/s of wheel speed error.
    pub kp: f32,
    /// Integral gain, A per rad of accumulated wheel angle error.
    pub ki: f32,
    /// Feed-forward, A per rad/s of wheel speed setpoint (viscous friction).
    pub kv: f32,
}

impl Default for Gains {
    fn default() -> Self {
        Self {
            kp: 1.2,
            ki: 30.0,
            kv: 0.0,
        }
    }
}

/// Rates and timeouts.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct Timing {
    /// Control loop rate, Hz (1 kHz by default).
    pub control_hz: u32,
    /// Odometry frames rate, Hz; must divide `control_hz`.
    pub odometry_hz: u32,
    /// Status and heartbeat frames rate, Hz; must divide `control_hz`.
    pub status_hz: u32,
    /// Velocity setpoint rate to velocity-mode drives, Hz (ODrive setpoints; for CiA 402
    /// drives the SYNC cycle, each with the targets and the drives' feedback); must divide
    /// `control_hz`.
    pub setpoint_hz: u32,
    /// Command watchdog, ms: without a fresh valid twist command for this long the robot
    /// stops and disables (latched).
    pub command_timeout_ms: u32,
    /// A motor never heard from this long after the first step faults as missing, ms.
    pub boot_timeout_ms: u32,
    /// A motor whose feedback is older than this many expected periods faults as stale.
    pub stale_periods: u32,
}

impl Default for Timing {
    fn default() -> Self {
        Self {
            control_hz: 1000,
            odometry_hz: 100,
            status_hz: 10,
            setpoint_hz: 200,
            command_timeout_ms: 100,
            boot_timeout_ms: 1000,
            stale_periods: 3,
        }
    }
}

/// Where the odometry takes each step's rotation from (`odometry.heading_source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(rename_all = "snake_case"))]
pub enum HeadingMode {
    /// `"wheels"`: forward kinematics of the wheel increments, as without a gyro.
    #[default]
    Wheels,
    /// `"gyro"`: the gyro's yaw rate (`IMU_YAW_RATE`) less its estimated bias, while the gyro
    /// is alive; the wheels while it is silent.
    Gyro,
}

/// Where the odometry's increments and heading come from, the gyro's parameters and the
/// tracking pods (`[odometry]`).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct OdometryConfig {
    /// Where each step's rotation comes from (default [`HeadingMode::Wheels`]).
    pub heading_source: HeadingMode,
    /// With the gyro: without a valid `IMU_YAW_RATE` for this long the wheels give the
    /// heading (and `STATUS.heading_source` reports the gyro silent), ms. Default 50: ten
    /// periods of a 200 Hz IMU. In `1..=10000`.
    pub gyro_timeout_ms: u32,
    /// With the gyro: how long the robot must stand still (no motion commanded, every wheel
    /// online and at rest) before its gyro readings count towards the bias estimate, ms: the
    /// chassis settles first. Default 50 (the built-in scenarios stand still for 100 ms
    /// before their first twist). In `0..=60000`.
    pub gyro_standstill_ms: u32,
    /// With the gyro: learn its bias while standing still and subtract it (default `true`).
    /// `false` for a gyro that removes its own bias.
    pub gyro_bias_estimation: bool,
    /// Where each step's increments come from: the wheels (default) or tracking pods
    /// ([`OdometryMode`]; `docs/control.md`, "Odometry from tracking pods").
    pub source: OdometryMode,
    /// With pods: without a valid `POD_COUNTS` for this long the wheels give the odometry
    /// (`ODOM_SLIP.source` reports the pods silent), ms. Default 50: ten periods of a 200 Hz
    /// pod node. In `1..=10000`.
    pub pod_timeout_ms: u32,
    /// The pods, in the order of `POD_COUNTS.count0..2`: two for `"pods2_gyro"`, three for
    /// `"pods3"`, none otherwise.
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Pods::is_empty"))]
    pub pods: Pods,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self {
            heading_source: HeadingMode::Wheels,
            gyro_timeout_ms: 50,
            gyro_standstill_ms: 50,
            gyro_bias_estimation: true,
            source: OdometryMode::Wheels,
            pod_timeout_ms: 50,
            pods: Pods::default(),
        }
    }
}

impl OdometryConfig {
    /// Whether every key is at its default (the section is then left out of the TOML).
    #[must_use]
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// A configuration value that is not acceptable: which field, which value, and why.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConfigError {
    /// Dotted path of the field, e.g. `"limits.max_wheel_speed"` or `"drive.esc_ids[2]"`.
    pub field: &'static str,
    /// The rejected value (integers and booleans widened).
    pub value: f64,
    /// What is expected of it.
    pub expected: &'static str,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Values come from f32 fields or integers: print the shortest form that reads back.
        #[allow(clippy::cast_possible_truncation)]
        let narrow = self.value as f32;
        if f64::from(narrow) == self.value {
            write!(f, "{} = {}: {}", self.field, narrow, self.expected)
        } else {
            write!(f, "{} = {}: {}", self.field, self.value, self.expected)
        }
    }
}

impl core::error::Error for ConfigError {}

fn positive(field: &'static str, value: f32) -> Result<(), ConfigError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(ConfigError {
            field,
            value: f64::from(value),
            expected: "a finite number > 0",
        })
    }
}

/// A gear ratio (motor turns per wheel turn): within [`GEAR_RATIO_RANGE`], so that every
/// conversion derived from it (counts or turns to wheel radians) is finite and nonzero.
fn check_gear_ratio(value: f32) -> Result<(), ConfigError> {
    if GEAR_RATIO_RANGE.contains(&value) {
        Ok(())
    } else {
        Err(ConfigError {
            field: "drive.gear_ratio",
            value: f64::from(value),
            expected: "a ratio in 0.01..=1000 (motor turns per wheel turn)",
        })
    }
}

/// The gear ratios a configuration may give: from a 100:1 step-up to a 1000:1 reduction.
pub const GEAR_RATIO_RANGE: core::ops::RangeInclusive<f32> = 0.01..=1000.0;

/// The `[geometry]` keys of the effectiveness factors, in axis order (x, y, yaw).
pub const EFFECTIVENESS_KEYS: [&str; 3] = [
    "geometry.forward_effectiveness",
    "geometry.lateral_effectiveness",
    "geometry.yaw_effectiveness",
];

/// An effectiveness factor: finite and in `(0, MAX_EFFECTIVENESS]`.
fn check_effectiveness(field: &'static str, value: f32) -> Result<(), ConfigError> {
    // Written so that NaN fails.
    #[allow(clippy::cast_possible_truncation)]
    let in_range = value > 0.0 && value <= kinematics::MAX_EFFECTIVENESS as f32;
    if in_range {
        Ok(())
    } else {
        Err(ConfigError {
            field,
            value: f64::from(value),
            expected: "a factor in (0, 1.5]: the fraction of the wheel-implied motion the \
                       robot makes along that axis (1 = no slip)",
        })
    }
}

fn positive_or_inf(field: &'static str, value: f32) -> Result<(), ConfigError> {
    if value > 0.0 {
        Ok(())
    } else {
        Err(ConfigError {
            field,
            value: f64::from(value),
            expected: "a number > 0 (inf allowed)",
        })
    }
}

fn non_negative(field: &'static str, value: f32) -> Result<(), ConfigError> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(ConfigError {
            field,
            value: f64::from(value),
            expected: "a finite number >= 0",
        })
    }
}

impl Config {
    /// The example 4 x M3508 / C620 chassis (`config/dji_m3508.toml`): 0.40 m x 0.36 m
    /// between wheel centres, 76 mm radius wheels, ESC ids 1-4, right side mirrored.
    #[must_use]
    pub fn dji_m3508_example() -> Self {
        Self {
            geometry: Geometry::Standard {
                lx: 0.20,
                ly: 0.18,
                wheel_radius: 0.076,
                forward_effectiveness: 1.0,
                lateral_effectiveness: 1.0,
                yaw_effectiveness: 1.0,
            },
            drive: Drive::Dji {
                model: EscModel::C620,
                esc_ids: [1, 2, 3, 4],
                gear_ratio: 3591.0 / 187.0,
                inverted: [false, true, false, true],
            },
            limits: Limits::default(),
            gains: Gains::default(),
            timing: Timing::default(),
            odometry: OdometryConfig::default(),
        }
    }

    /// The example 4-axis ODrive chassis (`config/odrive.toml`): nodes 0-3, 5:1 belt,
    /// 0.30 m x 0.25 m between wheel centres, 50 mm radius wheels.
    #[must_use]
    pub fn odrive_example() -> Self {
        Self {
            geometry: Geometry::Standard {
                lx: 0.15,
                ly: 0.125,
                wheel_radius: 0.05,
                forward_effectiveness: 1.0,
                lateral_effectiveness: 1.0,
                yaw_effectiveness: 1.0,
            },
            drive: Drive::Odrive {
                node_ids: [0, 1, 2, 3],
                gear_ratio: 5.0,
                inverted: [false, true, false, true],
                vel_ramp: false,
            },
            limits: Limits {
                max_wheel_speed: 60.0,
                ..Limits::default()
            },
            gains: Gains::default(),
            timing: Timing::default(),
            odometry: OdometryConfig::default(),
        }
    }

    /// The example CiA 402 chassis (`config/cia402.toml`): two dual-axis hub-motor drives
    /// (nodes 1 and 2, a ZLAC8015D-class drive per axle: target velocity in rpm, actual in
    /// 0.1 rpm), 0.50 m x 0.42 m between wheel centres, 100 mm radius wheels, a 250 Hz cycle.
    #[must_use]
    pub fn cia402_example() -> Self {
        Self {
            geometry: Geometry::Standard {
                lx: 0.25,
                ly: 0.21,
                wheel_radius: 0.1,
                forward_effectiveness: 1.0,
                lateral_effectiveness: 1.0,
                yaw_effectiveness: 1.0,
            },
            drive: Drive::Cia402(Cia402Drive {
                node_ids: [1, 1, 2, 2],
                axes: [1, 2, 1, 2],
                gear_ratio: 1.0,
                inverted: [false, true, false, true],
                target_rpm_per_unit: 1.0,
                actual_rpm_per_unit: 0.1,
                master_node: cia402_defaults::master_node(),
                heartbeat_ms: cia402_defaults::heartbeat_ms(),
                heartbeat_timeout_ms: cia402_defaults::heartbeat_timeout_ms(),
            }),
            limits: Limits {
                max_linear_speed: 1.5,
                max_angular_speed: 3.0,
                // Hub motors at 300 rpm: 31 rad/s.
                max_wheel_speed: 30.0,
                ..Limits::default()
            },
            gains: Gains::default(),
            timing: Timing {
                setpoint_hz: 250,
                ..Timing::default()
            },
            odometry: OdometryConfig::default(),
        }
    }

    /// The wheel maps for this geometry, with its effectiveness factors.
    ///
    /// # Errors
    /// The layout's [`GeometryError`] (non-finite, non-positive radius, singular, a factor
    /// out of range).
    pub fn kinematics(&self) -> Result<MecanumKinematics<f32, 4>, GeometryError> {
        self.kinematics_with(self.geometry.effectiveness())
    }

    /// The wheel maps for this geometry with the given factors.
    fn kinematics_with(
        &self,
        effectiveness: Effectiveness<f32>,
    ) -> Result<MecanumKinematics<f32, 4>, GeometryError> {
        match self.geometry {
            Geometry::Standard {
                lx,
                ly,
                wheel_radius,
                ..
            } => {
                MecanumKinematics::standard_with_effectiveness(lx, ly, wheel_radius, effectiveness)
            }
            Geometry::General { wheels, .. } => MecanumKinematics::with_effectiveness(
                wheels
                    .map(|w| WheelGeometry::new(w.x, w.y, w.axle_angle, w.roller_angle, w.radius)),
                effectiveness,
            ),
        }
    }

    /// Checks every field; the first error found names the field and the value.
    ///
    /// # Errors
    /// [`ConfigError`] for the first field out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        match self.geometry {
            Geometry::Standard {
                lx,
                ly,
                wheel_radius,
                ..
            } => {
                non_negative("geometry.lx", lx)?;
                non_negative("geometry.ly", ly)?;
                positive("geometry.wheel_radius", wheel_radius)?;
            }
            Geometry::General { wheels, .. } => {
                for w in &wheels {
                    positive("geometry.wheels[].radius", w.radius)?;
                }
            }
        }
        let k = self.geometry.effectiveness();
        for (field, value) in EFFECTIVENESS_KEYS.into_iter().zip(k.as_array()) {
            check_effectiveness(field, value)?;
        }
        if let Err(e) = self.kinematics() {
            // A factor in range can still scale the map out of f32 (a tiny one: 1e-38):
            // name it if the layout alone fits.
            if let GeometryError::Unrepresentable { .. } = e
                && self.kinematics_with(Effectiveness::ideal()).is_ok()
            {
                let (field, value) = EFFECTIVENESS_KEYS
                    .into_iter()
                    .zip(k.as_array())
                    .fold(("", f32::INFINITY), |m, c| if c.1 < m.1 { c } else { m });
                return Err(ConfigError {
                    field,
                    value: f64::from(value),
                    expected: "a factor whose scaled wheel map fits f32 (a tiny one does not)",
                });
            }
            return Err(geometry_error(e));
        }

        match self.drive {
            Drive::Dji {
                esc_ids,
                gear_ratio,
                ..
            } => {
                for (i, &id) in esc_ids.iter().enumerate() {
                    if EscId::new(id).is_none() {
                        return Err(ConfigError {
                            field: field_at("drive.esc_ids", i),
                            value: f64::from(id),
                            expected: "an ESC id in 1..=8",
                        });
                    }
                    if esc_ids[..i].contains(&id) {
                        return Err(ConfigError {
                            field: field_at("drive.esc_ids", i),
                            value: f64::from(id),
                            expected: "a different id on every wheel",
                        });
                    }
                }
                check_gear_ratio(gear_ratio)?;
            }
            Drive::Odrive {
                node_ids,
                gear_ratio,
                ..
            } => {
                for (i, &id) in node_ids.iter().enumerate() {
                    if NodeId::new(id).is_none() {
                        return Err(ConfigError {
                            field: field_at("drive.node_ids", i),
                            value: f64::from(id),
                            expected: "a node id in 0..=63",
                        });
                    }
                    // Node n owns the ids n << 5 ..= n << 5 | 0x1F; node 24's are the robot
                    // protocol's block (its heartbeat 0x301 would be read as a TWIST_CMD).
                    let first = u16::from(id) << 5;
                    if first <= robot::layout::ID_LAST && robot::layout::ID_FIRST <= first | 0x1F {
                        return Err(ConfigError {
                            field: field_at("drive.node_ids", i),
                            value: f64::from(id),
                            expected: "a node id whose CAN ids (node << 5 | cmd) are not the \
                                       robot protocol's 0x300..=0x31F (any but 24)",
                        });
                    }
                    if node_ids[..i].contains(&id) {
                        return Err(ConfigError {
                            field: field_at("drive.node_ids", i),
                            value: f64::from(id),
                            expected: "a different id on every wheel",
                        });
                    }
                }
                check_gear_ratio(gear_ratio)?;
            }
            Drive::Cia402(ref drive) => drive.check(self.timing.control_hz)?,
        }

        let l = &self.limits;
        positive("limits.max_linear_speed", l.max_linear_speed)?;
        positive("limits.max_angular_speed", l.max_angular_speed)?;
        positive("limits.max_linear_accel", l.max_linear_accel)?;
        positive("limits.max_angular_accel", l.max_angular_accel)?;
        positive_or_inf("limits.stop_linear_decel", l.stop_linear_decel)?;
        positive_or_inf("limits.stop_angular_decel", l.stop_angular_decel)?;
        positive("limits.max_wheel_speed", l.max_wheel_speed)?;
        positive("limits.max_current", l.max_current)?;
        if let Drive::Dji { model, .. } = self.drive
            && l.max_current > model.max_amps()
        {
            return Err(ConfigError {
                field: "limits.max_current",
                value: f64::from(l.max_current),
                expected: "at most the ESC's range (20 A for the C620, 10 A for the C610)",
            });
        }

        let g = &self.gains;
        non_negative("gains.kp", g.kp)?;
        non_negative("gains.ki", g.ki)?;
        non_negative("gains.kv", g.kv)?;

        let t = &self.timing;
        if !(10..=10_000).contains(&t.control_hz) {
            return Err(ConfigError {
                field: "timing.control_hz",
                value: f64::from(t.control_hz),
                expected: "a rate in 10..=10000 Hz",
            });
        }
        for (field, hz) in [
            ("timing.odometry_hz", t.odometry_hz),
            ("timing.status_hz", t.status_hz),
            ("timing.setpoint_hz", t.setpoint_hz),
        ] {
            if hz == 0 || hz > t.control_hz || !t.control_hz.is_multiple_of(hz) {
                return Err(ConfigError {
                    field,
                    value: f64::from(hz),
                    expected: "a rate > 0 that divides timing.control_hz",
                });
            }
        }
        if t.command_timeout_ms == 0 || t.command_timeout_ms > 60_000 {
            return Err(ConfigError {
                field: "timing.command_timeout_ms",
                value: f64::from(t.command_timeout_ms),
                expected: "a timeout in 1..=60000 ms",
            });
        }
        if t.boot_timeout_ms == 0 || t.boot_timeout_ms > 600_000 {
            return Err(ConfigError {
                field: "timing.boot_timeout_ms",
                value: f64::from(t.boot_timeout_ms),
                expected: "a timeout in 1..=600000 ms",
            });
        }
        if !(2..=1000).contains(&t.stale_periods) {
            return Err(ConfigError {
                field: "timing.stale_periods",
                value: f64::from(t.stale_periods),
                expected: "a count in 2..=1000",
            });
        }

        let o = &self.odometry;
        if !(1..=10_000).contains(&o.gyro_timeout_ms) {
            return Err(ConfigError {
                field: "odometry.gyro_timeout_ms",
                value: f64::from(o.gyro_timeout_ms),
                expected: "a timeout in 1..=10000 ms (silence of IMU_YAW_RATE after which the \
                           wheels give the heading)",
            });
        }
        if o.gyro_standstill_ms > 60_000 {
            return Err(ConfigError {
                field: "odometry.gyro_standstill_ms",
                value: f64::from(o.gyro_standstill_ms),
                expected: "a time in 0..=60000 ms (standing still before the gyro bias is \
                           learned)",
            });
        }
        if !(1..=10_000).contains(&o.pod_timeout_ms) {
            return Err(ConfigError {
                field: "odometry.pod_timeout_ms",
                value: f64::from(o.pod_timeout_ms),
                expected: "a timeout in 1..=10000 ms (silence of POD_COUNTS after which the \
                           wheels give the odometry)",
            });
        }
        if o.source == OdometryMode::Pods2Gyro && o.heading_source != HeadingMode::Gyro {
            return Err(ConfigError {
                field: "odometry.heading_source",
                value: 0.0,
                expected: "\"gyro\" with odometry.source = \"pods2_gyro\" (two pods cannot tell \
                           a rotation; the gyro gives it)",
            });
        }
        pods::localizer(o.source, &o.pods)?;
        Ok(())
    }
}

fn geometry_error(e: GeometryError) -> ConfigError {
    match e {
        GeometryError::NonFinite { wheel, .. } => ConfigError {
            field: field_at("geometry.wheels", wheel),
            value: f64::NAN,
            expected: "finite geometry values",
        },
        GeometryError::NonPositiveRadius { wheel, radius } => ConfigError {
            field: field_at("geometry.wheels.radius", wheel),
            value: radius,
            expected: "a radius > 0",
        },
        GeometryError::RollerParallelToAxle {
            wheel,
            roller_angle,
        } => ConfigError {
            field: field_at("geometry.wheels.roller_angle", wheel),
            value: roller_angle,
            expected: "a roller angle not parallel to the axle",
        },
        GeometryError::Singular { condition } => ConfigError {
            field: "geometry",
            value: condition,
            expected: "a layout whose roller axes are neither concurrent nor parallel (value: condition number)",
        },
        GeometryError::NegativeDistance { field, value } => ConfigError {
            field: if field == "lx" {
                "geometry.lx"
            } else {
                "geometry.ly"
            },
            value,
            expected: "a distance >= 0",
        },
        GeometryError::Unrepresentable { deviation } => ConfigError {
            field: "geometry",
            value: deviation,
            expected: "lengths and radius whose wheel map fits f32 (value: relative deviation; \
                       check the units)",
        },
        GeometryError::Effectiveness { axis, value } => ConfigError {
            field: match axis {
                kinematics::Axis::Forward => EFFECTIVENESS_KEYS[0],
                kinematics::Axis::Lateral => EFFECTIVENESS_KEYS[1],
                kinematics::Axis::Yaw => EFFECTIVENESS_KEYS[2],
            },
            value,
            expected: "a factor in (0, 1.5]",
        },
        _ => ConfigError {
            field: "geometry",
            value: f64::NAN,
            expected: "a valid layout",
        },
    }
}

/// `"prefix[i] (WHEEL)"` as a static string, for the four wheel indices.
fn field_at(prefix: &'static str, i: usize) -> &'static str {
    macro_rules! table {
        ($($p:literal),*) => {
            match prefix {
                $($p => [
                    concat!($p, "[0] (FL)"),
                    concat!($p, "[1] (FR)"),
                    concat!($p, "[2] (RL)"),
                    concat!($p, "[3] (RR)"),
                ][i.min(3)],)*
                _ => prefix,
            }
        };
    }
    table!(
        "drive.esc_ids",
        "drive.node_ids",
        "drive.axes",
        "geometry.wheels",
        "geometry.wheels.radius",
        "geometry.wheels.roller_angle"
    )
}

#[cfg(feature = "std")]
mod load {
    use std::boxed::Box;
    use std::path::{Path, PathBuf};
    use std::string::String;

    use super::{Config, ConfigError};
    use crate::input::TomlError;

    /// Why a configuration file could not be used.
    #[derive(Debug, thiserror::Error)]
    pub enum LoadError {
        /// The file could not be read.
        #[error("cannot read {path}: {source}")]
        Io {
            /// The file.
            path: PathBuf,
            /// The OS error.
            source: std::io::Error,
        },
        /// The TOML is malformed, has an unknown or missing field, or a value of the wrong type.
        /// (The message quotes the line and names the key: [`TomlError`]; not the error's
        /// `source`, whose text would show the line raw.)
        #[error("{path}: {parse}")]
        Toml {
            /// The file (or `<string>`).
            path: PathBuf,
            /// The parser's error, with line and column, and the key it points at.
            parse: Box<TomlError>,
        },
        /// A value is out of range.
        #[error("{path}: {source}")]
        Invalid {
            /// The file (or `<string>`).
            path: PathBuf,
            /// Which field and value.
            source: ConfigError,
        },
    }

    impl Config {
        /// Parses and validates a TOML configuration.
        ///
        /// # Errors
        /// [`LoadError::Toml`] for syntax, unknown fields and wrong types (with line, column
        /// and key), [`LoadError::Invalid`] naming the field and value out of range.
        pub fn from_toml_str(text: &str) -> Result<Self, LoadError> {
            Self::parse(text, Path::new("<string>"))
        }

        /// Reads, parses and validates a TOML configuration file.
        ///
        /// # Errors
        /// As [`from_toml_str`](Self::from_toml_str), plus [`LoadError::Io`].
        pub fn from_toml_file(path: &Path) -> Result<Self, LoadError> {
            let text = crate::input::read_toml_text(path).map_err(|source| LoadError::Io {
                path: path.to_path_buf(),
                source,
            })?;
            Self::parse(&text, path)
        }

        /// The configuration as TOML.
        #[must_use]
        pub fn to_toml_string(&self) -> String {
            // Every field is a number, bool, string, array or table: serialisation cannot fail.
            toml::to_string_pretty(self).unwrap_or_default()
        }

        fn parse(text: &str, path: &Path) -> Result<Self, LoadError> {
            let config: Self = toml::from_str(text).map_err(|parse| LoadError::Toml {
                path: path.to_path_buf(),
                parse: Box::new(TomlError::new(text, parse)),
            })?;
            config.validate().map_err(|source| LoadError::Invalid {
                path: path.to_path_buf(),
                source,
            })?;
            Ok(config)
        }
    }
}

#[cfg(feature = "std")]
pub use load::LoadError;
