//! What the kinematics tests share: the standard layout they write expected values for, its
//! general form, and the comparisons with a tolerance.

// Each test crate uses its own part of this module.
#![allow(dead_code)]

use kinematics::{ChassisVelocity, MecanumKinematics, WheelGeometry, WheelSpeeds};

/// Half the wheelbase, m.
pub const LX: f64 = 0.2;
/// Half the track width, m.
pub const LY: f64 = 0.15;
/// Wheel radius, m.
pub const R: f64 = 0.05;
/// `LX + LY`, the yaw lever of every wheel in the standard rows.
pub const K: f64 = LX + LY;
/// Tolerance of results the map computes exactly up to rounding.
pub const TOL: f64 = 1e-12;

/// The standard layout.
pub fn standard() -> MecanumKinematics<f64, 4> {
    MecanumKinematics::standard(LX, LY, R).expect("standard layout is valid")
}

/// The standard layout's wheels as a general layout: axles along y, rollers at ±45°.
pub fn standard_wheels() -> [WheelGeometry<f64>; 4] {
    let q = core::f64::consts::FRAC_PI_4;
    let a = core::f64::consts::FRAC_PI_2;
    [
        WheelGeometry::new(LX, LY, a, q, R),
        WheelGeometry::new(LX, -LY, a, -q, R),
        WheelGeometry::new(-LX, LY, a, -q, R),
        WheelGeometry::new(-LX, -LY, a, q, R),
    ]
}

pub fn assert_close(got: f64, want: f64, tol: f64, what: &str) {
    assert!(
        (got - want).abs() <= tol,
        "{what}: got {got}, want {want} (tol {tol})"
    );
}

pub fn assert_wheels(got: &WheelSpeeds<f64, 4>, want: [f64; 4], tol: f64, what: &str) {
    for (i, name) in ["FL", "FR", "RL", "RR"].iter().enumerate() {
        assert_close(got.0[i], want[i], tol, &format!("{what} {name}"));
    }
}

pub fn assert_twist(got: ChassisVelocity<f64>, want: ChassisVelocity<f64>, tol: f64, what: &str) {
    assert_close(got.vx, want.vx, tol, &format!("{what} vx"));
    assert_close(got.vy, want.vy, tol, &format!("{what} vy"));
    assert_close(got.wz, want.wz, tol, &format!("{what} wz"));
}
