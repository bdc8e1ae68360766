//! Round-trip and desaturation properties over random layouts and inputs.

use kinematics::{ChassisVelocity, MecanumKinematics, WheelGeometry, WheelSpeeds};
use proptest::prelude::*;

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
        lx in 0.02..1.0f64, ly in 0.0..1.0f64, r in 0.01..0.3f64, v in twist()
    ) {
        let kin = MecanumKinematics::<f64, 4>::standard(lx, ly, r).unwrap();
        let (back, residual) = kin.forward_with_residual(&kin.inverse(v));
        prop_assert!(close(back.vx, v.vx, 1e-9), "vx {} vs {}", back.vx, v.vx);
        prop_assert!(close(back.vy, v.vy, 1e-9), "vy {} vs {}", back.vy, v.vy);
        prop_assert!(close(back.wz, v.wz, 1e-9), "wz {} vs {}", back.wz, v.wz);
        prop_assert!(residual.max_abs() <= 1e-9 * (1.0 + kin.inverse(v).max_abs()));
    }

    #[test]
    fn general_layouts_round_trip_or_are_refused(
        wheels in proptest::array::uniform5(wheel()), v in twist()
    ) {
        // Random five-wheel layouts: either refused as singular, or exact round trip within
        // a tolerance that grows with the conditioning.
        if let Ok(kin) = MecanumKinematics::new(wheels) {
            let k = kin.condition_number();
            prop_assert!(k >= 1.0 - 1e-12);
            prop_assume!(k < 1e4);
            let back = kin.forward(&kin.inverse(v));
            let tol = 1e-12 * k * k;
            prop_assert!(close(back.vx, v.vx, tol) && close(back.vy, v.vy, tol)
                && close(back.wz, v.wz, tol), "{back:?} vs {v:?}, condition {k}");
        }
    }

    #[test]
    fn three_wheel_layouts_are_square_and_exact(
        wheels in proptest::array::uniform3(wheel()), w in proptest::array::uniform3(-50.0..50.0f64)
    ) {
        if let Ok(kin) = MecanumKinematics::new(wheels) {
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
                      vx in -3.0..3.0f32, vy in -3.0..3.0f32, wz in -6.0..6.0f32) {
        let kin = MecanumKinematics::<f32, 4>::standard(lx, ly, r).unwrap();
        let v = ChassisVelocity::new(vx, vy, wz);
        let back = kin.forward(&kin.inverse(v));
        prop_assert!((back.vx - vx).abs() < 1e-5 * (1.0 + vx.abs()));
        prop_assert!((back.vy - vy).abs() < 1e-5 * (1.0 + vy.abs()));
        prop_assert!((back.wz - wz).abs() < 1e-5 * (1.0 + wz.abs()));
    }
}
