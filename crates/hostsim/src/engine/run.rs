//! The in-process run: the real firmware core ([`InProcess`], the same `Controller` that
//! runs on the MCU) as the firmware node of the lockstep [engine](crate::engine), with a
//! simulated plant and a host on one simulated bus, in simulated time.
//!
//! [`run`] plays a [`Scenario`] on a [`SimPlant`] (the plant as the engine sees it), logging
//! to MCAP if asked ([`drivelog`]), and returns a [`RunSummary`]; [`run_observed`] also
//! shows an observer every firmware step ([`StepView`]), and [`run_until`] lets it end the
//! run early. The same scenario gives the same frames, bit for bit, and the log is all that
//! [`crate::replay`] needs to run the firmware again.

use std::collections::BTreeMap;
use std::ops::ControlFlow;
use std::sync::mpsc::Receiver;

use firmware::CanFrame;
use firmware::control::{Controller, Snapshot};
use firmware::protocol::robot::{self};

use crate::bus::{BusStats, Transmission};
use crate::engine::InProcess;
use crate::nodes::SimPlant;
use crate::scenario::Scenario;
use drivelog::{LogError, McapLog};

use super::LogOptions;

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
    pub track: Vec<super::TrackPoint>,
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
    /// The simulated parameter flash refused a read or an erase at boot.
    #[error("parameter flash: {0:?}")]
    Flash(embedded_storage::nor_flash::NorFlashErrorKind),
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
    observe: impl FnMut(&StepView<'_>) -> ControlFlow<()>,
) -> Result<RunSummary, SimError> {
    run_live(scenario, plant, log, options, None, observe)
}

/// [`run_until`], the host also sending the frames that come on `inbox`
/// ([`run_firmware_live`](crate::engine::run_firmware_live)): `hostsim run --live`'s
/// parameter requests.
///
/// # Errors
/// As [`run_until`].
pub fn run_live<P: SimPlant>(
    scenario: &Scenario,
    plant: &mut P,
    log: Option<&mut McapLog>,
    options: LogOptions,
    inbox: Option<&Receiver<CanFrame>>,
    mut observe: impl FnMut(&StepView<'_>) -> ControlFlow<()>,
) -> Result<RunSummary, SimError> {
    let mut core = InProcess::new(scenario, options)?;
    let run = crate::engine::run_firmware_live(
        scenario,
        &mut core,
        plant,
        log,
        options,
        inbox,
        |step| {
            observe(&StepView {
                t_us: step.t_us,
                controller: step.firmware.controller(),
                delivered: step.delivered,
                sent: step.sent,
                down: step.firmware.is_down(),
                truth: step.truth,
            })
        },
    )?;
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
