//! The `mecanum-runner` binary's library: its log ([`McapRecorder`]).
//!
//! [`McapRecorder`] is the [`mecanum_linux::Recorder`] that writes a run to drivelog's
//! [`McapLog`] (a ROS 2 bag in MCAP, the simulator's format), in its non-blocking mode
//! ([`McapLog::drop_when_behind`]): the control loop only pushes small values and never waits
//! for the disk. [`metadata`] is the log's `mecanum_drive` record; the odometry, wheels and
//! diagnostics are logged every [`SNAPSHOT_EVERY`] steps. With [`McapRecorder::rotating`] the
//! log is a directory of numbered files ([`rotated_path`]), each a complete log of its own.
//! [`Console`] is the binary's recorder: the log, and the link's losses on stderr.
//! [`McapRecorder::serve`] installs a live view's tap (`--live`) on the log, and on each file
//! of a rotated one.
//!
//! What each channel of the runner's log holds and at which times, what happens when the disk
//! falls behind or fails, and how rotation works (and what a later file replays) are
//! specified in `docs/logs.md`, sections "The runner's log (`--log FILE.mcap`)" and "Rotation
//! (`--log-max-mb N --log-keep K`)".

pub mod params;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use drivelog::{CoreLog, Direction, LogError, McapLog, MessageTap, msg};
use firmware::control::{Controller, Fault, SaveOutcome};
use firmware::protocol::robot::RobotState;
use firmware::{CanFrame, Config};
use mecanum_linux::{LinkEvent, Recorder};

/// The odometry, wheels and diagnostics are logged every this many steps (10 ms at 1 kHz).
pub const SNAPSHOT_EVERY: u32 = 10;

/// Messages the open batch may hold while the writer is behind (some 5 s of a 1 kHz run).
pub const MAX_PENDING_EVENTS: usize = 1 << 15;

/// The `program` metadata of the runner's logs.
pub const PROGRAM: &str = "mecanum-runner";

/// The metadata record of a runner's log, for the configuration `config`.
#[must_use]
pub fn metadata(config: &Config) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("config".to_string(), config.to_toml_string()),
        ("config_id".to_string(), format!("0x{:04x}", config.id())),
        ("program".to_string(), PROGRAM.to_string()),
        (
            "firmware_version".to_string(),
            env!("CARGO_PKG_VERSION").to_string(),
        ),
        (
            "protocol_version".to_string(),
            firmware::protocol::robot::PROTOCOL_VERSION.to_string(),
        ),
    ])
}

/// The metadata record of a runner's log for `controller` as it is: [`metadata`] of the
/// configuration in force and, when it did not start on its built-in configuration (a saved
/// set, `--params`), that built-in configuration (`builtin_config`) and the saved record's
/// number (`saved_seq`), which replay needs to make the same core.
#[must_use]
pub fn metadata_for(controller: &Controller) -> BTreeMap<String, String> {
    let mut m = metadata(controller.config());
    if controller.builtin() != controller.config() || controller.saved_seq() != 0 {
        m.insert(
            "builtin_config".to_string(),
            controller.builtin().to_toml_string(),
        );
        m.insert("saved_seq".to_string(), controller.saved_seq().to_string());
    }
    m
}

/// A [`Recorder`] that writes the run to an MCAP log. See the [crate documentation](crate) and
/// `docs/logs.md`, sections "The runner's log (`--log FILE.mcap`)" and "Rotation
/// (`--log-max-mb N --log-keep K`)".
pub struct McapRecorder {
    log: Option<McapLog>,
    rotation: Option<Rotation>,
    error: Option<LogError>,
    /// What the steps log of the core: the status lines, the snapshot and the odometry.
    core: CoreLog,
    dropped: u64,
    messages: u64,
    /// [`Self::serve`]: a new tap for each file, and the hand-over interval.
    tap: Option<(TapMaker, Duration)>,
}

/// Makes the tap of a live view ([`McapRecorder::serve`]), once for each file.
pub type TapMaker = Arc<dyn Fn() -> Box<dyn MessageTap> + Send + Sync>;

impl McapRecorder {
    /// Creates the log at `path` with the configuration `controller` starts on in its
    /// metadata ([`metadata_for`]).
    ///
    /// # Errors
    /// [`LogError`] naming the file.
    pub fn create(path: &Path, controller: &Controller) -> Result<Self, LogError> {
        Ok(Self::on_log(McapLog::create(
            path,
            &metadata_for(controller),
        )?))
    }

    /// A recorder on an open log (its metadata already written), switched to the
    /// non-blocking mode; for tests of a disk that stops answering
    /// ([`McapLog::on_writer`]).
    #[doc(hidden)]
    #[must_use]
    pub fn on_log(mut log: McapLog) -> Self {
        log.drop_when_behind(MAX_PENDING_EVENTS);
        Self {
            log: Some(log),
            rotation: None,
            error: None,
            core: CoreLog::new(SNAPSHOT_EVERY, SNAPSHOT_EVERY),
            dropped: 0,
            messages: 0,
            tap: None,
        }
    }

    /// Has a live view see the log as it is written: a tap from `make` on the current file,
    /// and on each later file of a rotated log as it is started (its clients keep their
    /// subscriptions), with hand-overs every `flush_interval` of log time
    /// ([`McapLog::set_flush_interval`]; `live::FLUSH_INTERVAL`). The tap runs on the log's
    /// writing thread: the loop never waits on it.
    pub fn serve(&mut self, make: TapMaker, flush_interval: Duration) {
        if let Some(log) = self.log.as_mut() {
            log.set_tap(make());
            log.set_flush_interval(flush_interval);
        }
        self.tap = Some((make, flush_interval));
    }

    /// A log rotated in `dir` (created if missing): files `runner-NNNNNN.mcap` of about
    /// `max_bytes` each, the newest `keep` kept. See `docs/logs.md`, section "Rotation
    /// (`--log-max-mb N --log-keep K`)".
    ///
    /// # Errors
    /// [`LogError`] naming the directory or the first file; `max_bytes` 0 or `keep` 0 as an
    /// error naming `--log-max-mb` / `--log-keep` and the value.
    pub fn rotating(
        dir: &Path,
        controller: &Controller,
        max_bytes: u64,
        keep: usize,
    ) -> Result<Self, LogError> {
        let invalid = |what: String| LogError::Io {
            path: dir.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::InvalidInput, what),
        };
        if max_bytes == 0 {
            return Err(invalid("--log-max-mb 0: the size limit must be > 0".into()));
        }
        if keep == 0 {
            return Err(invalid("--log-keep 0: at least 1 file must be kept".into()));
        }
        std::fs::create_dir_all(dir).map_err(|source| LogError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut recorder = Self::create(&rotated_path(dir, 1), controller)?;
        let mut rotation = Rotation {
            dir: dir.to_path_buf(),
            metadata: metadata_for(controller),
            config_id: controller.config_id(),
            max_bytes,
            keep,
            index: 1,
            finishing: None,
            dropped: 0,
            messages: 0,
            next: None,
        };
        rotation.prepare();
        recorder.rotation = Some(rotation);
        Ok(recorder)
    }

    /// Files started so far (1 without rotation).
    #[must_use]
    pub fn files(&self) -> u64 {
        self.rotation.as_ref().map_or(1, |r| r.index)
    }

    /// Starts the next file if the current one has reached the size limit.
    fn maybe_rotate(&mut self) {
        let (Some(rotation), Some(log)) = (self.rotation.as_mut(), self.log.as_ref()) else {
            return;
        };
        if log.bytes_written() < rotation.max_bytes {
            return;
        }
        // The next file was created on a thread when this one started; not ready yet (a
        // slow disk), the current file grows until the next step.
        if !rotation.next.as_ref().is_some_and(JoinHandle::is_finished) {
            return;
        }
        let prepared = rotation.next.take().map(|h| {
            h.join().unwrap_or_else(|_| {
                Err(LogError::Io {
                    path: rotation.dir.clone(),
                    source: std::io::Error::other("a log-creating thread panicked"),
                })
            })
        });
        let mut new = match prepared {
            Some(Ok(new)) => new,
            Some(Err(e)) => {
                // The run goes on with the current file: a rotation that failed is an error
                // at the end, and the file grows past the limit.
                self.error.get_or_insert(e);
                rotation.max_bytes = u64::MAX;
                return;
            }
            None => return,
        };
        if let Some((make, interval)) = &self.tap {
            new.set_tap(make());
            new.set_flush_interval(*interval);
        }
        let Some(old) = self.log.replace(new) else {
            return;
        };
        rotation.index += 1;
        rotation.dropped += old.dropped();
        rotation.messages += old.messages();
        // The file beyond `keep` once this one is started (each rotation removes one).
        let remove = rotation
            .index
            .checked_sub(rotation.keep as u64)
            .filter(|&i| i >= 1)
            .map(|i| rotated_path(&rotation.dir, i));
        // Each finishing thread first waits for the one before it: the files are finished
        // and removed in order, and the last thread's result holds every earlier error.
        let previous = rotation.finishing.take();
        let dir = rotation.dir.clone();
        let spawned = std::thread::Builder::new()
            .name("log-finish".into())
            .spawn(move || {
                let before = previous.map_or(Ok(()), |h| join_finisher(h, &dir));
                let finished = old.finish();
                let removed = remove.map_or(Ok(()), |path| match std::fs::remove_file(&path) {
                    Err(source) if source.kind() != std::io::ErrorKind::NotFound => {
                        Err(LogError::Io { path, source })
                    }
                    _ => Ok(()),
                });
                before.and(finished).and(removed)
            });
        match spawned {
            Ok(handle) => rotation.finishing = Some(handle),
            Err(source) => {
                self.error.get_or_insert(LogError::Io {
                    path: rotation.dir.clone(),
                    source,
                });
            }
        }
        rotation.prepare();
        // The new file opens with the state at its start.
        self.core.new_file();
    }

    /// Waits until the log's writer has written every batch handed over and the next
    /// rotated file is created: which step starts a file then follows the log time alone,
    /// not the speed of the threads (a test's seam; a run never waits for them).
    ///
    /// A write error stops the logging, as in [`Recorder::step_done`].
    #[doc(hidden)]
    pub fn settle(&mut self) {
        self.with(McapLog::wait_written);
        if let Some(next) = self.rotation.as_ref().and_then(|r| r.next.as_ref()) {
            while !next.is_finished() {
                std::thread::sleep(std::time::Duration::from_micros(100));
            }
        }
    }

    /// Messages dropped so far because the writer was behind.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.log.as_ref().map_or(self.dropped, McapLog::dropped)
            + self.rotation.as_ref().map_or(0, |r| r.dropped)
    }

    /// Messages logged so far.
    #[must_use]
    pub fn messages(&self) -> u64 {
        self.log.as_ref().map_or(self.messages, McapLog::messages)
            + self.rotation.as_ref().map_or(0, |r| r.messages)
    }

    /// Runs `f` on the log; the first error stops the logging.
    fn with(&mut self, f: impl FnOnce(&mut McapLog) -> Result<(), LogError>) {
        if let Some(log) = self.log.as_mut()
            && let Err(e) = f(log)
        {
            self.dropped = log.dropped();
            self.messages = log.messages();
            self.log = None;
            self.error = Some(e);
        }
    }

    /// Finishes the file (waits for the writer).
    ///
    /// # Errors
    /// The first [`LogError`] of the run, or of finishing.
    pub fn finish(mut self) -> Result<(), LogError> {
        let current = self.log.take().map_or(Ok(()), McapLog::finish);
        let mut first = self.error.take().map_or(Ok(()), Err);
        if let Some(rotation) = self.rotation.take() {
            // The file prepared for the next rotation is not part of the log.
            if let Some(Ok(Ok(unused))) = rotation.next.map(JoinHandle::join) {
                // Never finished, it is still its `.part`.
                let path = unused.part().unwrap_or(unused.path()).to_path_buf();
                drop(unused);
                if let Err(source) = std::fs::remove_file(&path) {
                    first = first.and(Err(LogError::Io { path, source }));
                }
            }
            if let Some(handle) = rotation.finishing {
                first = first.and(join_finisher(handle, &rotation.dir));
            }
        }
        first.and(current)
    }

    /// What the step (`last`: the shutdown) at `t_us` logs of the core: [`CoreLog`] decides.
    fn core(&mut self, t_us: u64, controller: &Controller, last: bool) {
        let t_ns = t_us * 1000;
        let Some(log) = self.log.as_mut() else {
            return;
        };
        let logged = if last {
            self.core.last(Some(log), t_ns, controller, None)
        } else {
            self.core.step(Some(log), t_ns, controller, None)
        };
        if let Err(e) = logged {
            self.dropped = log.dropped();
            self.messages = log.messages();
            self.log = None;
            self.error = Some(e);
        }
    }
}

/// `dir/runner-NNNNNN.mcap`: the `index`th file of a rotated log.
#[must_use]
pub fn rotated_path(dir: &Path, index: u64) -> PathBuf {
    dir.join(format!("runner-{index:06}.mcap"))
}

/// The thread finishing the rotated files before the current one.
type Finisher = JoinHandle<Result<(), LogError>>;

/// Waits for a finishing thread; its panic as an error naming `dir`.
fn join_finisher(handle: Finisher, dir: &Path) -> Result<(), LogError> {
    handle.join().unwrap_or_else(|_| {
        Err(LogError::Io {
            path: dir.to_path_buf(),
            source: std::io::Error::other("a log-finishing thread panicked"),
        })
    })
}

/// The state of a rotated log.
struct Rotation {
    dir: PathBuf,
    /// The next file's metadata: the configuration in force ([`Self::follow`]).
    metadata: BTreeMap<String, String>,
    /// The id of the configuration in `metadata`.
    config_id: u16,
    max_bytes: u64,
    keep: usize,
    /// The current file's number, from 1.
    index: u64,
    /// The thread finishing the earlier files (each then removes the file beyond `keep`).
    finishing: Option<Finisher>,
    /// Dropped and logged messages of the finished files.
    dropped: u64,
    messages: u64,
    /// The thread creating the next file (`index + 1`), ahead of its rotation.
    next: Option<JoinHandle<Result<McapLog, LogError>>>,
}

impl Rotation {
    /// Creates the next file on a thread: the loop only swaps it in. A next file prepared
    /// before (with a configuration no longer in force) is finished and removed first, on
    /// that thread.
    fn prepare(&mut self) {
        let path = rotated_path(&self.dir, self.index + 1);
        let metadata = self.metadata.clone();
        let stale = self.next.take();
        let spawned = std::thread::Builder::new()
            .name("log-create".into())
            .spawn(move || {
                if let Some(Ok(Ok(old))) = stale.map(JoinHandle::join) {
                    // Never written to: whether it finishes cleanly does not matter.
                    let _ = old.finish();
                    let _ = std::fs::remove_file(&path);
                }
                let mut log = McapLog::create(&path, &metadata)?;
                log.drop_when_behind(MAX_PENDING_EVENTS);
                Ok(log)
            });
        // Without a thread, no rotation: the current file grows past the limit.
        self.next = spawned.ok();
    }

    /// The next file records the configuration `controller` has in force (a parameter set
    /// over CAN): prepared again if it was prepared with another.
    fn follow(&mut self, controller: &Controller) {
        if controller.config_id() != self.config_id {
            self.metadata = metadata_for(controller);
            self.config_id = controller.config_id();
            self.prepare();
        }
    }
}

impl Recorder for McapRecorder {
    fn received(&mut self, t_us: u64, frame: &CanFrame) {
        let t = t_us * 1000;
        self.with(|log| log.frame(Direction::Rx, t, t, t, frame));
    }

    fn stepped(&mut self, t_us: u64, controller: &Controller) {
        self.with(|log| log.step(t_us * 1000, msg::Step::STEP));
        self.core(t_us, controller, false);
        if let Some(rotation) = self.rotation.as_mut() {
            rotation.follow(controller);
        }
    }

    fn shut_down(&mut self, t_us: u64, controller: &Controller) {
        self.with(|log| log.step(t_us * 1000, msg::Step::SHUTDOWN));
        self.core(t_us, controller, true);
    }

    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, _sent: bool) {
        let (publish, at) = (step_us * 1000, sent_us * 1000);
        self.with(|log| log.frame(Direction::Tx, at, publish, at, frame));
    }

    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        let (level, text) = match event {
            LinkEvent::Lost { error } => (
                msg::Log::ERROR,
                format!("CAN link lost ({error}): the core keeps stepping, nothing is sent"),
            ),
            LinkEvent::Restored { down_us, attempts } => (
                msg::Log::WARN,
                format!(
                    "CAN link back after {:.3} s down ({attempts} reopen attempts)",
                    down_us as f64 / 1e6
                ),
            ),
        };
        self.with(|log| log.text(t_us * 1000, level, &text));
    }

    fn saved(&mut self, t_us: u64, outcome: SaveOutcome) {
        self.with(|log| log.saved(t_us * 1000, outcome));
    }

    fn step_done(&mut self) {
        self.with(McapLog::maybe_flush);
        self.maybe_rotate();
    }
}

/// The binary's recorder: the log if there is one ([`McapRecorder`]), and the link's losses
/// and recoveries on stderr as they happen (a line each, from the loop's thread: link events
/// are rare), with the core's state after a gap:
///
/// ```text
/// mecanum-runner: can0: link LOST at 12.345 s (receive: Network is down (os error 100)); the core keeps stepping, nothing is sent; reopening with back-off
/// mecanum-runner: can0: link back at 14.367 s after 2.022 s down (5 reopen attempts); the core is FAULT (MOTOR_STALE): reset and enable to drive again
/// ```
pub struct Console<'a> {
    iface: &'a str,
    log: Option<&'a mut McapRecorder>,
    /// A recovery to print with the state of the next step.
    restored: Option<(u64, u64, u64)>,
}

impl<'a> Console<'a> {
    /// Tells `log` (if any) everything and stderr the link events of `iface`.
    pub fn new(iface: &'a str, log: Option<&'a mut McapRecorder>) -> Self {
        Self {
            iface,
            log,
            restored: None,
        }
    }
}

impl Recorder for Console<'_> {
    fn received(&mut self, t_us: u64, frame: &CanFrame) {
        if let Some(log) = self.log.as_deref_mut() {
            log.received(t_us, frame);
        }
    }

    fn stepped(&mut self, t_us: u64, controller: &Controller) {
        if let Some(log) = self.log.as_deref_mut() {
            log.stepped(t_us, controller);
        }
        if let Some((at, down_us, attempts)) = self.restored.take() {
            let state = match (controller.state(), controller.fault()) {
                (RobotState::Enabled, _) => RobotState::Enabled.to_string(),
                (s, Fault::None) => format!("{s}: enable to drive again"),
                (s, f) => format!("{s} ({f}): reset and enable to drive again"),
            };
            eprintln!(
                "mecanum-runner: {}: link back at {:.3} s after {:.3} s down ({attempts} reopen attempts); the core is {state}",
                self.iface,
                at as f64 / 1e6,
                down_us as f64 / 1e6
            );
        }
    }

    fn shut_down(&mut self, t_us: u64, controller: &Controller) {
        if let Some(log) = self.log.as_deref_mut() {
            log.shut_down(t_us, controller);
        }
    }

    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, sent: bool) {
        if let Some(log) = self.log.as_deref_mut() {
            log.sent(step_us, sent_us, frame, sent);
        }
    }

    fn link(&mut self, t_us: u64, event: LinkEvent<'_>) {
        if let Some(log) = self.log.as_deref_mut() {
            log.link(t_us, event);
        }
        match event {
            LinkEvent::Lost { error } => eprintln!(
                "mecanum-runner: {}: link LOST at {:.3} s ({error}); the core keeps stepping, nothing is sent; reopening with back-off",
                self.iface,
                t_us as f64 / 1e6
            ),
            LinkEvent::Restored { down_us, attempts } => {
                self.restored = Some((t_us, down_us, attempts));
            }
        }
    }

    fn saved(&mut self, t_us: u64, outcome: SaveOutcome) {
        if let Some(log) = self.log.as_deref_mut() {
            log.saved(t_us, outcome);
        }
    }

    fn step_done(&mut self) {
        if let Some(log) = self.log.as_deref_mut() {
            log.step_done();
        }
    }
}
