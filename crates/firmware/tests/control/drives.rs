//! What the drives are sent: ODrive setpoints and modes, DJI currents and their PI.

use crate::rig::*;

#[test]
fn odrive_enable_sends_mode_and_closed_loop_then_twist_gives_exact_setpoints() {
    let mut rig = Rig::odrive();
    rig.run_ms(20);
    rig.enable();
    let out = rig.tick();
    let mut seen_mode = 0;
    let mut seen_closed = 0;
    for f in &out {
        match odrive::Command::decode(f).map(|a| a.msg) {
            Ok(odrive::Command::SetControllerMode { control_mode, .. }) => {
                assert_eq!(control_mode, ControlMode::VelocityControl);
                seen_mode += 1;
            }
            Ok(odrive::Command::SetAxisState(AxisState::ClosedLoopControl)) => seen_closed += 1,
            _ => {}
        }
    }
    assert_eq!((seen_mode, seen_closed), (4, 4), "{out:?}");

    // Forward 0.5 m/s; ramp at 4 m/s² takes 125 ms. Keep commanding every 20 ms.
    for _ in 0..10 {
        rig.twist(0.5, 0.0, 0.0);
        rig.run_ms(20);
    }
    rig.twist(0.5, 0.0, 0.0);
    let vels = {
        let mut v = None;
        for _ in 0..5 {
            let o = rig.tick();
            if let Some(x) = odrive_vels(&rig.config, &o) {
                v = Some(x);
            }
        }
        v.expect("setpoints every 5 ms at 200 Hz")
    };
    // Wheel speed 0.5 / 0.05 = 10 rad/s; motor 10 * 5 / 2π rev/s; right side mirrored.
    let want = 10.0 * 5.0 / std::f32::consts::TAU;
    let expect = [want, -want, want, -want];
    for (got, want) in vels.iter().zip(expect) {
        assert!((got - want).abs() < 1e-4, "{vels:?} vs {expect:?}");
    }
}

#[test]
fn dji_twist_gives_currents_with_mounting_signs_and_pi_action() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    rig.twist(1.0, 0.0, 0.0);
    // First step: commanded twist is one ramp increment, 4 m/s² * 1 ms = 4 mm/s.
    let out = rig.tick();
    let amps = dji_currents(&out).expect("a current frame every period");
    let g = rig.config.gains;
    let sp = 0.004 / 0.076; // wheel rad/s
    let want = g.kp * sp + g.ki * sp * 1e-3;
    // Motors report zero speed, so the error is the setpoint; right side mirrored.
    let expect = [want, -want, want, -want];
    for (got, want) in amps.iter().zip(expect) {
        // The C620 resolution is 20/16384 A.
        assert!(
            (got - want).abs() <= 20.0 / 16384.0,
            "{amps:?} vs {expect:?}"
        );
    }
    // Held error: the integrator grows, the current rises, and it stops at max_current.
    for _ in 0..50 {
        rig.twist(1.0, 0.0, 0.0);
        rig.run_ms(10);
    }
    let amps = dji_currents(&rig.tick()).unwrap();
    let max = rig.config.limits.max_current;
    for (i, a) in amps.iter().enumerate() {
        let want = if i % 2 == 0 { max } else { -max };
        assert!(
            (a - want).abs() <= 20.0 / 16384.0,
            "saturated at ±max: {amps:?}"
        );
    }
}

#[test]
fn anti_windup_releases_at_once_when_the_wheel_catches_up() {
    let mut rig = Rig::dji();
    rig.run_ms(5);
    rig.enable();
    for _ in 0..100 {
        rig.twist(1.0, 0.0, 0.0);
        rig.run_ms(10);
    }
    // The wheels suddenly reach the setpoint (1 m/s / 0.076 m): with the integrator clamped
    // at the output limit the current falls below the limit on the very next step.
    let sp = 1.0 / 0.076;
    rig.speed = [sp, -sp, sp, -sp];
    rig.twist(1.0, 0.0, 0.0);
    let amps = dji_currents(&rig.tick()).unwrap();
    assert!(amps[0] <= rig.config.limits.max_current, "{amps:?}");
    rig.speed = [sp + 2.0, -(sp + 2.0), sp + 2.0, -(sp + 2.0)];
    rig.twist(1.0, 0.0, 0.0);
    let amps = dji_currents(&rig.tick()).unwrap();
    assert!(amps[0] < rig.config.limits.max_current - 1.0, "{amps:?}");
}
