//! The stuck-encoder watch of DJI rotors (`docs/control.md`, "Stuck encoder").

use crate::rig::*;

/// The rotor speed (rpm) a DJI rig reports for wheel `w` now.
fn rig_rpm(rig: &Rig, w: usize) -> i16 {
    let Drive::Dji { gear_ratio, .. } = rig.config.drive else {
        panic!("not a DJI config")
    };
    (rig.speed[w] * gear_ratio * 60.0 / std::f32::consts::TAU).round() as i16
}

/// A DJI rig enabled and driving with `twist`, its wheels following the setpoints exactly.
fn dji_driving(twist: [f32; 3], ms: u64) -> Rig {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    follow(&mut rig, twist, ms);
    rig
}

#[test]
fn a_stuck_encoder_that_still_reports_speed_faults_within_its_window() {
    use firmware::control::ENCODER_STUCK_SPINNING_US;
    // Cruising at 0.5 m/s: wheel 6.6 rad/s, rotor ~1200 rpm.
    let mut rig = dji_driving([0.5, 0.0, 0.0], 300);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    // RL's encoder freezes: the same angle and the same rpm in every frame from now on.
    let angle = rig.rotor[2].rem_euclid(8192.0) as u16;
    rig.frozen[2] = Some((angle, rig_rpm(&rig, 2)));
    let t_stuck = rig.now_us;
    let t_fault = rig
        .run_until(100, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the stuck encoder is found");
    assert_eq!(rig.ctl.fault(), Fault::EncoderStuck);
    // The first repeated angle arrives one feedback period after the freeze, is seen by the
    // next step, and the interval must then last the window.
    let latency = t_fault - t_stuck;
    assert!(
        (ENCODER_STUCK_SPINNING_US..=ENCODER_STUCK_SPINNING_US + 3_000).contains(&latency),
        "{latency} us"
    );
    assert!(dji_currents(&rig.tick()).is_some_and(all_zero));
    // A reset while it is still stuck faults again; once the encoder is back, reset clears.
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(2);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Fault, Fault::EncoderStuck)
    );
    rig.frozen[2] = None;
    rig.speed = [0.0; 4];
    rig.run_ms(2);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(50);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
}

#[test]
fn an_encoder_reading_zero_while_driven_and_the_others_turn_faults_within_its_window() {
    use firmware::control::ENCODER_STUCK_DRAGGED_US;
    // Turning while driving: every wheel at a different speed.
    let mut rig = dji_driving([0.4, 0.1, 0.8], 300);
    // FR's encoder dies reading zero speed at a fixed angle; the wheel itself keeps turning
    // with the chassis, so its PI sees a full error and drives it hard.
    let angle = rig.rotor[1].rem_euclid(8192.0) as u16;
    rig.frozen[1] = Some((angle, 0));
    let t_stuck = rig.now_us;
    let t_fault = rig
        .run_until(200, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the dead encoder is found");
    assert_eq!(rig.ctl.fault(), Fault::EncoderStuck);
    let latency = t_fault - t_stuck;
    assert!(
        (ENCODER_STUCK_DRAGGED_US..=ENCODER_STUCK_DRAGGED_US + 3_000).contains(&latency),
        "{latency} us"
    );
}

#[test]
fn a_genuinely_stalled_drive_is_not_a_stuck_encoder() {
    // Commanded forward, but the robot is against a wall: every rotor stands at rpm 0, every
    // PI saturates at max_current, for a whole second.
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..100 {
        rig.twist(0.8, 0.0, 0.0);
        rig.run_ms(10);
    }
    let amps = dji_currents(&rig.tick()).unwrap();
    assert!(
        amps.iter()
            .all(|a| a.abs() >= rig.config.limits.max_current - 0.01)
    );
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Enabled, Fault::None)
    );
    // Turning on the spot against the obstacle: the same.
    for _ in 0..50 {
        rig.twist(0.0, 0.0, 1.0);
        rig.run_ms(10);
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn normal_driving_never_looks_like_a_stuck_encoder() {
    let mut rig = dji_driving([0.0, 0.0, 0.0], 20);
    // Starts, stops, reversals (every wheel passes through zero speed), slow creeping (a
    // rotor moving a count at a time), strafes and turns on the spot.
    for twist in [
        [0.5, 0.0, 0.0],
        [-0.5, 0.0, 0.0],
        [0.0, 0.4, 0.0],
        [0.0, -0.4, 1.5],
        [0.002, 0.0, 0.0],
        [0.3, 0.3, -2.0],
        [0.0, 0.0, 0.0],
        [1.5, -0.5, 0.5],
    ] {
        follow(&mut rig, twist, 400);
        assert_eq!(
            (rig.ctl.state(), rig.ctl.fault()),
            (RobotState::Enabled, Fault::None),
            "{twist:?}"
        );
    }
}
