//! Per-axis effectiveness (slip-aware kinematics): inverse kinematics asks the wheels for
//! `diag(k)⁻¹` times the command, forward kinematics and odometry report `diag(k)` times what
//! the wheels imply. Expected values are written out by hand from the standard rows.

use kinematics::{
    Axis, ChassisVelocity, Effectiveness, GeometryError, MAX_EFFECTIVENESS, MecanumKinematics,
    Odometry, Pose2, WheelDeltas, WheelSpeeds,
};

mod common;
use common::{K, LX, LY, R, TOL, assert_close, assert_twist, standard, standard_wheels};

fn with(kx: f64, ky: f64, kw: f64) -> MecanumKinematics<f64, 4> {
    MecanumKinematics::standard_with_effectiveness(LX, LY, R, Effectiveness::new(kx, ky, kw))
        .unwrap()
}

#[test]
fn lateral_factor_scales_the_strafe_wheel_speeds_and_forward_undoes_it() {
    let kin = with(1.0, 0.72, 1.0);
    let command = ChassisVelocity::new(0.0, 0.5, 0.0);
    let wheels = kin.inverse(command);
    // Strafe left: FL and RR backward, FR and RL forward, each 0.5 / 0.72 / r.
    let a = 0.5 / 0.72 / R;
    assert_close(a, 13.888_888_888_888_89, 1e-9, "hand value");
    for (i, want) in [-a, a, a, -a].into_iter().enumerate() {
        assert_close(wheels.0[i], want, TOL, "strafe wheel");
    }
    // The robot really makes 72 % of what those wheels imply: the command.
    let (back, residual) = kin.forward_with_residual(&wheels);
    assert_twist(back, command, TOL, "forward of inverse");
    assert!(residual.max_abs() < TOL, "{residual:?}");
}

#[test]
fn forward_reports_k_times_the_wheel_twist_on_every_axis() {
    let (kx, ky, kw) = (0.95, 0.72, 0.88);
    let kin = with(kx, ky, kw);
    // Wheels turning as the ideal model asks for (0.4, -0.3, 1.2): 0.4 + 0.3 - 1.2 K over r,...
    let v = ChassisVelocity::new(0.4, -0.3, 1.2);
    let wheels = [
        (0.4 + 0.3 - 1.2 * K) / R,
        (0.4 - 0.3 + 1.2 * K) / R,
        (0.4 - 0.3 - 1.2 * K) / R,
        (0.4 + 0.3 + 1.2 * K) / R,
    ];
    let want = ChassisVelocity::new(kx * v.vx, ky * v.vy, kw * v.wz);
    assert_twist(kin.forward(&WheelSpeeds(wheels)), want, TOL, "forward");
    // Increments too: what odometry integrates.
    let dt = 0.01;
    let d = kin.displacement(&WheelDeltas(wheels.map(|w| w * dt)));
    assert_close(d.dx, kx * v.vx * dt, TOL, "dx");
    assert_close(d.dy, ky * v.vy * dt, TOL, "dy");
    assert_close(d.dtheta, kw * v.wz * dt, TOL, "dtheta");
    // And inverse asks the wheels for v / k: the wheels above for (kx, ky, kw) · v.
    let back = kin.inverse(want);
    for (i, w) in wheels.iter().enumerate() {
        assert_close(back.0[i], *w, 1e-11, "inverse of k v");
    }
}

#[test]
fn odometry_of_a_strafe_is_k_y_of_what_the_wheels_say() {
    // One metre of ideal strafe in 1000 steps: the ideal odometry says 1 m, the slip-aware
    // one 0.72 m, same heading (none) and no forward motion.
    let deltas = standard()
        .inverse(ChassisVelocity::new(0.0, 1.0, 0.0))
        .times(1e-3);
    let (mut a, mut b) = (
        Odometry::new(Pose2::default()),
        Odometry::new(Pose2::default()),
    );
    let slip = with(1.0, 0.72, 1.0);
    for _ in 0..1000 {
        a.update(&standard(), &deltas);
        b.update(&slip, &deltas);
    }
    assert_close(a.pose().y, 1.0, 1e-12, "ideal y");
    assert_close(b.pose().y, 0.72, 1e-12, "slip-aware y");
    assert_close(b.pose().x, 0.0, 1e-15, "x");
    assert_close(b.pose().heading, 0.0, 1e-15, "heading");
}

#[test]
fn the_residual_and_the_implied_speeds_do_not_depend_on_k() {
    // Slip between the wheels is a wheel-space quantity: the same wheels give the same
    // residual whatever the body-axis factors.
    let measured = WheelSpeeds::new(3.0, 11.5, -2.0, 7.0);
    let (_, r0) = standard().forward_with_residual(&measured);
    let (_, r1) = with(0.9, 0.7, 0.8).forward_with_residual(&measured);
    for (a, b) in r0.0.iter().zip(r1.0) {
        assert_close(b, *a, 1e-12, "residual");
    }
    assert!(r0.rms() > 1.0, "the pattern has a residual: {r0:?}");
    let i0 = standard().implied_by_others(&measured);
    let i1 = with(0.9, 0.7, 0.8).implied_by_others(&measured);
    for (a, b) in i0.iter().zip(i1) {
        assert_close(b.unwrap(), a.unwrap(), 1e-12, "implied");
    }
}

#[test]
fn desaturation_keeps_the_direction_of_the_command() {
    let kin = with(0.97, 0.72, 0.85);
    let command = ChassisVelocity::new(1.2, 0.9, 1.5);
    let wheels = kin.inverse(command);
    let limited = wheels.desaturate(20.0);
    assert!(wheels.max_abs() > 30.0, "saturates: {wheels:?}");
    assert_close(limited.max_abs(), 20.0, 1e-12, "peak on the limit");
    // What the robot makes of the limited wheels is the command times one factor.
    let got = kin.forward(&limited);
    let s = 20.0 / wheels.max_abs();
    assert_twist(
        got,
        ChassisVelocity::new(s * 1.2, s * 0.9, s * 1.5),
        1e-12,
        "desaturated",
    );
}

#[test]
fn default_factors_are_the_ideal_map_bit_for_bit() {
    let k = standard();
    assert_eq!(k.effectiveness(), Effectiveness::ideal());
    assert_eq!(
        Effectiveness::<f64>::default(),
        Effectiveness::new(1.0, 1.0, 1.0)
    );
    assert!(Effectiveness::<f32>::ideal().is_ideal());
    assert_eq!(
        MecanumKinematics::standard_with_effectiveness(LX, LY, R, Effectiveness::ideal()),
        Ok(k)
    );
    // The standard rows exactly as written (1/r and (lx+ly)/r in f64, one rounding each).
    let (a, b) = (1.0 / R, K / R);
    #[rustfmt::skip]
    let want = [
        [a, -a, -b],
        [a,  a,  b],
        [a,  a, -b],
        [a, -a,  b],
    ];
    for (i, row) in want.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            assert_eq!(
                k.inverse_matrix()[(i, j)].to_bits(),
                v.to_bits(),
                "J[{i}][{j}]"
            );
        }
    }
    // f32: forward of any wheels is the same bits with the default factors and the ideal map.
    let f = MecanumKinematics::<f32, 4>::standard(0.2, 0.18, 0.076).unwrap();
    let g = MecanumKinematics::<f32, 4>::standard_with_effectiveness(
        0.2,
        0.18,
        0.076,
        Effectiveness::new(1.0, 1.0, 1.0),
    )
    .unwrap();
    assert_eq!(f, g);
}

#[test]
fn factors_out_of_range_are_refused_naming_the_axis_and_value() {
    for (axis, index) in [(Axis::Forward, 0), (Axis::Lateral, 1), (Axis::Yaw, 2)] {
        for bad in [0.0, -1.0, 1.6, f64::NAN, f64::INFINITY, -0.0, 1.5 + 1e-15] {
            let mut k = [1.0; 3];
            k[index] = bad;
            let e = MecanumKinematics::standard_with_effectiveness(
                LX,
                LY,
                R,
                Effectiveness::new(k[0], k[1], k[2]),
            )
            .unwrap_err();
            match e {
                GeometryError::Effectiveness { axis: a, value } => {
                    assert_eq!(a, axis, "{bad}");
                    assert!(
                        value.to_bits() == bad.to_bits() || (bad.is_nan() && value.is_nan()),
                        "{value} vs {bad}"
                    );
                }
                other => panic!("{bad} on {axis:?}: {other:?}"),
            }
        }
        // The bounds: anything in (0, 1.5].
        for good in [MAX_EFFECTIVENESS, 1e-3, 0.5, 1.0] {
            let mut k = [1.0; 3];
            k[index] = good;
            let e = Effectiveness::new(k[0], k[1], k[2]);
            assert!(MecanumKinematics::standard_with_effectiveness(LX, LY, R, e).is_ok());
        }
    }
    let msg = GeometryError::Effectiveness {
        axis: Axis::Lateral,
        value: 1.6,
    }
    .to_string();
    assert!(msg.contains("lateral") && msg.contains("1.6"), "{msg}");
    // The general constructor checks them too (the first bad axis is named).
    let wheels = standard_wheels();
    assert_eq!(
        MecanumKinematics::with_effectiveness(wheels, Effectiveness::new(1.0, 0.7, -2.0)),
        Err(GeometryError::Effectiveness {
            axis: Axis::Yaw,
            value: -2.0
        })
    );
}

#[test]
fn general_layouts_take_the_factors_too() {
    let wheels = standard_wheels();
    let e = Effectiveness::new(0.9, 0.72, 0.8);
    let general = MecanumKinematics::with_effectiveness(wheels, e).unwrap();
    let standard_k = with(0.9, 0.72, 0.8);
    assert_eq!(general.effectiveness(), e);
    let diff = general.inverse_matrix() - standard_k.inverse_matrix();
    assert!(diff.amax() < 1e-12, "J differs by {}", diff.amax());
    let diff = general.forward_matrix() - standard_k.forward_matrix();
    assert!(diff.amax() < 1e-12, "J+ differs by {}", diff.amax());
    // The conditioning is the layout's, not the factors'.
    assert_close(
        general.condition_number(),
        standard().condition_number(),
        1e-12,
        "condition",
    );
}

#[test]
fn a_factor_whose_map_overflows_the_type_is_refused() {
    // Positive and finite, so in range, but 1/k overflows f32 in the inverse map.
    let e = MecanumKinematics::<f32, 4>::standard_with_effectiveness(
        0.2,
        0.18,
        0.076,
        Effectiveness::new(1.0, 1e-39, 1.0),
    )
    .unwrap_err();
    assert!(matches!(e, GeometryError::Unrepresentable { .. }), "{e:?}");
    // In f64 the same factor is representable, and exact to the type's precision.
    let k = MecanumKinematics::<f64, 4>::standard_with_effectiveness(
        0.2,
        0.18,
        0.076,
        Effectiveness::new(1.0, 1e-39, 1.0),
    )
    .unwrap();
    let v = ChassisVelocity::new(0.0, 1e-40, 0.0);
    let back = k.forward(&k.inverse(v));
    assert!((back.vy - 1e-40).abs() < 1e-52, "{back:?}");
}
