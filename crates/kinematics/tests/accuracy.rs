//! Numerical accuracy and input limits: the least-squares forward map in `f32`, layouts at the
//! edge of the float type, angle wrapping by the true 2π, desaturation's limit, negative
//! distances, and the documented exactness figures. Most of these tests failed on the code
//! before 2026-11-22 (the numbers it produced then are in the comments); the two on the
//! documented figures pin what the docs say, and `condition_limit_is_stated_per_type` tests
//! an accessor added then.

use kinematics::{
    ChassisVelocity, Encoder, EncoderConfig, GeometryError, MecanumKinematics, Odometry, Pose2,
    Twist2, WheelGeometry, WheelSpeeds, wrap_angle,
};
use proptest::prelude::*;

/// 2π split in two f64 constants, for reference reductions computed independently of the crate.
const TAU_HI: f64 = core::f64::consts::TAU;
const TAU_LO: f64 = 2.449_293_598_294_706_4e-16;

/// `x` reduced by the true 2π in f64 (error about 1e-16 for |x| < 1e6).
fn reference_wrap(x: f64) -> f64 {
    let r = libm::remainder(x, TAU_HI);
    let turns = ((x - r) / TAU_HI).round();
    r - turns * TAU_LO
}

// ---- the f32 forward map was computed as (JᵀJ)⁻¹Jᵀ in f32. -------------------------

/// A general f32 layout of condition number about 21 .
fn ill_conditioned_f32() -> [WheelGeometry<f32>; 4] {
    [
        (0.057_432_9, -0.242_964_95, 5.322_169_3, 0.785),
        (-0.267_722_5, -0.061_556_17, 1.757_553_6, 0.785),
        (0.143_445_03, -0.234_640_82, 0.450_331_78, -0.785),
        (0.086_503_99, -0.274_905_95, 3.404_663_6, -0.785),
    ]
    .map(|(x, y, a, d)| WheelGeometry::new(x, y, a, d, 0.05))
}

#[test]
fn f32_forward_map_is_accurate_on_an_ill_conditioned_layout() {
    let k = MecanumKinematics::<f32, 4>::new(ill_conditioned_f32()).unwrap();
    assert!(
        (k.condition_number() - 21.0).abs() < 1.0,
        "{}",
        k.condition_number()
    );
    // Round trip (before: 3e-4 off in vx).
    let v = ChassisVelocity::new(0.5f32, 0.3, 1.0);
    let b = k.forward(&k.inverse(v));
    let err = [
        (b.vx - v.vx).abs(),
        (b.vy - v.vy).abs(),
        (b.wz - v.wz).abs() * 0.2,
    ];
    assert!(
        err.iter().all(|e| *e < 1e-5),
        "round trip {b:?}, err {err:?}"
    );

    // J⁺ is the f64 pseudo-inverse (by SVD here) of J as rounded to f32, rounded once.
    let j = k.inverse_matrix().map(f64::from);
    let reference = j.pseudo_inverse(1e-14).unwrap();
    let got = k.forward_matrix().map(f64::from);
    let scale = reference.amax();
    let diff = (got - reference).amax() / scale;
    assert!(diff < 1e-7, "J+ off by {diff:e} of its largest entry");
}

#[test]
fn condition_limit_is_stated_per_type() {
    let f32_limit = MecanumKinematics::<f32, 4>::max_condition_number();
    let f64_limit = MecanumKinematics::<f64, 4>::max_condition_number();
    assert!((f32_limit - 362.04).abs() < 0.01, "{f32_limit}");
    assert!((f64_limit / 8.39e6 - 1.0).abs() < 1e-3, "{f64_limit}");
}

fn wheel_f32() -> impl Strategy<Value = WheelGeometry<f32>> {
    (
        -0.5..0.5f32,
        -0.5..0.5f32,
        -3.2..3.2f32,
        prop_oneof![0.3..1.3f32, -1.3..-0.3f32],
        0.02..0.2f32,
    )
        .prop_map(|(x, y, a, d, r)| WheelGeometry::new(x, y, a, d, r))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    /// Random accepted f32 layouts: the round trip is off by a few `condition · ε`, not
    /// `condition² · ε` (before: up to 100 times the bound below).
    #[test]
    fn f32_general_round_trip_error_grows_with_condition_not_its_square(
        wheels in proptest::array::uniform4(wheel_f32()),
        vx in -2.0..2.0f32, vy in -2.0..2.0f32, wz in -5.0..5.0f32,
    ) {
        if let Ok(kin) = MecanumKinematics::new(wheels) {
            let cond = f64::from(kin.condition_number());
            let limit = f64::from(MecanumKinematics::<f32, 4>::max_condition_number());
            prop_assert!((1.0 - 1e-6..=limit).contains(&cond), "condition {cond}");
            let len = libm::sqrt(wheels.iter().map(|w| f64::from(w.x * w.x + w.y * w.y)).sum::<f64>() / 4.0);
            let v = ChassisVelocity::new(vx, vy, wz);
            let b = kin.forward(&kin.inverse(v));
            let size = (f64::from(vx).powi(2) + f64::from(vy).powi(2) + (f64::from(wz) * len).powi(2)).sqrt();
            let err = (f64::from(b.vx - vx).powi(2) + f64::from(b.vy - vy).powi(2)
                + (f64::from(b.wz - wz) * len).powi(2)).sqrt();
            let bound = 8.0 * cond * f64::from(f32::EPSILON) * size + 1e-30;
            prop_assert!(err <= bound, "error {err:e} > {bound:e} at condition {cond}");
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    /// The same in f64 (QR instead of the normal equations there too): before, the error grew
    /// with the condition number squared.
    #[test]
    fn f64_general_round_trip_error_grows_with_condition_not_its_square(
        wheels in proptest::array::uniform4(wheel_f32()),
        vx in -2.0..2.0f64, vy in -2.0..2.0f64, wz in -5.0..5.0f64,
    ) {
        let wheels = wheels.map(|w| WheelGeometry::new(
            f64::from(w.x), f64::from(w.y), f64::from(w.axle_angle), f64::from(w.roller_angle),
            f64::from(w.radius),
        ));
        if let Ok(kin) = MecanumKinematics::new(wheels) {
            let cond = kin.condition_number();
            let len = libm::sqrt(wheels.iter().map(|w| w.x * w.x + w.y * w.y).sum::<f64>() / 4.0);
            let b = kin.forward(&kin.inverse(ChassisVelocity::new(vx, vy, wz)));
            let size = (vx * vx + vy * vy + (wz * len).powi(2)).sqrt();
            let err = ((b.vx - vx).powi(2) + (b.vy - vy).powi(2) + ((b.wz - wz) * len).powi(2)).sqrt();
            let bound = 8.0 * cond * f64::EPSILON * size + 1e-300;
            prop_assert!(err <= bound, "error {err:e} > {bound:e} at condition {cond}");
        }
    }
}

// ---- angles were reduced by fl(2π), not by 2π. ----------------------------------

#[test]
fn f32_wrap_angle_reduces_by_the_true_two_pi() {
    // Before: 0.9735084, off by 2.8e-5.
    let got = f64::from(wrap_angle(1000.0f32));
    assert!((got - 0.973_536_158_445_750_2).abs() < 1e-7, "{got}");
    // A sweep over ±1e5 rad (both the one-turn path and the many-turn path): within one
    // f32 ulp of the exactly reduced f32 input, and inside [-π, π].
    let pi = core::f32::consts::PI;
    let mut x = -1.0e5f32;
    while x < 1.0e5 {
        for v in [x, x * 1e-4, x * 3e-5] {
            let got = wrap_angle(v);
            let want = reference_wrap(f64::from(v));
            let ulp = f64::from(f32::EPSILON) * want.abs().max(0.5);
            assert!(
                (f64::from(got) - want).abs() <= ulp,
                "wrap_angle({v}) = {got}, want {want}"
            );
            assert!((-pi..=pi).contains(&got), "wrap_angle({v}) = {got}");
        }
        x += 97.123;
    }
    // Boundaries and non-finite inputs.
    assert_eq!(wrap_angle(pi), pi);
    assert_eq!(wrap_angle(-pi), -pi);
    assert!(wrap_angle(f32::NAN).is_nan() && wrap_angle(f32::INFINITY).is_nan());
    let just_over = f32::from_bits(pi.to_bits() + 1);
    assert!((f64::from(wrap_angle(just_over)) - reference_wrap(f64::from(just_over))).abs() < 3e-7);
}

#[test]
fn f64_wrap_angle_reduces_by_the_true_two_pi() {
    // Reference values from 300-bit arithmetic. Before: 1e6 was 3.9e-11 off, 1e15 0.039.
    for (x, want) in [
        (7.0f64, 0.716_814_692_820_413_5),
        (1000.0, 0.973_536_158_445_750_2),
        (1e6, -0.357_564_167_085_735),
        (-12345.678, 0.781_128_607_887_543_6),
        (1e15, 2.109_698_117_070_112_6),
    ] {
        let got = wrap_angle(x);
        assert!(
            (got - want).abs() < 1e-15,
            "wrap_angle({x}) = {got}, want {want}"
        );
    }
    assert_eq!(
        Pose2::new(0.0, 0.0, 1e6).heading,
        wrap_angle(1e6),
        "Pose2::new wraps the same way"
    );
}

#[test]
fn f32_odometry_heading_survives_ten_thousand_turns() {
    // One million steps of a bit more than 1/100 turn: 10,000 turns. Before: 1.75e-3 rad off.
    let step = (core::f64::consts::TAU / 100.0 + 1e-4) as f32;
    let mut o = Odometry::<f32>::new(Pose2::default());
    for _ in 0..1_000_000 {
        o.apply(Twist2::new(0.0, 0.0, step));
    }
    let exact = reference_wrap(1e6 * f64::from(step));
    let err = reference_wrap(f64::from(o.pose().heading) - exact);
    assert!(err.abs() < 3e-7, "10k turns: heading error {err:e} rad");
    // Backwards as well, with translation.
    let mut o = Odometry::<f32>::new(Pose2::new(0.0, 0.0, 3.0));
    for _ in 0..1_000_000 {
        o.apply(Twist2::new(1e-4, 0.0, -step));
    }
    let exact = reference_wrap(3.0 - 1e6 * f64::from(step));
    let err = reference_wrap(f64::from(o.pose().heading) - exact);
    assert!(
        err.abs() < 3e-7,
        "10k turns back: heading error {err:e} rad"
    );
}

// ---- desaturate let NaN through and overshot by an ulp. ---------------------------

#[test]
fn desaturate_stops_on_non_finite_wheels() {
    for bad in [f64::INFINITY, f64::NEG_INFINITY, f64::NAN] {
        // Before: [NaN, 0, -0, 0] for +inf (and NaN passed through unchanged).
        let w = WheelSpeeds::<f64, 4>::new(bad, 1.0, -2.0, 3.0).desaturate(10.0);
        assert_eq!(w, WheelSpeeds::zero(), "{bad}");
        let w = WheelSpeeds::<f32, 4>::new(1.0, 2.0, bad as f32, 3.0).desaturate(10.0);
        assert_eq!(w, WheelSpeeds::zero(), "{bad}");
    }
}

#[test]
fn desaturate_never_exceeds_the_limit() {
    // Before: 31.113079 > 31.113077.
    let w = WheelSpeeds::<f32, 4>::new(57.143_875, 0.0, 0.0, 0.0).desaturate(31.113_077);
    assert!(w.0[0] <= 31.113_077, "{} > 31.113077", w.0[0]);
    let w = WheelSpeeds::<f32, 4>::new(-57.143_875, 1.0, 0.0, 0.0).desaturate(31.113_077);
    assert!(w.0[0] >= -31.113_077, "{} < -31.113077", w.0[0]);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(5000))]

    /// No tolerance: the output magnitude never exceeds the limit, in f32 or f64.
    #[test]
    fn desaturate_limit_is_exact(
        w in proptest::array::uniform4(-1e4..1e4f32), max in 1e-3..1e3f32
    ) {
        let out = WheelSpeeds(w).desaturate(max);
        prop_assert!(out.0.iter().all(|x| x.abs() <= max), "{out:?} > {max}");
        let out = WheelSpeeds(w.map(f64::from)).desaturate(f64::from(max));
        prop_assert!(out.0.iter().all(|x| x.abs() <= f64::from(max)), "{out:?} > {max}");
    }
}

// ---- extreme finite layouts returned Ok with a zero or NaN forward map. ---------

fn round_trip_error<T: kinematics::Real>(
    k: &MecanumKinematics<T, 4>,
    v: ChassisVelocity<T>,
) -> f64 {
    let b = k.forward(&k.inverse(v));
    let len = k
        .wheels()
        .iter()
        .map(|w| w.x.to_f64().powi(2) + w.y.to_f64().powi(2))
        .sum::<f64>()
        .sqrt()
        / 2.0;
    let d = [
        (b.vx - v.vx).to_f64(),
        (b.vy - v.vy).to_f64(),
        (b.wz - v.wz).to_f64() * len,
    ];
    let s = [v.vx.to_f64(), v.vy.to_f64(), v.wz.to_f64() * len];
    d.iter().map(|x| x * x).sum::<f64>().sqrt() / s.iter().map(|x| x * x).sum::<f64>().sqrt()
}

#[test]
fn extreme_but_representable_layouts_get_an_accurate_forward_map() {
    // Before: forward gave vx = 0 (f32 r = 5.2e-7), a zero yaw row (f32 lx = 1.9e14) and
    // zeros/NaN (f64 r = 5e-52).
    let k = MecanumKinematics::<f32, 4>::standard(0.2, 0.15, 5.2e-7).unwrap();
    let e = round_trip_error(&k, ChassisVelocity::new(1.0, 0.5, 2.0));
    assert!(e < 1e-6, "f32 r = 5.2e-7: relative error {e:e}");
    let k = MecanumKinematics::<f32, 4>::standard(1.9e14, 0.15, 0.05).unwrap();
    let e = round_trip_error(&k, ChassisVelocity::new(1.0, 0.5, 2e-14));
    assert!(e < 1e-6, "f32 lx = 1.9e14: relative error {e:e}");
    let k = MecanumKinematics::<f64, 4>::standard(0.2, 0.15, 5e-52).unwrap();
    let e = round_trip_error(&k, ChassisVelocity::new(1.0, 0.5, 2.0));
    assert!(e < 1e-14, "f64 r = 5e-52: relative error {e:e}");
    // Entries of JᵀJ below the f64 range (1e-402): the power-of-two scaling keeps them.
    let k = MecanumKinematics::<f64, 4>::standard(0.2, 0.15, 1e200).unwrap();
    let e = round_trip_error(&k, ChassisVelocity::new(1.0, 0.5, 2.0));
    assert!(e < 1e-14, "f64 r = 1e200: relative error {e:e}");
}

#[test]
fn unrepresentable_layouts_are_refused_with_the_real_cause() {
    // J⁺ overflows f32 (r / (4 (lx + ly)) = 7.5e38).
    let e = MecanumKinematics::<f32, 4>::standard(0.05, 0.05, 3e38).unwrap_err();
    assert!(matches!(e, GeometryError::Unrepresentable { .. }), "{e:?}");
    // J overflows f32 ((lx + ly) / r = 2e60), and f64 (1 / r = 1e310).
    let e = MecanumKinematics::<f32, 4>::standard(1e30, 1e30, 1e-30).unwrap_err();
    assert!(matches!(e, GeometryError::Unrepresentable { deviation } if deviation.is_infinite()));
    let e = MecanumKinematics::<f64, 4>::standard(0.2, 0.15, 1e-310).unwrap_err();
    assert!(matches!(e, GeometryError::Unrepresentable { .. }), "{e:?}");
    let msg = e.to_string();
    assert!(
        msg.contains("float type") && !msg.contains("concurrent"),
        "{msg}"
    );
    // The yaw column of J underflows f32 to zero ((lx + ly) / r = 6e-60): before, this was
    // reported as concurrent roller axes.
    let tiny = MecanumKinematics::<f32, 4>::standard(3e-30, 3e-30, 1e30);
    assert!(
        matches!(tiny, Err(GeometryError::Unrepresentable { deviation }) if deviation > 0.5),
        "{tiny:?}"
    );
}

// ---- the standard layout took negative distances. ---------------------------------

#[test]
fn negative_standard_distances_are_refused() {
    // Before: Ok, and a ccw spin command turned the robot clockwise.
    assert_eq!(
        MecanumKinematics::<f64, 4>::standard(-0.2, -0.15, 0.05).unwrap_err(),
        GeometryError::NegativeDistance {
            field: "lx",
            value: -0.2
        }
    );
    assert_eq!(
        MecanumKinematics::<f32, 4>::standard(0.2, -0.15, 0.05).unwrap_err(),
        GeometryError::NegativeDistance {
            field: "ly",
            value: f64::from(-0.15f32)
        }
    );
    let msg = MecanumKinematics::<f64, 4>::standard(0.2, -0.15, 0.05)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("ly") && msg.contains("-0.15"), "{msg}");
    // Zero is a distance: wheels on an axis are fine, both zero is singular.
    assert!(MecanumKinematics::<f64, 4>::standard(0.0, 0.15, 0.05).is_ok());
    assert!(MecanumKinematics::<f64, 4>::standard(0.2, 0.0, 0.05).is_ok());
    assert!(matches!(
        MecanumKinematics::<f64, 4>::standard(0.0, 0.0, 0.05),
        Err(GeometryError::Singular { .. })
    ));
    // Non-finite values are still reported as such.
    assert!(matches!(
        MecanumKinematics::<f64, 4>::standard(f64::NEG_INFINITY, 0.1, 0.05),
        Err(GeometryError::NonFinite { field: "x", .. })
    ));
}

// ---- the documented precision figures. --------------------------------------------

#[test]
fn encoder_counts_are_exact_to_the_mantissa_of_t() {
    // The documentation said "exact for |counts| < 2^53"; in f32 it is 2^24. With 2^20
    // counts per turn the angle per count is a power of two times 2π, so the products below
    // are exact and only the conversion of the count can round.
    let config = |bits| EncoderConfig::<f32> {
        bits,
        counts_per_rev: 1 << 20,
        gear_ratio: 1.0,
        inverted: false,
    };
    let e = Encoder::new(&config(32)).unwrap();
    let per = e.counts_to_radians(1);
    // Exact up to 2^24 counts in f32 ...
    assert_eq!(e.counts_to_radians(1 << 24), per * 16_777_216.0);
    assert_ne!(
        e.counts_to_radians((1 << 24) - 1),
        e.counts_to_radians(1 << 24)
    );
    // ... and not beyond: 2^24 + 1 counts round to 2^24 (documented).
    assert_eq!(
        e.counts_to_radians((1 << 24) + 1),
        e.counts_to_radians(1 << 24)
    );
    // f64 resolves it.
    let e64 = Encoder::new(&EncoderConfig::<f64> {
        bits: 32,
        counts_per_rev: 1 << 20,
        gear_ratio: 1.0,
        inverted: false,
    })
    .unwrap();
    assert_ne!(
        e64.counts_to_radians((1 << 24) + 1),
        e64.counts_to_radians(1 << 24)
    );
}

#[test]
fn roller_angle_threshold_is_sqrt_epsilon() {
    let q = core::f64::consts::FRAC_PI_2;
    let layout64 = |d: f64| {
        [
            WheelGeometry::new(0.2, 0.2, q, d, 0.05),
            WheelGeometry::new(0.2, -0.2, q, -0.7, 0.05),
            WheelGeometry::new(-0.2, 0.2, q, -0.7, 0.05),
            WheelGeometry::new(-0.2, -0.2, q, 0.7, 0.05),
        ]
    };
    fn parallel<T: kinematics::Real>(r: Result<MecanumKinematics<T, 4>, GeometryError>) -> bool {
        matches!(r, Err(GeometryError::RollerParallelToAxle { wheel: 0, .. }))
    }
    // f64: √ε = 1.49e-8 rad.
    assert!(parallel(MecanumKinematics::<f64, 4>::new(layout64(1.4e-8))));
    assert!(!parallel(MecanumKinematics::<f64, 4>::new(layout64(
        1.6e-8
    ))));
    // f32: √ε = 3.45e-4 rad.
    let with = |d: f32| {
        let mut l = layout64(0.7).map(|w| {
            WheelGeometry::new(
                w.x as f32,
                w.y as f32,
                w.axle_angle as f32,
                w.roller_angle as f32,
                0.05,
            )
        });
        l[0].roller_angle = d;
        l
    };
    assert!(parallel(MecanumKinematics::<f32, 4>::new(with(3.4e-4))));
    assert!(!parallel(MecanumKinematics::<f32, 4>::new(with(3.5e-4))));
}
