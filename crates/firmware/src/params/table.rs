//! The parameter table: one entry per field, in object order. Ranges are the tuning bounds a
//! UI offers; `Config::validate` still decides (`> 0`, rates that divide `control_hz`, the
//! ESC's current range).

use core::f64::consts::TAU;

use super::Change::{Disabled, Fixed, Live};
use super::ParamType::{Boolean, Real32, Unsigned8, Unsigned32};
use super::{Param, pod, set_pod};
use crate::config::{Drive, Geometry, HeadingMode, OdometryMode, PODS_MAX};

/// A plain `f32` or `u32` field of `Config` at the path `$($f).+`.
macro_rules! field {
    ($name:literal, $index:literal, $sub:literal, Real32, $unit:literal, $low:expr, $high:expr,
     $change:ident, $doc:literal, $($f:ident).+) => {
        Param {
            name: $name, index: $index, sub: $sub, ty: Real32, unit: $unit, low: $low,
            high: $high, change: $change, doc: $doc,
            get: |c| Some(c.$($f).+.to_bits()),
            set: |c, v| { c.$($f).+ = f32::from_bits(v); true },
        }
    };
    ($name:literal, $index:literal, $sub:literal, Unsigned32, $unit:literal, $low:expr,
     $high:expr, $change:ident, $doc:literal, $($f:ident).+) => {
        Param {
            name: $name, index: $index, sub: $sub, ty: Unsigned32, unit: $unit, low: $low,
            high: $high, change: $change, doc: $doc,
            get: |c| Some(c.$($f).+),
            set: |c, v| { c.$($f).+ = v; true },
        }
    };
}

/// A field of the standard layout (`Geometry::Standard`).
macro_rules! standard {
    ($name:literal, $sub:literal, $f:ident, $high:expr, $doc:literal) => {
        Param {
            name: $name,
            index: 0x2000,
            sub: $sub,
            ty: Real32,
            unit: "m",
            low: 0.0,
            high: $high,
            change: Disabled,
            doc: $doc,
            get: |c| match c.geometry {
                Geometry::Standard { $f, .. } => Some($f.to_bits()),
                Geometry::General { .. } => None,
            },
            set: |c, v| match &mut c.geometry {
                Geometry::Standard { $f, .. } => {
                    *$f = f32::from_bits(v);
                    true
                }
                Geometry::General { .. } => false,
            },
        }
    };
}

/// An effectiveness factor, in either layout.
macro_rules! effectiveness {
    ($name:literal, $sub:literal, $f:ident, $doc:literal) => {
        Param {
            name: $name,
            index: 0x2000,
            sub: $sub,
            ty: Real32,
            unit: "",
            low: 0.0,
            high: kinematics::MAX_EFFECTIVENESS,
            change: Disabled,
            doc: $doc,
            get: |c| match c.geometry {
                Geometry::Standard { $f, .. } | Geometry::General { $f, .. } => Some($f.to_bits()),
            },
            set: |c, v| match &mut c.geometry {
                Geometry::Standard { $f, .. } | Geometry::General { $f, .. } => {
                    *$f = f32::from_bits(v);
                    true
                }
            },
        }
    };
}

/// Field `$f` of wheel `$i` of the general layout (object 0x2010 + i).
macro_rules! wheel {
    ($i:literal, $index:literal, $sub:literal, $f:ident, $unit:literal, $low:expr, $high:expr) => {
        Param {
            name: concat!("geometry.wheels[", $i, "].", stringify!($f)),
            index: $index,
            sub: $sub,
            ty: Real32,
            unit: $unit,
            low: $low,
            high: $high,
            change: Disabled,
            doc: concat!(
                "Wheel ",
                $i,
                " (FL, FR, RL, RR) of the general layout: ",
                stringify!($f)
            ),
            get: |c| match c.geometry {
                Geometry::General { wheels, .. } => Some(wheels[$i].$f.to_bits()),
                Geometry::Standard { .. } => None,
            },
            set: |c, v| match &mut c.geometry {
                Geometry::General { wheels, .. } => {
                    wheels[$i].$f = f32::from_bits(v);
                    true
                }
                Geometry::Standard { .. } => false,
            },
        }
    };
}

/// Field `$f` of pod `$i` (object 0x2020 + i).
macro_rules! pod_field {
    ($i:literal, $index:literal, $sub:literal, Real32, $f:ident, $unit:literal, $low:expr,
     $high:expr, $doc:literal) => {
        Param {
            name: concat!("odometry.pods[", $i, "].", stringify!($f)),
            index: $index,
            sub: $sub,
            ty: Real32,
            unit: $unit,
            low: $low,
            high: $high,
            change: Disabled,
            doc: $doc,
            get: |c| pod(c, $i).map(|p| p.$f.to_bits()),
            set: |c, v| set_pod(c, $i, |p| p.$f = f32::from_bits(v)),
        }
    };
    ($i:literal, $index:literal, $sub:literal, Unsigned32, $f:ident, $unit:literal, $low:expr,
     $high:expr, $doc:literal) => {
        Param {
            name: concat!("odometry.pods[", $i, "].", stringify!($f)),
            index: $index,
            sub: $sub,
            ty: Unsigned32,
            unit: $unit,
            low: $low,
            high: $high,
            change: Disabled,
            doc: $doc,
            get: |c| pod(c, $i).map(|p| p.$f),
            set: |c, v| set_pod(c, $i, |p| p.$f = v),
        }
    };
}

/// The five fields of pod `$i`.
macro_rules! pod {
    ($i:literal, $index:literal) => {
        [
            pod_field!(
                $i,
                $index,
                1,
                Real32,
                x,
                "m",
                -5.0,
                5.0,
                "Contact point, forward"
            ),
            pod_field!(
                $i,
                $index,
                2,
                Real32,
                y,
                "m",
                -5.0,
                5.0,
                "Contact point, left"
            ),
            pod_field!(
                $i,
                $index,
                3,
                Real32,
                direction_deg,
                "deg",
                -360.0,
                360.0,
                "Direction in which its count increases, CCW from the body's x axis"
            ),
            pod_field!(
                $i,
                $index,
                4,
                Real32,
                radius,
                "m",
                0.0,
                1.0,
                "Omni wheel radius"
            ),
            pod_field!(
                $i,
                $index,
                5,
                Unsigned32,
                counts_per_turn,
                "",
                1.0,
                1e6,
                "Encoder counts per turn (quadrature edges)"
            ),
        ]
    };
}

/// The five fields of wheel `$i`.
macro_rules! wheels {
    ($i:literal, $index:literal) => {
        [
            wheel!($i, $index, 1, x, "m", -5.0, 5.0),
            wheel!($i, $index, 2, y, "m", -5.0, 5.0),
            wheel!($i, $index, 3, axle_angle, "rad", -TAU, TAU),
            wheel!($i, $index, 4, roller_angle, "rad", -TAU, TAU),
            wheel!($i, $index, 5, radius, "m", 0.0, 1.0),
        ]
    };
}

/// A read-only field of the drive.
macro_rules! drive {
    ($name:literal, $sub:literal, $ty:ident, $unit:literal, $low:expr, $high:expr, $doc:literal,
     $get:expr) => {
        Param {
            name: $name,
            index: 0x2005,
            sub: $sub,
            ty: $ty,
            unit: $unit,
            low: $low,
            high: $high,
            change: Fixed,
            doc: $doc,
            get: $get,
            set: |_, _| false,
        }
    };
}

/// The drive's common fields: protocol number, gear ratio, the four ids, the inversion bits.
fn drive_fields(d: Drive) -> (u32, f32, [u8; 4], [bool; 4]) {
    match d {
        Drive::Dji {
            esc_ids,
            gear_ratio,
            inverted,
            ..
        } => (0, gear_ratio, esc_ids, inverted),
        Drive::Odrive {
            node_ids,
            gear_ratio,
            inverted,
            ..
        } => (1, gear_ratio, node_ids, inverted),
        Drive::Cia402(c) => (2, c.gear_ratio, c.node_ids, c.inverted),
    }
}

/// The drive's wheel `i` id.
fn drive_id(c: &crate::Config, i: usize) -> Option<u32> {
    Some(u32::from(drive_fields(c.drive).2[i]))
}

/// The parameters but the wheels and the pods: geometry, limits, gains, timing, odometry, drive.
#[rustfmt::skip]
const HEAD: [Param; 38] = [
    standard!("geometry.lx", 1, lx, 5.0, "Centre to wheel centres along x (standard layout)"),
    standard!("geometry.ly", 2, ly, 5.0, "Centre to wheel centres along y (standard layout)"),
    standard!("geometry.wheel_radius", 3, wheel_radius, 1.0, "Wheel radius (standard layout)"),
    effectiveness!("geometry.forward_effectiveness", 4, forward_effectiveness,
        "Fraction of the wheel-implied forward motion the robot makes (1 = no slip)"),
    effectiveness!("geometry.lateral_effectiveness", 5, lateral_effectiveness,
        "Fraction of the wheel-implied lateral motion the robot makes"),
    effectiveness!("geometry.yaw_effectiveness", 6, yaw_effectiveness,
        "Fraction of the wheel-implied yaw motion the robot makes"),
    field!("limits.max_linear_speed", 0x2001, 1, Real32, "m/s", 0.0, 20.0, Live,
        "Largest accepted linear speed command", limits.max_linear_speed),
    field!("limits.max_angular_speed", 0x2001, 2, Real32, "rad/s", 0.0, 50.0, Live,
        "Largest accepted yaw rate command", limits.max_angular_speed),
    field!("limits.max_linear_accel", 0x2001, 3, Real32, "m/s^2", 0.0, 1000.0, Live,
        "Linear acceleration limit of the commanded velocity", limits.max_linear_accel),
    field!("limits.max_angular_accel", 0x2001, 4, Real32, "rad/s^2", 0.0, 1000.0, Live,
        "Yaw acceleration limit", limits.max_angular_accel),
    field!("limits.stop_linear_decel", 0x2001, 5, Real32, "m/s^2", 0.0, f64::INFINITY, Live,
        "Linear deceleration after the command watchdog (inf: stop at once)",
        limits.stop_linear_decel),
    field!("limits.stop_angular_decel", 0x2001, 6, Real32, "rad/s^2", 0.0, f64::INFINITY, Live,
        "Yaw deceleration after the command watchdog (inf: stop at once)",
        limits.stop_angular_decel),
    field!("limits.max_wheel_speed", 0x2001, 7, Real32, "rad/s", 0.0, 1000.0, Disabled,
        "Largest wheel speed; setpoints are desaturated to it (ODrive: set at start)",
        limits.max_wheel_speed),
    field!("limits.max_current", 0x2001, 8, Real32, "A", 0.0, 100.0, Live,
        "Largest motor current the velocity loop commands (current-mode drives)",
        limits.max_current),
    field!("gains.kp", 0x2002, 1, Real32, "A/(rad/s)", 0.0, 100.0, Live,
        "Wheel velocity PI: proportional gain", gains.kp),
    field!("gains.ki", 0x2002, 2, Real32, "A/rad", 0.0, 10_000.0, Live,
        "Wheel velocity PI: integral gain", gains.ki),
    field!("gains.kv", 0x2002, 3, Real32, "A/(rad/s)", 0.0, 100.0, Live,
        "Wheel velocity feed-forward", gains.kv),
    field!("timing.control_hz", 0x2003, 1, Unsigned32, "Hz", 10.0, 10_000.0, Fixed,
        "Control loop rate", timing.control_hz),
    field!("timing.odometry_hz", 0x2003, 2, Unsigned32, "Hz", 1.0, 10_000.0, Disabled,
        "Odometry frames rate (divides control_hz)", timing.odometry_hz),
    field!("timing.status_hz", 0x2003, 3, Unsigned32, "Hz", 1.0, 10_000.0, Disabled,
        "Status and heartbeat rate (divides control_hz)", timing.status_hz),
    field!("timing.setpoint_hz", 0x2003, 4, Unsigned32, "Hz", 1.0, 10_000.0, Fixed,
        "Setpoint rate to velocity-mode drives, the CiA 402 SYNC", timing.setpoint_hz),
    field!("timing.command_timeout_ms", 0x2003, 5, Unsigned32, "ms", 1.0, 60_000.0, Live,
        "Command watchdog", timing.command_timeout_ms),
    field!("timing.boot_timeout_ms", 0x2003, 6, Unsigned32, "ms", 1.0, 600_000.0, Disabled,
        "A motor never heard from this long faults as missing", timing.boot_timeout_ms),
    field!("timing.stale_periods", 0x2003, 7, Unsigned32, "", 2.0, 1000.0, Disabled,
        "Feedback older than this many periods faults as stale", timing.stale_periods),
    Param {
        name: "odometry.heading_source", index: 0x2004, sub: 1, ty: Unsigned8, unit: "",
        low: 0.0, high: 1.0, change: Disabled, doc: "Heading from: 0 wheels, 1 gyro",
        get: |c| Some(c.odometry.heading_source as u32),
        set: |c, v| {
            c.odometry.heading_source = if v == 0 { HeadingMode::Wheels } else { HeadingMode::Gyro };
            true
        },
    },
    field!("odometry.gyro_timeout_ms", 0x2004, 2, Unsigned32, "ms", 1.0, 10_000.0, Live,
        "Gyro silence after which the wheels give the heading", odometry.gyro_timeout_ms),
    field!("odometry.gyro_standstill_ms", 0x2004, 3, Unsigned32, "ms", 0.0, 60_000.0, Live,
        "Standing still before the gyro bias is learned", odometry.gyro_standstill_ms),
    Param {
        name: "odometry.gyro_bias_estimation", index: 0x2004, sub: 4, ty: Boolean, unit: "",
        low: 0.0, high: 1.0, change: Disabled, doc: "Learn the gyro's bias at standstill",
        get: |c| Some(u32::from(c.odometry.gyro_bias_estimation)),
        set: |c, v| { c.odometry.gyro_bias_estimation = v != 0; true },
    },
    Param {
        name: "odometry.source", index: 0x2004, sub: 5, ty: Unsigned8, unit: "", low: 0.0,
        high: 2.0, change: Disabled, doc: "Odometry from: 0 wheels, 1 pods2_gyro, 2 pods3",
        get: |c| Some(c.odometry.source as u32),
        set: |c, v| {
            c.odometry.source = match v {
                0 => OdometryMode::Wheels,
                1 => OdometryMode::Pods2Gyro,
                _ => OdometryMode::Pods3,
            };
            true
        },
    },
    field!("odometry.pod_timeout_ms", 0x2004, 6, Unsigned32, "ms", 1.0, 10_000.0, Live,
        "Pod silence after which the wheels give the odometry", odometry.pod_timeout_ms),
    Param {
        name: "odometry.pod_count", index: 0x2004, sub: 7, ty: Unsigned8, unit: "", low: 0.0,
        high: PODS_MAX as f64, change: Fixed, doc: "Tracking pods configured",
        get: |c| Some(c.odometry.pods.len() as u32), set: |_, _| false,
    },
    drive!("drive.protocol", 1, Unsigned8, "", 0.0, 2.0, "Drive protocol: 0 dji, 1 odrive, 2 cia402",
        |c| Some(drive_fields(c.drive).0)),
    drive!("drive.gear_ratio", 2, Real32, "", 0.01, 1000.0, "Motor turns per wheel turn",
        |c| Some(drive_fields(c.drive).1.to_bits())),
    drive!("drive.ids[0]", 3, Unsigned8, "", 0.0, 127.0, "ESC id or node id of wheel 0 (FL)",
        |c| drive_id(c, 0)),
    drive!("drive.ids[1]", 4, Unsigned8, "", 0.0, 127.0, "ESC id or node id of wheel 1 (FR)",
        |c| drive_id(c, 1)),
    drive!("drive.ids[2]", 5, Unsigned8, "", 0.0, 127.0, "ESC id or node id of wheel 2 (RL)",
        |c| drive_id(c, 2)),
    drive!("drive.ids[3]", 6, Unsigned8, "", 0.0, 127.0, "ESC id or node id of wheel 3 (RR)",
        |c| drive_id(c, 3)),
    drive!("drive.inverted", 7, Unsigned8, "", 0.0, 15.0,
        "Inverted wheels, bit i for wheel i", |c| {
            let inverted = drive_fields(c.drive).3;
            Some((0..4).filter(|&i| inverted[i]).map(|i| 1 << i).sum())
        }),
];

/// The general layout's wheels (objects 0x2010..=0x2013).
#[rustfmt::skip]
const WHEELS: [[Param; 5]; 4] =
    [wheels!(0, 0x2010), wheels!(1, 0x2011), wheels!(2, 0x2012), wheels!(3, 0x2013)];

/// The pods (objects 0x2020..=0x2022).
#[rustfmt::skip]
const PODS: [[Param; 5]; PODS_MAX] = [pod!(0, 0x2020), pod!(1, 0x2021), pod!(2, 0x2022)];

/// Every parameter, in object order.
pub const PARAMS: [Param; 73] = join(&[
    &HEAD, &WHEELS[0], &WHEELS[1], &WHEELS[2], &WHEELS[3], &PODS[0], &PODS[1], &PODS[2],
]);

/// `parts` one after the other (`N` is their total length).
const fn join<const N: usize>(parts: &[&[Param]]) -> [Param; N] {
    let mut out = [parts[0][0]; N];
    let (mut k, mut i) = (0, 0);
    while i < parts.len() {
        let mut j = 0;
        while j < parts[i].len() {
            out[k] = parts[i][j];
            k += 1;
            j += 1;
        }
        i += 1;
    }
    assert!(
        k == N,
        "PARAMS: the parts' lengths add up to another length"
    );
    out
}
