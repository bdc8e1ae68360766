//! Real time: the simulated drives, or a log's frames, on a real SocketCAN bus.
//!
//! The simulated drives and logged frames on a real (or in-memory) CAN bus, paced by a clock.
//!
//! Everything here is written against the firmware runner's two small traits,
//! [`mecanum_linux::Bus`] (non-blocking receive, send) and [`mecanum_linux::Clock`]
//! (microseconds, sleep until), so the same code runs
//!
//! - on a SocketCAN interface with [`SocketCanBus`](mecanum_linux::SocketCanBus) and
//!   [`MonotonicClock`](mecanum_linux::MonotonicClock) (the `hostsim plant` and
//!   `hostsim replay --iface` commands), and
//! - in tests, on a [`MemoryBus`](mecanum_linux::testing::MemoryBus) in
//!   [`VirtualClock`](mecanum_linux::testing::VirtualClock) time, with no CAN interface, no real
//!   time and no flakiness: several loops (the firmware runner's [`mecanum_linux::run`],
//!   [`run_plant`], a scripted host) each on its own thread, advancing together in virtual
//!   time.
//!
//! [`run_plant`] runs a plant ([`PlantOptions`] → [`PlantReport`]); [`play_frames`] sends
//! logged frames at their times ([`PlayOptions`] → [`PlayReport`]). Their timing is specified
//! in `docs/simulator.md`, section "Real time" ("The plant loop", "The frame player").

use std::fmt;
use std::sync::atomic::AtomicUsize;

use firmware::CanFrame;
use mecanum_linux::{
    self as linux, Bus, Clock, ErrorLog, LatencyHistogram, LatencySummary, LoopReport, RunOptions,
    StopReason, id_text, send_with_retry, stop_requested,
};
use serde::Serialize;

use firmware::protocol::robot;

use crate::bus::Node;
use crate::nodes::SimPlant;
use crate::replay::TimedFrame;
use drivelog::{CoreLog, Direction, LogError, McapLog};

// ---------------------------------------------------------------------------------------------
// The plant loop

/// Tuning of [`run_plant`]. [`Default`] is what `hostsim plant` uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlantOptions {
    /// Tick period and plant step, µs. Default 1000 (1 kHz, the DJI feedback rate).
    pub period_us: u64,
    /// Stop on the first deadline at least this long after the start; `None`: run until the
    /// stop flag is set.
    pub duration_us: Option<u64>,
    /// Most frames passed to the plant in one tick; the rest wait. Default 1024.
    pub max_rx_per_tick: usize,
    /// Pause between two attempts to send a frame the bus reported busy. Default 20 µs.
    pub retry_backoff_us: u64,
    /// Most plant steps in one tick when catching up after a late tick. Default 100.
    pub max_catch_up: u32,
}

impl Default for PlantOptions {
    fn default() -> Self {
        Self {
            period_us: 1000,
            duration_us: None,
            max_rx_per_tick: 1024,
            retry_backoff_us: 20,
            max_catch_up: 100,
        }
    }
}

/// A pose `x, y, heading` (m, m, rad).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pose {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad (counter-clockwise).
    pub heading: f64,
}

/// A body velocity `vx, vy, wz` (m/s, m/s, rad/s).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Velocity {
    /// Forward, m/s.
    pub vx: f64,
    /// Leftward, m/s.
    pub vy: f64,
    /// Yaw rate, rad/s.
    pub wz: f64,
}

/// What [`run_plant`] did: the loop's figures (as `mecanum-runner`'s) and the plant's.
/// Serialises to the JSON of `hostsim plant --stats-json`.
pub type PlantReport = LoopReport<PlantFigures>;

/// The plant's figures in a [`PlantReport`]: its simulated time and its ground truth at the
/// end.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlantFigures {
    /// Simulated time of the plant at the end, s.
    pub simulated_s: f64,
    /// Time not simulated because a step was later than [`PlantOptions::max_catch_up`]
    /// periods, µs.
    pub skipped_us: u64,
    /// Ground-truth pose at the end (world frame).
    pub truth: Pose,
    /// Ground-truth body velocity at the end.
    pub velocity: Velocity,
}

impl fmt::Display for PlantFigures {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "simulated: {:.3} s ({} µs skipped)",
            self.simulated_s, self.skipped_us
        )?;
        writeln!(
            f,
            "ground truth: x {:+.4} m  y {:+.4} m  heading {:+.2}°",
            self.truth.x,
            self.truth.y,
            self.truth.heading.to_degrees()
        )?;
        write!(
            f,
            "velocity:     vx {:+.4} m/s  vy {:+.4} m/s  wz {:+.4} rad/s",
            self.velocity.vx, self.velocity.vy, self.velocity.wz
        )
    }
}

/// Runs `plant` on `bus` in real time (as `clock` tells it) until `stop` is non-zero or
/// `options.duration_us` has elapsed. See `docs/simulator.md`, section "Real time", "The
/// plant loop".
///
/// Bus errors are counted in the [`PlantReport`], never returned: the loop keeps running.
pub fn run_plant<P: SimPlant, B: Bus, C: Clock>(
    plant: &mut P,
    bus: &mut B,
    clock: &C,
    options: &PlantOptions,
    stop: &AtomicUsize,
) -> PlantReport {
    run_plant_observed(plant, bus, clock, options, stop, &mut ())
}

/// What [`run_plant_observed`] shows an observer (a log) as it runs. Both methods do nothing
/// by default; `()` is the observer that watches nothing.
pub trait PlantObserver<P> {
    /// A frame received from the bus (`sent == false`) or sent by the plant, at `t_us` µs
    /// after the start.
    fn frame(&mut self, t_us: u64, frame: &CanFrame, sent: bool) {
        let _ = (t_us, frame, sent);
    }
    /// The plant after a tick, at `t_us` µs of simulated time.
    fn tick(&mut self, t_us: u64, plant: &P) {
        let _ = (t_us, plant);
    }
}

impl<P> PlantObserver<P> for () {}

/// [`run_plant`], showing every frame and every tick to `observer`.
pub fn run_plant_observed<P: SimPlant, B: Bus, C: Clock, O: PlantObserver<P>>(
    plant: &mut P,
    bus: &mut B,
    clock: &C,
    options: &PlantOptions,
    stop: &AtomicUsize,
    observer: &mut O,
) -> PlantReport {
    let node = PlantNode {
        plant,
        observer,
        period: options.period_us.max(1),
        max_catch_up: options.max_catch_up,
        sim_us: 0,
        skipped_us: 0,
        feedback: Vec::with_capacity(16),
    };
    let loop_options = RunOptions {
        duration_us: options.duration_us,
        max_rx_per_step: options.max_rx_per_tick,
        retry_backoff_us: options.retry_backoff_us,
        // A link loss is counted as any error and the plant goes on sending: its peers' tests
        // see its sends fail while the link is down.
        watch_link: false,
        ..RunOptions::default()
    };
    linux::run_node(node, bus, clock, &loop_options, stop)
}

/// The plant as a node of the fixed-rate loop ([`linux::run_node`]), shown to an observer.
struct PlantNode<'a, P, O> {
    plant: &'a mut P,
    observer: &'a mut O,
    period: u64,
    max_catch_up: u32,
    /// Simulated time of the plant.
    sim_us: u64,
    /// Wall time that was not simulated (the catch-up cap).
    skipped_us: u64,
    feedback: Vec<(u64, CanFrame)>,
}

impl<P: SimPlant, O: PlantObserver<P>> linux::Node for PlantNode<'_, P, O> {
    type Figures = PlantFigures;

    fn period_micros(&self) -> u64 {
        self.period
    }

    fn on_frame(&mut self, t_us: u64, frame: &CanFrame) {
        self.plant.on_frame(self.sim_us, frame);
        self.observer.frame(t_us, frame, false);
    }

    /// The physics up to the elapsed time, then the feedback due.
    fn step(&mut self, t_us: u64, out: &mut Vec<CanFrame>) {
        let period = self.period;
        let elapsed = t_us.saturating_sub(self.skipped_us);
        let target = elapsed - elapsed % period;
        let mut steps = 0;
        while self.sim_us < target {
            if steps == self.max_catch_up {
                self.skipped_us += target - self.sim_us;
                break;
            }
            self.plant.advance(period as f64 * 1e-6);
            self.sim_us += period;
            steps += 1;
        }
        let (feedback, until_ns) = (&mut self.feedback, self.sim_us * 1000);
        feedback.clear();
        self.plant.feedback(until_ns, feedback);
        self.plant.node_frames(Node::Imu, until_ns, feedback);
        self.plant.node_frames(Node::Pods, until_ns, feedback);
        out.extend(feedback.iter().map(|(_, frame)| *frame));
    }

    fn sent(&mut self, step_us: u64, _sent_us: u64, frame: &CanFrame, sent: bool) {
        if sent {
            self.observer.frame(step_us, frame, true);
        }
    }

    fn step_done(&mut self) {
        self.observer.tick(self.sim_us, self.plant);
    }

    fn finish(self) -> PlantFigures {
        let [x, y, heading] = self.plant.truth();
        let [vx, vy, wz] = self.plant.truth_velocity();
        PlantFigures {
            simulated_s: self.sim_us as f64 * 1e-6,
            skipped_us: self.skipped_us,
            truth: Pose { x, y, heading },
            velocity: Velocity { vx, vy, wz },
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The plant's log

/// A [`PlantObserver`] that writes an MCAP log of a real-time run (`hostsim plant --log`), in
/// the simulator's format ([`drivelog`]), every frame on the bus once, seen from the
/// firmware: `/can/rx` for the plant's own feedback and the robot protocol's commands (what
/// the firmware receives), `/can/tx` for every other frame (what the firmware sends); the
/// host's twist commands (`/cmd_vel`); and every 10 ms the firmware's odometry (decoded from
/// its `ODOM_*` frames, `/odom`) and the plant's ground truth (`/ground_truth/odom`, `/tf`).
/// Log time counts from the plant's start: a frame is stamped with the clock at the tick
/// that received or sent it, a pose with the plant's simulated time, which follows the clock
/// except for time skipped after a stall ([`PlantFigures::skipped_us`]). A log with a tap (a
/// live view, [`McapLog::set_tap`]) has its status on `/diagnostics` every second.
///
/// A write error stops the logging (the run goes on) and is kept for [`PlantLog::finish`].
pub struct PlantLog {
    log: Option<McapLog>,
    error: Option<LogError>,
    odom: [f64; 3],
    odom_twist: [f64; 3],
    next_pose_us: u64,
    next_status_us: u64,
}

/// Period of the pose messages of a [`PlantLog`], µs.
const PLANT_LOG_POSE_PERIOD_US: u64 = 10_000;

/// Period of a [`PlantLog`]'s tap status on `/diagnostics` ([`McapLog::tap_status`]), µs.
const PLANT_LOG_STATUS_PERIOD_US: u64 = 1_000_000;

/// The longest [`play_frames`] sleeps without looking at its stop flag, µs.
const STOP_POLL_US: u64 = 50_000;

impl PlantLog {
    /// Starts logging into `log`.
    #[must_use]
    pub const fn new(log: McapLog) -> Self {
        Self {
            log: Some(log),
            error: None,
            odom: [0.0; 3],
            odom_twist: [0.0; 3],
            next_pose_us: 0,
            next_status_us: 0,
        }
    }

    fn write(&mut self, f: impl FnOnce(&mut McapLog) -> Result<(), LogError>) {
        if let Some(log) = self.log.as_mut()
            && let Err(e) = f(log).and_then(|()| log.maybe_flush())
        {
            self.error = Some(e);
            self.log = None;
        }
    }

    /// Closes the log (writing its summary); the first write error, if there was one.
    ///
    /// # Errors
    /// The first [`LogError`] of the run, or of closing the file.
    pub fn finish(self) -> Result<u64, LogError> {
        match (self.error, self.log) {
            (Some(e), _) => Err(e),
            (None, Some(log)) => {
                let messages = log.messages();
                log.finish()?;
                Ok(messages)
            }
            // Not reached: the log is only dropped together with an error.
            (None, None) => Ok(0),
        }
    }
}

impl<P: SimPlant> PlantObserver<P> for PlantLog {
    fn frame(&mut self, t_us: u64, frame: &CanFrame, sent: bool) {
        let message = robot::decode(frame).ok();
        // The firmware receives the drives' feedback and the host's commands, and sends the
        // rest.
        let direction = match message {
            _ if sent => Direction::Rx,
            Some(robot::Message::Command(_)) => Direction::Rx,
            _ => Direction::Tx,
        };
        match message {
            Some(robot::Message::Telemetry(robot::Telemetry::OdomPosition(p))) => {
                self.odom[0] = f64::from(p.x);
                self.odom[1] = f64::from(p.y);
            }
            Some(robot::Message::Telemetry(robot::Telemetry::OdomVelocity(v))) => {
                self.odom[2] = f64::from(v.heading);
                self.odom_twist = [v.vx, v.vy, v.wz].map(f64::from);
            }
            _ => {}
        }
        let t_ns = t_us.saturating_mul(1000);
        self.write(|log| log.frame(direction, t_ns, t_ns, t_ns, frame));
        if let Some(robot::Message::Command(robot::Command::Twist(t))) = message {
            self.write(|log| log.twist(t_ns, [t.vx, t.vy, t.wz]));
        }
    }

    fn tick(&mut self, t_us: u64, plant: &P) {
        if t_us >= self.next_pose_us {
            self.next_pose_us = t_us - t_us % PLANT_LOG_POSE_PERIOD_US + PLANT_LOG_POSE_PERIOD_US;
            let t_ns = t_us.saturating_mul(1000);
            let (odom, odom_twist) = (self.odom, self.odom_twist);
            let (truth, truth_twist) = (plant.truth(), plant.truth_velocity());
            self.write(|log| {
                CoreLog::odometry(log, t_ns, (odom, odom_twist), Some((truth, truth_twist)))
            });
        }
        if t_us >= self.next_status_us {
            self.next_status_us =
                t_us - t_us % PLANT_LOG_STATUS_PERIOD_US + PLANT_LOG_STATUS_PERIOD_US;
            self.write(|log| log.tap_status(t_us.saturating_mul(1000)));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The frame player

/// Tuning of [`play_frames`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlayOptions {
    /// Time scale: 2.0 plays twice as fast as logged. Must be finite and > 0 (otherwise 1.0
    /// is used). Default 1.0.
    pub speed: f64,
    /// Pause between two attempts to send a frame the bus reported busy. Default 20 µs.
    pub retry_backoff_us: u64,
    /// How long one frame may be retried after its due time before it is dropped. Default
    /// 100 ms.
    pub give_up_us: u64,
}

impl Default for PlayOptions {
    fn default() -> Self {
        Self {
            speed: 1.0,
            retry_backoff_us: 20,
            give_up_us: 100_000,
        }
    }
}

/// What [`play_frames`] did. Serialises to JSON.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlayReport {
    /// Frames to play.
    pub frames: usize,
    /// Frames sent.
    pub sent: u64,
    /// Frames dropped after errors.
    pub failed: u64,
    /// Send attempts repeated because the bus was busy (`ENOBUFS`; also `EAGAIN`).
    pub busy_retries: u64,
    /// The signal number (stop flag) that ended the playback early, if any.
    pub stopped_by: Option<usize>,
    /// Logged time from the first to the last frame, µs.
    pub log_span_us: u64,
    /// From the start to the end of the playback, µs of the clock.
    pub elapsed_us: u64,
    /// Lateness of each send after its due time (before any retry), µs.
    pub lateness: LatencySummary,
    /// The first and the last bus error (`first_error`, `last_error`).
    #[serde(flatten)]
    pub errors: ErrorLog,
}

impl fmt::Display for PlayReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "sent {} of {} frames ({} failed, {} busy retries) in {:.3} s (log span {:.3} s)",
            self.sent,
            self.frames,
            self.failed,
            self.busy_retries,
            self.elapsed_us as f64 / 1e6,
            self.log_span_us as f64 / 1e6
        )?;
        if let Some(n) = self.stopped_by {
            write!(f, "; stopped early by {}", StopReason::Signal(n))?;
        }
        write!(f, "\nlateness (send - due): {}", self.lateness)?;
        if self.errors != ErrorLog::default() {
            writeln!(f)?;
            self.errors.write_lines(f)?;
        }
        Ok(())
    }
}

/// Sends `frames` (in time order) on `bus`, each at `start + (t - t_first) / speed`, until
/// the last one is sent or `stop` becomes non-zero. See `docs/simulator.md`, section "Real
/// time", "The frame player".
pub fn play_frames<B: Bus, C: Clock>(
    frames: &[TimedFrame],
    bus: &mut B,
    clock: &C,
    options: &PlayOptions,
    stop: &AtomicUsize,
) -> PlayReport {
    let speed = if options.speed.is_finite() && options.speed > 0.0 {
        options.speed
    } else {
        1.0
    };
    let t_first = frames.first().map_or(0, |f| f.t_ns);
    let t_last = frames.last().map_or(0, |f| f.t_ns);
    let mut errors = ErrorLog::default();
    let mut lateness = LatencyHistogram::new();
    let (mut sent, mut failed, mut retries) = (0, 0, 0);
    let mut stopped_by = None;
    let start = clock.now_micros();
    for f in frames {
        let offset_us = (f.t_ns.saturating_sub(t_first) as f64 / 1000.0 / speed) as u64;
        let due = start.saturating_add(offset_us);
        // Sleep in slices, so that a stop is seen within STOP_POLL_US even in a long gap (a
        // log's gaps may be a minute, ten at --speed 0.1).
        loop {
            if let Some(n) = stop_requested(stop) {
                stopped_by = Some(n);
                break;
            }
            let now = clock.now_micros();
            if now >= due {
                break;
            }
            clock.sleep_until(due.min(now.saturating_add(STOP_POLL_US)));
        }
        if stopped_by.is_some() {
            break;
        }
        let now = clock.now_micros();
        lateness.record(now.saturating_sub(due));
        let give_up = now.max(due).saturating_add(options.give_up_us);
        match send_with_retry(
            bus,
            clock,
            &f.frame,
            give_up,
            options.retry_backoff_us,
            &mut retries,
        ) {
            Ok(()) => sent += 1,
            Err(e) => {
                failed += 1;
                errors.record(
                    format_args!(
                        "send {} (log time {:.6} s)",
                        id_text(&f.frame),
                        f.t_ns as f64 * 1e-9
                    ),
                    &e,
                );
            }
        }
    }
    PlayReport {
        frames: frames.len(),
        sent,
        failed,
        busy_retries: retries,
        stopped_by,
        log_span_us: t_last.saturating_sub(t_first) / 1000,
        elapsed_us: clock.now_micros().saturating_sub(start),
        lateness: lateness.summary(),
        errors,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::StandardId;
    use mecanum_linux::testing::{VirtualClock, VirtualClockHandle};
    use std::io;
    use std::sync::atomic::Ordering;

    fn frame(id: u16) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), &[id as u8]).unwrap()
    }

    #[test]
    fn play_frames_keeps_the_logged_spacing_scaled_by_speed() {
        struct Recorder<'a>(&'a VirtualClockHandle, Vec<(u64, CanFrame)>, u64);
        impl Bus for Recorder<'_> {
            fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
                Ok(None)
            }
            fn send(&mut self, f: &CanFrame) -> io::Result<()> {
                if self.2 > 0 {
                    self.2 -= 1;
                    return Err(io::Error::from_raw_os_error(libc::ENOBUFS));
                }
                self.1.push((self.0.now_micros(), *f));
                Ok(())
            }
        }
        let clock = VirtualClock::new(1_000);
        let h = clock.join();
        let frames: Vec<TimedFrame> = [(5_000_000_000, 1), (5_010_000_000, 2), (5_030_000_000, 3)]
            .map(|(t_ns, id)| TimedFrame {
                t_ns,
                frame: frame(id),
            })
            .to_vec();
        let mut bus = Recorder(&h, Vec::new(), 2);
        let options = PlayOptions {
            speed: 2.0,
            ..PlayOptions::default()
        };
        let r = play_frames(&frames, &mut bus, &h, &options, &AtomicUsize::new(0));
        let times: Vec<u64> = bus.1.iter().map(|x| x.0).collect();
        // Two ENOBUFS retries of 20 µs before the first frame went out.
        assert_eq!(times, [1_040, 6_000, 16_000]);
        assert_eq!((r.sent, r.failed, r.busy_retries), (3, 0, 2));
        assert_eq!(r.log_span_us, 30_000);
        assert_eq!(r.stopped_by, None);
        let stopped = play_frames(&frames, &mut bus, &h, &options, &AtomicUsize::new(2));
        assert_eq!((stopped.sent, stopped.stopped_by), (0, Some(2)));
    }

    #[test]
    fn play_frames_sees_a_stop_in_the_middle_of_a_long_gap() {
        /// A clock whose first sleep past 1 s brings a SIGINT (the flag set mid-gap).
        struct Signalled<'a> {
            now: core::cell::Cell<u64>,
            stop: &'a AtomicUsize,
        }
        impl Clock for Signalled<'_> {
            fn now_micros(&self) -> u64 {
                self.now.get()
            }
            fn sleep_until(&self, deadline_us: u64) {
                self.now.set(self.now.get().max(deadline_us));
                if self.now.get() >= 1_000_000 {
                    self.stop.store(2, Ordering::Relaxed);
                }
            }
        }
        struct Null;
        impl Bus for Null {
            fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
                Ok(None)
            }
            fn send(&mut self, _: &CanFrame) -> io::Result<()> {
                Ok(())
            }
        }
        // 59 s between two frames, played at a tenth of the speed: a 590 s gap.
        let frames = [(0, 1), (59_000_000_000, 2)].map(|(t_ns, id)| TimedFrame {
            t_ns,
            frame: frame(id),
        });
        let stop = AtomicUsize::new(0);
        let clock = Signalled {
            now: core::cell::Cell::new(0),
            stop: &stop,
        };
        let options = PlayOptions {
            speed: 0.1,
            ..PlayOptions::default()
        };
        let r = play_frames(&frames, &mut Null, &clock, &options, &stop);
        assert_eq!((r.sent, r.stopped_by), (1, Some(2)));
        assert!(
            clock.now_micros() <= 1_000_000 + STOP_POLL_US,
            "stopped at {} us",
            clock.now_micros()
        );
    }
}
