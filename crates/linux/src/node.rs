//! The one fixed-rate loop ([`run_node`]) and what runs in it (a [`Node`]): the runner's
//! control core ([`run_recorded`](crate::run_recorded)) and `hostsim plant`'s simulated drives.
//! The loop owns the schedule, the drain, the sends and their retries, the link and the stop;
//! a node says what it does with the frames drained, what it sends each period, what it sends
//! on the way out and what it adds to the [`LoopReport`].

use core::sync::atomic::AtomicUsize;

use firmware::CanFrame;

use crate::bus::{Bus, ErrorKind, classify, is_bus_error_frame};
use crate::clock::Clock;
use crate::report::{ErrorCounts, ErrorLog, LatencyHistogram, LinkReport, LoopReport, StopReason};
use crate::run::{LinkEvent, RunOptions, id_text, send_with_retry};
use crate::schedule::Schedule;
use crate::signals::stop_requested;

/// What runs in [`run_node`]: each period the loop passes it the frames drained from the bus,
/// steps it and sends what it produced; at the stop it sends its shutdown frames. Times are
/// µs since the loop's start (the first clock reading). Hooks without a body do nothing.
pub trait Node {
    /// The node's own figures, [`LoopReport::node`].
    type Figures;

    /// The loop's period, µs (at least 1 is used).
    fn period_micros(&self) -> u64;

    /// A frame drained from the bus at the start of the period at `t_us`.
    fn on_frame(&mut self, t_us: u64, frame: &CanFrame);

    /// The period at `t_us`, after its frames: pushes the frames to send, in order, into `out`
    /// (empty).
    fn step(&mut self, t_us: u64, out: &mut Vec<CanFrame>);

    /// A frame of the period (or shutdown) at `step_us` was handed to the bus at `sent_us`
    /// (`sent`), or given up then (not `sent`).
    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, sent: bool) {
        let _ = (step_us, sent_us, frame, sent);
    }

    /// The period's frames are sent (or given up).
    fn step_done(&mut self) {}

    /// The link was lost or came back at `t_us` (see [The link](crate::run_recorded#the-link)).
    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        let _ = (t_us, event);
    }

    /// The loop stopped; `t_us` is at least 1 µs after the last period. Pushes the frames that
    /// leave the node safe into `out` (empty); they are sent within
    /// [`RunOptions::shutdown_budget_us`].
    fn shutdown(&mut self, t_us: u64, out: &mut Vec<CanFrame>) {
        let _ = (t_us, out);
    }

    /// The node's figures, once the shutdown frames are out.
    fn finish(self) -> Self::Figures;
}

/// Runs `node` on `bus` at its period until `stop` is non-zero or `options.duration_us` has
/// elapsed, then sends its shutdown frames. The schedule, the retries, the link and the
/// jitter are those of [`run_recorded`](crate::run_recorded), which documents them.
///
/// Bus errors are counted in the [`LoopReport`], never returned: the loop keeps running.
pub fn run_node<N: Node, B: Bus, C: Clock>(
    mut node: N,
    bus: &mut B,
    clock: &C,
    options: &RunOptions,
    stop: &AtomicUsize,
) -> LoopReport<N::Figures> {
    let period = node.period_micros().max(1);
    let start = clock.now_micros();
    let mut io = Io {
        bus,
        clock,
        options,
        start,
        counters: Counters::default(),
        link: Link::new(options),
    };
    let (mut jitter, mut step_time) = (LatencyHistogram::new(), LatencyHistogram::new());
    let (mut steps, mut last_step_us) = (0, None);
    let mut schedule = Schedule::new(start, period);
    let mut out = Vec::with_capacity(32);
    let stop_reason = loop {
        let deadline = schedule.deadline();
        if io.link.stop {
            break StopReason::LinkLost;
        }
        if let Some(n) = stop_requested(stop) {
            break StopReason::Signal(n);
        }
        if let Some(d) = options.duration_us
            && deadline - start >= d
        {
            break StopReason::Duration;
        }
        clock.sleep_until(deadline);
        // A signal that arrived during the sleep stops the loop now, not one period later.
        if let Some(n) = stop_requested(stop) {
            break StopReason::Signal(n);
        }
        let woke = clock.now_micros();
        jitter.record(schedule.woke(woke));
        let now_us = woke - start;
        io.link.maybe_reopen(io.bus, woke, now_us, &mut node);
        io.drain(&mut node, woke, now_us);
        out.clear();
        node.step(now_us, &mut out);
        last_step_us = Some(now_us);
        steps += 1;
        let give_up = deadline.max(woke).saturating_add(period / 2);
        io.send_step(&mut node, &out, now_us, give_up);
        step_time.record(clock.now_micros().saturating_sub(woke));
        node.step_done();
        schedule.advance();
    };
    let shutdown_us = (clock.now_micros() - start).max(last_step_us.map_or(0, |t| t + 1));
    io.shut_down(&mut node, &mut out, shutdown_us);
    let node = node.finish();
    let (link, link_error) = io.link.finish(clock.now_micros());
    let c = io.counters;
    LoopReport {
        stop: stop_reason,
        period_us: period,
        elapsed_us: clock.now_micros().saturating_sub(start),
        steps,
        overruns: schedule.overruns(),
        frames_received: c.frames_received,
        rx_errors: c.rx_errors,
        bus_error_frames: c.bus_error_frames,
        rx_capped_steps: c.rx_capped_steps,
        frames_sent: c.frames_sent,
        send_retries: c.send_retries,
        send_errors: c.send_errors,
        send_errors_by_kind: c.send_kinds,
        rx_errors_by_kind: c.rx_kinds,
        link,
        link_error,
        errors: c.errors,
        jitter: jitter.summary(),
        step_time: step_time.summary(),
        node,
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

/// The loop's side of the bus: the bus, the clock, the counters and the link.
struct Io<'a, B, C> {
    bus: &'a mut B,
    clock: &'a C,
    options: &'a RunOptions,
    /// The first clock reading.
    start: u64,
    counters: Counters,
    link: Link,
}

impl<B: Bus, C: Clock> Io<'_, B, C> {
    /// Passes every frame waiting (at most [`RunOptions::max_rx_per_step`]) to `node`, all
    /// stamped `now_us` (clock time `woke`).
    fn drain<N: Node>(&mut self, node: &mut N, woke: u64, now_us: u64) {
        let c = &mut self.counters;
        let mut drained = 0;
        while self.link.up() && drained < self.options.max_rx_per_step {
            match self.bus.try_recv() {
                Ok(Some(frame)) => {
                    node.on_frame(now_us, &frame);
                    c.frames_received += 1;
                    drained += 1;
                }
                Ok(None) => break,
                Err(e) if is_bus_error_frame(&e) => {
                    // A bus event, not a failed read: the frames behind it are due too.
                    c.bus_error_frames += 1;
                    c.errors.record(format_args!("receive"), &e);
                    drained += 1;
                }
                Err(e) => {
                    c.rx_errors += 1;
                    let kind = classify(&e);
                    c.rx_kinds.count(kind);
                    c.errors.record(format_args!("receive"), &e);
                    self.link.on_error(kind, woke, now_us, &c.errors, node);
                    break;
                }
            }
        }
        if drained == self.options.max_rx_per_step {
            c.rx_capped_steps += 1;
        }
    }

    /// Sends one frame, busy errors retried until `give_up`; a failure is counted by kind
    /// and recorded as `what`.
    fn send(&mut self, frame: &CanFrame, give_up: u64, what: &str) -> Result<(), ErrorKind> {
        let (backoff, c) = (self.options.retry_backoff_us, &mut self.counters);
        let sent = send_with_retry(
            self.bus,
            self.clock,
            frame,
            give_up,
            backoff,
            &mut c.send_retries,
        );
        sent.map_err(|e| {
            let kind = classify(&e);
            c.send_kinds.count(kind);
            c.errors
                .record(format_args!("{what} {}", id_text(frame)), &e);
            kind
        })
    }

    /// Sends the frames of the period at `now_us`, busy ones retried until `give_up`.
    fn send_step<N: Node>(&mut self, node: &mut N, out: &[CanFrame], now_us: u64, give_up: u64) {
        let (clock, start) = (self.clock, self.start);
        for frame in out {
            if !self.link.up() {
                self.link.report.frames_not_sent += 1;
                node.sent(now_us, clock.now_micros() - start, frame, false);
                continue;
            }
            match self.send(frame, give_up, "send") {
                Ok(()) => {
                    self.counters.frames_sent += 1;
                    node.sent(now_us, clock.now_micros() - start, frame, true);
                }
                Err(kind) => {
                    self.counters.send_errors += 1;
                    let t = clock.now_micros();
                    node.sent(now_us, t - start, frame, false);
                    self.link
                        .on_error(kind, t, now_us, &self.counters.errors, node);
                }
            }
        }
    }

    /// One more try of a lost link (the shutdown frames are the ones that matter most), then
    /// the node's shutdown frames, busy ones retried for [`RunOptions::shutdown_budget_us`].
    fn shut_down<N: Node>(&mut self, node: &mut N, out: &mut Vec<CanFrame>, t_us: u64) {
        let (clock, start) = (self.clock, self.start);
        if !self.link.up() {
            self.link.next_try = 0;
            self.link
                .maybe_reopen(self.bus, clock.now_micros(), t_us, node);
        }
        out.clear();
        node.shutdown(t_us, out);
        let give_up = clock
            .now_micros()
            .saturating_add(self.options.shutdown_budget_us);
        for frame in out.iter() {
            let sent = self.send(frame, give_up, "shutdown send").is_ok();
            node.sent(t_us, clock.now_micros() - start, frame, sent);
        }
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
    /// [`RunOptions::watch_link`].
    watch: bool,
    exit_on_loss: bool,
    /// The error of the last loss.
    error: Option<String>,
    /// Stop at the next period ([`RunOptions::exit_on_link_loss`]).
    stop: bool,
    report: LinkReport,
}

impl Link {
    fn new(options: &RunOptions) -> Self {
        let min_us = options.link_retry_min_us.max(1);
        Self {
            since: None,
            next_try: 0,
            backoff: 0,
            attempts: 0,
            min_us,
            max_us: options.link_retry_max_us.max(min_us),
            watch: options.watch_link,
            exit_on_loss: options.exit_on_link_loss,
            error: None,
            stop: false,
            report: LinkReport::default(),
        }
    }

    const fn up(&self) -> bool {
        self.since.is_none()
    }

    /// A bus error of `kind` at clock time `t` (core time `t_us`); `errors.last` describes it.
    fn on_error<N: Node>(
        &mut self,
        kind: ErrorKind,
        t: u64,
        t_us: u64,
        errors: &ErrorLog,
        node: &mut N,
    ) {
        let loss = matches!(kind, ErrorKind::LinkDown | ErrorKind::NoDevice);
        if !self.watch || !loss || !self.up() {
            return;
        }
        self.since = Some(t);
        self.backoff = self.min_us;
        self.next_try = t.saturating_add(self.backoff);
        self.attempts = 0;
        self.report.losses += 1;
        self.stop = self.exit_on_loss;
        let error = errors.last.as_deref().unwrap_or("link lost");
        node.link(t_us, LinkEvent::Lost { error });
        self.error = Some(error.to_string());
    }

    /// While the link is down, tries [`Bus::reopen`] when the back-off allows (clock time
    /// `t`, core time `t_us`).
    fn maybe_reopen<B: Bus + ?Sized, N: Node>(
        &mut self,
        bus: &mut B,
        t: u64,
        t_us: u64,
        node: &mut N,
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
            let attempts = self.attempts;
            node.link(t_us, LinkEvent::Restored { down_us, attempts });
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
