//! The ODrive axis: its watchdog and its velocity loop.

use core::f64::consts::TAU;

use firmware::protocol::odrive::{AxisState, Command, ControlMode, InputMode};
use hostsim::nodes::plant::odrive::{ESTOP_REQUESTED, WATCHDOG_TIMER_EXPIRED};
use hostsim::nodes::plant::{
    Drive, OdriveAxis, OdriveFeedback, OdriveParams, Plant, Shaft, WHEELS, Wheel,
};
use kinematics::{ChassisVelocity, MecanumKinematics};

#[test]
fn odrive_watchdog_trips_after_its_timeout() {
    let params = OdriveParams {
        watchdog_timeout: Some(0.1),
        ..OdriveParams::default()
    };
    let mut axis = OdriveAxis::new(params).expect("valid");
    let rest = Shaft::default();
    axis.apply(&Command::SetAxisState(AxisState::ClosedLoopControl));
    assert_eq!(axis.axis_state(), AxisState::ClosedLoopControl);
    // Fed every 10 ms for 0.5 s: no trip.
    for k in 0..5000 {
        if k % 100 == 0 {
            axis.apply(&Command::SetInputVel {
                vel: 1.0,
                torque_ff: 0.0,
            });
        }
        axis.advance(1e-4, rest);
    }
    assert_eq!(axis.axis_state(), AxisState::ClosedLoopControl);
    assert_eq!(axis.errors(), 0);
    // Not fed after this: still running at 95 ms, tripped by 105 ms.
    axis.set_input_vel(1.0, 0.0);
    for _ in 0..950 {
        axis.advance(1e-4, rest);
    }
    assert_eq!(axis.axis_state(), AxisState::ClosedLoopControl);
    for _ in 0..100 {
        axis.advance(1e-4, rest);
    }
    assert_eq!(axis.axis_state(), AxisState::Idle);
    assert_eq!(axis.errors() & WATCHDOG_TIMER_EXPIRED, 0x0100_0000);
    assert_eq!(
        axis.heartbeat().axis_error & WATCHDOG_TIMER_EXPIRED,
        WATCHDOG_TIMER_EXPIRED
    );
    assert_eq!(axis.advance(1e-4, rest), 0.0, "idle: no torque");
    // Refuses closed loop until the errors are cleared.
    axis.apply(&Command::SetAxisState(AxisState::ClosedLoopControl));
    assert_eq!(axis.axis_state(), AxisState::Idle);
    assert_eq!(
        axis.apply(&Command::GetError),
        Some(OdriveFeedback::Error {
            active_errors: WATCHDOG_TIMER_EXPIRED,
            disarm_reason: WATCHDOG_TIMER_EXPIRED
        })
    );
    axis.apply(&Command::ClearErrors { identify: false });
    axis.apply(&Command::SetAxisState(AxisState::ClosedLoopControl));
    assert_eq!(axis.axis_state(), AxisState::ClosedLoopControl);
    axis.apply(&Command::Estop);
    assert_eq!(axis.axis_state(), AxisState::Idle);
    assert_eq!(axis.errors(), ESTOP_REQUESTED);

    // Disabled by default: a second without a setpoint does nothing.
    let mut axis = OdriveAxis::default();
    axis.apply(&Command::SetAxisState(AxisState::ClosedLoopControl));
    for _ in 0..10_000 {
        axis.advance(1e-4, rest);
    }
    assert_eq!(axis.axis_state(), AxisState::ClosedLoopControl);
    assert_eq!(axis.errors(), 0);
}

/// Puts every axis in closed loop with velocity `wheel` (rad/s per wheel, positive forward).
pub(super) fn odrive_command(plant: &mut Plant<OdriveAxis>, wheel: [f64; WHEELS]) {
    let inverted = plant.inverted();
    for w in Wheel::ALL {
        let i = w.index();
        let sign = if inverted[i] { -1.0 } else { 1.0 };
        let gear = plant.drive(w).gear_ratio();
        let vel = (sign * wheel[i] * gear / TAU) as f32;
        let axis = plant.drive_mut(w);
        axis.apply(&Command::SetInputVel {
            vel,
            torque_ff: 0.0,
        });
    }
}

#[test]
fn odrive_velocity_loop_reaches_its_setpoint() {
    let mut plant = Plant::odrive_example().expect("valid");
    let kin = MecanumKinematics::standard(0.15, 0.125, 0.05).expect("valid");
    let setpoints = kin.inverse(ChassisVelocity::new(1.0, 0.0, 0.0)).0;
    for w in Wheel::ALL {
        let axis = plant.drive_mut(w);
        axis.apply(&Command::SetControllerMode {
            control_mode: ControlMode::VelocityControl,
            input_mode: InputMode::VelRamp,
        });
        axis.apply(&Command::SetAxisState(AxisState::ClosedLoopControl));
    }
    let (mut encoders, mut heartbeats) = ([0_usize; WHEELS], [0_usize; WHEELS]);
    let mut last_vel = [0.0; WHEELS];
    for _ in 0..200 {
        odrive_command(&mut plant, setpoints);
        plant.step(0.01).expect("valid");
        for fb in plant.take_feedback() {
            let i = fb.wheel.index();
            match fb.feedback {
                OdriveFeedback::EncoderEstimates { vel, .. } => {
                    encoders[i] += 1;
                    last_vel[i] = vel;
                    assert_eq!(fb.time_ns % 10_000_000, 0);
                }
                OdriveFeedback::Heartbeat(hb) => {
                    heartbeats[i] += 1;
                    assert_eq!(hb.axis_state, AxisState::ClosedLoopControl);
                    assert_eq!(fb.time_ns % 100_000_000, 0);
                }
                OdriveFeedback::Error { .. } => unreachable!("not requested"),
            }
        }
    }
    // 2 s: estimates every 10 ms, heartbeats every 100 ms.
    assert_eq!(encoders, [200; WHEELS]);
    assert_eq!(heartbeats, [20; WHEELS]);
    for w in Wheel::ALL {
        let i = w.index();
        let target = plant.drive(w).vel_setpoint();
        println!(
            "{w:?}: setpoint {target:.3} rev/s, estimate {:.3} rev/s",
            last_vel[i]
        );
        assert!((last_vel[i] - target).abs() < 0.01 * target.abs(), "{w:?}");
    }
    let v = plant.velocity();
    println!("chassis {v:?}");
    assert!((v.vx - 1.0).abs() < 0.02 && v.vy.abs() < 0.01 && v.wz.abs() < 0.01);
}
