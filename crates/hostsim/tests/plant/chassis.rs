//! The chassis against the references and against the kinematics crate: strafe loss, the
//! wheel patterns of Table I, sign conventions, energy, and the roller ripple.

use core::f64::consts::{FRAC_PI_2, PI, TAU};

use hostsim::nodes::plant::{
    Chassis, ChassisParams, ChassisState, DjiDrive, Plant, Ripple, WHEELS, Wheel, WheelInput,
};
use kinematics::ChassisVelocity;

use super::{LX, LY, R, WheelPi, kin};

/// Runs the DJI example plant with the wheel PI at `setpoints` for `seconds`; returns the
/// mean body velocity over the last `average` seconds and the plant.
fn run_held(
    setpoints: [f64; WHEELS],
    seconds: f64,
    average: f64,
) -> (ChassisVelocity<f64>, Plant<DjiDrive>) {
    let mut plant = Plant::dji_m3508_example().expect("defaults are valid");
    let mut pi = WheelPi::new();
    let dt = 1e-3;
    let steps = (seconds / dt).round() as usize;
    let avg_from = steps - (average / dt).round() as usize;
    let (mut sx, mut sy, mut sw, mut n) = (0.0, 0.0, 0.0, 0.0);
    for k in 0..steps {
        pi.control(&mut plant, &setpoints, dt);
        plant.step(dt).expect("valid dt");
        plant.take_feedback();
        if k >= avg_from {
            let v = plant.velocity();
            sx += v.vx;
            sy += v.vy;
            sw += v.wz;
            n += 1.0;
        }
    }
    (ChassisVelocity::new(sx / n, sy / n, sw / n), plant)
}

#[test]
fn strafe_reaches_70_to_80_percent_of_forward() {
    let kin = kin();
    let forward = kin.inverse(ChassisVelocity::new(1.0, 0.0, 0.0)).0;
    let strafe = kin.inverse(ChassisVelocity::new(0.0, 1.0, 0.0)).0;
    let (vf, _) = run_held(forward, 2.0, 0.5);
    let (vs, plant) = run_held(strafe, 2.0, 0.5);
    let ratio = vs.vy / vf.vx;
    println!(
        "forward {:.4} m/s, strafe {:.4} m/s, ratio {ratio:.4}; strafe currents {:?} A",
        vf.vx,
        vs.vy,
        Wheel::ALL.map(|w| (plant.drive(w).current() * 100.0).round() / 100.0)
    );
    // Forward loses almost nothing: rollers do not spin.
    assert!((vf.vx - 1.0).abs() < 0.01, "forward {}", vf.vx);
    assert!(
        vf.vy.abs() < 1e-3 && vf.wz.abs() < 1e-3,
        "forward drifts: {vf:?}"
    );
    // FTC mecanum tutorials: strafe 70-80 % of forward.
    assert!((0.70..=0.80).contains(&ratio), "strafe/forward = {ratio}");
    assert!(
        vs.vx.abs() < 0.01 && vs.wz.abs() < 0.01,
        "strafe drifts: {vs:?}"
    );
}

#[test]
fn strafe_ratio_holds_at_other_speeds() {
    // The contact model makes the loss a ratio, (1 − ε)/(1 + ε), not an offset.
    let kin = kin();
    for speed in [0.3, 2.0] {
        let (vf, _) = run_held(
            kin.inverse(ChassisVelocity::new(speed, 0.0, 0.0)).0,
            2.0,
            0.5,
        );
        let (vs, _) = run_held(
            kin.inverse(ChassisVelocity::new(0.0, speed, 0.0)).0,
            2.0,
            0.5,
        );
        let ratio = vs.vy / vf.vx;
        println!(
            "{speed} m/s: forward {:.4}, strafe {:.4}, ratio {ratio:.4}",
            vf.vx, vs.vy
        );
        assert!((0.70..=0.80).contains(&ratio), "{speed} m/s: ratio {ratio}");
    }
}

/// Tlale and de Villiers, Table I: wheel 1 = FR, 2 = FL, 3 = RL, 4 = RR; north = +x, east = −y.
const TABLE_I: [(&str, &str, f64); 16] = [
    ("N", "++++", 0.0),
    ("N", "++00", 0.0),
    ("N", "00++", 0.0),
    ("S", "----", 180.0),
    ("S", "--00", 180.0),
    ("S", "00--", 180.0),
    ("E", "-+-+", -90.0),
    ("E", "-00+", -90.0),
    ("E", "0+-0", -90.0),
    ("W", "+-+-", 90.0),
    ("W", "+00-", 90.0),
    ("W", "0-+0", 90.0),
    ("NE", "0+0+", -45.0),
    ("SW", "0-0-", 135.0),
    ("NW", "+0+0", 45.0),
    ("SE", "-0-0", -135.0),
];

fn angle_diff_deg(a: f64, b: f64) -> f64 {
    (a - b + 180.0).rem_euclid(360.0) - 180.0
}

#[test]
fn table_i_patterns_move_in_their_compass_direction() {
    // Driven wheels at ±10 rad/s (0.76 m/s at the rim), the others held at 0 by the loop.
    // Zero-speed wheels drag (held by the loop, their contacts slide along the roller axes),
    // so a pattern with two held wheels moves slower than the least-squares half speed; the
    // direction of the N/S/E/W patterns holds by the layout's mirror symmetry (within 0.5°).
    // The diagonals lose their lateral component to the roller drag exactly as a strafe
    // does (as FTC mecanum tutorials report): they travel at atan(0.75) = 36.9° off the x axis
    // instead of 45°, so their tolerance is 10°. Heading: below 1° over the 2 s run (each pattern
    // is symmetric under a mirror or a half-turn, so the yaw torques cancel).
    const W: f64 = 10.0;
    let mut worst = (0.0_f64, 0.0_f64);
    for (name, pattern, compass) in TABLE_I {
        let c: Vec<f64> = pattern
            .chars()
            .map(|ch| match ch {
                '+' => W,
                '-' => -W,
                _ => 0.0,
            })
            .collect();
        // Table order FR, FL, RL, RR → FL, FR, RL, RR.
        let setpoints = [c[1], c[0], c[2], c[3]];
        let (_, plant) = run_held(setpoints, 2.0, 0.0);
        let pose = plant.pose();
        let direction = pose.y.atan2(pose.x).to_degrees();
        let err = angle_diff_deg(direction, compass);
        let heading = plant.state().yaw.to_degrees();
        let dist = pose.x.hypot(pose.y);
        println!(
            "{name:>2} {pattern}: travelled {dist:.3} m towards {direction:7.2}° \
             (compass {compass:6.1}°, error {err:+.3}°), heading change {heading:+.4}°"
        );
        assert!(dist > 0.1, "{pattern}: barely moved ({dist} m)");
        let tolerance = if name.len() == 2 { 10.0 } else { 0.5 };
        assert!(
            err.abs() < tolerance,
            "{pattern}: direction {direction}° vs {compass}°"
        );
        assert!(heading.abs() < 1.0, "{pattern}: heading changed {heading}°");
        worst = (worst.0.max(err.abs()), worst.1.max(heading.abs()));
    }
    println!(
        "worst direction error {:.4}°, worst heading change {:.4}°",
        worst.0, worst.1
    );
}

/// Forces the wheels to `inverse(v)` on a chassis with free rollers for `seconds`.
fn forced(v: ChassisVelocity<f64>, params: ChassisParams, seconds: f64) -> Chassis {
    let mut chassis = Chassis::new(params).expect("valid");
    let speeds = kin().inverse(v).0.map(WheelInput::Speed);
    chassis.step(seconds, &speeds).expect("valid step");
    chassis
}

#[test]
fn forced_kinematic_wheel_speeds_reach_the_twist() {
    // Forward, strafe and rotation within 1 %. A twist that translates *and* turns needs a
    // centripetal force m ω × v, which the contacts give only by slipping (about
    // m |ω v| / (4 μN / s0) ≈ 4 mm/s at 0.8 m/s and 0.8 rad/s): 1 % plus that slip.
    let params = ChassisParams::default().with_free_rollers();
    for (v, tolerance) in [
        (ChassisVelocity::new(1.0, 0.0, 0.0), 0.01),
        (ChassisVelocity::new(0.0, 1.0, 0.0), 0.01),
        (ChassisVelocity::new(0.0, 0.0, 1.0), 0.01),
        (ChassisVelocity::new(-0.7, 0.4, -0.8), 0.02),
    ] {
        let got = forced(v, params, 2.0).state().velocity;
        let scale = v.vx.hypot(v.vy).max(v.wz.abs() * LX.hypot(LY));
        let err = (got.vx - v.vx)
            .hypot(got.vy - v.vy)
            .max((got.wz - v.wz).abs() * LX.hypot(LY));
        println!("{v:?} → {got:?}, relative error {:.2e}", err / scale);
        assert!(err / scale < tolerance, "{v:?}: got {got:?}");
    }
}

#[test]
fn forced_rotation_turns_counter_clockwise_and_pose_follows() {
    // wz > 0 is counter-clockwise: after π/2 s at 1 rad/s the heading is +90°.
    let params = ChassisParams::default().with_free_rollers();
    let mut chassis = Chassis::new(params).expect("valid");
    let speeds = kin().inverse(ChassisVelocity::new(1.0, 0.0, 1.0)).0;
    // Start already moving at the twist so the pose integrates the steady arc.
    let state = ChassisState {
        velocity: ChassisVelocity::new(1.0, 0.0, 1.0),
        wheel_speed: speeds,
        ..ChassisState::default()
    };
    chassis.set_state(state).expect("finite");
    chassis
        .step(FRAC_PI_2, &speeds.map(WheelInput::Speed))
        .expect("valid");
    let pose = chassis.state().pose;
    // A quarter circle of radius 1 m to the left: (1, 1), heading 90°. The centripetal force
    // (20 N) comes from slip, which widens the arc by about a centimetre.
    println!("{pose:?}");
    assert!((pose.heading - FRAC_PI_2).abs() < 1e-6, "{pose:?}");
    assert!(
        (pose.x - 1.0).abs() < 0.02 && (pose.y - 1.0).abs() < 0.02,
        "{pose:?}"
    );
    assert!(
        pose.x > 1.0 && pose.y < 1.0,
        "the slip widens the arc outward: {pose:?}"
    );
}

#[test]
fn coasting_never_gains_energy() {
    // Free wheels (no torque), an inconsistent start: slip everywhere, rollers dragging.
    for ripple in [None, Some(Ripple::new(12, 0.05))] {
        let params = ChassisParams {
            ripple,
            ..ChassisParams::default()
        };
        let mut chassis = Chassis::new(params).expect("valid");
        chassis
            .set_state(ChassisState {
                velocity: ChassisVelocity::new(1.0, -0.8, 2.0),
                wheel_speed: [5.0, -12.0, 0.0, 20.0],
                ..ChassisState::default()
            })
            .expect("finite");
        let e0 = chassis.kinetic_energy();
        let mut last = e0;
        let zero = [WheelInput::Torque(0.0); WHEELS];
        for _ in 0..3000 {
            chassis.step(1e-3, &zero).expect("valid");
            let e = chassis.kinetic_energy();
            assert!(e <= last * (1.0 + 1e-12), "energy rose from {last} to {e}");
            last = e;
        }
        println!("ripple {ripple:?}: kinetic energy {e0:.3} J → {last:.3} J");
        assert!(last < 0.8 * e0);
    }
    // With the motors' friction the plant comes to rest.
    let mut plant = Plant::dji_m3508_example().expect("valid");
    let speeds = kin().inverse(ChassisVelocity::new(1.0, 0.5, 1.0)).0;
    plant
        .set_state(ChassisState {
            velocity: ChassisVelocity::new(1.0, 0.5, 1.0),
            wheel_speed: speeds,
            ..ChassisState::default()
        })
        .expect("finite");
    // With zero current the motors' gearbox friction brakes the robot.
    let e0 = plant.chassis().kinetic_energy();
    let mut last = e0;
    for _ in 0..3000 {
        plant.step(1e-3).expect("valid");
        let e = plant.chassis().kinetic_energy();
        assert!(e <= last * (1.0 + 1e-12), "energy rose from {last} to {e}");
        last = e;
    }
    println!("plant coasting: {e0:.3} J → {last:.3} J in 3 s");
    assert!(last < 0.5 * e0);
}

#[test]
fn ripple_moves_the_contact_point_after_eq_11() {
    let (k, d) = (12_u32, 0.05);
    let params = ChassisParams {
        ripple: Some(Ripple::new(k, d)),
        ..ChassisParams::default()
    };
    let pitch = TAU / f64::from(k);
    let mut chassis = Chassis::new(params).expect("valid");
    for u in [-0.49 * pitch, -0.2 * pitch, 0.0, 0.3 * pitch, 0.49 * pitch] {
        // Wheel angle u + 5 pitches: the same roller position.
        let phi = u + 5.0 * pitch;
        chassis
            .set_state(ChassisState {
                wheel_angle: [phi; WHEELS],
                ..ChassisState::default()
            })
            .expect("finite");
        chassis
            .step(1e-6, &[WheelInput::Speed(0.0); WHEELS])
            .expect("valid");
        for (i, w) in params.wheels.iter().enumerate() {
            // Eq. 11: c = a − d cot δ tan u (cos α, sin α).
            let shift = -d / w.roller_angle.tan() * u.tan();
            let cx = w.x + shift * w.axle_angle.cos();
            let cy = w.y + shift * w.axle_angle.sin();
            let c = chassis.contacts()[i].position;
            assert!(
                (c[0] - cx).abs() < 1e-9 && (c[1] - cy).abs() < 1e-9,
                "{i}: {c:?}"
            );
        }
    }
    // Off by default: the contact is under the wheel centre.
    let chassis = forced(
        ChassisVelocity::new(1.0, 0.0, 0.0),
        ChassisParams::default(),
        0.01,
    );
    for (c, w) in chassis
        .contacts()
        .iter()
        .zip(ChassisParams::default().wheels)
    {
        assert_eq!(c.position, [w.x, w.y]);
    }
}

#[test]
fn ripple_makes_a_strafe_speed_ripple_at_the_roller_frequency() {
    // Wheels forced at constant strafe speeds. Rolling straight has no ripple (eq. 15 reduces
    // to r ω = vx whatever the roller's tilt), but strafing goes with the tilted roller axis:
    // vy = r ω tan δ_eff / tan δ = r ω cos u, which dips once per roller pitch, by
    // 1 − cos(π/k) (4.9 % for k = 10), mean r ω sin(π/k)/(π/k) (98.4 %).
    let (k, d) = (10_u32, 0.05);
    let params = ChassisParams {
        ripple: Some(Ripple::new(k, d)),
        ..ChassisParams::default().with_free_rollers()
    };
    let mut chassis = Chassis::new(params).expect("valid");
    let w = 10.0;
    let strafe = [-w, w, w, -w].map(WheelInput::Speed);
    chassis.step(1.0, &strafe).expect("valid");
    let period = TAU / f64::from(k) / w;
    let mut samples = Vec::new();
    let dt = period / 50.0;
    for _ in 0..200 {
        chassis.step(dt, &strafe).expect("valid");
        samples.push(chassis.state().velocity.vy);
    }
    let mean = samples.iter().sum::<f64>() / samples.len() as f64;
    let (lo, hi) = samples
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    // Correlation with itself one pitch later (50 samples) vs half a pitch later (25).
    let corr = |lag: usize| {
        let n = samples.len() - lag;
        (0..n)
            .map(|i| (samples[i] - mean) * (samples[i + lag] - mean))
            .sum::<f64>()
            / n as f64
    };
    println!(
        "ripple: mean {mean:.4} m/s (rim {:.4}), peak-to-peak {:.4} m/s, corr(pitch) {:.2e}, \
         corr(pitch/2) {:.2e}",
        w * R,
        hi - lo,
        corr(50),
        corr(25)
    );
    let pitch_half = PI / f64::from(k);
    let mean_expected = w * R * pitch_half.sin() / pitch_half;
    assert!(
        (mean - mean_expected).abs() < 0.005 * mean_expected,
        "mean {mean}"
    );
    assert!(
        (hi - lo) > 0.5 * (1.0 - pitch_half.cos()) * w * R,
        "ripple {}",
        hi - lo
    );
    assert!(corr(50) > 0.0 && corr(25) < 0.0);
}
