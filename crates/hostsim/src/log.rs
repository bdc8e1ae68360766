//! MCAP logs of simulated (and real) runs.
//!
//! # Channels
//!
//! | topic | encoding | what |
//! |---|---|---|
//! | `/can/rx` | JSON, schema after `can_msgs/msg/Frame` | every frame the firmware received, at delivery time |
//! | `/can/tx` | same | every frame the firmware sent, at the step that sent it |
//! | `/can/bus` | same, plus `sender` and `fate` | every frame on the bus, at its end of transmission, including dropped ones |
//! | `/firmware/snapshot` | JSON | per control step: state, fault, commanded and measured twist, wheel setpoints, speeds, currents |
//! | `/cmd/twist` | JSON | the host's twist setpoint when it changes |
//! | `/motors/feedback` | JSON | decoded drive feedback (DJI: rotor angle, rpm, current, temperature; ODrive: estimates, heartbeat), every 10th frame per drive |
//! | `/odom/pose` | `foxglove.PoseInFrame` | the firmware's odometry (frame `world`: its origin is the start of the run, where the robot starts) |
//! | `/ground_truth/pose` | `foxglove.PoseInFrame` | the plant's pose (frame `world`) |
//! | `/tf` | `foxglove.FrameTransform` | `world → base_link` (truth) and `world → base_link_odom` (odometry) |
//! | `/firmware/log` | `foxglove.Log` | state changes and faults, as text |
//!
//! There is no Foxglove schema for CAN frames; the `/can/*` channels use the ROS
//! `can_msgs/msg/Frame` shape (`id`, `is_rtr`, `is_extended`, `is_error`, `dlc`, `data[8]`)
//! with an integer `data` array, so Foxglove can plot bytes. Times are simulated time: log time
//! 0 is the start of the run.
//!
//! The run's configuration (TOML) and scenario name and seed go in a `hostsim` metadata
//! record at the start, so `replay` can rebuild the same firmware.
//!
//! # Layout
//!
//! The log writes the MCAP records itself (module `write`, after
//! <https://mcap.dev/spec>): the magic and the Header, the Schema and Channel records and the
//! `hostsim` Metadata record; then the messages in zstd-compressed chunks, each Chunk record
//! followed by one Message Index record per channel it holds; then the Data End record (with
//! the CRC of everything before it), the summary section (the Schema and Channel records
//! again, Statistics, a Chunk Index per chunk, the Metadata Index, and a Summary Offset per
//! group), the Footer (with the summary's CRC) and the magic. Every Chunk record carries the
//! CRC of its uncompressed content.
//!
//! The caller's thread (the simulation's) only records each message's values (an `Event`:
//! a frame, a snapshot, a pose...) in a batch, and hands the batch over to a second thread at
//! each flush (see [`McapLog::maybe_flush`]). That thread turns the events into Message
//! records, in order and numbered as logged, chunks them (a chunk closes when its records
//! reach [`CHUNK_SIZE`] uncompressed bytes, and at the end of each batch), computes each
//! chunk's CRC, compresses it (zstd level [`ZSTD_LEVEL`]) and appends it with its message
//! indexes in one write. The JSON text, the protobuf encoding and the compression are all on
//! that thread, so they overlap the simulation. What the file holds depends only on the
//! messages logged and on when the batches were handed over, never on the threads' timing:
//! the same run gives the same messages, and the same bytes as long as every hand-over is due
//! to log time (half a second of wall-clock time between two hand-overs, in a run slower than
//! real time or on a stalled machine, moves a chunk boundary).
//!
//! # Crash safety
//!
//! Each chunk is built in memory and appended to the file whole, so the file on disk is always
//! a prefix of the finished file (no chunk header is patched afterwards). A batch is handed
//! over once a quarter of a second of log time, or half a second of wall-clock time, has
//! passed since the last hand-over; each hand-over then waits until the batch before it is in
//! the file. So at most two batches are not yet on disk: the one being written and the open
//! one. A run that dies (SIGKILL, a panic, the OOM killer) therefore leaves a file cut short
//! whose every complete chunk is readable, and loses at most the last half second of log
//! time before it died (and, for a run slower than real time, at most about half a second of
//! wall-clock time plus the few milliseconds of writing a batch): "at most the last second".
//! The file is created as `NAME.mcap.part` and renamed to `NAME.mcap` once its header,
//! channels and metadata are on disk, so a `.mcap` file always opens. There is no `fsync`:
//! this protects against the process dying, not against the machine losing power.
//!
//! An error of the writing thread (a full disk, say) comes back as [`LogError::Io`], naming
//! the file, from the next hand-over ([`McapLog::maybe_flush`], or a message that fills a
//! batch) or from [`McapLog::finish`]; every later hand-over fails too. A panic of that
//! thread comes back the same way, as an error.
//!
//! [`for_each_message`] reads such files: every complete chunk, then a [`Damage`] report that
//! names the byte offset where the unusable part starts (see [`read`]).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant as WallInstant};

use firmware::CanFrame;
use foxglove::Encode;
use foxglove::schemas::{FrameTransform, Log, PoseInFrame};
use mcap::records::op;

use crate::bus::{Fate, Node};

mod data;
mod json;
pub mod read;
mod write;

pub use json::write_frame_json;
pub use read::{Damage, Problem, ReadReport, for_each_message};
use write::{Batch, BatchWriter, Event, Sink};

/// Why a log could not be written.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// The file could not be created, written or compressed.
    #[error("{path}: {source}")]
    Io {
        /// The log file.
        path: PathBuf,
        /// The OS (or compressor's) error.
        source: io::Error,
    },
}

/// JSON schema of the `/can/*` channels (after `can_msgs/msg/Frame`).
pub const CAN_FRAME_SCHEMA: &str = r#"{"type":"object","title":"can_msgs/msg/Frame","properties":{"header":{"type":"object","properties":{"stamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},"frame_id":{"type":"string"}}},"id":{"type":"integer"},"is_rtr":{"type":"boolean"},"is_extended":{"type":"boolean"},"is_error":{"type":"boolean"},"dlc":{"type":"integer"},"data":{"type":"array","items":{"type":"integer","minimum":0,"maximum":255},"minItems":8,"maxItems":8},"sender":{"type":"string"},"fate":{"type":"string"}},"required":["id","is_rtr","is_extended","is_error","dlc","data"]}"#;

const SNAPSHOT_SCHEMA: &str = r#"{"type":"object","title":"mecanum/FirmwareSnapshot","properties":{"state":{"type":"string"},"fault":{"type":"string"},"commanded":{"type":"object"},"measured":{"type":"object"},"wheel_setpoints":{"type":"array","items":{"type":"number"}},"wheel_speeds":{"type":"array","items":{"type":"number"}},"currents":{"type":"array","items":{"type":"number"}},"motors_online":{"type":"integer"},"rx_errors":{"type":"integer"},"unknown_ids":{"type":"integer"}}}"#;

const FEEDBACK_SCHEMA: &str = r#"{"type":"object","title":"mecanum/MotorFeedback","properties":{"protocol":{"type":"string"},"id":{"type":"integer"},"rotor_angle":{"type":"integer"},"rotor_speed_rpm":{"type":"integer"},"current_a":{"type":"number"},"temperature_c":{"type":"integer"},"pos_rev":{"type":"number"},"vel_rev_s":{"type":"number"},"axis_error":{"type":"integer"},"axis_state":{"type":"string"}}}"#;

const TWIST_SCHEMA: &str = r#"{"type":"object","title":"mecanum/Twist","properties":{"vx":{"type":"number"},"vy":{"type":"number"},"wz":{"type":"number"},"streaming":{"type":"boolean"}}}"#;

/// Direction of a frame relative to the firmware.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Direction {
    /// Received by the firmware.
    Rx,
    /// Sent by the firmware.
    Tx,
}

/// Channel ids, as written in the Channel records (0 is not used).
#[derive(Clone, Copy)]
struct Channels {
    rx: u16,
    tx: u16,
    bus: u16,
    snapshot: u16,
    twist: u16,
    feedback: u16,
    odom: u16,
    truth: u16,
    tf: u16,
    log: u16,
}

const CHANNELS: Channels = Channels {
    rx: 1,
    tx: 2,
    bus: 3,
    snapshot: 4,
    twist: 5,
    feedback: 6,
    odom: 7,
    truth: 8,
    tf: 9,
    log: 10,
};

/// Channel ids run from 1 to this.
const LAST_CHANNEL: u16 = 10;

/// The MCAP magic, at the start and at the end of a file.
const MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// An MCAP log being written. See the [module documentation](self).
pub struct McapLog {
    path: PathBuf,
    /// The messages logged since the last hand-over to the writing thread.
    batch: Batch,
    /// The writing thread; `None` once finished.
    writer: Option<BatchWriter>,
    /// Set by the first write error: every later write fails with it.
    failed: Option<(io::ErrorKind, String)>,
    /// The Schema and Channel records as written at the start, for the summary.
    schemas: Vec<u8>,
    channels: Vec<u8>,
    /// The Metadata Index record of the `hostsim` metadata.
    metadata_index: Vec<u8>,
    messages: u64,
    /// Largest log time logged, ns.
    last_log_ns: u64,
    /// `last_log_ns` at the last hand-over.
    flushed_log_ns: u64,
    /// Wall-clock time of the last hand-over.
    last_flush: WallInstant,
    /// Calls of `maybe_flush`, to read the wall clock only every few.
    flush_calls: u64,
}

/// Log time between two hand-overs, ns. The batch in flight and the open one are what a run
/// that dies loses: at most twice this.
const FLUSH_LOG_INTERVAL_NS: u64 = 250_000_000;

/// Wall-clock time between two hand-overs, for runs slower than real time.
const FLUSH_WALL_INTERVAL: Duration = Duration::from_millis(500);

/// [`McapLog::maybe_flush`] reads the wall clock on every this many calls.
const CALLS_PER_CLOCK_READ: u64 = 64;

/// Events in a batch at which it is handed over even if [`McapLog::maybe_flush`] is not
/// called: bounds a batch's memory (about 3 MB; the square scenario logs some 2,900 events in
/// the quarter second between two hand-overs).
const MAX_BATCH_EVENTS: usize = 1 << 16;

/// Uncompressed size at which the writer closes a chunk, bytes. With the square scenario's
/// ~2.4 MB of messages per simulated second, chunks close at the hand-overs (a quarter of a
/// second, about 600 kB) first.
pub const CHUNK_SIZE: u64 = 1 << 20;

/// zstd level of the chunks: -3, one of zstd's fast (negative) levels. Measured on the
/// chunks of the 60 s square (600 kB each, fastest of 12 passes per chunk): level 1
/// compresses them 13.0x at 1.0 GB/s, -1 11.7x at the same speed, -2 9.9x at 1.17 GB/s, -3
/// 9.6x at 1.35 GB/s, -5 8.0x no faster, 3 13.0x at 0.78 GB/s. On the writing thread, the
/// busier of the two, -3 saves about 0.04 s of the 60 s square (the run's median wall time
/// 7 % lower than at level 1) for a file 17.5 % larger (26.3 MB against 22.3 MB, of which
/// 11 MB are the uncompressed message indexes). Level 1 is the choice where size matters more.
pub const ZSTD_LEVEL: i32 = -3;

/// Where a log is written until its header is on disk: `NAME.mcap.part` for `NAME.mcap`.
#[must_use]
pub fn part_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".part");
    PathBuf::from(name)
}

/// The Schema and Channel records of a hostsim log.
fn schemas_and_channels() -> (Vec<u8>, Vec<u8>) {
    let ch = CHANNELS;
    let mut schemas = Vec::new();
    let mut channels = Vec::new();
    let json_schemas = [
        (1, "can_msgs/msg/Frame", CAN_FRAME_SCHEMA),
        (2, "mecanum/FirmwareSnapshot", SNAPSHOT_SCHEMA),
        (3, "mecanum/Twist", TWIST_SCHEMA),
        (4, "mecanum/MotorFeedback", FEEDBACK_SCHEMA),
    ];
    for (id, name, schema) in json_schemas {
        write::schema(&mut schemas, id, name, "jsonschema", schema.as_bytes());
    }
    let fox = [
        (5, PoseInFrame::get_schema()),
        (6, FrameTransform::get_schema()),
        (7, Log::get_schema()),
    ];
    for (id, schema) in fox {
        let schema = schema.expect("foxglove schemas carry a schema");
        write::schema(
            &mut schemas,
            id,
            &schema.name,
            &schema.encoding,
            &schema.data,
        );
    }
    let protobuf = PoseInFrame::get_message_encoding();
    for (id, schema_id, topic, encoding) in [
        (ch.rx, 1, "/can/rx", "json"),
        (ch.tx, 1, "/can/tx", "json"),
        (ch.bus, 1, "/can/bus", "json"),
        (ch.snapshot, 2, "/firmware/snapshot", "json"),
        (ch.twist, 3, "/cmd/twist", "json"),
        (ch.feedback, 4, "/motors/feedback", "json"),
        (ch.odom, 5, "/odom/pose", &protobuf),
        (ch.truth, 5, "/ground_truth/pose", &protobuf),
        (ch.tf, 6, "/tf", &FrameTransform::get_message_encoding()),
        (ch.log, 7, "/firmware/log", &Log::get_message_encoding()),
    ] {
        write::channel(&mut channels, id, schema_id, topic, encoding);
    }
    (schemas, channels)
}

/// What a log starts with, up to its first chunk: the magic, the Header, the Schema and
/// Channel records and the `hostsim` Metadata record; and the parts of it the summary repeats.
struct Head {
    bytes: Vec<u8>,
    /// The Schema records.
    schemas: Vec<u8>,
    /// The Channel records.
    channels: Vec<u8>,
    /// The Metadata Index record of the metadata.
    metadata_index: Vec<u8>,
}

impl Head {
    fn new(metadata: &BTreeMap<String, String>) -> Self {
        let (schemas, channels) = schemas_and_channels();
        let mut bytes = MAGIC.to_vec();
        write::header(
            &mut bytes,
            "",
            concat!("mecanum hostsim ", env!("CARGO_PKG_VERSION")),
        );
        bytes.extend_from_slice(&schemas);
        bytes.extend_from_slice(&channels);
        let metadata_offset = bytes.len() as u64;
        write::metadata(&mut bytes, "hostsim", metadata);
        let metadata_length = bytes.len() as u64 - metadata_offset;
        let mut metadata_index = Vec::new();
        write::record(&mut metadata_index, op::METADATA_INDEX, |out| {
            out.extend_from_slice(&metadata_offset.to_le_bytes());
            out.extend_from_slice(&metadata_length.to_le_bytes());
            write::put_str(out, "hostsim");
        });
        Self {
            bytes,
            schemas,
            channels,
            metadata_index,
        }
    }
}

impl McapLog {
    /// Creates `path` and writes the header, schemas, channels and the run's metadata
    /// (`config` TOML, scenario name, seed, ...). The file is written as [`part_path`] and
    /// renamed to `path` once that much is on disk (see [Crash safety](self#crash-safety)).
    ///
    /// # Errors
    /// [`LogError`] naming the file.
    pub fn create(path: &Path, metadata: &BTreeMap<String, String>) -> Result<Self, LogError> {
        Self::create_with_chunk_size(path, metadata, CHUNK_SIZE)
    }

    /// As [`create`](Self::create), closing chunks at `chunk_size` uncompressed bytes instead
    /// of [`CHUNK_SIZE`]: small chunks make many chunk boundaries in a short log, for tests of
    /// damaged logs.
    ///
    /// # Errors
    /// [`LogError`] naming the file.
    pub fn create_with_chunk_size(
        path: &Path,
        metadata: &BTreeMap<String, String>,
        chunk_size: u64,
    ) -> Result<Self, LogError> {
        let part = part_path(path);
        let part_err = |source| LogError::Io {
            path: part.clone(),
            source,
        };
        let mut file = File::create(&part).map_err(part_err)?;
        let head = Head::new(metadata);
        file.write_all(&head.bytes).map_err(part_err)?;
        std::fs::rename(&part, path).map_err(|source| LogError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::start(path, Box::new(file), head, chunk_size)
    }

    /// A log of `path` whose `head` is written to `out` already: starts the writing thread,
    /// which appends to `out`.
    fn start(
        path: &Path,
        out: Box<dyn Write + Send>,
        head: Head,
        chunk_size: u64,
    ) -> Result<Self, LogError> {
        let sink = Sink::new(out, &head.bytes);
        let chunk_size = usize::try_from(chunk_size).unwrap_or(usize::MAX);
        let writer =
            BatchWriter::start(sink, chunk_size, ZSTD_LEVEL).map_err(|source| LogError::Io {
                path: path.to_path_buf(),
                source,
            })?;
        Ok(Self {
            path: path.to_path_buf(),
            batch: Batch::default(),
            writer: Some(writer),
            failed: None,
            schemas: head.schemas,
            channels: head.channels,
            metadata_index: head.metadata_index,
            messages: 0,
            last_log_ns: 0,
            flushed_log_ns: 0,
            last_flush: WallInstant::now(),
            flush_calls: 0,
        })
    }

    fn io_err(&self, source: io::Error) -> LogError {
        LogError::Io {
            path: self.path.clone(),
            source,
        }
    }

    /// Records `event`, `messages` messages at `t_ns`; hands the batch over if it is full.
    #[inline]
    fn push(&mut self, event: Event, t_ns: u64, messages: u64) -> Result<(), LogError> {
        self.batch.events.push(event);
        self.messages += messages;
        self.last_log_ns = self.last_log_ns.max(t_ns);
        if self.batch.events.len() >= MAX_BATCH_EVENTS {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Hands the batch, if it holds anything, to the writing thread (after waiting for the
    /// one in flight), and restarts the flush clocks.
    fn hand_over(&mut self) -> Result<(), LogError> {
        self.flushed_log_ns = self.last_log_ns;
        self.last_flush = WallInstant::now();
        if let Some((kind, text)) = &self.failed {
            // Do not let a log that can no longer be written grow in memory.
            self.batch.clear();
            return Err(self.io_err(io::Error::new(
                *kind,
                format!("an earlier write failed: {text}"),
            )));
        }
        if self.batch.is_empty() {
            return Ok(());
        }
        let Some(writer) = self.writer.as_mut() else {
            return Ok(());
        };
        let full = std::mem::take(&mut self.batch);
        match writer.send(full) {
            Ok(spare) => {
                if let Some(spare) = spare {
                    self.batch = spare;
                }
                Ok(())
            }
            Err(e) => {
                self.failed = Some((e.kind(), e.to_string()));
                Err(self.io_err(e))
            }
        }
    }

    /// Logs a frame the firmware received or sent.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn can(&mut self, t_ns: u64, dir: Direction, frame: &CanFrame) -> Result<(), LogError> {
        let event = Event::Can {
            t_ns,
            frame: *frame,
            dir,
        };
        self.push(event, t_ns, 1)
    }

    /// Logs a frame on the bus with its sender and fate.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn bus(
        &mut self,
        t_ns: u64,
        frame: &CanFrame,
        sender: Node,
        fate: Fate,
    ) -> Result<(), LogError> {
        let event = Event::Bus {
            t_ns,
            frame: *frame,
            sender,
            fate,
        };
        self.push(event, t_ns, 1)
    }

    /// Logs a firmware snapshot.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn snapshot(&mut self, t_ns: u64, s: &firmware::control::Snapshot) -> Result<(), LogError> {
        let index = self.batch.snapshots.len() as u32;
        self.batch.snapshots.push(*s);
        self.push(Event::Snapshot { t_ns, index }, t_ns, 1)
    }

    /// Logs a drive feedback frame, decoded; frames that are not drive feedback are skipped.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn motor_feedback(
        &mut self,
        t_ns: u64,
        frame: &CanFrame,
        drive: &firmware::config::Drive,
    ) -> Result<(), LogError> {
        use firmware::protocol::{dji, odrive};
        let event = match *drive {
            firmware::config::Drive::Dji { model, .. } => {
                let Ok(feedback) = dji::Feedback::decode(frame, model) else {
                    return Ok(());
                };
                Event::Dji { t_ns, feedback }
            }
            firmware::config::Drive::Odrive { .. } => {
                let Ok(feedback) = odrive::Feedback::decode(frame) else {
                    return Ok(());
                };
                Event::Odrive { t_ns, feedback }
            }
        };
        self.push(event, t_ns, 1)
    }

    /// Logs the host's twist setpoint.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn twist(&mut self, t_ns: u64, twist: [f32; 3], streaming: bool) -> Result<(), LogError> {
        let event = Event::Twist {
            t_ns,
            twist,
            streaming,
        };
        self.push(event, t_ns, 1)
    }

    /// Logs the odometry pose and the ground-truth pose (both in the `world` frame), and
    /// both as transforms for Foxglove's 3D panel.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn poses(&mut self, t_ns: u64, odom: [f64; 3], truth: [f64; 3]) -> Result<(), LogError> {
        let index = self.batch.poses.len() as u32;
        self.batch.poses.push([odom, truth]);
        self.push(Event::Poses { t_ns, index }, t_ns, 4)
    }

    /// Logs a text line (state change, fault) at `level` (foxglove: 1 debug, 2 info, 3 warning,
    /// 4 error).
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn text(&mut self, t_ns: u64, level: i32, message: &str) -> Result<(), LogError> {
        let index = self.batch.texts.len() as u32;
        self.batch.texts.push(message.to_string());
        self.push(Event::Text { t_ns, level, index }, t_ns, 1)
    }

    /// Hands the messages logged so far to the writing thread if a quarter of a second of log
    /// time, or half a second of wall-clock time, has passed since the last hand-over (see
    /// [Crash safety](self#crash-safety)). Call it after each step's messages, at least every
    /// few milliseconds of log time: it reads the wall clock only on every 64th call.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed (the previous batch, or an earlier one).
    pub fn maybe_flush(&mut self) -> Result<(), LogError> {
        self.flush_calls += 1;
        let log_due = self.last_log_ns.saturating_sub(self.flushed_log_ns) >= FLUSH_LOG_INTERVAL_NS;
        let wall_due = || self.last_flush.elapsed() >= FLUSH_WALL_INTERVAL;
        if log_due || (self.flush_calls.is_multiple_of(CALLS_PER_CLOCK_READ) && wall_due()) {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Messages logged so far.
    #[must_use]
    pub const fn messages(&self) -> u64 {
        self.messages
    }

    /// Writes the summary and closes the file.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn finish(mut self) -> Result<(), LogError> {
        self.close()
    }

    /// Hands over the last batch, waits for the writing thread to end, then writes the Data
    /// End record, the summary section and the Footer. Does nothing the second time.
    fn close(&mut self) -> Result<(), LogError> {
        if self.writer.is_none() {
            return Ok(());
        }
        let handed = self.hand_over();
        let Some(mut writer) = self.writer.take() else {
            return handed;
        };
        handed?;
        let mut sink = writer.finish().map_err(|e| self.io_err(e))?;
        let tail = self.tail(&sink);
        sink.out
            .write_all(&tail)
            .and_then(|()| sink.out.flush())
            .map_err(|e| self.io_err(e))
    }

    /// Everything after the last chunk: Data End, the summary section, the Footer, the magic.
    fn tail(&self, sink: &Sink) -> Vec<u8> {
        let mut tail = Vec::new();
        write::record(&mut tail, op::DATA_END, |out| {
            out.extend_from_slice(&sink.crc.clone().finalize().to_le_bytes());
        });
        let base = sink.len;
        let summary_start = tail.len();
        let stats = &sink.stats;
        let mut statistics = Vec::new();
        write::record(&mut statistics, op::STATISTICS, |out| {
            out.extend_from_slice(&stats.messages.to_le_bytes());
            out.extend_from_slice(&7u16.to_le_bytes()); // schemas
            out.extend_from_slice(&u32::from(LAST_CHANNEL).to_le_bytes());
            out.extend_from_slice(&0u32.to_le_bytes()); // attachments
            out.extend_from_slice(&1u32.to_le_bytes()); // metadata
            out.extend_from_slice(&sink.chunks.to_le_bytes());
            let (first, last) = if stats.messages == 0 {
                (0, 0)
            } else {
                (stats.first_ns, stats.last_ns)
            };
            out.extend_from_slice(&first.to_le_bytes());
            out.extend_from_slice(&last.to_le_bytes());
            let counts: Vec<(u16, u64)> = (0..=LAST_CHANNEL)
                .map(|c| (c, stats.counts[usize::from(c)]))
                .filter(|&(_, n)| n > 0)
                .collect();
            out.extend_from_slice(&((counts.len() * 10) as u32).to_le_bytes());
            for (c, n) in counts {
                out.extend_from_slice(&c.to_le_bytes());
                out.extend_from_slice(&n.to_le_bytes());
            }
        });
        let mut offsets = Vec::new();
        for (opcode, group) in [
            (op::SCHEMA, &self.schemas),
            (op::CHANNEL, &self.channels),
            (op::STATISTICS, &statistics),
            (op::CHUNK_INDEX, &sink.chunk_indexes),
            (op::METADATA_INDEX, &self.metadata_index),
        ] {
            if group.is_empty() {
                continue;
            }
            offsets.push((opcode, base + tail.len() as u64, group.len() as u64));
            tail.extend_from_slice(group);
        }
        let summary_offset_start = base + tail.len() as u64;
        for (opcode, start, length) in offsets {
            write::record(&mut tail, op::SUMMARY_OFFSET, |out| {
                out.push(opcode);
                out.extend_from_slice(&start.to_le_bytes());
                out.extend_from_slice(&length.to_le_bytes());
            });
        }
        write::record(&mut tail, op::FOOTER, |out| {
            out.extend_from_slice(&(base + summary_start as u64).to_le_bytes());
            out.extend_from_slice(&summary_offset_start.to_le_bytes());
            out.extend_from_slice(&[0; 4]);
        });
        // The summary CRC covers the summary section and the Footer up to the CRC itself.
        let crc_at = tail.len() - 4;
        let crc = crc32fast::hash(&tail[summary_start..crc_at]);
        tail[crc_at..].copy_from_slice(&crc.to_le_bytes());
        tail.extend_from_slice(MAGIC);
        tail
    }
}

impl Drop for McapLog {
    /// A log dropped without [`finish`](McapLog::finish) (a run that failed or panicked) is
    /// finished here, as well as it can be: errors are ignored.
    fn drop(&mut self) {
        let _ = self.close();
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use embedded_can::StandardId;
    use mcap::records::Record;

    use super::*;

    /// A file of its own for a test, removed when dropped.
    struct TempFile(PathBuf);

    impl TempFile {
        fn new(test: &str) -> Self {
            let name = format!("hostsim-log-{}-{test}.mcap", std::process::id());
            Self(std::env::temp_dir().join(name))
        }
    }

    impl Drop for TempFile {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }

    fn frame(i: u64) -> CanFrame {
        let id = StandardId::new(0x201 + (i % 4) as u16).unwrap();
        let b = i.to_le_bytes();
        CanFrame::standard(id, &[b[0], b[1], b[2], 7, 0, 255, 100, 9]).unwrap()
    }

    /// Logs milliseconds `steps` of every kind of message (13.6 a millisecond).
    fn log_steps(log: &mut McapLog, steps: std::ops::Range<u64>) -> Result<(), LogError> {
        let snapshot = firmware::Controller::new(&firmware::Config::dji_m3508_example())
            .unwrap()
            .snapshot();
        let drive = firmware::Config::dji_m3508_example().drive;
        for i in steps {
            let t = i * 1_000_000;
            for k in 0..4 {
                let f = frame(i * 4 + k);
                log.bus(t + 100 * k, &f, Node::Drives, Fate::Delivered)?;
                log.can(t + 100 * k, Direction::Rx, &f)?;
                log.motor_feedback(t + 100 * k, &f, &drive)?;
            }
            log.can(t, Direction::Tx, &frame(i))?;
            if i % 10 == 0 {
                log.snapshot(t, &snapshot)?;
                log.poses(t, [0.1, 0.2, 0.3], [0.1, 0.2, 0.31])?;
                log.twist(t, [0.5, 0.0, -0.25], true)?;
            }
            if i % 100 == 0 {
                log.text(t, 2, "state Enabled")?;
            }
            log.maybe_flush()?;
        }
        Ok(())
    }

    /// A record of `bytes` at `offset`: its opcode and fields.
    fn record_at(bytes: &[u8], offset: usize) -> (u8, &[u8]) {
        let len = u64::from_le_bytes(bytes[offset + 1..offset + 9].try_into().unwrap());
        (bytes[offset], &bytes[offset + 9..offset + 9 + len as usize])
    }

    #[test]
    fn a_log_reads_back_with_its_indexes_and_summary() {
        let file = TempFile::new("indexes");
        let mut log = McapLog::create_with_chunk_size(&file.0, &BTreeMap::new(), 64 << 10).unwrap();
        log_steps(&mut log, 0..1500).unwrap();
        let written = log.messages();
        log.finish().unwrap();
        let bytes = std::fs::read(&file.0).unwrap();

        // The project's reader: complete, every CRC checked.
        let mut read = Vec::new();
        let report = for_each_message(
            &bytes,
            |topic, t, data| read.push((topic.to_string(), t, data.to_vec())),
            |_, _| {},
        )
        .unwrap();
        assert!(report.is_complete(), "{report}");
        assert_eq!(report.messages, written);

        // The mcap crate: statistics, and every chunk through its index.
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let stats = summary.stats.as_ref().unwrap();
        assert_eq!(stats.message_count, written);
        assert_eq!(stats.channel_count, 10);
        assert_eq!(stats.schema_count, 7);
        assert_eq!(stats.metadata_count, 1);
        assert_eq!(stats.chunk_count as usize, summary.chunk_indexes.len());
        assert!(summary.chunk_indexes.len() > 10);
        assert_eq!(
            (stats.message_start_time, stats.message_end_time),
            (0, 1_499_000_300)
        );
        assert_eq!(summary.metadata_indexes.len(), 1);
        let mut from_index = Vec::new();
        for index in &summary.chunk_indexes {
            let start = index.chunk_start_offset as usize;
            let (opcode, fields) = record_at(&bytes, start);
            assert_eq!(opcode, op::CHUNK);
            assert_eq!(9 + fields.len() as u64, index.chunk_length);
            let Record::Chunk { header, data } = mcap::parse_record(opcode, fields).unwrap() else {
                panic!("not a chunk");
            };
            let content = zstd::bulk::decompress(&data, header.uncompressed_size as usize).unwrap();
            // Every message of the chunk is in its channel's message index, at its offset.
            let mut indexed = 0;
            for (&channel, &offset) in &index.message_index_offsets {
                let (opcode, fields) = record_at(&bytes, offset as usize);
                let Record::MessageIndex(mi) = mcap::parse_record(opcode, fields).unwrap() else {
                    panic!("not a message index");
                };
                assert_eq!(mi.channel_id, channel);
                for entry in &mi.records {
                    let (opcode, fields) = record_at(&content, entry.offset as usize);
                    let Record::Message { header, .. } =
                        mcap::parse_record(opcode, fields).unwrap()
                    else {
                        panic!("not a message");
                    };
                    assert_eq!(
                        (header.channel_id, header.log_time),
                        (channel, entry.log_time)
                    );
                    indexed += 1;
                }
            }
            let end = index.chunk_start_offset + index.chunk_length;
            assert_eq!(
                index.message_index_offsets.values().min().copied(),
                Some(end)
            );
            let before = from_index.len();
            for m in summary.stream_chunk(&bytes, index).unwrap() {
                let m = m.unwrap();
                from_index.push((m.channel.topic.clone(), m.log_time, m.data.to_vec()));
            }
            assert_eq!(indexed, from_index.len() - before);
        }
        assert_eq!(from_index, read);
        let counts: HashMap<&str, usize> = read.iter().fold(HashMap::new(), |mut m, r| {
            *m.entry(r.0.as_str()).or_default() += 1;
            m
        });
        assert_eq!(counts["/can/bus"], 6000);
        assert_eq!(counts["/tf"], 300);
        assert_eq!(counts["/firmware/log"], 15);
    }

    #[test]
    fn an_event_is_small() {
        // What the simulation's thread writes per message, instead of ~200 bytes of JSON.
        assert!(size_of::<Event>() <= 40, "{}", size_of::<Event>());
    }

    #[test]
    fn the_same_messages_make_the_same_file() {
        let (a, b) = (TempFile::new("same-a"), TempFile::new("same-b"));
        for file in [&a, &b] {
            let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
            log_steps(&mut log, 0..1200).unwrap();
            log.finish().unwrap();
        }
        // Chunks close on log time here, long before the half second of wall-clock time.
        assert_eq!(std::fs::read(&a.0).unwrap(), std::fs::read(&b.0).unwrap());
    }

    /// A file that takes `room` bytes, then fails as a full disk does (or panics).
    struct Full {
        room: usize,
        panic: bool,
    }

    impl Write for Full {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            if self.room == 0 {
                assert!(!self.panic, "a writer that panics");
                return Err(io::ErrorKind::StorageFull.into());
            }
            let n = buf.len().min(self.room);
            self.room -= n;
            Ok(n)
        }

        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    fn log_on(path: &Path, out: Full) -> McapLog {
        McapLog::start(path, Box::new(out), Head::new(&BTreeMap::new()), 16 << 10).unwrap()
    }

    #[test]
    fn a_full_disk_comes_back_as_an_error_naming_the_file() {
        let path = Path::new("/nowhere/full.mcap");
        let mut log = log_on(
            path,
            Full {
                room: 100_000,
                panic: false,
            },
        );
        let err = log_steps(&mut log, 0..10_000).unwrap_err();
        let LogError::Io { path: p, source } = &err;
        assert_eq!(p, path);
        assert_eq!(source.kind(), io::ErrorKind::StorageFull, "{err}");
        // Found at the hand-over after the batch whose write failed (100 kB hold some 3,000
        // messages here, a batch is 250 ms or 3,400 messages), not at the end of the run.
        assert!(log.messages() < 1000 * 14, "{}", log.messages());
        // Every later hand-over fails too, and so does finishing.
        let err = log_steps(&mut log, 20_000..21_000).unwrap_err();
        assert!(err.to_string().contains("an earlier write failed"), "{err}");
        let LogError::Io { path: p, source } = log.finish().unwrap_err();
        assert_eq!(
            (p.as_path(), source.kind()),
            (path, io::ErrorKind::StorageFull)
        );
    }

    #[test]
    fn a_writer_thread_that_panics_is_an_error_not_a_panic() {
        let path = Path::new("/nowhere/panic.mcap");
        let mut log = log_on(
            path,
            Full {
                room: 0,
                panic: true,
            },
        );
        let err = log_steps(&mut log, 0..10_000).unwrap_err();
        assert!(
            err.to_string().contains("writer thread has stopped"),
            "{err}"
        );
        assert!(log.finish().is_err());
        // Dropped without finishing: no panic either.
        let mut log = log_on(
            path,
            Full {
                room: 0,
                panic: true,
            },
        );
        let _ = log_steps(&mut log, 0..100);
        drop(log);
    }
}
