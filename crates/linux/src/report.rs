//! What a run reports: counts, the step-start lateness histogram, the link's gaps, and the
//! [`LoopReport`] the runner and `hostsim plant` print and write as JSON.

use core::fmt;
use std::io;

use serde::Serialize;

use firmware::protocol::RxErrorCounters;

use crate::bus::ErrorKind;

/// Errors counted by [`ErrorKind`].
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ErrorCounts {
    /// Busy: for sends, frames still refused as busy when their retries ran out.
    pub busy: u64,
    /// Link down (`ENETDOWN`).
    pub link_down: u64,
    /// Device gone (`ENODEV`, `ENXIO`).
    pub no_device: u64,
    /// Anything else.
    pub other: u64,
}

impl ErrorCounts {
    pub(crate) fn count(&mut self, kind: ErrorKind) {
        let n = match kind {
            ErrorKind::Busy => &mut self.busy,
            ErrorKind::LinkDown => &mut self.link_down,
            ErrorKind::NoDevice => &mut self.no_device,
            ErrorKind::Other => &mut self.other,
        };
        *n += 1;
    }
}

impl fmt::Display for ErrorCounts {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "busy {}, link down {}, no device {}, other {}",
            self.busy, self.link_down, self.no_device, self.other
        )
    }
}

/// Link losses and recoveries over a run (see [The link](crate::run_recorded#the-link)).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct LinkReport {
    /// Times the link was lost.
    pub losses: u64,
    /// Times it came back ([`Bus::reopen`](crate::Bus::reopen) succeeded).
    pub recoveries: u64,
    /// Calls of [`Bus::reopen`](crate::Bus::reopen).
    pub reopen_attempts: u64,
    /// Time the link was down in total (a loss not recovered counts up to the stop), µs.
    pub down_us: u64,
    /// The longest single gap, µs.
    pub longest_down_us: u64,
    /// Frames of the core not sent because the link was down.
    pub frames_not_sent: u64,
    /// Whether the link was down when the loop stopped.
    pub down_at_stop: bool,
}

/// Why [`run`](crate::run) stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// The stop flag was set to this value (the binary stores the signal number).
    Signal(usize),
    /// [`RunOptions::duration_us`](crate::RunOptions::duration_us) elapsed.
    Duration,
    /// The link was lost and [`RunOptions::exit_on_link_loss`](crate::RunOptions::exit_on_link_loss) is set; the error is
    /// [`Report::link_error`].
    LinkLost,
}

impl fmt::Display for StopReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::Signal(2) => f.write_str("SIGINT"),
            Self::Signal(15) => f.write_str("SIGTERM"),
            Self::Signal(n) => write!(f, "stop flag {n}"),
            Self::Duration => f.write_str("duration elapsed"),
            Self::LinkLost => f.write_str("link lost (exit on link loss)"),
        }
    }
}

/// A histogram of non-negative durations in microseconds with a fixed memory footprint
/// (about 200 KiB) whatever the number of samples.
///
/// Values below 2048 µs have a bucket each (exact); above, each power-of-two range is split
/// into 1024 buckets, so a reported value is within 0.1 % of the true one (and never below
/// it). Values above 2³² µs (71 minutes) are clamped.
#[derive(Clone)]
pub struct LatencyHistogram {
    buckets: Vec<u64>,
    count: u64,
    sum: u128,
    max: u64,
}

/// Values with one bucket each: `0..EXACT`.
const EXACT: u64 = 2048;
/// Sub-buckets per power of two above [`EXACT`].
const SUB: u64 = 1024;
/// Largest value recorded; larger ones are clamped to it.
const CLAMP: u64 = 1 << 32;

impl LatencyHistogram {
    /// An empty histogram.
    #[must_use]
    pub fn new() -> Self {
        let len = usize::try_from(Self::index(CLAMP) + 1).unwrap_or(0);
        Self {
            buckets: vec![0; len],
            count: 0,
            sum: 0,
            max: 0,
        }
    }

    /// Bucket of a value: `SUB · s + (v >> s)` with `s` the number of bits above 11.
    fn index(value: u64) -> u64 {
        let bits = u64::from(u64::BITS - value.leading_zeros());
        let shift = bits.saturating_sub(u64::from(EXACT.trailing_zeros()));
        SUB * shift + (value >> shift)
    }

    /// The largest value that falls into bucket `index`.
    fn upper(index: u64) -> u64 {
        if index < EXACT {
            return index;
        }
        let shift = index / SUB - 1;
        let mantissa = index - SUB * shift;
        ((mantissa + 1) << shift) - 1
    }

    /// Records one value.
    pub fn record(&mut self, us: u64) {
        let us = us.min(CLAMP);
        let i = usize::try_from(Self::index(us)).unwrap_or(usize::MAX);
        if let Some(b) = self.buckets.get_mut(i) {
            *b += 1;
        }
        self.count += 1;
        self.sum += u128::from(us);
        self.max = self.max.max(us);
    }

    /// Number of values recorded.
    #[must_use]
    pub const fn count(&self) -> u64 {
        self.count
    }

    /// Largest value recorded (exact); `None` when empty.
    #[must_use]
    pub fn max(&self) -> Option<u64> {
        (self.count > 0).then_some(self.max)
    }

    /// Mean of the values recorded (exact); `None` when empty.
    #[must_use]
    pub fn mean(&self) -> Option<f64> {
        (self.count > 0).then(|| self.sum as f64 / self.count as f64)
    }

    /// The `q`-quantile (`0 < q <= 1`; 0.99 for p99) by the nearest-rank method: the smallest
    /// recorded value `v` such that at least `ceil(q · count)` values are `<= v`. Exact below
    /// 2048 µs. `None` when empty.
    #[must_use]
    pub fn quantile(&self, q: f64) -> Option<u64> {
        if self.count == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for (i, &n) in self.buckets.iter().enumerate() {
            seen += n;
            if seen >= rank {
                return Some(Self::upper(i as u64).min(self.max));
            }
        }
        Some(self.max)
    }

    /// p50, p99, max and mean.
    #[must_use]
    pub fn summary(&self) -> LatencySummary {
        LatencySummary {
            samples: self.count,
            p50_us: self.quantile(0.50),
            p99_us: self.quantile(0.99),
            max_us: self.max(),
            mean_us: self.mean(),
        }
    }
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl fmt::Debug for LatencyHistogram {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("LatencyHistogram")
            .field("summary", &self.summary())
            .finish()
    }
}

/// Percentiles of a [`LatencyHistogram`], µs; `None` fields when nothing was recorded.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LatencySummary {
    /// Number of values.
    pub samples: u64,
    /// Median.
    pub p50_us: Option<u64>,
    /// 99th percentile.
    pub p99_us: Option<u64>,
    /// Maximum.
    pub max_us: Option<u64>,
    /// Mean.
    pub mean_us: Option<f64>,
}

impl fmt::Display for LatencySummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (self.p50_us, self.p99_us, self.max_us, self.mean_us) {
            (Some(p50), Some(p99), Some(max), Some(mean)) => write!(
                f,
                "p50 {p50} µs, p99 {p99} µs, max {max} µs, mean {mean:.1} µs ({} samples)",
                self.samples
            ),
            _ => f.write_str("no samples"),
        }
    }
}

/// The controller as the loop left it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ControllerReport {
    /// State when the loop stopped, before the shutdown (`Disabled`, `Enabled`, `Fault`,
    /// `Estop`).
    pub state_at_stop: &'static str,
    /// Fault (or last watchdog stop reason) when the loop stopped.
    pub fault_at_stop: &'static str,
    /// State after [`Controller::shutdown`](firmware::Controller::shutdown).
    pub state_after_shutdown: &'static str,
    /// Steps the controller ran.
    pub steps: u64,
    /// Bit i set when wheel i's motor had reported (FL, FR, RL, RR).
    pub motors_online: u8,
    /// Frames the controller rejected, by kind.
    pub rx_errors: RxErrorCounters,
    /// `TWIST_CMD`s not applied because their `seq` repeated the last accepted one's
    /// ([`Snapshot::repeated_seq`](firmware::control::Snapshot::repeated_seq)).
    pub repeated_seq: u32,
    /// CiA 402 drives: what the bus said of the latest drive fault
    /// ([`Controller::drive_issue`](firmware::Controller::drive_issue)), `node 2: SDO abort
    /// 0x06090011 on 0x6060:00 (...)`; `None` for other drives and without one.
    pub drive_issue: Option<String>,
    /// CiA 402 drives: EMCY frames received.
    pub drive_emcy: u32,
}

/// The shutdown frames and how many went out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ShutdownReport {
    /// Frames [`Controller::shutdown`](firmware::Controller::shutdown) returned.
    pub frames: usize,
    /// Frames sent.
    pub sent: usize,
    /// Frames that could not be sent within [`RunOptions::shutdown_budget_us`](crate::RunOptions::shutdown_budget_us).
    pub failed: usize,
}

/// What the fixed-rate loop ([`run_node`](crate::run_node)) did, with the node's own figures
/// in [`Self::node`]. Serialises to the JSON of `--stats-json`, the node's figures flattened
/// in; [`Display`](fmt::Display) is the summary the binaries print on exit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopReport<F> {
    /// Why the loop stopped.
    pub stop: StopReason,
    /// The loop's period, µs.
    pub period_us: u64,
    /// From the first deadline to the end of the shutdown, µs.
    pub elapsed_us: u64,
    /// Periods run (steps of the node).
    pub steps: u64,
    /// Steps that started more than one period late (the schedule was re-anchored).
    pub overruns: u64,
    /// Frames read from the bus and passed to the node.
    pub frames_received: u64,
    /// Receive errors (reading the bus failed); the drain stops for that step.
    pub rx_errors: u64,
    /// Error frames of the CAN controller ([`BusErrorFrame`](crate::BusErrorFrame): bus errors, error-passive,
    /// bus-off, restarts, missing ACKs...); the drain goes on after each.
    pub bus_error_frames: u64,
    /// Steps that left frames on the bus because [`RunOptions::max_rx_per_step`](crate::RunOptions::max_rx_per_step) was reached.
    pub rx_capped_steps: u64,
    /// Frames sent by the loop (not counting the shutdown frames).
    pub frames_sent: u64,
    /// Send attempts repeated because the bus was busy (`ENOBUFS`, `EAGAIN`).
    pub send_retries: u64,
    /// Frames the loop could not send (dropped) because sending failed; frames not tried
    /// while the link was down are [`LinkReport::frames_not_sent`].
    pub send_errors: u64,
    /// [`Self::send_errors`] (and the failed shutdown frames) by kind.
    pub send_errors_by_kind: ErrorCounts,
    /// [`Self::rx_errors`] by kind.
    pub rx_errors_by_kind: ErrorCounts,
    /// Link losses, gaps and recoveries.
    pub link: LinkReport,
    /// The error that caused the last link loss (`receive: Network is down (os error
    /// 100)`), if the link was lost.
    pub link_error: Option<String>,
    /// The first and the last bus error, with the frame id (`first_error`, `last_error`).
    #[serde(flatten)]
    pub errors: ErrorLog,
    /// Lateness of each step start after its deadline, µs.
    pub jitter: LatencySummary,
    /// Time from a step's start to its last frame sent, µs.
    pub step_time: LatencySummary,
    /// The node's own figures: its lines of the summary, its keys of the JSON.
    #[serde(flatten)]
    pub node: F,
}

/// What [`run`](crate::run) did: the loop's figures and the core's.
pub type Report = LoopReport<CoreFigures>;

/// The control core's figures in a [`Report`]: the shutdown and the controller.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CoreFigures {
    /// The shutdown frames.
    pub shutdown: ShutdownReport,
    /// The controller.
    pub controller: ControllerReport,
}

impl<F: fmt::Display> fmt::Display for LoopReport<F> {
    /// The loop's lines, then the node's.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "stopped: {} after {:.3} s; {} steps of {} µs, {} overruns",
            self.stop,
            self.elapsed_us as f64 / 1e6,
            self.steps,
            self.period_us,
            self.overruns
        )?;
        writeln!(f, "jitter (step start - deadline): {}", self.jitter)?;
        writeln!(f, "step time (start - last frame sent): {}", self.step_time)?;
        writeln!(
            f,
            "bus: {} frames received, {} sent, {} send retries, {} send errors, {} receive errors, {} bus error frames, {} capped drains",
            self.frames_received,
            self.frames_sent,
            self.send_retries,
            self.send_errors,
            self.rx_errors,
            self.bus_error_frames,
            self.rx_capped_steps
        )?;
        if self.send_errors_by_kind != ErrorCounts::default()
            || self.rx_errors_by_kind != ErrorCounts::default()
        {
            writeln!(
                f,
                "send errors: {}; receive errors: {}",
                self.send_errors_by_kind, self.rx_errors_by_kind
            )?;
        }
        let l = &self.link;
        if l.losses > 0 {
            writeln!(
                f,
                "link: lost {} time(s), back {} time(s){}; down {:.3} s in total, longest {:.3} s; {} reopen attempts; {} frames not sent while down",
                l.losses,
                l.recoveries,
                if l.down_at_stop { ", DOWN at stop" } else { "" },
                l.down_us as f64 / 1e6,
                l.longest_down_us as f64 / 1e6,
                l.reopen_attempts,
                l.frames_not_sent
            )?;
        }
        self.errors.write_lines(f)?;
        write!(f, "{}", self.node)
    }
}

impl fmt::Display for CoreFigures {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = &self.controller;
        let e = &c.rx_errors;
        writeln!(
            f,
            "controller: {} (fault {}) at stop, {} after shutdown; {} steps; motors online {:04b} (bit 0 = FL)",
            c.state_at_stop, c.fault_at_stop, c.state_after_shutdown, c.steps, c.motors_online
        )?;
        writeln!(
            f,
            "rejected frames: unknown_id {}, extended_id {}, remote {}, wrong_dlc {}, non_finite {}, out_of_range {}",
            e.unknown_id, e.extended_id, e.remote, e.wrong_dlc, e.non_finite, e.out_of_range
        )?;
        writeln!(
            f,
            "repeated twists (seq of the last accepted one): {}",
            c.repeated_seq
        )?;
        if let Some(issue) = &c.drive_issue {
            writeln!(f, "drive: {issue}; {} EMCY received", c.drive_emcy)?;
        }
        write!(
            f,
            "shutdown: {} of {} frames sent",
            self.shutdown.sent, self.shutdown.frames
        )?;
        if self.shutdown.failed > 0 {
            write!(f, " ({} NOT sent)", self.shutdown.failed)?;
        }
        Ok(())
    }
}

/// The first and the last I/O error of a loop, as log lines (`send 0x200: No buffer space
/// available`): what a report shows, in constant memory however many errors there were.
/// In a report's JSON, `first_error` and `last_error`.
#[derive(Debug, Default, Clone, PartialEq, Eq, serde::Serialize)]
pub struct ErrorLog {
    /// The first error.
    #[serde(rename = "first_error")]
    pub first: Option<String>,
    /// The last error.
    #[serde(rename = "last_error")]
    pub last: Option<String>,
}

impl ErrorLog {
    /// Records `what: error`.
    pub fn record(&mut self, what: fmt::Arguments<'_>, error: &io::Error) {
        let message = format!("{what}: {error}");
        if self.first.is_none() {
            self.first = Some(message.clone());
        }
        self.last = Some(message);
    }

    /// A report's lines of them, `first bus error: ...` and `last bus error: ...`, each ended
    /// by a newline (nothing without errors).
    ///
    /// # Errors
    /// The formatter's.
    pub fn write_lines(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (which, e) in [("first", &self.first), ("last", &self.last)] {
            if let Some(e) = e {
                writeln!(f, "{which} bus error: {e}")?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_a_known_sample() {
        let mut h = LatencyHistogram::new();
        assert_eq!(h.summary().p50_us, None);
        // 1..=100 in reverse order: nearest rank p50 = 50, p99 = 99.
        for v in (1..=100).rev() {
            h.record(v);
        }
        let s = h.summary();
        assert_eq!(
            (s.p50_us, s.p99_us, s.max_us),
            (Some(50), Some(99), Some(100))
        );
        assert_eq!(s.mean_us, Some(50.5));
        assert_eq!(h.quantile(1.0), Some(100));
        assert_eq!(h.quantile(0.0), Some(1));
        // 99 zeros and one outlier: p99 stays 0, max shows it.
        let mut h = LatencyHistogram::new();
        for _ in 0..99 {
            h.record(0);
        }
        h.record(5000);
        let s = h.summary();
        assert_eq!(
            (s.p50_us, s.p99_us, s.max_us),
            (Some(0), Some(0), Some(5000))
        );
    }

    #[test]
    fn histogram_buckets_are_exact_low_and_tight_high() {
        // Exact below 2048.
        for v in [0, 1, 1023, 1024, 2047] {
            assert_eq!(LatencyHistogram::upper(LatencyHistogram::index(v)), v);
        }
        // Above: contiguous, monotonic, upper bound >= value and within 0.1 %.
        let mut last = 0;
        for v in (2048..200_000).step_by(7).chain([CLAMP - 1, CLAMP]) {
            let i = LatencyHistogram::index(v);
            assert!(i >= last);
            last = i;
            let up = LatencyHistogram::upper(i);
            assert!(up >= v && (up - v) as f64 <= v as f64 * 1e-3, "{v} -> {up}");
            // The bucket below ends below v.
            assert!(LatencyHistogram::upper(i - 1) < v);
        }
        let mut h = LatencyHistogram::new();
        for v in [3000, 3001, 3002, 1 << 40] {
            h.record(v);
        }
        assert_eq!(h.quantile(0.5), Some(3001));
        assert_eq!(h.max(), Some(CLAMP));
    }
}
