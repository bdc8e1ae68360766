//! A node that goes wrong once started: a silent heartbeat, a reboot, a drive fault, an NMT
//! state other than operational; what each keeps for the log and how the host's reset recovers.

use firmware::control::{CANOPEN_NMT_GRACE_US, DriveIssue};
use firmware::protocol::canopen::{Message, NmtCommand, NmtState, NodeId};

use super::*;

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
        no_fault_reset(&mut rig, 2),
        "no fault reset before the host's"
    );
    rig.send(Command::Mode(ModeRequest::Reset));
    rig.run_ms(40);
    let after: Vec<u16> = controlwords_since(&mut rig, 2, t_reset);
    assert_eq!(after[0], 0x80, "{after:?}");
    assert!(after[1..].iter().all(|&cw| cw == 0x06), "{after:?}");
    assert_eq!(rig.canopen.node(2).statusword, sw::READY_TO_SWITCH_ON);
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    // Node 1 was not in fault: no edge for it.
    assert!(no_fault_reset(&mut rig, 1));
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
    let t_reset = reset(&mut rig);
    rig.run_ms(20);
    assert_eq!(
        nmt_commands(&rig, t_reset),
        [(t_reset, NmtCommand::Start, 1)]
    );
    assert_eq!(rig.canopen.node(1).sdo_log.len(), sdo_before);
    assert!(rig.canopen.node(1).operational());
    let words: Vec<u16> = controlwords_since(&mut rig, 1, t_reset);
    assert_eq!(words[0], 0x80, "{words:?}");
    assert!(no_fault_reset(&mut rig, 2));
    assert_eq!(
        (rig.ctl.state(), rig.ctl.fault()),
        (RobotState::Disabled, Fault::None)
    );
    // Enabled again, it drives.
    let t_enable = rig.now_us;
    drives_again(&mut rig, 1);
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
    let t_reset = reset(&mut rig);
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
    let t_reset = reset(&mut rig);
    rig.run_ms(20);
    assert_eq!(
        nmt_commands(&rig, t_reset),
        [(t_reset, NmtCommand::Start, 2)]
    );
    assert_eq!(rig.ctl.state(), RobotState::Disabled);
    drives_again(&mut rig, 2);
}

#[test]
fn a_node_back_pre_operational_after_its_heartbeat_was_lost_is_reset_and_configured_again() {
    let mut rig = enabled();
    lose_heartbeat(&mut rig, 2);
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
    let t_reset = reset(&mut rig);
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
    drives_again(&mut rig, 2);
}

#[test]
fn a_node_that_does_not_boot_after_a_recovery_reset_is_silent_after_the_consumer_time() {
    let mut rig = enabled();
    lose_heartbeat(&mut rig, 2);
    rig.canopen.node(2).heartbeat_silent = false;
    rig.canopen.node(2).enter(NmtState::PreOperational);
    rig.run_ms(10);
    rig.canopen.node(2).mute = true;
    let t_reset = reset(&mut rig);
    let t = rig
        .run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("faults again");
    assert_eq!(rig.ctl.fault(), Fault::DriveSilent);
    let waited = t - t_reset;
    assert!((150_000..=152_000).contains(&waited), "{waited} µs");
}
