//! Writing logs: [`McapLog`], and the thread that encodes and writes them.
//!
//! The caller's thread (a simulation, a control loop) only records each message's values in
//! a batch, and hands the batch over to a second thread at each flush
//! ([`McapLog::maybe_flush`]). That thread encodes the messages in CDR ([`crate::msg`])
//! straight into the open chunk of the file (`file`), which compresses each chunk whole with
//! zstd when it closes, at each hand-over or at [`CHUNK_SIZE`] uncompressed bytes. The file is
//! written as [`crate::part_path`] and renamed when the log is finished; an error of the
//! writing thread comes back as a [`LogError`] from the next hand-over. After
//! [`McapLog::drop_when_behind`] a hand-over never blocks: messages are dropped and counted
//! instead.
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
//!
//! The file holds the API; `encode` the recorded events and their CDR encoding, `file` the
//! MCAP file's records, `thread` the file's start and the thread that writes it.

use std::collections::BTreeMap;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant as WallInstant};

use firmware::CanFrame;
use firmware::control::{SaveOutcome, Snapshot};

use crate::msg;
use crate::{Channel, output::Staged};

mod encode;
mod file;
mod thread;

pub use encode::DIAGNOSTIC_NAME;
use encode::{Batch, Event, FaultRecord, OdometryRecord};
pub use thread::step_aside;
use thread::{BatchWriter, Writer, start_file};

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

/// zstd level of the chunks. See `docs/benchmarks.md` for the level against size and time.
pub const ZSTD_LEVEL: i32 = 1;

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
    /// Wall-clock time between two hand-overs (`None`: log time only,
    /// [`Self::flush_on_log_time_only`]).
    flush_wall_interval: Option<Duration>,
    /// Whether a tap was installed ([`Self::set_tap`]).
    tapped: bool,
}

impl McapLog {
    /// Creates the log file with the run's metadata ([`METADATA_NAME`](crate::METADATA_NAME): `config` TOML,
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
            flush_wall_interval: Some(FLUSH_WALL_INTERVAL),
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
        if self.flush_wall_interval.is_some() {
            self.flush_wall_interval = Some(interval.saturating_mul(2));
        }
    }

    /// Hands the messages over on log time only, never on the wall clock: for a run in
    /// simulated time, whose file must be the same bytes however fast the machine runs it
    /// (each hand-over ends a chunk, so a hand-over at a wall-clock moment would put the
    /// chunk boundaries where the machine's load put them). A run slower than real time then
    /// reaches the disk in steps of log time only.
    pub const fn flush_on_log_time_only(&mut self) {
        self.flush_wall_interval = None;
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

    /// Logs the end of a parameter save as the core was told it before the step at `t_ns`
    /// (`/firmware/store`): `outcome` is what
    /// [`Controller::on_saved`](firmware::Controller::on_saved) was given.
    ///
    /// # Errors
    /// [`LogError`] if writing the log failed.
    pub fn saved(&mut self, t_ns: u64, outcome: SaveOutcome) -> Result<(), LogError> {
        if !self.admit(t_ns, 1)? {
            return Ok(());
        }
        let (seq, abort_code) = match outcome {
            SaveOutcome::Stored { seq } => (seq, 0),
            SaveOutcome::Failed { code } => (0, code),
        };
        let result = msg::SaveResult {
            stamp: msg::Time::from_ns(t_ns),
            seq,
            abort_code,
        };
        self.push(Event::Saved { t_ns, result }, t_ns, 1)
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
        let wall_due = || {
            self.flush_wall_interval
                .is_some_and(|interval| self.last_flush.elapsed() >= interval)
        };
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
        let mut file = writer.finish().map_err(|e| self.io_err(e))?;
        file.finish().map_err(|e| self.io_err(e))?;
        file.into_inner().flush().map_err(|e| self.io_err(e))
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
