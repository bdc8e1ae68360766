//! The table against the configuration: every field reads and writes back, the object map is
//! unique, each parameter is a field of its own, and each refusal names the parameter, the
//! value and the rule.

extern crate std;
use std::string::ToString;
use std::vec::Vec;

use super::*;
use crate::config::{Geometry, HeadingMode, OdometryMode, WheelConfig};

/// The DJI example with three pods (pods3 odometry).
fn with_pods() -> Config {
    let mut c = Config::dji_m3508_example();
    let pod = |x, y, direction_deg| PodConfig {
        x,
        y,
        direction_deg,
        radius: 0.024,
        counts_per_turn: 2000,
    };
    c.odometry.source = OdometryMode::Pods3;
    c.odometry.pods = Pods::new(&[
        pod(0.1, 0.15, 0.0),
        pod(0.1, -0.15, 0.0),
        pod(-0.1, 0.0, 90.0),
    ])
    .unwrap();
    c.validate().unwrap();
    c
}

/// The DJI example in the general layout (the standard layout's wheels written out).
fn general() -> Config {
    let mut c = Config::dji_m3508_example();
    let Geometry::Standard {
        lx,
        ly,
        wheel_radius,
        ..
    } = c.geometry
    else {
        unreachable!()
    };
    let (q, axle) = (core::f32::consts::FRAC_PI_4, core::f32::consts::FRAC_PI_2);
    let wheel = |x, y, roller_angle| WheelConfig {
        x,
        y,
        axle_angle: axle,
        roller_angle,
        radius: wheel_radius,
    };
    c.geometry = Geometry::General {
        wheels: [
            wheel(lx, ly, q),
            wheel(lx, -ly, -q),
            wheel(-lx, ly, -q),
            wheel(-lx, -ly, q),
        ],
        forward_effectiveness: 1.0,
        lateral_effectiveness: 1.0,
        yaw_effectiveness: 1.0,
    };
    c.validate().unwrap();
    c
}

fn configs() -> [Config; 5] {
    [
        Config::dji_m3508_example(),
        Config::odrive_example(),
        Config::cia402_example(),
        with_pods(),
        general(),
    ]
}

fn raw(name: &str, value: f64) -> u32 {
    find(name).unwrap().ty.from_f64(value).unwrap()
}

fn set(c: &Config, name: &str, value: f64, enabled: bool) -> Result<Config, Refusal> {
    find(name).unwrap().write(c, raw(name, value), enabled)
}

#[test]
fn names_and_objects_are_unique_and_in_object_order() {
    for (i, p) in PARAMS.iter().enumerate() {
        for q in &PARAMS[..i] {
            assert_ne!(p.name, q.name);
            assert!(
                (q.index, q.sub) < (p.index, p.sub),
                "{} after {}",
                p.name,
                q.name
            );
        }
        assert!(p.sub >= 1 && p.index >= 0x2000, "{}", p.name);
        assert!(p.low <= p.high, "{}", p.name);
        assert_eq!(at(p.index, p.sub).unwrap().name, p.name);
    }
    assert!(find("gains.nope").is_none() && at(0x2002, 9).is_none());
}

#[test]
fn every_field_reads_and_writes_back_unchanged_within_its_range() {
    for c in configs() {
        let mut present = 0;
        for p in &PARAMS {
            let Ok(v) = p.read(&c) else { continue };
            present += 1;
            let value = p.ty.to_f64(v);
            assert!(p.low <= value && value <= p.high, "{} = {value}", p.name);
            if p.change != Change::Fixed {
                assert_eq!(p.write(&c, v, false), Ok(c), "{}", p.name);
            }
        }
        // Geometry (3 or 20 + 3), limits, gains, timing, odometry, drive; and the pods.
        let layout = if matches!(c.geometry, Geometry::Standard { .. }) {
            3
        } else {
            20
        };
        let pods = 5 * c.odometry.pods.len();
        assert_eq!(present, layout + 3 + 8 + 3 + 7 + 7 + 7 + pods);
    }
}

/// Each writable parameter is a field of its own: a new value changes the configuration's
/// bytes and no other parameter's reading.
#[test]
fn each_parameter_is_its_own_field() {
    for c in configs() {
        for p in PARAMS.iter().filter(|p| p.change != Change::Fixed) {
            let Ok(v) = p.read(&c) else { continue };
            // Another value that validates: a nudge within the range, or the other enum value.
            let x = p.ty.to_f64(v);
            let candidates = match p.ty {
                ParamType::Real32 => [x * 0.9, x * 1.1, x + 0.01, x - 0.01, 1.0, 0.5],
                _ => [x + 1.0, x - 1.0, 0.0, 1.0, 2.0, x * 2.0],
            };
            let changed = candidates.iter().find_map(|&x| {
                let new = p.ty.from_f64(x).filter(|&n| n != v)?;
                p.write(&c, new, false).ok()
            });
            let Some(changed) = changed else {
                // The pod count fixes odometry.source for these configurations.
                assert!(
                    p.name == "odometry.source" || p.name == "odometry.heading_source",
                    "{}",
                    p.name
                );
                continue;
            };
            assert_ne!(changed.encode(), c.encode(), "{}", p.name);
            for q in PARAMS.iter().filter(|q| q.name != p.name) {
                assert_eq!(q.read(&changed), q.read(&c), "{} moved {}", p.name, q.name);
            }
        }
    }
}

#[test]
fn refusals_name_the_parameter_the_value_and_the_rule() {
    let c = Config::dji_m3508_example();
    let cases: [(&str, f64, bool, u32, &str); 7] = [
        (
            "gains.kp",
            150.0,
            false,
            0x0609_0031,
            "gains.kp = 150: above 100",
        ),
        (
            "gains.ki",
            -1.0,
            true,
            0x0609_0032,
            "gains.ki = -1: below 0",
        ),
        (
            "geometry.lx",
            0.2,
            true,
            0x0800_0022,
            "geometry.lx: changes only while disabled",
        ),
        (
            "timing.control_hz",
            500.0,
            false,
            0x0601_0002,
            "timing.control_hz: read-only over CAN",
        ),
        (
            "timing.status_hz",
            7.0,
            false,
            0x0609_0030,
            "timing.status_hz",
        ),
        (
            "limits.max_current",
            25.0,
            true,
            0x0609_0030,
            "limits.max_current",
        ),
        ("odometry.source", 2.0, false, 0x0609_0030, "odometry"),
    ];
    for (name, value, enabled, code, text) in cases {
        let e = set(&c, name, value, enabled).unwrap_err();
        assert_eq!(e.abort_code(), code, "{name}: {e}");
        assert!(e.to_string().starts_with(text), "{name}: {e}");
    }
    // The configuration's own rule, with its field and value.
    let e = set(&c, "timing.status_hz", 7.0, false).unwrap_err();
    assert!(e.to_string().contains("divides timing.control_hz"), "{e}");
    // NaN, and fields this configuration does not have.
    let kp = find("gains.kp").unwrap();
    let e = kp.write(&c, f32::NAN.to_bits(), false).unwrap_err();
    assert_eq!(
        (e.abort_code(), e.to_string().as_str()),
        (0x0609_0030, "gains.kp = NaN: not a valid value")
    );
    for (name, config) in [("geometry.lx", general()), ("odometry.pods[0].x", c)] {
        let p = find(name).unwrap();
        assert_eq!(p.read(&config), Err(Refusal::Absent { name }));
        assert_eq!(
            p.write(&config, 0, false).unwrap_err().abort_code(),
            0x0609_0011
        );
    }
}

#[test]
fn a_live_change_while_enabled_changes_that_field_and_the_id() {
    let c = Config::dji_m3508_example();
    let new = set(&c, "gains.kp", 1.5, true).unwrap();
    let mut want = c;
    want.gains.kp = 1.5;
    assert_eq!(new, want);
    assert_ne!(new.id(), c.id());
    // inf is a setting of the stop decelerations, and a live one.
    let new = set(&c, "limits.stop_linear_decel", f64::INFINITY, true).unwrap();
    assert!(new.limits.stop_linear_decel.is_infinite());
    // Disabled-only parameters change while disabled; the heading source with them.
    let gyro = set(&c, "odometry.heading_source", 1.0, false).unwrap();
    assert_eq!(gyro.odometry.heading_source, HeadingMode::Gyro);
}

#[test]
fn values_convert_only_when_the_type_holds_them() {
    use ParamType::*;
    assert_eq!(Unsigned8.from_f64(255.0), Some(255));
    let refused: Vec<_> = [
        (Unsigned8, 256.0),
        (Unsigned8, 1.5),
        (Unsigned32, -1.0),
        (Boolean, 2.0),
    ]
    .into_iter()
    .filter_map(|(t, v)| t.from_f64(v))
    .collect();
    assert!(refused.is_empty(), "{refused:?}");
    assert_eq!(Real32.from_f64(f64::NAN), None);
    assert_eq!(
        Real32.to_f64(Real32.from_f64(1.2).unwrap()),
        f64::from(1.2f32)
    );
    assert_eq!(
        [Boolean, Unsigned8, Unsigned32, Real32].map(ParamType::size),
        [1, 1, 4, 4]
    );
}
