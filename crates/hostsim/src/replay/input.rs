//! A log's input to a replay: its frames, steps and configuration read from MCAP, or a
//! candump log classified by direction; and the bounds a replay keeps (time gaps).

use std::path::{Path, PathBuf};

use firmware::CanFrame;
use firmware::config::Config;
use serde::Serialize;

use drivelog::{Damage, ReadReport};

/// A frame with its log time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TimedFrame {
    /// Log time, ns of simulated time.
    pub t_ns: u64,
    /// The frame.
    pub frame: CanFrame,
}

/// The end of a parameter save as the core was told it, before the step at `t_ns`
/// (`/firmware/store`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TimedSave {
    /// Log time: the step's, ns.
    pub t_ns: u64,
    /// What the core was given.
    pub outcome: firmware::control::SaveOutcome,
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
    /// The built-in configuration's TOML and the saved record's number, when the core did
    /// not start on its built-in configuration (a runner on a saved set, `--params`).
    pub builtin: Option<(String, String)>,
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
    /// The ends of parameter saves the core was told (`/firmware/store`).
    pub saves: Vec<TimedSave>,
    /// The longest a sent frame took from its step to the end of its transmission, among
    /// those read, ns.
    pub tx_lag_ns: u64,
    /// Messages per topic.
    pub topics: std::collections::BTreeMap<String, u64>,
    /// The messages of the topics read here that did not decode.
    pub undecodable: drivelog::Undecodable,
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
    /// Messages replay needs (`/can/rx`, `/can/tx`, `/firmware/steps`) did not decode: a
    /// replay without them would feed or compare fewer frames than the run had.
    #[error("{path}: {undecodable}: replay needs every one of them")]
    Undecodable {
        /// The log file.
        path: PathBuf,
        /// How many, on which topics, and the first.
        undecodable: drivelog::Undecodable,
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
    /// A metadata entry's value is not what it should be.
    #[error("{path}: metadata `{key}` = \"{}\": not a number", firmware::input::quote(.value))]
    Metadata {
        /// The log file.
        path: PathBuf,
        /// The entry.
        key: &'static str,
        /// Its value.
        value: String,
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
/// most that long after time 0. Bounds the work of [`replay_frames`](super::replay_frames), [`replay_split`](super::replay_split) and a
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

/// Reads the frames and configuration of a hostsim MCAP log.
///
/// # Errors
/// [`ReplayError`] if the file cannot be read or nothing in it is readable. A damaged file is
/// not an error: [`LogContent::read`] says where the damage is.
pub fn read_log(path: &Path) -> Result<LogContent, ReplayError> {
    let bytes = drivelog::read::read_log_file(path).map_err(|source| ReplayError::Io {
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
pub const OLD_LAYOUT: &str = "an MCAP file without the `ros2` profile: not a ROS 2 bag with CDR \
     messages as this project writes, but another program's MCAP or a log in the JSON layout of \
     hostsim before its logs became ROS 2 bags (record such a run again)";

/// `true` for a log in the JSON layout of earlier versions: MCAP without the `ros2` profile.
#[must_use]
pub fn is_old_layout(read: &ReadReport) -> bool {
    read.profile != drivelog::PROFILE
}

/// The order in which a node's frames queued together leave on the bus: the one with the
/// lower arbitration field first (a standard id before the extended ids that share its top 11
/// bits), in queueing order among equals. [`read_log_bytes`] sorts the sent frames by their
/// step and then this; [`replay_frames`](super::replay_frames) sorts each step's frames by this.
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
    let mut content = LogContent::default();
    let mut config = None;
    let mut scenario = None;
    let mut program = None;
    let mut builtin = None;
    let read = drivelog::for_each_message(
        bytes,
        |m| {
            *content.topics.entry(m.topic.to_string()).or_default() += 1;
            let (list, t_ns) = match m.topic {
                "/firmware/steps" => {
                    if let Some(step) = content.undecodable.decode::<drivelog::msg::Step>(m) {
                        content.steps.push(StepTime {
                            t_ns: m.log_time,
                            shutdown: step.kind == drivelog::msg::Step::SHUTDOWN,
                        });
                    }
                    return;
                }
                "/firmware/store" => {
                    if let Some(s) = content.undecodable.decode::<drivelog::msg::SaveResult>(m) {
                        let outcome = match s.abort_code {
                            0 => firmware::control::SaveOutcome::Stored { seq: s.seq },
                            code => firmware::control::SaveOutcome::Failed { code },
                        };
                        content.saves.push(TimedSave {
                            t_ns: m.log_time,
                            outcome,
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
            if let Some(frame) = content.undecodable.frame(m) {
                list.push(TimedFrame { t_ns, frame });
            }
        },
        |name, kv| {
            if name == drivelog::METADATA_NAME {
                config = kv.get("config").cloned();
                scenario = kv.get("scenario").cloned();
                program = kv.get("program").cloned();
                builtin = kv
                    .get("builtin_config")
                    .cloned()
                    .zip(kv.get("saved_seq").cloned());
            }
        },
    )?;
    // Stable: frames of one step with equal arbitration fields keep their logged order.
    content.tx.sort_by_key(|f| (f.t_ns, wire_order(&f.frame)));
    content.config = config;
    content.scenario = scenario;
    content.program = program;
    content.builtin = builtin;
    content.read = read;
    Ok(content)
}

/// The `program` metadata of `hostsim plant`'s logs.
pub const PLANT_PROGRAM: &str = "hostsim plant";

/// An MCAP log ready to replay: what [`read_log`] read, the logged configuration and the
/// [`complete_part`] of its frames and steps.
#[derive(Debug, Clone)]
pub struct McapReplayInput {
    /// Everything read from the log.
    pub content: LogContent,
    /// The logged configuration, loaded and validated.
    pub config: Config,
    /// The built-in configuration and the saved record's number, when the logged core ran a
    /// saved set: what its restores put back.
    pub builtin: Option<(Config, u32)>,
    /// The inbound frames to feed.
    pub rx: Vec<TimedFrame>,
    /// The outbound frames to compare with.
    pub tx: Vec<TimedFrame>,
    /// The recorded steps (empty: step on the period grid).
    pub steps: Vec<StepTime>,
}

/// Reads an MCAP log for replay ([`replay_mcap`](super::replay_mcap), [`crate::replay::whatif::what_if_mcap`]): its
/// configuration and the complete part of its frames.
///
/// # Errors
/// [`ReplayError`] if the log cannot be read, has no usable configuration, is a log of
/// `hostsim plant`, or has no firmware frames.
pub fn open_mcap(path: &Path) -> Result<McapReplayInput, ReplayError> {
    let content = read_log(path)?;
    if content.undecodable.total() > 0 {
        return Err(ReplayError::Undecodable {
            path: path.to_path_buf(),
            undecodable: content.undecodable,
        });
    }
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
    let builtin = match &content.builtin {
        None => None,
        Some((text, seq)) => {
            let builtin = Config::from_toml_str(text).map_err(|source| ReplayError::Config {
                path: path.to_path_buf(),
                source: Box::new(source),
            })?;
            let seq = seq.parse::<u32>().map_err(|_| ReplayError::Metadata {
                path: path.to_path_buf(),
                key: "saved_seq",
                value: seq.clone(),
            })?;
            Some((builtin, seq))
        }
    };
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
        builtin,
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
    use firmware::config::{Cia402Drive, Drive};
    use firmware::protocol::{canopen, dji, odrive, robot};
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
        // The master's frames: NMT, SYNC and its heartbeat, and the SDO requests and RPDOs
        // to this robot's nodes.
        Drive::Cia402(Cia402Drive {
            node_ids,
            master_node,
            ..
        }) => match canopen::decode(frame) {
            Ok(canopen::Message::Nmt { .. } | canopen::Message::Sync { .. }) => true,
            Ok(canopen::Message::Heartbeat { node, .. }) => node.get() == master_node,
            Ok(
                m @ (canopen::Message::SdoRequest { .. }
                | canopen::Message::Rpdo1 { .. }
                | canopen::Message::Rpdo3 { .. }),
            ) => m.node().is_some_and(|n| node_ids.contains(&n.get())),
            _ => false,
        },
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
