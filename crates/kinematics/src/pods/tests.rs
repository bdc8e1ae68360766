//! Tests of the pod localizers: the forward model, Road Runner's formulas, round trips over
//! random layouts, the layouts refused and why, and the odometry they feed.

use super::*;
use crate::odometry::Odometry;
use crate::types::Pose2;
use core::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

/// A fixed-seed 64-bit LCG (Knuth's MMIX constants): uniform in `[lo, hi)`.
struct Lcg(u64);

impl Lcg {
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        #[allow(clippy::cast_precision_loss)]
        let unit = (self.0 >> 11) as f64 / (1_u64 << 53) as f64;
        lo + (hi - lo) * unit
    }

    fn twist(&mut self) -> Twist2<f64> {
        Twist2::new(
            self.uniform(-0.05, 0.05),
            self.uniform(-0.05, 0.05),
            self.uniform(-0.3, 0.3),
        )
    }

    fn pod(&mut self) -> PodGeometry<f64> {
        PodGeometry::new(
            self.uniform(-0.3, 0.3),
            self.uniform(-0.3, 0.3),
            self.uniform(-PI, PI),
        )
    }
}

fn pod(x: f64, y: f64, direction: f64) -> PodGeometry<f64> {
    PodGeometry::new(x, y, direction)
}

#[allow(clippy::cast_possible_truncation)]
fn pod32(p: PodGeometry<f64>) -> PodGeometry<f32> {
    PodGeometry::new(p.x as f32, p.y as f32, p.direction as f32)
}

fn assert_twist(got: Twist2<f64>, want: Twist2<f64>, tol: f64) {
    let err = (got.dx - want.dx)
        .abs()
        .max((got.dy - want.dy).abs())
        .max((got.dtheta - want.dtheta).abs());
    assert!(err <= tol, "got {got:?}, want {want:?}: error {err:e}");
}

// Road Runner's formulas, verbatim from its quickstart (`ThreeDeadWheelLocalizer`,
// `TwoDeadWheelLocalizer`), in its own parameters.
fn rr_three(par0_y: f64, par1_y: f64, perp_x: f64, par0: f64, par1: f64, perp: f64) -> Twist2<f64> {
    Twist2::new(
        (par0_y * par1 - par1_y * par0) / (par0_y - par1_y),
        perp_x / (par0_y - par1_y) * (par1 - par0) + perp,
        (par0 - par1) / (par0_y - par1_y),
    )
}

fn rr_two(par_y: f64, perp_x: f64, par: f64, perp: f64, h: f64) -> Twist2<f64> {
    Twist2::new(par - par_y * h, perp - perp_x * h, h)
}

/// Road Runner's three-wheel layout in this model: its par y is minus the pod's y.
fn rr_three_pods(
    par0_y: f64,
    par1_y: f64,
    perp_x: f64,
    xs: [f64; 2],
    perp_y: f64,
) -> [PodGeometry<f64>; 3] {
    [
        pod(xs[0], -par0_y, 0.0),
        pod(xs[1], -par1_y, 0.0),
        pod(perp_x, perp_y, FRAC_PI_2),
    ]
}

#[test]
fn forward_model_is_the_rigid_motion_of_the_contact_point() {
    // A pod left of the centre, measuring forward travel, rolls back in a CCW turn.
    let left = pod(0.0, 0.15, 0.0);
    assert!((left.arc(Twist2::new(0.0, 0.0, 0.1)) + 0.015).abs() < 1e-15);
    // One in front, measuring leftward travel, rolls forward (left) in a CCW turn.
    let front = pod(0.1, 0.0, FRAC_PI_2);
    assert!((front.arc(Twist2::new(0.0, 0.0, 0.1)) - 0.01).abs() < 1e-15);

    // First order in the increment: the contact point's displacement projected on u.
    let mut rng = Lcg(7);
    for _ in 0..200 {
        let p = rng.pod();
        let t = rng.twist();
        let small = Twist2::new(t.dx * 1e-4, t.dy * 1e-4, t.dtheta * 1e-4);
        let moved = Pose2::default().exp(small);
        let (s, c) = moved.heading.sin_cos();
        let (px, py) = (
            moved.x + c * p.x - s * p.y - p.x,
            moved.y + s * p.x + c * p.y - p.y,
        );
        let (su, cu) = p.direction.sin_cos();
        let projected = cu * px + su * py;
        // Second-order terms only: `(R(dθ) − I − dθ J) p` and the arc's bend of the
        // translation, about 1e-10 here against first-order arcs of about 1e-5 (a sign
        // slip in the model would be off by the latter).
        let second =
            small.dtheta.powi(2) * 0.5 + small.dtheta.abs() * (small.dx.abs() + small.dy.abs());
        let error = (p.arc(small) - projected).abs();
        assert!(error <= second + 1e-18, "{p:?} {small:?}: {error:e}");
    }
}

#[test]
fn road_runner_three_wheel_formulas_hold() {
    let mut rng = Lcg(1);
    // (par0Y, par1Y, perpX) in metres; the standard layout and skewed ones.
    for (par0_y, par1_y, perp_x) in [
        (0.15, -0.15, -0.10),
        (-0.18, 0.16, 0.07),
        (0.05, 0.20, 0.0),
        (-0.12, -0.02, -0.25),
    ] {
        // Road Runner ignores the pods' other coordinate: so does the model.
        let xs = [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)];
        let perp_y = rng.uniform(-0.2, 0.2);
        let loc =
            ThreePodLocalizer::three(rr_three_pods(par0_y, par1_y, perp_x, xs, perp_y)).unwrap();
        for _ in 0..100 {
            let [par0, par1, perp] = [(); 3].map(|()| rng.uniform(-0.05, 0.05));
            let want = rr_three(par0_y, par1_y, perp_x, par0, par1, perp);
            assert_twist(loc.increment([par0, par1, perp]), want, 1e-12);
            // And the forward model gives back the arcs.
            let arcs = loc.arcs(want);
            for (a, b) in arcs.into_iter().zip([par0, par1, perp]) {
                assert!((a - b).abs() < 1e-12);
            }
        }
    }
}

#[test]
fn road_runner_par_y_is_minus_the_pod_y() {
    // Taking Road Runner's par0Y/par1Y as the pods' y turns the heading the wrong way:
    // a CCW turn seen by pods at y = +0.15 (left) and −0.15 (right).
    let (par0_y, par1_y, perp_x) = (0.15, -0.15, -0.10);
    let twist = Twist2::new(0.0, 0.0, 0.2);
    let pods = [
        pod(0.0, par0_y, 0.0),
        pod(0.0, par1_y, 0.0),
        pod(perp_x, 0.0, FRAC_PI_2),
    ];
    let loc = ThreePodLocalizer::three(pods).unwrap();
    let [par0, par1, perp] = loc.arcs(twist);
    assert!(par0 < 0.0 && par1 > 0.0, "the left pod rolls back");
    assert_twist(loc.increment([par0, par1, perp]), twist, 1e-15);
    let rr = rr_three(par0_y, par1_y, perp_x, par0, par1, perp);
    assert!((rr.dtheta + 0.2).abs() < 1e-15, "{rr:?}");
    // With the sign mapped (par y = −y), Road Runner agrees.
    let rr = rr_three(-par0_y, -par1_y, perp_x, par0, par1, perp);
    assert_twist(rr, twist, 1e-15);
}

#[test]
fn road_runner_two_wheel_formulas_hold() {
    let mut rng = Lcg(2);
    for (par_y, perp_x) in [(0.15, -0.10), (-0.07, 0.12), (0.0, 0.0), (0.2, 0.2)] {
        let pods = [
            pod(rng.uniform(-0.2, 0.2), -par_y, 0.0),
            pod(perp_x, rng.uniform(-0.2, 0.2), FRAC_PI_2),
        ];
        let loc = TwoPodLocalizer::two(pods).unwrap();
        for _ in 0..100 {
            let [par, perp, h] = [(); 3].map(|()| rng.uniform(-0.05, 0.05));
            let want = rr_two(par_y, perp_x, par, perp, h);
            let got = loc.increment([par, perp], h);
            assert_twist(got, want, 1e-12);
            assert!(got.dtheta.to_bits() == h.to_bits(), "dθ passes through");
        }
    }
}

#[test]
fn road_runner_layout_mounted_at_45_degrees() {
    // Road Runner's layout in a frame B' turned 45° from the body: the pods' positions
    // turned by 45° and their directions too. Its formulas give the twist in B'; turned
    // back, the body twist.
    let (par0_y, par1_y, perp_x) = (0.14, -0.16, -0.09);
    let (s, c) = FRAC_PI_4.sin_cos();
    let turn = |p: PodGeometry<f64>| {
        pod(
            c * p.x - s * p.y,
            s * p.x + c * p.y,
            p.direction + FRAC_PI_4,
        )
    };
    let pods = rr_three_pods(par0_y, par1_y, perp_x, [0.03, -0.05], 0.02).map(turn);
    let loc = ThreePodLocalizer::three(pods).unwrap();
    let mut rng = Lcg(3);
    for _ in 0..100 {
        let [par0, par1, perp] = [(); 3].map(|()| rng.uniform(-0.05, 0.05));
        let t = rr_three(par0_y, par1_y, perp_x, par0, par1, perp);
        let want = Twist2::new(c * t.dx - s * t.dy, s * t.dx + c * t.dy, t.dtheta);
        assert_twist(loc.increment([par0, par1, perp]), want, 1e-12);
    }
}

#[test]
fn pods_at_45_degrees() {
    // Two pods in an X, heading from the gyro: forward, strafe and turn by hand.
    let loc = TwoPodLocalizer::two([pod(0.0, 0.1, FRAC_PI_4), pod(0.0, -0.1, -FRAC_PI_4)]).unwrap();
    let h = FRAC_PI_4.cos() * 0.1;
    assert_twist(
        loc.increment([h, h], 0.0),
        Twist2::new(0.1, 0.0, 0.0),
        1e-15,
    );
    assert_twist(
        loc.increment([h, -h], 0.0),
        Twist2::new(0.0, 0.1, 0.0),
        1e-15,
    );
    // A CCW turn of 0.2 rad: the left pod's contact point moves back 0.02 m, the right
    // one's forward.
    let r = FRAC_PI_4.cos() * 0.02;
    assert_twist(
        loc.increment([-r, r], 0.2),
        Twist2::new(0.0, 0.0, 0.2),
        1e-15,
    );
    assert!((loc.condition_number() - 2.0).abs() < 1e-15);

    // Three pods tangent to a circle of 0.1 m, 120° apart (a "kiwi" layout): a turn
    // rolls each pod by 0.1 dθ, and any twist comes back.
    let pods = [90.0_f64, 210.0, 330.0].map(|a| {
        let a = a.to_radians();
        pod(0.1 * a.cos(), 0.1 * a.sin(), a + FRAC_PI_2)
    });
    let loc = ThreePodLocalizer::three(pods).unwrap();
    assert_twist(loc.increment([0.03; 3]), Twist2::new(0.0, 0.0, 0.3), 1e-15);
    let twist = Twist2::new(0.02, -0.04, 0.1);
    assert_twist(loc.increment(loc.arcs(twist)), twist, 1e-15);
}

#[test]
fn round_trip_random_layouts_f64() {
    let mut rng = Lcg(4);
    let (mut three, mut two) = (0, 0);
    for _ in 0..2000 {
        let pods = [rng.pod(), rng.pod(), rng.pod()];
        if let Ok(loc) = ThreePodLocalizer::three(pods) {
            three += 1;
            for _ in 0..10 {
                let twist = rng.twist();
                assert_twist(loc.increment(loc.arcs(twist)), twist, 1e-9);
                // The per-pod model agrees with the precomputed one.
                for (p, a) in pods.iter().zip(loc.arcs(twist)) {
                    assert!((p.arc(twist) - a).abs() < 1e-15);
                }
            }
        }
        if let Ok(loc) = TwoPodLocalizer::two([pods[0], pods[1]]) {
            two += 1;
            for _ in 0..10 {
                let twist = rng.twist();
                let got = loc.increment(loc.arcs(twist), twist.dtheta);
                assert_twist(got, twist, 1e-9);
            }
        }
    }
    // Random layouts are almost never singular.
    assert!(three > 1990 && two > 1990, "{three} {two}");
}

#[test]
fn round_trip_random_layouts_f32() {
    let mut rng = Lcg(5);
    let (mut three, mut two) = (0, 0);
    for _ in 0..2000 {
        let pods = [rng.pod(), rng.pod(), rng.pod()].map(pod32);
        let size = rms_distance(&pods);
        // Relative to the size of the twist, yaw as the motion of a point `size` away.
        #[allow(clippy::cast_possible_truncation)]
        let check = |got: Twist2<f32>, want: Twist2<f64>| {
            let scale = want
                .dx
                .abs()
                .max(want.dy.abs())
                .max(want.dtheta.abs() * size);
            let err = (f64::from(got.dx) - want.dx)
                .abs()
                .max((f64::from(got.dy) - want.dy).abs())
                .max((f64::from(got.dtheta) - want.dtheta).abs() * size);
            assert!(err <= 1e-4 * scale, "{got:?} {want:?}: {:e}", err / scale);
        };
        #[allow(clippy::cast_possible_truncation)]
        let narrow = |t: Twist2<f64>| Twist2::new(t.dx as f32, t.dy as f32, t.dtheta as f32);
        let widen =
            |t: Twist2<f32>| Twist2::new(f64::from(t.dx), f64::from(t.dy), f64::from(t.dtheta));
        if let Ok(loc) = ThreePodLocalizer::three(pods) {
            three += 1;
            for _ in 0..10 {
                let twist = narrow(rng.twist());
                let want = widen(twist);
                check(loc.increment(loc.arcs(twist)), want);
            }
        }
        if let Ok(loc) = TwoPodLocalizer::two([pods[0], pods[1]]) {
            two += 1;
            for _ in 0..10 {
                let twist = narrow(rng.twist());
                let want = widen(twist);
                check(loc.increment(loc.arcs(twist), twist.dtheta), want);
            }
        }
    }
    assert!(three > 1900 && two > 1900, "{three} {two}");
}

#[test]
fn rejects_non_finite_parameters() {
    let ok = pod(0.0, 0.1, 0.0);
    let err = ThreePodLocalizer::three([ok, pod(0.1, f64::NAN, 1.0), ok]).unwrap_err();
    assert_eq!(err, PodLayoutError::NonFinite { pod: 1, field: "y" });
    let err = ThreePodLocalizer::three([ok, ok, pod(0.1, 0.0, f64::INFINITY)]).unwrap_err();
    assert_eq!(
        err,
        PodLayoutError::NonFinite {
            pod: 2,
            field: "direction"
        }
    );
    let err = TwoPodLocalizer::two([pod(f64::NEG_INFINITY, 0.0, 0.0), ok]).unwrap_err();
    assert_eq!(err, PodLayoutError::NonFinite { pod: 0, field: "x" });
}

#[test]
fn rejects_two_parallel_pods() {
    let err = TwoPodLocalizer::two([pod(0.0, 0.1, 0.3), pod(0.2, -0.1, 0.3)]).unwrap_err();
    let PodLayoutError::Parallel {
        first: 0,
        second: 1,
        angle,
        condition,
    } = err
    else {
        panic!("{err:?}")
    };
    assert!(angle.abs() < 1e-15 && condition == f64::INFINITY, "{err:?}");
    // Anti-parallel is parallel too: the angle says which.
    let err = TwoPodLocalizer::two([pod(0.0, 0.1, 0.3), pod(0.2, -0.1, 0.3 + PI)]).unwrap_err();
    let PodLayoutError::Parallel { angle, .. } = err else {
        panic!("{err:?}")
    };
    assert!((angle.abs() - PI).abs() < 1e-12, "{err:?}");
    // The threshold is relative to the type's precision: 1 mrad apart (condition 2000)
    // is refused in f32 (limit 362) and fine in f64 (limit 8.4e6).
    let pods = [pod(0.0, 0.1, 0.0), pod(0.0, -0.1, 1e-3)];
    let loc = TwoPodLocalizer::two(pods).unwrap();
    assert!((loc.condition_number() - 2000.0).abs() < 1e-3);
    let err = TwoPodLocalizer::two(pods.map(pod32)).unwrap_err();
    let PodLayoutError::Parallel {
        angle, condition, ..
    } = err
    else {
        panic!("{err:?}")
    };
    assert!(
        (angle - 1e-3).abs() < 1e-9 && (condition - 2000.0).abs() < 1.0,
        "{err:?}"
    );
    // Just inside the limit in f32: |sin| = 2 / 300.
    let inside = [pod(0.0, 0.1, 0.0), pod(0.0, -0.1, (2.0_f64 / 300.0).asin())];
    assert!(TwoPodLocalizer::two(inside.map(pod32)).is_ok());
    // Two pods at one point, crossing: fine (the heading comes from elsewhere).
    assert!(TwoPodLocalizer::two([pod(0.1, 0.1, 0.0), pod(0.1, 0.1, 2.0)]).is_ok());
}

#[test]
fn rejects_three_parallel_pods() {
    // Parallel, not collinear: the lateral translation is invisible.
    let err =
        ThreePodLocalizer::three([pod(0.0, 0.1, 0.0), pod(0.0, -0.1, 0.0), pod(0.1, 0.0, 0.0)])
            .unwrap_err();
    assert!(
        matches!(err, PodLayoutError::AllParallel { angle, condition }
            if angle == 0.0 && condition == f64::INFINITY),
        "{err:?}"
    );
    // Parallel and collinear; and anti-parallel ones.
    let err =
        ThreePodLocalizer::three([pod(0.0, 0.0, 0.0), pod(0.1, 0.0, 0.0), pod(0.2, 0.0, 0.0)])
            .unwrap_err();
    assert!(matches!(err, PodLayoutError::AllParallel { .. }), "{err:?}");
    let err =
        ThreePodLocalizer::three([pod(0.0, 0.1, 0.0), pod(0.0, -0.1, PI), pod(0.1, 0.0, 0.0)])
            .unwrap_err();
    assert!(
        matches!(err, PodLayoutError::AllParallel { angle, .. } if angle < 1e-15),
        "{err:?}"
    );
    // Nearly parallel (1e-4 rad spread) in f32: the largest angle is reported.
    let pods = [
        pod(0.0, 0.1, 0.0),
        pod(0.0, -0.1, 1e-4),
        pod(0.1, 0.0, -5e-5),
    ];
    let err = ThreePodLocalizer::three(pods.map(pod32)).unwrap_err();
    assert!(
        matches!(err, PodLayoutError::AllParallel { angle, condition }
            if (angle - 1.5e-4).abs() < 1e-8 && condition > 1e3),
        "{err:?}"
    );
}

#[test]
fn rejects_concurrent_pods() {
    // Three lines through (0.05, -0.02): a rotation about it is invisible.
    let (px, py) = (0.05, -0.02);
    let on_line = |t: f64, phi: f64| pod(px + t * phi.cos(), py + t * phi.sin(), phi);
    let pods = [on_line(0.1, 0.2), on_line(-0.15, 1.9), on_line(0.12, 4.0)];
    let err = ThreePodLocalizer::three(pods).unwrap_err();
    let PodLayoutError::Concurrent { x, y, condition } = err else {
        panic!("{err:?}")
    };
    assert!((x - px).abs() < 1e-12 && (y - py).abs() < 1e-12, "{err:?}");
    assert!(condition > 1e12, "{err:?}");
    // Invisible indeed: arcs of a rotation about the point are zero.
    let rotation = Twist2::new(0.3 * py, -0.3 * px, 0.3);
    for p in pods {
        assert!(p.arc(rotation).abs() < 1e-15);
    }

    // Two pods on one line, a third across it: the lines meet where it crosses.
    let err = ThreePodLocalizer::three([pod(0.0, 0.1, 0.0), pod(0.2, 0.1, PI), pod(0.1, 0.0, 1.0)])
        .unwrap_err();
    let PodLayoutError::Concurrent { x, y, .. } = err else {
        panic!("{err:?}")
    };
    let want_x = 0.1 + 0.1 / 1.0_f64.tan();
    assert!(
        (x - want_x).abs() < 1e-12 && (y - 0.1).abs() < 1e-12,
        "{err:?}"
    );

    // All three pods at one point: the lines meet there.
    let err =
        ThreePodLocalizer::three([pod(0.1, 0.2, 0.0), pod(0.1, 0.2, 2.0), pod(0.1, 0.2, 4.0)])
            .unwrap_err();
    assert!(
        matches!(err, PodLayoutError::Concurrent { x, y, .. }
            if (x - 0.1).abs() < 1e-12 && (y - 0.2).abs() < 1e-12),
        "{err:?}"
    );

    // Nearly concurrent: the third line misses the point by 10 µm. Refused in f32
    // (condition above 362), fine in f64.
    let pods = [
        on_line(0.1, 0.2),
        on_line(-0.15, 1.9),
        pod(
            px + 0.12 * 4.0_f64.cos(),
            py + 0.12 * 4.0_f64.sin() + 1e-5,
            4.0,
        ),
    ];
    let loc = ThreePodLocalizer::three(pods).unwrap();
    assert!(loc.condition_number() > 1e3 && loc.condition_number() < 1e5);
    let err = ThreePodLocalizer::three(pods.map(pod32)).unwrap_err();
    assert!(
        matches!(err, PodLayoutError::Concurrent { x, y, .. }
            if (x - px).abs() < 1e-6 && (y - py).abs() < 1e-6),
        "{err:?}"
    );
}

#[test]
fn rejects_unrepresentable_layouts() {
    // f32: a moment arm of 4.2e38 m overflows.
    let big = 3e38_f32;
    let pods = [
        PodGeometry::new(big, big, -core::f32::consts::FRAC_PI_4),
        PodGeometry::new(0.0, 0.0, 0.0),
        PodGeometry::new(0.0, 0.0, core::f32::consts::FRAC_PI_2),
    ];
    let err = ThreePodLocalizer::three(pods).unwrap_err();
    assert!(
        matches!(err, PodLayoutError::Unrepresentable { deviation } if deviation.is_infinite()),
        "{err:?}"
    );
    // f32: pods 1e-41 m from the origin (subnormal): the arms lose their digits.
    let tiny = 1e-41_f32;
    let pods = [
        PodGeometry::new(0.0, tiny, 0.0),
        PodGeometry::new(0.0, -tiny, 0.0),
        PodGeometry::new(tiny, 0.0, core::f32::consts::FRAC_PI_2),
    ];
    let err = ThreePodLocalizer::three(pods).unwrap_err();
    assert!(
        matches!(err, PodLayoutError::Unrepresentable { .. }),
        "{err:?}"
    );
    // Scale alone is no problem: the same layout in km or µm is accepted, same figure.
    let base = [
        pod(0.0, 0.15, 0.0),
        pod(0.0, -0.15, 0.0),
        pod(-0.1, 0.0, FRAC_PI_2),
    ];
    let k = ThreePodLocalizer::three(base).unwrap().condition_number();
    for scale in [1e-6, 1e3, 1e30] {
        let scaled = base.map(|p| pod(p.x * scale, p.y * scale, p.direction));
        let c = ThreePodLocalizer::three(scaled).unwrap().condition_number();
        assert!((c - k).abs() < 1e-12 * k, "{scale}: {c} vs {k}");
    }
}

#[test]
fn errors_name_the_pods() {
    extern crate std;
    use std::string::ToString;
    let e = PodLayoutError::NonFinite { pod: 2, field: "x" }.to_string();
    assert_eq!(e, "pod 2: x is not finite");
    let e = TwoPodLocalizer::two([pod(0.0, 0.1, 0.3), pod(0.2, -0.1, 0.3)])
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("pods 0 and 1 are (nearly) parallel"), "{e}");
    let e = PodLayoutError::Concurrent {
        x: 0.5,
        y: -0.25,
        condition: f64::INFINITY,
    }
    .to_string();
    assert!(
        e.contains("(0.5 m, -0.25 m)") && e.contains("rotation"),
        "{e}"
    );
}

#[test]
fn road_runner_layout_condition_and_limits() {
    let loc = ThreePodLocalizer::three(rr_three_pods(0.15, -0.15, -0.10, [0.0; 2], 0.0)).unwrap();
    let k = loc.condition_number();
    assert!((3.0..10.0).contains(&k), "{k}");
    assert!((PodLocalizer::<f64, 3>::max_condition_number() - 8.39e6).abs() < 1e4);
    assert!((PodLocalizer::<f32, 2>::max_condition_number() - 362.0).abs() < 0.1);
}

#[test]
fn feeds_odometry() {
    // Pods read a constant-velocity motion in 100 steps; integrated with
    // `Odometry::apply`, the pose is the one of the exact arc.
    let loc = ThreePodLocalizer::three(rr_three_pods(0.15, -0.15, -0.10, [0.0; 2], 0.0)).unwrap();
    let step = Twist2::new(0.004, 0.001, 0.015);
    let mut odometry = Odometry::new(Pose2::default());
    for _ in 0..100 {
        odometry.apply(loc.increment(loc.arcs(step)));
    }
    let want = Pose2::default().exp(Twist2::new(0.4, 0.1, 1.5));
    let got = odometry.pose();
    assert!((got.x - want.x).abs() < 1e-12 && (got.y - want.y).abs() < 1e-12);
    assert!((got.heading - want.heading).abs() < 1e-12);
}
