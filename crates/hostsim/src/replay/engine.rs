//! The replay engine: a fresh core on the logged inbound frames, stepped at the logged steps
//! (a runner's log) or on the period grid, its outbound frames compared with the logged ones.

use std::ops::ControlFlow;
use std::path::Path;

use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant};

use drivelog::ReadReport;

use super::*;

/// Why [`replay_frames`] or [`replay_split`] could not run.
#[derive(Debug, thiserror::Error)]
pub enum ReplayRunError {
    /// The firmware refuses the configuration.
    #[error("configuration refused: {0}")]
    Config(#[from] firmware::config::ConfigError),
    /// The frames' time line has a gap longer than [`MAX_GAP_NS`].
    #[error(transparent)]
    TimeGap(#[from] TimeGap),
}

/// The first frame where the replay and the log differ.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Difference {
    /// Index in the outbound stream.
    pub index: usize,
    /// Step time, ns.
    pub t_ns: u64,
    /// What the log has (None: the log ended).
    pub logged: Option<TimedFrame>,
    /// What the replay sent (None: the replay sent nothing more).
    pub replayed: Option<TimedFrame>,
}

/// The outcome of a replay.
#[derive(Debug, Clone)]
pub struct ReplayReport {
    /// Outbound frames compared.
    pub compared: usize,
    /// Inbound frames fed.
    pub fed: usize,
    /// Steps run.
    pub steps: u64,
    /// The first difference, if any.
    pub difference: Option<Difference>,
    /// What was read from the log, and where it is damaged if it is ([`replay_mcap`] sets it;
    /// a damaged log is replayed up to the time of its last message, see `docs/simulator.md`,
    /// section "Replay", "Damaged logs").
    pub read: Option<ReadReport>,
}

impl ReplayReport {
    /// `true` if every outbound frame matched, bit for bit, at the same step.
    #[must_use]
    pub fn identical(&self) -> bool {
        self.difference.is_none()
    }
}

/// Replays a hostsim MCAP log through a fresh firmware core: the whole log if it is intact,
/// else its complete part (see `docs/simulator.md`, section "Replay", "Damaged logs").
///
/// # Errors
/// [`ReplayError`] if the log cannot be read, has no usable configuration, or has a gap in
/// its time line longer than [`MAX_GAP_NS`].
pub fn replay_mcap(path: &Path) -> Result<ReplayReport, ReplayError> {
    let log = open_mcap(path)?;
    let inputs = Inputs {
        rx: &log.rx,
        saves: &log.content.saves,
    };
    let booted = match &log.builtin {
        None => Controller::new(&log.config),
        Some((builtin, seq)) => {
            Controller::new(builtin).and_then(|ctl| ctl.with_saved(&log.config, *seq))
        }
    };
    let replayed = booted.map_err(ReplayRunError::from).and_then(|ctl| {
        let period_ns = ctl.period_micros() * 1000;
        let schedule = step_schedule(period_ns, &log.rx, &log.tx, &log.steps)?;
        Ok(replay_schedule(ctl, inputs, &log.tx, schedule))
    });
    let mut report = replayed.map_err(|e| match e {
        ReplayRunError::Config(source) => ReplayError::Refused {
            path: path.to_path_buf(),
            source,
        },
        ReplayRunError::TimeGap(source) => ReplayError::TimeGap {
            path: path.to_path_buf(),
            source,
        },
    })?;
    report.read = Some(log.content.read);
    Ok(report)
}

/// Runs the core on `rx` and compares its output with `tx`. Steps run every period from 0
/// through the last logged time.
///
/// # Errors
/// [`ReplayRunError`] if the firmware refuses `config`, or if the frames' time line has a
/// gap longer than [`MAX_GAP_NS`] ([`check_time_gaps`]).
pub fn replay_frames(
    config: &Config,
    rx: &[TimedFrame],
    tx: &[TimedFrame],
) -> Result<ReplayReport, ReplayRunError> {
    let ctl = Controller::new(config)?;
    let grid = step_schedule(ctl.period_micros() * 1000, rx, tx, &[])?;
    Ok(replay_schedule(ctl, Inputs { rx, saves: &[] }, tx, grid))
}

/// Runs the core on `rx` and compares its output with `tx`, stepping at the recorded
/// `steps` (a runner's log, see `docs/simulator.md`, section "Replay", "Logs of
/// `mecanum-runner`").
///
/// # Errors
/// [`ReplayRunError`] if the firmware refuses `config`.
pub fn replay_at_steps(
    config: &Config,
    rx: &[TimedFrame],
    tx: &[TimedFrame],
    steps: &[StepTime],
) -> Result<ReplayReport, ReplayRunError> {
    let ctl = Controller::new(config)?;
    let inputs = Inputs { rx, saves: &[] };
    Ok(replay_schedule(ctl, inputs, tx, steps.iter().copied()))
}

/// Feeds `rx` to `ctl` and steps it at `schedule`, comparing its frames with `tx`.
fn replay_schedule(
    mut ctl: Controller,
    inputs: Inputs<'_>,
    tx: &[TimedFrame],
    schedule: impl Iterator<Item = StepTime>,
) -> ReplayReport {
    let mut out_index = 0;
    let mut steps = 0;
    let mut difference = None;
    let fed = run_schedule(
        &mut ctl,
        inputs,
        schedule,
        |StepTime { t_ns, .. }, sent, _| {
            for &frame in sent {
                let replayed = TimedFrame { t_ns, frame };
                let logged = tx.get(out_index).copied();
                if logged != Some(replayed) {
                    difference = Some(Difference {
                        index: out_index,
                        t_ns,
                        logged,
                        replayed: Some(replayed),
                    });
                    return ControlFlow::Break(());
                }
                out_index += 1;
            }
            // The log has a frame of this step (or earlier) that the replay did not send.
            if let Some(&logged) = tx.get(out_index)
                && logged.t_ns <= t_ns
            {
                difference = Some(Difference {
                    index: out_index,
                    t_ns: logged.t_ns,
                    logged: Some(logged),
                    replayed: None,
                });
                return ControlFlow::Break(());
            }
            steps += 1;
            ControlFlow::Continue(())
        },
    );
    if difference.is_none() && out_index < tx.len() {
        difference = Some(Difference {
            index: out_index,
            t_ns: tx[out_index].t_ns,
            logged: Some(tx[out_index]),
            replayed: None,
        });
    }
    ReplayReport {
        compared: out_index,
        fed,
        steps,
        difference,
        read: None,
    }
}

/// The steps of a replay of `rx` against `tx`: the recorded `steps` (a runner's log), or
/// without records one every `period_ns` from 0 through the last logged frame (the grid the
/// simulator stepped on), after [`check_time_gaps`] on the frames.
pub(crate) fn step_schedule<'a>(
    period_ns: u64,
    rx: &[TimedFrame],
    tx: &[TimedFrame],
    steps: &'a [StepTime],
) -> Result<Box<dyn Iterator<Item = StepTime> + 'a>, TimeGap> {
    if !steps.is_empty() {
        return Ok(Box::new(steps.iter().copied()));
    }
    check_time_gaps(rx.iter().chain(tx))?;
    let end_ns = rx.iter().chain(tx).map(|f| f.t_ns).max().unwrap_or(0);
    Ok(Box::new(
        std::iter::successors(Some(0u64), move |t| t.checked_add(period_ns))
            .take_while(move |&t| t <= end_ns)
            .map(|t_ns| StepTime {
                t_ns,
                shutdown: false,
            }),
    ))
}

/// A log's inputs to its core: the frames it received and the ends of the saves its edge
/// reported.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Inputs<'a> {
    /// `/can/rx`, in log time order.
    pub rx: &'a [TimedFrame],
    /// `/firmware/store`, in log time order.
    pub saves: &'a [TimedSave],
}

/// The replay loop, the one place where a log's inputs meet a core: before each step of
/// `schedule`, feeds `ctl` the frames of `rx` logged at or before the step's time (each at
/// its own logged time) and, as the edge did before that step, takes the save it asked for
/// and gives it the ends of saves logged by then; runs the step (or the shutdown), and
/// passes `on_step` the step, the frames it sent in [`wire_order`] and the core after it.
/// Stops at the end of the schedule or when `on_step` breaks. Returns the number of inbound
/// frames fed.
pub(crate) fn run_schedule(
    ctl: &mut Controller,
    inputs: Inputs<'_>,
    schedule: impl Iterator<Item = StepTime>,
    mut on_step: impl FnMut(StepTime, &[CanFrame], &Controller) -> ControlFlow<()>,
) -> usize {
    let (mut next_rx, mut next_save) = (0, 0);
    let mut sent: Vec<CanFrame> = Vec::new();
    for step in schedule {
        while let Some(f) = inputs.rx.get(next_rx)
            && f.t_ns <= step.t_ns
        {
            ctl.on_frame(Instant::from_micros(f.t_ns / 1000), &f.frame);
            next_rx += 1;
        }
        let _ = ctl.take_save();
        while let Some(s) = inputs.saves.get(next_save)
            && s.t_ns <= step.t_ns
        {
            ctl.on_saved(s.outcome);
            next_save += 1;
        }
        let out = if step.shutdown {
            ctl.shutdown()
        } else {
            ctl.step(Instant::from_micros(step.t_ns / 1000))
        };
        sent.clear();
        sent.extend(out.iter().copied());
        sent.sort_by_key(wire_order);
        if on_step(step, &sent, ctl).is_break() {
            break;
        }
    }
    next_rx
}
