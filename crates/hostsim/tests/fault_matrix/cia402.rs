//! The CiA 402 rows: each fault of a CANopen drive on the example robot (two dual-axis nodes,
//! a 250 Hz cycle), injected into the simulated node while the robot drives. A stop is the
//! fault's state with quick stop (`0x02`) and zero targets delivered to every node; latencies
//! run from what the firmware could first have known, read from the bus deliveries (the
//! node's last heartbeat, the enable step sent). The rows of a communication error (the
//! runner killed, a bus-off) go on to the host's reset and enable, and show the robot
//! driving again.

use firmware::control::{CIA402_TRANSITION_TIMEOUT_US, Fault};
use firmware::protocol::canopen::DriveState402;
use firmware::protocol::canopen::{self, Message, NmtCommand, NmtState};
use firmware::protocol::robot::RobotState;
use hostsim::bus::{Fate, Node};
use hostsim::engine::{LogOptions, run_observed};
use hostsim::scenario::{Action, FaultName, NodeFault, Scenario, WheelFault};

use super::{MOMENTS, MS, Row, add_action, drive, moment, ms, us};

/// SDO transfers of a dual-axis node's configuration (`docs/protocol.md`, "Configuration of
/// a node"): RPDO2 off, the device type, 33 writes, the mode of operation display.
const SDO_TRANSFERS: usize = 37;

/// What a CiA 402 run shows.
#[derive(Debug, Default)]
struct Record {
    /// Every step: time, state, fault.
    steps: Vec<(u64, RobotState, Fault)>,
    /// Heartbeats delivered from the drives: time, node, state.
    heartbeats: Vec<(u64, u8, NmtState)>,
    /// The master's heartbeats delivered: time.
    heartbeat_master: Vec<u64>,
    /// RPDO1s delivered from the firmware: time, node, controlword, target; RPDO3 targets
    /// as controlword `None`.
    rpdos: Vec<(u64, u8, Option<u16>, i32)>,
    /// NMT starts sent: time, node.
    starts: Vec<(u64, u8)>,
    /// Every NMT command sent to one node: time, command, node.
    nmt: Vec<(u64, NmtCommand, u8)>,
    /// EMCY frames delivered from the drives: time, node, error code.
    emcys: Vec<(u64, u8, u16)>,
    /// Statuswords delivered from the drives (TPDO1): time, node, statusword.
    statuswords: Vec<(u64, u8, u16)>,
    /// SDO requests delivered: time, node, object.
    sdo: Vec<(u64, u8, (u16, u8))>,
    /// The firmware's drive issue and EMCY count at the end.
    issue: Option<String>,
    emcy: u32,
}

impl Record {
    fn first(&self, from_us: u64, want: (RobotState, Fault)) -> Option<u64> {
        self.steps
            .iter()
            .find(|(t, st, f)| *t >= from_us && (*st, *f) == want)
            .map(|s| s.0)
    }

    /// The first heartbeat of `node` from `from_us` on that says `state`.
    fn heartbeat(&self, from_us: u64, node: u8, state: NmtState) -> Option<u64> {
        self.heartbeats
            .iter()
            .find(|h| h.0 >= from_us && (h.1, h.2) == (node, state))
            .map(|h| h.0)
    }

    /// The first target other than zero sent from `from_us` on.
    fn first_target(&self, from_us: u64) -> Option<u64> {
        self.rpdos
            .iter()
            .find(|r| r.0 >= from_us && r.3 != 0)
            .map(|r| r.0)
    }

    /// The first time from `from_us` by which every node's statusword shows operation
    /// enabled.
    fn operation_enabled(&self, from_us: u64) -> Option<u64> {
        [1, 2]
            .iter()
            .map(|&node| {
                self.statuswords
                    .iter()
                    .find(|(t, n, sw)| {
                        *t >= from_us
                            && *n == node
                            && DriveState402::from_statusword(*sw)
                                == Some(DriveState402::OperationEnabled)
                    })
                    .map(|s| s.0)
            })
            .try_fold(0, |m, t| t.map(|t| t.max(m)))
    }

    /// The state and fault at the last step.
    fn last(&self) -> (RobotState, Fault) {
        self.steps
            .last()
            .map_or((RobotState::Fault, Fault::None), |s| (s.1, s.2))
    }

    /// The first time from `from_us` by which each of `nodes` has been sent quick stop with
    /// zero targets (RPDO1 and RPDO3).
    fn quick_stopped(&self, from_us: u64, nodes: &[u8]) -> Option<u64> {
        nodes
            .iter()
            .map(|&node| {
                let rpdo1 = self.rpdos.iter().find(|(t, n, cw, target)| {
                    *t >= from_us && *n == node && *cw == Some(0x02) && *target == 0
                })?;
                let rpdo3 = self.rpdos.iter().find(|(t, n, cw, target)| {
                    *t >= rpdo1.0 && *n == node && cw.is_none() && *target == 0
                })?;
                Some(rpdo3.0)
            })
            .try_fold(0, |m, t| t.map(|t| t.max(m)))
    }
}

fn run(s: &Scenario) -> Record {
    let mut plant = hostsim::engine::plant_for(s).unwrap();
    let mut rec = Record::default();
    let mut last = None;
    run_observed(s, &mut plant, None, LogOptions::default(), |v| {
        for tx in v.delivered.iter().filter(|tx| tx.fate != Fate::Dropped) {
            let t = tx.delivered_ns / 1000;
            match (tx.from, canopen::decode(&tx.frame)) {
                (Node::Drives, Ok(Message::Heartbeat { node, state })) => {
                    rec.heartbeats.push((t, node.get(), state));
                }
                (Node::Controller, Ok(Message::Heartbeat { .. })) => {
                    rec.heartbeat_master.push(t);
                }
                (Node::Drives, Ok(Message::Emcy { node, emcy })) => {
                    rec.emcys.push((t, node.get(), emcy.error_code));
                }
                (
                    Node::Drives,
                    Ok(Message::Tpdo1 {
                        node, statusword, ..
                    }),
                ) => rec.statuswords.push((t, node.get(), statusword)),
                (
                    Node::Controller,
                    Ok(Message::Rpdo1 {
                        node,
                        controlword,
                        target,
                    }),
                ) => rec.rpdos.push((t, node.get(), Some(controlword), target)),
                (Node::Controller, Ok(Message::Rpdo3 { node, target })) => {
                    rec.rpdos.push((t, node.get(), None, target));
                }
                (
                    Node::Controller,
                    Ok(Message::Nmt {
                        command,
                        node: Some(node),
                    }),
                ) => {
                    rec.nmt.push((t, command, node.get()));
                    if command == NmtCommand::Start {
                        rec.starts.push((t, node.get()));
                    }
                }
                (Node::Controller, Ok(Message::SdoRequest { node, request })) => {
                    rec.sdo.push((t, node.get(), request.object()));
                }
                _ => {}
            }
        }
        if v.down {
            // The runner is dead: no state.
            return;
        }
        let snap = v.controller.snapshot();
        rec.steps.push((v.t_us, snap.state, snap.fault));
        last = Some((
            v.controller.drive_issue().map(|i| i.to_string()),
            v.controller.drive_emcy_count(),
        ));
    })
    .unwrap();
    (rec.issue, rec.emcy) = last.unwrap_or_default();
    rec
}

/// The matrix's drive on the CiA 402 example.
fn scenario(onset_s: f64, kind: FaultName, wheel: usize, until_s: Option<f64>) -> Scenario {
    let mut s = drive(super::TURN, onset_s.max(0.40) + super::TAIL_S);
    s.config = firmware::Config::cia402_example();
    s.wheel_faults.push(WheelFault {
        kind,
        wheel,
        from_us: us(onset_s),
        until_us: until_s.map_or(s.duration_us() + 1, us),
    });
    s
}

/// A stop row: the fault's state reached `latency` after `from_us` (within `budget`), then
/// quick stop with zero targets to each of `nodes` (the started ones) within one cycle.
#[allow(clippy::too_many_arguments)]
fn stop_row(
    fault: &str,
    onset: (f64, &str),
    rec: &Record,
    want: Fault,
    from_us: Option<u64>,
    budget: (u64, u64),
    nodes: &[u8],
    extra: (bool, String),
) -> Row {
    let cycle_us = 1_000_000 / u64::from(firmware::Config::cia402_example().timing.setpoint_hz);
    let hit = rec.first(us(onset.0), (RobotState::Fault, want));
    let latency = hit.zip(from_us).map(|(h, f)| h.saturating_sub(f));
    let stopped = hit.and_then(|h| rec.quick_stopped(h, nodes)).zip(hit);
    let stop_latency = stopped.map(|(s, h)| s - h);
    let pass = latency.is_some_and(|l| (budget.0..=budget.1).contains(&l))
        && stop_latency.is_some_and(|l| l <= cycle_us + MS)
        && extra.0;
    Row {
        fault: fault.into(),
        onset: moment(onset),
        expected: format!(
            "FAULT ({}), quick stop and zero targets to {}",
            want.as_str(),
            if nodes.len() == 2 {
                "every node".to_string()
            } else {
                let list: Vec<String> = nodes.iter().map(u8::to_string).collect();
                format!("node {} (the started ones)", list.join(", "))
            }
        ),
        budget: if budget.0 > 0 {
            format!("{} to {}", ms(budget.0), ms(budget.1))
        } else {
            format!("≤ {}", ms(budget.1))
        },
        measured: latency.map_or("-".into(), ms),
        detail: format!(
            "quick stop {} later (≤ one {} cycle); {}",
            stop_latency.map_or("never".into(), ms),
            ms(cycle_us),
            extra.1
        ),
        pass,
    }
}

pub(super) fn rows() -> Vec<Row> {
    let cruising = MOMENTS[1];
    let consumer_us = 150 * MS;
    vec![
        heartbeat_lost_row(cruising, consumer_us),
        reboot_row(cruising),
        drive_fault_row(cruising),
        sdo_abort_row(),
        enable_refused_row(),
        runner_restart_row(cruising, consumer_us),
        bus_off_row(cruising),
    ]
}

/// Node 2's heartbeat stops: the fault from its last heartbeat, after the consumer time.
fn heartbeat_lost_row(cruising: (f64, &str), consumer_us: u64) -> Row {
    let rec = run(&scenario(cruising.0, FaultName::DriveSilent, 3, None));
    let last_beat = rec
        .heartbeats
        .iter()
        .filter(|(t, n, _)| *n == 2 && *t <= us(cruising.0) + MS)
        .map(|h| h.0)
        .next_back();
    let issue = rec.issue.clone().unwrap_or_default();
    stop_row(
        "CiA 402: a drive's heartbeat stops (node 2)",
        cruising,
        &rec,
        Fault::DriveSilent,
        last_beat,
        (consumer_us, consumer_us + MS),
        &[1, 2],
        (
            issue == "node 2: heartbeat lost",
            format!("from its last heartbeat; \"{issue}\""),
        ),
    )
}

/// Node 1 reboots: boot-up 2 ms later; configured again; no target before the end.
fn reboot_row(cruising: (f64, &str)) -> Row {
    let rec = run(&scenario(cruising.0, FaultName::DriveReboot, 0, None));
    let onset = us(cruising.0);
    let restarted = rec.starts.iter().any(|(t, n)| *t > onset && *n == 1);
    let moved = rec
        .rpdos
        .iter()
        .any(|(t, _, _, target)| *t > onset + 10 * MS && *target != 0);
    let sdo_again = rec
        .sdo
        .iter()
        .filter(|(t, n, _)| *t > onset && *n == 1)
        .count();
    stop_row(
        "CiA 402: a drive reboots (node 1)",
        cruising,
        &rec,
        Fault::DriveRebooted,
        Some(onset),
        (2 * MS, 4 * MS),
        // Node 1 lost its power and its configuration in the reboot: no PDOs until started.
        &[2],
        (
            restarted && !moved && sdo_again == SDO_TRANSFERS,
            format!(
                "boot-up 2 ms after the reboot; configured again ({sdo_again} SDO transfers, \
                 started: {restarted}), no target until the host's reset (none after: {})",
                !moved
            ),
        ),
    )
}

/// Node 2 faults (statusword bit 3, EMCY 0x2310): seen in the next cycle's TPDO.
fn drive_fault_row(cruising: (f64, &str)) -> Row {
    let rec = run(&scenario(cruising.0, FaultName::DriveFault, 2, None));
    let issue = rec.issue.clone().unwrap_or_default();
    stop_row(
        "CiA 402: a drive faults (node 2, EMCY 0x2310)",
        cruising,
        &rec,
        Fault::DriveError,
        Some(us(cruising.0)),
        (0, 4 * MS + 2 * MS),
        &[1, 2],
        (
            rec.emcy == 1 && issue.ends_with("last EMCY 0x2310"),
            format!("{} EMCY counted; \"{issue}\"", rec.emcy),
        ),
    )
}

/// Node 1 aborts the write of the mode: the fault at the step after the answer.
fn sdo_abort_row() -> Row {
    let boot = (0.0, "configuring");
    let rec = run(&scenario(boot.0, FaultName::SdoAbort, 0, None));
    let request = rec
        .sdo
        .iter()
        .find(|(_, n, o)| *n == 1 && *o == (0x6060, 0))
        .map(|r| r.0);
    let issue = rec.issue.clone().unwrap_or_default();
    let hit = rec.first(0, (RobotState::Fault, Fault::DriveSetup));
    let latency = hit.zip(request).map(|(h, r)| h - r);
    Row {
        fault: "CiA 402: a drive aborts an SDO write (node 1, 0x6060)".into(),
        onset: moment(boot),
        expected: "FAULT (DRIVE_SETUP) naming the object and the abort code".into(),
        budget: format!("≤ {}", ms(2 * MS)),
        measured: latency.map_or("-".into(), ms),
        detail: format!("from the request; \"{issue}\""),
        pass: latency.is_some_and(|l| l <= 2 * MS)
            && issue.starts_with("node 1: SDO abort 0x06090030 on 0x6060:00"),
    }
}

/// Node 2 never reaches operation enabled: the enable step times out.
fn enable_refused_row() -> Row {
    let enabling = (0.05, "enabling");
    let rec = run(&scenario(0.0, FaultName::EnableRefused, 3, None));
    let enable_op = rec
        .rpdos
        .iter()
        .find(|(_, n, cw, _)| *n == 2 && *cw == Some(0x0F))
        .map(|r| r.0);
    let issue = rec.issue.clone().unwrap_or_default();
    let timeout = CIA402_TRANSITION_TIMEOUT_US;
    stop_row(
        "CiA 402: a drive's enable does not come (node 2)",
        enabling,
        &rec,
        Fault::DriveTransition,
        enable_op,
        (timeout, timeout + 2 * MS),
        &[1, 2],
        (
            issue.contains("last statusword 0x0233 (SWITCHED_ON)")
                && !rec.rpdos.iter().any(|r| r.3 != 0),
            format!("from the first 0x0F sent, the robot never moved; \"{issue}\""),
        ),
    )
}

/// The host's reset and enable of the recovery rows: a reset at `reset_s`, an enable 50 ms
/// later.
fn reset_and_enable(s: &mut Scenario, reset_s: f64) {
    add_action(
        s,
        Action {
            reset: true,
            ..Action::at(reset_s)
        },
    );
    add_action(
        s,
        Action {
            enable: true,
            ..Action::at(reset_s + 0.05)
        },
    );
}

/// The runner killed while the robot drives, started again 0.3 s later: the drives' consumer
/// times out on the master's heartbeat, they fault and go pre-operational; the new core
/// resets, configures and starts them; after the host's reset and enable the robot drives.
fn runner_restart_row(onset: (f64, &str), consumer_us: u64) -> Row {
    let (killed_s, restarted_s, reset_s) = (onset.0, onset.0 + 0.30, onset.0 + 0.40);
    let mut s = drive(super::TURN, reset_s + 0.35);
    s.config = firmware::Config::cia402_example();
    s.node_faults.push(NodeFault {
        kind: FaultName::RunnerRestart,
        from_us: us(killed_s),
        until_us: us(restarted_s),
    });
    reset_and_enable(&mut s, reset_s);
    let rec = run(&s);
    let (killed, restarted, enable) = (us(killed_s), us(restarted_s), us(reset_s + 0.05));
    // The master's last heartbeat the drives heard, and their pre-operational heartbeats.
    let master_beat = rec
        .heartbeat_master
        .iter()
        .copied()
        .rfind(|&t| t < killed + MS);
    let pre_op = [1, 2].map(|n| rec.heartbeat(killed, n, NmtState::PreOperational));
    let latency = master_beat
        .zip(pre_op[0].zip(pre_op[1]))
        .map(|(m, (a, b))| a.max(b) - m);
    let timeouts = rec
        .emcys
        .iter()
        .filter(|e| e.0 >= killed && e.0 < restarted && e.2 == 0x8130)
        .count();
    // The new core: its NMT commands, SDO transfers and start.
    let commands: Vec<(NmtCommand, u8)> = rec
        .nmt
        .iter()
        .filter(|n| n.0 >= restarted)
        .map(|&(_, c, n)| (c, n))
        .collect();
    let sdo = rec
        .sdo
        .iter()
        .filter(|r| r.0 >= restarted && r.1 == 1)
        .count();
    let started = rec
        .starts
        .iter()
        .filter(|r| r.0 >= restarted)
        .map(|r| r.0)
        .max();
    let operation = rec.operation_enabled(enable);
    let moving = rec.first_target(enable);
    let frames_dead = rec
        .rpdos
        .iter()
        .filter(|r| r.0 > killed + MS && r.0 < restarted)
        .count();
    let want_commands = [
        (NmtCommand::ResetCommunication, 1),
        (NmtCommand::ResetCommunication, 2),
        (NmtCommand::Start, 1),
        (NmtCommand::Start, 2),
    ];
    let pass = latency.is_some_and(|l| (consumer_us..=consumer_us + MS).contains(&l))
        && timeouts == 2
        && frames_dead == 0
        && commands.len() == 4
        && want_commands.iter().all(|c| commands.contains(c))
        && sdo == SDO_TRANSFERS
        && operation.is_some()
        && moving.is_some()
        && rec.last() == (RobotState::Enabled, Fault::None);
    let after = |t: Option<u64>, from: u64| t.map_or("never".into(), |t| ms(t - from));
    Row {
        fault: "CiA 402: the runner killed and restarted 0.30 s later".into(),
        onset: moment(onset),
        expected: "both drives PRE_OPERATIONAL after the consumer time; the new core resets, \
                   configures and starts them; ENABLED and driving after the host's reset and \
                   enable"
            .into(),
        budget: format!("{} to {}", ms(consumer_us), ms(consumer_us + MS)),
        measured: latency.map_or("-".into(), ms),
        detail: format!(
            "from the master's last heartbeat to both drives' 0x7F ({timeouts} EMCY 0x8130); \
             the new core at +{}: reset communication, {sdo} SDO transfers a node, started \
             {} after its first step; reset {} later, enable 50 ms after it: operation enabled \
             in {}, targets in {}",
            ms(restarted - killed),
            after(started, restarted),
            ms(us(reset_s) - restarted),
            after(operation, enable),
            after(moving, enable)
        ),
        pass,
    }
}

/// Node 2 bus-off for 2 ms (128 x 11 recessive bits at 1 Mbit/s take 1.4 ms): back
/// pre-operational with EMCY 0x8140; the robot faults `DRIVE_NMT`; the host's reset starts
/// the node (its configuration is intact) and the robot drives again after the enable.
fn bus_off_row(onset: (f64, &str)) -> Row {
    let (off_s, back_s, reset_s) = (onset.0, onset.0 + 0.002, onset.0 + 0.15);
    let mut s = scenario(off_s, FaultName::DriveBusOff, 2, Some(back_s));
    reset_and_enable(&mut s, reset_s);
    let rec = run(&s);
    let (back, reset, enable) = (us(back_s), us(reset_s), us(reset_s + 0.05));
    let pre_op = rec.heartbeat(us(off_s), 2, NmtState::PreOperational);
    let emcy = rec
        .emcys
        .iter()
        .find(|e| e.0 >= us(off_s) && e.1 == 2)
        .map(|e| e.2);
    let issue = rec.issue.clone().unwrap_or_default();
    let commands: Vec<_> = rec
        .nmt
        .iter()
        .filter(|n| n.0 >= reset)
        .map(|&(_, c, n)| (c, n))
        .collect();
    let sdo = rec.sdo.iter().filter(|r| r.0 >= us(off_s)).count();
    let operation = rec.operation_enabled(enable);
    let moving = rec.first_target(enable);
    let after = |t: Option<u64>, from: u64| t.map_or("never".into(), |t| ms(t - from));
    let mut row = stop_row(
        "CiA 402: a drive bus-off for 2 ms (node 2)",
        onset,
        &rec,
        Fault::DriveNmt,
        Some(back),
        (0, 2 * MS),
        &[1, 2],
        (
            emcy == Some(0x8140)
                && pre_op.is_some_and(|t| t >= back)
                && issue == "node 2: NMT PRE_OPERATIONAL"
                && commands == [(NmtCommand::Start, 2)]
                && sdo == 0
                && operation.is_some()
                && moving.is_some()
                && rec.last() == (RobotState::Enabled, Fault::None),
            format!(
                "from its return (EMCY 0x{:04X}, heartbeat 0x7F {} after it); \"{issue}\"; \
                 reset 0.15 s after the bus-off: NMT start to node 2 only, {sdo} SDO \
                 transfers; enable 50 ms later: operation enabled in {}, targets in {}",
                emcy.unwrap_or(0),
                after(pre_op, back),
                after(operation, enable),
                after(moving, enable)
            ),
        ),
    );
    row.expected
        .push_str("; ENABLED and driving after the host's reset and enable");
    row
}
