//! The in-process run: the real firmware core ([`InProcess`], the same `Controller` that
//! runs on the MCU) as the firmware node of the lockstep [engine](crate::engine), with a
//! simulated plant and a host on one simulated bus, in simulated time.
//!
//! [`run`] plays a [`Scenario`] on a [`SimPlant`] (the plant as the engine sees it), logging
//! to MCAP if asked ([`crate::log`]), and returns a [`RunSummary`]; [`run_observed`] also
//! shows an observer every firmware step ([`StepView`]), and [`run_until`] lets it end the
//! run early. The same scenario gives the same frames, bit for bit, and the log is all that
//! [`crate::replay`] needs to run the firmware again.

use std::collections::BTreeMap;
use std::ops::ControlFlow;

use firmware::CanFrame;
use firmware::control::{Controller, Snapshot};
use firmware::protocol::robot::{self};

use crate::bus::{BusStats, Node, Transmission};
use crate::engine::InProcess;
use crate::log::{LogError, McapLog};
use crate::scenario::Scenario;

pub use crate::engine::{LogOptions, log_transmission, queue_feedback, set_wheel_faults};

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
    /// [`firmware::StreamHash`] of every frame the firmware sent, with its step time: equal hashes, equal
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
    log: Option<&mut McapLog>,
    options: LogOptions,
    mut observe: impl FnMut(&StepView<'_>) -> ControlFlow<()>,
) -> Result<RunSummary, SimError> {
    let mut core = InProcess::new(scenario, options)?;
    let run = crate::engine::run(scenario, &mut core, plant, log, options, |step| {
        observe(&StepView {
            t_us: step.t_us,
            controller: step.firmware.controller(),
            delivered: step.delivered,
            sent: step.sent,
            down: step.firmware.is_down(),
            truth: step.truth,
        })
    })?;
    let record = run.record;
    let (odometry, truth) = record.pose.unwrap_or((run.truth, run.truth));
    Ok(RunSummary {
        scenario: scenario.name.clone(),
        duration_s: run.duration_s,
        steps: run.steps,
        tx_frames: run.tx_frames,
        rx_frames: run.rx_frames,
        bus: run.bus,
        bus_load: run.bus_load,
        truth,
        odometry,
        final_position_error: libm::hypot(odometry[0] - truth[0], odometry[1] - truth[1]),
        max_position_error: record.max_position_error,
        final_heading_error: kinematics::wrap_angle(odometry[2] - truth[2]),
        last: core.controller().snapshot(),
        transitions: record.transitions,
        heading_changes: record.heading_changes,
        tx_hash: run.tx_hash,
        track: record.track,
    })
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

/// A plant for the unit tests of what wraps or drives one: it moves at a constant body
/// velocity and only counts time.
#[cfg(test)]
pub(crate) mod test_plant {
    use firmware::CanFrame;

    use super::SimPlant;

    /// A plant moving at the body velocity `v`, whose travel is exactly `v · t` (or, with
    /// `integrates = false`, that leaves the integral to the wrapper); it records every
    /// advance and every frame it is given, with the plant time then.
    pub(crate) struct Moving {
        pub now_ns: u64,
        pub v: [f64; 3],
        pub integrates: bool,
        pub advances: Vec<u64>,
        pub frames: Vec<(u64, CanFrame)>,
    }

    impl Moving {
        pub fn new(v: [f64; 3]) -> Self {
            Self {
                now_ns: 0,
                v,
                integrates: true,
                advances: Vec::new(),
                frames: Vec::new(),
            }
        }
    }

    impl SimPlant for Moving {
        fn on_frame(&mut self, _: u64, frame: &CanFrame) {
            self.frames.push((self.now_ns, *frame));
        }
        fn feedback(&mut self, _: u64, _: &mut Vec<(u64, CanFrame)>) {}
        fn advance(&mut self, dt: f64) {
            self.advance_ns((dt * 1e9).round() as u64);
        }
        fn advance_ns(&mut self, dt_ns: u64) {
            self.advances.push(dt_ns);
            self.now_ns += dt_ns;
        }
        fn truth(&self) -> [f64; 3] {
            [0.0; 3]
        }
        fn truth_velocity(&self) -> [f64; 3] {
            self.v
        }
        fn truth_travel(&self) -> Option<[f64; 3]> {
            let t = self.now_ns as f64 * 1e-9;
            self.integrates.then(|| self.v.map(|v| v * t))
        }
        fn set_faults(&mut self, _: u64, _: [bool; 4], _: [bool; 4]) {}
    }
}
