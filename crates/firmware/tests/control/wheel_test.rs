//! The wheel test (bring-up check) and the wheel runaway watch.

use crate::rig::*;

fn wheel_test(wheel: u8, speed: f32, duration_ms: u16) -> Command {
    Command::WheelTest(robot::WheelTest {
        wheel,
        speed,
        duration_ms,
    })
}

/// The `WHEEL_TEST_RESULT`s in the rig's log, with their times.
fn test_results(rig: &Rig) -> Vec<(u64, robot::WheelTestResult)> {
    rig.log
        .iter()
        .filter_map(|(t, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::WheelTestResult(r)) => Some((*t, r)),
            _ => None,
        })
        .collect()
}

#[test]
fn a_wheel_test_drives_that_wheel_alone_gently_and_reports_how_far_it_turned() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    // FR (wheel 1, mounted mirrored) at 3 rad/s for 500 ms.
    rig.send(wheel_test(1, 3.0, 500));
    let limit = firmware::control::WHEEL_TEST_CURRENT_FRACTION * rig.config.limits.max_current;
    let start = rig.now_us;
    let mut peak = 0.0f32;
    for _ in 0..500 {
        let out = rig.tick();
        assert_eq!(rig.ctl.state(), RobotState::WheelTest);
        let amps = dji_currents(&out).expect("current frames in the test");
        // Only ESC 2 (FR) gets current, within a quarter of max_current, pushing forward
        // (negative on the mirrored motor).
        assert_eq!((amps[0], amps[2], amps[3]), (0.0, 0.0, 0.0), "{amps:?}");
        assert!(
            amps[1] <= 0.0 && amps[1] >= -limit - 20.0 / 16384.0,
            "{amps:?}"
        );
        peak = peak.min(amps[1]);
        // The wheel follows: its motor turns backwards (mirrored) at 3 rad/s.
        rig.speed[1] = -3.0;
    }
    let out = rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert!(all_zero(dji_currents(&out).unwrap()));
    let results = test_results(&rig);
    assert_eq!(results.len(), 1, "{results:?}");
    let (t, r) = results[0];
    assert_eq!(
        t - start,
        500_000,
        "the result goes out at the step the test ends"
    );
    assert_eq!((r.wheel, r.outcome), (1, robot::TestOutcome::Done));
    // 499 ms at 3 rad/s (the first step's feedback still reported 0).
    assert!((r.angle - 1.497).abs() < 0.01, "angle {}", r.angle);
    // The first step's, kp · 3 rad/s + ki · 3 rad/s · 1 ms, in the wheel's sense.
    let g = rig.config.gains;
    let first = g.kp * 3.0 + g.ki * 3.0 * 1e-3;
    assert!(
        (r.peak_current - first).abs() < 0.01 && (peak + first).abs() < 0.01,
        "{r:?}"
    );
    // The robot stays disabled and can be enabled as usual.
    rig.speed[1] = 0.0;
    rig.run_ms(50);
    rig.enable();
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn a_wheel_test_is_refused_unless_disabled_and_ends_on_disable_or_estop() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    rig.send(wheel_test(0, 2.0, 1000));
    rig.run_ms(2);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    let r = test_results(&rig);
    assert_eq!(r.len(), 1);
    assert_eq!(
        (r[0].1.wheel, r[0].1.outcome),
        (0, robot::TestOutcome::Refused)
    );

    rig.send(Command::Mode(ModeRequest::Disable));
    rig.send(wheel_test(2, -2.0, 1000));
    rig.run_ms(100);
    assert_eq!(rig.ctl.state(), RobotState::WheelTest);
    rig.enable();
    rig.tick();
    assert_eq!(
        rig.ctl.state(),
        RobotState::WheelTest,
        "enable is ignored meanwhile"
    );
    rig.send(Command::Mode(ModeRequest::Disable));
    let out = rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert!(all_zero(dji_currents(&out).unwrap()));
    let r = test_results(&rig);
    assert_eq!(
        (r[1].1.wheel, r[1].1.outcome),
        (2, robot::TestOutcome::Stopped)
    );

    rig.send(wheel_test(3, 2.0, 1000));
    rig.run_ms(10);
    rig.send(Command::Estop);
    let out = rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    assert!(all_zero(dji_currents(&out).unwrap()));
    let r = test_results(&rig);
    assert_eq!(
        (r[2].1.wheel, r[2].1.outcome),
        (3, robot::TestOutcome::Stopped)
    );
    rig.send(wheel_test(3, 2.0, 1000));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    assert_eq!(test_results(&rig)[3].1.outcome, robot::TestOutcome::Refused);
}

#[test]
fn an_odrive_wheel_test_puts_only_that_axis_in_closed_loop() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.send(wheel_test(2, 4.0, 200));
    let out = rig.tick();
    let Drive::Odrive {
        node_ids,
        gear_ratio,
        ..
    } = rig.config.drive
    else {
        unreachable!()
    };
    let closed: Vec<u8> = out
        .iter()
        .filter_map(|f| odrive::Command::decode(f).ok())
        .filter(|a| a.msg == odrive::Command::SetAxisState(AxisState::ClosedLoopControl))
        .map(|a| a.node.get())
        .collect();
    assert_eq!(closed, vec![node_ids[2]]);
    let vels = rig
        .run_ms(20)
        .iter()
        .find_map(|o| odrive_vels(&rig.config, o))
        .expect("velocity setpoints in the test");
    let want = 4.0 * gear_ratio / core::f32::consts::TAU; // RL: not mirrored
    assert_eq!(vels[..2], [0.0, 0.0]);
    assert!((vels[2] - want).abs() < 1e-3 && vels[3] == 0.0, "{vels:?}");
    rig.run_ms(200);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert_eq!(test_results(&rig)[0].1.outcome, robot::TestOutcome::Done);
}

#[test]
fn a_wheel_test_whose_wheel_runs_the_other_way_faults() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.send(wheel_test(0, 3.0, 2000));
    // The motor's current and its encoder disagree: positive feedback. (One wheel driven:
    // no fight to see, the runaway watch is what catches it.)
    use firmware::control::{RUNAWAY_SATURATION, RUNAWAY_WINDOW_US, WHEEL_TEST_CURRENT_FRACTION};
    let limit = WHEEL_TEST_CURRENT_FRACTION * rig.config.limits.max_current;
    let (mut saturated, mut faulted) = (None, None);
    let t0 = rig.now_us;
    for k in 0..2000u64 {
        rig.speed[0] = -0.01 * k as f32;
        let amps = dji_currents(&rig.tick()).unwrap();
        if rig.ctl.state() == RobotState::Fault {
            faulted = Some(rig.now_us - TICK_US);
            break;
        }
        if saturated.is_none() && amps[0].abs() >= RUNAWAY_SATURATION * limit {
            saturated = Some(rig.now_us - TICK_US);
        }
    }
    // Saturated within a few ms; the window over, the fault comes at the first step whose
    // feedback turns at least RUNAWAY_MIN_SPEED (1 rad/s) the other way: 100 ms in.
    let (saturated, faulted) = (saturated.expect("saturated"), faulted.expect("a runaway"));
    assert!(
        faulted - saturated >= RUNAWAY_WINDOW_US,
        "{} µs after saturation",
        faulted - saturated
    );
    assert!(
        saturated - t0 < 10_000,
        "saturated {} µs in",
        saturated - t0
    );
    assert!(
        (99_000..=102_000).contains(&(faulted - t0)),
        "faulted {} µs in",
        faulted - t0
    );
    assert_eq!(rig.ctl.fault(), Fault::WheelRunaway);
    rig.tick();
    let r = test_results(&rig);
    assert_eq!(
        (r[0].1.wheel, r[0].1.outcome),
        (0, robot::TestOutcome::Fault)
    );
    assert!(r[0].1.angle < 0.0, "{:?}", r[0]);
}
