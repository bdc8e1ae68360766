//! Replay: run the firmware core again on a log's inbound frames and check that it sends the
//! same frames, bit for bit.
//!
//! [`replay_mcap`] replays an MCAP log ([`crate::log`]) through a fresh [`Controller`] built
//! from the logged configuration and returns a [`ReplayReport`] with the first difference, if
//! any; [`replay_frames`] and [`replay_at_steps`] do the same on frames already read. A
//! candump log ([`replay_candump`]) is split into the two directions with [`split_candump`]
//! and replayed with [`replay_split`], which also compares the odometry ([`CandumpReplay`]).
//! [`check_time_gaps`] bounds the work.
//!
//! How frames and steps are ordered, how a `mecanum-runner` log and a candump log replay,
//! what of a damaged log is replayed and why gaps are refused: `docs/simulator.md`, section
//! "Replay".

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant};
use serde::Serialize;

use crate::log::{Damage, ReadReport};

/// A frame with its log time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TimedFrame {
    /// Log time, ns of simulated time.
    pub t_ns: u64,
    /// The frame.
    pub frame: CanFrame,
}

/// A recorded step of a runner: when, and whether it was the shutdown.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepTime {
    /// The time passed to the core, ns.
    pub t_ns: u64,
    /// `Controller::shutdown` rather than `Controller::step`.
    pub shutdown: bool,
}

/// What a log holds for replay.
#[derive(Debug, Clone, Default)]
pub struct LogContent {
    /// The configuration TOML from the metadata, if any.
    pub config: Option<String>,
    /// Scenario name from the metadata.
    pub scenario: Option<String>,
    /// The program that wrote the log, from the metadata (`hostsim run`, [`PLANT_PROGRAM`]).
    pub program: Option<String>,
    /// Frames the firmware received.
    pub rx: Vec<TimedFrame>,
    /// Frames the firmware sent, at the step that sent them, in [`wire_order`].
    pub tx: Vec<TimedFrame>,
    /// The recorded steps (`/firmware/steps`, a runner's log; empty for the simulator's).
    pub steps: Vec<StepTime>,
    /// The longest a sent frame took from its step to the end of its transmission, among
    /// those read, ns.
    pub tx_lag_ns: u64,
    /// Messages per topic.
    pub topics: std::collections::BTreeMap<String, u64>,
    /// What the reader read, and where the log is damaged if it is.
    pub read: ReadReport,
}

/// Why a log could not be replayed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The log file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Not an MCAP file, or unreadable from the start.
    #[error("{path}: not a readable MCAP file: {reason}")]
    NotMcap {
        /// The log file.
        path: PathBuf,
        /// The reader's error.
        reason: String,
    },
    /// A log in the JSON layout of earlier versions, which this version does not read.
    #[error("{path}: {}", OLD_LAYOUT)]
    OldLayout {
        /// The log file.
        path: PathBuf,
    },
    /// The log has no configuration to rebuild the firmware from.
    #[error(
        "{path}: no `mecanum_drive` metadata with a `config` entry (was it written by hostsim or \
         mecanum-runner?)"
    )]
    NoConfig {
        /// The log file.
        path: PathBuf,
    },
    /// The logged configuration does not load.
    #[error("{path}: logged configuration: {source}")]
    Config {
        /// The log file.
        path: PathBuf,
        /// The error.
        source: Box<firmware::config::LoadError>,
    },
    /// The logged configuration is refused by the firmware.
    #[error("{path}: logged configuration: {source}")]
    Refused {
        /// The log file.
        path: PathBuf,
        /// The error.
        source: firmware::config::ConfigError,
    },
    /// The log's time line has a gap too long to replay.
    #[error("{path}: {source}")]
    TimeGap {
        /// The log file.
        path: PathBuf,
        /// The gap.
        source: TimeGap,
    },
    /// No firmware frame to compare with: a log of `hostsim plant` (the bus only, no
    /// `/can/rx` or `/can/tx`), or a log cut short before its first complete step.
    #[error("{path}: nothing to replay: {why}")]
    NothingToReplay {
        /// The log file.
        path: PathBuf,
        /// Which of the two it is.
        why: &'static str,
    },
}

/// Longest silence replay accepts between two consecutive frames of a log (in time order),
/// and between the log's start and its first frame, ns: 60 s. A running core sends its
/// heartbeat every 100 ms and the drives report at up to 1 kHz, so a longer silence is a
/// corrupt timestamp (or a capture across a stopped bus, which replay cannot follow anyway).
pub const MAX_GAP_NS: u64 = 60_000_000_000;

/// A jump in a log's time line longer than [`MAX_GAP_NS`]; see [`check_time_gaps`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "the log's time jumps from {:.6} s to {:.6} s (frame {frame} at {:.6} s): more than the \
     {} s replay accepts between two frames; a corrupt timestamp?",
    *from_ns as f64 * 1e-9,
    *to_ns as f64 * 1e-9,
    *to_ns as f64 * 1e-9,
    MAX_GAP_NS / 1_000_000_000
)]
pub struct TimeGap {
    /// Time before the gap (the previous frame, or the start), ns.
    pub from_ns: u64,
    /// Time after the gap, ns.
    pub to_ns: u64,
    /// The frame after the gap, in candump notation.
    pub frame: String,
}

/// Checks that `frames`, taken in time order, are at most [`MAX_GAP_NS`] apart, the first at
/// most that long after time 0. Bounds the work of [`replay_frames`], [`replay_split`] and a
/// playback to [`MAX_GAP_NS`] of log time per frame.
///
/// # Errors
/// The first [`TimeGap`] found.
pub fn check_time_gaps<'a>(
    frames: impl IntoIterator<Item = &'a TimedFrame>,
) -> Result<(), TimeGap> {
    let mut sorted: Vec<&TimedFrame> = frames.into_iter().collect();
    sorted.sort_by_key(|f| f.t_ns);
    let mut previous = 0;
    for f in sorted {
        if f.t_ns - previous > MAX_GAP_NS {
            return Err(TimeGap {
                from_ns: previous,
                to_ns: f.t_ns,
                frame: drivelog::candump::format_frame(&f.frame),
            });
        }
        previous = f.t_ns;
    }
    Ok(())
}

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

/// Reads the frames and configuration of a hostsim MCAP log.
///
/// # Errors
/// [`ReplayError`] if the file cannot be read or nothing in it is readable. A damaged file is
/// not an error: [`LogContent::read`] says where the damage is.
pub fn read_log(path: &Path) -> Result<LogContent, ReplayError> {
    let bytes = std::fs::read(path).map_err(|source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let content = read_log_bytes(&bytes).map_err(|damage| ReplayError::NotMcap {
        path: path.to_path_buf(),
        reason: damage.to_string(),
    })?;
    if is_old_layout(&content.read) {
        return Err(ReplayError::OldLayout {
            path: path.to_path_buf(),
        });
    }
    Ok(content)
}

/// What a log in the earlier JSON layout is, in one line.
pub const OLD_LAYOUT: &str = "a log in the JSON layout of hostsim before its logs became ROS 2 \
     bags (MCAP profile `ros2`, CDR messages); this version reads only the new layout: record \
     the run again";

/// `true` for a log in the JSON layout of earlier versions: MCAP without the `ros2` profile.
#[must_use]
pub fn is_old_layout(read: &ReadReport) -> bool {
    read.profile != crate::log::PROFILE
}

/// The order in which a node's frames queued together leave on the bus: the one with the
/// lower arbitration field first (a standard id before the extended ids that share its top 11
/// bits), in queueing order among equals. [`read_log_bytes`] sorts the sent frames by their
/// step and then this; [`replay_frames`] sorts each step's frames by this.
#[must_use]
pub fn wire_order(frame: &CanFrame) -> u64 {
    use embedded_can::{Frame as _, Id};
    match frame.id() {
        Id::Standard(id) => u64::from(id.as_raw()) << 19,
        Id::Extended(id) => {
            (u64::from(id.as_raw() >> 18) << 19) | (1 << 18) | u64::from(id.as_raw() & 0x3FFFF)
        }
    }
}

/// As [`read_log`], from bytes.
///
/// # Errors
/// The [`Damage`] at the start if nothing is readable (not an MCAP file).
pub fn read_log_bytes(bytes: &[u8]) -> Result<LogContent, Damage> {
    use crate::log::msg::{Frame, decode};
    let mut content = LogContent::default();
    let mut config = None;
    let mut scenario = None;
    let mut program = None;
    let read = crate::log::for_each_message(
        bytes,
        |m| {
            *content.topics.entry(m.topic.to_string()).or_default() += 1;
            let (list, t_ns) = match m.topic {
                "/firmware/steps" => {
                    if let Ok(step) = decode::<crate::log::msg::Step>(m.data) {
                        content.steps.push(StepTime {
                            t_ns: m.log_time,
                            shutdown: step.kind == crate::log::msg::Step::SHUTDOWN,
                        });
                    }
                    return;
                }
                "/can/rx" => (&mut content.rx, m.log_time),
                "/can/tx" => {
                    let lag = m.log_time.saturating_sub(m.publish_time);
                    content.tx_lag_ns = content.tx_lag_ns.max(lag);
                    (&mut content.tx, m.publish_time)
                }
                _ => return,
            };
            if let Some(frame) = decode::<Frame>(m.data).ok().and_then(|f| f.to_can()) {
                list.push(TimedFrame { t_ns, frame });
            }
        },
        |name, kv| {
            if name == crate::log::METADATA_NAME {
                config = kv.get("config").cloned();
                scenario = kv.get("scenario").cloned();
                program = kv.get("program").cloned();
            }
        },
    )?;
    // Stable: frames of one step with equal arbitration fields keep their logged order.
    content.tx.sort_by_key(|f| (f.t_ns, wire_order(&f.frame)));
    content.config = config;
    content.scenario = scenario;
    content.program = program;
    content.read = read;
    Ok(content)
}

/// The `program` metadata of `hostsim plant`'s logs.
pub const PLANT_PROGRAM: &str = "hostsim plant";

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
    let replayed = if log.steps.is_empty() {
        replay_frames(&log.config, &log.rx, &log.tx)
    } else {
        replay_at_steps(&log.config, &log.rx, &log.tx, &log.steps)
    };
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

/// An MCAP log ready to replay: what [`read_log`] read, the logged configuration and the
/// [`complete_part`] of its frames and steps.
#[derive(Debug, Clone)]
pub struct McapReplayInput {
    /// Everything read from the log.
    pub content: LogContent,
    /// The logged configuration, loaded and validated.
    pub config: Config,
    /// The inbound frames to feed.
    pub rx: Vec<TimedFrame>,
    /// The outbound frames to compare with.
    pub tx: Vec<TimedFrame>,
    /// The recorded steps (empty: step on the period grid).
    pub steps: Vec<StepTime>,
}

/// Reads an MCAP log for replay ([`replay_mcap`], [`crate::whatif::what_if_mcap`]): its
/// configuration and the complete part of its frames.
///
/// # Errors
/// [`ReplayError`] if the log cannot be read, has no usable configuration, is a log of
/// `hostsim plant`, or has no firmware frames.
pub fn open_mcap(path: &Path) -> Result<McapReplayInput, ReplayError> {
    let content = read_log(path)?;
    let text = content
        .config
        .as_deref()
        .ok_or_else(|| ReplayError::NoConfig {
            path: path.to_path_buf(),
        })?;
    let config = Config::from_toml_str(text).map_err(|source| ReplayError::Config {
        path: path.to_path_buf(),
        source: Box::new(source),
    })?;
    if content.program.as_deref() == Some(PLANT_PROGRAM) {
        return Err(ReplayError::NothingToReplay {
            path: path.to_path_buf(),
            why: "a log of `hostsim plant`, which stamps the firmware's frames when the plant \
                  saw them on the interface, not at the firmware's steps: replay the firmware's \
                  own log, or a candump capture of the interface (`candump -L`)",
        });
    }
    let (rx, tx, steps) = complete_part(&content);
    if rx.is_empty() && tx.is_empty() {
        let logged = |topic: &str| content.topics.get(topic).is_some_and(|&n| n > 0);
        return Err(ReplayError::NothingToReplay {
            path: path.to_path_buf(),
            why: if logged("/can/rx") || logged("/can/tx") {
                "the log was cut short before its first complete step"
            } else {
                "the log holds no CAN frames"
            },
        });
    }
    Ok(McapReplayInput {
        content,
        config,
        rx,
        tx,
        steps,
    })
}

/// The frames of a log to replay: all of an intact log's, and of one whose every message was
/// read (damage after the data section, in the summary); of a log cut short, those before
/// its cut-off (see `docs/simulator.md`, section "Replay", "Damaged logs").
#[must_use]
pub fn complete_part(content: &LogContent) -> (Vec<TimedFrame>, Vec<TimedFrame>, Vec<StepTime>) {
    let read = &content.read;
    let cut_off = read
        .last_time_ns
        .map(|last| last.saturating_sub(content.tx_lag_ns));
    let keep =
        |t_ns: u64| read.is_complete() || read.data_complete || cut_off.is_some_and(|c| t_ns < c);
    (
        content
            .rx
            .iter()
            .filter(|f| keep(f.t_ns))
            .copied()
            .collect(),
        content
            .tx
            .iter()
            .filter(|f| keep(f.t_ns))
            .copied()
            .collect(),
        content
            .steps
            .iter()
            .filter(|s| keep(s.t_ns))
            .copied()
            .collect(),
    )
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
    Ok(replay_schedule(ctl, rx, tx, grid))
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
    Ok(replay_schedule(ctl, rx, tx, steps.iter().copied()))
}

/// Feeds `rx` to `ctl` and steps it at `schedule`, comparing its frames with `tx`.
fn replay_schedule(
    mut ctl: Controller,
    rx: &[TimedFrame],
    tx: &[TimedFrame],
    schedule: impl Iterator<Item = StepTime>,
) -> ReplayReport {
    let mut out_index = 0;
    let mut steps = 0;
    let mut difference = None;
    let fed = run_schedule(&mut ctl, rx, schedule, |StepTime { t_ns, .. }, sent, _| {
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
    });
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

/// The replay loop, the one place where a log's inbound frames meet a core: before each
/// step of `schedule`, feeds `ctl` the frames of `rx` logged at or before the step's time
/// (each at its own logged time), runs the step (or the shutdown), and passes `on_step` the
/// step, the frames it sent in [`wire_order`] and the core after it. Stops at the end of
/// the schedule or when `on_step` breaks. Returns the number of inbound frames fed.
pub(crate) fn run_schedule(
    ctl: &mut Controller,
    rx: &[TimedFrame],
    schedule: impl Iterator<Item = StepTime>,
    mut on_step: impl FnMut(StepTime, &[CanFrame], &Controller) -> ControlFlow<()>,
) -> usize {
    let mut next_rx = 0;
    let mut sent: Vec<CanFrame> = Vec::new();
    for step in schedule {
        while let Some(f) = rx.get(next_rx)
            && f.t_ns <= step.t_ns
        {
            ctl.on_frame(Instant::from_micros(f.t_ns / 1000), &f.frame);
            next_rx += 1;
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

// ---------------------------------------------------------------------------------------------
// candump logs

/// The two log formats `hostsim replay` reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LogFormat {
    /// A hostsim MCAP log (configuration, `/can/rx`, `/can/tx`).
    Mcap,
    /// A candump log (`candump -L`): every frame on the bus, both directions mixed.
    Candump,
}

/// The format of the log at `path`: the MCAP magic decides; else a `.log` or `.candump`
/// extension, or content starting like a candump line, means candump; anything else is
/// treated as MCAP (whose reader then says what is wrong).
///
/// # Errors
/// [`ReplayError::Io`] if the file cannot be read.
pub fn detect_format(path: &Path) -> Result<LogFormat, ReplayError> {
    use std::io::Read as _;
    let io = |source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut head = Vec::with_capacity(64);
    std::fs::File::open(path)
        .map_err(io)?
        .take(64)
        .read_to_end(&mut head)
        .map_err(io)?;
    if head.starts_with(b"\x89MCAP") {
        return Ok(LogFormat::Mcap);
    }
    let by_extension = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("log") || e.eq_ignore_ascii_case("candump"));
    if by_extension || drivelog::candump::looks_like_candump(&head) {
        Ok(LogFormat::Candump)
    } else {
        Ok(LogFormat::Mcap)
    }
}

/// Whether the firmware configured by `config` sends `frame` (as opposed to receiving it):
/// the drive's command frames (DJI current commands `0x200`/`0x1FF` of a group that holds
/// a configured ESC, for a DJI configuration; ODrive commands to a configured node for an
/// ODrive configuration) and
/// the robot's telemetry (`ODOM_POSITION`, `ODOM_VELOCITY`, `STATUS`, `HEARTBEAT`), each
/// only if it decodes with the firmware's codec. Everything else on the bus (motor
/// feedback, host commands, other nodes' traffic, malformed frames) is something the
/// firmware receives.
#[must_use]
pub fn firmware_sends(config: &Config, frame: &CanFrame) -> bool {
    use firmware::config::Drive;
    use firmware::protocol::{dji, odrive, robot};
    if robot::Telemetry::decode(frame).is_ok() {
        return true;
    }
    match config.drive {
        // Only the command frames of the groups this robot's ESCs are in: another board may
        // drive ESCs 5-8 on the same bus.
        Drive::Dji { model, esc_ids, .. } => {
            dji::CurrentCommand::decode(frame, model).is_ok_and(|c| {
                esc_ids
                    .iter()
                    .filter_map(|&id| dji::EscId::new(id))
                    .any(|id| id.group() == c.group)
            })
        }
        Drive::Odrive { node_ids, .. } => {
            odrive::Command::decode(frame).is_ok_and(|c| node_ids.contains(&c.node.get()))
        }
    }
}

/// A candump log split by direction, times relative to its first frame.
#[derive(Debug, Clone, Default)]
pub struct SplitLog {
    /// Frames the firmware received.
    pub rx: Vec<TimedFrame>,
    /// Frames the firmware sent.
    pub tx: Vec<TimedFrame>,
    /// Every frame, in log order.
    pub all: Vec<TimedFrame>,
    /// Absolute time of the first frame, ns.
    pub t0_ns: u64,
    /// Interfaces seen, in order of first appearance.
    pub interfaces: Vec<String>,
}

/// Splits candump entries with [`firmware_sends`]. Entries are taken in time order (a
/// stable sort, for logs merged from several captures); all interfaces are taken as one bus.
#[must_use]
pub fn split_candump(config: &Config, entries: &[drivelog::candump::Entry]) -> SplitLog {
    let mut order: Vec<&drivelog::candump::Entry> = entries.iter().collect();
    order.sort_by_key(|e| e.t_ns);
    let t0_ns = order.first().map_or(0, |e| e.t_ns);
    let mut split = SplitLog {
        t0_ns,
        ..SplitLog::default()
    };
    for e in order {
        if !split.interfaces.contains(&e.iface) {
            split.interfaces.push(e.iface.clone());
        }
        let f = TimedFrame {
            t_ns: e.t_ns - t0_ns,
            frame: e.frame,
        };
        split.all.push(f);
        if firmware_sends(config, &e.frame) {
            split.tx.push(f);
        } else {
            split.rx.push(f);
        }
    }
    split
}

/// Tolerances of the odometry comparison of a candump replay.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OdometryTolerance {
    /// Largest position difference, m. Default 0.01.
    pub position_m: f64,
    /// Largest heading difference, rad. Default 0.01.
    pub heading_rad: f64,
}

impl Default for OdometryTolerance {
    fn default() -> Self {
        Self {
            position_m: 0.01,
            heading_rad: 0.01,
        }
    }
}

/// An odometry reading: pose and body velocity at a time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OdometryReading {
    /// Time since the log's first frame, s.
    pub t_s: f64,
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub heading: f64,
    /// Forward velocity, m/s.
    pub vx: f64,
    /// Leftward velocity, m/s.
    pub vy: f64,
    /// Yaw rate, rad/s.
    pub wz: f64,
}

/// The logged odometry against the replayed core's.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OdometryComparison {
    /// The last logged `ODOM_POSITION` (x, y) and `ODOM_VELOCITY` (heading, velocity),
    /// decoded with the robot codec; `t_s` is the `ODOM_POSITION` frame's time.
    pub logged: OdometryReading,
    /// The replayed core at its last step at or before `logged.t_s`.
    pub replayed: OdometryReading,
    /// Distance between the two positions, m.
    pub position_error_m: f64,
    /// Heading difference (wrapped), rad.
    pub heading_error_rad: f64,
    /// Largest velocity component difference, m/s or rad/s (reported, not judged).
    pub velocity_error: f64,
    /// The tolerances applied.
    pub tolerance: OdometryTolerance,
    /// Position and heading within the tolerances.
    pub agrees: bool,
}

/// A frame in a report: candump text and time since the log's first frame.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ReportFrame {
    /// Time since the log's first frame (replayed: the step time), s.
    pub t_s: String,
    /// The frame in candump notation.
    pub frame: String,
}

impl ReportFrame {
    pub(crate) fn new(f: &TimedFrame) -> Self {
        Self {
            t_s: format!("{:.6}", f.t_ns as f64 * 1e-9),
            frame: drivelog::candump::format_frame(&f.frame),
        }
    }
}

/// The first difference between the logged and the replayed outbound streams (time
/// ignored).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct StreamDifference {
    /// Index in the outbound stream.
    pub index: usize,
    /// What the log has (`None`: the log has no more).
    pub logged: Option<ReportFrame>,
    /// What the replay sent (`None`: the replay sent no more).
    pub replayed: Option<ReportFrame>,
}

/// The outcome of a candump replay. Serialises to the JSON of `hostsim replay --json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CandumpReplay {
    /// Interfaces in the log.
    pub interfaces: Vec<String>,
    /// Frames in the log.
    pub frames: usize,
    /// Frames the firmware received (fed to the replay).
    pub received: usize,
    /// Frames the firmware sent (compared).
    pub sent: usize,
    /// Control period, µs.
    pub period_us: u64,
    /// Steps run.
    pub steps: u64,
    /// From the first to the last frame, s.
    pub duration_s: f64,
    /// Frames the replayed core sent.
    pub replayed: usize,
    /// Leading outbound frames that are equal, time ignored.
    pub matching_prefix: usize,
    /// The outbound streams are equal frame for frame (time ignored).
    pub identical: bool,
    /// The first difference, if any.
    pub first_difference: Option<StreamDifference>,
    /// The odometry comparison; `None` if the log has no odometry frames.
    pub odometry: Option<OdometryComparison>,
    /// The replayed core's pose after its last step.
    pub final_pose: OdometryReading,
    /// Frames the replayed core rejected (malformed, unknown id, ...), by kind.
    pub rejected: firmware::protocol::RxErrorCounters,
}

impl CandumpReplay {
    /// `identical`, `odometry_agrees` or `differs`.
    #[must_use]
    pub fn verdict(&self) -> &'static str {
        if self.identical {
            "identical"
        } else if self.odometry.as_ref().is_some_and(|o| o.agrees) {
            "odometry_agrees"
        } else {
            "differs"
        }
    }

    /// The replay agrees with the log: identical streams, or the same odometry.
    #[must_use]
    pub fn agrees(&self) -> bool {
        self.verdict() != "differs"
    }
}

/// Why a candump log could not be replayed.
#[derive(Debug, thiserror::Error)]
pub enum CandumpReplayError {
    /// The log could not be read or has a bad line.
    #[error(transparent)]
    Read(#[from] drivelog::candump::ReadError),
    /// The log has no frames.
    #[error("{}: no frames", path.display())]
    Empty {
        /// The log file.
        path: PathBuf,
    },
    /// The configuration is refused by the firmware.
    #[error("configuration refused: {0}")]
    Refused(#[from] firmware::config::ConfigError),
    /// The log's time line has a gap too long to replay.
    #[error("{}: {source}", path.display())]
    TimeGap {
        /// The log file.
        path: PathBuf,
        /// The gap.
        source: TimeGap,
    },
}

/// Replays a candump log: see [`replay_split`].
///
/// # Errors
/// [`CandumpReplayError`] naming the file and line, or the configuration error.
pub fn replay_candump(
    path: &Path,
    config: &Config,
    tolerance: OdometryTolerance,
) -> Result<CandumpReplay, CandumpReplayError> {
    let entries = drivelog::candump::read_file(path)?;
    if entries.is_empty() {
        return Err(CandumpReplayError::Empty {
            path: path.to_path_buf(),
        });
    }
    replay_split(config, &split_candump(config, &entries), tolerance).map_err(|e| match e {
        ReplayRunError::Config(e) => CandumpReplayError::Refused(e),
        ReplayRunError::TimeGap(source) => CandumpReplayError::TimeGap {
            path: path.to_path_buf(),
            source,
        },
    })
}

fn reading(t_ns: u64, pose: [f32; 3], velocity: [f32; 3]) -> OdometryReading {
    OdometryReading {
        t_s: t_ns as f64 * 1e-9,
        x: f64::from(pose[0]),
        y: f64::from(pose[1]),
        heading: f64::from(pose[2]),
        vx: f64::from(velocity[0]),
        vy: f64::from(velocity[1]),
        wz: f64::from(velocity[2]),
    }
}

/// Runs a fresh [`Controller`] on a split candump log and compares it with the log.
///
/// Steps run every control period from the first frame (time 0) through the last one.
/// Before each step, the received frames logged at or before the step time are fed,
/// stamped with the step time (as the Linux runner stamps what it drains). The outbound
/// frames are compared with the logged ones in order, time ignored: a real-time log is
/// not on the replay's step grid, so only the order and the contents can match exactly.
/// The odometry is compared at the last logged `ODOM_POSITION`: the replayed core's pose
/// at its last step at or before that time against the logged pose (x, y from
/// `ODOM_POSITION`, heading from the last `ODOM_VELOCITY`).
///
/// The replayed core starts disabled at pose zero, as the runner does: a capture that
/// starts after the runner was enabled or had moved replays a core that never enables (the
/// frame streams differ) and whose odometry is offset by the runner's earlier motion. Start
/// the capture before the runner.
///
/// # Errors
/// [`ReplayRunError`] if the firmware refuses `config`, or if the log's time line has a gap
/// longer than [`MAX_GAP_NS`] ([`check_time_gaps`]).
pub fn replay_split(
    config: &Config,
    log: &SplitLog,
    tolerance: OdometryTolerance,
) -> Result<CandumpReplay, ReplayRunError> {
    use firmware::protocol::robot::Telemetry;
    let mut ctl = Controller::new(config)?;
    check_time_gaps(&log.all)?;
    let period_ns = ctl.period_micros() * 1000;

    // The last logged odometry.
    let mut logged_pos = None;
    let mut logged_vel = None;
    for f in &log.tx {
        match Telemetry::decode(&f.frame) {
            Ok(Telemetry::OdomPosition(p)) => logged_pos = Some((f.t_ns, p)),
            Ok(Telemetry::OdomVelocity(v)) => logged_vel = Some(v),
            _ => {}
        }
    }
    let target_ns = logged_pos.map(|(t, _)| t);

    let end_ns = log.all.last().map_or(0, |f| f.t_ns);
    let mut next_rx = 0;
    let mut out_index = 0usize;
    let mut first_difference = None;
    let mut steps = 0u64;
    let mut at_target = None;
    let mut t_ns = 0u64;
    let mut last_step_ns = 0u64;
    let state = |ctl: &Controller| {
        let s = ctl.snapshot();
        (
            [s.pose.x, s.pose.y, s.pose.heading],
            [s.measured.vx, s.measured.vy, s.measured.wz],
        )
    };
    while t_ns <= end_ns {
        let now = Instant::from_micros(t_ns / 1000);
        while let Some(f) = log.rx.get(next_rx)
            && f.t_ns <= t_ns
        {
            ctl.on_frame(now, &f.frame);
            next_rx += 1;
        }
        // A step's frames leave in the bus's order (a capture of a simulated or a real CAN
        // bus), or in the order the core queued them (a vcan capture): compared in one order.
        let mut sent: Vec<CanFrame> = ctl.step(now).iter().copied().collect();
        sent.sort_by_key(wire_order);
        let end = (out_index + sent.len()).min(log.tx.len());
        let mut logged: Vec<TimedFrame> = log.tx[out_index.min(end)..end].to_vec();
        logged.sort_by_key(|f| wire_order(&f.frame));
        for (i, frame) in sent.into_iter().enumerate() {
            let logged = logged.get(i);
            if first_difference.is_none() && logged.map(|l| l.frame) != Some(frame) {
                first_difference = Some(StreamDifference {
                    index: out_index,
                    logged: logged.map(ReportFrame::new),
                    replayed: Some(ReportFrame::new(&TimedFrame { t_ns, frame })),
                });
            }
            out_index += 1;
        }
        steps += 1;
        last_step_ns = t_ns;
        if target_ns.is_some_and(|t| t_ns <= t) {
            at_target = Some((t_ns, state(&ctl)));
        }
        // The gap check bounds end_ns far below u64::MAX; stop rather than wrap regardless.
        let Some(next) = t_ns.checked_add(period_ns) else {
            break;
        };
        t_ns = next;
    }
    if first_difference.is_none() && out_index < log.tx.len() {
        first_difference = Some(StreamDifference {
            index: out_index,
            logged: Some(ReportFrame::new(&log.tx[out_index])),
            replayed: None,
        });
    }
    let matching_prefix = first_difference.as_ref().map_or(out_index, |d| d.index);

    let odometry = match (logged_pos, at_target) {
        (Some((t, p)), Some((t_rep, (pose, vel)))) => {
            let v = logged_vel.unwrap_or_default();
            let logged = reading(t, [p.x, p.y, v.heading], [v.vx, v.vy, v.wz]);
            let replayed = reading(t_rep, pose, vel);
            let position_error_m = (logged.x - replayed.x).hypot(logged.y - replayed.y);
            let heading_error_rad = kinematics::wrap_angle(logged.heading - replayed.heading).abs();
            let velocity_error = (logged.vx - replayed.vx)
                .abs()
                .max((logged.vy - replayed.vy).abs())
                .max((logged.wz - replayed.wz).abs());
            Some(OdometryComparison {
                logged,
                replayed,
                position_error_m,
                heading_error_rad,
                velocity_error,
                tolerance,
                agrees: position_error_m <= tolerance.position_m
                    && heading_error_rad <= tolerance.heading_rad,
            })
        }
        _ => None,
    };
    let (pose, vel) = state(&ctl);
    Ok(CandumpReplay {
        interfaces: log.interfaces.clone(),
        frames: log.all.len(),
        received: log.rx.len(),
        sent: log.tx.len(),
        period_us: ctl.period_micros(),
        steps,
        duration_s: end_ns as f64 * 1e-9,
        replayed: out_index,
        matching_prefix,
        identical: first_difference.is_none(),
        first_difference,
        odometry,
        final_pose: reading(last_step_ns, pose, vel),
        rejected: ctl.snapshot().rx_errors,
    })
}

/// The frames of a hostsim MCAP log for playback: `/can/rx`, `/can/tx` or both merged by
/// time (received first at equal times, the order the simulator used).
#[must_use]
pub fn mcap_playback(content: &LogContent, rx: bool, tx: bool) -> Vec<TimedFrame> {
    let mut out: Vec<TimedFrame> = Vec::new();
    if rx {
        out.extend(&content.rx);
    }
    if tx {
        out.extend(&content.tx);
    }
    // Stable: the rx frames stay ahead of tx frames logged at the same time.
    out.sort_by_key(|f| f.t_ns);
    out
}
