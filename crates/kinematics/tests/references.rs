//! The references' worked examples (crates/kinematics/README.md, "References"), as test vectors.

use kinematics::{ChassisVelocity, MecanumKinematics, Real, WheelSpeeds};

/// A documentation page's worked example: a 15 cm x 20 cm robot with 60 mm wheels at its corners,
/// vx = 0.22, vy = 0.11.
fn doc_page_worked_example<T: Real + core::fmt::Debug>() {
    // Wheels at the extremities: lx = 0.20 / 2, ly = 0.15 / 2, r = 0.060 / 2.
    let kin =
        MecanumKinematics::<T, 4>::standard(T::lit(0.10), T::lit(0.075), T::lit(0.03)).unwrap();
    let w = kin.inverse(ChassisVelocity::new(T::lit(0.22), T::lit(0.11), T::zero()));
    for (got, want, name) in [
        (w.fl(), 3.66, "FL"),
        (w.fr(), 11.0, "FR"),
        (w.rl(), 11.0, "RL"),
        (w.rr(), 3.66, "RR"),
    ] {
        assert!(
            (got.to_f64() - want).abs() < 0.01,
            "{name}: {got:?} rad/s, the reference says {want}"
        );
    }
    // And its forward equations bring the twist back.
    let v = kin.forward(&w);
    assert!((v.vx.to_f64() - 0.22).abs() < 1e-5 && (v.vy.to_f64() - 0.11).abs() < 1e-5);
    assert!(v.wz.to_f64().abs() < 1e-5);
}

#[test]
fn doc_page_worked_example_f64() {
    doc_page_worked_example::<f64>();
}

#[test]
fn doc_page_worked_example_f32() {
    doc_page_worked_example::<f32>();
}

/// The vendor page, eq. 8: the same map written with L1 + L2 for lx + ly, wheels 1-4 = FL, FR, RL,
/// RR, and its y axis pointing right (its eq. 7 for wheel 1 has +vy where ours has -vy).
#[test]
fn vendor_page_eq_8() {
    let (l1, l2, big_r) = (0.3, 0.2, 0.1);
    let kin = MecanumKinematics::<f64, 4>::standard(l1, l2, big_r).unwrap();
    let m = [
        [1.0, 1.0, -(l1 + l2)],
        [1.0, -1.0, l1 + l2],
        [1.0, -1.0, -(l1 + l2)],
        [1.0, 1.0, l1 + l2],
    ];
    for (vx, vy_right, w0) in [
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
        (0.4, -0.7, 1.3),
    ] {
        let ours = kin.inverse(ChassisVelocity::new(vx, -vy_right, w0));
        for (i, row) in m.iter().enumerate() {
            let seed = (row[0] * vx + row[1] * vy_right + row[2] * w0) / big_r;
            assert!(
                (ours.0[i] - seed).abs() < 1e-12,
                "wheel {}: ours {} seed {seed}",
                i + 1,
                ours.0[i]
            );
        }
    }
}

/// The FTC tutorial: forward 0.6, strafe 0.4, rotation 0.3 give raw powers -0.1, 1.3, 0.7, 0.5;
/// normalising by the largest keeps the ratios: -0.077, 1.0, 0.538, 0.385.
///
/// The seed's rows (FL = forward - strafe - rotation, ...) are exactly our standard rows with
/// lx + ly = 1 and r = 1 when strafe is taken left-positive and rotation counter-clockwise:
/// its prose calls them right-positive and clockwise, but with rollers pointing to the centre
/// (the layout it draws) strafing right turns FL forward, which its FL row only does for
/// left-positive strafe. The numbers are what the test checks.
fn ftc_normalisation<T: Real + core::fmt::Debug>() {
    let kin = MecanumKinematics::<T, 4>::standard(T::lit(0.5), T::lit(0.5), T::one()).unwrap();
    let raw = kin.inverse(ChassisVelocity::new(T::lit(0.6), T::lit(0.4), T::lit(0.3)));
    let want_raw = [-0.1, 1.3, 0.7, 0.5];
    for (got, want) in raw.0.iter().zip(want_raw) {
        assert!((got.to_f64() - want).abs() < 1e-6, "raw {raw:?}");
    }
    let norm = raw.desaturate(T::one());
    let want = [-0.077, 1.0, 0.538, 0.385];
    for (i, name) in ["FL", "FR", "BL", "BR"].iter().enumerate() {
        let got = norm.0[i].to_f64();
        assert!(
            (got - want[i]).abs() < 0.001,
            "{name}: {got}, the reference says {}",
            want[i]
        );
    }
    // Already inside the range: untouched.
    let small = WheelSpeeds::new(T::lit(0.1), T::lit(-0.9), T::lit(0.5), T::zero());
    assert_eq!(small.desaturate(T::one()), small);
}

#[test]
fn ftc_normalisation_f64() {
    ftc_normalisation::<f64>();
}

#[test]
fn ftc_normalisation_f32() {
    ftc_normalisation::<f32>();
}

/// Tlale and de Villiers, Table I: wheel sign patterns for the eight compass directions. The table
/// numbers the wheels 1 = FR, 2 = FL, 3 = RL, 4 = RR. North is forward (+x), west is left (+y).
#[test]
fn tlale_de_villiers_table_i_compass_directions() {
    let s = core::f64::consts::FRAC_1_SQRT_2;
    #[rustfmt::skip]
    let table: [(&str, [i8; 4], (f64, f64)); 16] = [
        ("north",      [ 1,  1,  1,  1], ( 1.0,  0.0)),
        ("north",      [ 1,  1,  0,  0], ( 1.0,  0.0)),
        ("north",      [ 0,  0,  1,  1], ( 1.0,  0.0)),
        ("south",      [-1, -1, -1, -1], (-1.0,  0.0)),
        ("south",      [-1, -1,  0,  0], (-1.0,  0.0)),
        ("south",      [ 0,  0, -1, -1], (-1.0,  0.0)),
        ("east",       [-1,  1, -1,  1], ( 0.0, -1.0)),
        ("east",       [-1,  0,  0,  1], ( 0.0, -1.0)),
        ("east",       [ 0,  1, -1,  0], ( 0.0, -1.0)),
        ("west",       [ 1, -1,  1, -1], ( 0.0,  1.0)),
        ("west",       [ 1,  0,  0, -1], ( 0.0,  1.0)),
        ("west",       [ 0, -1,  1,  0], ( 0.0,  1.0)),
        ("north-east", [ 0,  1,  0,  1], ( s,   -s)),
        ("south-west", [ 0, -1,  0, -1], (-s,    s)),
        ("north-west", [ 1,  0,  1,  0], ( s,    s)),
        ("south-east", [-1,  0, -1,  0], (-s,   -s)),
    ];
    // A non-square layout, so that a rotation leak would show.
    let kin = MecanumKinematics::<f64, 4>::standard(0.25, 0.18, 0.05).unwrap();
    for (name, [w1, w2, w3, w4], (dx, dy)) in table {
        // Table order 1 = FR, 2 = FL, 3 = RL, 4 = RR -> ours FL, FR, RL, RR.
        let speeds = WheelSpeeds::new(f64::from(w2), f64::from(w1), f64::from(w3), f64::from(w4))
            .0
            .map(|w| 10.0 * w);
        let v = kin.forward(&WheelSpeeds(speeds));
        let norm = v.vx.hypot(v.vy);
        assert!(norm > 0.1, "{name} {:?}: no translation", [w1, w2, w3, w4]);
        assert!(
            (v.vx / norm - dx).abs() < 1e-12 && (v.vy / norm - dy).abs() < 1e-12,
            "{name} {:?}: moves towards ({}, {})",
            [w1, w2, w3, w4],
            v.vx / norm,
            v.vy / norm
        );
        assert!(v.wz.abs() < 1e-12, "{name}: rotates at {}", v.wz);
    }
}
