//! [`Config::validate`]: every field checked, the first one out of range named with its
//! value ([`ConfigError`]).

use core::fmt;
use core::ops::RangeInclusive;

use kinematics::{Effectiveness, GeometryError};

use super::{
    Config, Drive, Gains, Geometry, HeadingMode, Limits, OdometryConfig, OdometryMode, Timing, pods,
};
use crate::protocol::dji::EscId;
use crate::protocol::odrive::NodeId;
use crate::protocol::robot;

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

/// `Ok` if `ok`, else the error naming `field`, its `value` and what is `expected`.
fn require(
    ok: bool,
    field: &'static str,
    value: impl Into<f64>,
    expected: &'static str,
) -> Result<(), ConfigError> {
    if ok {
        Ok(())
    } else {
        Err(ConfigError {
            field,
            value: value.into(),
            expected,
        })
    }
}

pub(super) fn positive(field: &'static str, value: f32) -> Result<(), ConfigError> {
    let ok = value.is_finite() && value > 0.0;
    require(ok, field, value, "a finite number > 0")
}

/// A gear ratio (motor turns per wheel turn): within [`GEAR_RATIO_RANGE`], so that every
/// conversion derived from it (counts or turns to wheel radians) is finite and nonzero.
pub(super) fn check_gear_ratio(value: f32) -> Result<(), ConfigError> {
    require(
        GEAR_RATIO_RANGE.contains(&value),
        "drive.gear_ratio",
        value,
        "a ratio in 0.01..=1000 (motor turns per wheel turn)",
    )
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
    require(
        in_range,
        field,
        value,
        "a factor in (0, 1.5]: the fraction of the wheel-implied motion the robot makes along \
         that axis (1 = no slip)",
    )
}

fn positive_or_inf(field: &'static str, value: f32) -> Result<(), ConfigError> {
    require(value > 0.0, field, value, "a number > 0 (inf allowed)")
}

fn non_negative(field: &'static str, value: f32) -> Result<(), ConfigError> {
    let ok = value.is_finite() && value >= 0.0;
    require(ok, field, value, "a finite number >= 0")
}

impl Config {
    /// Checks every field; the first error found names the field and the value.
    ///
    /// # Errors
    /// [`ConfigError`] for the first field out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.check_geometry()?;
        self.check_drive()?;
        check_limits(&self.limits, self.drive)?;
        check_gains(&self.gains)?;
        check_timing(&self.timing)?;
        check_odometry(&self.odometry)
    }

    /// The layout's numbers, the effectiveness factors, and the wheel maps they make.
    fn check_geometry(&self) -> Result<(), ConfigError> {
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
        Ok(())
    }

    /// The drive's ids (valid, and one a wheel) and gear ratio; CiA 402's own checks.
    fn check_drive(&self) -> Result<(), ConfigError> {
        match self.drive {
            Drive::Dji {
                esc_ids,
                gear_ratio,
                ..
            } => {
                wheel_ids("drive.esc_ids", esc_ids, |id| {
                    EscId::new(id).map(|_| ()).ok_or("an ESC id in 1..=8")
                })?;
                check_gear_ratio(gear_ratio)
            }
            Drive::Odrive {
                node_ids,
                gear_ratio,
                ..
            } => {
                wheel_ids("drive.node_ids", node_ids, check_odrive_node)?;
                check_gear_ratio(gear_ratio)
            }
            Drive::Cia402(ref drive) => drive.check(self.timing.control_hz),
        }
    }
}

/// Each wheel's id in `ids`: acceptable to `check` (else its `Err` is what is expected), and
/// none the same as an earlier wheel's.
fn wheel_ids(
    prefix: &'static str,
    ids: [u8; 4],
    check: impl Fn(u8) -> Result<(), &'static str>,
) -> Result<(), ConfigError> {
    for (i, &id) in ids.iter().enumerate() {
        let refused = |expected| ConfigError {
            field: field_at(prefix, i),
            value: f64::from(id),
            expected,
        };
        check(id).map_err(refused)?;
        if ids[..i].contains(&id) {
            return Err(refused("a different id on every wheel"));
        }
    }
    Ok(())
}

/// An ODrive node id: in 0..=63, and not one whose CAN ids are the robot protocol's.
fn check_odrive_node(id: u8) -> Result<(), &'static str> {
    if NodeId::new(id).is_none() {
        return Err("a node id in 0..=63");
    }
    // Node n owns the ids n << 5 ..= n << 5 | 0x1F; node 24's are the robot
    // protocol's block (its heartbeat 0x301 would be read as a TWIST_CMD).
    let first = u16::from(id) << 5;
    if first <= robot::layout::ID_LAST && robot::layout::ID_FIRST <= first | 0x1F {
        return Err("a node id whose CAN ids (node << 5 | cmd) are not the \
                    robot protocol's 0x300..=0x31F (any but 24)");
    }
    Ok(())
}

/// Speeds, accelerations and the current, within what the drive's ESCs can take.
fn check_limits(l: &Limits, drive: Drive) -> Result<(), ConfigError> {
    positive("limits.max_linear_speed", l.max_linear_speed)?;
    positive("limits.max_angular_speed", l.max_angular_speed)?;
    positive("limits.max_linear_accel", l.max_linear_accel)?;
    positive("limits.max_angular_accel", l.max_angular_accel)?;
    positive_or_inf("limits.stop_linear_decel", l.stop_linear_decel)?;
    positive_or_inf("limits.stop_angular_decel", l.stop_angular_decel)?;
    positive("limits.max_wheel_speed", l.max_wheel_speed)?;
    positive("limits.max_current", l.max_current)?;
    if let Drive::Dji { model, .. } = drive
        && l.max_current > model.max_amps()
    {
        return Err(ConfigError {
            field: "limits.max_current",
            value: f64::from(l.max_current),
            expected: "at most the ESC's range (20 A for the C620, 10 A for the C610)",
        });
    }
    Ok(())
}

fn check_gains(g: &Gains) -> Result<(), ConfigError> {
    non_negative("gains.kp", g.kp)?;
    non_negative("gains.ki", g.ki)?;
    non_negative("gains.kv", g.kv)
}

/// The control rate, the rates that divide it, and the timeouts.
fn check_timing(t: &Timing) -> Result<(), ConfigError> {
    in_range(
        "timing.control_hz",
        t.control_hz,
        10..=10_000,
        "a rate in 10..=10000 Hz",
    )?;
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
    in_range(
        "timing.command_timeout_ms",
        t.command_timeout_ms,
        1..=60_000,
        "a timeout in 1..=60000 ms",
    )?;
    in_range(
        "timing.boot_timeout_ms",
        t.boot_timeout_ms,
        1..=600_000,
        "a timeout in 1..=600000 ms",
    )?;
    in_range(
        "timing.stale_periods",
        t.stale_periods,
        2..=1000,
        "a count in 2..=1000",
    )
}

/// The gyro's and the pods' timeouts, the heading source their mode needs, and the pods.
fn check_odometry(o: &OdometryConfig) -> Result<(), ConfigError> {
    in_range(
        "odometry.gyro_timeout_ms",
        o.gyro_timeout_ms,
        1..=10_000,
        "a timeout in 1..=10000 ms (silence of IMU_YAW_RATE after which the \
         wheels give the heading)",
    )?;
    in_range(
        "odometry.gyro_standstill_ms",
        o.gyro_standstill_ms,
        0..=60_000,
        "a time in 0..=60000 ms (standing still before the gyro bias is \
         learned)",
    )?;
    in_range(
        "odometry.pod_timeout_ms",
        o.pod_timeout_ms,
        1..=10_000,
        "a timeout in 1..=10000 ms (silence of POD_COUNTS after which the \
         wheels give the odometry)",
    )?;
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

/// An integer setting within `range`.
fn in_range(
    field: &'static str,
    value: u32,
    range: RangeInclusive<u32>,
    expected: &'static str,
) -> Result<(), ConfigError> {
    require(range.contains(&value), field, value, expected)
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
pub(super) fn field_at(prefix: &'static str, i: usize) -> &'static str {
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
