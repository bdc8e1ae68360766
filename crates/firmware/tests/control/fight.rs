//! Wheels that fight (`docs/control.md`, "Wheels that fight").

use crate::rig::*;

/// Enables, drives forward at `vx`, and from `from_ms` on makes wheel `wheel`'s motor report
/// `motor_speed` (its own sign) while the others follow their setpoints exactly. Returns the
/// rig and, if it faulted, the time of the faulting step µs after the onset of the fight:
/// the first step of the interval running at the fault in which the residual of the
/// currents the motors acted on (the oracle: the rig's current frames, in the wheels' sense,
/// through the configuration's kinematics) was at or above the fight threshold.
fn fight_run(wheel: usize, motor_speed: f32, vx: f32, from_ms: u64) -> (Rig, Option<u64>) {
    fight_run_stalling(wheel, motor_speed, vx, from_ms, None)
}

/// [`fight_run`], with the loop stalled once, if `stall` says so: before step `k` the clock
/// jumps `us` (a late runner), so that step is the only one the core sees of that time.
fn fight_run_stalling(
    wheel: usize,
    motor_speed: f32,
    vx: f32,
    from_ms: u64,
    stall: Option<(u64, u64)>,
) -> (Rig, Option<u64>) {
    use firmware::control::FIGHT_CURRENT_FRACTION;
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    let kin = rig.config.kinematics().unwrap();
    let threshold = FIGHT_CURRENT_FRACTION * rig.config.limits.max_current;
    let mirrored = |i: usize| if i % 2 == 1 { -1.0 } else { 1.0 };
    let mut onset = None;
    for k in 0..1000u64 {
        if k % 10 == 0 {
            rig.twist(vx, 0.0, 0.0);
        }
        let snap = rig.ctl.snapshot();
        for i in 0..4 {
            rig.speed[i] = mirrored(i) * snap.wheel_setpoints.0[i];
        }
        if k >= from_ms {
            rig.speed[wheel] = motor_speed;
        }
        // The currents the motors act on at this step: the last step's, wheel sense.
        let acting = kinematics::WheelSpeeds(snap.currents);
        let (_, residual) = kin.forward_with_residual(&acting);
        if residual.rms() >= threshold {
            onset.get_or_insert(rig.now_us);
        } else {
            onset = None;
        }
        if let Some((at_k, us)) = stall
            && at_k == k
        {
            rig.now_us += us;
        }
        let out = rig.tick();
        let amps = dji_currents(&out).unwrap();
        if rig.ctl.state() == RobotState::Fault {
            assert!(all_zero(amps), "zero torque at once: {amps:?}");
            let at = rig.now_us - TICK_US;
            return (rig, onset.map(|s| at - s));
        }
    }
    (rig, None)
}

#[test]
fn a_wheel_that_does_not_follow_while_the_others_do_is_a_fight_within_the_window() {
    use firmware::control::FIGHT_WINDOW_US;
    // FL commanded forward at 0.5 m/s, its motor turning backwards at 5 rad/s; then RR
    // (mirrored) at 1 m/s = 13.2 rad/s but held at 2 rad/s (blocked); then RR turning
    // backwards. Each time the three others follow: the currents fight.
    for (wheel, motor_speed, vx, from_ms) in
        [(0, -5.0, 0.5, 100), (3, -2.0, 1.0, 0), (3, 1.5, 1.0, 0)]
    {
        let (rig, latency) = fight_run(wheel, motor_speed, vx, from_ms);
        assert_eq!(
            (rig.ctl.state(), rig.ctl.fault()),
            (RobotState::Fault, Fault::WheelFight),
            "wheel {wheel} at {motor_speed}"
        );
        let latency = latency.expect("a fight before the fault");
        assert!(
            (FIGHT_WINDOW_US..=FIGHT_WINDOW_US + 2_000).contains(&latency),
            "wheel {wheel}: {latency} µs after the onset"
        );
    }
    let (mut rig, _) = fight_run(0, -5.0, 0.5, 100);
    rig.send(Command::StatusRequest);
    rig.tick();
    assert_eq!(rig.status().fault, Fault::WheelFight);
    // Latched: a twist does not move it, a reset clears it.
    rig.speed = [0.0; 4];
    rig.twist(0.5, 0.0, 0.0);
    rig.run_ms(5);
    assert_eq!(rig.ctl.state(), RobotState::Fault);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
}

#[test]
fn a_stalled_loop_does_not_judge_a_fight_on_one_late_look() {
    use firmware::control::FIGHT_WINDOW_US;
    // FL lags from 100 ms on; 20 ms later the loop stalls for 100 ms (a late runner): the
    // window has passed in time but the core saw one step of it. It faults only once it has
    // seen the window's 60 steps: the window and the stall after the onset.
    let stall_us = FIGHT_WINDOW_US + 40_000;
    let (rig, latency) = fight_run_stalling(0, -5.0, 0.5, 100, Some((120, stall_us)));
    assert_eq!(rig.ctl.fault(), Fault::WheelFight);
    let latency = latency.expect("a fight before the fault");
    assert!(
        (FIGHT_WINDOW_US + stall_us..=FIGHT_WINDOW_US + stall_us + 2_000).contains(&latency),
        "{latency} µs after the onset"
    );
}

#[test]
fn wheels_that_follow_do_not_fight_however_hard_they_accelerate() {
    // Full speed forward from rest and back, every wheel following its setpoint: large
    // currents, no residual.
    let (rig, latency) = fight_run(0, 0.0, 2.5, u64::MAX);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault(), latency),
        (RobotState::Enabled, Fault::None, None)
    );
}
