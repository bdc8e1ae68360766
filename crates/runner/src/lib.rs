//! The `mecanum-runner` binary's library: its log ([`McapRecorder`]).
//!
//! # The runner's log (`--log FILE.mcap`)
//!
//! The same format as the simulator's logs (drivelog's [`McapLog`]: a ROS 2 bag in MCAP), fed
//! from the control loop through [`firmware::linux::Recorder`]. Log time 0 is the runner's
//! first step; every time is the one the core was given, in ns (µs · 1000):
//!
//! - `/can/rx`: every frame passed to `on_frame`, at its time (log time, publish time and
//!   stamp alike);
//! - `/can/tx`: every frame a step (or the shutdown) produced, publish time = that step's
//!   time, log time and stamp = when it was handed to the socket (or given up: the frame is
//!   logged all the same, so that replay compares what the core sent);
//! - `/firmware/steps`: the time of each step and of the shutdown. The runner's steps are
//!   real times, late by the wake-up latency and re-anchored after an overrun, not on the
//!   simulator's grid: replay steps at these times (hostsim's `replay_at_steps`), so a run
//!   replays bit for bit;
//! - `/odom`, `/tf`, `/joint_states`, `/diagnostics` every [`SNAPSHOT_EVERY`] steps, and the
//!   state and fault changes on `/rosout`;
//! - metadata `mecanum_drive`: `config` (the TOML), `program` = `mecanum-runner`,
//!   `firmware_version`, `protocol_version`.
//!
//! The loop only pushes small values; [`McapLog`] encodes and writes on its own thread, in
//! its non-blocking mode ([`McapLog::drop_when_behind`]): if the disk falls behind, messages
//! are dropped and counted ([`McapRecorder::dropped`], the `--stats-json` `log.dropped`, and a
//! `/rosout` warning) and the loop never waits. A write error stops the logging (the run goes
//! on) and is reported at the end.

use std::collections::BTreeMap;
use std::path::Path;

use drivelog::{Direction, LogError, McapLog, OdometrySource, msg};
use firmware::CanFrame;
use firmware::control::{Controller, Fault};
use firmware::linux::Recorder;
use firmware::protocol::robot::RobotState;

/// The odometry, wheels and diagnostics are logged every this many steps (10 ms at 1 kHz).
pub const SNAPSHOT_EVERY: u64 = 10;

/// Messages the open batch may hold while the writer is behind (some 5 s of a 1 kHz run).
pub const MAX_PENDING_EVENTS: usize = 1 << 15;

/// The `program` metadata of the runner's logs.
pub const PROGRAM: &str = "mecanum-runner";

/// The metadata record of a runner's log, for the configuration `config_toml`.
#[must_use]
pub fn metadata(config_toml: &str) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("config".to_string(), config_toml.to_string()),
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

/// A [`Recorder`] that writes the run to an MCAP log. See the [crate documentation](crate).
pub struct McapRecorder {
    log: Option<McapLog>,
    error: Option<LogError>,
    steps: u64,
    state: Option<(RobotState, Fault)>,
    dropped: u64,
    messages: u64,
}

impl McapRecorder {
    /// Creates the log at `path` with `config_toml` in its metadata.
    ///
    /// # Errors
    /// [`LogError`] naming the file.
    pub fn create(path: &Path, config_toml: &str) -> Result<Self, LogError> {
        let mut log = McapLog::create(path, &metadata(config_toml))?;
        log.drop_when_behind(MAX_PENDING_EVENTS);
        Ok(Self {
            log: Some(log),
            error: None,
            steps: 0,
            state: None,
            dropped: 0,
            messages: 0,
        })
    }

    /// Messages dropped so far because the writer was behind.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.log.as_ref().map_or(self.dropped, McapLog::dropped)
    }

    /// Messages logged so far.
    #[must_use]
    pub fn messages(&self) -> u64 {
        self.log.as_ref().map_or(self.messages, McapLog::messages)
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
        if let Some(e) = self.error.take() {
            return Err(e);
        }
        match self.log.take() {
            Some(log) => log.finish(),
            None => Ok(()),
        }
    }

    fn snapshot(&mut self, t_us: u64, controller: &Controller, every: bool) {
        let s = controller.snapshot();
        let t_ns = t_us * 1000;
        if every {
            self.with(|log| {
                log.snapshot(t_ns, &s)?;
                log.odometry(
                    t_ns,
                    OdometrySource::Firmware,
                    [s.pose.x, s.pose.y, s.pose.heading].map(f64::from),
                    [s.measured.vx, s.measured.vy, s.measured.wz].map(f64::from),
                )
            });
        }
        let now = (s.state, s.fault);
        if self.state != Some(now) {
            self.state = Some(now);
            let level = match s.state {
                RobotState::Fault => msg::Log::ERROR,
                RobotState::Estop => msg::Log::WARN,
                _ => msg::Log::INFO,
            };
            let text = if s.fault == Fault::None {
                format!("state {:?}", s.state)
            } else {
                format!("state {:?}, fault {:?}", s.state, s.fault)
            };
            self.with(|log| log.text(t_ns, level, &text));
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
        let every = self.steps.is_multiple_of(SNAPSHOT_EVERY);
        self.steps += 1;
        self.snapshot(t_us, controller, every);
    }

    fn shut_down(&mut self, t_us: u64, controller: &Controller) {
        self.with(|log| log.step(t_us * 1000, msg::Step::SHUTDOWN));
        self.snapshot(t_us, controller, true);
    }

    fn sent(&mut self, step_us: u64, sent_us: u64, frame: &CanFrame, _sent: bool) {
        let (publish, at) = (step_us * 1000, sent_us * 1000);
        self.with(|log| log.frame(Direction::Tx, at, publish, at, frame));
    }

    fn step_done(&mut self) {
        self.with(McapLog::maybe_flush);
    }
}
