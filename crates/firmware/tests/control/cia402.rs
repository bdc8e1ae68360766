//! CiA 402 drives: configuration by SDO, the enable sequence, the cycle, odometry from the
//! actual velocities, and each fault with what it keeps for the log.

use firmware::control::{
    CANOPEN_NMT_GRACE_US, CANOPEN_SDO_TIMEOUT_US, CIA402_TRANSITION_TIMEOUT_US, DriveIssue,
};
use firmware::protocol::canopen::{self, Message, NmtCommand, NmtState, NodeId, SdoRequest};

use embedded_can::{Frame, Id};

use crate::rig::*;

/// A frame's standard id (`u16::MAX` for an extended one).
fn sid(f: &CanFrame) -> u16 {
    match f.id() {
        Id::Standard(id) => id.as_raw(),
        Id::Extended(_) => u16::MAX,
    }
}

/// The example: two dual-axis nodes (1: FL, FR; 2: RL, RR), a 250 Hz cycle.
fn rig() -> Rig {
    let mut c = Config::cia402_example();
    c.limits.stop_linear_decel = f32::INFINITY;
    c.limits.stop_angular_decel = f32::INFINITY;
    Rig::new(c)
}

/// The CANopen messages of a step's output.
fn messages(out: &Outbox) -> Vec<Message> {
    out.iter().filter_map(|f| canopen::decode(f).ok()).collect()
}

/// A configured, started rig (every motor online).
fn started() -> Rig {
    let mut rig = rig();
    rig.run_until(200, |r, _| r.ctl.snapshot().motors_online == 0b1111)
        .expect("both nodes configured and reporting");
    rig
}

/// A started rig, enabled and every node operation enabled.
fn enabled() -> Rig {
    let mut rig = started();
    rig.enable();
    wait_enabled(&mut rig).expect("the enable sequence completes");
    rig
}

/// Runs until every node is operation enabled (at most 100 ms); the time it was.
fn wait_enabled(rig: &mut Rig) -> Option<u64> {
    rig.run_until(100, |r, _| {
        r.canopen
            .nodes
            .iter()
            .all(|n| n.statusword == sw::OPERATION_ENABLED)
    })
}

/// The (controlword, targets) of the last RPDOs to `node` in the log.
fn last_rpdo(rig: &Rig, node: u8) -> (u16, i32, i32) {
    let mut cw = None;
    let mut t = (0, 0);
    for (_, f) in &rig.log {
        match canopen::decode(f) {
            Ok(Message::Rpdo1 {
                node: n,
                controlword,
                target,
            }) if n.get() == node => {
                cw = Some(controlword);
                t.0 = target;
            }
            Ok(Message::Rpdo3 { node: n, target }) if n.get() == node => t.1 = target,
            _ => {}
        }
    }
    (cw.expect("an RPDO was sent"), t.0, t.1)
}

#[test]
fn each_node_is_reset_configured_in_the_documented_order_and_started() {
    let mut rig = rig();
    let first = rig.tick();
    // The master's own boot-up is its first frame (node 127: 0x77F, 0x00).
    assert_eq!(
        messages(&first)[0],
        Message::Heartbeat {
            node: NodeId::new(127).unwrap(),
            state: NmtState::BootUp
        }
    );
    let resets: Vec<_> = messages(&first)
        .into_iter()
        .filter_map(|m| match m {
            Message::Nmt {
                command: NmtCommand::ResetCommunication,
                node,
            } => node.map(|n| n.get()),
            _ => None,
        })
        .collect();
    assert_eq!(resets, [1, 2], "each node reset at the first step");
    let t = rig
        .run_until(200, |r, _| r.ctl.snapshot().motors_online == 0b1111)
        .expect("configured");
    // 37 transfers a node, both nodes in parallel, one a step (the answer comes before the
    // next step), then NMT start and the first SYNC's answer.
    assert!((37_000..=43_000).contains(&t), "configured at {t} µs");
    rig.run_ms(30);

    let log = &rig.canopen.node(1).sdo_log;
    assert_eq!(log.len(), 37, "{log:#x?}");
    let dl = |index, sub, value, size| SdoRequest::Download {
        index,
        sub,
        value,
        size,
    };
    // The RPDO2 of the predefined set (0x300 + node: the robot's block) is switched off
    // first, before the device type.
    assert_eq!(log[0], dl(0x1401, 1, 0x8000_0301, 4));
    assert_eq!(
        log[1],
        SdoRequest::Upload {
            index: 0x1000,
            sub: 0
        }
    );
    assert_eq!(
        log[2],
        dl(0x6060, 0, 3, 1),
        "profile velocity before anything else"
    );
    assert_eq!(log[3], dl(0x1017, 0, 50, 2));
    assert_eq!(log[4], dl(0x1016, 1, 127 << 16 | 150, 4));
    // A disable slows down on the drive's ramp: shutdown and disable operation option 1.
    assert_eq!(log[5..7], [dl(0x605B, 0, 1, 2), dl(0x605C, 0, 1, 2)]);
    // RPDO1: disable, clear, map, count, type, enable.
    assert_eq!(
        log[7..14],
        [
            dl(0x1400, 1, 0x8000_0201, 4),
            dl(0x1600, 0, 0, 1),
            dl(0x1600, 1, 0x6040_0010, 4),
            dl(0x1600, 2, 0x60FF_0120, 4),
            dl(0x1600, 0, 2, 1),
            dl(0x1400, 2, 0xFF, 1),
            dl(0x1400, 1, 0x201, 4),
        ]
    );
    assert_eq!(log.iter().filter(|r| r.object() == (0x1401, 1)).count(), 1);
    assert!(log.contains(&dl(0x1A01, 1, 0x606C_0220, 4)));
    // Last, the mode of operation display read back before NMT start.
    assert_eq!(
        log[36],
        SdoRequest::Upload {
            index: 0x6061,
            sub: 0
        }
    );
    // NMT start once the last answer came, then SYNC and the RPDOs every 4 ms.
    let syncs: Vec<u64> = rig
        .log
        .iter()
        .filter(|(_, f)| matches!(canopen::decode(f), Ok(Message::Sync { .. })))
        .map(|(t, _)| *t)
        .collect();
    assert!(syncs.len() >= 2);
    assert!(syncs.windows(2).all(|w| w[1] - w[0] == 4_000), "{syncs:?}");
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    assert_eq!(last_rpdo(&rig, 1), (0x06, 0, 0), "shutdown while disabled");
    // The master's heartbeat, 0x77F, every 50 ms.
    let beats: Vec<u64> = rig
        .log
        .iter()
        .filter(|(_, f)| {
            matches!(canopen::decode(f), Ok(Message::Heartbeat { node, .. }) if node.get() == 127)
        })
        .map(|(t, _)| *t)
        .collect();
    assert_eq!(beats[..2], [0, 50_000]);
    let states: Vec<u8> = rig
        .log
        .iter()
        .filter(|(_, f)| sid(f) == canopen::layout::HEARTBEAT.id + 127)
        .take(2)
        .map(|(_, f)| f.data()[0])
        .collect();
    assert_eq!(states, [0x00, 0x05], "boot-up, then operational");
}

#[test]
fn an_enable_runs_shutdown_switch_on_enable_operation_checking_each_state() {
    let mut rig = started();
    let t0 = rig.now_us;
    rig.enable();
    rig.twist(0.5, 0.0, 0.0);
    wait_enabled(&mut rig).expect("enabled");
    for node in [1, 2] {
        let words: Vec<u16> = rig
            .canopen
            .node(node)
            .controlwords
            .iter()
            .filter(|(t, _)| *t >= t0)
            .map(|(_, cw)| *cw)
            .collect();
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
fn an_sdo_abort_faults_naming_the_node_object_and_code_and_the_reset_retries() {
    let mut rig = rig();
    rig.canopen.node(2).abort = Some(((0x6060, 0), 0x0609_0030));
    rig.run_until(100, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the abort faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveSetup);
    let issue = rig.ctl.drive_issue().unwrap();
    assert_eq!(
        issue,
        DriveIssue::SdoAbort {
            node: 2,
            object: (0x6060, 0),
            code: 0x0609_0030
        }
    );
    assert_eq!(
        issue.to_string(),
        "node 2: SDO abort 0x06090030 on 0x6060:00 (invalid value for parameter)"
    );
    // Node 2 is told nothing more (RPDO2 off, device type, mode); node 1 carries on.
    assert_eq!(rig.canopen.node(2).sdo_log.len(), 3);
    rig.canopen.node(2).abort = None;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_until(200, |r, _| r.ctl.snapshot().motors_online == 0b1111)
        .expect("configured on the retry");
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    rig.enable();
    rig.run_ms(50);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn an_unanswered_sdo_faults_after_its_timeout() {
    let mut rig = rig();
    rig.canopen.node(1).sdo_silent = true;
    let t = rig
        .run_until(1000, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("times out");
    // The first transfer (RPDO2 off) went out at the second step (1 ms); the timeout is
    // strict.
    assert_eq!(t, 1_000 + CANOPEN_SDO_TIMEOUT_US + 1_000);
    assert_eq!(rig.ctl.fault(), Fault::DriveSetup);
    assert_eq!(
        rig.ctl.drive_issue(),
        Some(DriveIssue::SdoTimeout {
            node: 1,
            object: (0x1401, 1)
        })
    );
    // The master gives the transfer up with an abort, "SDO protocol timed out", in the step
    // that judged the timeout: 0x601 80 01 14 01 00 00 04 05.
    let aborts: Vec<(u64, Vec<u8>)> = rig
        .log
        .iter()
        .filter(|(_, f)| sid(f) == 0x601 && f.data()[0] == 0x80)
        .map(|(t, f)| (*t, f.data().to_vec()))
        .collect();
    assert_eq!(
        aborts,
        [(t, vec![0x80, 0x01, 0x14, 0x01, 0x00, 0x00, 0x04, 0x05])]
    );
    assert_eq!(
        rig.canopen.node(1).sdo_log.last(),
        Some(&SdoRequest::Abort {
            index: 0x1401,
            sub: 1,
            code: 0x0504_0000
        })
    );
}

#[test]
fn a_silent_heartbeat_quick_stops_within_the_consumer_time() {
    let mut rig = enabled();
    rig.canopen.node(2).heartbeat_silent = true;
    // The last heartbeat came at the last multiple of 50 ms.
    let last = rig.now_us / 50_000 * 50_000;
    let t = rig
        .run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the silence faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveSilent);
    let latency = t - last;
    assert!(
        (150_000..=151_000).contains(&latency),
        "{latency} µs after the last heartbeat"
    );
    // Quick stop and zero targets to every node at the next cycle.
    rig.run_ms(5);
    assert_eq!(last_rpdo(&rig, 1), (0x02, 0, 0));
    assert_eq!(last_rpdo(&rig, 2), (0x02, 0, 0));
    assert_eq!(
        rig.ctl.drive_issue().map(|i| i.to_string()),
        Some("node 2: heartbeat lost".into())
    );
}

#[test]
fn a_node_that_reboots_is_configured_again_and_needs_the_hosts_reset_and_enable() {
    let mut rig = enabled();
    let before = rig.canopen.node(1).sdo_log.len();
    rig.canopen.node(1).reboot();
    rig.run_until(10, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the boot-up faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveRebooted);
    rig.run_until(200, |r, _| {
        r.canopen.nodes[0].sdo_log.len() == 2 * before && r.canopen.nodes[0].operational()
    })
    .expect("node 1 is configured again and started");
    assert_eq!(rig.canopen.node(1).mode, 3);
    // No motion until the host resets and enables: node 1 is told quick stop.
    rig.run_ms(10);
    assert_eq!(rig.ctl.state(), RobotState::Fault);
    assert_eq!(last_rpdo(&rig, 1).0, 0x02);
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(10);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    rig.enable();
    wait_enabled(&mut rig).expect("enabled again");
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
}

#[test]
fn a_drive_fault_is_reset_by_one_edge_on_the_hosts_reset_only() {
    let mut rig = enabled();
    rig.canopen.node(2).fault(0x2310);
    rig.run_until(20, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the statusword's fault bit faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveError);
    assert_eq!(rig.ctl.drive_emcy_count(), 1);
    let issue = rig.ctl.drive_issue().unwrap();
    assert_eq!(
        issue.to_string(),
        "node 2: statusword 0x0218 (FAULT), last EMCY 0x2310"
    );
    rig.run_ms(100);
    let t_reset = rig.now_us;
    assert!(
        rig.canopen
            .node(2)
            .controlwords
            .iter()
            .all(|(_, cw)| cw & 0x80 == 0),
        "no fault reset before the host's"
    );
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(40);
    let after: Vec<u16> = rig
        .canopen
        .node(2)
        .controlwords
        .iter()
        .filter(|(t, _)| *t >= t_reset)
        .map(|(_, cw)| *cw)
        .collect();
    assert_eq!(after[0], 0x80, "{after:?}");
    assert!(after[1..].iter().all(|&cw| cw == 0x06), "{after:?}");
    assert_eq!(rig.canopen.node(2).statusword, sw::READY_TO_SWITCH_ON);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    // Node 1 was not in fault: no edge for it.
    assert!(
        rig.canopen
            .node(1)
            .controlwords
            .iter()
            .all(|(_, cw)| cw & 0x80 == 0)
    );
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
fn a_node_that_never_boots_is_missing_after_the_boot_timeout() {
    let mut rig = rig();
    rig.canopen.node(2).mute = true;
    let t = rig
        .run_until(1500, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("missing");
    assert_eq!(rig.ctl.fault(), Fault::MotorMissing);
    assert_eq!(t, 1_001_000);
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

/// The NMT commands in the log from `from_us` on: (time, command, node).
fn nmt_commands(rig: &Rig, from_us: u64) -> Vec<(u64, NmtCommand, u8)> {
    rig.log
        .iter()
        .filter(|(t, _)| *t >= from_us)
        .filter_map(|(t, f)| match canopen::decode(f) {
            Ok(Message::Nmt {
                command,
                node: Some(node),
            }) => Some((*t, command, node.get())),
            _ => None,
        })
        .collect()
}

/// Whether any RPDO sent from `from_us` on carries a target other than zero.
fn moved_since(rig: &Rig, from_us: u64) -> bool {
    rig.log.iter().filter(|(t, _)| *t >= from_us).any(|(_, f)| {
        matches!(
            canopen::decode(f),
            Ok(Message::Rpdo1 { target, .. } | Message::Rpdo3 { target, .. }) if target != 0
        )
    })
}

/// Drives at 0.5 m/s for `ms` milliseconds.
fn drive(rig: &mut Rig, ms: u64) {
    for _ in 0..ms {
        rig.twist(0.5, 0.0, 0.0);
        rig.tick();
    }
}

#[test]
fn a_started_node_that_turns_pre_operational_faults_naming_it_and_the_reset_starts_it() {
    let mut rig = enabled();
    drive(&mut rig, 100);
    assert!(moved_since(&rig, 0));
    // A communication error (a consumer time-out, a bus-off): CiA 301's default behaviour.
    rig.canopen.node(1).enter(NmtState::PreOperational);
    let t0 = rig.now_us;
    let t = rig
        .run_until(5, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the heartbeat faults the robot");
    // Its heartbeat comes in with the next step's frames.
    assert_eq!(t, t0);
    assert_eq!(rig.ctl.fault(), Fault::DriveNmt);
    let issue = rig.ctl.drive_issue().unwrap();
    assert_eq!(
        issue,
        DriveIssue::NotOperational {
            node: 1,
            state: NmtState::PreOperational
        }
    );
    assert_eq!(issue.to_string(), "node 1: NMT PRE_OPERATIONAL");
    // Quick stop and zero targets to every node; nothing else until the host's reset.
    rig.run_ms(100);
    assert_eq!(last_rpdo(&rig, 1), (0x02, 0, 0));
    assert_eq!(last_rpdo(&rig, 2), (0x02, 0, 0));
    assert!(!moved_since(&rig, t + 5_000));
    assert_eq!(nmt_commands(&rig, t0), []);
    assert_eq!(rig.ctl.state(), RobotState::Fault);

    // The reset starts node 1 again (its configuration is intact: no SDO), with a fault
    // reset in its first cycle; node 2 is left alone.
    let sdo_before = rig.canopen.node(1).sdo_log.len();
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(20);
    assert_eq!(
        nmt_commands(&rig, t_reset),
        [(t_reset, NmtCommand::Start, 1)]
    );
    assert_eq!(rig.canopen.node(1).sdo_log.len(), sdo_before);
    assert!(rig.canopen.node(1).operational());
    let words: Vec<u16> = rig
        .canopen
        .node(1)
        .controlwords
        .iter()
        .filter(|(t, _)| *t >= t_reset)
        .map(|(_, cw)| *cw)
        .collect();
    assert_eq!(words[0], 0x80, "{words:?}");
    assert!(
        rig.canopen
            .node(2)
            .controlwords
            .iter()
            .all(|(_, cw)| cw & 0x80 == 0)
    );
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    // Enabled again, it drives.
    let t_enable = rig.now_us;
    rig.enable();
    wait_enabled(&mut rig).expect("enabled again");
    drive(&mut rig, 200);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    assert_eq!(last_rpdo(&rig, 1), (0x0F, 48, -48));
    assert!(moved_since(&rig, t_enable));
}

#[test]
fn a_stopped_node_faults_as_well_and_the_reset_starts_it() {
    let mut rig = enabled();
    // Past the grace after the start.
    rig.run_ms(30);
    rig.canopen.node(2).enter(NmtState::Stopped);
    rig.run_until(5, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the heartbeat faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveNmt);
    assert_eq!(
        rig.ctl.drive_issue().map(|i| i.to_string()),
        Some("node 2: NMT STOPPED".into())
    );
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(100);
    assert_eq!(
        nmt_commands(&rig, t_reset),
        [(t_reset, NmtCommand::Start, 2)]
    );
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
}

#[test]
fn a_heartbeat_that_may_predate_the_start_is_not_judged() {
    let mut rig = rig();
    let start = rig
        .run_until(200, |_, out| {
            messages(out).iter().any(|m| {
                matches!(
                    m,
                    Message::Nmt {
                        command: NmtCommand::Start,
                        ..
                    }
                )
            })
        })
        .expect("started");
    // A pre-operational heartbeat queued before the start reached the node.
    let node = NodeId::new(1).unwrap();
    let stale = Message::Heartbeat {
        node,
        state: NmtState::PreOperational,
    };
    rig.run_ms(5);
    rig.raw(stale.to_can_frame());
    rig.run_ms(30);
    assert_eq!(rig.ctl.state(), RobotState::Disabled, "within the grace");
    assert!(rig.now_us - start > CANOPEN_NMT_GRACE_US);
    rig.raw(stale.to_can_frame());
    rig.tick();
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Fault, Fault::DriveNmt)
    );
}

#[test]
fn a_late_heartbeat_after_the_stale_fault_still_names_the_nmt_state_and_the_reset_recovers() {
    let mut rig = enabled();
    drive(&mut rig, 20);
    // Pre-operational, said only by the next periodic heartbeat: the TPDOs stop first.
    rig.canopen.node(2).nmt = NmtState::PreOperational;
    rig.run_until(20, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("stale");
    assert_eq!(rig.ctl.fault(), Fault::MotorStale);
    rig.run_ms(60);
    assert_eq!(
        rig.ctl.drive_issue().map(|i| i.to_string()),
        Some("node 2: NMT PRE_OPERATIONAL".into())
    );
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(20);
    assert_eq!(
        nmt_commands(&rig, t_reset),
        [(t_reset, NmtCommand::Start, 2)]
    );
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    rig.enable();
    wait_enabled(&mut rig).expect("enabled again");
    drive(&mut rig, 200);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    assert_eq!(last_rpdo(&rig, 2), (0x0F, 48, -48));
}

#[test]
fn a_node_back_pre_operational_after_its_heartbeat_was_lost_is_reset_and_configured_again() {
    let mut rig = enabled();
    rig.canopen.node(2).heartbeat_silent = true;
    rig.run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the silence faults the robot");
    assert_eq!(rig.ctl.fault(), Fault::DriveSilent);
    // Back, pre-operational: whether it booted meanwhile no one can tell.
    rig.canopen.node(2).heartbeat_silent = false;
    rig.canopen.node(2).enter(NmtState::PreOperational);
    rig.run_ms(10);
    // The first issue is kept until the reset.
    assert_eq!(
        rig.ctl.drive_issue().map(|i| i.to_string()),
        Some("node 2: heartbeat lost".into())
    );
    let sdo_before = rig.canopen.node(2).sdo_log.len();
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_until(200, |r, _| r.canopen.nodes[1].operational())
        .expect("node 2 reset, configured again and started");
    let nmt = nmt_commands(&rig, t_reset);
    assert_eq!(
        nmt.iter().map(|&(_, c, n)| (c, n)).collect::<Vec<_>>(),
        [(NmtCommand::ResetCommunication, 2), (NmtCommand::Start, 2)]
    );
    assert_eq!(nmt[0].0, t_reset);
    assert_eq!(rig.canopen.node(2).sdo_log.len(), 2 * sdo_before);
    // No feedback fault while it was configured again.
    rig.run_ms(20);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    rig.enable();
    wait_enabled(&mut rig).expect("enabled again");
    drive(&mut rig, 200);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    assert_eq!(last_rpdo(&rig, 2), (0x0F, 48, -48));
}

#[test]
fn a_node_that_does_not_boot_after_a_recovery_reset_is_silent_after_the_consumer_time() {
    let mut rig = enabled();
    rig.canopen.node(2).heartbeat_silent = true;
    rig.run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the silence faults the robot");
    rig.canopen.node(2).heartbeat_silent = false;
    rig.canopen.node(2).enter(NmtState::PreOperational);
    rig.run_ms(10);
    rig.canopen.node(2).mute = true;
    let t_reset = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    let t = rig
        .run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("faults again");
    assert_eq!(rig.ctl.fault(), Fault::DriveSilent);
    let waited = t - t_reset;
    assert!((150_000..=152_000).contains(&waited), "{waited} µs");
}

/// The example with nodes 1 (FL, FR) and 31 (RL, RR): node 31's predefined RPDO2, 0x31F,
/// is the robot's own `HEARTBEAT`; node 1's, 0x301, a host's `TWIST_CMD`. Both drives start
/// themselves after their boot-up.
fn self_starting() -> Rig {
    let mut c = Config::cia402_example();
    if let Drive::Cia402(drive) = &mut c.drive {
        drive.node_ids = [1, 1, 31, 31];
    }
    let mut rig = Rig::new(c);
    for n in &mut rig.canopen.nodes {
        n.self_starting = true;
    }
    rig
}

/// The robot's own frames (`0x300..=0x31F`) in the log: (time, id).
fn robot_frames(rig: &Rig) -> Vec<(u64, u16)> {
    rig.log
        .iter()
        .map(|(t, f)| (*t, sid(f)))
        .filter(|(_, id)| (0x300..=0x31F).contains(id))
        .collect()
}

#[test]
fn a_self_starting_drive_takes_no_robot_frame_as_a_controlword() {
    let mut rig = self_starting();
    // A host that keeps the contract: nothing in the block before the robot's HEARTBEAT;
    // then a twist every millisecond at 15 mm/s, bytes 0-1 0x000F ("enable operation").
    for _ in 0..300 {
        if rig.log.iter().any(|(_, f)| sid(f) == 0x31F) {
            rig.twist(0.015, 0.0, 0.0);
        }
        rig.tick();
    }
    for node in [1, 31] {
        let n = rig.canopen.node(node);
        assert_eq!(n.rpdo2_taken, [], "node {node} took a robot frame");
        assert_eq!(n.rpdo2, 0x8000_0300 + u32::from(node));
    }
    // The robot held its block from its start until both RPDO2-off writes were answered
    // (at 1 ms: the boot-ups came at 1 ms), and spoke at the next step.
    let off = [1, 31].map(|n| rig.canopen.node(n).rpdo2_off_at.expect("RPDO2 off"));
    assert_eq!(off, [1_000, 1_000]);
    let frames = robot_frames(&rig);
    assert_eq!(frames[0].0, 2_000, "{:?}", &frames[..4]);
    assert!(frames.iter().any(|&(t, id)| (t, id) == (2_000, 0x31F)));
    // Both nodes were seen operational unstarted (their heartbeat at the boot-up), sent to
    // pre-operational at the next step, refused until the host's reset: DRIVE_NMT.
    let preops: Vec<(u64, u8)> = nmt_commands(&rig, 0)
        .into_iter()
        .filter(|c| c.1 == NmtCommand::EnterPreOperational)
        .map(|(t, _, n)| (t, n))
        .collect();
    assert_eq!(preops, [(1_000, 1), (1_000, 31)]);
    assert_eq!(rig.ctl.state(), RobotState::Fault);
    assert_eq!(rig.ctl.fault(), Fault::DriveNmt);
    let issue = rig.ctl.drive_issue().unwrap();
    assert!(
        matches!(issue, DriveIssue::SelfStarted { node: 1 | 31 }),
        "{issue:?}"
    );
    assert_eq!(
        DriveIssue::SelfStarted { node: 1 }.to_string(),
        "node 1: NMT OPERATIONAL before NMT start (a self-starting drive: its RPDO2 0x301 is \
         in the robot's block)"
    );
    // Configured and started all the same: the host's reset acknowledges, and it drives.
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.enable();
    let t = wait_enabled(&mut rig).expect("enabled after the reset");
    assert!(t - 300_000 <= 20_000, "{} µs", t - 300_000);
    drive(&mut rig, 100);
    assert!(moved_since(&rig, 300_000));
    assert_eq!(rig.canopen.node(1).rpdo2_taken, []);
}

#[test]
fn a_host_that_speaks_at_once_meets_a_self_starting_drive_for_one_step_only() {
    // The window the master cannot close: a host (or an IMU, a pod node) that sends in the
    // block without waiting for the robot's HEARTBEAT. Before RPDO2 went off first it was
    // the 31st transfer, about 31 ms; now one SDO round trip.
    let mut rig = self_starting();
    for _ in 0..100 {
        rig.twist(0.015, 0.0, 0.0);
        rig.tick();
    }
    assert_eq!(rig.canopen.node(1).rpdo2_taken, [(1_000, 0x000F)]);
    // The robot's own frames never: node 31 took no HEARTBEAT.
    assert_eq!(rig.canopen.node(31).rpdo2_taken, []);
}

#[test]
fn a_robot_frame_on_a_nodes_open_rpdo2_is_not_sent_even_when_faulted() {
    // Node 31 (not self-starting here) never answers its RPDO2-off write: the robot holds
    // its block until the SDO time-out fails the node, then speaks (STATUS says why), but
    // never on 0x31F while node 31's RPDO2 may be on.
    let mut rig = self_starting();
    for n in &mut rig.canopen.nodes {
        n.self_starting = false;
    }
    rig.canopen.node(31).sdo_silent = true;
    let t = rig
        .run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("times out");
    assert_eq!(t, 202_000);
    rig.run_ms(300);
    let frames = robot_frames(&rig);
    assert!(
        frames.iter().all(|&(_, id)| id != 0x31F),
        "a HEARTBEAT went out"
    );
    // Nothing in the block before the time-out; STATUS (0x312) says why from then on.
    assert_eq!(frames[0], (202_000, 0x310));
    assert!(frames.iter().any(|&(t, id)| id == 0x312 && t == 202_000));
    assert_eq!(rig.status().fault, Fault::DriveSetup);
}

#[test]
fn an_sdo_answer_with_the_wrong_command_is_not_taken() {
    let mut rig = rig();
    // Node 1 answers the write of 0x6060 with an upload response on the same object.
    rig.canopen.node(1).wrong_answer = Some((0x6060, 0));
    let t = rig
        .run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("times out");
    // 0x6060 is the third transfer, sent at 3 ms; not answered, it times out.
    assert_eq!(t, 3_000 + CANOPEN_SDO_TIMEOUT_US + 1_000);
    assert_eq!(
        rig.ctl.drive_issue(),
        Some(DriveIssue::SdoTimeout {
            node: 1,
            object: (0x6060, 0)
        })
    );
    let log = &rig.canopen.node(1).sdo_log;
    assert_eq!(log.len(), 4, "{log:x?}");
    assert_eq!(
        log[3],
        SdoRequest::Abort {
            index: 0x6060,
            sub: 0,
            code: 0x0504_0000
        }
    );
}

/// The times NMT start went to each node.
fn starts(rig: &Rig, node: u8) -> Vec<u64> {
    nmt_commands(rig, 0)
        .into_iter()
        .filter(|c| c.1 == NmtCommand::Start && c.2 == node)
        .map(|c| c.0)
        .collect()
}

#[test]
fn the_mode_display_is_read_until_it_shows_profile_velocity_before_the_start() {
    let mut rig = rig();
    // Node 1's 0x6061 still shows 0 for three reads after 0x6060 = 3.
    rig.canopen.node(1).mode_lag_reads = 3;
    rig.run_ms(150);
    let reads = rig
        .canopen
        .node(1)
        .sdo_log
        .iter()
        .filter(|r| r.object() == (0x6061, 0))
        .count();
    assert_eq!(reads, 4);
    // Three more reads, each CIA402_MODE_POLL_US (10 ms) after the answer, which comes at
    // the next step: node 1 starts 3 x 11 ms after node 2.
    let (one, two) = (starts(&rig, 1), starts(&rig, 2));
    assert_eq!((one.len(), two.len()), (1, 1), "{one:?} {two:?}");
    assert_eq!(one[0] - two[0], 33_000);
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
}

#[test]
fn a_mode_display_that_never_shows_profile_velocity_fails_the_configuration() {
    let mut rig = rig();
    rig.canopen.node(1).mode_lag_reads = 1_000;
    rig.canopen.node(1).mode_shown_before = -1;
    let t = rig
        .run_until(1_000, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the mode is not shown");
    // The first read at 37 ms, 49 more 10 ms after each answer (at the next step): the
    // 50th answer at about 37 + 49 x 11 = 576 ms.
    assert!((570_000..=580_000).contains(&t), "{t} µs");
    assert_eq!(rig.ctl.fault(), Fault::DriveSetup);
    let issue = rig.ctl.drive_issue().unwrap();
    assert_eq!(issue, DriveIssue::ModeNotShown { node: 1, mode: -1 });
    assert_eq!(
        issue.to_string(),
        "node 1: mode of operation display 0x6061 = -1, not 3 (profile velocity), after 50 reads"
    );
    assert_eq!(starts(&rig, 1), []);
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
        let mut words: Vec<u16> = rig
            .canopen
            .node(node)
            .controlwords
            .iter()
            .filter(|(t, _)| *t >= t0)
            .map(|(_, cw)| *cw)
            .collect();
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
    let mut words: Vec<u16> = rig
        .canopen
        .node(1)
        .controlwords
        .iter()
        .filter(|(t, _)| *t >= t0)
        .map(|(_, cw)| *cw)
        .collect();
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
