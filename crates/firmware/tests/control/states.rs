//! States, their latches, motor freshness, determinism and shutdown.

use crate::rig::*;

#[test]
fn a_stale_motor_faults_within_three_feedback_periods() {
    let mut rig = Rig::dji();
    rig.run_ms(10);
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(5);
    rig.alive[2] = false; // RL goes silent
    let t_silent = rig.now_us;
    let t_fault = rig
        .run_until(50, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("stale motor faults");
    assert_eq!(rig.ctl.fault(), Fault::MotorStale);
    // Last feedback at t_silent - 1 ms; stale after 3 ms; seen at the next step.
    assert!(t_fault - t_silent <= 4_000, "{} us", t_fault - t_silent);
    // A stale motor is not online.
    rig.send(Command::StatusRequest);
    rig.tick();
    assert_eq!(rig.status().motors_online, 0b1011);
    // Fault means no torque.
    assert!(dji_currents(&rig.tick()).is_some_and(all_zero));
    // Reset while the motor is still silent faults again; back alive, reset clears it.
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Fault);
    rig.alive[2] = true;
    rig.tick();
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(5);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
}

#[test]
fn a_motor_never_seen_faults_after_the_boot_timeout() {
    let mut rig = Rig::dji();
    rig.alive[1] = false;
    let t = rig
        .run_until(2000, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("missing motor faults");
    assert_eq!(rig.ctl.fault(), Fault::MotorMissing);
    assert_eq!(
        t, 1_001_000,
        "boot timeout 1000 ms, detected on the next step"
    );
    assert_eq!(rig.status().motors_online, 0b1101);
}

#[test]
fn the_latch_holds_until_enable_and_a_fresh_command() {
    let mut rig = Rig::odrive();
    let _ = watchdog_zero_time(&mut rig, false);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    // Twists alone do nothing.
    for _ in 0..20 {
        rig.twist(0.4, 0.0, 0.0);
        let out = rig.tick();
        assert!(odrive_vels(&rig.config, &out).is_none_or(all_zero));
    }
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    // Enable alone: enabled, but holding still (no fresh command yet).
    rig.enable();
    for _ in 0..50 {
        let out = rig.tick();
        assert!(odrive_vels(&rig.config, &out).is_none_or(all_zero));
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    // A fresh command after the enable moves it.
    rig.twist(0.4, 0.0, 0.0);
    let moved = rig.run_until(20, |r, o| {
        odrive_vels(&r.config, o).is_some_and(|v| v[0] > 0.0)
    });
    assert!(moved.is_some());
}

#[test]
fn estop_latches_until_reset_then_enable_and_a_fresh_command() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..10 {
        rig.twist(0.5, 0.0, 0.0);
        rig.run_ms(10);
    }
    rig.send(Command::Estop);
    let out = rig.tick();
    assert!(
        dji_currents(&out).is_some_and(all_zero),
        "e-stop cuts torque at once"
    );
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    // Enable and twists are ignored while e-stopped.
    rig.enable();
    rig.twist(0.5, 0.0, 0.0);
    rig.run_ms(20);
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    rig.send(Command::StatusRequest);
    rig.tick();
    assert_eq!(rig.status().state, RobotState::Estop);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    rig.enable();
    rig.twist(0.5, 0.0, 0.0);
    let out = rig.tick();
    assert!(dji_currents(&out).is_some_and(|a| a[0] > 0.0));
}

#[test]
fn same_inputs_same_frames_bit_for_bit() {
    let run = || {
        let mut rig = Rig::dji();
        rig.run_ms(5);
        rig.enable();
        for k in 0..50 {
            rig.twist(0.01 * k as f32, -0.005 * k as f32, 0.02 * k as f32);
            rig.speed = [
                k as f32 * 0.1,
                -(k as f32) * 0.1,
                k as f32 * 0.12,
                -(k as f32) * 0.09,
            ];
            rig.run_ms(7);
        }
        rig.log
    };
    let (a, b) = (run(), run());
    assert!(a.len() > 300);
    assert_eq!(a, b);
}

#[test]
fn shutdown_sends_zero_and_idle() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.enable();
    rig.twist(0.3, 0.0, 0.0);
    rig.run_ms(50);
    let out = rig.ctl.shutdown();
    let mut zero = 0;
    let mut idle = 0;
    for f in &out {
        match odrive::Command::decode(f).map(|a| a.msg) {
            Ok(odrive::Command::SetInputVel { vel: 0.0, .. }) => zero += 1,
            Ok(odrive::Command::SetAxisState(AxisState::Idle)) => idle += 1,
            _ => {}
        }
    }
    assert_eq!((zero, idle), (4, 4));
    let mut dji = Rig::dji();
    dji.run_ms(5);
    assert!(dji_currents(&dji.ctl.shutdown()).is_some_and(all_zero));
}

#[test]
fn the_heartbeat_uptime_wraps_after_2_pow_32_ms() {
    let mut rig = Rig::dji();
    rig.run_ms(1);
    rig.now_us += (1u64 << 32) * 1000;
    rig.run_ms(200);
    let uptime = rig
        .log
        .iter()
        .rev()
        .find_map(|(_, f)| match robot::Telemetry::decode(f) {
            Ok(robot::Telemetry::Heartbeat(h)) => Some(h.uptime_ms),
            _ => None,
        })
        .unwrap();
    assert!((1..=201).contains(&uptime), "uptime {uptime} ms");
}
