//! The enable sequence, the cycle and the odometry from the actual velocities, and the ways
//! out of motion: a transition that does not come, an estop, quick stop, a disable.

use firmware::control::{CIA402_TRANSITION_TIMEOUT_US, DriveIssue};
use firmware::protocol::canopen::{self, Message};

use super::*;

#[test]
fn an_enable_runs_shutdown_switch_on_enable_operation_checking_each_state() {
    let mut rig = started();
    let t0 = rig.now_us;
    rig.enable();
    rig.twist(0.5, 0.0, 0.0);
    wait_enabled(&mut rig).expect("enabled");
    for node in [1, 2] {
        let words: Vec<u16> = controlwords_since(&mut rig, node, t0);
        let mut steps = words.clone();
        steps.dedup();
        assert_eq!(steps, [0x06, 0x07, 0x0F], "node {node}: {words:?}");
    }
    // Targets only once both nodes are enabled; then 0.5 m/s on 0.1 m wheels: 5 rad/s,
    // 47.7 rpm, the mirrored wheels negative.
    let mut targets = Vec::new();
    for _ in 0..400 {
        rig.twist(0.5, 0.0, 0.0);
        rig.tick();
        targets.push(last_rpdo(&rig, 1));
    }
    assert_eq!(*targets.last().unwrap(), (0x0F, 48, -48));
}

#[test]
fn the_odometry_integrates_the_actual_velocities_of_both_axes() {
    let mut rig = enabled();
    let x0 = rig.ctl.pose().x;
    for _ in 0..1000 {
        rig.twist(0.5, 0.0, 0.0);
        rig.tick();
    }
    // 1 s at 0.5 m/s (an eighth of a second of ramp at 4 m/s²: 0.03125 m less), the drive
    // reporting 477 x 0.1 rpm for 48 rpm asked: 0.49951 m/s.
    let x = rig.ctl.pose().x - x0;
    let expected = (0.5 - 0.5 * 0.125 / 2.0 / 1.0 * 1.0) * (47.7 / 48.0 * 48.0 / 47.746);
    assert!(
        (x - expected as f32).abs() < 0.01,
        "x {x}, expected {expected}"
    );
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn a_transition_that_does_not_come_faults_with_the_last_statusword() {
    let mut rig = started();
    rig.canopen.node(1).refuses_enable = true;
    let t0 = rig.now_us;
    rig.enable();
    let t = rig
        .run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("times out");
    assert_eq!(rig.ctl.fault(), Fault::DriveTransition);
    // The enable step that does not come is the third; each step counts from the last.
    let took = t - t0;
    assert!(
        took > CIA402_TRANSITION_TIMEOUT_US && took <= CIA402_TRANSITION_TIMEOUT_US + 20_000,
        "{took} µs"
    );
    assert_eq!(
        rig.ctl.drive_issue(),
        Some(DriveIssue::TransitionTimeout {
            node: 1,
            controlword: 0x0F,
            statusword: Some(sw::SWITCHED_ON)
        })
    );
    // Node 2 went through; no target reached either node meanwhile.
    assert!(rig.log.iter().all(|(_, f)| !matches!(
        canopen::decode(f),
        Ok(Message::Rpdo1 { target, .. }) if target != 0
    )));
}

#[test]
fn an_estop_quick_stops_every_node_with_zero_targets() {
    let mut rig = enabled();
    for _ in 0..200 {
        rig.twist(0.5, 0.0, 0.0);
        rig.tick();
    }
    assert_ne!(last_rpdo(&rig, 1).1, 0);
    rig.send(Command::Estop);
    rig.run_ms(5);
    assert_eq!(rig.ctl.state(), RobotState::Estop);
    assert_eq!(last_rpdo(&rig, 1), (0x02, 0, 0));
    assert_eq!(last_rpdo(&rig, 2), (0x02, 0, 0));
}

#[test]
fn a_node_left_in_quick_stop_is_sent_disable_voltage_until_it_leaves_it() {
    let mut rig = enabled();
    rig.send(Command::Estop);
    rig.run_ms(5);
    // A drive with quick stop option 5-8 stays in quick stop active.
    rig.canopen.node(1).statusword = sw::QUICK_STOP_ACTIVE;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(9);
    assert_eq!(
        last_rpdo(&rig, 1).0,
        0x00,
        "disable voltage out of quick stop"
    );
    assert_eq!(rig.canopen.node(1).statusword, sw::SWITCH_ON_DISABLED);
    rig.run_ms(8);
    assert_eq!(last_rpdo(&rig, 1).0, 0x06, "then shutdown");
    assert_eq!(rig.canopen.node(1).statusword, sw::READY_TO_SWITCH_ON);
}

#[test]
fn an_enable_from_quick_stop_active_goes_through_disable_voltage() {
    let mut rig = enabled();
    drive(&mut rig, 100);
    rig.send(Command::Estop);
    rig.run_ms(10);
    // The scripted drives keep quick stop active (option code 5-8).
    assert!(
        rig.canopen
            .nodes
            .iter()
            .all(|n| n.statusword == sw::QUICK_STOP_ACTIVE)
    );
    let t0 = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.enable();
    let t = wait_enabled(&mut rig).expect("enabled out of quick stop active");
    // Four steps (0x00, 0x06, 0x07, 0x0F), each sent until the next cycle's TPDO shows its
    // state: two 4 ms cycles a step at most. (0x06 alone, as before, was no transition
    // there: DRIVE_TRANSITION after 250 ms.)
    assert!((20_000..=32_000).contains(&(t - t0)), "{} µs", t - t0);
    for node in [1, 2] {
        let mut words: Vec<u16> = controlwords_since(&mut rig, node, t0);
        words.dedup();
        assert_eq!(words, [0x00, 0x06, 0x07, 0x0F], "node {node}");
    }
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

/// Disables the robot driving at 0.5 m/s; node 1's first axis's actual velocity at each
/// change in the next 200 ms, and the controlwords it got.
fn disable_while_moving(rig: &mut Rig) -> (Vec<i32>, Vec<u16>) {
    drive(rig, 300);
    assert_eq!(
        rig.canopen.node(1).actual[0],
        480,
        "0.5 m/s: 48 rpm, 480 raw"
    );
    let t0 = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Disable));
    let mut actual = Vec::new();
    let mut last = 480;
    for _ in 0..200 {
        rig.tick();
        let now = rig.canopen.node(1).actual[0];
        if now != last {
            actual.push(now);
            last = now;
        }
    }
    assert_eq!(rig.canopen.node(1).statusword, sw::READY_TO_SWITCH_ON);
    let mut words: Vec<u16> = controlwords_since(rig, 1, t0);
    words.dedup();
    (actual, words)
}

#[test]
fn a_disable_while_moving_slows_down_on_the_drives_ramp() {
    let mut rig = enabled();
    assert_eq!(rig.canopen.node(1).shutdown_option, 1, "0x605B = 1 written");
    let (actual, words) = disable_while_moving(&mut rig);
    assert_eq!(words, [0x06], "a shutdown, the drive slows down");
    // 480 raw down by 40 a cycle: 12 cycles (48 ms) with torque on the way down.
    assert_eq!(actual.len(), 12, "{actual:?}");
    assert_eq!(actual[0], 440);
    assert!(actual.windows(2).all(|w| w[1] == w[0] - 40), "{actual:?}");
    assert_eq!(*actual.last().unwrap(), 0);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
}

#[test]
fn a_drive_without_the_option_codes_is_configured_and_stops_at_once() {
    let mut rig = rig();
    rig.canopen.node(1).lacks_options = true;
    rig.run_until(200, |r, _| r.ctl.snapshot().motors_online == 0b1111)
        .expect("configured without 0x605B / 0x605C");
    rig.enable();
    wait_enabled(&mut rig).expect("enabled");
    assert_eq!(rig.canopen.node(1).shutdown_option, 0);
    let (actual, words) = disable_while_moving(&mut rig);
    assert_eq!(words, [0x06]);
    // The torque goes with the shutdown (the drive's option 0): what the master cannot
    // change on such a drive, as before.
    assert_eq!(actual, [0], "{actual:?}");
}
