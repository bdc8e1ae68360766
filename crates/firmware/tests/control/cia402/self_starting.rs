//! Drives that start themselves after their boot-up, whose predefined RPDO2 lies in the
//! robot's block: no robot frame is taken as a controlword.

use firmware::control::DriveIssue;
use firmware::protocol::canopen::NmtCommand;

use super::*;

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
