//! Configuration by SDO and the start: the documented order, a node that aborts, does not
//! answer, answers wrongly or never boots, and the mode display read back before NMT start.

use firmware::control::{CANOPEN_SDO_TIMEOUT_US, DriveIssue};
use firmware::protocol::canopen::{self, Message, NmtCommand, NmtState, NodeId, SdoRequest};

use super::*;

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
