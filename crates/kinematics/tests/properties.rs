//! Round-trip and desaturation properties over random layouts, effectiveness factors and
//! inputs.

use kinematics::{ChassisVelocity, Effectiveness, MecanumKinematics, WheelGeometry, WheelSpeeds};
use proptest::prelude::*;

/// Effectiveness factors: the ideal ones a quarter of the time, else each in [0.3, 1.5].
fn effectiveness() -> impl Strategy<Value = Effectiveness<f64>> {
    prop_oneof![
        1 => Just(Effectiveness::ideal()),
        3 => (0.3..=1.5f64, 0.3..=1.5f64, 0.3..=1.5f64)
            .prop_map(|(kx, ky, kw)| Effectiveness::new(kx, ky, kw)),
    ]
}

fn twist() -> impl Strategy<Value = ChassisVelocity<f64>> {
    (-5.0..5.0f64, -5.0..5.0f64, -10.0..10.0f64).prop_map(|(x, y, z)| ChassisVelocity::new(x, y, z))
}

fn wheel() -> impl Strategy<Value = WheelGeometry<f64>> {
    (
        -1.0..1.0f64,
        -1.0..1.0f64,
        -3.2..3.2f64,
        prop_oneof![0.3..1.3f64, -1.3..-0.3f64],
        0.02..0.2f64,
    )
        .prop_map(|(x, y, a, d, r)| WheelGeometry::new(x, y, a, d, r))
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + b.abs())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn standard_inverse_then_forward_is_identity(
        lx in 0.02..1.0f64, ly in 0.0..1.0f64, r in 0.01..0.3f64, v in twist(),
        e in effectiveness()
    ) {
        let kin = MecanumKinematics::<f64, 4>::standard_with_effectiveness(lx, ly, r, e).unwrap();
        let (back, residual) = kin.forward_with_residual(&kin.inverse(v));
        prop_assert!(close(back.vx, v.vx, 1e-9), "vx {} vs {}", back.vx, v.vx);
        prop_assert!(close(back.vy, v.vy, 1e-9), "vy {} vs {}", back.vy, v.vy);
        prop_assert!(close(back.wz, v.wz, 1e-9), "wz {} vs {}", back.wz, v.wz);
        prop_assert!(residual.max_abs() <= 1e-9 * (1.0 + kin.inverse(v).max_abs()));
    }

    #[test]
    fn standard_factors_scale_the_ideal_maps(
        lx in 0.02..1.0f64, ly in 0.0..1.0f64, r in 0.01..0.3f64, v in twist(),
        e in effectiveness()
    ) {
        // Forward reports diag(k) times the ideal twist of the same wheels; inverse asks the
        // wheels for the ideal speeds of v / k.
        let ideal = MecanumKinematics::<f64, 4>::standard(lx, ly, r).unwrap();
        let kin = MecanumKinematics::<f64, 4>::standard_with_effectiveness(lx, ly, r, e).unwrap();
        let w = ideal.inverse(v);
        let got = kin.forward(&w);
        prop_assert!(close(got.vx, e.kx * v.vx, 1e-9) && close(got.vy, e.ky * v.vy, 1e-9)
            && close(got.wz, e.kw * v.wz, 1e-9), "{got:?} vs k {e:?} times {v:?}");
        let asked = kin.inverse(v);
        let want = ideal.inverse(ChassisVelocity::new(v.vx / e.kx, v.vy / e.ky, v.wz / e.kw));
        for (a, b) in asked.0.iter().zip(want.0) {
            prop_assert!(close(*a, b, 1e-9), "{asked:?} vs {want:?}");
        }
    }

    #[test]
    fn forward_then_inverse_is_identity_on_the_wheels_range(
        lx in 0.02..1.0f64, ly in 0.0..1.0f64, r in 0.01..0.3f64, u in twist(),
        e in effectiveness()
    ) {
        // Any wheel speeds the layout can produce (J u for some u) come back unchanged.
        let ideal = MecanumKinematics::<f64, 4>::standard(lx, ly, r).unwrap();
        let kin = MecanumKinematics::<f64, 4>::standard_with_effectiveness(lx, ly, r, e).unwrap();
        let w = ideal.inverse(u);
        let back = kin.inverse(kin.forward(&w));
        for (a, b) in back.0.iter().zip(w.0) {
            prop_assert!((a - b).abs() <= 1e-9 * (1.0 + w.max_abs()), "{back:?} vs {w:?}");
        }
    }

    #[test]
    fn desaturation_keeps_the_commanded_direction_with_any_factors(
        lx in 0.02..1.0f64, ly in 0.0..1.0f64, r in 0.01..0.3f64, v in twist(),
        e in effectiveness(), max in 0.1..60.0f64
    ) {
        // The robot makes s · v for one s in (0, 1]: same direction as the command.
        let kin = MecanumKinematics::<f64, 4>::standard_with_effectiveness(lx, ly, r, e).unwrap();
        let wheels = kin.inverse(v);
        let made = kin.forward(&wheels.desaturate(max));
        let s = if wheels.max_abs() > max { max / wheels.max_abs() } else { 1.0 };
        prop_assert!(s > 0.0 && s <= 1.0);
        let tol = 1e-9 * (1.0 + v.vx.abs() + v.vy.abs() + v.wz.abs());
        prop_assert!((made.vx - s * v.vx).abs() <= tol && (made.vy - s * v.vy).abs() <= tol
            && (made.wz - s * v.wz).abs() <= tol, "{made:?} vs {s} · {v:?}");
    }

    #[test]
    fn general_layouts_round_trip_or_are_refused(
        wheels in proptest::array::uniform5(wheel()), v in twist(), e in effectiveness()
    ) {
        // Random five-wheel layouts: either refused as singular, or exact round trip within
        // a tolerance that grows with the conditioning, and with the ratio of the factors
        // (the error of J⁺J − I in entry (i, j) comes back scaled by k_i / k_j).
        if let Ok(kin) = MecanumKinematics::with_effectiveness(wheels, e) {
            let k = kin.condition_number();
            prop_assert!(k >= 1.0 - 1e-12);
            prop_assume!(k < 1e4);
            let back = kin.forward(&kin.inverse(v));
            let [kx, ky, kw] = e.as_array();
            let ratio = kx.max(ky).max(kw) / kx.min(ky).min(kw);
            let tol = 1e-12 * k * k * ratio;
            prop_assert!(close(back.vx, v.vx, tol) && close(back.vy, v.vy, tol)
                && close(back.wz, v.wz, tol), "{back:?} vs {v:?}, condition {k}");
        }
    }

    #[test]
    fn three_wheel_layouts_are_square_and_exact(
        wheels in proptest::array::uniform3(wheel()), w in proptest::array::uniform3(-50.0..50.0f64),
        e in effectiveness()
    ) {
        // Square: every wheel speed is in the range, so forward then inverse is the identity
        // (that is the residual), whatever the factors.
        if let Ok(kin) = MecanumKinematics::with_effectiveness(wheels, e) {
            prop_assume!(kin.condition_number() < 1e4);
            let (_, residual) = kin.forward_with_residual(&WheelSpeeds(w));
            let k = kin.condition_number();
            prop_assert!(residual.max_abs() <= 1e-12 * k * k * 50.0, "{residual:?}");
        }
    }

    #[test]
    fn desaturation_keeps_ratios_and_respects_the_limit(
        w in proptest::array::uniform4(-100.0..100.0f64), max in 0.1..60.0f64
    ) {
        let input = WheelSpeeds(w);
        let out = input.desaturate(max);
        let peak = input.max_abs();
        prop_assert!(out.max_abs() <= max * (1.0 + 1e-15));
        if peak > max {
            prop_assert!(close(out.max_abs(), max, 1e-15));
        } else {
            prop_assert_eq!(out, input);
        }
        // One common factor k in (0, 1]: out = k * in, so signs and ratios are kept.
        let k = out.max_abs() / peak;
        for (o, i) in out.0.iter().zip(w) {
            prop_assert!((o - k * i).abs() <= 1e-14 * max);
            prop_assert!(*o == 0.0 || o.signum() == i.signum());
        }
    }

    #[test]
    fn f32_round_trip(lx in 0.05..1.0f32, ly in 0.05..1.0f32, r in 0.02..0.2f32,
                      vx in -3.0..3.0f32, vy in -3.0..3.0f32, wz in -6.0..6.0f32,
                      k in proptest::array::uniform3(0.3..=1.5f32)) {
        let e = Effectiveness::new(k[0], k[1], k[2]);
        let kin = MecanumKinematics::<f32, 4>::standard_with_effectiveness(lx, ly, r, e).unwrap();
        let v = ChassisVelocity::new(vx, vy, wz);
        let back = kin.forward(&kin.inverse(v));
        prop_assert!((back.vx - vx).abs() < 1e-5 * (1.0 + vx.abs()));
        prop_assert!((back.vy - vy).abs() < 1e-5 * (1.0 + vy.abs()));
        prop_assert!((back.wz - wz).abs() < 1e-5 * (1.0 + wz.abs()));
    }
}
