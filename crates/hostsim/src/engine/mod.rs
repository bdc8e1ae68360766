//! The lockstep engine: a firmware node, the nodes and a scenario on one bus; in-process runs.
//!
//! A firmware node, the simulated plant and the scenario's host on one bit-timed bus, in
//! simulated time; [`run`] and its kin run the in-process core.
//!
//! The firmware is a node behind one trait, [`Firmware`]: the in-process core
//! ([`InProcess`], the same `Controller` that runs on the MCU) or an emulated board
//! (boardsim's). The engine owns everything else: the bus with its faults, the host, the plant
//! with the scenario's IMU and pod nodes, the wheel faults, and what a run records for its
//! log, its summary and its plot track ([`Outcome`]). One tick is one control period; between
//! ticks the plant advances in segments that end at the drives' next feedback, and each frame
//! for the drives acts from its delivery time. Nothing here reads a clock or draws an unseeded
//! random number: the same scenario and node give the same frames, bit for bit.
//!
//! The order of one tick (host, feedback, bus, firmware, plant), when feedback and commands
//! take effect, and what a run logs are specified in `docs/simulator.md`, section "Lockstep
//! runner".

mod core;
mod nodes;
mod plant_io;
mod run;

use std::ops::ControlFlow;
use std::sync::mpsc::Receiver;

use firmware::{CanFrame, StreamHash};

use crate::bus::{Bus, BusStats, Fate, Node, Transmission};
use crate::nodes::SimPlant;
use crate::nodes::host::HostNode;
use crate::scenario::Scenario;
use drivelog::{LogError, McapLog};

pub use self::core::InProcess;
pub use self::nodes::plant_for;
pub use self::run::{
    RunSummary, SimError, StepView, run, run_live, run_metadata, run_observed, run_until,
};
pub use plant_io::{log_transmission, queue_feedback, set_wheel_faults};

/// What to log.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LogOptions {
    /// Log the frames the fault injector dropped or corrupted on `/can/faults`.
    pub faults: bool,
    /// Log the firmware's wheels and diagnostics every this many steps (0: never).
    pub snapshot_every: u32,
    /// Log the odometry and the ground truth every this many steps (0: never).
    pub pose_every: u32,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            faults: true,
            snapshot_every: 10,
            pose_every: 10,
        }
    }
}

/// The firmware as a node of the engine: it sees the bus's deliveries and puts its frames on
/// the bus, and tells the engine what it shows.
pub trait Firmware {
    /// Why the node ended a run.
    type Error: From<LogError>;

    /// Called once before the first tick, with the bus empty at time 0.
    ///
    /// # Errors
    /// The node could not start.
    fn start(&mut self, _bus: &mut Bus) -> Result<(), Self::Error> {
        Ok(())
    }

    /// Runs the node and the bus up to `until_ns`, appending to `done` every transmission
    /// delivered by then that it has not appended yet, in delivery order, with its final fate.
    ///
    /// # Errors
    /// The node stopped.
    fn run_until(
        &mut self,
        bus: &mut Bus,
        until_ns: u64,
        done: &mut Vec<Transmission>,
    ) -> Result<(), Self::Error>;

    /// The engine's tick at `t_us`: the plant is there, its feedback and the host's frames up
    /// to then are queued, `delivered` holds what the bus delivered since the previous tick.
    /// A node that steps at the tick (the in-process core) runs the bus to the tick (adding
    /// to `delivered` what was queued so late that it is delivered by now), takes its frames,
    /// steps and puts what it sends on the bus at `t_us`, appended to `sent`; a node with its
    /// own timer (a board) does nothing here.
    ///
    /// # Errors
    /// The node stopped.
    fn tick(
        &mut self,
        bus: &mut Bus,
        t_us: u64,
        delivered: &mut Vec<Transmission>,
        sent: &mut Vec<CanFrame>,
    ) -> Result<(), Self::Error>;

    /// Whether the node takes the frames delivered now (false while it is down).
    fn receiving(&self) -> bool {
        true
    }

    /// After the tick at `t_us`: logs what the node shows (its state lines, internals,
    /// odometry) and records its state changes, heading source changes and pose in `record`.
    /// `truth` is the plant's pose now, `velocity` gives its body velocity.
    ///
    /// # Errors
    /// The log could not be written.
    fn observe(
        &mut self,
        t_us: u64,
        log: Option<&mut McapLog>,
        truth: [f64; 3],
        velocity: &dyn Fn() -> [f64; 3],
        record: &mut Record,
    ) -> Result<(), Self::Error>;

    /// A frame the node sent has reached the bus's receivers (or was dropped), with the
    /// plant's `truth` then: for a node that shows itself through its frames (a board's
    /// telemetry). Nothing by default.
    ///
    /// # Errors
    /// The log could not be written, or the frame shows a wrong node (a board image built
    /// for another robot).
    fn on_own_frame(
        &mut self,
        _tx: &Transmission,
        _log: Option<&mut McapLog>,
        _truth: &dyn Fn() -> ([f64; 3], [f64; 3]),
        _record: &mut Record,
    ) -> Result<(), Self::Error> {
        Ok(())
    }

    /// After the run, the bus (and the node, if it must run for its frames to leave) up to
    /// `until_ns` at most, so that the frames the node sent at its last steps complete:
    /// appended to `done` as by [`Self::run_until`], they are logged and shown to
    /// [`Self::on_own_frame`]. Nothing by default.
    ///
    /// # Errors
    /// The node stopped.
    fn drain(
        &mut self,
        _bus: &mut Bus,
        _until_ns: u64,
        _done: &mut Vec<Transmission>,
    ) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// Moves the transmissions of `pending` delivered by `until_ns` to `done`, in delivery order
/// (those delivered at one instant in the order they were added): what a node's
/// [`Firmware::run_until`] hands the engine.
pub fn deliver_due(pending: &mut Vec<Transmission>, until_ns: u64, done: &mut Vec<Transmission>) {
    pending.sort_by_key(|tx| tx.delivered_ns);
    let due = pending.partition_point(|tx| tx.delivered_ns <= until_ns);
    done.extend(pending.drain(..due));
}

/// One sample of the trajectories: time s, truth `[x, y]`, odometry `[x, y]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackPoint {
    /// Simulated time, s.
    pub t: f64,
    /// Ground-truth position, m.
    pub truth: [f64; 2],
    /// Odometry position, m.
    pub odom: [f64; 2],
}

/// What a run recorded of the firmware node as it went: filled by the engine and by the node
/// ([`Firmware::observe`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Record {
    /// State changes `(time s, state, fault)`.
    pub transitions: Vec<(f64, String, String)>,
    /// Changes of the heading source `(time s, source)`.
    pub heading_changes: Vec<(f64, String)>,
    /// Ground truth and the node's odometry every 10 ms (a board: at its odometry frames).
    pub track: Vec<TrackPoint>,
    /// The node's last odometry `[x, y, heading]` and the ground truth then.
    pub pose: Option<([f64; 3], [f64; 3])>,
    /// Largest position error of the odometry against the ground truth, m.
    pub max_position_error: f64,
}

impl Record {
    /// The node's odometry `pose` against the ground truth `truth` at the same time: the
    /// final pose and the largest error.
    pub fn pose(&mut self, pose: [f64; 3], truth: [f64; 3]) {
        self.pose = Some((pose, truth));
        self.max_position_error = self
            .max_position_error
            .max(libm::hypot(pose[0] - truth[0], pose[1] - truth[1]));
    }

    /// A point of the plot track at `t` (s).
    pub fn track_point(&mut self, t: f64, pose: [f64; 3], truth: [f64; 3]) {
        self.track.push(TrackPoint {
            t,
            truth: [truth[0], truth[1]],
            odom: [pose[0], pose[1]],
        });
    }
}

/// What the engine shows an observer after each tick.
#[derive(Debug)]
pub struct Step<'a, F> {
    /// Simulated time of the tick, µs.
    pub t_us: u64,
    /// The firmware node just after the tick.
    pub firmware: &'a F,
    /// Every transmission that reached the receivers since the previous tick, in delivery
    /// order: all senders, all fates (dropped ones too).
    pub delivered: &'a [Transmission],
    /// The frames the node sent at this tick (none for a node with its own timer).
    pub sent: &'a [CanFrame],
    /// Ground-truth pose `[x, y, heading]` at the tick.
    pub truth: [f64; 3],
}

/// Figures of a finished run.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// Ticks run.
    pub steps: u64,
    /// Simulated time of the run's end (the scenario's duration, or the last tick of a run
    /// its observer ended), s.
    pub duration_s: f64,
    /// Frames the node sent.
    pub tx_frames: u64,
    /// Frames delivered to the node.
    pub rx_frames: u64,
    /// [`StreamHash`] of every frame the node sent at a tick, with the tick's time.
    pub tx_hash: u64,
    /// Bus figures.
    pub bus: BusStats,
    /// Bus load over the run (0..1).
    pub bus_load: f64,
    /// Ground-truth pose at the last tick.
    pub truth: [f64; 3],
    /// What the node showed.
    pub record: Record,
}

/// How long after a run's last tick the bus runs on, so that the frames the firmware sent at
/// its last steps are logged: far longer than a frame waits on a loaded bus.
const DRAIN_NS: u64 = 100_000_000;

/// Runs `scenario` with `firmware` as the firmware node and `plant` as the drives and body,
/// logging to `log` if given. `observe` sees every tick and may end the run early with
/// [`ControlFlow::Break`] (as at the scenario's end: the frames on the wire logged, the
/// figures of the ticks run).
///
/// # Errors
/// The node's error: it stopped, or the log could not be written.
pub fn run_firmware<F: Firmware, P: SimPlant>(
    scenario: &Scenario,
    firmware: &mut F,
    plant: &mut P,
    log: Option<&mut McapLog>,
    options: LogOptions,
    observe: impl FnMut(&Step<'_, F>) -> ControlFlow<()>,
) -> Result<Outcome, F::Error> {
    run_firmware_live(scenario, firmware, plant, log, options, None, observe)
}

/// [`run_firmware`], the host sending besides its script the frames that come on `inbox`
/// (a live server's parameter requests), each at the first tick after it came: a live run,
/// in wall-clock time, whose frames are logged as the script's are.
///
/// # Errors
/// As [`run_firmware`].
pub fn run_firmware_live<F: Firmware, P: SimPlant>(
    scenario: &Scenario,
    firmware: &mut F,
    plant: &mut P,
    log: Option<&mut McapLog>,
    options: LogOptions,
    inbox: Option<&Receiver<CanFrame>>,
    observe: impl FnMut(&Step<'_, F>) -> ControlFlow<()>,
) -> Result<Outcome, F::Error> {
    // The scenario's IMU node and pod node, if any, on the plant (without them, a
    // pass-through).
    let mut with_imu = crate::nodes::imu::WithImu::new(plant, scenario.imu.as_ref(), scenario.seed);
    let plant = nodes::with_pods(&mut with_imu, scenario);
    let mut engine = Engine::new(scenario, plant, log, options);
    engine.inbox = inbox;
    engine.run(firmware, observe)
}

/// One run's moving parts.
struct Engine<'s, 'l, P> {
    scenario: &'s Scenario,
    period_us: u64,
    plant: P,
    log: Option<&'l mut McapLog>,
    options: LogOptions,
    bus: Bus,
    host: HostNode,
    /// Frames the host sends besides its script ([`run_firmware_live`]).
    inbox: Option<&'l Receiver<CanFrame>>,
    host_frames: Vec<(u64, CanFrame)>,
    twists: Vec<(u64, [f32; 3])>,
    feedback: Vec<(u64, CanFrame)>,
    /// Delivered since the last tick.
    delivered: Vec<Transmission>,
    sent: Vec<CanFrame>,
    tx_frames: u64,
    rx_frames: u64,
    hash: StreamHash,
    record: Record,
}

impl<'s, 'l, P: SimPlant> Engine<'s, 'l, P> {
    fn new(
        scenario: &'s Scenario,
        plant: P,
        log: Option<&'l mut McapLog>,
        options: LogOptions,
    ) -> Self {
        let duration_us = scenario.duration_us();
        let mut record = Record::default();
        record.track.reserve((duration_us / 10_000 + 2) as usize);
        Self {
            scenario,
            // The control period, as the core has it.
            period_us: 1_000_000 / u64::from(scenario.config.timing.control_hz),
            plant,
            log,
            options,
            bus: Bus::new(1_000_000, scenario.bus_faults.clone(), scenario.seed),
            host: nodes::host(scenario),
            inbox: None,
            host_frames: Vec::new(),
            twists: Vec::new(),
            feedback: Vec::with_capacity(16),
            delivered: Vec::new(),
            sent: Vec::new(),
            tx_frames: 0,
            rx_frames: 0,
            hash: StreamHash::default(),
            record,
        }
    }

    fn run<F: Firmware>(
        mut self,
        fw: &mut F,
        mut observe: impl FnMut(&Step<'_, F>) -> ControlFlow<()>,
    ) -> Result<Outcome, F::Error> {
        if let Some(l) = self.log.as_deref_mut() {
            // The same run, the same bytes, on a busy machine too.
            l.flush_on_log_time_only();
        }
        fw.start(&mut self.bus)?;
        let duration_us = self.scenario.duration_us();
        // Ground truth at the last tick (the plant then advances one more period, which the
        // firmware never sees).
        let mut last_truth = self.plant.truth();
        let (mut t_us, mut steps, mut stopped_at_us) = (0u64, 0u64, None);
        set_wheel_faults(self.scenario, &mut self.plant, 0);
        while t_us <= duration_us {
            let truth = self.tick(fw, t_us)?;
            last_truth = truth;
            let flow = observe(&Step {
                t_us,
                firmware: fw,
                delivered: &self.delivered,
                sent: &self.sent,
                truth,
            });
            self.delivered.clear();
            steps += 1;
            if flow.is_break() {
                stopped_at_us = Some(t_us);
                t_us += self.period_us;
                break;
            }
            // The plant, with the wheel faults of the period's end: the feedback stamped
            // then (emitted as the plant gets there) already shows them.
            set_wheel_faults(self.scenario, &mut self.plant, t_us + self.period_us);
            self.advance_period(fw, t_us * 1000)?;
            t_us += self.period_us;
        }
        self.finish(fw, t_us * 1000, steps, stopped_at_us, last_truth)
    }

    /// The tick at `t_us`: the host's frames, the drives' feedback, the node's step, and what
    /// the run logs and records of it. Returns the ground truth then.
    fn tick<F: Firmware>(&mut self, fw: &mut F, t_us: u64) -> Result<[f64; 3], F::Error> {
        let t_ns = t_us * 1000;
        self.twists.clear();
        self.host_frames.clear();
        self.host
            .frames_until(t_us, &mut self.host_frames, &mut self.twists);
        if let Some(inbox) = self.inbox {
            self.host_frames
                .extend(inbox.try_iter().map(|frame| (t_ns, frame)));
        }
        for &(at_ns, frame) in &self.host_frames {
            self.bus.send(at_ns, Node::Host, frame);
        }
        let bus = &mut self.bus;
        queue_feedback(&mut self.plant, &mut self.feedback, t_ns, |t, n, f| {
            bus.send(t, n, f);
        });
        self.sent.clear();
        fw.tick(&mut self.bus, t_us, &mut self.delivered, &mut self.sent)?;
        self.log_deliveries(fw.receiving())?;
        for f in &self.sent {
            self.hash.add(t_us, f);
        }
        self.tx_frames += self.sent.len() as u64;
        let plant = &self.plant;
        let truth = plant.truth();
        let velocity = || plant.truth_velocity();
        fw.observe(
            t_us,
            self.log.as_deref_mut(),
            truth,
            &velocity,
            &mut self.record,
        )?;
        if let Some(l) = self.log.as_deref_mut() {
            l.maybe_flush()?;
        }
        Ok(truth)
    }

    /// Logs the deliveries since the last tick, in delivery order, with the host's setpoint
    /// changes in time order among them, and counts the frames the node took (none if it is
    /// not `receiving`: a dead runner receives and logs nothing).
    fn log_deliveries(&mut self, receiving: bool) -> Result<(), LogError> {
        let mut twists_logged = 0;
        for tx in &self.delivered {
            if !receiving && tx.from != Node::Controller {
                continue;
            }
            if let Some(l) = self.log.as_deref_mut() {
                while let Some(&(at_ns, twist)) = self.twists.get(twists_logged)
                    && at_ns <= tx.delivered_ns
                {
                    l.twist(at_ns, twist)?;
                    twists_logged += 1;
                }
                log_transmission(l, tx, self.options)?;
            }
            if tx.fate != Fate::Dropped && tx.from != Node::Controller {
                self.rx_frames += 1;
            }
        }
        if let Some(l) = self.log.as_deref_mut() {
            for &(at_ns, twist) in &self.twists[twists_logged..] {
                l.twist(at_ns, twist)?;
            }
        }
        Ok(())
    }

    /// Advances the plant over the period from `t_ns`, together with the node and the bus:
    /// the frames for the drives (from the firmware and the host) act from their delivery
    /// time, as on a real drive, and the drives' feedback goes on the bus as it is sent. The
    /// bus runs ahead of the plant only up to the drives' next feedback, whose frames may win
    /// arbitration over the ones waiting.
    fn advance_period<F: Firmware>(&mut self, fw: &mut F, t_ns: u64) -> Result<(), F::Error> {
        let end_ns = t_ns + self.period_us * 1000;
        let mut now_ns = t_ns;
        while now_ns < end_ns {
            let horizon = end_ns.min(self.plant.next_feedback_ns().max(now_ns + 1));
            let (first, segment_start) = (self.delivered.len(), now_ns);
            fw.run_until(&mut self.bus, horizon, &mut self.delivered)?;
            // This segment's deliveries, each once and in order (two may share an instant
            // when a delay fault moves one). A frame its sender queued late (with a time the
            // bus had passed: a host faster than the core, a sensor node between feedbacks)
            // may have been delivered before the segment: the plant has gone past it.
            for tx in &self.delivered[first..] {
                if tx.from == Node::Controller {
                    let plant = &self.plant;
                    let truth = || (plant.truth(), plant.truth_velocity());
                    fw.on_own_frame(tx, self.log.as_deref_mut(), &truth, &mut self.record)?;
                }
                let for_drives = tx.from != Node::Drives && tx.fate != Fate::Dropped;
                if for_drives && tx.delivered_ns > segment_start {
                    self.plant.advance_ns(tx.delivered_ns - now_ns);
                    now_ns = tx.delivered_ns;
                    self.plant.on_frame(tx.delivered_ns / 1000, &tx.frame);
                }
            }
            self.plant.advance_ns(horizon - now_ns);
            now_ns = horizon;
            let bus = &mut self.bus;
            queue_feedback(&mut self.plant, &mut self.feedback, now_ns, |t, n, f| {
                bus.send(t, n, f);
            });
        }
        Ok(())
    }

    fn finish<F: Firmware>(
        mut self,
        fw: &mut F,
        end_ns: u64,
        steps: u64,
        stopped_at_us: Option<u64>,
        truth: [f64; 3],
    ) -> Result<Outcome, F::Error> {
        let (bus, bus_load) = (self.bus.stats(), self.bus.load(end_ns));
        // The frames the node sent at its last steps, once they are off the wire.
        let mut done = std::mem::take(&mut self.delivered);
        let drained = done.len();
        fw.drain(&mut self.bus, end_ns + DRAIN_NS, &mut done)?;
        for (i, tx) in done.iter().enumerate() {
            if tx.from != Node::Controller {
                continue;
            }
            if i >= drained {
                let plant = &self.plant;
                let truth = || (plant.truth(), plant.truth_velocity());
                fw.on_own_frame(tx, self.log.as_deref_mut(), &truth, &mut self.record)?;
            }
            if let Some(l) = self.log.as_deref_mut() {
                log_transmission(l, tx, self.options)?;
            }
        }
        Ok(Outcome {
            steps,
            duration_s: stopped_at_us.map_or(self.scenario.duration_s, |t| t as f64 * 1e-6),
            tx_frames: self.tx_frames,
            rx_frames: self.rx_frames,
            tx_hash: self.hash.value(),
            bus,
            bus_load,
            truth,
            record: self.record,
        })
    }
}

#[cfg(test)]
mod tests;
