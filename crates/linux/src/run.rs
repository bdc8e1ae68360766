//! The fixed-rate loop ([`run`], [`run_recorded`]) and what it tells a [`Recorder`].

use core::sync::atomic::{AtomicUsize, Ordering};
use std::io;

use embedded_can::Frame as _;

use firmware::CanFrame;
use firmware::control::{Controller, Instant};

use crate::bus::{Bus, ErrorKind, classify, is_bus_error_frame, is_busy};
use crate::clock::Clock;
use crate::report::{
    ControllerReport, ErrorCounts, ErrorLog, LatencyHistogram, LinkReport, Report, ShutdownReport,
    StopReason,
};
use crate::schedule::Schedule;

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

/// What the loop did, as [`run_recorded`] reports it (see [Recording](crate::run_recorded#recording)).
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

    /// The link was lost or came back at `t_us` (see [The link](crate::run_recorded#the-link)).
    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        let _ = (t_us, event);
    }

    /// A step and its frames are done: the place to hand the records over.
    fn step_done(&mut self) {}
}

impl Recorder for () {}

/// Runs `controller` on `bus` at its fixed rate until `stop` is non-zero or
/// `options.duration_us` has elapsed, then sends the shutdown frames. See [`run_recorded`]
/// for the schedule, the retry policy and what is measured.
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

/// [`run`], telling `recorder` what the loop does.
///
/// # Recording
///
/// [`run_recorded`] tells a [`Recorder`] what the loop did, from the loop's thread, with the
/// times the core saw (µs since the first step's clock reading): each frame passed to
/// [`Controller::on_frame`], each step (before its frames go out), each frame the step
/// produced with the time it was handed to the bus (or given up), and the shutdown. The
/// shutdown is stamped at least 1 µs after the last step, so that its frames never share a
/// time with that step's. A recorder must only push small values: the loop waits for it.
///
/// # Scheduling
///
/// Steps are due at absolute deadlines `start + k · period` (`period` from
/// [`Controller::period_micros`]; the [`Schedule`]). A deadline is never computed from the previous wake-up,
/// so lateness does not accumulate (no drift). For each step the loop:
///
/// 1. sleeps until the deadline, then reads the clock once: `now`;
/// 2. records the lateness `now - deadline` (see *Jitter*); when it exceeds one period the
///    step counts as an **overrun** and the schedule is re-anchored at `now`
///    (`start := now, k := 0`) instead of running a burst of catch-up steps;
/// 3. drains every frame waiting on the bus (non-blocking reads, at most
///    [`RunOptions::max_rx_per_step`]) into [`Controller::on_frame`], all stamped `now`;
/// 4. runs [`Controller::step`] at `now` and sends its frames in order.
///
/// `now` is passed to the core as microseconds since the first step's clock reading, so the
/// core's [`Instant`] starts near zero.
///
/// # Sending
///
/// A full transmit queue is normal on a busy bus: SocketCAN reports it as `ENOBUFS` (the
/// interface queue is full) or `EAGAIN` (the socket buffer is full, non-blocking socket).
/// Those are retried every [`RunOptions::retry_backoff_us`] until half a period after the
/// step's deadline; a frame still not sent then is dropped and counted in
/// [`Report::send_errors`]. Any other error (interface down, ...) is counted at once. Nothing
/// on the bus ever stops the loop.
///
/// # The link
///
/// On a robot the interface itself fails: a USB adapter is unplugged, a cable breaks, the
/// link is set down. SocketCAN then reports `ENETDOWN` (the link is down: every send, and
/// one receive) or `ENODEV`/`ENXIO` (the device is gone: the socket stays dead even when a
/// device of the same name comes back). Either is a **link loss** ([`classify`]). The loop
/// keeps stepping the core at its rate, so the watchdog and the state machine see the silence
/// as it is (no motor feedback: the core faults and stays faulted until a reset and a new
/// enable, as for any other loss of its motors); it stops reading and sending, counts the
/// frames it did not send ([`LinkReport::frames_not_sent`]) and tries [`Bus::reopen`] with an
/// exponential back-off ([`RunOptions::link_retry_min_us`] doubling up to
/// [`RunOptions::link_retry_max_us`]). The first reopen that succeeds resumes reading and
/// sending; the gap is in [`Report::link`] and told to the [`Recorder`] ([`LinkEvent`]) as
/// it happens. With [`RunOptions::exit_on_link_loss`] the loop stops instead
/// ([`StopReason::LinkLost`]). Errors are counted by kind ([`ErrorCounts`]) for sends and
/// receives.
///
/// # Stopping
///
/// The loop stops when the `stop` flag becomes non-zero (the binary stores the signal number
/// from SIGINT/SIGTERM there) or when [`RunOptions::duration_us`] has elapsed. It then sends
/// [`Controller::shutdown`]'s frames (zero current for DJI ESCs; zero velocity and the idle
/// state for ODrive axes), retrying busy errors for up to
/// [`RunOptions::shutdown_budget_us`], and returns a [`Report`].
///
/// # Jitter
///
/// Jitter is measured as the **lateness of each step's start**: the clock reading after the
/// sleep minus the step's deadline (never negative: a sleep never ends early). It is recorded
/// in a fixed-size [`LatencyHistogram`] (exact below 2048 µs, within 0.1 % above), so a run
/// of any length uses the same memory; [`Report::jitter`] has its p50, p99 and maximum. The
/// time from wake-up to the last frame sent is recorded the same way
/// ([`Report::step_time`]).
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
    let mut steps = 0;

    let start = clock.now_micros();
    let mut last_step_us = None;
    let mut schedule = Schedule::new(start, period);
    let mut link = Link::new(options);
    let stop_reason = loop {
        let deadline = schedule.deadline();
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
        jitter.record(schedule.woke(woke));
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
        schedule.advance();
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
    let (state_at_stop, fault_at_stop) = (at_stop.state.as_str(), at_stop.fault.as_str());

    Report {
        stop: stop_reason,
        period_us: period,
        elapsed_us: clock.now_micros().saturating_sub(start),
        steps,
        overruns: schedule.overruns(),
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
        errors: counters.errors,
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
            state_after_shutdown: after.state.as_str(),
            steps: after.steps,
            motors_online: at_stop.motors_online,
            rx_errors: at_stop.rx_errors,
            repeated_seq: at_stop.repeated_seq,
            drive_issue: controller.drive_issue().map(|i| i.to_string()),
            drive_emcy: controller.drive_emcy_count(),
        },
    }
}

/// The link as the loop sees it (see [The link](crate::run_recorded#the-link)).
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
