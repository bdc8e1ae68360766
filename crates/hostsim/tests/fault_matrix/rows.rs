//! The rows of the matrix and how each is judged: a watchdog stop, the stale-feedback rule,
//! a fault state within its budget, a host fault ridden through, and the special cases.

use firmware::Config;
use firmware::control::{ENCODER_STUCK_DRAGGED_US, ENCODER_STUCK_MIN_CURRENT, Fault};
use firmware::protocol::robot::RobotState;
use hostsim::bus::FaultKind;
use hostsim::nodes::host::{HostFault, HostFaultKind};
use hostsim::scenario::{FaultName, Scenario, WheelFault};
use kinematics::ChassisVelocity;

use super::MS;
use super::drive::{TAIL_S, TURN, at, drive, silenced, us};
use super::record::{Record, Step, run};

/// One row of the matrix.
pub(super) struct Row {
    pub(super) fault: String,
    pub(super) onset: String,
    pub(super) expected: String,
    pub(super) budget: String,
    pub(super) measured: String,
    pub(super) detail: String,
    pub(super) pass: bool,
}

pub(super) fn ms(us: u64) -> String {
    format!("{:.2} ms", us as f64 / 1000.0)
}

/// The watchdog stop budget: timeout, then the ramp from `commanded` at the stop
/// decelerations, within two control periods.
pub(super) fn stop_budget_us(config: &Config, commanded: ChassisVelocity<f32>) -> u64 {
    let l = &config.limits;
    let ramp_s = (commanded.vx.hypot(commanded.vy) / l.stop_linear_decel)
        .max(commanded.wz.abs() / l.stop_angular_decel);
    u64::from(config.timing.command_timeout_ms) * MS
        + (f64::from(ramp_s) * 1e6).ceil() as u64
        + 2 * MS
}

/// A watchdog stop after `onset_us`: detection, zero current, and the latch afterwards until
/// `until_us`. Returns (zero latency from the last accepted twist, budget, detection latency).
pub(super) fn check_watchdog_stop(
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

pub(super) fn watchdog_row(fault: &str, onset: (f64, &str), s: &Scenario, rec: &Record) -> Row {
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

pub(super) fn moment((t, name): (f64, &str)) -> String {
    format!("{t:.2} s {name}")
}

/// A row whose outcome follows the firmware's stale rule: MotorStale at the first step where
/// a motor's feedback gap exceeds the limit, Enabled otherwise. `budget_from_onset` bounds
/// the fault's latency where a fault is certain.
pub(super) fn stale_rule_row(
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

pub(super) fn state_row(
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

/// The host stops incrementing `seq` and repeats its last twist frame unchanged at 50 Hz
/// from the onset to the end: the watchdog stops the robot as if the host were silent, and
/// every repeat is counted (those after the stop too).
pub(super) fn repeated_twist_row(m: (f64, &str)) -> Row {
    let mut s = at(m.0);
    let onset_us = us(m.0);
    let end_us = s.duration_us();
    s.host_faults.push(HostFault {
        kind: HostFaultKind::RepeatedTwist,
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
pub(super) fn host_tolerated_row(fault: &str, onset: (f64, &str), s: &Scenario) -> Row {
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
pub(super) fn stuck_at_rest_row(config: &Config) -> Row {
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
pub(super) fn non_finite_row(m: (f64, &str), base: Option<&Record>) -> Row {
    let mut s = at(m.0);
    s.host_faults.push(HostFault {
        kind: HostFaultKind::NonFiniteTwist,
        from_us: us(m.0),
        until_us: us(m.0 + 0.2),
    });
    let Some(base) = base else {
        let s = silenced(s, m.0);
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
