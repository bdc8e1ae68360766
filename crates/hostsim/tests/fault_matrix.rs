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

use std::fmt::Write as _;
use std::path::Path;

use firmware::Config;
use firmware::control::{
    ENCODER_STUCK_DRAGGED_US, ENCODER_STUCK_MIN_CURRENT, ENCODER_STUCK_SPINNING_US, Fault,
};
use firmware::protocol::dji::{self, CurrentCommand, EscModel};
use firmware::protocol::robot::{Command, RobotState};
use hostsim::bus::{self, Fate, FaultKind, Node, SplitMix64};
use hostsim::drives::SimDrives;
use hostsim::scenario::{Action, FaultName, HostFault, Scenario, WheelFault};
use hostsim::sim::{LogOptions, StepView, run_observed};
use kinematics::ChassisVelocity;

const MS: u64 = 1_000;

#[path = "fault_matrix/cia402.rs"]
mod cia402;

// ---------------------------------------------------------------------------------------
// Recording a run

/// One control step as the record shows it.
#[derive(Debug, Clone, Copy)]
struct Step {
    t_us: u64,
    state: RobotState,
    fault: Fault,
    commanded: ChassisVelocity<f32>,
    /// The step's DJI current frame, A (motor sign).
    currents: [f32; 4],
    /// The wheel speed setpoints are all zero.
    setpoints_zero: bool,
    rx_errors: u64,
    /// Twists the firmware counted as repeats of the last accepted one.
    repeated_seq: u64,
    odom_error_m: f64,
    /// A motor's feedback gap has exceeded the stale limit by this step (the oracle).
    stale_due: bool,
}

impl Step {
    fn zero_current(&self) -> bool {
        self.currents.iter().all(|&a| a == 0.0)
    }
}

#[derive(Debug, Default)]
struct Record {
    steps: Vec<Step>,
    /// Delivery times (µs) of the twist commands the firmware must accept.
    twists: Vec<u64>,
    /// Delivery times (µs) of the twists that repeat the `seq` of the last one in `twists`:
    /// the firmware must count them and not accept them.
    repeats: Vec<u64>,
    /// Repeats whose bytes differ from the twist they repeat.
    repeats_changed: u64,
    /// Host frames corrupted on the bus.
    corrupted_host: u64,
    /// Largest gap (µs) between two decodable feedback frames of one motor, at step times.
    max_feedback_gap_us: u64,
}

impl Record {
    fn at(&self, t_us: u64) -> &Step {
        let i = self.steps.partition_point(|s| s.t_us < t_us);
        &self.steps[i.min(self.steps.len() - 1)]
    }

    /// The first step at or after `from_us` that satisfies `pred`.
    fn first(&self, from_us: u64, pred: impl Fn(&Step) -> bool) -> Option<&Step> {
        self.steps.iter().find(|s| s.t_us >= from_us && pred(s))
    }

    /// The last accepted twist delivered at or before `t_us`.
    fn last_twist(&self, t_us: u64) -> Option<u64> {
        self.twists.iter().rev().copied().find(|&t| t <= t_us)
    }

    /// Largest gap (µs) between accepted twists delivered in `[from_us, until_us)`.
    fn max_twist_gap(&self, from_us: u64, until_us: u64) -> u64 {
        let mut last = self.last_twist(from_us).unwrap_or(from_us);
        let mut gap = 0;
        for &t in self.twists.iter().filter(|&&t| t > from_us && t < until_us) {
            gap = gap.max(t - last);
            last = t;
        }
        gap.max(until_us.saturating_sub(last))
    }
}

/// The `seq` of `frame` if it is a twist the firmware must take: it decodes and is within
/// the configured limits. (It is a command if its `seq` differs from the last command's,
/// else a repeat: see [`run`].)
fn acceptable_twist(config: &Config, frame: &firmware::CanFrame) -> Option<u8> {
    let Ok(Command::Twist(t)) = Command::decode(frame) else {
        return None;
    };
    let l = &config.limits;
    (t.vx.hypot(t.vy) <= l.max_linear_speed && t.wz.abs() <= l.max_angular_speed).then_some(t.seq)
}

fn run(s: &Scenario) -> Record {
    let config = s.config;
    let stale_us = 1_000 * u64::from(config.timing.stale_periods);
    let mut plant = SimDrives::new(&config).unwrap();
    let mut rec = Record::default();
    let mut last_feedback: [Option<u64>; 4] = [None; 4];
    let mut stale_seen = false;
    // The last twist command: its seq and its frame. (The host never repeats a seq on its
    // own, so across its enables this is the firmware's rule too.)
    let mut last_twist: Option<(u8, firmware::CanFrame)> = None;
    let observe = |v: &StepView<'_>| {
        for tx in v.delivered.iter().filter(|tx| tx.fate != Fate::Dropped) {
            let t_us = tx.delivered_ns / 1000;
            match tx.from {
                Node::Host => {
                    rec.corrupted_host += u64::from(tx.fate == Fate::Corrupted);
                    match (acceptable_twist(&config, &tx.frame), last_twist) {
                        (Some(seq), Some((last, frame))) if seq == last => {
                            rec.repeats.push(t_us);
                            rec.repeats_changed += u64::from(tx.frame != frame);
                        }
                        (Some(seq), _) => {
                            rec.twists.push(t_us);
                            last_twist = Some((seq, tx.frame));
                        }
                        (None, _) => {}
                    }
                }
                Node::Drives => {
                    if let Ok(fb) = dji::Feedback::decode(&tx.frame, EscModel::C620) {
                        let wheel = usize::from(fb.esc.get() - 1);
                        last_feedback[wheel] = Some(t_us);
                    }
                }
                // The fault matrix's scenarios have no IMU and no pods.
                Node::Controller | Node::Imu | Node::Pods => {}
            }
        }
        // The firmware's stale rule, from the deliveries: feedback older than the limit.
        for seen in last_feedback.iter().flatten() {
            let gap = v.t_us - seen;
            rec.max_feedback_gap_us = rec.max_feedback_gap_us.max(gap);
            stale_seen |= gap > stale_us;
        }
        let snap = v.controller.snapshot();
        let currents = v
            .sent
            .iter()
            .find_map(|f| CurrentCommand::decode(f, EscModel::C620).ok())
            .map(|c| c.amps())
            .expect("a current frame every step");
        let p = snap.pose;
        rec.steps.push(Step {
            t_us: v.t_us,
            state: snap.state,
            fault: snap.fault,
            commanded: snap.commanded,
            currents,
            setpoints_zero: snap.wheel_setpoints.0.iter().all(|&w| w == 0.0),
            rx_errors: u64::from(snap.rx_errors.total()),
            repeated_seq: u64::from(snap.repeated_seq),
            odom_error_m: (f64::from(p.x) - v.truth[0]).hypot(f64::from(p.y) - v.truth[1]),
            stale_due: stale_seen,
        });
    };
    run_observed(s, &mut plant, None, LogOptions::default(), observe).unwrap();
    rec
}

// ---------------------------------------------------------------------------------------
// The drive every fault is injected into

/// Enable at 50 ms; 0.6 m/s forward from 0.1 s (accelerating at 4 m/s² until 0.25 s, then
/// cruising); from 0.6 s `turn` (the ramp into it takes about 0.1 s). Twists stream at
/// 50 Hz.
fn drive(turn: [f32; 3], duration_s: f64) -> Scenario {
    let mut s = Scenario::from_toml("duration_s = 1.0\nseed = 11", Path::new("matrix.toml"))
        .expect("a minimal scenario");
    s.duration_s = duration_s;
    s.actions = vec![
        Action {
            enable: true,
            ..Action::at(0.05)
        },
        Action::twist(0.1, 0.6, 0.0, 0.0),
        Action::twist(0.6, turn[0], turn[1], turn[2]),
    ];
    s
}

const TURN: [f32; 3] = [0.4, 0.2, 1.0];

/// The moments of the drive a fault starts at.
const MOMENTS: [(f64, &str); 3] = [
    (0.15, "accelerating"),
    (0.40, "cruising"),
    (0.75, "turning"),
];

/// How long each run goes on after the onset, s.
const TAIL_S: f64 = 0.35;

fn at(onset_s: f64) -> Scenario {
    drive(TURN, onset_s + TAIL_S)
}

fn us(s: f64) -> u64 {
    (s * 1e6).round() as u64
}

fn bus_fault(s: &mut Scenario, kind: FaultKind, from_s: f64, len_s: f64, sender: Node) {
    s.bus_faults.push(bus::Fault {
        kind,
        from_us: us(from_s),
        until_us: us(from_s + len_s),
        sender: Some(sender),
    });
}

fn add_action(s: &mut Scenario, a: Action) {
    s.actions.push(a);
    s.actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
}

// ---------------------------------------------------------------------------------------
// Outcomes

/// One row of the matrix.
struct Row {
    fault: String,
    onset: String,
    expected: String,
    budget: String,
    measured: String,
    detail: String,
    pass: bool,
}

fn ms(us: u64) -> String {
    format!("{:.2} ms", us as f64 / 1000.0)
}

/// The watchdog stop budget: timeout, then the ramp from `commanded` at the stop
/// decelerations, within two control periods.
fn stop_budget_us(config: &Config, commanded: ChassisVelocity<f32>) -> u64 {
    let l = &config.limits;
    let ramp_s = (commanded.vx.hypot(commanded.vy) / l.stop_linear_decel)
        .max(commanded.wz.abs() / l.stop_angular_decel);
    u64::from(config.timing.command_timeout_ms) * MS
        + (f64::from(ramp_s) * 1e6).ceil() as u64
        + 2 * MS
}

/// A watchdog stop after `onset_us`: detection, zero current, and the latch afterwards until
/// `until_us`. Returns (zero latency from the last accepted twist, budget, detection latency).
fn check_watchdog_stop(
    config: &Config,
    rec: &Record,
    onset_us: u64,
    until_us: u64,
) -> Result<(u64, u64, u64), String> {
    let timeout_us = u64::from(config.timing.command_timeout_ms) * MS;
    let wd = rec
        .first(onset_us, |s| s.fault == Fault::Watchdog)
        .ok_or("the watchdog never fired")?;
    let last = rec
        .last_twist(wd.t_us)
        .ok_or("no twist before the watchdog")?;
    let detection = wd.t_us - last;
    if !(detection > timeout_us && detection <= timeout_us + MS) {
        return Err(format!("watchdog {detection} us after the last twist"));
    }
    let before = rec.at(wd.t_us - MS).commanded;
    let budget = stop_budget_us(config, before);
    let zero = rec
        .first(wd.t_us, Step::zero_current)
        .ok_or("the currents never reached zero")?;
    if (zero.state, zero.fault) != (RobotState::Disabled, Fault::Watchdog) {
        return Err(format!("zero current in {}/{}", zero.state, zero.fault));
    }
    if zero.t_us >= until_us {
        return Err(format!("not stopped by {until_us} us"));
    }
    // Latched: no current from then on, whatever arrives.
    if let Some(s) = rec.first(zero.t_us, |s| {
        s.t_us < until_us && (!s.zero_current() || s.state != RobotState::Disabled)
    }) {
        return Err(format!(
            "motion or state change after the stop at {} us",
            s.t_us
        ));
    }
    let latency = zero.t_us - last;
    if latency > budget {
        return Err(format!(
            "zero current {latency} us after the last twist, budget {budget}"
        ));
    }
    Ok((latency, budget, detection))
}

fn watchdog_row(fault: &str, onset: (f64, &str), s: &Scenario, rec: &Record) -> Row {
    let onset_us = us(onset.0);
    let end_us = s.duration_us() + 1;
    let (pass, budget, measured, detail) =
        match check_watchdog_stop(&s.config, rec, onset_us, end_us) {
            Ok((latency, budget, detection)) => (
                true,
                format!("≤ {} after the last twist", ms(budget)),
                ms(latency),
                format!("watchdog {} after the last twist", ms(detection)),
            ),
            Err(e) => (false, "-".into(), "-".into(), e),
        };
    Row {
        fault: fault.into(),
        onset: moment(onset),
        expected: "zero current, then DISABLED (WATCHDOG), latched".into(),
        budget,
        measured,
        detail,
        pass,
    }
}

fn moment((t, name): (f64, &str)) -> String {
    format!("{t:.2} s {name}")
}

/// A row whose outcome follows the firmware's stale rule: MotorStale at the first step where
/// a motor's feedback gap exceeds the limit, Enabled otherwise. `budget_from_onset` bounds
/// the fault's latency where a fault is certain.
fn stale_rule_row(
    fault: &str,
    onset: (f64, &str),
    s: &Scenario,
    base: &Record,
    budget_from_onset: Option<u64>,
) -> Row {
    let rec = run(s);
    let onset_us = us(onset.0);
    let end_us = s.duration_us();
    let predicted = rec.first(onset_us, |st| st.stale_due).map(|st| st.t_us);
    let faulted = rec.first(onset_us, |st| st.state == RobotState::Fault);
    let odom = |r: &Record| r.at(end_us).odom_error_m;
    let d_odom = (odom(&rec) - odom(base)).abs();
    let stale_us = 1_000 * u64::from(s.config.timing.stale_periods);
    let gap = format!(
        "largest feedback gap {} (limit {})",
        ms(rec.max_feedback_gap_us),
        ms(stale_us)
    );
    let (expected, budget, measured, detail, pass) = match predicted {
        None => {
            let last = rec.at(end_us);
            (
                "ENABLED, no fault".to_string(),
                "-".to_string(),
                format!("{}, {}", last.state, last.fault),
                format!(
                    "{gap}; odometry error within {:.1} mm of the run without it",
                    d_odom * 1e3
                ),
                faulted.is_none()
                    && (last.state, last.fault) == (RobotState::Enabled, Fault::None)
                    && budget_from_onset.is_none()
                    && d_odom <= 2e-3,
            )
        }
        Some(t) => {
            let latency = faulted.map(|f| f.t_us - onset_us);
            let ok = faulted
                .is_some_and(|f| f.t_us == t && f.fault == Fault::MotorStale && f.zero_current())
                && latency.is_some_and(|l| budget_from_onset.is_none_or(|b| l <= b));
            let budget = budget_from_onset.map_or_else(
                || "the step a feedback gap exceeds the limit".to_string(),
                |b| format!("≤ {} after onset", ms(b)),
            );
            let detail = match budget_from_onset {
                Some(_) => gap,
                None => format!(
                    "{gap}, first at {:.3} s: faulted at that step",
                    t as f64 * 1e-6
                ),
            };
            (
                "FAULT (MOTOR_STALE), zero current".to_string(),
                budget,
                latency.map_or("-".to_string(), ms),
                detail,
                ok,
            )
        }
    };
    Row {
        fault: fault.into(),
        onset: moment(onset),
        expected,
        budget,
        measured,
        detail,
        pass,
    }
}

fn state_row(
    fault: &str,
    onset: (f64, &str),
    s: &Scenario,
    want: (RobotState, Fault),
    from_us: u64,
    budget: (u64, u64),
    detail: impl Fn(&Record) -> String,
) -> Row {
    let rec = run(s);
    let hit = rec.first(us(onset.0), |st| (st.state, st.fault) == want);
    let latency = hit.map(|h| h.t_us - from_us);
    let pass = hit.is_some_and(Step::zero_current)
        && latency.is_some_and(|l| (budget.0..=budget.1).contains(&l));
    Row {
        fault: fault.into(),
        onset: moment(onset),
        expected: format!("{} ({}), zero current", want.0, want.1),
        budget: if budget.0 > 0 {
            format!("{} to {}", ms(budget.0), ms(budget.1))
        } else {
            format!("≤ {}", ms(budget.1))
        },
        measured: latency.map_or("-".into(), ms),
        detail: detail(&rec),
        pass,
    }
}

// ---------------------------------------------------------------------------------------
// The matrix

fn matrix() -> Vec<Row> {
    let config = Config::dji_m3508_example();
    let stale_us = 1_000 * u64::from(config.timing.stale_periods);
    // Stale limit, then the next control step.
    let stale_budget = stale_us + MS;
    let mut rows = Vec::new();
    // The drive without faults, once per moment, for comparisons.
    let bases = MOMENTS.map(|m| run(&at(m.0)));

    for (m, base) in MOMENTS.into_iter().zip(&bases) {
        for rate in [0.01, 0.05] {
            let mut s = at(m.0);
            bus_fault(&mut s, FaultKind::Drop { rate }, m.0, 0.3, Node::Drives);
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
        let mut s = at(m.0);
        bus_fault(&mut s, FaultKind::Drop { rate: 0.05 }, m.0, 0.3, Node::Host);
        rows.push(host_tolerated_row("drop 5 % of host frames, 0.3 s", m, &s));
    }
    for (m, base) in MOMENTS.into_iter().zip(&bases) {
        let mut s = at(m.0);
        bus_fault(&mut s, FaultKind::Burst, m.0, 0.002, Node::Drives);
        rows.push(stale_rule_row(
            "burst: all feedback lost for 2 ms",
            m,
            &s,
            base,
            None,
        ));
        let mut s = at(m.0);
        bus_fault(&mut s, FaultKind::Burst, m.0, 0.010, Node::Drives);
        let name = "burst: all feedback lost for 10 ms";
        rows.push(stale_rule_row(name, m, &s, base, Some(stale_budget)));
        let mut s = at(m.0);
        bus_fault(&mut s, FaultKind::Burst, m.0, 0.150, Node::Host);
        rows.push(watchdog_row(
            "burst: host frames lost for 150 ms",
            m,
            &s,
            &run(&s),
        ));
    }
    for (m, base) in MOMENTS.into_iter().zip(&bases) {
        let mut s = at(m.0);
        bus_fault(
            &mut s,
            FaultKind::Delay { micros: 2_000 },
            m.0,
            0.3,
            Node::Drives,
        );
        rows.push(stale_rule_row(
            "delay: feedback 2 ms later",
            m,
            &s,
            base,
            None,
        ));
        let mut s = at(m.0);
        bus_fault(
            &mut s,
            FaultKind::Delay { micros: 10_000 },
            m.0,
            0.3,
            Node::Drives,
        );
        let name = "delay: feedback 10 ms later";
        rows.push(stale_rule_row(name, m, &s, base, Some(stale_budget)));
        let mut s = at(m.0);
        bus_fault(
            &mut s,
            FaultKind::Delay { micros: 30_000 },
            m.0,
            0.3,
            Node::Host,
        );
        rows.push(host_tolerated_row("delay: host frames 30 ms later", m, &s));
    }
    for (m, base) in MOMENTS.into_iter().zip(&bases) {
        let mut s = at(m.0);
        bus_fault(
            &mut s,
            FaultKind::Corrupt { rate: 0.5 },
            m.0,
            0.3,
            Node::Host,
        );
        rows.push(host_tolerated_row(
            "corrupt byte in 50 % of host frames",
            m,
            &s,
        ));
        let mut s = at(m.0);
        bus_fault(
            &mut s,
            FaultKind::Corrupt { rate: 0.02 },
            m.0,
            0.3,
            Node::Drives,
        );
        rows.push(stale_rule_row(
            "corrupt byte in 2 % of feedback",
            m,
            &s,
            base,
            None,
        ));
    }
    for m in MOMENTS {
        let mut s = at(m.0);
        s.wheel_faults.push(WheelFault {
            kind: FaultName::StuckEncoder,
            wheel: 2,
            from_us: us(m.0),
            until_us: s.duration_us() + 1,
        });
        // Rule 1: the first repeated angle comes one feedback period after the onset and
        // reaches the next step; the interval must then last the window.
        let budget = (
            ENCODER_STUCK_SPINNING_US,
            ENCODER_STUCK_SPINNING_US + 3 * MS,
        );
        rows.push(state_row(
            "stuck encoder (RL), frozen angle and rpm",
            m,
            &s,
            (RobotState::Fault, Fault::EncoderStuck),
            us(m.0),
            budget,
            |_| "rule 1: still angle while reporting speed".into(),
        ));
    }
    rows.push(stuck_at_rest_row(&config));
    for m in MOMENTS {
        let mut s = at(m.0);
        s.wheel_faults.push(WheelFault {
            kind: FaultName::MotorOffline,
            wheel: 1,
            from_us: us(m.0),
            until_us: s.duration_us() + 1,
        });
        rows.push(state_row(
            "motor offline (FR)",
            m,
            &s,
            (RobotState::Fault, Fault::MotorStale),
            us(m.0),
            (0, stale_budget),
            |_| "its last frame is the one due 1 ms before the onset".into(),
        ));
    }
    for m in MOMENTS {
        let mut s = at(m.0);
        add_action(
            &mut s,
            Action {
                silence: true,
                ..Action::at(m.0)
            },
        );
        rows.push(watchdog_row(
            "bus silence: the host stops sending",
            m,
            &s,
            &run(&s),
        ));
    }
    for m in MOMENTS {
        rows.push(repeated_twist_row(m));
    }
    for (m, base) in MOMENTS.into_iter().zip(&bases) {
        rows.push(non_finite_row(m, Some(base)));
    }
    for m in MOMENTS {
        rows.push(non_finite_row(m, None));
    }
    for (turn, onset, name) in [
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
    ] {
        let mut s = drive(turn, onset.0 + TAIL_S);
        add_action(
            &mut s,
            Action {
                silence: true,
                ..Action::at(onset.0)
            },
        );
        rows.push(watchdog_row(name, onset, &s, &run(&s)));
    }
    rows.extend(cia402::rows());
    rows
}

/// The host stops incrementing `seq` and repeats its last twist frame unchanged at 50 Hz
/// from the onset to the end: the watchdog stops the robot as if the host were silent, and
/// every repeat is counted (those after the stop too).
fn repeated_twist_row(m: (f64, &str)) -> Row {
    let mut s = at(m.0);
    let onset_us = us(m.0);
    let end_us = s.duration_us();
    s.host_faults.push(HostFault {
        kind: FaultName::RepeatedTwist,
        from_us: onset_us,
        until_us: end_us + 1,
    });
    let rec = run(&s);
    let mut row = watchdog_row(
        "repeated twist: the host stops incrementing seq, its last frame again at 50 Hz",
        m,
        &s,
        &rec,
    );
    row.expected = format!("{}; repeats counted", row.expected);
    // The firmware's count against the repeats delivered; at 50 Hz from the first frame due at
    // or after the onset to the end.
    let counted = rec.at(end_us).repeated_seq - rec.at(onset_us - MS).repeated_seq;
    let delivered = rec.repeats.len() as u64;
    let due = (TAIL_S * 50.0) as u64;
    // Each repeat is the last frame before the onset, byte for byte, and no twist after
    // the onset is taken for a command.
    let all_repeats = rec.repeats_changed == 0 && rec.last_twist(end_us) < Some(onset_us);
    // The wheel setpoints are zero from the step the currents are (the stop's end) on.
    let zero_current = rec
        .first(onset_us, |st| {
            st.zero_current() && st.state == RobotState::Disabled
        })
        .map(|st| st.t_us);
    let zero_setpoints = rec
        .first(onset_us, |st| st.setpoints_zero)
        .map(|st| st.t_us);
    let setpoints_ok = zero_setpoints.is_some()
        && zero_setpoints == zero_current
        && rec
            .steps
            .iter()
            .filter(|st| zero_setpoints.is_some_and(|t| st.t_us >= t))
            .all(|st| st.setpoints_zero);
    row.pass &= counted == delivered
        && (due..=due + 1).contains(&delivered)
        && all_repeats
        && setpoints_ok
        && rec.at(end_us).rx_errors == rec.at(onset_us - MS).rx_errors;
    row.detail = format!(
        "{}; wheel setpoints zero at the same step{}; {counted} of {delivered} repeats counted, none a rejected frame",
        row.detail,
        if setpoints_ok { "" } else { " NOT" },
    );
    row
}

/// Host-side faults the firmware must ride through: Enabled, no fault, every gap between
/// accepted twists below the timeout; rejected frames counted.
fn host_tolerated_row(fault: &str, onset: (f64, &str), s: &Scenario) -> Row {
    let corrupting = s
        .bus_faults
        .iter()
        .any(|f| matches!(f.kind, FaultKind::Corrupt { .. }));
    let rec = run(s);
    let onset_us = us(onset.0);
    let end_us = s.duration_us();
    let timeout_us = u64::from(s.config.timing.command_timeout_ms) * MS;
    let gap = rec.max_twist_gap(onset_us, onset_us + us(0.3));
    let last = rec.at(end_us);
    let rejected = last.rx_errors - rec.at(onset_us).rx_errors;
    // A byte flipped into `seq` can repeat the last command's: counted, not taken.
    let repeated = last.repeated_seq - rec.at(onset_us).repeated_seq;
    let pass = gap < timeout_us
        && rec
            .first(onset_us, |st| st.state != RobotState::Enabled)
            .is_none()
        && last.fault == Fault::None
        && repeated == rec.repeats.len() as u64
        && rejected + repeated <= rec.corrupted_host;
    Row {
        fault: fault.into(),
        onset: moment(onset),
        expected: if corrupting {
            "ENABLED, no fault; frames out of range rejected and counted".into()
        } else {
            "ENABLED, no fault".into()
        },
        budget: format!("twist gaps < {}", ms(timeout_us)),
        measured: format!("{}, {}", last.state, last.fault),
        detail: if rec.corrupted_host > 0 {
            let repeats = if repeated > 0 {
                format!(", {repeated} a repeat of the last seq")
            } else {
                String::new()
            };
            format!(
                "largest twist gap {}; {} corrupted: {rejected} rejected{repeats}, {} accepted as another valid twist",
                ms(gap),
                rec.corrupted_host,
                rec.corrupted_host - rejected - repeated
            )
        } else {
            format!("largest twist gap {}", ms(gap))
        },
        pass,
    }
}

/// Encoder stuck while the robot stands, then the robot drives off (rule 2).
fn stuck_at_rest_row(config: &Config) -> Row {
    let mut s = drive(TURN, 0.5);
    s.wheel_faults.push(WheelFault {
        kind: FaultName::StuckEncoder,
        wheel: 2,
        from_us: us(0.02),
        until_us: s.duration_us() + 1,
    });
    let rec = run(&s);
    let min_current = ENCODER_STUCK_MIN_CURRENT * config.limits.max_current;
    // The signature: the stuck wheel is driven hard (its PI sees no speed) while the others
    // turn; the firmware reads that current at the next step.
    let driven = rec.first(us(0.1), |st| st.currents[2].abs() >= min_current);
    let hit = rec.first(us(0.1), |st| st.state == RobotState::Fault);
    let (pass, measured, detail) = match (driven, hit) {
        (Some(d), Some(h)) => {
            let latency = h.t_us - d.t_us;
            (
                h.fault == Fault::EncoderStuck
                    && h.zero_current()
                    && latency <= ENCODER_STUCK_DRAGGED_US + 2 * MS,
                ms(latency),
                format!(
                    "rule 2: {} after the drive-off, {} after RL's current reached {min_current:.0} A",
                    ms(h.t_us - us(0.1)),
                    ms(latency)
                ),
            )
        }
        _ => (false, "-".into(), "no signature or no fault".into()),
    };
    Row {
        fault: "stuck encoder (RL) at rest, then drive off".into(),
        onset: "0.02 s at rest".into(),
        expected: "FAULT (ENCODER_STUCK), zero current".into(),
        budget: format!(
            "≤ {} after it is driven hard",
            ms(ENCODER_STUCK_DRAGGED_US + 2 * MS)
        ),
        measured,
        detail,
        pass,
    }
}

/// Non-finite twists injected for 0.2 s: alongside the host's stream (`base`: the same drive
/// without them; the robot keeps the last valid command, bit for bit), or instead of it
/// (`None`: the watchdog stops the robot).
fn non_finite_row(m: (f64, &str), base: Option<&Record>) -> Row {
    let mut s = at(m.0);
    s.host_faults.push(HostFault {
        kind: FaultName::NonFiniteTwist,
        from_us: us(m.0),
        until_us: us(m.0 + 0.2),
    });
    let Some(base) = base else {
        add_action(
            &mut s,
            Action {
                silence: true,
                ..Action::at(m.0)
            },
        );
        let rec = run(&s);
        let mut row = watchdog_row("non-finite twists only (host stream replaced)", m, &s, &rec);
        let rejected = rec.at(s.duration_us()).rx_errors - rec.at(us(m.0) - MS).rx_errors;
        row.pass &= rejected == 30;
        row.detail = format!("{}; {rejected} of 30 rejected", row.detail);
        return row;
    };
    let rec = run(&s);
    let window = us(m.0)..us(m.0 + 0.2);
    let rejected = rec.at(s.duration_us()).rx_errors - rec.at(window.start - MS).rx_errors;
    // Rejected frames change nothing but the counters: the commanded twist follows the
    // valid stream exactly as without them.
    let same = rec
        .steps
        .iter()
        .zip(&base.steps)
        .all(|(a, b)| a.commanded == b.commanded);
    let last = rec.at(s.duration_us());
    let pass = same
        && rejected == 30
        && rec
            .first(window.start, |st| st.state != RobotState::Enabled)
            .is_none()
        && last.fault == Fault::None;
    Row {
        fault: "non-finite twists (NaN, +inf, -inf) injected, 0.2 s".into(),
        onset: moment(m),
        expected: "ENABLED; all rejected and counted; last valid command kept".into(),
        budget: "-".into(),
        measured: format!("{}, {}", last.state, last.fault),
        detail: format!(
            "{rejected} of 30 rejected; commanded twist {} the run without them",
            if same { "identical to" } else { "DIFFERS from" }
        ),
        pass,
    }
}

fn table(rows: &[Row]) -> String {
    let mut t = String::from(
        "| fault | onset | expected | budget | measured | detail | pass |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        writeln!(
            t,
            "| {} | {} | {} | {} | {} | {} | {} |",
            r.fault,
            r.onset,
            r.expected,
            r.budget,
            r.measured,
            r.detail,
            if r.pass { "yes" } else { "**NO**" }
        )
        .unwrap();
    }
    t
}

// ---------------------------------------------------------------------------------------
// The table in docs/reliability.md

fn doc_path() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/reliability.md")
}

/// Checks (or, with `UPDATE_FAULT_MATRIX` set, rewrites) the block between
/// `<!-- {name}:begin -->` and `<!-- {name}:end -->` in docs/reliability.md. One test at a
/// time reads and writes the file.
fn keep_in_docs(name: &str, block: &str) {
    static DOC: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one_at_a_time = DOC
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let path = doc_path();
    let doc = std::fs::read_to_string(&path).unwrap();
    let (begin, end) = (
        format!("<!-- {name}:begin -->\n"),
        format!("<!-- {name}:end -->"),
    );
    let (Some(b), Some(e)) = (doc.find(&begin), doc.find(&end)) else {
        panic!("{} has no {begin:?} ... {end:?} block", path.display());
    };
    let current = &doc[b + begin.len()..e];
    if current == block {
        return;
    }
    if std::env::var_os("UPDATE_FAULT_MATRIX").is_some() {
        let updated = format!("{}{block}{}", &doc[..b + begin.len()], &doc[e..]);
        std::fs::write(&path, updated).unwrap();
    } else {
        panic!(
            "docs/reliability.md ({name}) is out of date; rerun with UPDATE_FAULT_MATRIX=1 to \
             rewrite it. Now:\n{block}"
        );
    }
}

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

/// The fault matrix's line of the current figures at the top of docs/reliability.md.
fn current_figures(rows: &[Row]) -> String {
    let faults: std::collections::BTreeSet<&str> = rows
        .iter()
        .map(|r| r.fault.split(',').next().unwrap_or(&r.fault))
        .collect();
    let stops = rows
        .iter()
        .filter(|r| r.expected.contains("zero current") || r.expected.contains("zero targets"))
        .count();
    let mut t = String::new();
    writeln!(t, "| fault matrix (the simulator, lockstep) | rows | kinds of fault | rows that must stop the motors | in their specified state within budget |").unwrap();
    writeln!(t, "|---|---|---|---|---|").unwrap();
    writeln!(
        t,
        "| `cargo test -p hostsim --test fault_matrix` | {} | {} | {stops} | {} of {} |",
        rows.len(),
        faults.len(),
        rows.iter().filter(|r| r.pass).count(),
        rows.len()
    )
    .unwrap();
    t
}

// ---------------------------------------------------------------------------------------
// 1,000 random dropouts

/// One dropout of the random campaign.
#[derive(Debug, Clone, Copy)]
struct Dropout {
    enable_s: f64,
    onset_s: f64,
    twist: [f32; 3],
    /// The host goes silent (`false`: its frames are lost on the bus, it keeps sending).
    silence: bool,
}

const DROPOUTS: usize = 1_000;

/// The campaign: per dropout, enable, a random twist (a third pure turns, a third
/// translations, a third both), a random time of driving (5-100 ms: often still
/// accelerating), then the host goes silent or loses its frames on the bus until shortly
/// before the next enable.
fn campaign(seed: u64) -> (Scenario, Vec<Dropout>) {
    let config = Config::dji_m3508_example();
    let mut rng = SplitMix64(seed);
    let mut uniform = |lo: f64, hi: f64| lo + (hi - lo) * rng.unit();
    let mut s = drive(TURN, 1.0);
    s.actions.clear();
    let mut drops = Vec::with_capacity(DROPOUTS);
    let mut t = 0.02;
    for i in 0..DROPOUTS {
        let kind = uniform(0.0, 3.0);
        let (vx, vy) = if kind < 1.0 {
            (0.0, 0.0)
        } else {
            (uniform(-1.0, 1.0), uniform(-0.7, 0.7))
        };
        let wz = if kind >= 2.0 { 0.0 } else { uniform(-2.5, 2.5) };
        let twist = [vx as f32, vy as f32, wz as f32];
        let onset = t + 0.002 + uniform(0.005, 0.1);
        let silence = i % 2 == 0;
        let stop = stop_budget_us(&config, ChassisVelocity::new(twist[0], twist[1], twist[2]));
        let next = onset + stop as f64 * 1e-6 + 0.035;
        s.actions.push(Action {
            enable: true,
            ..Action::at(t)
        });
        s.actions
            .push(Action::twist(t + 0.002, twist[0], twist[1], twist[2]));
        if silence {
            s.actions.push(Action {
                silence: true,
                ..Action::at(onset)
            });
        } else {
            // Lost on the bus until 22 ms before the next enable: the twist (at least one
            // at 50 Hz) that then arrives finds the robot stopped and must not move it.
            bus_fault(
                &mut s,
                FaultKind::Burst,
                onset,
                next - 0.022 - onset,
                Node::Host,
            );
        }
        drops.push(Dropout {
            enable_s: t,
            onset_s: onset,
            twist,
            silence,
        });
        t = next;
    }
    s.duration_s = t;
    (s, drops)
}

#[derive(Debug, Default)]
struct Stats {
    n: usize,
    min: u64,
    max: u64,
    sum: u64,
}

impl Stats {
    fn add(&mut self, x: u64) {
        self.min = if self.n == 0 { x } else { self.min.min(x) };
        self.max = self.max.max(x);
        self.sum += x;
        self.n += 1;
    }

    fn line(&self) -> String {
        let ms = |us: u64| format!("{:.3}", us as f64 / 1000.0);
        format!(
            "{} / {} / {} ms",
            ms(self.min),
            ms(self.sum / self.n.max(1) as u64),
            ms(self.max)
        )
    }
}

#[test]
fn the_watchdog_stops_every_one_of_1000_random_dropouts() {
    let (s, drops) = campaign(0x5EED_D20F);
    let wall = std::time::Instant::now();
    let rec = run(&s);
    let wall_s = wall.elapsed().as_secs_f64();
    let (mut zero, mut detect, mut margin) = (Stats::default(), Stats::default(), Stats::default());
    let mut turns = 0;
    let mut failures = Vec::new();
    for (i, d) in drops.iter().enumerate() {
        let enable_us = us(d.enable_s);
        let next_us = drops.get(i + 1).map_or(s.duration_us(), |n| us(n.enable_s));
        // Driving before the dropout.
        let moving = rec.at(us(d.onset_s)).commanded != ChassisVelocity::default();
        let enabled = rec
            .first(enable_us, |s| s.state == RobotState::Enabled)
            .is_some_and(|s| s.t_us < us(d.onset_s));
        let result = if moving && enabled {
            check_watchdog_stop(&s.config, &rec, us(d.onset_s), next_us).and_then(|r| {
                // After a lost-frames burst, twists arrive at the stopped robot (and the
                // check above found it still stopped).
                let stopped_at = rec.last_twist(us(d.onset_s)).unwrap_or(0) + r.0;
                let late = rec.twists.iter().any(|&t| t > stopped_at && t < next_us);
                if d.silence || late {
                    Ok(r)
                } else {
                    Err("no twist reached the stopped robot".to_string())
                }
            })
        } else {
            Err("not enabled and moving at the onset".to_string())
        };
        match result {
            Ok((latency, budget, detection)) => {
                zero.add(latency);
                detect.add(detection);
                margin.add(budget - latency);
                turns += usize::from(d.twist[2] != 0.0);
            }
            Err(e) => failures.push((i, *d, e)),
        }
    }
    assert!(
        failures.is_empty(),
        "{} failed: {:#?}",
        failures.len(),
        &failures[..failures.len().min(5)]
    );
    let silent = drops.iter().filter(|d| d.silence).count();
    let mut t = String::new();
    writeln!(t, "| dropouts | with a turn | host silent / frames lost | simulated | zero current after the last twist (min / mean / max) | watchdog after the last twist (min / mean / max) | budget left (min / mean / max) | failed |").unwrap();
    writeln!(t, "|---|---|---|---|---|---|---|---|").unwrap();
    writeln!(
        t,
        "| {} | {turns} | {silent} / {} | {:.0} s | {} | {} | {} | 0 |",
        drops.len(),
        drops.len() - silent,
        s.duration_s,
        zero.line(),
        detect.line(),
        margin.line()
    )
    .unwrap();
    println!("{t}\n({:.1} s simulated in {wall_s:.1} s)", s.duration_s);
    keep_in_docs("watchdog-dropouts", &t);
}
