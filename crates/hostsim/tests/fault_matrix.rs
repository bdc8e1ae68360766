//! The fault matrix: every fault the simulator injects, at several moments of a drive, run in
//! lockstep with the real firmware core; each must end in the state the firmware specifies
//! (`docs/control.md`) within its latency budget. The CiA 402 drives' rows are in
//! `fault_matrix/cia402.rs`.
//!
//! Latencies are measured from the simulator's record, not from the firmware's opinion of
//! itself: the fault's onset is the scenario time, the reaction is the first step whose state
//! (and, for a stop, whose current frame) shows it, and what the firmware *should* have seen
//! (gaps in a motor's feedback, the last twist it accepted) comes from the bus deliveries.
//!
//! `cargo test -p hostsim --test fault_matrix -- --nocapture` prints the tables. They are kept
//! in `docs/reliability.md` (section "Fault matrix") and checked against it; after a change
//! that moves a figure, `UPDATE_FAULT_MATRIX=1 cargo test -p hostsim --test fault_matrix`
//! rewrites them there.

use firmware::Config;
use firmware::control::{ENCODER_STUCK_SPINNING_US, Fault};
use firmware::protocol::robot::RobotState;
use hostsim::bus::{FaultKind, Node};
use hostsim::scenario::{FaultName, Scenario, WheelFault};

const MS: u64 = 1_000;

#[path = "fault_matrix/cia402.rs"]
mod cia402;
#[path = "fault_matrix/docs.rs"]
mod docs;
#[path = "fault_matrix/drive.rs"]
mod drive;
#[path = "fault_matrix/dropouts.rs"]
mod dropouts;
#[path = "fault_matrix/record.rs"]
mod record;
#[path = "fault_matrix/rows.rs"]
mod rows;

use docs::{current_figures, keep_in_docs, table};
use drive::{MOMENTS, TAIL_S, TURN, add_action, at, bus_fault, drive, faulted, silenced, us};
use record::{Record, run};
use rows::{
    Row, host_tolerated_row, moment, ms, non_finite_row, repeated_twist_row, stale_rule_row,
    state_row, stuck_at_rest_row, watchdog_row,
};

#[test]
fn every_fault_ends_in_its_specified_state_within_its_budget() {
    let rows = matrix();
    let t = table(&rows);
    println!("{t}");
    let failed: Vec<_> = rows
        .iter()
        .filter(|r| !r.pass)
        .map(|r| (&r.fault, &r.onset, &r.detail))
        .collect();
    assert!(failed.is_empty(), "failed rows: {failed:#?}");
    keep_in_docs("fault-matrix", &t);
    keep_in_docs("current-fault-matrix", &current_figures(&rows));
}

/// Every row, in the table's order.
fn matrix() -> Vec<Row> {
    let config = Config::dji_m3508_example();
    let stale_us = 1_000 * u64::from(config.timing.stale_periods);
    // Stale limit, then the next control step.
    let stale_budget = stale_us + MS;
    let mut rows = Vec::new();
    // The drive without faults, once per moment, for comparisons.
    let bases = MOMENTS.map(|m| run(&at(m.0)));
    let with_bases = || MOMENTS.into_iter().zip(&bases);

    for (m, base) in with_bases() {
        rows.extend(dropped_frame_rows(m, base));
    }
    for (m, base) in with_bases() {
        rows.extend(burst_rows(m, base, stale_budget));
    }
    for (m, base) in with_bases() {
        rows.extend(delay_rows(m, base, stale_budget));
    }
    for (m, base) in with_bases() {
        rows.extend(corrupt_rows(m, base));
    }
    rows.extend(MOMENTS.map(stuck_encoder_row));
    rows.push(stuck_at_rest_row(&config));
    rows.extend(MOMENTS.map(|m| motor_offline_row(m, stale_budget)));
    rows.extend(MOMENTS.map(silence_row));
    rows.extend(MOMENTS.map(repeated_twist_row));
    rows.extend(with_bases().map(|(m, base)| non_finite_row(m, Some(base))));
    rows.extend(MOMENTS.map(|m| non_finite_row(m, None)));
    rows.extend(manoeuvre_watchdog_rows());
    rows.extend(cia402::rows());
    rows
}

/// Feedback and host frames dropped at random: 1 % and 5 % of the feedback for 0.3 s (and,
/// while cruising, 5 % for 3 s), 5 % of the host's frames.
fn dropped_frame_rows(m: (f64, &str), base: &Record) -> Vec<Row> {
    let mut rows = Vec::new();
    for rate in [0.01, 0.05] {
        let s = faulted(m.0, FaultKind::Drop { rate }, 0.3, Node::Drives);
        let name = format!("drop {:.0} % of feedback, 0.3 s", rate * 100.0);
        rows.push(stale_rule_row(&name, m, &s, base, None));
    }
    if m.1 == "cruising" {
        // Sustained loss: three frames of one motor in a row go missing now and then.
        let mut s = drive(TURN, 3.0 + TAIL_S);
        bus_fault(
            &mut s,
            FaultKind::Drop { rate: 0.05 },
            m.0,
            3.0,
            Node::Drives,
        );
        let base = run(&drive(TURN, 3.0 + TAIL_S));
        let name = "drop 5 % of feedback, 3 s";
        rows.push(stale_rule_row(name, m, &s, &base, None));
    }
    let s = faulted(m.0, FaultKind::Drop { rate: 0.05 }, 0.3, Node::Host);
    rows.push(host_tolerated_row("drop 5 % of host frames, 0.3 s", m, &s));
    rows
}

/// Bursts: all feedback lost for 2 ms and for 10 ms, the host's frames for 150 ms.
fn burst_rows(m: (f64, &str), base: &Record, stale_budget: u64) -> [Row; 3] {
    let s = faulted(m.0, FaultKind::Burst, 0.002, Node::Drives);
    let short = stale_rule_row("burst: all feedback lost for 2 ms", m, &s, base, None);
    let s = faulted(m.0, FaultKind::Burst, 0.010, Node::Drives);
    let name = "burst: all feedback lost for 10 ms";
    let long = stale_rule_row(name, m, &s, base, Some(stale_budget));
    let s = faulted(m.0, FaultKind::Burst, 0.150, Node::Host);
    let host = watchdog_row("burst: host frames lost for 150 ms", m, &s, &run(&s));
    [short, long, host]
}

/// Delays: the feedback 2 ms and 10 ms later, the host's frames 30 ms later.
fn delay_rows(m: (f64, &str), base: &Record, stale_budget: u64) -> [Row; 3] {
    let delay = |micros| FaultKind::Delay { micros };
    let s = faulted(m.0, delay(2_000), 0.3, Node::Drives);
    let short = stale_rule_row("delay: feedback 2 ms later", m, &s, base, None);
    let s = faulted(m.0, delay(10_000), 0.3, Node::Drives);
    let name = "delay: feedback 10 ms later";
    let long = stale_rule_row(name, m, &s, base, Some(stale_budget));
    let s = faulted(m.0, delay(30_000), 0.3, Node::Host);
    let host = host_tolerated_row("delay: host frames 30 ms later", m, &s);
    [short, long, host]
}

/// A corrupted byte in half the host's frames, and in 2 % of the feedback.
fn corrupt_rows(m: (f64, &str), base: &Record) -> [Row; 2] {
    let s = faulted(m.0, FaultKind::Corrupt { rate: 0.5 }, 0.3, Node::Host);
    let host = host_tolerated_row("corrupt byte in 50 % of host frames", m, &s);
    let s = faulted(m.0, FaultKind::Corrupt { rate: 0.02 }, 0.3, Node::Drives);
    let feedback = stale_rule_row("corrupt byte in 2 % of feedback", m, &s, base, None);
    [host, feedback]
}

/// The drive with the wheel fault `kind` on `wheel` from `m` to the end.
fn wheel_fault(m: (f64, &str), kind: FaultName, wheel: usize) -> Scenario {
    let mut s = at(m.0);
    s.wheel_faults.push(WheelFault {
        kind,
        wheel,
        from_us: us(m.0),
        until_us: s.duration_us() + 1,
    });
    s
}

/// RL's encoder stuck while the robot drives (rule 1).
fn stuck_encoder_row(m: (f64, &str)) -> Row {
    let s = wheel_fault(m, FaultName::StuckEncoder, 2);
    // Rule 1: the first repeated angle comes one feedback period after the onset and
    // reaches the next step; the interval must then last the window.
    let budget = (
        ENCODER_STUCK_SPINNING_US,
        ENCODER_STUCK_SPINNING_US + 3 * MS,
    );
    state_row(
        "stuck encoder (RL), frozen angle and rpm",
        m,
        &s,
        (RobotState::Fault, Fault::EncoderStuck),
        us(m.0),
        budget,
        |_| "rule 1: still angle while reporting speed".into(),
    )
}

/// FR's motor goes offline.
fn motor_offline_row(m: (f64, &str), stale_budget: u64) -> Row {
    let s = wheel_fault(m, FaultName::MotorOffline, 1);
    state_row(
        "motor offline (FR)",
        m,
        &s,
        (RobotState::Fault, Fault::MotorStale),
        us(m.0),
        (0, stale_budget),
        |_| "its last frame is the one due 1 ms before the onset".into(),
    )
}

/// The host stops sending.
fn silence_row(m: (f64, &str)) -> Row {
    let s = silenced(at(m.0), m.0);
    watchdog_row("bus silence: the host stops sending", m, &s, &run(&s))
}

/// The host goes silent during a spin, an arc, and while strafing and turning.
fn manoeuvre_watchdog_rows() -> [Row; 3] {
    [
        (
            [0.0, 0.0, 2.0],
            (0.70, "spinning on the spot"),
            "watchdog expiry during a spin",
        ),
        (
            [0.5, 0.0, 1.0],
            (0.77, "arc"),
            "watchdog expiry during an arc",
        ),
        (
            [0.0, -0.4, -1.5],
            (0.85, "strafing and turning"),
            "watchdog expiry while strafing and turning",
        ),
    ]
    .map(|(turn, onset, name)| {
        let s = silenced(drive(turn, onset.0 + TAIL_S), onset.0);
        watchdog_row(name, onset, &s, &run(&s))
    })
}
