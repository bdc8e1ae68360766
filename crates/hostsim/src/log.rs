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
//! # Crash safety
//!
//! Messages go into zstd-compressed chunks, each built in memory and appended to the file
//! whole, so the file on disk is always a prefix of the finished file (no chunk header is
//! patched afterwards). [`McapLog::maybe_flush`] closes the open chunk and hands the file's
//! buffer to the operating system once half a second of log time or of wall-clock time has
//! passed since the last flush, whichever comes first. A run that dies (SIGKILL, a panic, the
//! OOM killer) therefore leaves a file cut short whose every complete chunk is readable, and
//! loses at most the last half second of log time before it died (and at most about half a
//! second of wall-clock time): "at most the last second". The file is created as
//! `NAME.mcap.part` and renamed to `NAME.mcap` once its header and metadata are on disk, so a
//! `.mcap` file always opens. There is no `fsync`: this protects against the process dying,
//! not against the machine losing power.
//!
//! [`for_each_message`] reads such files: every complete chunk, then a [`Damage`] report that
//! names the byte offset where the unusable part starts (see [`read`]).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant as WallInstant};

use firmware::CanFrame;
use foxglove::Encode;
use foxglove::schemas::{FrameTransform, Log, PoseInFrame, Quaternion, Timestamp, Vector3};

use crate::bus::{Fate, Node};

mod json;
pub mod read;

pub use json::write_frame_json;
pub use read::{Damage, Problem, ReadReport, for_each_message};

/// Why a log could not be written.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// The file could not be created or written.
    #[error("{path}: {source}")]
    Io {
        /// The log file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The MCAP writer failed.
    #[error("{path}: MCAP: {source}")]
    Mcap {
        /// The log file.
        path: PathBuf,
        /// The writer's error.
        source: mcap::McapError,
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

/// An MCAP log being written. See the [module documentation](self).
pub struct McapLog {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    ch: Channels,
    seq: u32,
    buf: Vec<u8>,
    messages: u64,
    /// Largest log time written, ns.
    last_log_ns: u64,
    /// `last_log_ns` at the last flush.
    flushed_log_ns: u64,
    /// Wall-clock time of the last flush.
    last_flush: WallInstant,
    /// Calls of `maybe_flush`, to read the wall clock only every few.
    flush_calls: u64,
}

/// Log time between two flushes, ns: a run that dies loses at most this much log time.
const FLUSH_LOG_INTERVAL_NS: u64 = 500_000_000;

/// Wall-clock time between two flushes, for runs slower than real time.
const FLUSH_WALL_INTERVAL: Duration = Duration::from_millis(500);

/// [`McapLog::maybe_flush`] reads the wall clock on every this many calls.
const CALLS_PER_CLOCK_READ: u64 = 64;

/// Uncompressed size at which the writer closes a chunk, bytes.
pub const CHUNK_SIZE: u64 = 1 << 20;

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
        let file = File::create(&part).map_err(|source| LogError::Io {
            path: part.clone(),
            source,
        })?;
        let mcap_err = |source| LogError::Mcap {
            path: path.to_path_buf(),
            source,
        };
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(1)
            .chunk_size(Some(chunk_size))
            // Build each chunk in memory and append it whole, rather than writing a placeholder
            // header and patching it when the chunk closes: the file on disk is then always a
            // prefix of the finished file, and a killed run leaves a file cut short, never one
            // with an unpatched chunk header.
            .disable_seeking(true)
            .profile("")
            .library(concat!("mecanum hostsim ", env!("CARGO_PKG_VERSION")));
        let mut writer = options
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(mcap_err)?;
        let none = BTreeMap::new();
        let json_channel = |w: &mut mcap::Writer<_>, topic: &str, name: &str, schema: &str| {
            let sid = w.add_schema(name, "jsonschema", schema.as_bytes())?;
            w.add_channel(sid, topic, "json", &none)
        };
        let rx = json_channel(
            &mut writer,
            "/can/rx",
            "can_msgs/msg/Frame",
            CAN_FRAME_SCHEMA,
        )
        .map_err(mcap_err)?;
        let tx = json_channel(
            &mut writer,
            "/can/tx",
            "can_msgs/msg/Frame",
            CAN_FRAME_SCHEMA,
        )
        .map_err(mcap_err)?;
        let bus = json_channel(
            &mut writer,
            "/can/bus",
            "can_msgs/msg/Frame",
            CAN_FRAME_SCHEMA,
        )
        .map_err(mcap_err)?;
        let snapshot = json_channel(
            &mut writer,
            "/firmware/snapshot",
            "mecanum/FirmwareSnapshot",
            SNAPSHOT_SCHEMA,
        )
        .map_err(mcap_err)?;
        let twist = json_channel(&mut writer, "/cmd/twist", "mecanum/Twist", TWIST_SCHEMA)
            .map_err(mcap_err)?;
        let feedback = json_channel(
            &mut writer,
            "/motors/feedback",
            "mecanum/MotorFeedback",
            FEEDBACK_SCHEMA,
        )
        .map_err(mcap_err)?;
        let fox_channel =
            |w: &mut mcap::Writer<_>, topic: &str, schema: foxglove::Schema, enc: String| {
                let sid = w.add_schema(&schema.name, &schema.encoding, &schema.data)?;
                w.add_channel(sid, topic, &enc, &none)
            };
        let pose_schema = PoseInFrame::get_schema().expect("foxglove schemas carry a schema");
        let odom = fox_channel(
            &mut writer,
            "/odom/pose",
            pose_schema.clone(),
            PoseInFrame::get_message_encoding(),
        )
        .map_err(mcap_err)?;
        let truth = fox_channel(
            &mut writer,
            "/ground_truth/pose",
            pose_schema,
            PoseInFrame::get_message_encoding(),
        )
        .map_err(mcap_err)?;
        let tf = fox_channel(
            &mut writer,
            "/tf",
            FrameTransform::get_schema().expect("schema"),
            FrameTransform::get_message_encoding(),
        )
        .map_err(mcap_err)?;
        let log = fox_channel(
            &mut writer,
            "/firmware/log",
            Log::get_schema().expect("schema"),
            Log::get_message_encoding(),
        )
        .map_err(mcap_err)?;
        writer
            .write_metadata(&mcap::records::Metadata {
                name: "hostsim".to_string(),
                metadata: metadata.clone(),
            })
            .map_err(mcap_err)?;
        writer.flush().map_err(mcap_err)?;
        std::fs::rename(&part, path).map_err(|source| LogError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            writer,
            ch: Channels {
                rx,
                tx,
                bus,
                snapshot,
                twist,
                feedback,
                odom,
                truth,
                tf,
                log,
            },
            seq: 0,
            buf: Vec::with_capacity(512),
            messages: 0,
            last_log_ns: 0,
            flushed_log_ns: 0,
            last_flush: WallInstant::now(),
            flush_calls: 0,
        })
    }

    fn mcap_err(&self, source: mcap::McapError) -> LogError {
        LogError::Mcap {
            path: self.path.clone(),
            source,
        }
    }

    fn write(&mut self, channel: u16, t_ns: u64) -> Result<(), LogError> {
        self.seq = self.seq.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: self.seq,
            log_time: t_ns,
            publish_time: t_ns,
        };
        self.messages += 1;
        self.last_log_ns = self.last_log_ns.max(t_ns);
        self.writer
            .write_to_known_channel(&header, &self.buf)
            .map_err(|e| LogError::Mcap {
                path: self.path.clone(),
                source: e,
            })
    }

    fn encode_fox<T: Encode>(&mut self, msg: &T) {
        self.buf.clear();
        // Encoding into a Vec cannot run out of space.
        let _ = msg.encode(&mut self.buf);
    }

    /// Logs a frame the firmware received or sent.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn can(&mut self, t_ns: u64, dir: Direction, frame: &CanFrame) -> Result<(), LogError> {
        self.buf.clear();
        write_frame_json(&mut self.buf, t_ns, frame, None);
        let ch = match dir {
            Direction::Rx => self.ch.rx,
            Direction::Tx => self.ch.tx,
        };
        self.write(ch, t_ns)
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
        self.buf.clear();
        write_frame_json(&mut self.buf, t_ns, frame, Some((sender, fate)));
        self.write(self.ch.bus, t_ns)
    }

    /// Logs a firmware snapshot.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn snapshot(&mut self, t_ns: u64, s: &firmware::control::Snapshot) -> Result<(), LogError> {
        self.buf.clear();
        let arr = |a: &[f32; 4]| format!("[{},{},{},{}]", a[0], a[1], a[2], a[3]);
        let _ = write!(
            self.buf,
            r#"{{"state":"{:?}","fault":"{:?}","commanded":{{"vx":{},"vy":{},"wz":{}}},"measured":{{"vx":{},"vy":{},"wz":{}}},"wheel_setpoints":{},"wheel_speeds":{},"currents":{},"motors_online":{},"rx_errors":{},"unknown_ids":{}}}"#,
            s.state,
            s.fault,
            s.commanded.vx,
            s.commanded.vy,
            s.commanded.wz,
            s.measured.vx,
            s.measured.vy,
            s.measured.wz,
            arr(&s.wheel_setpoints.0),
            arr(&s.wheel_speeds.0),
            arr(&s.currents),
            s.motors_online,
            s.rx_errors.total() - s.rx_errors.unknown_id,
            s.rx_errors.unknown_id,
        );
        self.write(self.ch.snapshot, t_ns)
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
        self.buf.clear();
        match *drive {
            firmware::config::Drive::Dji { model, .. } => {
                let Ok(f) = dji::Feedback::decode(frame, model) else {
                    return Ok(());
                };
                let _ = write!(
                    self.buf,
                    r#"{{"protocol":"dji","id":{},"rotor_angle":{},"rotor_speed_rpm":{},"current_a":{},"temperature_c":{}}}"#,
                    f.esc.get(),
                    f.rotor_angle,
                    f.rotor_speed_rpm,
                    f.current_amps(),
                    f.temperature_c
                );
            }
            firmware::config::Drive::Odrive { .. } => {
                let Ok(a) = odrive::Feedback::decode(frame) else {
                    return Ok(());
                };
                let id = a.node.get();
                let _ = match a.msg {
                    odrive::Feedback::EncoderEstimates { pos, vel } => write!(
                        self.buf,
                        r#"{{"protocol":"odrive","id":{id},"pos_rev":{pos},"vel_rev_s":{vel}}}"#
                    ),
                    odrive::Feedback::Heartbeat(h) => write!(
                        self.buf,
                        r#"{{"protocol":"odrive","id":{id},"axis_error":{},"axis_state":"{:?}"}}"#,
                        h.axis_error, h.axis_state
                    ),
                    odrive::Feedback::Error { active_errors, .. } => write!(
                        self.buf,
                        r#"{{"protocol":"odrive","id":{id},"axis_error":{active_errors}}}"#
                    ),
                };
            }
        }
        self.write(self.ch.feedback, t_ns)
    }

    /// Logs the host's twist setpoint.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn twist(&mut self, t_ns: u64, twist: [f32; 3], streaming: bool) -> Result<(), LogError> {
        self.buf.clear();
        let _ = write!(
            self.buf,
            r#"{{"vx":{},"vy":{},"wz":{},"streaming":{}}}"#,
            twist[0], twist[1], twist[2], streaming
        );
        self.write(self.ch.twist, t_ns)
    }

    /// Logs the odometry pose (`odom` frame) and the ground-truth pose (`world` frame), and
    /// both as transforms for Foxglove's 3D panel.
    ///
    /// # Errors
    /// [`LogError`] if the write fails.
    pub fn poses(&mut self, t_ns: u64, odom: [f64; 3], truth: [f64; 3]) -> Result<(), LogError> {
        for (pose, frame, child, pose_ch) in [
            (odom, "odom", "base_link_odom", self.ch.odom),
            (truth, "world", "base_link", self.ch.truth),
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
            self.encode_fox(&msg);
            self.write(pose_ch, t_ns)?;
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
            self.encode_fox(&tf);
            self.write(self.ch.tf, t_ns)?;
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
        self.encode_fox(&msg);
        self.write(self.ch.log, t_ns)
    }

    /// Closes the open chunk and hands the file's buffer to the operating system if half a
    /// second of log time, or of wall-clock time, has passed since the last flush (see
    /// [Crash safety](self#crash-safety)). Call it after each step's messages, at least every
    /// few milliseconds of log time: it reads the wall clock only on every 64th call.
    ///
    /// # Errors
    /// [`LogError`] if the flush fails.
    pub fn maybe_flush(&mut self) -> Result<(), LogError> {
        self.flush_calls += 1;
        let log_due = self.last_log_ns.saturating_sub(self.flushed_log_ns) >= FLUSH_LOG_INTERVAL_NS;
        let wall_due = || self.last_flush.elapsed() >= FLUSH_WALL_INTERVAL;
        if log_due || (self.flush_calls.is_multiple_of(CALLS_PER_CLOCK_READ) && wall_due()) {
            self.writer.flush().map_err(|e| self.mcap_err(e))?;
            self.flushed_log_ns = self.last_log_ns;
            self.last_flush = WallInstant::now();
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
        self.writer.finish().map_err(|e| self.mcap_err(e))?;
        Ok(())
    }
}
