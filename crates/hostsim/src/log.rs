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
//! | `/odom/pose` | `foxglove.PoseInFrame` | the firmware's odometry (frame `odom`) |
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
//! The writer writes the MCAP records itself (module `write`, after
//! <https://mcap.dev/spec>): the magic and the Header, the Schema and Channel records and the
//! `hostsim` Metadata record; then the messages in zstd-compressed chunks, each Chunk record
//! followed by one Message Index record per channel it holds; then the Data End record (with
//! the CRC of everything before it), the summary section (the Schema and Channel records
//! again, Statistics, a Chunk Index per chunk, the Metadata Index, and a Summary Offset per
//! group), the Footer (with the summary's CRC) and the magic. Every Chunk record carries the
//! CRC of its uncompressed content.
//!
//! The messages of a chunk are built, uncompressed, on the caller's thread. Closing a chunk
//! hands it to a second thread, which computes its CRC, compresses it (zstd level
//! [`ZSTD_LEVEL`]) and appends it with its message indexes in one write, while the caller goes
//! on with the next chunk. Message order and content do not depend on that thread: the file
//! holds the messages in the order they were logged.
//!
//! # Crash safety
//!
//! Each chunk is built in memory and appended to the file whole, so the file on disk is always
//! a prefix of the finished file (no chunk header is patched afterwards). The open chunk is
//! closed and handed to the writing thread once a quarter of a second of log time, or half a
//! second of wall-clock time, has passed since the last chunk was closed (and whenever it
//! reaches its size, [`CHUNK_SIZE`] uncompressed bytes by default); see
//! [`McapLog::maybe_flush`]. At most one chunk is in flight: closing a chunk first waits until
//! the previous one is written. A run that dies (SIGKILL, a panic, the OOM killer) therefore
//! leaves a file cut short whose every complete chunk is readable, and loses at most the chunk
//! in flight and the open one: the last half second of log time before it died (and at most
//! about half a second of wall-clock time plus the few milliseconds of compressing a chunk):
//! "at most the last second". The file is created as `NAME.mcap.part` and renamed to
//! `NAME.mcap` once its header, channels and metadata are on disk, so a `.mcap` file always
//! opens. There is no `fsync`: this protects against the process dying, not against the
//! machine losing power.
//!
//! An error of the writing thread (a full disk, say) comes back as [`LogError::Io`] from the
//! next call that closes a chunk ([`McapLog::maybe_flush`], a message that fills the chunk, or
//! [`McapLog::finish`]), and every later such call fails too.
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
use foxglove::schemas::{FrameTransform, Log, PoseInFrame, Quaternion, Timestamp, Vector3};
use mcap::records::op;

use crate::bus::{Fate, Node};

mod json;
pub mod read;
mod write;

pub use json::write_frame_json;
pub use read::{Damage, Problem, ReadReport, for_each_message};
use write::{Chunk, ChunkWriter, Sink};

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
    seq: u32,
    /// The open chunk.
    chunk: Chunk,
    /// Uncompressed size at which the open chunk is closed, bytes.
    chunk_size: usize,
    /// The thread that compresses and appends chunks; `None` once finished.
    writer: Option<ChunkWriter>,
    /// Set by the first write error: every later write fails with it.
    failed: Option<(io::ErrorKind, String)>,
    /// The Schema and Channel records as written at the start, for the summary.
    schemas: Vec<u8>,
    channels: Vec<u8>,
    /// The Metadata Index record of the `hostsim` metadata.
    metadata_index: Vec<u8>,
    /// Messages per channel id.
    counts: [u64; LAST_CHANNEL as usize + 1],
    messages: u64,
    /// Earliest log time written, ns (`u64::MAX` before the first message).
    first_log_ns: u64,
    /// Largest log time written, ns.
    last_log_ns: u64,
    /// `last_log_ns` when the last chunk was closed.
    flushed_log_ns: u64,
    /// Wall-clock time when the last chunk was closed.
    last_flush: WallInstant,
    /// Calls of `maybe_flush`, to read the wall clock only every few.
    flush_calls: u64,
}

/// Log time between two chunk closes, ns. The chunk in flight and the open one are what a run
/// that dies loses: at most twice this.
const FLUSH_LOG_INTERVAL_NS: u64 = 250_000_000;

/// Wall-clock time between two chunk closes, for runs slower than real time.
const FLUSH_WALL_INTERVAL: Duration = Duration::from_millis(500);

/// [`McapLog::maybe_flush`] reads the wall clock on every this many calls.
const CALLS_PER_CLOCK_READ: u64 = 64;

/// Uncompressed size at which the writer closes a chunk, bytes. With the square scenario's
/// ~2.4 MB of messages per simulated second, chunks close on log time (about 600 kB) first.
pub const CHUNK_SIZE: u64 = 1 << 20;

/// zstd level of the chunks (the level the `mcap` crate's writer was given before this
/// writer replaced it).
pub const ZSTD_LEVEL: i32 = 1;

/// Where a log is written until its header is on disk: `NAME.mcap.part` for `NAME.mcap`.
#[must_use]
pub fn part_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".part");
    PathBuf::from(name)
}

fn ns_stamp(t_ns: u64) -> Timestamp {
    Timestamp::new((t_ns / 1_000_000_000) as u32, (t_ns % 1_000_000_000) as u32)
}

fn yaw_quaternion(yaw: f64) -> Quaternion {
    let (s, c) = (yaw * 0.5).sin_cos();
    Quaternion {
        x: 0.0,
        y: 0.0,
        z: s,
        w: c,
    }
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

/// Four numbers as a JSON array, formatted in place (no `String` per array).
struct JsonArray<'a>(&'a [f32; 4]);

impl std::fmt::Display for JsonArray<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [a, b, c, d] = self.0;
        write!(f, "[{a},{b},{c},{d}]")
    }
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
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head.bytes);
        let sink = Sink {
            out,
            len: head.bytes.len() as u64,
            crc,
            chunk_indexes: Vec::new(),
            chunks: 0,
        };
        let writer = ChunkWriter::start(sink, ZSTD_LEVEL).map_err(|source| LogError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let chunk_size = usize::try_from(chunk_size).unwrap_or(usize::MAX);
        Ok(Self {
            path: path.to_path_buf(),
            seq: 0,
            chunk: Chunk::new(
                usize::from(LAST_CHANNEL) + 1,
                chunk_size.min(CHUNK_SIZE as usize) + 4096,
            ),
            chunk_size,
            writer: Some(writer),
            failed: None,
            schemas: head.schemas,
            channels: head.channels,
            metadata_index: head.metadata_index,
            counts: [0; LAST_CHANNEL as usize + 1],
            messages: 0,
            first_log_ns: u64::MAX,
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

    /// Starts a message on `channel` at `t_ns`: its data is then appended to
    /// `self.chunk.records` and the message ended with [`end`](Self::end). Returns where the
    /// record starts.
    #[inline]
    fn begin(&mut self, channel: u16, t_ns: u64) -> usize {
        self.seq = self.seq.wrapping_add(1);
        let start = self.chunk.records.len();
        write::begin_message(&mut self.chunk.records, channel, self.seq, t_ns);
        start
    }

    /// Ends the message begun at `start` with [`begin`](Self::begin); closes the chunk if it
    /// has reached its size.
    #[inline]
    fn end(&mut self, channel: u16, t_ns: u64, start: usize) -> Result<(), LogError> {
        let chunk = &mut self.chunk;
        write::end_message(&mut chunk.records, start);
        chunk.index[usize::from(channel)].push((t_ns, start as u64));
        chunk.start_ns = chunk.start_ns.min(t_ns);
        chunk.end_ns = chunk.end_ns.max(t_ns);
        self.counts[usize::from(channel)] += 1;
        self.messages += 1;
        self.first_log_ns = self.first_log_ns.min(t_ns);
        self.last_log_ns = self.last_log_ns.max(t_ns);
        if chunk.records.len() >= self.chunk_size {
            self.close_chunk()?;
        }
        Ok(())
    }

    /// Hands the open chunk, if it holds anything, to the writing thread (after waiting for
    /// the one in flight), and restarts the flush clocks.
    fn close_chunk(&mut self) -> Result<(), LogError> {
        self.flushed_log_ns = self.last_log_ns;
        self.last_flush = WallInstant::now();
        if let Some((kind, text)) = &self.failed {
            // Do not let a log that can no longer be written grow in memory.
            self.chunk.records.clear();
            for entries in &mut self.chunk.index {
                entries.clear();
            }
            return Err(self.io_err(io::Error::new(
                *kind,
                format!("an earlier write failed: {text}"),
            )));
        }
        if self.chunk.records.is_empty() {
            return Ok(());
        }
        let Some(writer) = self.writer.as_mut() else {
            return Ok(());
        };
        let spare = writer.wait().and_then(|spare| {
            let next = spare.unwrap_or_else(|| {
                Chunk::new(self.chunk.index.len(), self.chunk.records.capacity())
            });
            let full = std::mem::replace(&mut self.chunk, next);
            writer.send(full)
        });
        match spare {
            Ok(_) => Ok(()),
            Err(e) => {
                self.failed = Some((e.kind(), e.to_string()));
                Err(self.io_err(e))
            }
        }
    }

    /// Logs a frame the firmware received or sent.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn can(&mut self, t_ns: u64, dir: Direction, frame: &CanFrame) -> Result<(), LogError> {
        let ch = match dir {
            Direction::Rx => CHANNELS.rx,
            Direction::Tx => CHANNELS.tx,
        };
        let start = self.begin(ch, t_ns);
        write_frame_json(&mut self.chunk.records, t_ns, frame, None);
        self.end(ch, t_ns, start)
    }

    /// Logs a frame on the bus with its sender and fate.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn bus(
        &mut self,
        t_ns: u64,
        frame: &CanFrame,
        sender: Node,
        fate: Fate,
    ) -> Result<(), LogError> {
        let start = self.begin(CHANNELS.bus, t_ns);
        write_frame_json(&mut self.chunk.records, t_ns, frame, Some((sender, fate)));
        self.end(CHANNELS.bus, t_ns, start)
    }

    /// Logs a firmware snapshot.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn snapshot(&mut self, t_ns: u64, s: &firmware::control::Snapshot) -> Result<(), LogError> {
        let start = self.begin(CHANNELS.snapshot, t_ns);
        let buf = &mut self.chunk.records;
        let _ = write!(
            buf,
            r#"{{"state":"{:?}","fault":"{:?}","commanded":{{"vx":{},"vy":{},"wz":{}}},"measured":{{"vx":{},"vy":{},"wz":{}}},"wheel_setpoints":{},"wheel_speeds":{},"currents":{},"motors_online":{},"rx_errors":{},"unknown_ids":{}}}"#,
            s.state,
            s.fault,
            s.commanded.vx,
            s.commanded.vy,
            s.commanded.wz,
            s.measured.vx,
            s.measured.vy,
            s.measured.wz,
            JsonArray(&s.wheel_setpoints.0),
            JsonArray(&s.wheel_speeds.0),
            JsonArray(&s.currents),
            s.motors_online,
            s.rx_errors.total() - s.rx_errors.unknown_id,
            s.rx_errors.unknown_id,
        );
        self.end(CHANNELS.snapshot, t_ns, start)
    }

    /// Logs a drive feedback frame, decoded; frames that are not drive feedback are skipped.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn motor_feedback(
        &mut self,
        t_ns: u64,
        frame: &CanFrame,
        drive: &firmware::config::Drive,
    ) -> Result<(), LogError> {
        use firmware::protocol::{dji, odrive};
        let ch = CHANNELS.feedback;
        match *drive {
            firmware::config::Drive::Dji { model, .. } => {
                let Ok(f) = dji::Feedback::decode(frame, model) else {
                    return Ok(());
                };
                let start = self.begin(ch, t_ns);
                let _ = write!(
                    self.chunk.records,
                    r#"{{"protocol":"dji","id":{},"rotor_angle":{},"rotor_speed_rpm":{},"current_a":{},"temperature_c":{}}}"#,
                    f.esc.get(),
                    f.rotor_angle,
                    f.rotor_speed_rpm,
                    f.current_amps(),
                    f.temperature_c
                );
                self.end(ch, t_ns, start)
            }
            firmware::config::Drive::Odrive { .. } => {
                let Ok(a) = odrive::Feedback::decode(frame) else {
                    return Ok(());
                };
                let id = a.node.get();
                let start = self.begin(ch, t_ns);
                let buf = &mut self.chunk.records;
                let _ = match a.msg {
                    odrive::Feedback::EncoderEstimates { pos, vel } => write!(
                        buf,
                        r#"{{"protocol":"odrive","id":{id},"pos_rev":{pos},"vel_rev_s":{vel}}}"#
                    ),
                    odrive::Feedback::Heartbeat(h) => write!(
                        buf,
                        r#"{{"protocol":"odrive","id":{id},"axis_error":{},"axis_state":"{:?}"}}"#,
                        h.axis_error, h.axis_state
                    ),
                    odrive::Feedback::Error { active_errors, .. } => write!(
                        buf,
                        r#"{{"protocol":"odrive","id":{id},"axis_error":{active_errors}}}"#
                    ),
                };
                self.end(ch, t_ns, start)
            }
        }
    }

    /// Logs the host's twist setpoint.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn twist(&mut self, t_ns: u64, twist: [f32; 3], streaming: bool) -> Result<(), LogError> {
        let start = self.begin(CHANNELS.twist, t_ns);
        let _ = write!(
            self.chunk.records,
            r#"{{"vx":{},"vy":{},"wz":{},"streaming":{}}}"#,
            twist[0], twist[1], twist[2], streaming
        );
        self.end(CHANNELS.twist, t_ns, start)
    }

    /// Logs a Foxglove message on `channel`.
    fn fox<T: Encode>(&mut self, channel: u16, t_ns: u64, msg: &T) -> Result<(), LogError> {
        let start = self.begin(channel, t_ns);
        // Encoding into a Vec cannot run out of space.
        let _ = msg.encode(&mut self.chunk.records);
        self.end(channel, t_ns, start)
    }

    /// Logs the odometry pose (`odom` frame) and the ground-truth pose (`world` frame), and
    /// both as transforms for Foxglove's 3D panel.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn poses(&mut self, t_ns: u64, odom: [f64; 3], truth: [f64; 3]) -> Result<(), LogError> {
        for (pose, frame, child, pose_ch) in [
            (odom, "odom", "base_link_odom", CHANNELS.odom),
            (truth, "world", "base_link", CHANNELS.truth),
        ] {
            let msg = PoseInFrame {
                timestamp: Some(ns_stamp(t_ns)),
                frame_id: frame.to_string(),
                pose: Some(foxglove::schemas::Pose {
                    position: Some(Vector3 {
                        x: pose[0],
                        y: pose[1],
                        z: 0.0,
                    }),
                    orientation: Some(yaw_quaternion(pose[2])),
                }),
            };
            self.fox(pose_ch, t_ns, &msg)?;
            let tf = FrameTransform {
                timestamp: Some(ns_stamp(t_ns)),
                parent_frame_id: "world".to_string(),
                child_frame_id: child.to_string(),
                translation: Some(Vector3 {
                    x: pose[0],
                    y: pose[1],
                    z: 0.0,
                }),
                rotation: Some(yaw_quaternion(pose[2])),
            };
            self.fox(CHANNELS.tf, t_ns, &tf)?;
        }
        Ok(())
    }

    /// Logs a text line (state change, fault) at `level` (foxglove: 1 debug, 2 info, 3 warning,
    /// 4 error).
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn text(&mut self, t_ns: u64, level: i32, message: &str) -> Result<(), LogError> {
        let msg = Log {
            timestamp: Some(ns_stamp(t_ns)),
            level,
            message: message.to_string(),
            name: "firmware".to_string(),
            file: String::new(),
            line: 0,
        };
        self.fox(CHANNELS.log, t_ns, &msg)
    }

    /// Closes the open chunk and hands it to the writing thread if a quarter of a second of
    /// log time, or half a second of wall-clock time, has passed since a chunk was last closed
    /// (see [Crash safety](self#crash-safety)). Call it after each step's messages, at least
    /// every few milliseconds of log time: it reads the wall clock only on every 64th call.
    ///
    /// # Errors
    /// [`LogError`] if writing a chunk failed (this one's predecessor, or an earlier one).
    pub fn maybe_flush(&mut self) -> Result<(), LogError> {
        self.flush_calls += 1;
        let log_due = self.last_log_ns.saturating_sub(self.flushed_log_ns) >= FLUSH_LOG_INTERVAL_NS;
        let wall_due = || self.last_flush.elapsed() >= FLUSH_WALL_INTERVAL;
        if log_due || (self.flush_calls.is_multiple_of(CALLS_PER_CLOCK_READ) && wall_due()) {
            self.close_chunk()?;
        }
        Ok(())
    }

    /// Messages written so far.
    #[must_use]
    pub const fn messages(&self) -> u64 {
        self.messages
    }

    /// Writes the summary and closes the file.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn finish(mut self) -> Result<(), LogError> {
        self.close()
    }

    /// Writes the open chunk, waits for the writing thread to end, then writes the Data End
    /// record, the summary section and the Footer. Does nothing the second time.
    fn close(&mut self) -> Result<(), LogError> {
        if self.writer.is_none() {
            return Ok(());
        }
        let closed = self.close_chunk();
        let Some(mut writer) = self.writer.take() else {
            return closed;
        };
        closed?;
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
        let mut statistics = Vec::new();
        write::record(&mut statistics, op::STATISTICS, |out| {
            out.extend_from_slice(&self.messages.to_le_bytes());
            out.extend_from_slice(&7u16.to_le_bytes()); // schemas
            out.extend_from_slice(&u32::from(LAST_CHANNEL).to_le_bytes());
            out.extend_from_slice(&0u32.to_le_bytes()); // attachments
            out.extend_from_slice(&1u32.to_le_bytes()); // metadata
            out.extend_from_slice(&sink.chunks.to_le_bytes());
            let (first, last) = if self.messages == 0 {
                (0, 0)
            } else {
                (self.first_log_ns, self.last_log_ns)
            };
            out.extend_from_slice(&first.to_le_bytes());
            out.extend_from_slice(&last.to_le_bytes());
            let counts: Vec<(u16, u64)> = (0..=LAST_CHANNEL)
                .map(|c| (c, self.counts[usize::from(c)]))
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

    /// Logs `steps` milliseconds of every kind of message.
    fn log_steps(log: &mut McapLog, steps: u64) -> Result<(), LogError> {
        let snapshot = firmware::Controller::new(&firmware::Config::dji_m3508_example())
            .unwrap()
            .snapshot();
        let drive = firmware::Config::dji_m3508_example().drive;
        for i in 0..steps {
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
        log_steps(&mut log, 1500).unwrap();
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
    fn the_same_messages_make_the_same_file() {
        let (a, b) = (TempFile::new("same-a"), TempFile::new("same-b"));
        for file in [&a, &b] {
            let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
            log_steps(&mut log, 1200).unwrap();
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
        let err = log_steps(&mut log, 10_000).unwrap_err();
        let LogError::Io { path: p, source } = &err;
        assert_eq!(p, path);
        assert_eq!(source.kind(), io::ErrorKind::StorageFull, "{err}");
        // Found within a chunk or two of the failed write (100 kB hold some 3,000 messages
        // here), not at the end of the run.
        assert!(log.messages() < 400 * 23, "{}", log.messages());
        // Every later write that reaches the file fails too, and so does finishing.
        let err = log_steps(&mut log, 1000).unwrap_err();
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
        let err = log_steps(&mut log, 10_000).unwrap_err();
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
        let _ = log_steps(&mut log, 100);
        drop(log);
    }
}
