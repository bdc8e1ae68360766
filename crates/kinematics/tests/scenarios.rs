//! Named scenario matrix for the wheel maps, plus the seed documents' worked examples.
//!
//! Scenarios (straight, strafe, rotation, mixed, off-centre rotation) × (inverse, forward,
//! forward of increments). Expected values are written out by hand from the standard rows,
//! not computed by the code under test.

use kinematics::{
    ChassisVelocity, GeometryError, MecanumKinematics, WheelDeltas, WheelGeometry, WheelSpeeds,
};

mod common;
use common::{
    K, LX, LY, R, TOL, assert_close, assert_twist, assert_wheels, standard, standard_wheels,
};

/// (name, twist, expected wheel speeds written out from the standard rows)
fn scenarios() -> Vec<(&'static str, ChassisVelocity<f64>, [f64; 4])> {
    vec![
        (
            "straight",
            ChassisVelocity::new(1.0, 0.0, 0.0),
            [20.0, 20.0, 20.0, 20.0],
        ),
        (
            "reverse",
            ChassisVelocity::new(-0.5, 0.0, 0.0),
            [-10.0, -10.0, -10.0, -10.0],
        ),
        (
            "strafe left",
            ChassisVelocity::new(0.0, 1.0, 0.0),
            [-20.0, 20.0, 20.0, -20.0],
        ),
        (
            "rotation ccw",
            ChassisVelocity::new(0.0, 0.0, 1.0),
            [-K / R, K / R, -K / R, K / R],
        ),
        (
            "mixed",
            ChassisVelocity::new(0.5, -0.25, 2.0),
            [
                (0.5 + 0.25 - 2.0 * K) / R,
                (0.5 - 0.25 + 2.0 * K) / R,
                (0.5 - 0.25 - 2.0 * K) / R,
                (0.5 + 0.25 + 2.0 * K) / R,
            ],
        ),
    ]
}

#[test]
fn inverse_matrix() {
    let kin = standard();
    for (name, twist, want) in scenarios() {
        assert_wheels(&kin.inverse(twist), want, TOL, name);
    }
}

#[test]
fn forward_matrix() {
    let kin = standard();
    for (name, twist, wheels) in scenarios() {
        let (got, residual) = kin.forward_with_residual(&WheelSpeeds(wheels));
        assert_twist(got, twist, TOL, name);
        assert!(residual.rms() < TOL, "{name}: residual {residual:?}");
    }
}

#[test]
fn forward_of_increments_matrix() {
    let kin = standard();
    let dt = 0.01;
    for (name, twist, wheels) in scenarios() {
        let d = kin.displacement(&WheelDeltas(wheels.map(|w| w * dt)));
        assert_close(d.dx, twist.vx * dt, TOL, name);
        assert_close(d.dy, twist.vy * dt, TOL, name);
        assert_close(d.dtheta, twist.wz * dt, TOL, name);
    }
}

#[test]
fn rotation_about_a_wheel_leaves_that_wheel_still() {
    let kin = standard();
    // About the front-left wheel centre: FL's rollers are at rest over the ground.
    let w = kin.inverse_about(ChassisVelocity::new(0.0, 0.0, 1.5), LX, LY);
    assert_close(w.fl(), 0.0, TOL, "FL about FL");
    // The body origin moves on a circle about (LX, LY): v_o = ω × (o - c).
    let v = kin.forward(&w);
    assert_twist(
        v,
        ChassisVelocity::new(1.5 * LY, -1.5 * LX, 1.5),
        TOL,
        "about FL",
    );
    // About the origin it is the plain inverse.
    let t = ChassisVelocity::new(0.3, 0.2, -1.0);
    assert_wheels(
        &kin.inverse_about(t, 0.0, 0.0),
        kin.inverse(t).0,
        TOL,
        "about origin",
    );
}

#[test]
fn off_centre_rotation_matrix() {
    let kin = standard();
    // Spinning about a point 1 m ahead: the origin moves sideways (to the right for ccw).
    let w = kin.inverse_about(ChassisVelocity::new(0.0, 0.0, 1.0), 1.0, 0.0);
    let want = [
        (1.0 - K) / R,  // vx=0, vy=-1: FL = (0 + 1 - K)/R
        (-1.0 + K) / R, // FR = (0 - 1 + K)/R
        (-1.0 - K) / R, // RL = (0 - 1 - K)/R
        (1.0 + K) / R,  // RR = (0 + 1 + K)/R
    ];
    assert_wheels(&w, want, TOL, "about (1, 0)");
}

#[test]
fn residual_measures_wheel_disagreement() {
    let kin = standard();
    // The one pattern the standard layout cannot produce: front wheels against rear wheels,
    // (+1, +1, -1, -1). It is orthogonal to every column of J, so forward kinematics ignores
    // it and the residual is all of it.
    let slip = WheelSpeeds::new(1.0, 1.0, -1.0, -1.0);
    let base = kin.inverse(ChassisVelocity::new(0.4, 0.1, 0.3));
    let mut measured = base;
    for (m, s) in measured.0.iter_mut().zip(slip.0) {
        *m += 0.5 * s;
    }
    let (v, residual) = kin.forward_with_residual(&measured);
    assert_twist(v, ChassisVelocity::new(0.4, 0.1, 0.3), TOL, "with slip");
    assert_wheels(&residual, slip.0.map(|s| 0.5 * s), TOL, "residual");
    assert_close(residual.rms(), 0.5, TOL, "residual rms");
}

#[test]
fn each_wheel_as_the_other_three_imply_it() {
    let kin = standard();
    for (name, _, wheels) in scenarios() {
        // Agreeing wheels: every wheel is what the others say.
        let implied = kin.implied_by_others(&WheelSpeeds(wheels));
        for (i, w) in implied.iter().enumerate() {
            assert_close(w.expect("four wheels"), wheels[i], 1e-9, name);
        }
        // One wheel reads zero (a dead sensor): the others still give its true speed, the
        // standard rows' FL + FR = RL + RR solved for that wheel.
        for dead in 0..4 {
            let mut measured = wheels;
            measured[dead] = 0.0;
            let [fl, fr, rl, rr] = measured;
            let want = [rl + rr - fr, rl + rr - fl, fl + fr - rr, fl + fr - rl][dead];
            let got = kin.implied_by_others(&WheelSpeeds(measured))[dead].unwrap();
            assert_close(got, want, 1e-9, name);
            assert_close(got, wheels[dead], 1e-9, name);
        }
    }
    // Three wheels: nothing is over-determined, nothing is implied.
    let three =
        MecanumKinematics::new(three_wheel([0.0, 0.0, core::f64::consts::FRAC_PI_2])).unwrap();
    assert_eq!(
        three.implied_by_others(&WheelSpeeds([1.0, 2.0, 3.0])),
        [None; 3]
    );
}

#[test]
fn general_model_equals_standard_rows() {
    let general = MecanumKinematics::new(standard_wheels()).unwrap();
    let standard = standard();
    let diff = general.inverse_matrix() - standard.inverse_matrix();
    assert!(diff.amax() < 1e-12, "J differs by {}", diff.amax());
    let diff = general.forward_matrix() - standard.forward_matrix();
    assert!(diff.amax() < 1e-12, "J+ differs by {}", diff.amax());
    assert_close(
        standard.condition_number(),
        general.condition_number(),
        1e-9,
        "condition",
    );
}

#[test]
fn condition_number_of_the_square_layout_is_sqrt2() {
    let kin = MecanumKinematics::<f64, 4>::standard(0.2, 0.2, 0.05).unwrap();
    assert_close(kin.condition_number(), 2f64.sqrt(), 1e-12, "square");
    let f32kin = MecanumKinematics::<f32, 4>::standard(0.2, 0.2, 0.05).unwrap();
    assert!((f32kin.condition_number() - 2f32.sqrt()).abs() < 1e-5);
    // Rectangular layouts are between 1 and sqrt 2.
    let rect = MecanumKinematics::<f64, 4>::standard(0.3, 0.1, 0.05).unwrap();
    assert!(rect.condition_number() >= 1.0 && rect.condition_number() < 2f64.sqrt());
}

/// Three wheels 120° apart, 45° rollers. Wheel i's roller axis (direction alpha + delta) is
/// turned by `offset[i]` from the line through the centre: all offsets zero makes the three
/// roller axes concurrent at the centre.
fn three_wheel(offset: [f64; 3]) -> [WheelGeometry<f64>; 3] {
    let q = core::f64::consts::FRAC_PI_4;
    let mut wheels = [WheelGeometry::new(0.0, 0.0, 0.0, q, 0.04); 3];
    for (i, w) in wheels.iter_mut().enumerate() {
        let phi = (i as f64) * 2.0 * core::f64::consts::FRAC_PI_3;
        let (s, c) = phi.sin_cos();
        w.x = 0.25 * c;
        w.y = 0.25 * s;
        w.axle_angle = phi + offset[i] - q;
    }
    wheels
}

#[test]
fn concurrent_roller_axes_are_refused() {
    let q = core::f64::consts::FRAC_PI_4;
    let err = MecanumKinematics::new(three_wheel([0.0; 3])).unwrap_err();
    assert!(matches!(err, GeometryError::Singular { condition } if condition > 1e6));
    // The same layout with four wheels on a common point, and all-parallel roller axes.
    let parallel = [
        WheelGeometry::new(0.2, 0.2, core::f64::consts::FRAC_PI_2, q, 0.05),
        WheelGeometry::new(0.2, -0.2, core::f64::consts::FRAC_PI_2, q, 0.05),
        WheelGeometry::new(-0.2, 0.2, core::f64::consts::FRAC_PI_2, q, 0.05),
        WheelGeometry::new(-0.2, -0.2, core::f64::consts::FRAC_PI_2, q, 0.05),
    ];
    assert!(matches!(
        MecanumKinematics::new(parallel),
        Err(GeometryError::Singular { .. })
    ));
    // f32 refuses it too.
    let f32wheels = three_wheel([0.0; 3])
        .map(|w| WheelGeometry::new(w.x as f32, w.y as f32, w.axle_angle as f32, q as f32, 0.04));
    assert!(matches!(
        MecanumKinematics::new(f32wheels),
        Err(GeometryError::Singular { .. })
    ));
}

#[test]
fn generic_three_wheel_layout_is_inverted_exactly() {
    // Turn one roller axis by 90°: it now misses the centre.
    let kin = MecanumKinematics::new(three_wheel([0.0, 0.0, core::f64::consts::FRAC_PI_2]))
        .expect("not concurrent");
    assert!(kin.condition_number() < 10.0);
    let twist = ChassisVelocity::new(0.3, -0.7, 1.1);
    let (back, residual) = kin.forward_with_residual(&kin.inverse(twist));
    assert_twist(back, twist, 1e-12, "3-wheel round trip");
    assert!(residual.max_abs() < 1e-12);
    // Square and invertible: any wheel speeds are reachable, forward then inverse is exact.
    let w = WheelSpeeds([3.0, -1.0, 7.5]);
    let again = kin.inverse(kin.forward(&w));
    for (a, b) in again.0.iter().zip(w.0) {
        assert_close(*a, b, 1e-12, "wheel");
    }
}

#[test]
fn bad_geometry_names_the_wheel_and_value() {
    assert_eq!(
        MecanumKinematics::<f64, 4>::standard(0.2, 0.1, 0.0).unwrap_err(),
        GeometryError::NonPositiveRadius {
            wheel: 0,
            radius: 0.0
        }
    );
    assert_eq!(
        MecanumKinematics::<f64, 4>::standard(f64::NAN, 0.1, 0.05).unwrap_err(),
        GeometryError::NonFinite {
            wheel: 0,
            field: "x"
        }
    );
    assert!(matches!(
        MecanumKinematics::<f64, 4>::standard(0.0, 0.0, 0.05),
        Err(GeometryError::Singular { .. })
    ));
    let mut wheels = three_wheel([0.0, 0.0, 1.0]);
    wheels[2].roller_angle = 0.0;
    assert_eq!(
        MecanumKinematics::new(wheels).unwrap_err(),
        GeometryError::RollerParallelToAxle {
            wheel: 2,
            roller_angle: 0.0
        }
    );
    wheels[2].roller_angle = 0.5;
    wheels[1].radius = f64::INFINITY;
    assert_eq!(
        MecanumKinematics::new(wheels).unwrap_err(),
        GeometryError::NonFinite {
            wheel: 1,
            field: "radius"
        }
    );
    // Display names the value.
    let msg = format!(
        "{}",
        GeometryError::NonPositiveRadius {
            wheel: 3,
            radius: -0.1
        }
    );
    assert!(msg.contains("wheel 3") && msg.contains("-0.1"), "{msg}");
}

#[test]
fn desaturation_cases() {
    let w = WheelSpeeds::new(-4.0, 12.0, 6.0, -3.0);
    // Over the limit: one factor, the peak lands on the limit.
    let d = w.desaturate(10.0);
    assert_wheels(&d, [-4.0 / 1.2, 10.0, 5.0, -2.5], 1e-12, "scaled");
    // Under the limit: untouched, bit for bit.
    assert_eq!(w.desaturate(12.0), w);
    assert_eq!(w.desaturate(100.0), w);
    // A negative peak scales the same way.
    let n = WheelSpeeds::new(-20.0, 5.0, 0.0, 10.0).desaturate(10.0);
    assert_wheels(&n, [-10.0, 2.5, 0.0, 5.0], 1e-12, "negative peak");
    // Non-positive or NaN limits stop the wheels.
    assert_eq!(w.desaturate(0.0), WheelSpeeds::zero());
    assert_eq!(w.desaturate(-1.0), WheelSpeeds::zero());
    assert_eq!(w.desaturate(f64::NAN), WheelSpeeds::zero());
}
