//! Replay: run the firmware core again on a log's inbound frames and check that it sends the
//! same frames, bit for bit.
//!
//! A hostsim MCAP log holds the configuration (metadata record `hostsim`, key `config`), every
//! frame the firmware received (`/can/rx`, at its delivery time) and every frame it sent
//! (`/can/tx`, at the step that sent it). Steps happen every control period from time 0.
//! Replay builds a fresh [`Controller`] from the logged configuration, feeds each received
//! frame before the first step at or after its time — the order the simulator used — and
//! compares what comes out with `/can/tx`, frame by frame. The first difference is reported
//! with its time, the expected frame and the replayed one.
//!
//! The reader takes every complete record: a file cut short (a killed run) is replayed up to
//! the last complete chunk, and the error that stopped the reading is reported with its
//! byte offset.

use std::path::{Path, PathBuf};

use embedded_can::{Frame, StandardId};
use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant};

/// A frame with its log time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TimedFrame {
    /// Log time, ns of simulated time.
    pub t_ns: u64,
    /// The frame.
    pub frame: CanFrame,
}

/// What a log holds for replay.
#[derive(Debug, Clone, Default)]
pub struct LogContent {
    /// The configuration TOML from the metadata, if any.
    pub config: Option<String>,
    /// Scenario name from the metadata.
    pub scenario: Option<String>,
    /// Frames the firmware received.
    pub rx: Vec<TimedFrame>,
    /// Frames the firmware sent.
    pub tx: Vec<TimedFrame>,
    /// Messages per topic.
    pub topics: std::collections::BTreeMap<String, u64>,
    /// Why reading stopped early, with the byte offset, if it did.
    pub truncated: Option<String>,
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
    /// The log has no configuration to rebuild the firmware from.
    #[error("{path}: no `hostsim` metadata with a `config` entry (was it written by hostsim?)")]
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
}

/// Reads the frames and configuration of a hostsim MCAP log.
///
/// # Errors
/// [`ReplayError`] if the file cannot be read or is not MCAP at all. A file cut short is not
/// an error: [`LogContent::truncated`] says where it stopped.
pub fn read_log(path: &Path) -> Result<LogContent, ReplayError> {
    let bytes = std::fs::read(path).map_err(|source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    read_log_bytes(&bytes).map_err(|reason| ReplayError::NotMcap {
        path: path.to_path_buf(),
        reason,
    })
}

/// As [`read_log`], from bytes.
///
/// # Errors
/// A description if the bytes do not start like an MCAP file.
pub fn read_log_bytes(bytes: &[u8]) -> Result<LogContent, String> {
    use mcap::read::Options;
    use mcap::records::Record;

    let options = Options::IgnoreEndMagic.into();
    let reader =
        mcap::read::ChunkFlattener::new_with_options(bytes, options).map_err(|e| e.to_string())?;
    let mut content = LogContent::default();
    let mut topics: std::collections::HashMap<u16, String> = std::collections::HashMap::new();
    let mut read_any = false;
    for record in reader {
        let record = match record {
            Ok(r) => r,
            Err(e) => {
                if !read_any {
                    return Err(e.to_string());
                }
                content.truncated = Some(format!("{e} (file size {} bytes)", bytes.len()));
                break;
            }
        };
        read_any = true;
        match record {
            Record::Channel(c) => {
                topics.insert(c.id, c.topic.to_string());
            }
            Record::Metadata(m) if m.name == "hostsim" => {
                content.config = m.metadata.get("config").cloned();
                content.scenario = m.metadata.get("scenario").cloned();
            }
            Record::Message { header, data } => {
                let Some(topic) = topics.get(&header.channel_id) else {
                    continue;
                };
                *content.topics.entry(topic.clone()).or_default() += 1;
                let list = match topic.as_str() {
                    "/can/rx" => &mut content.rx,
                    "/can/tx" => &mut content.tx,
                    _ => continue,
                };
                if let Some(frame) = parse_frame_json(&data) {
                    list.push(TimedFrame {
                        t_ns: header.log_time,
                        frame,
                    });
                }
            }
            _ => {}
        }
    }
    Ok(content)
}

/// Parses a `/can/*` JSON message back into a frame; `None` if it is not one.
#[must_use]
pub fn parse_frame_json(data: &[u8]) -> Option<CanFrame> {
    let v: serde_json::Value = serde_json::from_slice(data).ok()?;
    let id = u16::try_from(v.get("id")?.as_u64()?).ok()?;
    let dlc = u8::try_from(v.get("dlc")?.as_u64()?).ok()?;
    if dlc > 8 || v.get("is_extended")?.as_bool()? {
        return None;
    }
    let mut buf = [0u8; 8];
    for (b, x) in buf.iter_mut().zip(v.get("data")?.as_array()?) {
        *b = u8::try_from(x.as_u64()?).ok()?;
    }
    Some(CanFrame::from_buffer(StandardId::new(id)?, buf, dlc))
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
    /// Where reading stopped early, if it did.
    pub truncated: Option<String>,
}

impl ReplayReport {
    /// `true` if every outbound frame matched, bit for bit, at the same step.
    #[must_use]
    pub fn identical(&self) -> bool {
        self.difference.is_none()
    }
}

/// Replays a hostsim MCAP log through a fresh firmware core.
///
/// # Errors
/// [`ReplayError`] if the log cannot be read or has no usable configuration.
pub fn replay_mcap(path: &Path) -> Result<ReplayReport, ReplayError> {
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
    let mut report = replay_frames(&config, &content.rx, &content.tx).map_err(|source| {
        ReplayError::Refused {
            path: path.to_path_buf(),
            source,
        }
    })?;
    report.truncated = content.truncated;
    Ok(report)
}

/// Runs the core on `rx` and compares its output with `tx`. Steps run every period from 0
/// through the last logged time.
///
/// # Errors
/// The configuration error if the firmware refuses `config`.
pub fn replay_frames(
    config: &Config,
    rx: &[TimedFrame],
    tx: &[TimedFrame],
) -> Result<ReplayReport, firmware::config::ConfigError> {
    let mut ctl = Controller::new(config)?;
    let period_ns = ctl.period_micros() * 1000;
    let end_ns = rx.iter().chain(tx).map(|f| f.t_ns).max().unwrap_or(0);
    let mut next_rx = 0;
    let mut out_index = 0;
    let mut steps = 0;
    let mut difference = None;
    let mut t_ns = 0;
    'run: while t_ns <= end_ns {
        while let Some(f) = rx.get(next_rx)
            && f.t_ns <= t_ns
        {
            ctl.on_frame(Instant::from_micros(f.t_ns / 1000), &f.frame);
            next_rx += 1;
        }
        for frame in ctl.step(Instant::from_micros(t_ns / 1000)) {
            let replayed = TimedFrame { t_ns, frame };
            let logged = tx.get(out_index).copied();
            if logged != Some(replayed) {
                difference = Some(Difference {
                    index: out_index,
                    t_ns,
                    logged,
                    replayed: Some(replayed),
                });
                break 'run;
            }
            out_index += 1;
        }
        steps += 1;
        t_ns += period_ns;
    }
    if difference.is_none() && out_index < tx.len() {
        difference = Some(Difference {
            index: out_index,
            t_ns: tx[out_index].t_ns,
            logged: Some(tx[out_index]),
            replayed: None,
        });
    }
    Ok(ReplayReport {
        compared: out_index,
        fed: next_rx,
        steps,
        difference,
        truncated: None,
    })
}

/// `id#data` in candump notation.
#[must_use]
pub fn candump_text(frame: &CanFrame) -> String {
    let id = match frame.id() {
        embedded_can::Id::Standard(id) => format!("{:03X}", id.as_raw()),
        embedded_can::Id::Extended(id) => format!("{:08X}", id.as_raw()),
    };
    let data: String = frame.data().iter().map(|b| format!("{b:02X}")).collect();
    format!("{id}#{data}")
}
