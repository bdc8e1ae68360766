//! The lockstep runner: the real firmware core, a simulated plant and a host on one
//! simulated bus, in simulated time.
//!
//! [`run`] plays a [`Scenario`] on a [`SimPlant`] (the plant as the runner sees it), logging
//! to MCAP if asked ([`crate::log`]), and returns a [`RunSummary`]; [`run_observed`] also
//! shows an observer every firmware step ([`StepView`]), and [`run_until`] lets it end the
//! run early. A tick is one control period (1 ms
//! by default). Nothing here reads a clock or draws an unseeded random number: the same
//! scenario gives the same frames, bit for bit, and the log is all that [`crate::replay`]
//! needs to run the firmware again.
//!
//! The order of one tick (host, feedback, bus, firmware step, plant), when feedback and
//! commands take effect, and what a run logs are specified in `docs/simulator.md`, section
//! "Lockstep runner".

use std::collections::BTreeMap;
use std::ops::ControlFlow;

use firmware::control::{Controller, Instant, Outbox, Snapshot};
use firmware::protocol::robot::{self};
use firmware::{CanFrame, StreamHash};

use crate::bus::{Bus, BusStats, Fate, Node, Transmission};
use crate::host::HostNode;
use crate::log::{Direction, LogError, McapLog};
use crate::scenario::Scenario;

/// The plant as the runner sees it: drives that take command frames and produce feedback
/// frames, and a body with a true pose.
pub trait SimPlant {
    /// A frame from the bus (the drives pick out their commands; anything else is ignored).
    fn on_frame(&mut self, t_us: u64, frame: &CanFrame);
    /// Feedback frames the drives have sent up to `until_ns`, each with its send time (ns),
    /// in time order; called once per tick.
    fn feedback(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>);
    /// The frames a sensor node on the plant has sent as bus node `node` up to `until_ns`
    /// (`IMU_YAW_RATE` as [`Node::Imu`], `POD_COUNTS` as [`Node::Pods`]), as
    /// [`Self::feedback`]. None by default: see [`crate::sensor::WithNode`], which the runner
    /// puts around the plant for the scenario's IMU and pods.
    fn node_frames(&mut self, _node: Node, _until_ns: u64, _out: &mut Vec<(u64, CanFrame)>) {}
    /// Advances the physics by `dt` seconds.
    fn advance(&mut self, dt: f64);
    /// Advances the physics by `dt_ns` nanoseconds ([`Self::advance`] by default).
    fn advance_ns(&mut self, dt_ns: u64) {
        self.advance(dt_ns as f64 * 1e-9);
    }
    /// When the drives next send feedback, ns of the plant's time (`u64::MAX`: not known,
    /// the runner then takes the period's end). The runner lets the bus run no further
    /// before it has those frames, which may win arbitration over the ones waiting.
    fn next_feedback_ns(&self) -> u64 {
        u64::MAX
    }
    /// Ground-truth pose `[x, y, heading]` in the world frame (m, m, rad).
    fn truth(&self) -> [f64; 3];
    /// Ground-truth body velocity `[vx, vy, wz]`.
    fn truth_velocity(&self) -> [f64; 3];
    /// Ground-truth body velocity integrated over time since the plant was built,
    /// `[∫vx dt, ∫vy dt, ∫wz dt]` (m, m, rad), in the plant's own integration steps
    /// ([`crate::plant::Chassis::body_travel`]); `None` (the default) for a plant that does
    /// not keep it: [`crate::pods::WithPods`] then integrates [`Self::truth_velocity`] itself.
    fn truth_travel(&self) -> Option<[f64; 3]> {
        None
    }
    /// Plant faults from `at_ns` on (at once if the plant is there already): `stuck[i]`
    /// freezes wheel i's encoder, `offline[i]` silences its drive. The motion before `at_ns`
    /// does not feel them; the feedback stamped `at_ns` does.
    fn set_faults(&mut self, at_ns: u64, stuck: [bool; 4], offline: [bool; 4]);
    /// CiA 402 drives' faults in force from `at_ns` on, by wheel (the wheel's node): a plant
    /// without CANopen nodes has none (such a scenario is refused before the run).
    fn set_drive_faults(&mut self, _at_ns: u64, _faults: [DriveFaults; 4]) {}
}

/// The CiA 402 faults in force on one wheel's drive (its node), from the scenario's
/// `drive_*`, `enable_refused` and `sdo_abort` faults.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DriveFaults {
    /// `drive_silent`: no heartbeat.
    pub silent: bool,
    /// `drive_reboot`: its rising edge reboots the node.
    pub reboot: bool,
    /// `drive_fault`: its rising edge faults the node.
    pub fault: bool,
    /// `enable_refused`.
    pub refuses_enable: bool,
    /// `sdo_abort`: the write of 0x6060 is aborted.
    pub sdo_abort: bool,
    /// `drive_bus_off`: its CAN controller is bus-off (it comes back when this ends).
    pub bus_off: bool,
}

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

/// Figures of a finished run.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    /// Scenario name.
    pub scenario: String,
    /// Simulated time, s.
    pub duration_s: f64,
    /// Control steps run.
    pub steps: u64,
    /// Frames the firmware sent.
    pub tx_frames: u64,
    /// Frames the firmware received.
    pub rx_frames: u64,
    /// Bus figures.
    pub bus: BusStats,
    /// Bus load over the run (0..1).
    pub bus_load: f64,
    /// Ground-truth pose at the last step (the time of the final odometry).
    pub truth: [f64; 3],
    /// Final odometry pose.
    pub odometry: [f64; 3],
    /// Final position error of odometry against ground truth, m.
    pub final_position_error: f64,
    /// Largest position error during the run, m.
    pub max_position_error: f64,
    /// Final heading error, rad.
    pub final_heading_error: f64,
    /// Final firmware snapshot.
    pub last: Snapshot,
    /// State changes `(time s, state, fault)`.
    pub transitions: Vec<(f64, String, String)>,
    /// [`StreamHash`] of every frame the firmware sent, with its step time: equal hashes, equal
    /// streams.
    pub tx_hash: u64,
    /// Changes of the firmware's heading source `(time s, source)` (gyro heading only: a
    /// robot without a gyro stays on `Wheels`).
    pub heading_changes: Vec<(f64, String)>,
    /// Ground truth and odometry every 10 ms, for plots.
    pub track: Vec<crate::plot::TrackPoint>,
}

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The configuration was refused by the firmware.
    #[error("configuration: {0}")]
    Config(#[from] firmware::config::ConfigError),
    /// The log could not be written.
    #[error(transparent)]
    Log(#[from] LogError),
}

/// What the runner shows an observer after each firmware step (see [`run_observed`]).
#[derive(Debug)]
pub struct StepView<'a> {
    /// Simulated time of the step, µs.
    pub t_us: u64,
    /// The firmware just after the step ([`Controller::snapshot`] for the details).
    pub controller: &'a Controller,
    /// Every transmission that reached the receivers since the previous step, in delivery
    /// order: all senders, all fates (dropped ones too).
    pub delivered: &'a [Transmission],
    /// The frames the firmware sent at this step.
    pub sent: &'a [CanFrame],
    /// The firmware is not running (a `runner_restart` fault's window): `controller` is the
    /// core as it stopped, it received nothing and `sent` is empty.
    pub down: bool,
    /// Ground-truth pose `[x, y, heading]` at the step.
    pub truth: [f64; 3],
}

/// How long after a run's last step the bus runs on, so that the frames the firmware sent at
/// its last steps are logged: far longer than a frame waits on a loaded bus.
const DRAIN_NS: u64 = 100_000_000;

/// Logs one transmission: on `/can/rx` if the firmware received it, on `/can/tx` if it sent
/// it (dropped or not), and on `/can/faults` if the fault injector dropped or corrupted it.
///
/// # Errors
/// The log could not be written.
pub fn log_transmission(
    l: &mut McapLog,
    tx: &Transmission,
    options: LogOptions,
) -> Result<(), LogError> {
    if options.faults && tx.fate != Fate::Delivered {
        l.bus_fault(
            tx.end_ns,
            tx.from.name(),
            tx.fate.name(),
            &tx.sent,
            &tx.frame,
        )?;
    }
    if tx.from == Node::Controller {
        l.frame(
            Direction::Tx,
            tx.delivered_ns,
            tx.queued_ns,
            tx.end_ns,
            &tx.sent,
        )
    } else if tx.fate != Fate::Dropped {
        l.frame(
            Direction::Rx,
            tx.delivered_ns,
            tx.queued_ns,
            tx.end_ns,
            &tx.frame,
        )
    } else {
        Ok(())
    }
}

/// Runs `scenario` with `plant`, logging to `log` if given; `progress` is called with the
/// simulated time (µs) every simulated 100 ms.
///
/// # Errors
/// [`SimError`] if the configuration is refused or the log cannot be written.
pub fn run<P: SimPlant>(
    scenario: &Scenario,
    plant: &mut P,
    log: Option<&mut McapLog>,
    options: LogOptions,
    mut progress: impl FnMut(u64),
) -> Result<RunSummary, SimError> {
    run_observed(scenario, plant, log, options, |step| {
        if step.t_us.is_multiple_of(100_000) {
            progress(step.t_us);
        }
    })
}

/// [`run`], calling `observe` after every firmware step: for tests and tools that measure
/// what happens step by step (fault latencies, command streams).
///
/// # Errors
/// [`SimError`] if the configuration is refused or the log cannot be written.
pub fn run_observed<P: SimPlant>(
    scenario: &Scenario,
    plant: &mut P,
    log: Option<&mut McapLog>,
    options: LogOptions,
    mut observe: impl FnMut(&StepView<'_>),
) -> Result<RunSummary, SimError> {
    run_until(scenario, plant, log, options, |step| {
        observe(step);
        ControlFlow::Continue(())
    })
}

/// [`run_observed`], whose observer may end the run after any step with
/// [`ControlFlow::Break`] (a run stopped by Ctrl-C): the run then ends as at the scenario's
/// end (the frames on the wire logged, the summary of the steps run), and the summary's
/// `duration_s` is the simulated time of the last step.
///
/// # Errors
/// [`SimError`] if the configuration is refused or the log cannot be written.
pub fn run_until<P: SimPlant>(
    scenario: &Scenario,
    plant: &mut P,
    mut log: Option<&mut McapLog>,
    options: LogOptions,
    mut observe: impl FnMut(&StepView<'_>) -> ControlFlow<()>,
) -> Result<RunSummary, SimError> {
    // The scenario's IMU node and pod node, if any, on the plant (without them, a
    // pass-through).
    let plant = &mut crate::imu::WithImu::new(plant, scenario.imu.as_ref(), scenario.seed);
    let plant = &mut crate::pods::WithPods::for_scenario(plant, scenario);
    let mut ctl = Controller::new(&scenario.config)?;
    // The runner's deaths: from, until (µs); a fresh core starts at `until`.
    let restarts: Vec<(u64, u64)> = scenario
        .node_faults
        .iter()
        .filter(|f| f.kind == crate::scenario::FaultName::RunnerRestart)
        .map(|f| (f.from_us, f.until_us))
        .collect();
    let mut was_down = false;
    let period_us = ctl.period_micros();
    let period_ns = period_us * 1000;
    let mut bus = Bus::new(1_000_000, scenario.bus_faults.clone(), scenario.seed);
    let mut host = HostNode::new(scenario);
    let mut host_frames = Vec::new();
    let duration_us = scenario.duration_us();
    let mut in_flight: Vec<Transmission> = Vec::new();
    let mut delivered: Vec<Transmission> = Vec::new();
    let mut feedback = Vec::with_capacity(16);
    let mut summary_tx = 0u64;
    let mut summary_rx = 0u64;
    let mut hash = StreamHash::default();
    let mut max_err = 0.0f64;
    // Ground truth at the last step, the time of the last odometry (the plant then advances
    // one more period, which the firmware never sees).
    let mut last_truth = plant.truth();
    let mut transitions = Vec::new();
    // The firmware boots DISABLED without a fault: the log says the changes from there.
    let mut core_log =
        crate::log::CoreLog::new(options.snapshot_every, options.pose_every).from_boot();
    let mut heading_changes = Vec::new();
    let mut t_us = 0u64;
    let mut step = 0u64;
    let mut track = Vec::with_capacity((duration_us / 10_000 + 2) as usize);
    let mut stopped_at_us = None;

    set_wheel_faults(scenario, plant, 0);
    let mut twists_to_log = Vec::new();
    let mut out = Outbox::new();
    while t_us <= duration_us {
        let t_ns = t_us * 1000;
        let down = restarts
            .iter()
            .any(|&(from, until)| from <= t_us && t_us < until);
        if was_down && !down {
            ctl = Controller::new(&scenario.config)?;
        }
        was_down = down;
        twists_to_log.clear();
        // 1. Host.
        host_frames.clear();
        host.frames_until(t_us, &mut host_frames, &mut twists_to_log);
        for &(at_ns, frame) in &host_frames {
            bus.send(at_ns, Node::Host, frame);
        }

        // 2. Drives (their faults of t were set before the plant reached t, below).
        queue_feedback(plant, &mut feedback, t_ns, |t, n, f| bus.send(t, n, f));

        // 3. Bus up to t.
        bus.advance_into(t_ns + 1, &mut in_flight);
        // 4. Deliveries due by t, in delivery order.
        in_flight.sort_by_key(|tx| tx.delivered_ns);
        let due = in_flight.partition_point(|tx| tx.delivered_ns <= t_ns);
        delivered.clear();
        delivered.extend(in_flight.drain(..due));
        let mut twists_logged = 0;
        for tx in &delivered {
            // A dead runner receives (and logs) nothing.
            if down && tx.from != Node::Controller {
                continue;
            }
            if let Some(l) = log.as_deref_mut() {
                // The host's setpoint changes in time order with the deliveries.
                while let Some(&(at_ns, twist)) = twists_to_log.get(twists_logged)
                    && at_ns <= tx.delivered_ns
                {
                    l.twist(at_ns, twist)?;
                    twists_logged += 1;
                }
                log_transmission(l, tx, options)?;
            }
            if tx.fate == Fate::Dropped || tx.from == Node::Controller {
                continue;
            }
            ctl.on_frame(Instant::from_micros(tx.delivered_ns / 1000), &tx.frame);
            summary_rx += 1;
        }
        if let Some(l) = log.as_deref_mut() {
            for &(at_ns, twist) in &twists_to_log[twists_logged..] {
                l.twist(at_ns, twist)?;
            }
        }

        // 5. Firmware step.
        if down {
            out.clear();
        } else {
            ctl.step_into(Instant::from_micros(t_us), &mut out);
        }
        for f in &out {
            bus.send(t_ns, Node::Controller, *f);
            hash.add(t_us, f);
            summary_tx += 1;
        }
        let odom = pose_array(ctl.pose());
        let truth = plant.truth();
        last_truth = truth;
        max_err = max_err.max(libm::hypot(odom[0] - truth[0], odom[1] - truth[1]));
        if t_us.is_multiple_of(10_000) {
            track.push(crate::plot::TrackPoint {
                t: t_us as f64 * 1e-6,
                truth: [truth[0], truth[1]],
                odom: [odom[0], odom[1]],
            });
        }
        let truth_now = || (truth, plant.truth_velocity());
        let changes = if down {
            crate::log::Changes::default()
        } else {
            core_log.step(log.as_deref_mut(), t_ns, &ctl, Some(&truth_now))?
        };
        if changes.state {
            let (state, fault) = (ctl.state().to_string(), ctl.fault().to_string());
            transitions.push((t_us as f64 * 1e-6, state, fault));
        }
        if changes.heading {
            heading_changes.push((t_us as f64 * 1e-6, ctl.heading_source().to_string()));
        }
        if let Some(l) = log.as_deref_mut() {
            l.maybe_flush()?;
        }

        let flow = observe(&StepView {
            t_us,
            controller: &ctl,
            delivered: &delivered,
            sent: &out,
            truth,
            down,
        });
        if flow.is_break() {
            stopped_at_us = Some(t_us);
            step += 1;
            t_us += period_us;
            break;
        }

        // 6. Plant, with the wheel faults of the period's end: the feedback stamped then
        // (emitted as the plant gets there) already shows them.
        set_wheel_faults(scenario, plant, t_us + period_us);
        advance_period(
            plant,
            &mut bus,
            &mut in_flight,
            &mut feedback,
            t_ns,
            period_ns,
        );
        t_us += period_us;
        step += 1;
    }

    let end_ns = t_us * 1000;
    let (bus_stats, bus_load) = (bus.stats(), bus.load(end_ns));
    if let Some(l) = log {
        // The frames the firmware sent at its last steps, once they are off the wire.
        bus.advance_into(end_ns + DRAIN_NS, &mut in_flight);
        in_flight.sort_by_key(|tx| tx.delivered_ns);
        for tx in in_flight.iter().filter(|tx| tx.from == Node::Controller) {
            log_transmission(l, tx, options)?;
        }
    }
    let odom = pose_array(ctl.pose());
    let truth = last_truth;
    Ok(RunSummary {
        scenario: scenario.name.clone(),
        duration_s: stopped_at_us.map_or(scenario.duration_s, |t| t as f64 * 1e-6),
        steps: step,
        tx_frames: summary_tx,
        rx_frames: summary_rx,
        bus: bus_stats,
        bus_load,
        truth,
        odometry: odom,
        final_position_error: libm::hypot(odom[0] - truth[0], odom[1] - truth[1]),
        max_position_error: max_err,
        final_heading_error: kinematics::wrap_angle(odom[2] - truth[2]),
        last: ctl.snapshot(),
        transitions,
        heading_changes,
        tx_hash: hash.value(),
        track,
    })
}

/// The firmware's pose as `[x, y, heading]` in f64, the plant's format.
fn pose_array(p: kinematics::Pose2<f32>) -> [f64; 3] {
    [f64::from(p.x), f64::from(p.y), f64::from(p.heading)]
}

#[cfg(test)]
fn id_of(frame: &CanFrame) -> u16 {
    match embedded_can::Frame::id(frame) {
        embedded_can::Id::Standard(id) => id.as_raw(),
        embedded_can::Id::Extended(_) => 0,
    }
}

/// Advances the plant over the period `(t_ns, t_ns + period_ns]`, together with the bus: the
/// frames for the drives (commands from the firmware and the host) act from their delivery
/// time, as on a real drive, and the drives' feedback goes on the bus as it is sent. The bus
/// runs ahead of the plant only up to the drives' next feedback, whose frames may win
/// arbitration over the ones waiting. Every transmission stays in `in_flight` for the
/// firmware's side (step 4 of the next ticks).
fn advance_period<P: SimPlant>(
    plant: &mut P,
    bus: &mut Bus,
    in_flight: &mut Vec<Transmission>,
    feedback: &mut Vec<(u64, CanFrame)>,
    t_ns: u64,
    period_ns: u64,
) {
    let end_ns = t_ns + period_ns;
    let mut now_ns = t_ns;
    while now_ns < end_ns {
        let horizon = end_ns.min(plant.next_feedback_ns().max(now_ns + 1));
        // Frames delivered by `horizon` started before it: all of them are known after this.
        bus.advance_into(horizon, in_flight);
        in_flight.sort_by_key(|tx| tx.delivered_ns);
        // This segment's deliveries, `(segment_start, horizon]`, each once and in order (two
        // may share an instant when a delay fault moves one).
        let segment_start = now_ns;
        for tx in in_flight.iter() {
            let for_drives = tx.from != Node::Drives && tx.fate != Fate::Dropped;
            if for_drives && tx.delivered_ns > segment_start && tx.delivered_ns <= horizon {
                plant.advance_ns(tx.delivered_ns - now_ns);
                now_ns = tx.delivered_ns;
                plant.on_frame(tx.delivered_ns / 1000, &tx.frame);
            }
        }
        plant.advance_ns(horizon - now_ns);
        now_ns = horizon;
        queue_feedback(plant, feedback, now_ns, |t, n, f| bus.send(t, n, f));
    }
}

/// Hands `send` the drives' feedback frames, the IMU's and the pod node's frames sent up to
/// `until_ns`, each with its send time and its node (the drives', then the IMU's, then the
/// pods', each in time order); `feedback` is scratch space.
pub fn queue_feedback<P: SimPlant>(
    plant: &mut P,
    feedback: &mut Vec<(u64, CanFrame)>,
    until_ns: u64,
    mut send: impl FnMut(u64, Node, CanFrame),
) {
    for node in [Node::Drives, Node::Imu, Node::Pods] {
        feedback.clear();
        match node {
            Node::Drives => plant.feedback(until_ns, feedback),
            _ => plant.node_frames(node, until_ns, feedback),
        }
        for &(at_ns, f) in feedback.iter() {
            send(at_ns, node, f);
        }
    }
}

/// Sets the scenario's wheel faults in force at `t_us` on the plant, from `t_us` on.
pub fn set_wheel_faults<P: SimPlant>(s: &Scenario, plant: &mut P, t_us: u64) {
    let stuck = wheel_flags(s, t_us, crate::scenario::FaultName::StuckEncoder);
    let offline = wheel_flags(s, t_us, crate::scenario::FaultName::MotorOffline);
    plant.set_faults(t_us * 1000, stuck, offline);
    if s.wheel_faults.iter().any(|f| f.kind.cia402_only()) {
        use crate::scenario::FaultName as F;
        let [silent, reboot, fault, refuses_enable, sdo_abort, bus_off] = [
            F::DriveSilent,
            F::DriveReboot,
            F::DriveFault,
            F::EnableRefused,
            F::SdoAbort,
            F::DriveBusOff,
        ]
        .map(|kind| wheel_flags(s, t_us, kind));
        let faults = core::array::from_fn(|i| DriveFaults {
            silent: silent[i],
            reboot: reboot[i],
            fault: fault[i],
            refuses_enable: refuses_enable[i],
            sdo_abort: sdo_abort[i],
            bus_off: bus_off[i],
        });
        plant.set_drive_faults(t_us * 1000, faults);
    }
}

fn wheel_flags(s: &Scenario, t_us: u64, kind: crate::scenario::FaultName) -> [bool; 4] {
    let mut flags = [false; 4];
    for f in &s.wheel_faults {
        if f.kind == kind && f.active(t_us) {
            flags[f.wheel] = true;
        }
    }
    flags
}

/// The run's metadata for the log: configuration TOML, scenario name, seed, tool version.
/// A scenario's `[plant]`, when it has one, is the `plant` key (TOML).
#[must_use]
pub fn run_metadata(scenario: &Scenario) -> BTreeMap<String, String> {
    let mut metadata = BTreeMap::from([
        ("config".to_string(), scenario.config.to_toml_string()),
        (
            "config_id".to_string(),
            format!("0x{:04x}", scenario.config.id()),
        ),
        ("scenario".to_string(), scenario.name.clone()),
        ("seed".to_string(), scenario.seed.to_string()),
        ("program".to_string(), "hostsim run".to_string()),
        (
            "hostsim_version".to_string(),
            env!("CARGO_PKG_VERSION").to_string(),
        ),
        (
            "protocol_version".to_string(),
            robot::PROTOCOL_VERSION.to_string(),
        ),
    ]);
    if !scenario.plant.is_empty() {
        let plant = toml::to_string(&scenario.plant).unwrap_or_default();
        metadata.insert("plant".to_string(), plant);
    }
    metadata
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::{Fault, FaultKind, frame_bits};
    use embedded_can::StandardId;

    /// Records the plant time of every frame it is given.
    #[derive(Default)]
    struct Recorder {
        now_ns: u64,
        applied: Vec<(u64, u16)>,
    }

    impl SimPlant for Recorder {
        fn on_frame(&mut self, _: u64, frame: &CanFrame) {
            self.applied.push((self.now_ns, id_of(frame)));
        }
        fn feedback(&mut self, _: u64, _: &mut Vec<(u64, CanFrame)>) {}
        fn advance(&mut self, dt: f64) {
            self.advance_ns((dt * 1e9).round() as u64);
        }
        fn advance_ns(&mut self, dt_ns: u64) {
            self.now_ns += dt_ns;
        }
        fn truth(&self) -> [f64; 3] {
            [0.0; 3]
        }
        fn truth_velocity(&self) -> [f64; 3] {
            [0.0; 3]
        }
        fn set_faults(&mut self, _: u64, _: [bool; 4], _: [bool; 4]) {}
    }

    #[test]
    fn an_observer_can_end_the_run_after_any_step() {
        let s = Scenario::load("square", None).unwrap();
        let mut plant = crate::drives::SimDrives::for_scenario(&s).unwrap();
        let mut last = 0;
        let summary = run_until(&s, &mut plant, None, LogOptions::default(), |step| {
            last = step.t_us;
            if step.t_us >= 500_000 {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })
        .unwrap();
        assert_eq!(last, 500_000);
        assert_eq!(summary.steps, 501);
        assert!(
            (summary.duration_s - 0.5).abs() < 1e-12,
            "{}",
            summary.duration_s
        );
        // The same steps as a whole run's first half second.
        let mut whole = Vec::new();
        let mut plant = crate::drives::SimDrives::for_scenario(&s).unwrap();
        run_observed(&s, &mut plant, None, LogOptions::default(), |step| {
            if step.t_us <= 500_000 {
                whole.push(step.controller.pose());
            }
        })
        .unwrap();
        assert_eq!(summary.odometry, pose_array(whole[500]));
    }

    #[test]
    fn frames_for_the_drives_act_at_their_delivery_even_at_the_same_instant() {
        let frame = |id| CanFrame::standard(StandardId::new(id).unwrap(), &[0; 8]).unwrap();
        let (a, b) = (frame(0x200), frame(0x300));
        // 0x200 wins arbitration and ends first; delayed by the length of 0x300, it reaches
        // the drives at the very instant 0x300 does.
        let delay_us = u64::from(frame_bits(&b));
        let mut bus = Bus::new(
            1_000_000,
            vec![Fault {
                kind: FaultKind::Delay { micros: delay_us },
                from_us: 0,
                until_us: 1_000,
                sender: Some(Node::Controller),
            }],
            1,
        );
        bus.send(0, Node::Controller, a);
        bus.send(0, Node::Host, b);
        let mut plant = Recorder::default();
        let (mut in_flight, mut feedback) = (Vec::new(), Vec::new());
        advance_period(
            &mut plant,
            &mut bus,
            &mut in_flight,
            &mut feedback,
            0,
            1_000_000,
        );
        let at = u64::from(frame_bits(&a) + frame_bits(&b)) * 1000;
        assert_eq!(plant.applied, [(at, 0x200), (at, 0x300)]);
        assert_eq!(plant.now_ns, 1_000_000);
        // Both stay in flight for the firmware's side.
        assert_eq!(in_flight.len(), 2);
    }
}
