//! CiA 402 drives: configuration by SDO, the enable sequence, the cycle, odometry from the
//! actual velocities, and each fault with what it keeps for the log.
//!
//! One file a concern: the configuration and start (`setup.rs`), enabling and stopping
//! (`enable.rs`), faults once started (`faults.rs`), self-starting drives
//! (`self_starting.rs`); the helpers they share are here.

mod enable;
mod faults;
mod self_starting;
mod setup;

use firmware::protocol::canopen::{self, Message, NmtCommand};

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

/// The controlwords `node` got from `from_us` on.
fn controlwords_since(rig: &mut Rig, node: u8, from_us: u64) -> Vec<u16> {
    rig.canopen
        .node(node)
        .controlwords
        .iter()
        .filter(|(t, _)| *t >= from_us)
        .map(|(_, cw)| *cw)
        .collect()
}

/// Whether `node` never got a fault reset (controlword bit 7).
fn no_fault_reset(rig: &mut Rig, node: u8) -> bool {
    rig.canopen
        .node(node)
        .controlwords
        .iter()
        .all(|(_, cw)| cw & 0x80 == 0)
}

/// Sends the host's reset; the time it was sent.
fn reset(rig: &mut Rig) -> u64 {
    let t = rig.now_us;
    rig.send(Command::Mode(ModeRequest::Reset));
    t
}

/// Silences `node`'s heartbeat until the robot faults (within 400 ms).
fn lose_heartbeat(rig: &mut Rig, node: u8) {
    rig.canopen.node(node).heartbeat_silent = true;
    rig.run_until(400, |r, _| r.ctl.state() == RobotState::Fault)
        .expect("the silence faults the robot");
}

/// Enables the robot again and drives 200 ms at 0.5 m/s: enabled, and `node` given the
/// targets (48 rpm, the mirrored axis -48).
fn drives_again(rig: &mut Rig, node: u8) {
    rig.enable();
    wait_enabled(rig).expect("enabled again");
    drive(rig, 200);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    assert_eq!(last_rpdo(rig, node), (0x0F, 48, -48));
}
