//! Writing logs: [`McapLog`], and the thread that encodes and writes them.
//!
//! The caller's thread (a simulation, a control loop) only records each message's values in
//! a batch, and hands the batch over to a second thread at each flush
//! ([`McapLog::maybe_flush`]). That thread encodes the messages in CDR ([`crate::msg`]) and
//! writes them with the `mcap` crate's [`Writer`](mcap::Writer), in zstd chunks of at most
//! [`CHUNK_SIZE`] uncompressed bytes. The file is written as [`crate::part_path`] and
//! renamed when the log is finished; an error of the writing thread
//! comes back as a [`LogError`] from the next hand-over. After [`McapLog::drop_when_behind`] a hand-over never blocks: messages are
//! dropped and counted instead.
//!
//! A [`MessageTap`] installed with [`McapLog::set_tap`] sees every message on that thread,
//! as it is written: the channel, the log and publish times, and the very CDR bytes of the
//! file (a live view serves them: the `live` crate). It runs after the message is in the
//! `mcap` writer, on the writing thread, so the caller never waits on it; a tap must not
//! block either, or the hand-overs that wait for the writer would wait for it.
//! [`McapLog::set_flush_interval`] makes the hand-overs (and so what a tap receives at once)
//! more frequent than every quarter second.
//!
//! The rest is specified in `docs/logs.md`: section "The writer thread" (why the file does
//! not depend on the threads' timing), "Crash safety" (what a killed run leaves: at most the
//! last second lost, the log a `.part` until finished) and "A control loop that must not
//! wait: dropping instead of blocking".

use std::collections::BTreeMap;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TryRecvError, TrySendError, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant as WallInstant};

use firmware::CanFrame;
use firmware::control::Snapshot;
use mcap::records::{MessageHeader, Metadata};
use mcap::write::NoSeek;

use crate::msg::{self, Header, RosMsg};
use crate::output::Staged;
use crate::{Channel, METADATA_NAME, POD_NAMES, PROFILE, WHEEL_NAMES, frames};

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

/// Direction of a frame, seen from the firmware.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Direction {
    /// Received by the firmware (`/can/rx`).
    Rx,
    /// Sent by the firmware (`/can/tx`).
    Tx,
}

/// Whose odometry a pose is.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum OdometrySource {
    /// The firmware's (`/odom`, `odom` → `base_link`).
    Firmware,
    /// The plant's ground truth (`/ground_truth/odom`, `odom` → `base_link_truth`).
    GroundTruth,
}

/// Log time between two hand-overs, ns, by default ([`McapLog::set_flush_interval`]). The
/// batch in flight and the open one are what a run that dies loses: at most twice this.
const FLUSH_LOG_INTERVAL_NS: u64 = 250_000_000;

/// Wall-clock time between two hand-overs, for runs slower than real time, by default: twice
/// the log-time interval.
const FLUSH_WALL_INTERVAL: Duration = Duration::from_millis(500);

/// What sees every message of a log as the writing thread writes it: a live view, say. See
/// [`McapLog::set_tap`].
///
/// Every method but [`channels`](Self::channels) runs on the writing thread, between the
/// messages it writes: a tap that
/// blocks holds up the log (and a caller whose hand-over waits for the writer), so a tap
/// hands the bytes on without waiting, and drops (and counts) what it cannot hand on.
pub trait MessageTap: Send {
    /// Once, when the tap is installed ([`McapLog::set_tap`], on the caller's thread) and
    /// before any message: the log's channels, in channel id order. Each names its
    /// topic ([`Channel::topic`]), its ROS 2 type ([`Channel::def`]: `name`, and the
    /// `ros2msg` text of the file's Schema record, [`msg::MsgDef::schema_text`]); the
    /// message encoding is `cdr`.
    fn channels(&mut self, channels: &[Channel]);

    /// A message, as the file has it: its channel, log time and publish time (ns), and its
    /// CDR bytes (the Message record's data). Called in file order.
    fn message(&mut self, channel: Channel, log_ns: u64, publish_ns: u64, cdr: &[u8]);

    /// The end of a hand-over's messages: they are all in the file's buffer now (and on disk
    /// but for the file's own buffering). A tap that gathers messages sends them here.
    fn end_batch(&mut self) {}

    /// A status of the tap's own to add to each `/diagnostics` message after the firmware's
    /// ([`DIAGNOSTIC_NAME`]), in the file and so for every reader of it: a live view reports
    /// its clients and what they lost there. `None` (the default): the message is as without
    /// a tap.
    fn status(&mut self) -> Option<msg::DiagnosticStatus> {
        None
    }
}

/// [`McapLog::maybe_flush`] reads the wall clock on every this many calls.
const CALLS_PER_CLOCK_READ: u64 = 64;

/// Events in a batch at which it is handed over even if [`McapLog::maybe_flush`] is not
/// called: bounds a batch's memory (about 3 MB).
const MAX_BATCH_EVENTS: usize = 1 << 16;

/// Uncompressed size at which the writer closes a chunk, bytes. The square scenario logs
/// about 150 kB of messages in the quarter second between two hand-overs, so its chunks close
/// at the hand-overs.
pub const CHUNK_SIZE: u64 = 1 << 20;

/// zstd level of the chunks (the `mcap` crate takes levels from 1). See `docs/benchmarks.md`
/// for the level against size and time.
pub const ZSTD_LEVEL: u32 = 1;

/// A logged message, or the two of an odometry, as values: the writing thread encodes them.
#[derive(Clone, Copy)]
enum Event {
    /// `/can/rx` or `/can/tx`.
    Frame {
        log_ns: u64,
        publish_ns: u64,
        stamp_ns: u64,
        frame: CanFrame,
        dir: Direction,
    },
    /// `/can/faults`: [`Batch::faults`]`[index]`.
    Fault { t_ns: u64, index: u32 },
    /// `/cmd_vel`.
    Twist { t_ns: u64, twist: [f32; 3] },
    /// `/joint_states` and `/diagnostics`: [`Batch::snapshots`]`[index]`.
    Snapshot { t_ns: u64, index: u32 },
    /// `/odom` or `/ground_truth/odom`, and `/tf`: [`Batch::odometry`]`[index]`.
    Odometry { t_ns: u64, index: u32 },
    /// `/rosout`: [`Batch::texts`]`[index]`.
    Text { t_ns: u64, level: u8, index: u32 },
    /// `/firmware/steps`.
    Step { t_ns: u64, kind: u8 },
    /// `/diagnostics` with the tap's status alone ([`McapLog::tap_status`]).
    TapStatus { t_ns: u64 },
}

/// A `/can/faults` message's values.
#[derive(Clone, Copy)]
struct FaultRecord {
    sender: &'static str,
    fate: &'static str,
    sent: CanFrame,
    received: [u8; 8],
}

/// An odometry message's values.
#[derive(Clone, Copy)]
struct OdometryRecord {
    source: OdometrySource,
    pose: [f64; 3],
    twist: [f64; 3],
}

/// The messages logged between two hand-overs to the writing thread, in order. The larger
/// values are kept beside the events, so that an event stays small.
#[derive(Default)]
struct Batch {
    events: Vec<Event>,
    faults: Vec<FaultRecord>,
    snapshots: Vec<Snapshot>,
    odometry: Vec<OdometryRecord>,
    texts: Vec<String>,
    /// A tap for the writing thread to install before this batch's messages
    /// ([`McapLog::set_tap`]).
    tap: Option<Box<dyn MessageTap>>,
}

impl Batch {
    fn is_empty(&self) -> bool {
        self.events.is_empty()
    }

    fn clear(&mut self) {
        self.events.clear();
        self.faults.clear();
        self.snapshots.clear();
        self.odometry.clear();
        self.texts.clear();
    }
}

/// The file under the `mcap` writer: passes writes on until the first error, then refuses
/// every later one (so that nothing follows a failed write, not even the summary the `mcap`
/// writer tries to write when dropped), and refuses to write while its thread panics.
struct Out {
    inner: Box<dyn Write + Send>,
    failed: bool,
    /// Bytes passed on so far: [`McapLog::bytes_written`].
    written: Arc<AtomicU64>,
}

impl Out {
    fn check(&self) -> io::Result<()> {
        if self.failed || std::thread::panicking() {
            return Err(io::Error::other("an earlier write to this log failed"));
        }
        Ok(())
    }
}

impl Write for Out {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.check()?;
        let n = self.inner.write(buf).inspect_err(|_| self.failed = true)?;
        self.written.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.check()?;
        self.inner.flush().inspect_err(|_| self.failed = true)
    }
}

type Writer = mcap::Writer<NoSeek<Out>>;

fn mcap_err(e: mcap::McapError) -> io::Error {
    match e {
        mcap::McapError::Io(e) => e,
        other => io::Error::other(other),
    }
}

/// Starts an MCAP file on `out`: the header, the schemas and channels, the metadata, all on
/// disk when this returns.
fn start_file(
    out: Box<dyn Write + Send>,
    metadata: &BTreeMap<String, String>,
    chunk_size: u64,
    written: Arc<AtomicU64>,
) -> io::Result<Writer> {
    let options = mcap::WriteOptions::new()
        .profile(PROFILE)
        .library(concat!("drivelog ", env!("CARGO_PKG_VERSION")))
        .compression(Some(mcap::Compression::Zstd))
        .compression_level(ZSTD_LEVEL)
        // The writing thread is the one extra core a run has; zstd's own workers would
        // compete with the run for it.
        .compression_threads(0)
        .chunk_size(Some(chunk_size))
        .disable_seeking(true);
    let mut writer = options
        .create(NoSeek::new(Out {
            inner: out,
            failed: false,
            written,
        }))
        .map_err(mcap_err)?;
    // The metadata first: a log cut anywhere after it still has its configuration.
    writer
        .write_metadata(&Metadata {
            name: METADATA_NAME.to_string(),
            metadata: metadata.clone(),
        })
        .map_err(mcap_err)?;
    for channel in Channel::ALL {
        let def = channel.def();
        let schema = writer
            .add_schema(def.name, "ros2msg", def.schema_text().as_bytes())
            .map_err(mcap_err)?;
        let id = channel.id();
        writer
            .add_channel_with_id(id, schema, channel.topic(), "cdr", &BTreeMap::new())
            .map_err(mcap_err)?;
    }
    writer.flush().map_err(mcap_err)?;
    Ok(writer)
}

/// An MCAP log being written. See the [module documentation](self) and `docs/logs.md`.
pub struct McapLog {
    path: PathBuf,
    /// The `.part` the log is written as until [`McapLog::finish`] renames it (`None` for a
    /// log on a writer of the caller's).
    staged: Option<Staged>,
    /// The messages logged since the last hand-over to the writing thread.
    batch: Batch,
    /// The writing thread; `None` once finished.
    writer: Option<BatchWriter>,
    /// Set by the first write error: every later write fails with it.
    failed: Option<(io::ErrorKind, String)>,
    messages: u64,
    /// Largest log time logged, ns.
    last_log_ns: u64,
    /// `last_log_ns` at the last hand-over.
    flushed_log_ns: u64,
    /// Wall-clock time of the last hand-over.
    last_flush: WallInstant,
    /// Calls of `maybe_flush`, to read the wall clock only every few.
    flush_calls: u64,
    /// [`McapLog::drop_when_behind`]: hand-overs never wait, and a batch holds at most this
    /// many events (more are dropped).
    max_pending: Option<usize>,
    /// Messages dropped because the writer was behind.
    dropped: u64,
    /// `dropped` when last reported on `/rosout`.
    dropped_reported: u64,
    /// Bytes the writing thread has passed to the file (or writer) so far.
    written: Arc<AtomicU64>,
    /// Log time between two hand-overs, ns ([`Self::set_flush_interval`]).
    flush_log_interval_ns: u64,
    /// Wall-clock time between two hand-overs.
    flush_wall_interval: Duration,
    /// Whether a tap was installed ([`Self::set_tap`]).
    tapped: bool,
}

impl McapLog {
    /// Creates the log file with the run's metadata ([`METADATA_NAME`]: `config` TOML,
    /// scenario, seed, ...). The file is written as [`crate::part_path`] (created without
    /// following links: [`Staged`]) and renamed to `path` by [`finish`](Self::finish), so a
    /// run that fails leaves the last good log at `path` (see `docs/logs.md`, section "Crash
    /// safety").
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
        let staged = Staged::create(path)?.keep_part();
        let part_err = |source| LogError::Io {
            path: staged.part().to_path_buf(),
            source,
        };
        let file = staged.file().try_clone().map_err(part_err)?;
        let written = Arc::new(AtomicU64::new(0));
        let writer = start_file(
            Box::new(BufWriter::with_capacity(1 << 16, file)),
            metadata,
            chunk_size,
            Arc::clone(&written),
        )
        .map_err(part_err)?;
        let mut log = Self::start(path, writer, written)?;
        log.staged = Some(staged);
        Ok(log)
    }

    /// A log of `path` written to `out` (header, channels and metadata at once), for tests
    /// of a failing disk.
    ///
    /// # Errors
    /// [`LogError`] naming `path`.
    #[doc(hidden)]
    pub fn on_writer(
        path: &Path,
        out: Box<dyn Write + Send>,
        metadata: &BTreeMap<String, String>,
        chunk_size: u64,
    ) -> Result<Self, LogError> {
        let io_err = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        let written = Arc::new(AtomicU64::new(0));
        let writer = start_file(out, metadata, chunk_size, Arc::clone(&written)).map_err(io_err)?;
        Self::start(path, writer, written)
    }

    fn start(path: &Path, writer: Writer, written: Arc<AtomicU64>) -> Result<Self, LogError> {
        let writer = BatchWriter::start(writer).map_err(|source| LogError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            staged: None,
            batch: Batch::default(),
            writer: Some(writer),
            failed: None,
            messages: 0,
            last_log_ns: 0,
            flushed_log_ns: 0,
            last_flush: WallInstant::now(),
            flush_calls: 0,
            max_pending: None,
            dropped: 0,
            dropped_reported: 0,
            written,
            flush_log_interval_ns: FLUSH_LOG_INTERVAL_NS,
            flush_wall_interval: FLUSH_WALL_INTERVAL,
            tapped: false,
        })
    }

    /// Bytes the writing thread has written so far (to the buffered file: at each hand-over,
    /// not each message). The header, channels and metadata count from the start; what is
    /// still in the open batch does not. One relaxed atomic load: cheap enough for a control
    /// loop to read every step (the runner's `--log-max-mb` rotation does).
    #[must_use]
    pub fn bytes_written(&self) -> u64 {
        self.written.load(Ordering::Relaxed)
    }

    /// The log's file, once [`finish`](Self::finish)ed; until then it is written as
    /// [`part`](Self::part).
    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file the log is written as until it is finished ([`crate::part_path`]: a run
    /// that fails or dies leaves it there, readable up to its last whole chunk); `None` for
    /// a log on a writer of the caller's.
    #[must_use]
    pub fn part(&self) -> Option<&Path> {
        self.staged.as_ref().map(Staged::part)
    }

    /// Has `tap` see every message from the open batch on, on the writing thread (see
    /// [`MessageTap`]); it is shown the channels at once. Install it before the first
    /// message for it to see them all. The tap
    /// goes to the writing thread with the next hand-over, and is dropped when that thread
    /// ends ([`finish`](Self::finish)); a second call replaces a tap not yet handed over, and
    /// the one installed before it from the next hand-over on.
    pub fn set_tap(&mut self, mut tap: Box<dyn MessageTap>) {
        tap.channels(&Channel::ALL);
        self.batch.tap = Some(tap);
        self.tapped = true;
    }

    /// Logs a `/diagnostics` message at `t_ns` with the tap's status alone
    /// ([`MessageTap::status`]; none if it gives none), for a log without the firmware's
    /// snapshots, which carry it otherwise: the plant's. Without a tap, nothing is logged.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn tap_status(&mut self, t_ns: u64) -> Result<(), LogError> {
        if !self.tapped || !self.admit(t_ns, 1)? {
            return Ok(());
        }
        self.push(Event::TapStatus { t_ns }, t_ns, 1)
    }

    /// Hands the messages over every `interval` of log time (and twice that of wall-clock
    /// time, for runs slower than real time) instead of every quarter second: what a
    /// [`MessageTap`] receives then comes at most `interval` late (a live view wants some
    /// 50 ms). Each hand-over ends a chunk, so a short interval makes more, smaller chunks
    /// (a somewhat larger file); a killed run loses at most twice the interval of log time.
    /// The wall clock is still read on every 64th [`maybe_flush`](Self::maybe_flush) only.
    pub fn set_flush_interval(&mut self, interval: Duration) {
        let ns = u64::try_from(interval.as_nanos())
            .unwrap_or(u64::MAX)
            .max(1);
        self.flush_log_interval_ns = ns;
        self.flush_wall_interval = interval.saturating_mul(2);
    }

    fn io_err(&self, source: io::Error) -> LogError {
        LogError::Io {
            path: self.part().unwrap_or(&self.path).to_path_buf(),
            source,
        }
    }

    /// Never wait for the writing thread from now on: drop (and count) messages instead once
    /// the open batch holds `max_pending_events` events while the writer is still busy with
    /// the previous batch (a batch that reaches that size is handed over early otherwise) (see
    /// `docs/logs.md`, section "A control loop that must not wait: dropping instead of
    /// blocking").
    /// [`finish`](Self::finish) still waits for the writer.
    pub fn drop_when_behind(&mut self, max_pending_events: usize) {
        self.max_pending = Some(max_pending_events.max(1));
        if let Some(writer) = &self.writer {
            writer.background.store(true, Ordering::Relaxed);
        }
    }

    /// Messages dropped so far because the writer was behind ([`Self::drop_when_behind`]).
    #[must_use]
    pub const fn dropped(&self) -> u64 {
        self.dropped
    }

    /// In the non-blocking mode, a full batch is handed over early; `Ok(false)` (and the
    /// messages counted as dropped) if the writer is still busy with the previous one.
    #[inline]
    fn admit(&mut self, t_ns: u64, messages: u64) -> Result<bool, LogError> {
        match self.max_pending {
            Some(max) if self.batch.events.len() >= max => {
                self.hand_over()?;
                if self.batch.events.len() < max {
                    return Ok(true);
                }
                self.dropped += messages;
                self.last_log_ns = self.last_log_ns.max(t_ns);
                Ok(false)
            }
            _ => Ok(true),
        }
    }

    /// Adds the `/rosout` warning of the messages dropped since the last one to the batch.
    fn report_drops(&mut self) {
        if self.dropped > self.dropped_reported {
            let n = self.dropped - self.dropped_reported;
            self.dropped_reported = self.dropped;
            let index = self.batch.texts.len() as u32;
            self.batch.texts.push(format!(
                "{n} messages dropped: the log writer fell behind ({} in all)",
                self.dropped
            ));
            self.batch.events.push(Event::Text {
                t_ns: self.last_log_ns,
                level: msg::Log::WARN,
                index,
            });
            self.messages += 1;
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
        if self.max_pending.is_some() {
            return match writer.try_send(full) {
                Ok(Ok(spare)) => {
                    if let Some(spare) = spare {
                        self.batch = spare;
                    }
                    self.report_drops();
                    Ok(())
                }
                Ok(Err(back)) => {
                    // The writer is busy: keep the batch open, try again at the next call.
                    self.batch = back;
                    self.flushed_log_ns =
                        self.last_log_ns.saturating_sub(self.flush_log_interval_ns);
                    Ok(())
                }
                Err(e) => {
                    self.failed = Some((e.kind(), e.to_string()));
                    Err(self.io_err(e))
                }
            };
        }
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

    /// Logs a frame the firmware received ([`Direction::Rx`]) or sent. `log_ns`: when the
    /// firmware took it (rx) or when it completed on the wire (tx); `publish_ns`: when its
    /// sender queued it (for tx, the control step that sent it); `stamp_ns`: when it
    /// completed on the wire.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    #[inline]
    pub fn frame(
        &mut self,
        dir: Direction,
        log_ns: u64,
        publish_ns: u64,
        stamp_ns: u64,
        frame: &CanFrame,
    ) -> Result<(), LogError> {
        if !self.admit(log_ns, 1)? {
            return Ok(());
        }
        let event = Event::Frame {
            log_ns,
            publish_ns,
            stamp_ns,
            frame: *frame,
            dir,
        };
        self.push(event, log_ns, 1)
    }

    /// Logs a frame the bus's fault injector dropped or corrupted (`/can/faults`): its
    /// `sender` and `fate` (`dropped`, `corrupted`), the frame as `sent` and as `received`.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn bus_fault(
        &mut self,
        t_ns: u64,
        sender: &'static str,
        fate: &'static str,
        sent: &CanFrame,
        received: &CanFrame,
    ) -> Result<(), LogError> {
        use embedded_can::Frame as _;
        if !self.admit(t_ns, 1)? {
            return Ok(());
        }
        let mut data = [0u8; 8];
        data[..received.data().len()].copy_from_slice(received.data());
        let index = self.batch.faults.len() as u32;
        self.batch.faults.push(FaultRecord {
            sender,
            fate,
            sent: *sent,
            received: data,
        });
        self.push(Event::Fault { t_ns, index }, t_ns, 1)
    }

    /// Logs the host's twist setpoint `[vx, vy, wz]` (`/cmd_vel`).
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn twist(&mut self, t_ns: u64, twist: [f32; 3]) -> Result<(), LogError> {
        if !self.admit(t_ns, 1)? {
            return Ok(());
        }
        self.push(Event::Twist { t_ns, twist }, t_ns, 1)
    }

    /// Logs a firmware snapshot: the wheels (`/joint_states`) and the state, fault and
    /// counters (`/diagnostics`).
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn snapshot(&mut self, t_ns: u64, s: &Snapshot) -> Result<(), LogError> {
        if !self.admit(t_ns, 2)? {
            return Ok(());
        }
        let index = self.batch.snapshots.len() as u32;
        self.batch.snapshots.push(*s);
        self.push(Event::Snapshot { t_ns, index }, t_ns, 2)
    }

    /// Logs an odometry: `pose` `[x, y, yaw]` in `odom` and body `twist` `[vx, vy, wz]`, on
    /// `/odom` or `/ground_truth/odom` and as its transform on `/tf`.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn odometry(
        &mut self,
        t_ns: u64,
        source: OdometrySource,
        pose: [f64; 3],
        twist: [f64; 3],
    ) -> Result<(), LogError> {
        if !self.admit(t_ns, 2)? {
            return Ok(());
        }
        let index = self.batch.odometry.len() as u32;
        self.batch.odometry.push(OdometryRecord {
            source,
            pose,
            twist,
        });
        self.push(Event::Odometry { t_ns, index }, t_ns, 2)
    }

    /// Logs a text line (state change, fault) on `/rosout` at `level`
    /// ([`msg::Log::INFO`], [`msg::Log::ERROR`], ...).
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn text(&mut self, t_ns: u64, level: u8, message: &str) -> Result<(), LogError> {
        if !self.admit(t_ns, 1)? {
            return Ok(());
        }
        let index = self.batch.texts.len() as u32;
        self.batch.texts.push(message.to_string());
        self.push(Event::Text { t_ns, level, index }, t_ns, 1)
    }

    /// Logs a control step of a runner in real time at `t_ns`, the time passed to the core
    /// (`/firmware/steps`, `kind` [`msg::Step::STEP`] or [`msg::Step::SHUTDOWN`]).
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    #[inline]
    pub fn step(&mut self, t_ns: u64, kind: u8) -> Result<(), LogError> {
        if !self.admit(t_ns, 1)? {
            return Ok(());
        }
        self.push(Event::Step { t_ns, kind }, t_ns, 1)
    }

    /// Hands the messages logged so far to the writing thread if a quarter of a second of log
    /// time, or half a second of wall-clock time, has passed since the last hand-over (see
    /// `docs/logs.md`, section "Crash safety"; other intervals: [`Self::set_flush_interval`]).
    /// Call it after each step's messages, at least every few milliseconds of log time: it
    /// reads the wall clock only on every 64th call.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed (the previous batch, or an earlier one).
    pub fn maybe_flush(&mut self) -> Result<(), LogError> {
        self.flush_calls += 1;
        let log_due =
            self.last_log_ns.saturating_sub(self.flushed_log_ns) >= self.flush_log_interval_ns;
        let wall_due = || self.last_flush.elapsed() >= self.flush_wall_interval;
        if log_due || (self.flush_calls.is_multiple_of(CALLS_PER_CLOCK_READ) && wall_due()) {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Waits until every batch handed over so far is in the file (the open batch stays
    /// open): [`bytes_written`](Self::bytes_written) then follows the log time alone, not the
    /// writing thread's speed. For tests of what a size limit does; a control loop never calls
    /// it.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn wait_written(&mut self) -> Result<(), LogError> {
        let Some(writer) = self.writer.as_mut() else {
            return Ok(());
        };
        match writer.wait() {
            Ok(_) => Ok(()),
            Err(e) => {
                self.failed = Some((e.kind(), e.to_string()));
                Err(self.io_err(e))
            }
        }
    }

    /// Messages logged so far.
    #[must_use]
    pub const fn messages(&self) -> u64 {
        self.messages
    }

    /// Writes the summary, closes the file and renames it from [`part`](Self::part) to
    /// [`path`](Self::path), replacing the file there.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed (the `.part` stays, as far as it got).
    pub fn finish(mut self) -> Result<(), LogError> {
        self.close()?;
        match self.staged.take() {
            Some(staged) => staged.commit().map(drop),
            None => Ok(()),
        }
    }

    /// Hands over the last batch, waits for the writing thread to end, then has the `mcap`
    /// writer write the summary section and the footer. Does nothing the second time.
    fn close(&mut self) -> Result<(), LogError> {
        if self.writer.is_none() {
            return Ok(());
        }
        // The end waits for the writer: the last batch and the last drop count go in whole.
        self.max_pending = None;
        self.report_drops();
        let handed = self.hand_over();
        let Some(mut writer) = self.writer.take() else {
            return handed;
        };
        handed?;
        let mut mcap = writer.finish().map_err(|e| self.io_err(e))?;
        mcap.finish().map_err(|e| self.io_err(mcap_err(e)))?;
        mcap.into_inner()
            .into_inner()
            .flush()
            .map_err(|e| self.io_err(e))
    }
}

impl Drop for McapLog {
    /// A log dropped without [`finish`](McapLog::finish) (a run that failed or panicked) is
    /// finished here, as well as it can be, and stays at [`McapLog::part`]: errors are
    /// ignored.
    fn drop(&mut self) {
        let _ = self.close();
    }
}

/// The writing thread's state: the `mcap` writer, the encoding buffer and the tap.
struct Encoder {
    writer: Writer,
    buf: Vec<u8>,
    tap: Option<Box<dyn MessageTap>>,
}

impl Encoder {
    /// Encodes and writes `batch`'s messages, then ends the chunk and flushes the file
    /// (installing the tap that came with it first).
    fn batch(&mut self, batch: &mut Batch) -> io::Result<()> {
        if let Some(tap) = batch.tap.take() {
            self.tap = Some(tap);
        }
        for event in &batch.events {
            self.event(batch, event).map_err(mcap_err)?;
        }
        self.writer.flush().map_err(mcap_err)?;
        if let Some(tap) = self.tap.as_mut() {
            tap.end_batch();
        }
        Ok(())
    }

    #[inline]
    fn write<M: RosMsg>(
        &mut self,
        channel: Channel,
        log_ns: u64,
        publish_ns: u64,
        msg: &M,
    ) -> mcap::McapResult<()> {
        self.buf.clear();
        msg::encode(&mut self.buf, msg);
        let header = MessageHeader {
            channel_id: channel.id(),
            // Not numbered: the specification's "recorded as zero" for messages whose
            // publisher assigns no sequence. A global count costs 0.9 MB (8 %) of the 60 s
            // square's log, whose messages compress to about 20 bytes each.
            sequence: 0,
            log_time: log_ns,
            publish_time: publish_ns,
        };
        self.writer.write_to_known_channel(&header, &self.buf)?;
        if let Some(tap) = self.tap.as_mut() {
            tap.message(channel, log_ns, publish_ns, &self.buf);
        }
        Ok(())
    }

    fn event(&mut self, batch: &Batch, event: &Event) -> mcap::McapResult<()> {
        match *event {
            Event::Frame {
                log_ns,
                publish_ns,
                stamp_ns,
                frame,
                dir,
            } => {
                let channel = match dir {
                    Direction::Rx => Channel::CanRx,
                    Direction::Tx => Channel::CanTx,
                };
                let m = msg::Frame::from_can(stamp_ns, &frame);
                self.write(channel, log_ns, publish_ns, &m)
            }
            Event::Fault { t_ns, index } => {
                let f = &batch.faults[index as usize];
                let m = msg::BusFault {
                    header: Header::new(t_ns, ""),
                    sender: f.sender.to_string(),
                    fate: f.fate.to_string(),
                    frame: msg::Frame::from_can(t_ns, &f.sent),
                    received: f.received,
                };
                self.write(Channel::CanFaults, t_ns, t_ns, &m)
            }
            Event::Twist { t_ns, twist } => {
                let m = msg::TwistStamped {
                    header: Header::new(t_ns, frames::BASE_LINK),
                    twist: msg::Twist::planar(twist.map(f64::from)),
                };
                self.write(Channel::CmdVel, t_ns, t_ns, &m)
            }
            Event::Snapshot { t_ns, index } => {
                let s = &batch.snapshots[index as usize];
                self.write(Channel::JointStates, t_ns, t_ns, &joint_state(t_ns, s))?;
                let mut m = diagnostics(t_ns, s);
                if let Some(status) = self.tap.as_mut().and_then(|tap| tap.status()) {
                    m.status.push(status);
                }
                self.write(Channel::Diagnostics, t_ns, t_ns, &m)
            }
            Event::Odometry { t_ns, index } => {
                let o = batch.odometry[index as usize];
                let (channel, child) = match o.source {
                    OdometrySource::Firmware => (Channel::Odom, frames::BASE_LINK),
                    OdometrySource::GroundTruth => (Channel::GroundTruth, frames::BASE_LINK_TRUTH),
                };
                let header = Header::new(t_ns, frames::ODOM);
                let pose = msg::Pose::planar(o.pose);
                let m = msg::Odometry {
                    header: header.clone(),
                    child_frame_id: child.to_string(),
                    pose: msg::PoseWithCovariance {
                        pose,
                        covariance: [0.0; 36],
                    },
                    twist: msg::TwistWithCovariance {
                        twist: msg::Twist::planar(o.twist),
                        covariance: [0.0; 36],
                    },
                };
                self.write(channel, t_ns, t_ns, &m)?;
                let tf = msg::TfMessage {
                    transforms: vec![msg::TransformStamped {
                        header,
                        child_frame_id: child.to_string(),
                        transform: msg::Transform {
                            translation: msg::Vector3 {
                                x: pose.position.x,
                                y: pose.position.y,
                                z: 0.0,
                            },
                            rotation: pose.orientation,
                        },
                    }],
                };
                self.write(Channel::Tf, t_ns, t_ns, &tf)
            }
            Event::Text { t_ns, level, index } => {
                let m = msg::Log {
                    stamp: msg::Time::from_ns(t_ns),
                    level,
                    name: "firmware".to_string(),
                    msg: batch.texts[index as usize].clone(),
                    ..msg::Log::default()
                };
                self.write(Channel::Rosout, t_ns, t_ns, &m)
            }
            Event::Step { t_ns, kind } => {
                let m = msg::Step {
                    stamp: msg::Time::from_ns(t_ns),
                    kind,
                };
                self.write(Channel::Steps, t_ns, t_ns, &m)
            }
            Event::TapStatus { t_ns } => {
                let m = msg::DiagnosticArray {
                    header: Header::new(t_ns, ""),
                    status: self
                        .tap
                        .as_mut()
                        .and_then(|tap| tap.status())
                        .into_iter()
                        .collect(),
                };
                self.write(Channel::Diagnostics, t_ns, t_ns, &m)
            }
        }
    }
}

/// `/joint_states` of a snapshot.
/// A robot with tracking pods adds them after the wheels (`pod0`...), with a position only:
/// ROS allows `velocity` and `effort` shorter than `name`, and no speed or effort of a pod is
/// known to the core.
fn joint_state(t_ns: u64, s: &Snapshot) -> msg::JointState {
    let pods = usize::from(s.pods).min(POD_NAMES.len());
    let mut name = WHEEL_NAMES.map(str::to_string).to_vec();
    name.extend(POD_NAMES[..pods].iter().map(|n| (*n).to_string()));
    let mut position = s.wheel_angles.map(f64::from).to_vec();
    position.extend(s.pod_angles[..pods].iter().map(|&a| f64::from(a)));
    msg::JointState {
        header: Header::new(t_ns, ""),
        name,
        position,
        velocity: s.wheel_speeds.0.map(f64::from).to_vec(),
        effort: s.currents.map(f64::from).to_vec(),
    }
}

/// The name of the firmware's [`msg::DiagnosticStatus`].
pub const DIAGNOSTIC_NAME: &str = "mecanum_drive: firmware";

/// `/diagnostics` of a snapshot: one status, [`DIAGNOSTIC_NAME`] (and a tap's after it,
/// [`MessageTap::status`]), whose values are named
/// `state`, `fault`, `motors_online` (a mask, wheel i at bit i), `steps`, `commanded_vx`...,
/// `measured_vx`..., `setpoint_fl`... (rad/s), one counter per rejected-frame kind
/// (`rx_unknown_id`, `rx_wrong_dlc`...) and `repeated_seq` (twists and gyro frames not used
/// because their `seq` repeated the last accepted one's). A robot configured for gyro heading
/// adds `heading_source` (`Gyro`, or `WheelsGyroSilent`: the gyro is silent and the wheels
/// give the heading, which makes the status a warning), `gyro_bias` (rad/s) and
/// `gyro_bias_samples`; without a gyro these keys are absent, as before they existed. A robot
/// with tracking pods adds `odometry_source` (`PODS2_GYRO`, `PODS3`, or `WHEELS_PODS_SILENT`, a
/// warning) and the slip estimate `slip_vx`, `slip_vy` (m/s), `slip_wz` (rad/s).
fn diagnostics(t_ns: u64, s: &Snapshot) -> msg::DiagnosticArray {
    use firmware::protocol::robot::{HeadingSource, OdometrySource, RobotState};
    let gyro_silent = s.heading_source == HeadingSource::WheelsGyroSilent;
    let pods_silent = s.odometry_source == OdometrySource::WheelsPodsSilent;
    let level = match s.state {
        RobotState::Fault => msg::DiagnosticStatus::ERROR,
        RobotState::Estop => msg::DiagnosticStatus::WARN,
        _ if gyro_silent || pods_silent => msg::DiagnosticStatus::WARN,
        _ => msg::DiagnosticStatus::OK,
    };
    let mut message = if s.fault == firmware::protocol::robot::Fault::None {
        s.state.to_string()
    } else {
        format!("{}, fault {}", s.state, s.fault)
    };
    if gyro_silent {
        message.push_str(", heading from the wheels: gyro silent");
    }
    if pods_silent {
        message.push_str(", odometry from the wheels: pods silent");
    }
    let mut values = Vec::with_capacity(24);
    let mut kv = |key: &str, value: String| {
        values.push(msg::KeyValue {
            key: key.to_string(),
            value,
        });
    };
    kv("state", s.state.to_string());
    kv("fault", s.fault.to_string());
    kv("motors_online", format!("{:#06b}", s.motors_online));
    kv("steps", s.steps.to_string());
    for (prefix, v) in [("commanded", &s.commanded), ("measured", &s.measured)] {
        kv(&format!("{prefix}_vx"), v.vx.to_string());
        kv(&format!("{prefix}_vy"), v.vy.to_string());
        kv(&format!("{prefix}_wz"), v.wz.to_string());
    }
    for (name, sp) in WHEEL_NAMES.iter().zip(s.wheel_setpoints.0) {
        kv(&format!("setpoint_{name}"), sp.to_string());
    }
    let e = &s.rx_errors;
    for (key, n) in [
        ("rx_unknown_id", e.unknown_id),
        ("rx_extended_id", e.extended_id),
        ("rx_remote", e.remote),
        ("rx_wrong_dlc", e.wrong_dlc),
        ("rx_non_finite", e.non_finite),
        ("rx_out_of_range", e.out_of_range),
        ("repeated_seq", s.repeated_seq),
    ] {
        kv(key, n.to_string());
    }
    if s.heading_source != HeadingSource::Wheels {
        kv("heading_source", s.heading_source.to_string());
        kv("gyro_bias", s.gyro_bias.to_string());
        kv("gyro_bias_samples", s.gyro_bias_samples.to_string());
    }
    if s.pods > 0 {
        kv("odometry_source", s.odometry_source.to_string());
        kv("slip_vx", s.slip.vx.to_string());
        kv("slip_vy", s.slip.vy.to_string());
        kv("slip_wz", s.slip.wz.to_string());
    }
    msg::DiagnosticArray {
        header: Header::new(t_ns, ""),
        status: vec![msg::DiagnosticStatus {
            level,
            name: DIAGNOSTIC_NAME.to_string(),
            message,
            hardware_id: String::new(),
            values,
        }],
    }
}

/// Lowers the calling thread's priority as far as an unprivileged thread can (Linux:
/// `SCHED_BATCH`, niceness 19; also out of a real-time class inherited from a runner started
/// with `chrt`). Best effort: a refusal leaves the thread as it was. The log's writing thread
/// does it in the non-blocking mode, and a live server's thread (the `live` crate) always:
/// neither may hold up a control loop that shares their process.
pub fn step_aside() {
    #[cfg(target_os = "linux")]
    {
        use thread_priority::unix::{
            NormalThreadSchedulePolicy, ThreadSchedulePolicy, set_thread_priority_and_policy,
            thread_native_id,
        };
        let _ = set_thread_priority_and_policy(
            thread_native_id(),
            thread_priority::ThreadPriority::Min,
            ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Batch),
        );
    }
}

/// The thread that writes batches, and the two channels to it: batches go there, and each
/// comes back (emptied, for reuse) once it is in the file, or the error that stopped the
/// thread.
struct BatchWriter {
    to_thread: Option<SyncSender<Batch>>,
    from_thread: Receiver<io::Result<Batch>>,
    thread: Option<JoinHandle<Writer>>,
    /// A batch was sent and has not come back yet.
    in_flight: bool,
    /// The thread lowers its own priority before its next batch (see `docs/logs.md`, section
    /// "A control loop that must not wait: dropping instead of blocking").
    background: Arc<AtomicBool>,
}

impl BatchWriter {
    /// Starts the thread, which writes with `writer`.
    fn start(writer: Writer) -> io::Result<Self> {
        let mut encoder = Encoder {
            writer,
            buf: Vec::with_capacity(1024),
            tap: None,
        };
        // One batch waits while the thread writes the one before it; two answers at most are
        // pending (the previous batch's, and the waiting one's if the thread is quick).
        let (to_thread, batches) = sync_channel::<Batch>(1);
        let (done, from_thread) = sync_channel(2);
        let background = Arc::new(AtomicBool::new(false));
        let thread_background = Arc::clone(&background);
        let thread = std::thread::Builder::new()
            .name("mcap-writer".to_string())
            .spawn(move || {
                let mut in_background = false;
                for mut batch in batches {
                    if !in_background && thread_background.load(Ordering::Relaxed) {
                        in_background = true;
                        step_aside();
                    }
                    match encoder.batch(&mut batch) {
                        Ok(()) => {
                            batch.clear();
                            if done.send(Ok(batch)).is_err() {
                                break;
                            }
                        }
                        Err(e) => {
                            let _ = done.send(Err(e));
                            break;
                        }
                    }
                }
                encoder.writer
            })?;
        Ok(Self {
            to_thread: Some(to_thread),
            from_thread,
            thread: Some(thread),
            in_flight: false,
            background,
        })
    }

    /// Waits until the batch in flight, if any, is in the file; returns it emptied.
    fn wait(&mut self) -> io::Result<Option<Batch>> {
        if !self.in_flight {
            return Ok(None);
        }
        self.in_flight = false;
        match self.from_thread.recv() {
            Ok(result) => result.map(Some),
            Err(_) => Err(stopped()),
        }
    }

    /// Hands `batch` to the thread, then waits until the one handed over before it is in the
    /// file, and returns that one, emptied, for reuse. The thread finds `batch` waiting when
    /// it is done with the previous one: it does not idle between batches while this thread
    /// wakes up.
    fn send(&mut self, batch: Batch) -> io::Result<Option<Batch>> {
        let sent = self
            .to_thread
            .as_ref()
            .is_some_and(|to_thread| to_thread.send(batch).is_ok());
        // The previous batch's error, if that is what stopped the thread.
        let previous = self.wait()?;
        if !sent {
            return Err(stopped());
        }
        self.in_flight = true;
        Ok(previous)
    }

    /// As [`send`](Self::send), without waiting: if the batch in flight is not in the file
    /// yet, gives `batch` back (`Ok(Err(batch))`) instead.
    fn try_send(&mut self, batch: Batch) -> io::Result<Result<Option<Batch>, Batch>> {
        let mut spare = None;
        if self.in_flight {
            match self.from_thread.try_recv() {
                Ok(result) => {
                    self.in_flight = false;
                    spare = Some(result?);
                }
                Err(TryRecvError::Empty) => return Ok(Err(batch)),
                Err(TryRecvError::Disconnected) => {
                    self.in_flight = false;
                    return Err(stopped());
                }
            }
        }
        let Some(to_thread) = self.to_thread.as_ref() else {
            return Err(stopped());
        };
        match to_thread.try_send(batch) {
            Ok(()) => {
                self.in_flight = true;
                Ok(Ok(spare))
            }
            Err(TrySendError::Full(batch)) => Ok(Err(batch)),
            Err(TrySendError::Disconnected(_)) => Err(stopped()),
        }
    }

    /// Waits for the batch in flight, stops the thread and returns the `mcap` writer.
    fn finish(&mut self) -> io::Result<Writer> {
        self.wait()?;
        self.to_thread = None;
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(writer)) => Ok(writer),
            _ => Err(stopped()),
        }
    }
}

/// The error for a thread that is gone without saying why (it panicked, or an earlier error
/// was already reported).
fn stopped() -> io::Error {
    io::Error::other("the MCAP writer thread has stopped")
}

impl Drop for BatchWriter {
    fn drop(&mut self) {
        // Let the thread finish the batch in flight and end.
        self.to_thread = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use embedded_can::{Frame as _, StandardId};

    use super::*;
    use crate::read::for_each_message;

    /// A file of its own for a test, removed when dropped.
    struct TempFile(PathBuf);

    impl TempFile {
        fn new(test: &str) -> Self {
            let name = format!("drivelog-{}-{test}.mcap", std::process::id());
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

    /// Logs milliseconds `steps` of every kind of message (5 frames a millisecond, the rest
    /// every 10 ms).
    fn log_steps(log: &mut McapLog, steps: std::ops::Range<u64>) -> Result<(), LogError> {
        let snapshot = firmware::Controller::new(&firmware::Config::dji_m3508_example())
            .unwrap()
            .snapshot();
        for i in steps {
            let t = i * 1_000_000;
            for k in 0..4 {
                let f = frame(i * 4 + k);
                log.frame(Direction::Rx, t + 100 * k, t + 100 * k, t + 100 * k, &f)?;
            }
            log.frame(Direction::Tx, t + 500, t, t + 450, &frame(i))?;
            if i % 10 == 0 {
                log.snapshot(t, &snapshot)?;
                log.odometry(
                    t,
                    OdometrySource::Firmware,
                    [0.1, 0.2, 0.3],
                    [0.5, 0.0, 0.1],
                )?;
                log.odometry(
                    t,
                    OdometrySource::GroundTruth,
                    [0.1, 0.2, 0.31],
                    [0.5, 0.0, 0.1],
                )?;
                log.twist(t, [0.5, 0.0, -0.25])?;
                log.bus_fault(t, "drives", "dropped", &frame(i), &frame(i))?;
            }
            if i % 100 == 0 {
                log.text(t, msg::Log::INFO, "state ENABLED")?;
            }
            log.maybe_flush()?;
        }
        Ok(())
    }

    #[test]
    fn a_log_reads_back_through_the_crates_index_and_our_reader_alike() {
        let file = TempFile::new("indexes");
        let metadata = BTreeMap::from([("config".to_string(), "x = 1".to_string())]);
        let mut log = McapLog::create_with_chunk_size(&file.0, &metadata, 64 << 10).unwrap();
        log_steps(&mut log, 0..1500).unwrap();
        let written = log.messages();
        log.finish().unwrap();
        let bytes = std::fs::read(&file.0).unwrap();

        // This crate's reader: complete, every CRC checked, in file order.
        let mut read = Vec::new();
        let mut meta = Vec::new();
        let report = for_each_message(
            &bytes,
            |m| {
                read.push((
                    m.topic.to_string(),
                    m.log_time,
                    m.publish_time,
                    m.data.to_vec(),
                ));
            },
            |name, kv| meta.push((name.to_string(), kv.clone())),
        )
        .unwrap();
        assert!(report.is_complete(), "{report}");
        assert_eq!(report.messages, written);
        assert_eq!(report.profile, "ros2");
        assert_eq!(meta, vec![(METADATA_NAME.to_string(), metadata)]);

        // The mcap crate: statistics, schemas, and every chunk through its index.
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let stats = summary.stats.as_ref().unwrap();
        assert_eq!(stats.message_count, written);
        assert_eq!(stats.channel_count, Channel::ALL.len() as u32);
        assert_eq!(stats.metadata_count, 1);
        assert!(summary.chunk_indexes.len() > 10);
        for c in summary.channels.values() {
            let channel = Channel::from_topic(&c.topic).unwrap();
            assert_eq!(c.id, channel.id());
            assert_eq!(c.message_encoding, "cdr");
            let schema = c.schema.as_ref().unwrap();
            assert_eq!(
                (schema.name.as_str(), schema.encoding.as_str()),
                (channel.def().name, "ros2msg")
            );
            assert_eq!(&*schema.data, channel.def().schema_text().as_bytes());
        }
        let mut from_index = Vec::new();
        let mut indexes = summary.chunk_indexes.clone();
        indexes.sort_by_key(|c| c.chunk_start_offset);
        for index in &indexes {
            // Each chunk's message index lists its messages (the first chunk holds the
            // schemas and channels only, and has none).
            let listed: usize = if index.message_index_offsets.is_empty() {
                0
            } else {
                summary
                    .read_message_indexes(&bytes, index)
                    .unwrap()
                    .values()
                    .map(Vec::len)
                    .sum()
            };
            let before = from_index.len();
            for m in summary.stream_chunk(&bytes, index).unwrap() {
                let m = m.unwrap();
                from_index.push((
                    m.channel.topic.clone(),
                    m.log_time,
                    m.publish_time,
                    m.data.to_vec(),
                ));
            }
            assert_eq!(listed, from_index.len() - before);
        }
        assert_eq!(from_index, read);
        let counts: HashMap<&str, usize> = read.iter().fold(HashMap::new(), |mut m, r| {
            *m.entry(r.0.as_str()).or_default() += 1;
            m
        });
        assert_eq!(counts["/can/rx"], 6000);
        assert_eq!(counts["/can/tx"], 1500);
        assert_eq!(counts["/tf"], 300);
        assert_eq!(counts["/rosout"], 15);

        // The messages decode to what was logged.
        let tx = read.iter().find(|r| r.0 == "/can/tx").unwrap();
        let f: msg::Frame = msg::decode(&tx.3).unwrap();
        assert_eq!((tx.1, tx.2, f.header.stamp.to_ns()), (500, 0, 450));
        assert_eq!(f.to_can(), Some(frame(0)));
        let fault = read.iter().find(|r| r.0 == "/can/faults").unwrap();
        let fault: msg::BusFault = msg::decode(&fault.3).unwrap();
        assert_eq!(
            (fault.sender.as_str(), fault.fate.as_str()),
            ("drives", "dropped")
        );
        assert_eq!(fault.received.to_vec(), frame(0).data().to_vec());
        let js = read.iter().find(|r| r.0 == "/joint_states").unwrap();
        let js: msg::JointState = msg::decode(&js.3).unwrap();
        assert_eq!(js.name, WHEEL_NAMES.map(str::to_string).to_vec());
        assert_eq!(
            (js.position.len(), js.velocity.len(), js.effort.len()),
            (4, 4, 4)
        );
        let diag = read.iter().find(|r| r.0 == "/diagnostics").unwrap();
        let diag: msg::DiagnosticArray = msg::decode(&diag.3).unwrap();
        let status = &diag.status[0];
        assert_eq!(status.value("state"), Some("DISABLED"));
        assert_eq!(status.value("rx_wrong_dlc"), Some("0"));
        assert_eq!(status.value("repeated_seq"), Some("0"));
        let tf = read.iter().rfind(|r| r.0 == "/tf").unwrap();
        let tf: msg::TfMessage = msg::decode(&tf.3).unwrap();
        let t = &tf.transforms[0];
        assert_eq!(
            (t.header.frame_id.as_str(), t.child_frame_id.as_str()),
            ("odom", "base_link_truth")
        );
        assert!((t.transform.rotation.yaw() - 0.31).abs() < 1e-12);
    }

    #[test]
    fn bytes_written_counts_what_the_writer_thread_wrote() {
        let tmp = TempFile::new("bytes-written");
        let mut log = McapLog::create(&tmp.0, &BTreeMap::new()).unwrap();
        let header = log.bytes_written();
        // The header, schemas, channels and metadata, on disk (in the `.part`) at creation.
        assert_eq!(
            header,
            std::fs::metadata(log.part().unwrap()).unwrap().len()
        );
        assert!(header > 1000, "{header} bytes");
        // 600 ms: hand-overs at 250 and 500 ms, the second waits for the first's writing.
        log_steps(&mut log, 0..600).unwrap();
        let written = log.bytes_written();
        assert!(written > header + 10_000, "{header} -> {written} bytes");
        log.finish().unwrap();
        let len = std::fs::metadata(&tmp.0).unwrap().len();
        assert!(written < len, "{written} written, file {len}");
    }

    #[test]
    fn wait_written_leaves_every_handed_batch_in_the_file() {
        let tmp = TempFile::new("wait-written");
        let mut log = McapLog::create(&tmp.0, &BTreeMap::new()).unwrap();
        log.drop_when_behind(1 << 15);
        // Hand-overs at 250 and 500 ms, neither waited for; the last 100 ms stay open.
        log_steps(&mut log, 0..600).unwrap();
        log.wait_written().unwrap();
        let written = log.bytes_written();
        // Each batch ends with a flush: what was written is on disk, whatever the thread's speed.
        assert_eq!(
            written,
            std::fs::metadata(log.part().unwrap()).unwrap().len()
        );
        assert!(written > 10_000, "{written} bytes");
        log.wait_written().unwrap();
        assert_eq!(log.bytes_written(), written, "the open batch stays open");
        assert_eq!(log.dropped(), 0);
        log.finish().unwrap();
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

    /// A tap that keeps what it is shown, behind a mutex the test reads.
    #[derive(Default)]
    struct Seen {
        channels: Vec<Vec<Channel>>,
        messages: Vec<(String, u64, u64, Vec<u8>)>,
        batches: usize,
    }

    struct Keep(std::sync::Arc<std::sync::Mutex<Seen>>);

    impl MessageTap for Keep {
        fn channels(&mut self, channels: &[Channel]) {
            self.0.lock().unwrap().channels.push(channels.to_vec());
        }
        fn message(&mut self, channel: Channel, log_ns: u64, publish_ns: u64, cdr: &[u8]) {
            let m = (
                channel.topic().to_string(),
                log_ns,
                publish_ns,
                cdr.to_vec(),
            );
            self.0.lock().unwrap().messages.push(m);
        }
        fn end_batch(&mut self) {
            self.0.lock().unwrap().batches += 1;
        }
        fn status(&mut self) -> Option<msg::DiagnosticStatus> {
            Some(msg::DiagnosticStatus {
                name: "tap".to_string(),
                values: vec![msg::KeyValue {
                    key: "seen".to_string(),
                    value: self.0.lock().unwrap().messages.len().to_string(),
                }],
                ..msg::DiagnosticStatus::default()
            })
        }
    }

    #[test]
    fn a_tap_sees_every_message_as_the_file_has_it() {
        let file = TempFile::new("tap");
        let seen = std::sync::Arc::new(std::sync::Mutex::new(Seen::default()));
        let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
        log.set_tap(Box::new(Keep(seen.clone())));
        log.set_flush_interval(Duration::from_millis(50));
        log_steps(&mut log, 0..600).unwrap();
        log.finish().unwrap();
        let bytes = std::fs::read(&file.0).unwrap();
        let mut read = Vec::new();
        let report = for_each_message(
            &bytes,
            |m| {
                read.push((
                    m.topic.to_string(),
                    m.log_time,
                    m.publish_time,
                    m.data.to_vec(),
                ))
            },
            |_, _| {},
        )
        .unwrap();
        assert!(report.is_complete(), "{report}");
        let seen = seen.lock().unwrap();
        assert_eq!(seen.channels, vec![Channel::ALL.to_vec()]);
        assert_eq!(seen.messages.len(), read.len());
        assert!(
            seen.messages == read,
            "the tap saw other bytes than the file's"
        );
        // A hand-over every 50 ms of log time: 12 in 600 ms, and the last at the finish.
        assert_eq!(seen.batches, 12);
        // The tap's status follows the firmware's on /diagnostics, in the file too.
        let diag = read.iter().rfind(|r| r.0 == "/diagnostics").unwrap();
        let diag: msg::DiagnosticArray = msg::decode(&diag.3).unwrap();
        assert_eq!(diag.status.len(), 2);
        assert_eq!(diag.status[0].name, DIAGNOSTIC_NAME);
        assert_eq!(diag.status[1].name, "tap");
        let n: usize = diag.status[1].value("seen").unwrap().parse().unwrap();
        assert!(n > 0 && n < read.len(), "{n}");
    }

    #[test]
    fn a_tap_status_alone_is_logged_only_with_a_tap() {
        let diagnostics = |tap: bool| {
            let file = TempFile::new(if tap { "tap-status" } else { "no-tap-status" });
            let seen = std::sync::Arc::new(std::sync::Mutex::new(Seen::default()));
            let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
            if tap {
                log.set_tap(Box::new(Keep(seen)));
            }
            log.step(1_000, msg::Step::STEP).unwrap();
            log.tap_status(2_000).unwrap();
            let messages = log.messages();
            log.finish().unwrap();
            let mut out = Vec::new();
            let bytes = std::fs::read(&file.0).unwrap();
            for_each_message(
                &bytes,
                |m| {
                    if m.topic == "/diagnostics" {
                        let d: msg::DiagnosticArray = msg::decode(m.data).unwrap();
                        let names: Vec<_> = d.status.iter().map(|s| s.name.clone()).collect();
                        out.push((m.log_time, d.header.stamp, names));
                    }
                },
                |_, _| {},
            )
            .unwrap();
            (messages, out)
        };
        let (messages, tapped) = diagnostics(true);
        assert_eq!(messages, 2);
        assert_eq!(
            tapped,
            vec![(2_000, msg::Time::from_ns(2_000), vec!["tap".to_string()])]
        );
        assert_eq!(diagnostics(false), (1, vec![]));
    }

    #[test]
    fn without_a_tap_diagnostics_have_the_firmware_status_alone() {
        let file = TempFile::new("no-tap");
        let mut log = McapLog::create(&file.0, &BTreeMap::new()).unwrap();
        log_steps(&mut log, 0..20).unwrap();
        log.finish().unwrap();
        let bytes = std::fs::read(&file.0).unwrap();
        let mut statuses = Vec::new();
        for_each_message(
            &bytes,
            |m| {
                if m.topic == "/diagnostics" {
                    let d: msg::DiagnosticArray = msg::decode(m.data).unwrap();
                    statuses.push(d.status.len());
                }
            },
            |_, _| {},
        )
        .unwrap();
        assert_eq!(statuses, vec![1, 1]);
    }

    #[test]
    fn an_event_is_small() {
        // What the caller's thread writes per frame, instead of the encoded message.
        assert!(size_of::<Event>() <= 48, "{}", size_of::<Event>());
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
        McapLog::on_writer(path, Box::new(out), &BTreeMap::new(), 16 << 10).unwrap()
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
        // Found at the hand-over after the batch whose write failed (100 kB hold some 1.2 s
        // of these messages, a batch is 250 ms), not at the end of the run.
        assert!(log.messages() < 2_000 * 6, "{}", log.messages());
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
        // Room for the header, schemas and metadata; the first batch's chunk panics.
        let mut log = log_on(
            path,
            Full {
                room: 20_000,
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
                room: 20_000,
                panic: true,
            },
        );
        let _ = log_steps(&mut log, 0..1000);
        drop(log);
    }

    /// A file whose writes wait while `stalled` is set (a disk that stops answering), kept
    /// in memory.
    struct Stalling {
        stalled: std::sync::Arc<std::sync::atomic::AtomicBool>,
        bytes: std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
    }

    impl Write for Stalling {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            while self.stalled.load(std::sync::atomic::Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(1));
            }
            self.bytes.lock().unwrap().extend_from_slice(buf);
            Ok(buf.len())
        }

        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn behind_a_stalled_writer_messages_are_dropped_and_counted_not_waited_for() {
        use std::sync::atomic::Ordering;
        let stalled = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let bytes = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let out = Stalling {
            stalled: stalled.clone(),
            bytes: bytes.clone(),
        };
        let path = Path::new("/nowhere/stalled.mcap");
        let mut log = McapLog::on_writer(path, Box::new(out), &BTreeMap::new(), CHUNK_SIZE)
            .expect("header written before the stall");
        log.drop_when_behind(1000);
        stalled.store(true, Ordering::Relaxed);
        // A failed assertion must not leave the writer stalled: the log's drop waits for it.
        struct Unstall(std::sync::Arc<std::sync::atomic::AtomicBool>);
        impl Drop for Unstall {
            fn drop(&mut self) {
                self.0.store(false, std::sync::atomic::Ordering::Relaxed);
            }
        }
        let _unstall = Unstall(stalled.clone());
        let mut slowest = Duration::ZERO;
        let mut steps = |log: &mut McapLog, range: std::ops::Range<u64>| {
            for i in range {
                let t = i * 1_000_000;
                for k in 0..5 {
                    log.frame(Direction::Rx, t, t, t, &frame(i * 5 + k))
                        .unwrap();
                }
                let begin = WallInstant::now();
                // A blocking hand-over would wait for the stalled writer forever.
                log.maybe_flush().unwrap();
                slowest = slowest.max(begin.elapsed());
            }
        };
        // Two seconds of 5 frames a millisecond: the first 1000 frames (full batch) go to the
        // writer, which stalls on them; the next batch fills up to 1000 and the rest of the
        // 10 000 are dropped.
        steps(&mut log, 0..2000);
        assert_eq!(log.dropped(), 10_000 - 1000 - 1000);
        assert_eq!(log.messages(), 1000 + 1000);
        // The disk answers again: once the writer has caught up, nothing more is dropped (here
        // less than a batch: this loop runs far faster than the writer).
        stalled.store(false, Ordering::Relaxed);
        std::thread::sleep(Duration::from_millis(500));
        steps(&mut log, 2000..2100);
        assert_eq!(log.dropped(), 8000);
        assert!(slowest < Duration::from_millis(100), "{slowest:?}");
        log.finish().unwrap();

        let bytes = bytes.lock().unwrap().clone();
        let mut frames = 0;
        let mut warnings = Vec::new();
        let report = for_each_message(
            &bytes,
            |m| match m.topic {
                "/can/rx" => frames += 1,
                "/rosout" => warnings.push(msg::decode::<msg::Log>(m.data).unwrap()),
                _ => {}
            },
            |_, _| {},
        )
        .unwrap();
        assert!(report.is_complete(), "{report}");
        assert_eq!(frames, 1000 + 1000 + 500);
        assert_eq!(warnings.len(), 1);
        assert_eq!(warnings[0].level, msg::Log::WARN);
        assert!(
            warnings[0].msg.starts_with("8000 messages dropped"),
            "{}",
            warnings[0].msg
        );
    }
}
