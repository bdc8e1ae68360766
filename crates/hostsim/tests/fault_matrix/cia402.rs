//! The CiA 402 rows: each fault of a CANopen drive on the example robot (two dual-axis nodes,
//! a 250 Hz cycle), injected into the simulated node while the robot drives. A stop is the
//! fault's state with quick stop (`0x02`) and zero targets delivered to every node; latencies
//! run from what the firmware could first have known, read from the bus deliveries (the
//! node's last heartbeat, the enable step sent).

use firmware::control::{CIA402_TRANSITION_TIMEOUT_US, Fault};
use firmware::protocol::canopen::{self, Message, NmtCommand, NmtState};
use firmware::protocol::robot::RobotState;
use hostsim::bus::{Fate, Node};
use hostsim::drives::SimDrives;
use hostsim::scenario::{FaultName, Scenario, WheelFault};
use hostsim::sim::{LogOptions, run_observed};

use super::{MOMENTS, MS, Row, drive, moment, ms, us};

/// What a CiA 402 run shows.
#[derive(Debug, Default)]
struct Record {
    /// Every step: time, state, fault.
    steps: Vec<(u64, RobotState, Fault)>,
    /// Heartbeats delivered from the drives: time, node, state.
    heartbeats: Vec<(u64, u8, NmtState)>,
    /// RPDO1s delivered from the firmware: time, node, controlword, target; RPDO3 targets
    /// as controlword `None`.
    rpdos: Vec<(u64, u8, Option<u16>, i32)>,
    /// NMT starts sent: time, node.
    starts: Vec<(u64, u8)>,
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
    let mut plant = SimDrives::for_scenario(s).unwrap();
    let mut rec = Record::default();
    let mut last = None;
    run_observed(s, &mut plant, None, LogOptions::default(), |v| {
        for tx in v.delivered.iter().filter(|tx| tx.fate != Fate::Dropped) {
            let t = tx.delivered_ns / 1000;
            match (tx.from, canopen::decode(&tx.frame)) {
                (Node::Drives, Ok(Message::Heartbeat { node, state })) => {
                    rec.heartbeats.push((t, node.get(), state));
                }
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
                        command: NmtCommand::Start,
                        node: Some(node),
                    }),
                ) => rec.starts.push((t, node.get())),
                (Node::Controller, Ok(Message::SdoRequest { node, request })) => {
                    rec.sdo.push((t, node.get(), request.object()));
                }
                _ => {}
            }
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
    let mut rows = Vec::new();
    let cruising = MOMENTS[1];
    let consumer_us = 150 * MS;

    // Node 2's heartbeat stops: the fault from its last heartbeat, after the consumer time.
    let rec = run(&scenario(cruising.0, FaultName::DriveSilent, 3, None));
    let last_beat = rec
        .heartbeats
        .iter()
        .filter(|(t, n, _)| *n == 2 && *t <= us(cruising.0) + MS)
        .map(|h| h.0)
        .next_back();
    let issue = rec.issue.clone().unwrap_or_default();
    rows.push(stop_row(
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
    ));

    // Node 1 reboots: boot-up 2 ms later; configured again; no target before the end.
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
    rows.push(stop_row(
        "CiA 402: a drive reboots (node 1)",
        cruising,
        &rec,
        Fault::DriveRebooted,
        Some(onset),
        (2 * MS, 4 * MS),
        // Node 1 lost its power and its configuration in the reboot: no PDOs until started.
        &[2],
        (
            restarted && !moved && sdo_again == 34,
            format!(
                "boot-up 2 ms after the reboot; configured again ({sdo_again} SDO transfers, \
                 started: {restarted}), no target until the host's reset (none after: {})",
                !moved
            ),
        ),
    ));

    // Node 2 faults (statusword bit 3, EMCY 0x2310): seen in the next cycle's TPDO.
    let rec = run(&scenario(cruising.0, FaultName::DriveFault, 2, None));
    let issue = rec.issue.clone().unwrap_or_default();
    rows.push(stop_row(
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
    ));

    // Node 1 aborts the write of the mode: the fault at the step after the answer.
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
    rows.push(Row {
        fault: "CiA 402: a drive aborts an SDO write (node 1, 0x6060)".into(),
        onset: moment(boot),
        expected: "FAULT (DRIVE_SETUP) naming the object and the abort code".into(),
        budget: format!("≤ {}", ms(2 * MS)),
        measured: latency.map_or("-".into(), ms),
        detail: format!("from the request; \"{issue}\""),
        pass: latency.is_some_and(|l| l <= 2 * MS)
            && issue.starts_with("node 1: SDO abort 0x06090030 on 0x6060:00"),
    });

    // Node 2 never reaches operation enabled: the enable step times out.
    let enabling = (0.05, "enabling");
    let rec = run(&scenario(0.0, FaultName::EnableRefused, 3, None));
    let enable_op = rec
        .rpdos
        .iter()
        .find(|(_, n, cw, _)| *n == 2 && *cw == Some(0x0F))
        .map(|r| r.0);
    let issue = rec.issue.clone().unwrap_or_default();
    let timeout = CIA402_TRANSITION_TIMEOUT_US;
    rows.push(stop_row(
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
    ));
    rows
}
