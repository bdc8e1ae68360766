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

use kinematics::{Effectiveness, GeometryError, MecanumKinematics, WheelGeometry};

use crate::protocol::dji::EscModel;

mod cia402;
mod encoding;
mod examples;
#[cfg(feature = "std")]
mod load;
mod pods;
#[cfg(feature = "serde")]
mod tagged;
mod validate;
pub use cia402::{Cia402Drive, defaults as cia402_defaults};
pub use encoding::ENCODED_LEN;
#[cfg(feature = "std")]
pub use load::LoadError;
pub use pods::{OdometryMode, PODS_MAX, PodConfig, Pods};
pub(crate) use pods::{PodSolve, localizer as pod_localizer};
pub use validate::{ConfigError, EFFECTIVENESS_KEYS, GEAR_RATIO_RANGE};
use validate::{check_gear_ratio, field_at, positive};

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

impl Config {
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
}
