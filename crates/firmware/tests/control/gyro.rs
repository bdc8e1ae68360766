//! Gyro heading (`odometry.heading_source = "gyro"`, `IMU_YAW_RATE`).

use crate::rig::*;

/// The DJI example with the heading from the gyro.
fn gyro_config() -> Config {
    let mut c = Config::dji_m3508_example();
    c.odometry.heading_source = firmware::config::HeadingMode::Gyro;
    c
}

impl Rig {
    /// Sends an `IMU_YAW_RATE`.
    fn gyro(&mut self, yaw_rate: f32, seq: u8) {
        self.send(Command::ImuYawRate(robot::ImuYawRate { yaw_rate, seq }));
    }

    /// Runs `ms` steps with a 200 Hz IMU reading `rate` (its frames at every 5th ms, `seq`
    /// counting on from `*seq`).
    fn run_with_gyro(&mut self, ms: u64, rate: f32, seq: &mut u8) {
        for _ in 0..ms {
            if (self.now_us / 1000).is_multiple_of(5) {
                self.gyro(rate, *seq);
                *seq = seq.wrapping_add(1);
            }
            self.tick();
        }
    }

    /// The last `ODOM_VELOCITY` sent.
    fn odom_velocity(&self) -> robot::OdomVelocity {
        self.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::OdomVelocity(v)) => Some(v),
                _ => None,
            })
            .expect("an odometry frame was sent")
    }
}

#[test]
fn gyro_heading_is_the_rate_less_the_bias_learned_standing_still() {
    use firmware::control::HeadingSource;
    let mut rig = Rig::new(gyro_config());
    let bias = 0.002f32; // 0.115 °/s
    let mut seq = 0;
    // Disabled, wheels at rest: the bias is learned once the robot has stood still for
    // gyro_standstill_ms (50 ms); until then the uncorrected rate turns the heading.
    rig.run_with_gyro(1000, bias, &mut seq);
    let s = rig.ctl.snapshot();
    assert_eq!(s.heading_source, HeadingSource::Gyro);
    assert_eq!(rig.status().heading_source, HeadingSource::Gyro);
    assert!((s.gyro_bias - bias).abs() < 1e-7, "bias {}", s.gyro_bias);
    // Frames at 50..995 ms (the standstill began at the first step, t = 0).
    assert_eq!(s.gyro_bias_samples, 190);
    let before = rig.ctl.pose().heading;
    // 50 ms at the uncorrected rate (and 1 ms more: the first frame counts from the step
    // after it), then nothing.
    assert!(
        (before - bias * 0.051).abs() < 2e-6,
        "heading {before} after the standstill"
    );
    rig.run_with_gyro(100, bias, &mut seq);
    assert!((rig.ctl.pose().heading - before).abs() < 1e-6);

    // Pushed forward at 0.2 m/s with the wheels turning (not at rest from the step that
    // sees them turn: no more bias samples) while the gyro reads 0.5 rad/s: the rotation is
    // the gyro's less the bias, the translation the wheels'.
    let wheel = 0.2 / 0.076;
    rig.speed = [wheel, -wheel, wheel, -wheel];
    rig.gyro(bias, seq);
    seq += 1;
    rig.tick();
    let samples = rig.ctl.snapshot().gyro_bias_samples;
    let before = rig.ctl.pose().heading;
    rig.run_with_gyro(1000, 0.5 + bias, &mut seq);
    let s = rig.ctl.snapshot();
    assert_eq!(s.gyro_bias_samples, samples);
    let turned = rig.ctl.pose().heading - before;
    // From the first frame at the new rate on: 996 steps.
    assert!((turned - 0.5 * 0.996).abs() < 1e-4, "turned {turned} rad");
    assert!((s.measured.wz - 0.5).abs() < 1e-6, "wz {}", s.measured.wz);
    assert!((rig.odom_velocity().wz - 0.5).abs() <= 0.0005);
    // 0.2 m along an arc turning 0.5 rad: the chord's length 2 sin(0.25) / 0.5 * 0.2.
    let p = rig.ctl.pose();
    let chord = p.x.hypot(p.y);
    let want = 2.0 * (0.25f32).sin() / 0.5 * 0.2;
    assert!((chord - want).abs() < 2e-3, "chord {chord}, want {want}");
    assert!(
        p.y > 0.04,
        "the arc bends left (counter-clockwise): y {}",
        p.y
    );
}

#[test]
fn the_bias_is_not_learned_while_moving_or_when_switched_off() {
    // Enabled and commanded to drive, the wheels still at rest (just starting): not a
    // standstill.
    let mut rig = Rig::new(gyro_config());
    let mut seq = 0;
    rig.enable();
    for _ in 0..50 {
        rig.twist(0.3, 0.0, 0.0);
        rig.run_with_gyro(10, 0.01, &mut seq);
    }
    assert_eq!(rig.ctl.snapshot().gyro_bias_samples, 0);

    let mut config = gyro_config();
    config.odometry.gyro_bias_estimation = false;
    let mut rig = Rig::new(config);
    rig.run_with_gyro(1000, 0.01, &mut seq);
    let s = rig.ctl.snapshot();
    assert_eq!((s.gyro_bias, s.gyro_bias_samples), (0.0, 0));
    // The whole bias turns the heading: 0.01 rad/s for 999 steps.
    assert!((rig.ctl.pose().heading - 0.00999).abs() < 2e-5);
}

#[test]
fn a_silent_gyro_hands_the_heading_to_the_wheels_and_takes_it_back() {
    use firmware::control::HeadingSource;
    let mut rig = Rig::new(gyro_config());
    let mut seq = 0;
    // Not heard yet: the wheels, and the reason.
    rig.run_ms(200);
    assert_eq!(rig.status().heading_source, HeadingSource::WheelsGyroSilent);
    rig.run_with_gyro(300, 0.0, &mut seq);
    assert_eq!(rig.status().heading_source, HeadingSource::Gyro);

    // Driving, the gyro reads a turn the wheels do not see (the wheels say straight).
    rig.enable();
    let wheel = 0.2 / 0.076;
    rig.speed = [wheel, -wheel, wheel, -wheel];
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        rig.run_with_gyro(10, 0.3, &mut seq);
    }
    // The last frame went out at the last multiple of 5 ms; then silence.
    let last_frame_us = (rig.now_us - 1000) / 5000 * 5000;
    let (heading, heading_us) = (rig.ctl.pose().heading, rig.now_us);
    let mut fell_back = None;
    // 200 ms: a STATUS goes out after the fallback.
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        for _ in 0..10 {
            let t = rig.now_us;
            rig.tick();
            if fell_back.is_none() && rig.ctl.heading_source() == HeadingSource::WheelsGyroSilent {
                fell_back = Some(t);
            }
        }
    }
    // gyro_timeout_ms = 50: the first step more than 50 ms after the last frame.
    assert_eq!(fell_back, Some(last_frame_us + 51_000));
    // A warning, not a fault: still driving.
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Enabled, Fault::None)
    );
    let s = rig.status();
    assert_eq!(
        (s.state, s.heading_source),
        (RobotState::Enabled, HeadingSource::WheelsGyroSilent)
    );
    // Meanwhile the wheels' heading (straight, but for the scripted encoders' rounding: a
    // few 1e-4 rad over these 150 ms) held, after the gyro's turn until the fallback.
    let silent_turn = rig.ctl.pose().heading - heading;
    let gyro_turn = 0.3 * (last_frame_us + 51_000 - heading_us) as f32 * 1e-6;
    assert!(
        (silent_turn - gyro_turn).abs() < 5e-4,
        "turned {silent_turn} rad during the silence, the gyro {gyro_turn}"
    );

    // Back: a fresh frame (a restarted node counts from anywhere) makes the gyro the source
    // at the next step.
    seq = 0;
    rig.gyro(0.3, seq);
    seq += 1;
    rig.tick();
    assert_eq!(rig.ctl.heading_source(), HeadingSource::Gyro);
    let h = rig.ctl.pose().heading;
    rig.twist(0.2, 0.0, 0.0);
    rig.run_with_gyro(99, 0.3, &mut seq);
    let back = rig.ctl.pose().heading - h;
    assert!((back - 0.3 * 0.099).abs() < 1e-4, "{back}");
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn malformed_and_repeated_imu_frames_are_counted_and_not_used() {
    use firmware::control::HeadingSource;
    let mut rig = Rig::new(gyro_config());
    let mut seq = 0;
    rig.run_with_gyro(100, 0.0, &mut seq);
    let imu = |data: &[u8]| {
        CanFrame::standard(embedded_can::StandardId::new(0x304).unwrap(), data).unwrap()
    };
    let with = |rate: f32| {
        let mut d = [0u8; 8];
        d[..4].copy_from_slice(&rate.to_le_bytes());
        d[4] = 200;
        d
    };
    // For 200 ms only malformed frames, every 5 ms: wrong DLC, NaN, -inf, 36 rad/s.
    let bad: [&[u8]; 4] = [
        &[0; 7],
        &with(f32::NAN),
        &with(f32::NEG_INFINITY),
        &with(36.0),
    ];
    for i in 0..40 {
        rig.raw(imu(bad[i % 4]));
        rig.run_ms(5);
    }
    let s = rig.ctl.snapshot();
    assert_eq!(s.heading_source, HeadingSource::WheelsGyroSilent);
    let e = s.rx_errors;
    assert_eq!((e.wrong_dlc, e.non_finite, e.out_of_range), (10, 20, 10));
    assert_eq!(e.unknown_id, 0);
    rig.run_ms(100);
    let (_, c) = rig.counters();
    assert_eq!((c.wrong_dlc, c.non_finite, c.out_of_range), (10, 20, 10));
    assert_eq!(rig.status().rx_errors, 40);
    assert_eq!(rig.status().heading_source, HeadingSource::WheelsGyroSilent);

    // A node stuck on one frame: the first is taken, its repeats are counted and do not
    // keep the gyro alive (not even after the silence they cause).
    let repeats_before = rig.ctl.snapshot().repeated_seq;
    for _ in 0..40 {
        rig.gyro(0.7, 9);
        rig.run_ms(5);
    }
    let s = rig.ctl.snapshot();
    assert_eq!(s.repeated_seq - repeats_before, 39);
    assert_eq!(s.heading_source, HeadingSource::WheelsGyroSilent);
    // It turned the heading only while its one frame was fresh: 0.7 rad/s for 50 ms.
    assert_eq!(s.state, RobotState::Disabled);
    rig.run_ms(100);
    assert_eq!(rig.counters().1.repeated_seq, 39);
}

#[test]
fn without_a_gyro_configured_imu_frames_change_nothing() {
    use firmware::control::HeadingSource;
    // The same drive, one rig hearing an IMU that reads 0.5 rad/s, one hearing none: every
    // frame the core sends is the same (STATUS.heading_source stays WHEELS).
    let drive = |imu: bool| {
        let mut rig = Rig::dji();
        let mut seq = 0;
        rig.run_ms(50);
        rig.enable();
        let wheel = 0.2 / 0.076;
        rig.speed = [wheel, -wheel, wheel, -wheel];
        for _ in 0..50 {
            rig.twist(0.2, 0.0, 0.0);
            if imu {
                rig.run_with_gyro(10, 0.5, &mut seq);
            } else {
                rig.run_ms(10);
            }
        }
        rig
    };
    let (with, without) = (drive(true), drive(false));
    assert_eq!(with.log, without.log);
    assert_eq!(with.ctl.heading_source(), HeadingSource::Wheels);
    assert_eq!(with.status().heading_source, HeadingSource::Wheels);
    assert_eq!(with.ctl.pose(), without.ctl.pose());
}
