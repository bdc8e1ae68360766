//! Odometry from the wheels, and the lateral effectiveness.

use crate::rig::*;

#[test]
fn odometry_follows_the_wheels_and_is_published_at_100_hz() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    // Wheels turning as for 0.5 m/s forward (motor sign: right side mirrored).
    let w = 0.5 / 0.076;
    rig.speed = [w, -w, w, -w];
    let start = rig.log.len();
    rig.run_ms(1000);
    let pose = rig.ctl.pose();
    assert!((pose.x - 0.5).abs() < 2e-3, "x = {}", pose.x);
    assert!(pose.y.abs() < 1e-3 && pose.heading.abs() < 1e-3);
    let positions: Vec<_> = rig.log[start..]
        .iter()
        .filter_map(|(t, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::OdomPosition(p)) => Some((*t, p)),
            _ => None,
        })
        .collect();
    assert_eq!(positions.len(), 100);
    let v = rig.ctl.snapshot().measured;
    assert!((v.vx - 0.5).abs() < 0.01, "measured vx {}", v.vx);
}

/// `config` with its `lateral_effectiveness` set to `k`.
fn with_lateral_effectiveness(mut config: Config, k: f32) -> Config {
    let Geometry::Standard {
        lateral_effectiveness,
        ..
    } = &mut config.geometry
    else {
        panic!("the examples are standard layouts")
    };
    *lateral_effectiveness = k;
    config
}

#[test]
fn a_lateral_effectiveness_scales_the_odometry_of_the_same_wheel_motion_by_itself() {
    // The same wheels (0.3 m/s forward and 0.5 m/s to the left as the ideal model reads
    // them) into a default controller and one configured with lateral_effectiveness 0.72.
    let mut ideal = Rig::dji();
    let mut slip = Rig::new(with_lateral_effectiveness(
        Config::dji_m3508_example(),
        0.72,
    ));
    let (f, l) = (0.3 / 0.076, 0.5 / 0.076);
    // Wheel speeds FL, FR, RL, RR = f - l, f + l, f + l, f - l; motor sign: right mirrored.
    let motor = [f - l, -(f + l), f + l, -(f - l)];
    for rig in [&mut ideal, &mut slip] {
        rig.run_ms(5);
        rig.speed = motor;
        rig.run_ms(1000);
    }
    let (a, b) = (ideal.ctl.pose(), slip.ctl.pose());
    assert!(
        (a.y - 0.5).abs() < 2e-3 && (a.x - 0.3).abs() < 2e-3,
        "{a:?}"
    );
    // The lateral odometry by exactly the factor, the rest unchanged: to f32 rounding, and
    // to what the heading (a few µrad from the encoder quantisation, the same bits in both)
    // carries between the axes, (1 - 0.72) times the other axis' travel times sin(heading).
    assert_eq!(b.heading.to_bits(), a.heading.to_bits());
    let turned = |travel: f32| (1.0 - 0.72) * travel * a.heading.abs();
    assert!(a.heading.abs() < 1e-5, "{a:?}");
    assert!(
        (b.y - 0.72 * a.y).abs() <= turned(a.x) + 1e-6 * a.y,
        "{} vs 0.72 * {}",
        b.y,
        a.y
    );
    assert!(
        (b.x - a.x).abs() <= turned(a.y) + 1e-6 * a.x,
        "{} vs {}",
        b.x,
        a.x
    );
    let (va, vb) = (ideal.ctl.snapshot().measured, slip.ctl.snapshot().measured);
    assert!(
        (vb.vy - 0.72 * va.vy).abs() <= 1e-6 * va.vy,
        "{vb:?} vs {va:?}"
    );
    assert_eq!(vb.vx.to_bits(), va.vx.to_bits());
    assert_eq!(vb.wz.to_bits(), va.wz.to_bits());
    // And the ODOM_POSITION frames say so (0.1 mm resolution).
    let last_y = |rig: &Rig| {
        rig.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::OdomPosition(p)) => Some(p.y),
                _ => None,
            })
            .expect("odometry frames")
    };
    assert!((last_y(&slip) - 0.72 * last_y(&ideal)).abs() <= 2e-4);
}

#[test]
fn a_lateral_effectiveness_asks_the_wheels_for_the_strafe_divided_by_it() {
    let setpoints = |config: Config| {
        let mut c = config;
        c.limits.stop_linear_decel = f32::INFINITY;
        c.limits.stop_angular_decel = f32::INFINITY;
        let mut rig = Rig::new(c);
        rig.run_ms(20);
        rig.enable();
        // 0.5 m/s to the left; the ramp at 4 m/s² takes 125 ms.
        for _ in 0..10 {
            rig.twist(0.0, 0.5, 0.0);
            rig.run_ms(20);
        }
        rig.twist(0.0, 0.5, 0.0);
        (0..5)
            .filter_map(|_| {
                let out = rig.tick();
                odrive_vels(&rig.config, &out)
            })
            .last()
            .expect("setpoints every 5 ms at 200 Hz")
    };
    let ideal = setpoints(Config::odrive_example());
    let slip = setpoints(with_lateral_effectiveness(Config::odrive_example(), 0.72));
    // Wheels FL, FR, RL, RR = (-a, a, a, -a) with a = 0.5 / 0.72 / 0.05 rad/s; motor rev/s
    // through the 5:1 belt, the right side mirrored: (-m, -m, m, m).
    let m = 0.5 / 0.72 / 0.05 * 5.0 / std::f32::consts::TAU;
    for (w, want) in [-m, -m, m, m].into_iter().enumerate() {
        assert!((slip[w] - want).abs() <= 1e-5 * m, "{slip:?} vs {want}");
        assert!(
            (slip[w] * 0.72 - ideal[w]).abs() <= 1e-5 * m,
            "{slip:?} vs {ideal:?}"
        );
    }
}
