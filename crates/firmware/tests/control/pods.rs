//! Odometry from tracking pods (`odometry.source = "pods3" | "pods2_gyro"`, `POD_COUNTS`).

use firmware::config::{HeadingMode, OdometryMode, PodConfig, Pods};
use firmware::control::OdometrySource;
use kinematics::{PodGeometry, Twist2};

use crate::rig::*;

/// Road Runner's three-wheel layout: two forward-counting pods 0.12 m either side, one
/// left-counting pod 0.1 m ahead; 24 mm omni wheels, 2000 counts a turn.
const LAYOUT: [PodConfig; 3] = [
    pod(0.0, 0.12, 0.0),
    pod(0.0, -0.12, 0.0),
    pod(0.1, 0.0, 90.0),
];

const fn pod(x: f32, y: f32, direction_deg: f32) -> PodConfig {
    PodConfig {
        x,
        y,
        direction_deg,
        radius: 0.024,
        counts_per_turn: 2000,
    }
}

fn pods3_config() -> Config {
    let mut c = Config::dji_m3508_example();
    c.odometry.source = OdometryMode::Pods3;
    c.odometry.pods = Pods::new(&LAYOUT).unwrap();
    c
}

fn pods2_config() -> Config {
    let mut c = Config::dji_m3508_example();
    c.odometry.source = OdometryMode::Pods2Gyro;
    c.odometry.heading_source = HeadingMode::Gyro;
    // The scripted gyro reads the true rate, unbiased (a first frame at the new rate before
    // the wheels report theirs would count as a standstill sample).
    c.odometry.gyro_bias_estimation = false;
    c.odometry.pods = Pods::new(&[LAYOUT[0], LAYOUT[2]]).unwrap();
    c
}

/// The pod node: the pods' travel from a true body motion, counted as an encoder counts.
struct PodNode {
    pods: Vec<PodConfig>,
    /// Each pod's travel, m (exact).
    travel: [f64; 3],
    seq: u8,
}

impl PodNode {
    fn new(config: &Config) -> Self {
        Self {
            pods: config.odometry.pods.as_slice().to_vec(),
            travel: [0.0; 3],
            seq: 0,
        }
    }

    /// The body moved by `twist` (a small increment, body frame).
    fn advance(&mut self, twist: Twist2<f64>) {
        for (t, p) in self.travel.iter_mut().zip(&self.pods) {
            let g = PodGeometry {
                x: f64::from(p.x),
                y: f64::from(p.y),
                direction: f64::from(p.direction_deg).to_radians(),
            };
            *t += g.arc(twist);
        }
    }

    fn frame(&mut self) -> Command {
        let mut counts = [0u16; 3];
        for ((c, t), p) in counts.iter_mut().zip(self.travel).zip(&self.pods) {
            let per_count =
                std::f64::consts::TAU * f64::from(p.radius) / f64::from(p.counts_per_turn);
            *c = (t / per_count).floor() as i64 as u16;
        }
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        Command::PodCounts(robot::PodCounts { counts, seq })
    }
}

impl Rig {
    /// Runs `ms` steps while the body truly moves at (vx, vy, wz), the pods sending at
    /// 200 Hz (every 5th ms) unless `silent`.
    fn run_with_pods(&mut self, node: &mut PodNode, ms: u64, [vx, vy, wz]: [f64; 3], silent: bool) {
        for _ in 0..ms {
            if !silent && (self.now_us / 1000).is_multiple_of(5) {
                let f = node.frame();
                self.send(f);
            }
            self.tick();
            node.advance(Twist2 {
                dx: vx * 1e-3,
                dy: vy * 1e-3,
                dtheta: wz * 1e-3,
            });
        }
    }

    fn last_slip(&self) -> Option<robot::OdomSlip> {
        self.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::OdomSlip(s)) => Some(s),
                _ => None,
            })
    }
}

/// The wheel speeds (motor side, DJI example: right motors mirrored) of a forward motion.
fn forward_wheels(v: f32) -> [f32; 4] {
    let w = v / 0.076;
    [w, -w, w, -w]
}

#[test]
fn three_pods_see_the_slide_the_wheels_do_not() {
    let config = pods3_config();
    let mut rig = Rig::new(config);
    let mut node = PodNode::new(&config);
    // Not heard yet: the wheels, and the reason.
    rig.run_ms(20);
    assert_eq!(
        rig.ctl.snapshot().odometry_source,
        OdometrySource::WheelsPodsSilent
    );
    rig.run_with_pods(&mut node, 20, [0.0; 3], false);
    assert_eq!(rig.ctl.snapshot().odometry_source, OdometrySource::Pods3);
    // The wheels say 0.3 m/s forward; the body also slides left at 0.1 m/s and turns at
    // 0.2 rad/s, which the pods see.
    rig.speed = forward_wheels(0.3);
    rig.run_with_pods(&mut node, 1000, [0.3, 0.1, 0.2], false);
    let p = rig.ctl.pose();
    // The exact arc of (0.3, 0.1, 0.2) for 1 s (less the one frame interval not yet sent).
    let want = kinematics::Pose2::<f64>::default().exp(Twist2 {
        dx: 0.3,
        dy: 0.1,
        dtheta: 0.2,
    });
    let count = std::f64::consts::TAU * 0.024 / 2000.0;
    assert!(
        (f64::from(p.x) - want.x).abs() < 0.3 * 0.005 + 2.0 * count,
        "x {} want {}",
        p.x,
        want.x
    );
    assert!(
        (f64::from(p.y) - want.y).abs() < 0.1 * 0.005 + 0.01,
        "y {} want {}",
        p.y,
        want.y
    );
    assert!(
        (f64::from(p.heading) - 0.2).abs() < 0.2 * 0.005 + 2.0 * count / 0.24,
        "heading {}",
        p.heading
    );
    // The slip: the wheels' velocity less the pods', settled after 1 s (ten time constants).
    let s = rig.ctl.snapshot().slip;
    assert!(s.vx.abs() < 0.01, "slip vx {}", s.vx);
    assert!((s.vy + 0.1).abs() < 0.01, "slip vy {}", s.vy);
    assert!((s.wz + 0.2).abs() < 0.02, "slip wz {}", s.wz);
    let sent = rig.last_slip().expect("ODOM_SLIP sent with the odometry");
    assert_eq!(sent.source, OdometrySource::Pods3);
    assert!((sent.vy - s.vy).abs() < 0.002);
    // ODOM_VELOCITY reports the wheels' velocity less the slip: the pods', smoothly.
    let v = rig
        .log
        .iter()
        .rev()
        .find_map(|(_, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::OdomVelocity(v)) => Some(v),
            _ => None,
        })
        .unwrap();
    assert!(
        (v.vx - 0.3).abs() < 0.01 && (v.vy - 0.1).abs() < 0.01 && (v.wz - 0.2).abs() < 0.02,
        "{v:?}"
    );
}

#[test]
fn two_pods_take_the_rotation_from_the_gyro() {
    let config = pods2_config();
    let mut rig = Rig::new(config);
    let mut node = PodNode::new(&config);
    let mut seq = 0u8;
    // Gyro and pods together: the gyro at 200 Hz reading the true rate (no bias).
    let mut run = |rig: &mut Rig, node: &mut PodNode, ms: u64, v: [f64; 3]| {
        for _ in 0..ms {
            if (rig.now_us / 1000).is_multiple_of(5) {
                rig.send(Command::ImuYawRate(robot::ImuYawRate {
                    yaw_rate: v[2] as f32,
                    seq,
                }));
                seq = seq.wrapping_add(1);
            }
            rig.run_with_pods(node, 1, v, false);
        }
    };
    run(&mut rig, &mut node, 100, [0.0; 3]);
    assert_eq!(
        rig.ctl.snapshot().odometry_source,
        OdometrySource::Pods2Gyro
    );
    rig.speed = forward_wheels(0.3);
    run(&mut rig, &mut node, 1000, [0.3, -0.1, 0.3]);
    let p = rig.ctl.pose();
    let want = kinematics::Pose2::<f64>::default().exp(Twist2 {
        dx: 0.3,
        dy: -0.1,
        dtheta: 0.3,
    });
    assert!(
        (f64::from(p.x) - want.x).abs() < 0.004,
        "x {} want {}",
        p.x,
        want.x
    );
    assert!(
        (f64::from(p.y) - want.y).abs() < 0.004,
        "y {} want {}",
        p.y,
        want.y
    );
    assert!(
        (f64::from(p.heading) - 0.3).abs() < 0.003,
        "heading {}",
        p.heading
    );
    assert_eq!(rig.last_slip().unwrap().source, OdometrySource::Pods2Gyro);
}

#[test]
fn silent_pods_hand_the_odometry_to_the_wheels_without_a_jump_and_take_it_back() {
    let config = pods3_config();
    let mut rig = Rig::new(config);
    let mut node = PodNode::new(&config);
    rig.run_with_pods(&mut node, 50, [0.0; 3], false);
    rig.enable();
    rig.speed = forward_wheels(0.2);
    // Body and wheels agree (no slide): 0.2 m/s forward.
    for _ in 0..50 {
        rig.twist(0.2, 0.0, 0.0);
        rig.run_with_pods(&mut node, 10, [0.2, 0.0, 0.0], false);
    }
    let last_frame_us = (rig.now_us - 1000) / 5000 * 5000;
    let mut fell_back = None;
    let mut xs = Vec::new();
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        for _ in 0..10 {
            let t = rig.now_us;
            rig.run_with_pods(&mut node, 1, [0.2, 0.0, 0.0], true);
            xs.push(rig.ctl.pose().x);
            if fell_back.is_none()
                && rig.ctl.snapshot().odometry_source == OdometrySource::WheelsPodsSilent
            {
                fell_back = Some(t);
            }
        }
    }
    // pod_timeout_ms = 50: the first step more than 50 ms after the last frame.
    assert_eq!(fell_back, Some(last_frame_us + 51_000));
    // A warning, not a fault.
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Enabled, Fault::None)
    );
    assert_eq!(
        rig.last_slip().unwrap().source,
        OdometrySource::WheelsPodsSilent
    );
    // No jump: no step moved x by more than two steps' travel (0.2 mm a step), though the
    // fallback's step applies the wheels' 50 ms since the last frame.
    let most = xs.windows(2).map(|w| w[1] - w[0]).fold(0.0f32, f32::max);
    assert!(most < 0.2 * 0.051 + 1e-4, "largest step {most} m");
    // The pose kept up with the body through the silence (the wheels agree with it).
    let t = rig.now_us as f64 * 1e-6;
    let true_x = node.travel[0];
    assert!(
        (f64::from(rig.ctl.pose().x) - true_x).abs() < 0.003,
        "x {} true {true_x} at {t} s",
        rig.ctl.pose().x
    );

    // Back: the first frame sets the baseline, the next moves the pose by its interval only
    // (nothing counted twice): the pose still follows the body.
    for _ in 0..30 {
        rig.twist(0.2, 0.0, 0.0);
        rig.run_with_pods(&mut node, 10, [0.2, 0.0, 0.0], false);
    }
    assert_eq!(rig.ctl.snapshot().odometry_source, OdometrySource::Pods3);
    let true_x = node.travel[0];
    assert!(
        (f64::from(rig.ctl.pose().x) - true_x).abs() < 0.003,
        "x {} true {true_x}",
        rig.ctl.pose().x
    );
}

#[test]
fn repeated_pod_frames_are_counted_and_not_used() {
    let config = pods3_config();
    let mut rig = Rig::new(config);
    let mut node = PodNode::new(&config);
    rig.run_with_pods(&mut node, 50, [0.0; 3], false);
    let before = rig.counters().1.repeated_seq;
    node.advance(Twist2 {
        dx: 0.01,
        dy: 0.0,
        dtheta: 0.0,
    });
    let Command::PodCounts(mut c) = node.frame() else {
        unreachable!()
    };
    c.seq = node.seq.wrapping_sub(2); // the last frame's seq again
    rig.send(Command::PodCounts(c));
    rig.run_ms(1000);
    assert_eq!(rig.counters().1.repeated_seq, before + 1);
    // Not used: the pose did not move, and with no valid frame the pods went silent.
    assert_eq!(rig.ctl.pose().x, 0.0);
    assert_eq!(
        rig.ctl.snapshot().odometry_source,
        OdometrySource::WheelsPodsSilent
    );
}

#[test]
fn without_pods_configured_pod_frames_change_nothing() {
    let config = Config::dji_m3508_example();
    let run = |with_pods: bool| {
        let mut rig = Rig::new(config);
        let mut node = PodNode {
            pods: LAYOUT.to_vec(),
            travel: [0.0; 3],
            seq: 0,
        };
        rig.enable();
        rig.speed = forward_wheels(0.2);
        for _ in 0..30 {
            rig.twist(0.2, 0.0, 0.0);
            rig.run_with_pods(&mut node, 10, [0.2, 0.1, 0.0], !with_pods);
        }
        rig.log
    };
    let (with, without) = (run(true), run(false));
    assert_eq!(with, without);
    assert!(without.iter().all(|(_, f)| !matches!(
        robot::Telemetry::decode(f),
        Ok(robot::Telemetry::OdomSlip(_))
    )));
}
