//! ODrive axes: errors, their clearing, position jumps and axis states.

use crate::rig::*;

/// Clear_Errors frames in a step's output: the node ids they go to.
fn clear_errors_nodes(out: &Outbox) -> Vec<u8> {
    out.iter()
        .filter_map(|f| match odrive::Command::decode(f) {
            Ok(a) if matches!(a.msg, odrive::Command::ClearErrors { .. }) => Some(a.node.get()),
            _ => None,
        })
        .collect()
}

#[test]
fn a_reset_clears_an_odrive_drive_error_and_the_robot_can_drive_again() {
    let mut rig = odrive_driving();
    rig.axis_error[1] = 0x0100_0000; // the axis watchdog expired
    rig.run_until(150, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the heartbeat's error faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveError);
    rig.run_ms(300);
    assert_eq!(rig.ctl.state(), RobotState::Fault, "latched");

    rig.send(Command::Mode(ModeRequest::Reset));
    // A heartbeat sent before the drive got Clear_Errors still carries the error: ignored.
    rig.raw(odrive_heartbeat(1, AxisState::Idle, 0x0100_0000));
    let out = rig.tick();
    assert_eq!(clear_errors_nodes(&out), [0, 1, 2, 3]);
    // Three heartbeat periods later the errors are gone and nothing faulted again.
    rig.run_ms(300);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(20);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    let vels = (0..20)
        .find_map(|_| {
            let out = rig.tick();
            odrive_vels(&rig.config, &out)
        })
        .expect("setpoints at their rate");
    assert!(vels[0] > 0.0, "{vels:?}");
}

#[test]
fn an_odrive_error_whose_cause_persists_faults_again_after_the_reset() {
    let mut rig = odrive_driving();
    rig.axis_error[2] = 0x0000_0800; // a hardware fault: Clear_Errors does not remove it
    rig.error_persists[2] = true;
    rig.run_until(150, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("faults");
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    let t = rig
        .run_until(300, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the first heartbeat after the grace faults again");
    assert_eq!(rig.ctl.fault(), Fault::DriveError);
    // Heartbeats every 100 ms; the first one more than 150 ms after the clear.
    assert!(t - t_reset <= 251_000, "{} us", t - t_reset);
}

#[test]
fn an_odrive_position_jump_is_not_integrated_and_is_counted() {
    let mut rig = Rig::odrive();
    rig.run_ms(50);
    // The drive on wheel 0 reboots: its position estimate restarts 1000 turns lower.
    rig.rotor[0] -= 1000.0;
    rig.run_ms(50);
    let s = rig.ctl.snapshot();
    assert_eq!(s.rx_errors.out_of_range, 1);
    assert!(
        s.pose.x.abs() < 1e-6 && s.pose.y.abs() < 1e-6 && s.pose.heading.abs() < 1e-6,
        "{:?}",
        s.pose
    );
    // The new count is the reference from then on: driving moves the pose as usual.
    let Drive::Odrive { inverted, .. } = rig.config.drive else {
        unreachable!()
    };
    let w = 0.5 / 0.05; // the example's 50 mm wheels
    rig.speed = inverted.map(|i| if i { -w } else { w });
    rig.run_ms(1000);
    let x = rig.ctl.pose().x;
    assert!((x - 0.5).abs() < 0.02, "x = {x}");
    assert_eq!(rig.ctl.snapshot().rx_errors.out_of_range, 1);
}

#[test]
fn an_odrive_axis_that_leaves_closed_loop_while_enabled_faults() {
    // Right after the enable, a heartbeat still reporting Idle predates the request.
    let mut rig = Rig::odrive();
    rig.run_ms(150);
    rig.enable();
    rig.raw(odrive_heartbeat(3, AxisState::Idle, 0));
    rig.tick();
    rig.run_ms(10);
    rig.raw(odrive_heartbeat(3, AxisState::Idle, 0));
    rig.tick();
    assert_eq!(rig.ctl.state(), RobotState::Enabled);

    // Later, an axis reporting Idle with no error (another node commanded it, a reboot that
    // kept its errors to itself) cannot follow its setpoints: the robot faults.
    for _ in 0..20 {
        rig.twist(0.2, 0.0, 0.0);
        rig.run_ms(10);
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    rig.raw(odrive_heartbeat(3, AxisState::Idle, 0));
    rig.tick();
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Fault, Fault::DriveError)
    );
}
