//! The control core in the fixed-rate loop ([`run`], [`run_recorded`]), what it tells a
//! [`Recorder`], and where it saves its parameters ([`ParamStore`]).

use core::sync::atomic::AtomicUsize;
use std::io;

use embedded_can::Frame as _;

use firmware::control::{Controller, Instant, SaveOutcome, Snapshot};
use firmware::{CanFrame, Config};

use crate::bus::{Bus, is_busy};
use crate::clock::Clock;
use crate::node::{Node, run_node};
use crate::report::{ControllerReport, CoreFigures, Report, ShutdownReport};

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
    /// Stop the loop on a link loss ([`StopReason::LinkLost`](crate::StopReason::LinkLost))
    /// instead of waiting for the link to come back. Default `false`.
    pub exit_on_link_loss: bool,
    /// Treat `ENETDOWN`, `ENODEV` and `ENXIO` as a link loss (see
    /// [The link](crate::run_recorded#the-link)). `false`: count them as any other error and
    /// go on reading and sending every period, as `hostsim plant` does. Default `true`.
    pub watch_link: bool,
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
            watch_link: true,
        }
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

    /// Before the step at `t_us`, [`Controller::on_saved`] was given `outcome`: the end of a
    /// parameter save (an input of the core, as a frame is).
    fn saved(&mut self, t_us: u64, outcome: SaveOutcome) {
        let _ = (t_us, outcome);
    }

    /// A step and its frames are done: the place to hand the records over.
    fn step_done(&mut self) {}
}

/// Where the loop saves the parameter set the core asks it to ([`Controller::take_save`]):
/// a file for the runner. The loop calls [`begin`](Self::begin) after the step that asked, and
/// [`poll`](Self::poll) before every step; neither may block it.
pub trait ParamStore {
    /// Starts storing `config`, saved under the built-in configuration's id `builtin_id`.
    ///
    /// # Errors
    /// How the save ended at once (refused), told to the core before the next step.
    fn begin(&mut self, config: &Config, builtin_id: u16) -> Result<(), SaveOutcome>;

    /// The end of the save being stored, once it has ended.
    fn poll(&mut self) -> Option<SaveOutcome>;
}

/// No store: every save is refused with `0x0800_0020` (data cannot be stored).
impl ParamStore for () {
    fn begin(&mut self, _: &Config, _: u16) -> Result<(), SaveOutcome> {
        Err(SaveOutcome::Failed {
            code: firmware::protocol::canopen::abort_code::NOT_STORED,
        })
    }

    fn poll(&mut self) -> Option<SaveOutcome> {
        None
    }
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
    run_recorded(controller, bus, clock, options, stop, &mut (), &mut ())
}

/// [`run`], telling `recorder` what the loop does and saving parameters to `store`.
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
/// [`Controller::period_micros`]; the [`Schedule`](crate::Schedule)). A deadline is never computed from the previous wake-up,
/// so lateness does not accumulate (no drift). For each step the loop:
///
/// 1. sleeps until the deadline, then reads the clock once: `now`;
/// 2. records the lateness `now - deadline` (see *Jitter*); when it exceeds one period the
///    step counts as an **overrun** and the schedule is re-anchored at `now`
///    (`start := now, k := 0`) instead of running a burst of catch-up steps;
/// 3. drains every frame waiting on the bus (non-blocking reads, at most
///    [`RunOptions::max_rx_per_step`]) into [`Controller::on_frame`], all stamped `now`;
/// 4. gives the core the end of a parameter save from `store` ([`ParamStore::poll`]), if one
///    ended, then runs [`Controller::step`] at `now` and sends its frames in order; a save the
///    step asked for is handed to `store` ([`ParamStore::begin`]).
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
/// [`Report::send_errors`](crate::LoopReport::send_errors). Any other error (interface down, ...) is counted at once. Nothing
/// on the bus ever stops the loop.
///
/// # The link
///
/// On a robot the interface itself fails: a USB adapter is unplugged, a cable breaks, the
/// link is set down. SocketCAN then reports `ENETDOWN` (the link is down: every send, and
/// one receive) or `ENODEV`/`ENXIO` (the device is gone: the socket stays dead even when a
/// device of the same name comes back). Either is a **link loss** ([`classify`](crate::classify)). The loop
/// keeps stepping the core at its rate, so the watchdog and the state machine see the silence
/// as it is (no motor feedback: the core faults and stays faulted until a reset and a new
/// enable, as for any other loss of its motors); it stops reading and sending, counts the
/// frames it did not send ([`LinkReport::frames_not_sent`](crate::LinkReport::frames_not_sent)) and tries [`Bus::reopen`] with an
/// exponential back-off ([`RunOptions::link_retry_min_us`] doubling up to
/// [`RunOptions::link_retry_max_us`]). The first reopen that succeeds resumes reading and
/// sending; the gap is in [`Report::link`](crate::LoopReport::link) and told to the [`Recorder`] ([`LinkEvent`]) as
/// it happens. With [`RunOptions::exit_on_link_loss`] the loop stops instead
/// ([`StopReason::LinkLost`](crate::StopReason::LinkLost)). Errors are counted by kind ([`ErrorCounts`](crate::ErrorCounts)) for sends and
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
/// in a fixed-size [`LatencyHistogram`](crate::LatencyHistogram) (exact below 2048 µs, within 0.1 % above), so a run
/// of any length uses the same memory; [`Report::jitter`](crate::LoopReport::jitter) has its p50, p99 and maximum. The
/// time from wake-up to the last frame sent is recorded the same way
/// ([`Report::step_time`](crate::LoopReport::step_time)).
pub fn run_recorded<B: Bus, C: Clock, R: Recorder + ?Sized>(
    controller: &mut Controller,
    bus: &mut B,
    clock: &C,
    options: &RunOptions,
    stop: &AtomicUsize,
    recorder: &mut R,
    store: &mut dyn ParamStore,
) -> Report {
    let core = Core {
        controller,
        recorder,
        store,
        refused: None,
        at_stop: None,
        shutdown: ShutdownReport {
            frames: 0,
            sent: 0,
            failed: 0,
        },
    };
    run_node(core, bus, clock, options, stop)
}

/// The control core as a [`Node`] of the loop, telling its [`Recorder`].
struct Core<'a, R: ?Sized> {
    controller: &'a mut Controller,
    recorder: &'a mut R,
    store: &'a mut dyn ParamStore,
    /// A save the store refused at once, told to the core before the next step.
    refused: Option<SaveOutcome>,
    /// The controller when the loop stopped, before its shutdown.
    at_stop: Option<Snapshot>,
    shutdown: ShutdownReport,
}

impl<R: Recorder + ?Sized> Node for Core<'_, R> {
    type Figures = CoreFigures;

    fn period_micros(&self) -> u64 {
        self.controller.period_micros()
    }

    fn on_frame(&mut self, t_us: u64, frame: &CanFrame) {
        self.controller.on_frame(Instant::from_micros(t_us), frame);
        self.recorder.received(t_us, frame);
    }

    fn step(&mut self, t_us: u64, out: &mut Vec<CanFrame>) {
        if let Some(outcome) = self.refused.take().or_else(|| self.store.poll()) {
            self.controller.on_saved(outcome);
            self.recorder.saved(t_us, outcome);
        }
        out.extend(self.controller.step(Instant::from_micros(t_us)));
        self.recorder.stepped(t_us, self.controller);
        if let Some(config) = self.controller.take_save() {
            self.refused = self
                .store
                .begin(&config, self.controller.builtin_id())
                .err();
        }
    }

    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, sent: bool) {
        if self.at_stop.is_some() && sent {
            self.shutdown.sent += 1;
        }
        self.recorder.sent(step_us, sent_us, frame, sent);
    }

    fn step_done(&mut self) {
        self.recorder.step_done();
    }

    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        self.recorder.link(t_us, event);
    }

    fn shutdown(&mut self, t_us: u64, out: &mut Vec<CanFrame>) {
        self.at_stop = Some(self.controller.snapshot());
        out.extend(self.controller.shutdown());
        self.shutdown.frames = out.len();
        self.recorder.shut_down(t_us, self.controller);
    }

    fn finish(self) -> CoreFigures {
        self.recorder.step_done();
        let c = self.controller;
        let at_stop = self.at_stop.unwrap_or_else(|| c.snapshot());
        let after = c.snapshot();
        let shutdown = ShutdownReport {
            failed: self.shutdown.frames - self.shutdown.sent,
            ..self.shutdown
        };
        let controller = ControllerReport {
            state_at_stop: at_stop.state.as_str(),
            fault_at_stop: at_stop.fault.as_str(),
            state_after_shutdown: after.state.as_str(),
            steps: after.steps,
            motors_online: at_stop.motors_online,
            rx_errors: at_stop.rx_errors,
            repeated_seq: at_stop.repeated_seq,
            drive_issue: c.drive_issue().map(|i| i.to_string()),
            drive_emcy: c.drive_emcy_count(),
        };
        CoreFigures {
            shutdown,
            controller,
        }
    }
}
