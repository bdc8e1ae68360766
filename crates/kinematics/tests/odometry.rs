//! Odometry against the analytic arc, and encoder integration over many wraps.

use kinematics::{
    ChassisVelocity, Encoder, EncoderConfig, MecanumKinematics, Odometry, Pose2, Twist2, wrap_angle,
};
use proptest::prelude::*;

/// The pose after moving at constant body velocity `v` for `t` seconds from `p0`: the world
/// velocity R(h0 + wz τ)(vx, vy) integrated over τ in [0, t]. In closed form where the total
/// turn is large; where it is small the closed form divides a difference of sines by a small
/// number and loses digits, so the integral is taken by composite Simpson instead (an
/// independent method, error far below the tolerances used).
fn analytic(p0: Pose2<f64>, v: ChassisVelocity<f64>, t: f64) -> (f64, f64, f64) {
    let h0 = p0.heading;
    let h = h0 + v.wz * t;
    let (ix, iy) = if (v.wz * t).abs() >= 0.1 {
        // ∫cos = (sin h - sin h0)/wz, ∫sin = -(cos h - cos h0)/wz
        ((h.sin() - h0.sin()) / v.wz, -(h.cos() - h0.cos()) / v.wz)
    } else {
        let n = 2000;
        let step = t / f64::from(n);
        let (mut ic, mut is) = (0.0, 0.0);
        for k in 0..=n {
            let w = if k == 0 || k == n {
                1.0
            } else if k % 2 == 1 {
                4.0
            } else {
                2.0
            };
            let (s, c) = (h0 + v.wz * step * f64::from(k)).sin_cos();
            ic += w * c;
            is += w * s;
        }
        (ic * step / 3.0, is * step / 3.0)
    };
    (
        p0.x + v.vx * ix - v.vy * iy,
        p0.y + v.vx * iy + v.vy * ix,
        h,
    )
}

/// Drives `steps` steps of `dt` through the wheels (inverse kinematics, increments, forward
/// kinematics, SE(2) exponential) and compares with the analytic arc, relative to the path
/// length (at least 1 m).
fn check_arc(v: ChassisVelocity<f64>, p0: Pose2<f64>, dt: f64, steps: u32, rel: f64) {
    let kin = MecanumKinematics::<f64, 4>::standard(0.21, 0.17, 0.076).unwrap();
    let deltas = kin.inverse(v).times(dt);
    let mut odo = Odometry::new(p0);
    for _ in 0..steps {
        odo.update(&kin, &deltas);
    }
    let t = dt * f64::from(steps);
    let (x, y, h) = analytic(p0, v, t);
    let p = odo.pose();
    let scale = (v.vx.hypot(v.vy) * t).max(1.0);
    let err = (p.x - x).hypot(p.y - y);
    assert!(
        err <= rel * scale,
        "{v:?} dt {dt} x{steps}: ({}, {}) vs ({x}, {y}), error {err:e}",
        p.x,
        p.y
    );
    let dh = wrap_angle(p.heading - h).abs();
    assert!(
        dh <= rel * (v.wz.abs() * t).max(1.0),
        "heading off by {dh:e}"
    );
}

#[test]
fn constant_twist_matches_the_arc_at_any_step_size() {
    let twists = [
        ("straight", ChassisVelocity::new(1.2, 0.0, 0.0)),
        ("strafe", ChassisVelocity::new(0.0, -0.8, 0.0)),
        ("spin", ChassisVelocity::new(0.0, 0.0, 2.5)),
        ("arc", ChassisVelocity::new(0.9, 0.3, 0.7)),
        ("tiny rotation", ChassisVelocity::new(0.5, 0.2, 1e-7)),
        ("fast turn", ChassisVelocity::new(-0.4, 1.1, -6.0)),
    ];
    let p0 = Pose2::new(1.5, -2.0, 2.9);
    // 10 s of motion cut into 1e-4 s .. 10 s steps: the same arc every time.
    for (_name, v) in twists {
        for (dt, steps) in [
            (1e-4, 100_000),
            (1e-3, 10_000),
            (0.01, 1000),
            (0.25, 40),
            (10.0, 1),
        ] {
            check_arc(v, p0, dt, steps, 1e-9);
        }
    }
}

#[test]
fn euler_would_fail_this_test() {
    // The exponential's point: one 2 s step of a turn lands on the arc, where a first-order
    // update (straight line along the initial heading) misses it by tens of centimetres.
    let v = ChassisVelocity::new(1.0, 0.0, 1.0);
    let mut odo = Odometry::new(Pose2::default());
    let p = odo.apply(v.times(2.0));
    let (x, y, _) = analytic(Pose2::default(), v, 2.0);
    assert!((p.x - x).abs() < 1e-12 && (p.y - y).abs() < 1e-12);
    assert!(
        (2.0 - x).hypot(0.0 - y) > 0.5,
        "the arc is far from the Euler step"
    );
}

#[test]
fn series_and_closed_form_agree_at_the_switch() {
    // Just below and above the 1e-3 rad switch between series and sin(h)/h.
    for dtheta in [1.999e-3, 2.0e-3, 2.001e-3, -2.0e-3, 1e-9, 0.0] {
        let t = Twist2::new(0.7, -0.2, dtheta);
        let p = Pose2::new(0.0, 0.0, 0.3).exp(t);
        let v = ChassisVelocity::new(0.7, -0.2, dtheta);
        let (x, y, _) = analytic(Pose2::new(0.0, 0.0, 0.3), v, 1.0);
        assert!(
            (p.x - x).abs() < 1e-14 && (p.y - y).abs() < 1e-14,
            "{dtheta}"
        );
    }
}

/// The closed form of `Pose2::exp` with nothing skipped, to check its zero-step shortcut.
fn exp_in_full(p: Pose2<f32>, t: Twist2<f32>) -> Pose2<f32> {
    use kinematics::Real;
    let half = t.dtheta * 0.5;
    let (sin_mid, cos_mid) = (p.heading + half).sin_cos_libm();
    let sinc_half = if half.abs() < 1e-3 {
        let h2 = half * half;
        1.0 - h2 / 6.0 * (1.0 - h2 / 20.0)
    } else {
        half.sin_cos_libm().0 / half
    };
    let (dx, dy) = (t.dx * sinc_half, t.dy * sinc_half);
    Pose2 {
        x: p.x + cos_mid * dx - sin_mid * dy,
        y: p.y + sin_mid * dx + cos_mid * dy,
        heading: wrap_angle(p.heading + t.dtheta),
    }
}

#[test]
fn zero_step_gives_the_bits_of_the_full_formula() {
    let values = [
        0.0f32,
        -0.0,
        1e-40,
        -1e-40,
        1e-7,
        -2.5,
        3.0e7,
        f32::MAX,
        f32::INFINITY,
        f32::NAN,
    ];
    let headings = [
        0.0f32,
        -0.0,
        0.3,
        -2.9,
        3.1415925,
        -3.1415925,
        1e-30,
        f32::NAN,
    ];
    let bits = |p: Pose2<f32>| [p.x, p.y, p.heading].map(|v| (v.is_nan(), v.to_bits()));
    for &x in &values {
        for &y in &values {
            for &heading in &headings {
                for t in [
                    Twist2::new(0.0, 0.0, 0.0),
                    Twist2::new(-0.0, 0.0, -0.0),
                    Twist2::new(0.0, -0.0, 0.0),
                    Twist2::new(-0.0, -0.0, -0.0),
                ] {
                    let p = Pose2 { x, y, heading };
                    let (got, want) = (bits(p.exp(t)), bits(exp_in_full(p, t)));
                    // NaN results only need to be NaN.
                    let same = got
                        .iter()
                        .zip(&want)
                        .all(|(g, w)| if w.0 { g.0 } else { g == w });
                    assert!(same, "{p:?} {t:?}: {got:?} vs {want:?}");
                }
            }
        }
    }
}

#[test]
fn set_and_reset_pose() {
    let mut odo = Odometry::new(Pose2::new(1.0, 2.0, 0.5));
    odo.apply(Twist2::new(1.0, 0.0, 0.0));
    odo.set_pose(Pose2::new(-3.0, 4.0, 7.0));
    let p = odo.pose();
    assert_eq!((p.x, p.y), (-3.0, 4.0));
    assert!((p.heading - (7.0 - 2.0 * core::f64::consts::PI)).abs() < 1e-15);
    odo.reset();
    assert_eq!(odo.pose(), Pose2::default());
}

#[test]
fn heading_stays_wrapped_over_many_turns() {
    let mut odo = Odometry::<f64>::new(Pose2::default());
    for _ in 0..100_000 {
        odo.apply(Twist2::new(0.0, 0.0, 0.1));
    }
    let h = odo.pose().heading;
    assert!(h.abs() <= core::f64::consts::PI);
    let want = wrap_angle(10_000.0f64);
    assert!((h - want).abs() < 1e-9, "{h} vs {want}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    #[test]
    fn arc_property(vx in -2.0..2.0f64, vy in -2.0..2.0f64, wz in -4.0..4.0f64,
                    h0 in -3.1..3.1f64, dt in 1e-3..0.5f64, steps in 1u32..400) {
        check_arc(ChassisVelocity::new(vx, vy, wz), Pose2::new(0.3, -0.1, h0), dt, steps, 1e-9);
    }
}

/// A deterministic step sequence (xorshift), each step below half the counter range.
fn steps(seed: u64, max_step: u64) -> impl Iterator<Item = u64> {
    let mut s = seed;
    core::iter::from_fn(move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        Some(s % max_step)
    })
}

/// Drives a `bits`-wide counter through `wraps` full wraps in steps of random size (forward or
/// backward), checking the integer total and the angle at the end against exact arithmetic.
fn run_wraps(bits: u8, wraps: u64, backward: bool) {
    let config = EncoderConfig {
        bits,
        counts_per_rev: 8192,
        gear_ratio: 3591.0 / 187.0,
        inverted: false,
    };
    let mut enc = Encoder::<f64>::new(&config).unwrap();
    let modulus = 1u64 << bits;
    let target = wraps * modulus;
    let mut raw: u64 = 12345 % modulus;
    enc.update(raw as u32).unwrap();
    let mut travelled: u64 = 0;
    for step in steps(0x9E37_79B9_7F4A_7C15, modulus / 2) {
        let step = step.min(target - travelled);
        raw = if backward {
            (raw + modulus - step) % modulus
        } else {
            (raw + step) % modulus
        };
        let d = enc.update(raw as u32).unwrap();
        assert_eq!(d.unsigned_abs(), step);
        travelled += step;
        if travelled == target {
            break;
        }
    }
    let sign = if backward { -1 } else { 1 };
    assert_eq!(enc.total_counts(), sign * target as i64);
    // The angle is the exact count times the scale: no accumulated float error.
    let want =
        sign as f64 * target as f64 * (2.0 * core::f64::consts::PI / (8192.0 * 3591.0 / 187.0));
    assert!(
        (enc.angle() - want).abs() <= want.abs() * 1e-15,
        "{} vs {want}",
        enc.angle()
    );
}

#[test]
fn encoder_13_bit_one_million_wraps_forward() {
    run_wraps(13, 1_000_000, false);
}

#[test]
fn encoder_13_bit_one_million_wraps_backward() {
    run_wraps(13, 1_000_000, true);
}

#[test]
fn encoder_16_bit_wraps() {
    run_wraps(16, 100_000, true);
}

#[test]
fn encoder_32_bit_one_million_wraps() {
    run_wraps(32, 1_000_000, false);
}

#[test]
fn encoder_speed_and_sign() {
    // One rotor turn in 1 ms on an M3508: 2π / (3591/187) rad of wheel in 1 ms.
    let cfg = EncoderConfig::<f64>::dji_m3508(false);
    let enc = Encoder::new(&cfg).unwrap();
    let want = 2.0 * core::f64::consts::PI / (3591.0 / 187.0) / 1e-3;
    assert!((enc.speed(8192, 1e-3) - want).abs() < 1e-9);
    // A mirrored motor: the same counts roll the robot backward.
    let mirrored = Encoder::new(&EncoderConfig::<f64>::dji_m3508(true)).unwrap();
    assert_eq!(mirrored.speed(8192, 1e-3), -enc.speed(8192, 1e-3));
    // M2006: 36:1.
    let m2006 = Encoder::new(&EncoderConfig::<f32>::dji_m2006(false)).unwrap();
    assert!((m2006.counts_to_radians(8192 * 36) - 2.0 * core::f32::consts::PI).abs() < 1e-5);
}

/// Tiny steps far from the origin in f32 (1 kHz, slow motion): the compensated sums keep what
/// plain f32 additions would round away (8 % of the distance at 200 m, all of a slow turn).
#[test]
fn f32_odometry_keeps_tiny_steps_far_from_the_origin() {
    // 1 s at 5 cm/s in 1 ms steps, starting 200 m out, heading 0.
    let mut odo = Odometry::<f32>::new(Pose2::new(200.0, -200.0, 0.0));
    for _ in 0..1000 {
        odo.apply(Twist2::new(5e-5, 5e-5, 0.0));
    }
    let p = odo.pose();
    // One f32 ulp at 200 is 15 µm.
    assert!((p.x - 200.05).abs() < 2e-5, "x = {}", p.x);
    assert!((p.y - (-199.95)).abs() < 2e-5, "y = {}", p.y);

    // 1 s at 0.1 mrad/s from a heading of 3 rad: each step is below half an ulp of 3.
    let mut odo = Odometry::<f32>::new(Pose2::new(0.0, 0.0, 3.0));
    for _ in 0..1000 {
        odo.apply(Twist2::new(0.0, 0.0, 1e-7));
    }
    let h = odo.pose().heading;
    assert!((f64::from(h) - 3.0001).abs() < 3e-7, "heading {h}");

    // Across the ±π wrap the compensation carries over: 20 s of 0.2 rad/s past π.
    let mut odo = Odometry::<f32>::new(Pose2::new(0.0, 0.0, 3.0));
    let mut exact = Odometry::<f64>::new(Pose2::new(0.0, 0.0, 3.0));
    for _ in 0..20_000 {
        odo.apply(Twist2::new(1e-4, 0.0, 2e-4));
        exact.apply(Twist2::new(1e-4, 0.0, 2e-4));
    }
    let (p, q) = (odo.pose(), exact.pose());
    assert!(
        (f64::from(p.heading) - q.heading).abs() < 1e-6,
        "{p:?} vs {q:?}"
    );
    assert!((f64::from(p.x) - q.x).abs() < 1e-5 && (f64::from(p.y) - q.y).abs() < 1e-5);
}

/// `log` inverts `exp` (the SE(2) logarithm), and `relative` undoes a composition: the
/// increment `a.relative(b).log()` of a step taken from `a` is the step, in `a`'s body frame.
/// Over turns from 0 to just under half a turn either way (and the series branch below
/// 1e-3 rad), the worst error is printed and held to 1e-12 m / rad in `f64`.
#[test]
fn log_inverts_exp_and_relative_gives_the_body_frame_increment() {
    let mut worst = 0.0f64;
    let starts = [
        Pose2::<f64>::default(),
        Pose2::new(1.5, -2.0, 2.9),
        Pose2::new(-0.3, 0.7, -3.0),
    ];
    for start in starts {
        for &dtheta in &[
            0.0,
            1e-9,
            -4e-4,
            1e-3,
            0.2,
            -1.0,
            2.5,
            -3.1,
            std::f64::consts::PI - 1e-9,
        ] {
            for &(dx, dy) in &[(0.0, 0.0), (0.5, 0.0), (0.0, -0.75), (-0.3, 0.4)] {
                let step = Twist2::new(dx, dy, dtheta);
                let end = start.exp(step);
                let back = start.relative(end).log();
                for e in [back.dx - dx, back.dy - dy, back.dtheta - dtheta] {
                    worst = worst.max(e.abs());
                }
            }
        }
    }
    println!("log(relative(exp)) worst error {worst:.2e}");
    assert!(worst < 1e-12, "{worst:e}");

    // A pose seen from itself is the origin, and from the origin it is itself.
    let p = Pose2::new(0.4f64, -1.2, 1.0);
    let q = p.relative(p);
    assert!(
        q.x.abs() < 1e-15 && q.y.abs() < 1e-15 && q.heading == 0.0,
        "{q:?}"
    );
    assert_eq!(Pose2::default().relative(p), p);
}
