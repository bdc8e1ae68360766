//! The Linux edge of the mecanum drive: the control core at a fixed rate on a SocketCAN
//! interface.
//!
//! # What a runner does
//!
//! The [`Controller`] is a pure state machine: it reads no clock and does no I/O. A runner
//! owns both. [`run`] is the runner's whole loop, written against two small traits so that it
//! can be tested without a CAN interface or real time:
//!
//! - a [`Bus`]: non-blocking receive, send; [`SocketCanBus`] is the SocketCAN one;
//! - a [`Clock`]: microseconds since an arbitrary epoch and "sleep until";
//!   [`MonotonicClock`] is `CLOCK_MONOTONIC` (through [`std::time::Instant`]).
//!
//! The `mecanum-runner` binary is [`SocketCanBus`] + [`MonotonicClock`] + [`run_recorded`] +
//! a command line, signal handling and its log (a [`Recorder`]).
//!
//! # Recording
//!
//! [`run_recorded`] tells a [`Recorder`] what the loop did, from the loop's thread, with the
//! times the core saw (µs since the first step's clock reading): each frame passed to
//! [`Controller::on_frame`], each step (before its frames go out), each frame the step
//! produced with the time it was handed to the bus (or given up), and the shutdown. The
//! shutdown is stamped at least 1 µs after the last step, so that its frames never share a
//! time with that step's. A recorder must only push small values: the loop waits for it.
//!
//! # Scheduling
//!
//! Steps are due at absolute deadlines `start + k · period` (`period` from
//! [`Controller::period_micros`]). A deadline is never computed from the previous wake-up,
//! so lateness does not accumulate (no drift). For each step the loop:
//!
//! 1. sleeps until the deadline, then reads the clock once: `now`;
//! 2. records the lateness `now - deadline` (see *Jitter*); when it exceeds one period the
//!    step counts as an **overrun** and the schedule is re-anchored at `now`
//!    (`start := now, k := 0`) instead of running a burst of catch-up steps;
//! 3. drains every frame waiting on the bus (non-blocking reads, at most
//!    [`RunOptions::max_rx_per_step`]) into [`Controller::on_frame`], all stamped `now`;
//! 4. runs [`Controller::step`] at `now` and sends its frames in order.
//!
//! `now` is passed to the core as microseconds since the first step's clock reading, so the
//! core's [`Instant`] starts near zero.
//!
//! # Sending
//!
//! A full transmit queue is normal on a busy bus: SocketCAN reports it as `ENOBUFS` (the
//! interface queue is full) or `EAGAIN` (the socket buffer is full, non-blocking socket).
//! Those are retried every [`RunOptions::retry_backoff_us`] until half a period after the
//! step's deadline; a frame still not sent then is dropped and counted in
//! [`Report::send_errors`]. Any other error (interface down, ...) is counted at once. Nothing
//! on the bus ever stops the loop.
//!
//! # The link
//!
//! On a robot the interface itself fails: a USB adapter is unplugged, a cable breaks, the
//! link is set down. SocketCAN then reports `ENETDOWN` (the link is down: every send, and
//! one receive) or `ENODEV`/`ENXIO` (the device is gone: the socket stays dead even when a
//! device of the same name comes back). Either is a **link loss** ([`classify`]). The loop
//! keeps stepping the core at its rate, so the watchdog and the state machine see the silence
//! as it is (no motor feedback: the core faults and stays faulted until a reset and a new
//! enable, as for any other loss of its motors); it stops reading and sending, counts the
//! frames it did not send ([`LinkReport::frames_not_sent`]) and tries [`Bus::reopen`] with an
//! exponential back-off ([`RunOptions::link_retry_min_us`] doubling up to
//! [`RunOptions::link_retry_max_us`]). The first reopen that succeeds resumes reading and
//! sending; the gap is in [`Report::link`] and told to the [`Recorder`] ([`LinkEvent`]) as
//! it happens. With [`RunOptions::exit_on_link_loss`] the loop stops instead
//! ([`StopReason::LinkLost`]). Errors are counted by kind ([`ErrorCounts`]) for sends and
//! receives.
//!
//! # Stopping
//!
//! The loop stops when the `stop` flag becomes non-zero (the binary stores the signal number
//! from SIGINT/SIGTERM there) or when [`RunOptions::duration_us`] has elapsed. It then sends
//! [`Controller::shutdown`]'s frames (zero current for DJI ESCs; zero velocity and the idle
//! state for ODrive axes), retrying busy errors for up to
//! [`RunOptions::shutdown_budget_us`], and returns a [`Report`].
//!
//! # Jitter
//!
//! Jitter is measured as the **lateness of each step's start**: the clock reading after the
//! sleep minus the step's deadline (never negative: a sleep never ends early). It is recorded
//! in a fixed-size [`LatencyHistogram`] (exact below 2048 µs, within 0.1 % above), so a run
//! of any length uses the same memory; [`Report::jitter`] has its p50, p99 and maximum. The
//! time from wake-up to the last frame sent is recorded the same way
//! ([`Report::step_time`]).

use core::fmt;
use core::sync::atomic::{AtomicUsize, Ordering};
use std::io;
use std::path::PathBuf;
use std::time::Duration;

use embedded_can::Frame as _;
use serde::Serialize;

use firmware::CanFrame;
use firmware::control::{Controller, Instant, Snapshot};
use firmware::protocol::RxErrorCounters;

/// A CAN bus as the runner needs it: a non-blocking receive and a send.
pub trait Bus {
    /// The next received frame, `Ok(None)` when none is waiting. Must not block.
    ///
    /// # Errors
    /// Whatever the bus reports; the runner counts it and stops draining for this step.
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>>;

    /// Queues one frame for sending. Should not block for long; a full queue is reported as
    /// an error that [`is_busy`] recognises, and the runner retries it.
    ///
    /// # Errors
    /// Whatever the bus reports.
    fn send(&mut self, frame: &CanFrame) -> io::Result<()>;

    /// Makes the bus usable again after a link loss ([`ErrorKind::LinkDown`],
    /// [`ErrorKind::NoDevice`]): for SocketCAN, opens a new socket on the interface once it
    /// exists and is up. Called by the runner with a back-off while the link is down, from
    /// the loop's thread, so it must not block. The default does nothing and succeeds (a bus
    /// that recovers by itself).
    ///
    /// # Errors
    /// The bus is still unusable; the runner tries again later.
    fn reopen(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// A monotonic clock in microseconds that can sleep.
pub trait Clock {
    /// Microseconds since an arbitrary, fixed epoch; never decreases.
    fn now_micros(&self) -> u64;

    /// Returns when [`now_micros`](Self::now_micros) is at least `deadline_us` (at once if it
    /// already is).
    fn sleep_until(&self, deadline_us: u64);
}

/// `CLOCK_MONOTONIC` through [`std::time::Instant`], with an optional busy-wait before each
/// deadline.
///
/// A plain sleep wakes up late by the kernel's timer slack (50 µs by default for normal
/// threads) plus the scheduling latency. With `spin_us > 0` the clock sleeps until
/// `spin_us` before the deadline and spins for the rest, which trades CPU time for a lower
/// lateness.
#[derive(Debug, Clone, Copy)]
pub struct MonotonicClock {
    epoch: std::time::Instant,
    spin_us: u64,
}

impl MonotonicClock {
    /// A clock whose epoch is now; `spin_us` as in the type's documentation (0: no spinning).
    #[must_use]
    pub fn new(spin_us: u64) -> Self {
        Self {
            epoch: std::time::Instant::now(),
            spin_us,
        }
    }
}

impl Clock for MonotonicClock {
    fn now_micros(&self) -> u64 {
        u64::try_from(self.epoch.elapsed().as_micros()).unwrap_or(u64::MAX)
    }

    fn sleep_until(&self, deadline_us: u64) {
        // `now_micros` rounds down, so sleeping `deadline - now` never wakes up early.
        let remaining = deadline_us.saturating_sub(self.now_micros());
        if remaining > self.spin_us {
            std::thread::sleep(Duration::from_micros(remaining - self.spin_us));
        }
        while self.now_micros() < deadline_us {
            core::hint::spin_loop();
        }
    }
}

/// Whether a send error means "the transmit queue is full, try again shortly": `ENOBUFS`
/// (interface queue full) or `EAGAIN`/`EWOULDBLOCK` (socket buffer full).
#[must_use]
pub fn is_busy(error: &io::Error) -> bool {
    error.kind() == io::ErrorKind::WouldBlock || error.raw_os_error() == Some(libc::ENOBUFS)
}

/// What an I/O error of the bus means to the runner, for the counters ([`ErrorCounts`]) and
/// the link handling (see [The link](self#the-link)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// The transmit queue is full ([`is_busy`]): retried.
    Busy,
    /// The link is down (`ENETDOWN`): a link loss.
    LinkDown,
    /// The device is gone (`ENODEV`, `ENXIO`: unplugged, or removed): a link loss; the bus
    /// must be reopened.
    NoDevice,
    /// Anything else.
    Other,
}

/// Classifies a bus error (see [`ErrorKind`]).
#[must_use]
pub fn classify(error: &io::Error) -> ErrorKind {
    if is_busy(error) {
        return ErrorKind::Busy;
    }
    match error.raw_os_error() {
        Some(libc::ENETDOWN) => ErrorKind::LinkDown,
        Some(libc::ENODEV | libc::ENXIO) => ErrorKind::NoDevice,
        _ => ErrorKind::Other,
    }
}

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
    fn count(&mut self, kind: ErrorKind) {
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

/// Link losses and recoveries over a run (see [The link](self#the-link)).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct LinkReport {
    /// Times the link was lost.
    pub losses: u64,
    /// Times it came back ([`Bus::reopen`] succeeded).
    pub recoveries: u64,
    /// Calls of [`Bus::reopen`].
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

/// A change of the link, as [`run_recorded`] tells its [`Recorder`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkEvent<'a> {
    /// The link was lost; `error` is what the bus said (`send 0x200: Network is down (os
    /// error 100)`).
    Lost {
        /// The error, with what was being done.
        error: &'a str,
    },
    /// [`Bus::reopen`] succeeded after the link had been down for `down_us`, at its
    /// `attempts`-th try since the loss.
    Restored {
        /// How long the link was down, µs.
        down_us: u64,
        /// Reopen attempts since the loss.
        attempts: u64,
    },
}

/// Tuning of [`run`]. [`Default`] is what the binary uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RunOptions {
    /// Stop on the first deadline at least this long after the start; `None`: run until the
    /// stop flag is set.
    pub duration_us: Option<u64>,
    /// Most frames passed to the controller before one step; the rest wait for the next step
    /// (a flooded bus cannot starve the loop). Default 1024.
    pub max_rx_per_step: usize,
    /// Pause between two attempts to send a frame the bus reported busy. Default 20 µs.
    pub retry_backoff_us: u64,
    /// How long the shutdown frames may be retried in total. Default 100 ms.
    pub shutdown_budget_us: u64,
    /// First pause before [`Bus::reopen`] after a link loss; it doubles after each failed
    /// attempt. Default 10 ms.
    pub link_retry_min_us: u64,
    /// Longest pause between two [`Bus::reopen`] attempts: a link that comes back is in use
    /// again at most this long after. Default 200 ms.
    pub link_retry_max_us: u64,
    /// Stop the loop on a link loss ([`StopReason::LinkLost`]) instead of waiting for the
    /// link to come back. Default `false`.
    pub exit_on_link_loss: bool,
}

impl Default for RunOptions {
    fn default() -> Self {
        Self {
            duration_us: None,
            max_rx_per_step: 1024,
            retry_backoff_us: 20,
            shutdown_budget_us: 100_000,
            link_retry_min_us: 10_000,
            link_retry_max_us: 200_000,
            exit_on_link_loss: false,
        }
    }
}

/// Why [`run`] stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// The stop flag was set to this value (the binary stores the signal number).
    Signal(usize),
    /// [`RunOptions::duration_us`] elapsed.
    Duration,
    /// The link was lost and [`RunOptions::exit_on_link_loss`] is set; the error is
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
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ControllerReport {
    /// State when the loop stopped, before the shutdown (`Disabled`, `Enabled`, `Fault`,
    /// `Estop`).
    pub state_at_stop: &'static str,
    /// Fault (or last watchdog stop reason) when the loop stopped.
    pub fault_at_stop: &'static str,
    /// State after [`Controller::shutdown`].
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
}

/// The shutdown frames and how many went out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ShutdownReport {
    /// Frames [`Controller::shutdown`] returned.
    pub frames: usize,
    /// Frames sent.
    pub sent: usize,
    /// Frames that could not be sent within [`RunOptions::shutdown_budget_us`].
    pub failed: usize,
}

/// What [`run`] did. Serialises to the JSON of the binary's `--stats-json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Why the loop stopped.
    pub stop: StopReason,
    /// The control period, µs.
    pub period_us: u64,
    /// From the first deadline to the end of the shutdown, µs.
    pub elapsed_us: u64,
    /// Steps run.
    pub steps: u64,
    /// Steps that started more than one period late (the schedule was re-anchored).
    pub overruns: u64,
    /// Frames read from the bus and passed to the controller.
    pub frames_received: u64,
    /// Receive errors (reading the bus failed); the drain stops for that step.
    pub rx_errors: u64,
    /// Error frames of the CAN controller ([`BusErrorFrame`]: bus errors, error-passive,
    /// bus-off, restarts, missing ACKs...); the drain goes on after each.
    pub bus_error_frames: u64,
    /// Steps that left frames on the bus because [`RunOptions::max_rx_per_step`] was reached.
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
    /// The first bus error, with the frame id, for the log.
    pub first_error: Option<String>,
    /// The last bus error.
    pub last_error: Option<String>,
    /// Lateness of each step start after its deadline, µs.
    pub jitter: LatencySummary,
    /// Time from a step's start to its last frame sent, µs.
    pub step_time: LatencySummary,
    /// The shutdown frames.
    pub shutdown: ShutdownReport,
    /// The controller.
    pub controller: ControllerReport,
}

impl fmt::Display for Report {
    /// The human-readable summary the binary prints on exit.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = &self.controller;
        let e = &c.rx_errors;
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
        if let Some(first) = &self.first_error {
            writeln!(f, "first bus error: {first}")?;
        }
        if let Some(last) = &self.last_error {
            writeln!(f, "last bus error: {last}")?;
        }
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

/// Installs the stop signals a runner honours and returns the flag [`run`] polls:
///
/// - the first SIGINT or SIGTERM stores its number in the flag, so the loop ends cleanly at
///   the next step (and sends its shutdown frames);
/// - a second one while the flag is set exits the process at once with status 1 (for a
///   loop that does not stop).
///
/// (signal-hook runs the actions in registration order: the exit checks the `stopping` flag
/// before the same signal sets it.) Call it once per process, before the bus is opened.
///
/// # Errors
/// The OS refused a handler; the message names the signal.
pub fn stop_on_signals() -> io::Result<std::sync::Arc<AtomicUsize>> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    use std::sync::Arc;
    use std::sync::atomic::AtomicBool;
    let stop = Arc::new(AtomicUsize::new(0));
    let stopping = Arc::new(AtomicBool::new(false));
    for signal in [SIGINT, SIGTERM] {
        let number = usize::try_from(signal).unwrap_or(1);
        signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(&stopping))
            .and_then(|_| signal_hook::flag::register(signal, Arc::clone(&stopping)))
            .and_then(|_| signal_hook::flag::register_usize(signal, Arc::clone(&stop), number))
            .map_err(|e| {
                io::Error::new(
                    e.kind(),
                    format!("cannot install the handler of signal {signal}: {e}"),
                )
            })?;
    }
    Ok(stop)
}

/// An error and its causes on one line, each cause once (`a: b: c`): many errors already
/// include their source in their own message, so a cause whose text is already there is
/// skipped. For the binaries' error messages.
pub fn error_line(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(c) = cause {
        let next = c.to_string();
        if !text.contains(&next) {
            text.push_str(": ");
            text.push_str(&next);
        }
        cause = c.source();
    }
    text
}

/// Counters the loop keeps.
#[derive(Default)]
struct Counters {
    frames_received: u64,
    rx_errors: u64,
    bus_error_frames: u64,
    rx_capped_steps: u64,
    frames_sent: u64,
    send_retries: u64,
    send_errors: u64,
    send_kinds: ErrorCounts,
    rx_kinds: ErrorCounts,
    errors: ErrorLog,
}

/// The first and the last I/O error of a loop, as log lines (`send 0x200: No buffer space
/// available`): what a report shows, in constant memory however many errors there were.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct ErrorLog {
    /// The first error.
    pub first: Option<String>,
    /// The last error.
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
}

/// The id of a frame for a log line: `0x200` (standard), `0x12345678` (extended).
pub fn id_text(frame: &CanFrame) -> String {
    match frame.id() {
        embedded_can::Id::Standard(id) => format!("{:#05x}", id.as_raw()),
        embedded_can::Id::Extended(id) => format!("{:#010x}", id.as_raw()),
    }
}

/// Sends one frame, retrying busy errors ([`is_busy`]) every `backoff_us` while the clock is
/// before `give_up_us` (at least one attempt is always made); adds the retries to `retries`.
///
/// # Errors
/// The last busy error once the clock has reached `give_up_us`, or the first other error.
pub fn send_with_retry<B: Bus, C: Clock>(
    bus: &mut B,
    clock: &C,
    frame: &CanFrame,
    give_up_us: u64,
    backoff_us: u64,
    retries: &mut u64,
) -> io::Result<()> {
    loop {
        match bus.send(frame) {
            Ok(()) => return Ok(()),
            Err(e) if is_busy(&e) => {
                let now = clock.now_micros();
                if now.saturating_add(backoff_us) > give_up_us {
                    return Err(e);
                }
                *retries += 1;
                clock.sleep_until(now + backoff_us.max(1));
            }
            Err(e) => return Err(e),
        }
    }
}

fn state_name(s: &Snapshot) -> (&'static str, &'static str) {
    use firmware::control::Fault;
    use firmware::protocol::robot::RobotState;
    let state = match s.state {
        RobotState::Disabled => "Disabled",
        RobotState::Enabled => "Enabled",
        RobotState::Fault => "Fault",
        RobotState::Estop => "Estop",
        RobotState::WheelTest => "WheelTest",
    };
    let fault = match s.fault {
        Fault::None => "None",
        Fault::MotorStale => "MotorStale",
        Fault::MotorMissing => "MotorMissing",
        Fault::DriveError => "DriveError",
        Fault::Watchdog => "Watchdog",
        Fault::Config => "Config",
        Fault::EncoderStuck => "EncoderStuck",
        Fault::WheelRunaway => "WheelRunaway",
        Fault::WheelFight => "WheelFight",
    };
    (state, fault)
}

/// What the loop did, as [`run_recorded`] reports it (see [Recording](self#recording)).
/// Times are µs since the first step's clock reading: exactly what the core was given. Every
/// method does nothing by default; `()` records nothing.
pub trait Recorder {
    /// `frame` was passed to [`Controller::on_frame`] at `t_us`.
    fn received(&mut self, t_us: u64, frame: &CanFrame) {
        let _ = (t_us, frame);
    }

    /// [`Controller::step`] ran at `t_us`; its frames follow ([`Self::sent`]).
    fn stepped(&mut self, t_us: u64, controller: &Controller) {
        let _ = (t_us, controller);
    }

    /// [`Controller::shutdown`] ran, stamped `t_us`; its frames follow.
    fn shut_down(&mut self, t_us: u64, controller: &Controller) {
        let _ = (t_us, controller);
    }

    /// A frame of the step (or shutdown) at `step_us` was handed to the bus at `sent_us`
    /// (`sent`), or given up then (not `sent`).
    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, sent: bool) {
        let _ = (step_us, sent_us, frame, sent);
    }

    /// The link was lost or came back at `t_us` (see [The link](self#the-link)).
    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        let _ = (t_us, event);
    }

    /// A step and its frames are done: the place to hand the records over.
    fn step_done(&mut self) {}
}

impl Recorder for () {}

/// Runs `controller` on `bus` at its fixed rate until `stop` is non-zero or
/// `options.duration_us` has elapsed, then sends the shutdown frames. See the
/// [module documentation](self) for the schedule, the retry policy and what is measured.
///
/// Bus errors are counted in the [`Report`], never returned: the loop keeps running.
pub fn run<B: Bus, C: Clock>(
    controller: &mut Controller,
    bus: &mut B,
    clock: &C,
    options: &RunOptions,
    stop: &AtomicUsize,
) -> Report {
    run_recorded(controller, bus, clock, options, stop, &mut ())
}

/// [`run`], telling `recorder` what the loop does (see [Recording](self#recording)).
pub fn run_recorded<B: Bus, C: Clock, R: Recorder + ?Sized>(
    controller: &mut Controller,
    bus: &mut B,
    clock: &C,
    options: &RunOptions,
    stop: &AtomicUsize,
    recorder: &mut R,
) -> Report {
    let period = controller.period_micros().max(1);
    let mut counters = Counters::default();
    let mut jitter = LatencyHistogram::new();
    let mut step_time = LatencyHistogram::new();
    let mut overruns = 0;
    let mut steps = 0;

    let start = clock.now_micros();
    let mut last_step_us = None;
    let mut anchor = start;
    let mut k: u64 = 0;
    let mut link = Link::new(options);
    let stop_reason = loop {
        let deadline = anchor.saturating_add(k.saturating_mul(period));
        if link.stop {
            break StopReason::LinkLost;
        }
        if let Some(reason) = stop_requested(stop) {
            break reason;
        }
        if let Some(d) = options.duration_us
            && deadline - start >= d
        {
            break StopReason::Duration;
        }
        clock.sleep_until(deadline);
        // A signal that arrived during the sleep stops the loop now, not one step later.
        if let Some(reason) = stop_requested(stop) {
            break reason;
        }
        let woke = clock.now_micros();
        let late = woke.saturating_sub(deadline);
        jitter.record(late);
        if late > period {
            overruns += 1;
            anchor = woke;
            k = 0;
        }
        let now_us = woke - start;
        let now = Instant::from_micros(now_us);
        link.maybe_reopen(bus, woke, now_us, recorder);

        let mut drained = 0;
        while link.up() && drained < options.max_rx_per_step {
            match bus.try_recv() {
                Ok(Some(frame)) => {
                    controller.on_frame(now, &frame);
                    recorder.received(now_us, &frame);
                    counters.frames_received += 1;
                    drained += 1;
                }
                Ok(None) => break,
                Err(e) if is_bus_error_frame(&e) => {
                    // A bus event, not a failed read: the frames behind it are due too.
                    counters.bus_error_frames += 1;
                    counters.errors.record(format_args!("receive"), &e);
                    drained += 1;
                }
                Err(e) => {
                    counters.rx_errors += 1;
                    let kind = classify(&e);
                    counters.rx_kinds.count(kind);
                    counters.errors.record(format_args!("receive"), &e);
                    link.on_error(kind, woke, now_us, &counters.errors, recorder);
                    break;
                }
            }
        }
        if drained == options.max_rx_per_step {
            counters.rx_capped_steps += 1;
        }

        let out = controller.step(now);
        recorder.stepped(now_us, controller);
        last_step_us = Some(now_us);
        steps += 1;
        let give_up = deadline.max(woke).saturating_add(period / 2);
        for frame in &out {
            if !link.up() {
                link.report.frames_not_sent += 1;
                recorder.sent(now_us, clock.now_micros() - start, frame, false);
                continue;
            }
            match send_with_retry(
                bus,
                clock,
                frame,
                give_up,
                options.retry_backoff_us,
                &mut counters.send_retries,
            ) {
                Ok(()) => {
                    counters.frames_sent += 1;
                    recorder.sent(now_us, clock.now_micros() - start, frame, true);
                }
                Err(e) => {
                    counters.send_errors += 1;
                    let kind = classify(&e);
                    counters.send_kinds.count(kind);
                    counters
                        .errors
                        .record(format_args!("send {}", id_text(frame)), &e);
                    let t = clock.now_micros();
                    recorder.sent(now_us, t - start, frame, false);
                    link.on_error(kind, t, now_us, &counters.errors, recorder);
                }
            }
        }
        step_time.record(clock.now_micros().saturating_sub(woke));
        recorder.step_done();
        k += 1;
    };

    let at_stop = controller.snapshot();
    let frames = controller.shutdown();
    let shutdown_us = (clock.now_micros() - start).max(last_step_us.map_or(0, |t| t + 1));
    // One more try of a lost link: the shutdown frames are the ones that matter most.
    if !link.up() {
        link.next_try = 0;
        link.maybe_reopen(bus, clock.now_micros(), shutdown_us, recorder);
    }
    recorder.shut_down(shutdown_us, controller);
    let give_up = clock
        .now_micros()
        .saturating_add(options.shutdown_budget_us);
    let mut sent = 0;
    for frame in &frames {
        match send_with_retry(
            bus,
            clock,
            frame,
            give_up,
            options.retry_backoff_us,
            &mut counters.send_retries,
        ) {
            Ok(()) => {
                sent += 1;
                recorder.sent(shutdown_us, clock.now_micros() - start, frame, true);
            }
            Err(e) => {
                counters.send_kinds.count(classify(&e));
                counters
                    .errors
                    .record(format_args!("shutdown send {}", id_text(frame)), &e);
                recorder.sent(shutdown_us, clock.now_micros() - start, frame, false);
            }
        }
    }
    recorder.step_done();
    let (link, link_error) = link.finish(clock.now_micros());
    let after = controller.snapshot();
    let (state_at_stop, fault_at_stop) = state_name(&at_stop);

    Report {
        stop: stop_reason,
        period_us: period,
        elapsed_us: clock.now_micros().saturating_sub(start),
        steps,
        overruns,
        frames_received: counters.frames_received,
        rx_errors: counters.rx_errors,
        bus_error_frames: counters.bus_error_frames,
        rx_capped_steps: counters.rx_capped_steps,
        frames_sent: counters.frames_sent,
        send_retries: counters.send_retries,
        send_errors: counters.send_errors,
        send_errors_by_kind: counters.send_kinds,
        rx_errors_by_kind: counters.rx_kinds,
        link,
        link_error,
        first_error: counters.errors.first,
        last_error: counters.errors.last,
        jitter: jitter.summary(),
        step_time: step_time.summary(),
        shutdown: ShutdownReport {
            frames: frames.len(),
            sent,
            failed: frames.len() - sent,
        },
        controller: ControllerReport {
            state_at_stop,
            fault_at_stop,
            state_after_shutdown: state_name(&after).0,
            steps: after.steps,
            motors_online: at_stop.motors_online,
            rx_errors: at_stop.rx_errors,
            repeated_seq: at_stop.repeated_seq,
        },
    }
}

/// The link as the loop sees it (see [The link](self#the-link)).
struct Link {
    /// When the link was lost (clock µs), while it is down.
    since: Option<u64>,
    /// Clock time of the next [`Bus::reopen`] attempt.
    next_try: u64,
    /// The pause before that attempt.
    backoff: u64,
    /// Attempts since the loss.
    attempts: u64,
    min_us: u64,
    max_us: u64,
    exit_on_loss: bool,
    /// The error of the last loss.
    error: Option<String>,
    /// Stop at the next step ([`RunOptions::exit_on_link_loss`]).
    stop: bool,
    report: LinkReport,
}

impl Link {
    fn new(options: &RunOptions) -> Self {
        Self {
            since: None,
            next_try: 0,
            backoff: 0,
            attempts: 0,
            min_us: options.link_retry_min_us.max(1),
            max_us: options
                .link_retry_max_us
                .max(options.link_retry_min_us.max(1)),
            exit_on_loss: options.exit_on_link_loss,
            error: None,
            stop: false,
            report: LinkReport::default(),
        }
    }

    fn up(&self) -> bool {
        self.since.is_none()
    }

    /// A bus error of `kind` at clock time `t` (core time `t_us`); `errors.last` describes it.
    fn on_error<R: Recorder + ?Sized>(
        &mut self,
        kind: ErrorKind,
        t: u64,
        t_us: u64,
        errors: &ErrorLog,
        recorder: &mut R,
    ) {
        if !matches!(kind, ErrorKind::LinkDown | ErrorKind::NoDevice) || !self.up() {
            return;
        }
        self.since = Some(t);
        self.backoff = self.min_us;
        self.next_try = t.saturating_add(self.backoff);
        self.attempts = 0;
        self.report.losses += 1;
        self.stop = self.exit_on_loss;
        let error = errors.last.as_deref().unwrap_or("link lost");
        recorder.link(t_us, LinkEvent::Lost { error });
        self.error = Some(error.to_string());
    }

    /// While the link is down, tries [`Bus::reopen`] when the back-off allows (clock time
    /// `t`, core time `t_us`).
    fn maybe_reopen<B: Bus + ?Sized, R: Recorder + ?Sized>(
        &mut self,
        bus: &mut B,
        t: u64,
        t_us: u64,
        recorder: &mut R,
    ) {
        let Some(since) = self.since else { return };
        if t < self.next_try {
            return;
        }
        self.attempts += 1;
        self.report.reopen_attempts += 1;
        if bus.reopen().is_ok() {
            let down_us = t.saturating_sub(since);
            self.close_gap(down_us);
            self.report.recoveries += 1;
            self.since = None;
            recorder.link(
                t_us,
                LinkEvent::Restored {
                    down_us,
                    attempts: self.attempts,
                },
            );
        } else {
            self.backoff = self.backoff.saturating_mul(2).min(self.max_us);
            self.next_try = t.saturating_add(self.backoff);
        }
    }

    fn close_gap(&mut self, down_us: u64) {
        self.report.down_us += down_us;
        self.report.longest_down_us = self.report.longest_down_us.max(down_us);
    }

    /// The report and the last loss's error, a gap still open counted up to clock time `t`.
    fn finish(mut self, t: u64) -> (LinkReport, Option<String>) {
        if let Some(since) = self.since {
            self.close_gap(t.saturating_sub(since));
            self.report.down_at_stop = true;
        }
        (self.report, self.error)
    }
}

fn stop_requested(stop: &AtomicUsize) -> Option<StopReason> {
    match stop.load(Ordering::Relaxed) {
        0 => None,
        n => Some(StopReason::Signal(n)),
    }
}

/// Why a SocketCAN interface could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// No interface of that name.
    #[error(
        "CAN interface {iface:?} does not exist ({source}); a virtual one: \
         `ip link add dev {iface} type vcan && ip link set up {iface}`"
    )]
    NoSuchInterface {
        /// The interface name.
        iface: String,
        /// The OS error.
        source: io::Error,
    },
    /// The kernel has no SocketCAN (`EAFNOSUPPORT`).
    #[error(
        "cannot open CAN interface {iface:?}: no SocketCAN in this kernel, or the can and \
         can_raw modules are not loaded ({source})"
    )]
    NoSocketCan {
        /// The interface name.
        iface: String,
        /// The OS error.
        source: io::Error,
    },
    /// The interface exists but is down.
    #[error(
        "CAN interface {iface:?} is down (flags {flags:#x} in {}); bring it up: \
         `ip link set up {iface}`",
        .path.display()
    )]
    Down {
        /// The interface name.
        iface: String,
        /// The interface flags read.
        flags: u32,
        /// Where they were read.
        path: PathBuf,
    },
    /// Any other error while opening or configuring the socket.
    #[error("cannot open CAN interface {iface:?}: {source}")]
    Io {
        /// The interface name.
        iface: String,
        /// The OS error.
        source: io::Error,
    },
}

/// An error frame of the CAN controller, as [`Bus::try_recv`] of [`SocketCanBus`] reports it
/// (inside an [`io::Error`]; see [`is_bus_error_frame`]): a bus error, error-passive or
/// bus-off, a controller problem (RX overflow), a restart, a missing ACK. The text is
/// SocketCAN's decoding of the frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BusErrorFrame(pub String);

impl fmt::Display for BusErrorFrame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "error frame: {}", self.0)
    }
}

impl std::error::Error for BusErrorFrame {}

/// Whether `e` is a [`BusErrorFrame`]: a bus event to count, after which the bus goes on
/// delivering frames, unlike a failed read.
#[must_use]
pub fn is_bus_error_frame(e: &io::Error) -> bool {
    e.get_ref().is_some_and(|inner| inner.is::<BusErrorFrame>())
}

/// The error frames [`SocketCanBus`] asks SocketCAN for: every class (`CAN_ERR_MASK`) but
/// lost arbitration (`CAN_ERR_LOSTARB`, 0x2), which is how a CAN bus shares itself, not a
/// fault: on a busy bus it would drown the real errors.
const ERROR_CLASSES: u32 = libc::CAN_ERR_MASK & !libc::CAN_ERR_LOSTARB;

/// A raw SocketCAN socket on one interface, non-blocking, classic CAN frames, and the
/// controller's error frames (every class but lost arbitration: bus errors, error-passive,
/// bus-off, restarts, missing ACKs), which SocketCAN does not deliver unless asked to.
#[derive(Debug)]
pub struct SocketCanBus {
    socket: socketcan::CanSocket,
    iface: String,
}

impl SocketCanBus {
    /// Opens `iface` (e.g. `vcan0`, `can0`) in non-blocking mode and checks that it is up.
    ///
    /// # Errors
    /// An [`OpenError`] naming the interface.
    pub fn open(iface: &str) -> Result<Self, OpenError> {
        use socketcan::{Socket as _, SocketOptions as _};
        let socket = socketcan::CanSocket::open(iface).map_err(|source| {
            let iface = iface.to_string();
            match source.raw_os_error() {
                Some(libc::ENODEV | libc::ENXIO) => OpenError::NoSuchInterface { iface, source },
                Some(libc::EAFNOSUPPORT | libc::EPROTONOSUPPORT) => {
                    OpenError::NoSocketCan { iface, source }
                }
                _ if source.kind() == io::ErrorKind::NotFound => {
                    OpenError::NoSuchInterface { iface, source }
                }
                _ => OpenError::Io { iface, source },
            }
        })?;
        socket
            .set_nonblocking(true)
            .and_then(|()| socket.set_error_filter(ERROR_CLASSES))
            .map_err(|source| OpenError::Io {
                iface: iface.to_string(),
                source,
            })?;
        // Writes to a down interface fail with ENETDOWN: refuse at startup instead. The flags
        // file may be unreadable (no sysfs): then the check is skipped.
        let path = PathBuf::from(format!("/sys/class/net/{iface}/flags"));
        if let Ok(text) = std::fs::read_to_string(&path)
            && let Ok(flags) = u32::from_str_radix(text.trim().trim_start_matches("0x"), 16)
            && flags & 1 == 0
        {
            return Err(OpenError::Down {
                iface: iface.to_string(),
                flags,
                path,
            });
        }
        Ok(Self {
            socket,
            iface: iface.to_string(),
        })
    }

    /// The interface's name.
    #[must_use]
    pub fn iface(&self) -> &str {
        &self.iface
    }
}

impl Bus for SocketCanBus {
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
        use socketcan::Socket as _;
        match self.socket.read_frame() {
            Ok(socketcan::CanFrame::Error(e)) => {
                Err(io::Error::other(BusErrorFrame(e.into_error().to_string())))
            }
            Ok(frame) => CanFrame::from_frame(&frame).map(Some).ok_or_else(|| {
                io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("frame with DLC {} is not a classic CAN frame", frame.dlc()),
                )
            }),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(None),
            Err(e) => Err(e),
        }
    }

    fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
        use socketcan::Socket as _;
        let frame: socketcan::CanFrame = frame.convert().ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("socketcan rejected frame {}", id_text(frame)),
            )
        })?;
        self.socket.write_frame(&frame)
    }

    /// Opens a new socket on the interface (see [`SocketCanBus::open`]): a socket whose
    /// device was removed stays dead even when a device of the same name comes back, and
    /// the frames queued before a link loss are stale. Fails while the interface is missing
    /// or down; costs a sysfs read and a socket when it does not.
    fn reopen(&mut self) -> io::Result<()> {
        let fresh = Self::open(&self.iface).map_err(io::Error::other)?;
        *self = fresh;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::cell::{Cell, RefCell};
    use firmware::config::Config;
    use firmware::protocol::robot::{Command, ModeRequest, TwistCmd};
    use std::collections::VecDeque;
    use std::rc::Rc;

    /// Simulated time: `sleep_until` jumps to the deadline plus a scripted wake-up latency.
    #[derive(Default)]
    struct FakeClock {
        now: Cell<u64>,
        latencies: RefCell<VecDeque<u64>>,
    }

    impl FakeClock {
        fn at(t: u64) -> Rc<Self> {
            let c = Rc::new(Self::default());
            c.now.set(t);
            c
        }
        fn advance(&self, us: u64) {
            self.now.set(self.now.get() + us);
        }
    }

    impl Clock for FakeClock {
        fn now_micros(&self) -> u64 {
            self.now.get()
        }
        fn sleep_until(&self, deadline_us: u64) {
            let late = self.latencies.borrow_mut().pop_front().unwrap_or(0);
            self.now.set(self.now.get().max(deadline_us) + late);
        }
    }

    /// A bus in memory: frames arrive at given times; sends are recorded with their time.
    /// `busy` makes the next sends fail with ENOBUFS; `stop_at` sets the stop flag on the
    /// first send at or after that time (a signal arriving while the loop runs).
    struct MemoryBus {
        clock: Rc<FakeClock>,
        incoming: VecDeque<(u64, CanFrame)>,
        sent: Vec<(u64, CanFrame)>,
        busy: u64,
        attempts: u64,
        stop_at: Option<(u64, Rc<AtomicUsize>)>,
        /// The link is down in this clock interval: sends fail with ENETDOWN, the first
        /// receive in it too (as SocketCAN does), and reopening fails.
        down: Option<(u64, u64)>,
        down_reported: bool,
        reopens: Vec<(u64, bool)>,
    }

    impl MemoryBus {
        fn new(clock: &Rc<FakeClock>) -> Self {
            Self {
                clock: Rc::clone(clock),
                incoming: VecDeque::new(),
                sent: Vec::new(),
                busy: 0,
                attempts: 0,
                stop_at: None,
                down: None,
                down_reported: false,
                reopens: Vec::new(),
            }
        }
        fn is_down(&self) -> bool {
            let now = self.clock.now_micros();
            self.down
                .is_some_and(|(from, to)| (from..to).contains(&now))
        }
        fn sent_ids(&self) -> Vec<(u64, u16)> {
            self.sent.iter().map(|(t, f)| (*t, raw_id(f))).collect()
        }
    }

    impl Bus for MemoryBus {
        fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
            if self.is_down() {
                if !self.down_reported {
                    self.down_reported = true;
                    return Err(io::Error::from_raw_os_error(libc::ENETDOWN));
                }
                return Ok(None);
            }
            match self.incoming.front() {
                Some(&(t, f)) if t <= self.clock.now_micros() => {
                    self.incoming.pop_front();
                    Ok(Some(f))
                }
                _ => Ok(None),
            }
        }
        fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
            self.attempts += 1;
            let now = self.clock.now_micros();
            if let Some((t, flag)) = &self.stop_at
                && now >= *t
            {
                flag.store(15, Ordering::Relaxed);
            }
            if self.is_down() {
                return Err(io::Error::from_raw_os_error(libc::ENETDOWN));
            }
            if self.busy > 0 {
                self.busy -= 1;
                return Err(io::Error::from_raw_os_error(libc::ENOBUFS));
            }
            self.sent.push((now, *frame));
            Ok(())
        }
        fn reopen(&mut self) -> io::Result<()> {
            let ok = !self.is_down();
            self.reopens.push((self.clock.now_micros(), ok));
            if ok {
                Ok(())
            } else {
                Err(io::Error::from_raw_os_error(libc::ENETDOWN))
            }
        }
    }

    fn raw_id(f: &CanFrame) -> u16 {
        match f.id() {
            embedded_can::Id::Standard(id) => id.as_raw(),
            embedded_can::Id::Extended(_) => u16::MAX,
        }
    }

    fn dji() -> Controller {
        Controller::new(&Config::dji_m3508_example()).unwrap()
    }

    fn for_ms(ms: u64) -> RunOptions {
        RunOptions {
            duration_us: Some(ms * 1000),
            ..RunOptions::default()
        }
    }

    const T0: u64 = 7_000_000;

    /// Times of the DJI command frames (0x200), one per step.
    fn motor_times(bus: &MemoryBus) -> Vec<u64> {
        bus.sent_ids()
            .into_iter()
            .filter(|&(_, id)| id == 0x200)
            .map(|(t, _)| t)
            .collect()
    }

    #[test]
    fn steps_at_absolute_deadlines() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        let mut ctl = dji();
        let r = run(
            &mut ctl,
            &mut bus,
            &*clock,
            &for_ms(10),
            &AtomicUsize::new(0),
        );
        assert_eq!(r.stop, StopReason::Duration);
        assert_eq!(r.period_us, 1000);
        assert_eq!(r.steps, 10);
        assert_eq!(r.controller.steps, 10);
        assert_eq!(r.overruns, 0);
        // 10 steps + the shutdown frame.
        let expected: Vec<u64> = (0..10).map(|k| T0 + k * 1000).chain([T0 + 9000]).collect();
        assert_eq!(motor_times(&bus), expected);
        assert_eq!(r.jitter.samples, 10);
        assert_eq!(r.jitter.max_us, Some(0));
        // Step 0: motor command, odometry (2), status, status counters, heartbeat; steps 1-9:
        // motor command.
        assert_eq!(r.frames_sent, 6 + 9);
        let first: Vec<u16> = bus.sent_ids().iter().take(6).map(|x| x.1).collect();
        assert_eq!(first, [0x200, 0x310, 0x311, 0x312, 0x313, 0x31F]);
        assert_eq!(r.send_errors, 0);
        assert_eq!(r.shutdown.sent, 1);
    }

    #[test]
    fn a_late_wake_up_does_not_shift_the_schedule() {
        let clock = FakeClock::at(T0);
        clock.latencies.borrow_mut().extend([0, 300, 0, 999, 0]);
        let mut bus = MemoryBus::new(&clock);
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(5),
            &AtomicUsize::new(0),
        );
        let t = motor_times(&bus);
        assert_eq!(&t[..5], &[T0, T0 + 1300, T0 + 2000, T0 + 3999, T0 + 4000]);
        assert_eq!(r.overruns, 0);
        assert_eq!(r.jitter.max_us, Some(999));
        assert_eq!(r.jitter.p50_us, Some(0));
    }

    #[test]
    fn an_overrun_is_counted_and_re_anchors() {
        let clock = FakeClock::at(T0);
        clock.latencies.borrow_mut().extend([0, 0, 2500, 0, 0]);
        let mut bus = MemoryBus::new(&clock);
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(7),
            &AtomicUsize::new(0),
        );
        let t = motor_times(&bus);
        // Step 2 was due at +2000 and ran at +4500; the next steps follow it by one period,
        // with no catch-up burst.
        assert_eq!(&t[..5], &[T0, T0 + 1000, T0 + 4500, T0 + 5500, T0 + 6500]);
        assert_eq!(r.overruns, 1);
        assert_eq!(r.jitter.max_us, Some(2500));
    }

    #[test]
    fn slow_steps_within_one_period_are_not_overruns() {
        let clock = FakeClock::at(T0);
        // Every step takes 1.2 periods in sends: each starts late, the lateness grows by
        // 200 µs a step until it passes one period (step 6, 1200 µs late), then re-anchors.
        struct Slow(MemoryBus);
        impl Bus for Slow {
            fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
                self.0.try_recv()
            }
            fn send(&mut self, f: &CanFrame) -> io::Result<()> {
                let sent = self.0.send(f);
                if raw_id(f) == 0x200 {
                    self.0.clock.advance(1200);
                }
                sent
            }
        }
        let mut slow = Slow(MemoryBus::new(&clock));
        let r = run(
            &mut dji(),
            &mut slow,
            &*clock,
            &for_ms(8),
            &AtomicUsize::new(0),
        );
        assert_eq!(r.steps, 7);
        assert_eq!(r.overruns, 1);
        assert_eq!(r.jitter.max_us, Some(1200));
        assert_eq!(r.step_time.p50_us, Some(1200));
        // Step 6 was due at +6000 and started at +7200.
        let t = motor_times(&slow.0);
        assert_eq!(t[6], T0 + 7200);
    }

    #[test]
    fn frames_received_before_a_step_are_fed_to_it() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        let status_req = Command::StatusRequest.to_can_frame();
        bus.incoming.push_back((T0 + 2500, status_req));
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(5),
            &AtomicUsize::new(0),
        );
        let status: Vec<u64> = bus
            .sent_ids()
            .into_iter()
            .filter(|&(_, id)| id == 0x312)
            .map(|(t, _)| t)
            .collect();
        // The periodic status of step 0, then the requested one at the first step after the
        // request arrived.
        assert_eq!(status, [T0, T0 + 3000]);
        assert_eq!(r.frames_received, 1);
    }

    #[test]
    fn every_waiting_frame_is_drained_up_to_the_cap() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        // Unknown ids: counted by the controller as rejected.
        let junk = CanFrame::standard(embedded_can::StandardId::new(0x123).unwrap(), &[1]).unwrap();
        for _ in 0..10 {
            bus.incoming.push_back((T0 + 500, junk));
        }
        let options = RunOptions {
            max_rx_per_step: 4,
            ..for_ms(5)
        };
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &options,
            &AtomicUsize::new(0),
        );
        assert_eq!(r.frames_received, 10);
        assert_eq!(r.controller.rx_errors.unknown_id, 10);
        // Steps 1 and 2 took 4 frames each, step 3 the last 2.
        assert_eq!(r.rx_capped_steps, 2);
    }

    fn drive_frames(t: u64) -> [(u64, CanFrame); 2] {
        [
            (t, Command::Mode(ModeRequest::Enable).to_can_frame()),
            (
                t + 1,
                Command::Twist(TwistCmd {
                    vx: 1.0,
                    vy: 0.0,
                    wz: 0.0,
                    seq: 0,
                })
                .to_can_frame(),
            ),
        ]
    }

    #[test]
    fn a_stop_sends_the_shutdown_frames() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        bus.incoming.extend(drive_frames(T0 + 100));
        let stop = Rc::new(AtomicUsize::new(0));
        bus.stop_at = Some((T0 + 5000, Rc::clone(&stop)));
        let mut ctl = dji();
        let r = run(&mut ctl, &mut bus, &*clock, &RunOptions::default(), &stop);
        assert_eq!(r.stop, StopReason::Signal(15));
        assert_eq!(r.stop.to_string(), "SIGTERM");
        assert_eq!(r.steps, 6);
        assert_eq!(r.controller.state_at_stop, "Enabled");
        assert_eq!(r.controller.state_after_shutdown, "Disabled");
        let motor: Vec<&CanFrame> = bus
            .sent
            .iter()
            .filter(|(_, f)| raw_id(f) == 0x200)
            .map(|(_, f)| f)
            .collect();
        assert_eq!(motor.len(), 7);
        // Driving before the stop; zero current after it.
        assert_ne!(motor[5].data(), &[0; 8]);
        assert_eq!(motor[6].data(), &[0; 8]);
        assert_eq!(bus.sent.last().map(|(_, f)| *f), Some(*motor[6]));
        assert_eq!(
            r.shutdown,
            ShutdownReport {
                frames: 1,
                sent: 1,
                failed: 0
            }
        );
    }

    #[test]
    fn odrive_shutdown_is_zero_velocity_then_idle_per_axis() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        let mut ctl = Controller::new(&Config::odrive_example()).unwrap();
        let r = run(
            &mut ctl,
            &mut bus,
            &*clock,
            &for_ms(3),
            &AtomicUsize::new(0),
        );
        assert_eq!(r.shutdown.frames, 8);
        let tail: Vec<u16> = bus.sent_ids()[bus.sent.len() - 8..]
            .iter()
            .map(|x| x.1)
            .collect();
        // node << 5 | 0x0D (Set_Input_Vel), node << 5 | 0x07 (Set_Axis_State).
        assert_eq!(tail, [0x0D, 0x07, 0x2D, 0x27, 0x4D, 0x47, 0x6D, 0x67]);
    }

    #[test]
    fn busy_sends_are_retried() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        bus.busy = 3;
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(3),
            &AtomicUsize::new(0),
        );
        assert_eq!(r.send_retries, 3);
        assert_eq!(r.send_errors, 0);
        assert_eq!(r.frames_sent, 6 + 2);
        // The first frame went out after three 20 µs back-offs.
        assert_eq!(bus.sent[0], (T0 + 60, bus.sent[0].1));
        assert!(r.first_error.is_none());
    }

    #[test]
    fn a_bus_that_stays_busy_drops_frames_and_keeps_the_schedule() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        bus.busy = u64::MAX;
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(4),
            &AtomicUsize::new(0),
        );
        assert_eq!(r.steps, 4);
        assert_eq!(r.overruns, 0);
        assert_eq!(r.frames_sent, 0);
        assert_eq!(r.send_errors, 6 + 3);
        // Retries end half a period after the deadline.
        assert!(r.jitter.max_us.unwrap() < 1000, "{r:?}");
        assert_eq!(r.shutdown.failed, 1);
        let e = r.first_error.as_deref().unwrap();
        assert!(e.starts_with("send 0x200: "), "{e}");
        // The shutdown was retried for its whole budget.
        assert!(r.elapsed_us >= 3000 + RunOptions::default().shutdown_budget_us - 20);
    }

    #[test]
    fn other_send_errors_are_counted_without_retry() {
        struct Down;
        impl Bus for Down {
            fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
                Err(io::Error::from_raw_os_error(libc::EIO))
            }
            fn send(&mut self, _: &CanFrame) -> io::Result<()> {
                Err(io::Error::from_raw_os_error(libc::EIO))
            }
        }
        let clock = FakeClock::at(T0);
        let r = run(
            &mut dji(),
            &mut Down,
            &*clock,
            &for_ms(2),
            &AtomicUsize::new(0),
        );
        assert_eq!(r.steps, 2);
        assert_eq!(r.send_retries, 0);
        assert_eq!(r.send_errors, 6 + 1);
        assert_eq!(r.rx_errors, 2);
        assert!(r.first_error.unwrap().starts_with("receive: "));
        assert!(r.last_error.unwrap().starts_with("shutdown send 0x200: "));
        assert_eq!(r.shutdown.failed, 1);
        // The shutdown frame too.
        assert_eq!(r.send_errors_by_kind.other, 7 + 1);
        assert_eq!(r.rx_errors_by_kind.other, 2);
        assert_eq!(r.link, LinkReport::default());
    }

    /// What a recorder hears of the link: (core µs, "lost: error" / "back after N µs, try K").
    #[derive(Default)]
    struct LinkLog(Vec<(u64, String)>);

    impl Recorder for LinkLog {
        fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
            let text = match event {
                LinkEvent::Lost { error } => format!("lost: {error}"),
                LinkEvent::Restored { down_us, attempts } => {
                    format!("back after {down_us} µs, try {attempts}")
                }
            };
            self.0.push((t_us, text));
        }
    }

    #[test]
    fn a_lost_link_keeps_the_core_stepping_and_resumes_when_it_is_back() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        // Down from 5 ms to 25 ms.
        bus.down = Some((T0 + 5_000, T0 + 25_000));
        let mut events = LinkLog::default();
        let mut ctl = dji();
        let r = run_recorded(
            &mut ctl,
            &mut bus,
            &*clock,
            &for_ms(60),
            &AtomicUsize::new(0),
            &mut events,
        );
        // Every step ran, on schedule.
        assert_eq!((r.steps, r.overruns), (60, 0));
        // Lost at the first receive of the 5 ms step; reopen tried 10 ms later (15 ms,
        // down), then 20 ms after that (35 ms, up).
        assert_eq!(
            bus.reopens,
            [(T0 + 15_000, false), (T0 + 35_000, true)],
            "reopen attempts"
        );
        assert_eq!(
            events.0,
            [
                (
                    5_000,
                    "lost: receive: Network is down (os error 100)".to_string()
                ),
                (35_000, "back after 30000 µs, try 2".to_string()),
            ]
        );
        let l = r.link;
        assert_eq!(
            (l.losses, l.recoveries, l.reopen_attempts, l.down_at_stop),
            (1, 1, 2, false)
        );
        assert_eq!((l.down_us, l.longest_down_us), (30_000, 30_000));
        // Steps 5..=34 (30 steps) sent nothing, none tried: 30 motor commands and the
        // odometry pairs of the 10, 20 and 30 ms steps.
        assert_eq!(l.frames_not_sent, 30 + 3 * 2);
        let times = motor_times(&bus);
        assert_eq!(times.len(), 60 - 30 + 1, "{times:?}");
        assert!(
            times
                .iter()
                .all(|&t| !(T0 + 5_000..T0 + 35_000).contains(&t))
        );
        assert_eq!(r.rx_errors_by_kind.link_down, 1);
        assert_eq!(r.send_errors, 0, "no send was tried while down");
        assert_eq!(r.shutdown.failed, 0);
        let text = r.to_string();
        assert!(
            text.contains("link: lost 1 time(s), back 1 time(s); down 0.030 s in total"),
            "{text}"
        );
    }

    #[test]
    fn a_link_lost_on_a_send_backs_off_up_to_the_limit() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        // The receive of the first down step already happened: the send sees it first.
        bus.down = Some((T0 + 2_000, T0 + 1_000_000));
        bus.down_reported = true;
        let options = RunOptions {
            link_retry_min_us: 10_000,
            link_retry_max_us: 40_000,
            ..for_ms(200)
        };
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &options,
            &AtomicUsize::new(0),
        );
        let tries: Vec<u64> = bus.reopens.iter().map(|&(t, _)| t - T0).collect();
        // 10, 20, 40, 40, 40 ms apart; then the one try before the shutdown.
        assert_eq!(
            tries,
            [12_000, 32_000, 72_000, 112_000, 152_000, 192_000, 199_000]
        );
        assert_eq!(r.send_errors_by_kind.link_down, 1 + 1);
        assert!(r.link.down_at_stop);
        assert_eq!(r.link.down_us, 199_000 - 2_000);
        assert_eq!(r.shutdown.failed, 1);
    }

    #[test]
    fn exit_on_link_loss_stops_the_loop_with_the_reason() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        bus.down = Some((T0 + 3_000, u64::MAX));
        let options = RunOptions {
            exit_on_link_loss: true,
            ..for_ms(50)
        };
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &options,
            &AtomicUsize::new(0),
        );
        // The step that saw the loss ran (the core is never skipped); the next one stops.
        assert_eq!((r.stop, r.steps), (StopReason::LinkLost, 4));
        assert_eq!(r.stop.to_string(), "link lost (exit on link loss)");
        assert!(r.link.down_at_stop);
        assert_eq!(r.link.losses, 1);
        // The one reopen before the shutdown failed; the shutdown frame was tried.
        assert_eq!(r.link.reopen_attempts, 1);
        assert_eq!(
            r.link_error.as_deref(),
            Some("receive: Network is down (os error 100)")
        );
        assert_eq!(r.shutdown.failed, 1);
        assert_eq!(
            serde_json::to_value(r.stop).unwrap(),
            serde_json::json!("link_lost")
        );
    }

    #[test]
    fn bus_errors_are_classified_for_the_link() {
        let e = io::Error::from_raw_os_error;
        assert_eq!(classify(&e(libc::ENOBUFS)), ErrorKind::Busy);
        assert_eq!(classify(&e(libc::EAGAIN)), ErrorKind::Busy);
        assert_eq!(classify(&e(libc::ENETDOWN)), ErrorKind::LinkDown);
        assert_eq!(classify(&e(libc::ENODEV)), ErrorKind::NoDevice);
        assert_eq!(classify(&e(libc::ENXIO)), ErrorKind::NoDevice);
        assert_eq!(classify(&e(libc::EIO)), ErrorKind::Other);
    }

    #[test]
    fn bus_error_frames_are_counted_and_the_frames_behind_them_still_read() {
        /// Two twist commands with a controller error frame between them, then nothing.
        struct Noisy(VecDeque<io::Result<Option<CanFrame>>>);
        impl Bus for Noisy {
            fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
                self.0.pop_front().unwrap_or(Ok(None))
            }
            fn send(&mut self, _: &CanFrame) -> io::Result<()> {
                Ok(())
            }
        }
        let twist = |seq| {
            Command::Twist(TwistCmd {
                vx: 0.1,
                vy: 0.0,
                wz: 0.0,
                seq,
            })
            .to_can_frame()
        };
        let error = io::Error::other(BusErrorFrame("bus-off".into()));
        assert!(is_bus_error_frame(&error));
        assert!(!is_bus_error_frame(&io::Error::from_raw_os_error(
            libc::ENETDOWN
        )));
        let mut bus = Noisy(VecDeque::from([
            Ok(Some(twist(0))),
            Err(error),
            Ok(Some(twist(1))),
        ]));
        let clock = FakeClock::at(T0);
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(2),
            &AtomicUsize::new(0),
        );
        assert_eq!(
            (r.frames_received, r.bus_error_frames, r.rx_errors),
            (2, 1, 0)
        );
        assert_eq!(
            r.first_error.as_deref(),
            Some("receive: error frame: bus-off")
        );
        assert!(r.to_string().contains("1 bus error frames"), "{r}");
    }

    #[test]
    fn a_stop_before_the_first_step_still_shuts_down() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &RunOptions::default(),
            &AtomicUsize::new(2),
        );
        assert_eq!((r.stop, r.steps), (StopReason::Signal(2), 0));
        assert_eq!(r.stop.to_string(), "SIGINT");
        assert_eq!(r.jitter.p99_us, None);
        assert_eq!(bus.sent_ids(), [(T0, 0x200)]);
        assert_eq!(r.controller.rx_errors.unknown_id, 0);
        let text = r.to_string();
        assert!(
            text.contains("jitter (step start - deadline): no samples"),
            "{text}"
        );
        assert!(text.contains("shutdown: 1 of 1 frames sent"), "{text}");
    }

    #[test]
    fn the_report_serialises_to_json() {
        let clock = FakeClock::at(T0);
        let mut bus = MemoryBus::new(&clock);
        let r = run(
            &mut dji(),
            &mut bus,
            &*clock,
            &for_ms(2),
            &AtomicUsize::new(0),
        );
        let v: serde_json::Value = serde_json::to_value(&r).unwrap();
        assert_eq!(v["stop"], "duration");
        assert_eq!(v["steps"], 2);
        assert_eq!(v["jitter"]["p99_us"], 0);
        assert_eq!(v["controller"]["state_at_stop"], "Disabled");
        assert_eq!(v["controller"]["rx_errors"]["wrong_dlc"], 0);
        assert_eq!(v["controller"]["repeated_seq"], 0);
        assert_eq!(v["shutdown"]["sent"], 1);
        let stopped = serde_json::to_value(StopReason::Signal(2)).unwrap();
        assert_eq!(stopped, serde_json::json!({ "signal": 2 }));
    }

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

    #[test]
    fn busy_errors_are_enobufs_and_eagain() {
        assert!(is_busy(&io::Error::from_raw_os_error(libc::ENOBUFS)));
        assert!(is_busy(&io::Error::from_raw_os_error(libc::EAGAIN)));
        assert!(!is_busy(&io::Error::from_raw_os_error(libc::ENETDOWN)));
    }

    #[test]
    fn opening_a_missing_interface_names_it() {
        let e = SocketCanBus::open("nosuchcan9").unwrap_err();
        let text = e.to_string();
        assert!(text.contains("\"nosuchcan9\""), "{text}");
    }

    #[test]
    fn monotonic_clock_never_wakes_early() {
        for spin in [0, 200] {
            let c = MonotonicClock::new(spin);
            let deadline = c.now_micros() + 1500;
            c.sleep_until(deadline);
            assert!(c.now_micros() >= deadline);
            // A past deadline returns at once.
            c.sleep_until(0);
        }
    }

    /// The only test in this process that installs the handlers or raises a signal: a
    /// second SIGTERM would end the test binary, by design.
    #[test]
    fn the_first_stop_signal_sets_the_flag_to_its_number() {
        let stop = stop_on_signals().unwrap();
        assert_eq!(stop.load(Ordering::Relaxed), 0);
        signal_hook::low_level::raise(signal_hook::consts::SIGTERM).unwrap();
        assert_eq!(stop.load(Ordering::Relaxed), 15);
    }

    #[test]
    fn an_error_line_names_each_cause_once() {
        #[derive(Debug)]
        struct Outer(io::Error, &'static str);
        impl fmt::Display for Outer {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.1)
            }
        }
        impl std::error::Error for Outer {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let cause = || io::Error::other("disk full");
        let e = Outer(cause(), "writing log.mcap");
        assert_eq!(error_line(&e), "writing log.mcap: disk full");
        let e = Outer(cause(), "writing log.mcap: disk full");
        assert_eq!(error_line(&e), "writing log.mcap: disk full");
    }
}
