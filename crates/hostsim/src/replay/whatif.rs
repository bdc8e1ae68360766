//! What-if replay: a logged session through a core built from another configuration, to see
//! what a gain or limit change would have changed in the frames the firmware sent.
//!
//! [`what_if_mcap`] replays a log's inbound frames through a fresh [`Controller`] built from
//! a configuration file and returns a [`WhatIfReport`] ([`IdComparison`], [`SeriesDiff`],
//! [`StateComparison`]); [`what_if_frames`] does the same on frames already read, and
//! [`check_compatible`] refuses a configuration for other drives ([`Incompatible`]). It is
//! open loop: the plant's reaction to the changed outputs is **not** simulated.
//!
//! What is fed, what is compared, what is refused and why the report is deterministic:
//! `docs/simulator.md`, section "What-if replay".

use std::collections::BTreeMap;
use std::fmt;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use firmware::CanFrame;
use firmware::config::{Cia402Drive, Config, ConfigError, Drive, LoadError};
use firmware::control::Controller;
use firmware::protocol::robot::{Fault, RobotState, Telemetry};
use firmware::protocol::{canopen, dji, odrive};
use serde::Serialize;

use crate::replay::{
    Inputs, ReplayError, ReportFrame, StepTime, TimeGap, TimedFrame, open_mcap, run_schedule,
    step_schedule, wire_order,
};
use drivelog::ReadReport;

/// The first line of every what-if report: what it is, and what it is not.
pub const OPEN_LOOP_NOTE: &str = "what-if, open loop: the logged inbound frames (motor \
     feedback, host commands) are fed as recorded; the plant's reaction to the changed outputs \
     is not simulated";

/// Wheel names, in the order of every wheel array.
pub const WHEELS: [&str; 4] = ["FL", "FR", "RL", "RR"];

/// A what-if configuration that cannot replay a log: which field differs, and both values.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field} differs (log: {logged}, what-if: {what_if}): {why}")]
pub struct Incompatible {
    /// The dotted field, e.g. `drive.protocol` or `drive.esc_ids`.
    pub field: &'static str,
    /// The logged value.
    pub logged: String,
    /// The what-if value.
    pub what_if: String,
    /// Why that cannot be replayed.
    pub why: &'static str,
}

const OTHER_BUS: &str = "the recorded inbound frames are another drive's feedback and mean \
     nothing to this configuration";

/// Checks that `what_if` drives the same motors on the same bus as `logged`: the same
/// protocol, ESC model and ESC ids (DJI) or node ids (ODrive), wheel for wheel.
///
/// # Errors
/// The first [`Incompatible`] field.
pub fn check_compatible(logged: &Config, what_if: &Config) -> Result<(), Incompatible> {
    let ids = |ids: [u8; 4]| format!("{ids:?}");
    match (logged.drive, what_if.drive) {
        (
            Drive::Dji {
                model: m0,
                esc_ids: i0,
                ..
            },
            Drive::Dji {
                model: m1,
                esc_ids: i1,
                ..
            },
        ) => {
            if m0 != m1 {
                return Err(Incompatible {
                    field: "drive.model",
                    logged: model_name(m0).into(),
                    what_if: model_name(m1).into(),
                    why: "the recorded feedback came from the logged ESC model (another current \
                          scale and encoder)",
                });
            }
            if i0 != i1 {
                return Err(Incompatible {
                    field: "drive.esc_ids",
                    logged: ids(i0),
                    what_if: ids(i1),
                    why: OTHER_BUS,
                });
            }
        }
        (Drive::Odrive { node_ids: i0, .. }, Drive::Odrive { node_ids: i1, .. }) => {
            if i0 != i1 {
                return Err(Incompatible {
                    field: "drive.node_ids",
                    logged: ids(i0),
                    what_if: ids(i1),
                    why: OTHER_BUS,
                });
            }
        }
        (
            Drive::Cia402(Cia402Drive {
                node_ids: i0,
                axes: a0,
                ..
            }),
            Drive::Cia402(Cia402Drive {
                node_ids: i1,
                axes: a1,
                ..
            }),
        ) => {
            if (i0, a0) != (i1, a1) {
                let field = if i0 == i1 {
                    "drive.axes"
                } else {
                    "drive.node_ids"
                };
                let (l, w) = if i0 == i1 { (a0, a1) } else { (i0, i1) };
                return Err(Incompatible {
                    field,
                    logged: ids(l),
                    what_if: ids(w),
                    why: OTHER_BUS,
                });
            }
        }
        (a, b) => {
            return Err(Incompatible {
                field: "drive.protocol",
                logged: protocol_name(&a).into(),
                what_if: protocol_name(&b).into(),
                why: OTHER_BUS,
            });
        }
    }
    Ok(())
}

fn protocol_name(drive: &Drive) -> &'static str {
    match drive {
        Drive::Dji { .. } => "dji",
        Drive::Odrive { .. } => "odrive",
        Drive::Cia402(_) => "cia402",
    }
}

fn model_name(model: dji::EscModel) -> &'static str {
    match model {
        dji::EscModel::C620 => "c620",
        dji::EscModel::C610 => "c610",
    }
}

/// Why a what-if could not run on given frames.
#[derive(Debug, thiserror::Error)]
pub enum WhatIfRunError {
    /// The what-if configuration describes other drives.
    #[error(transparent)]
    Incompatible(#[from] Incompatible),
    /// The firmware refuses the what-if configuration.
    #[error("refused by the firmware: {0}")]
    Refused(#[from] ConfigError),
    /// The frames' time line has a gap longer than [`crate::replay::MAX_GAP_NS`].
    #[error(transparent)]
    TimeGap(#[from] TimeGap),
}

/// Why `hostsim replay LOG --config FILE` could not run.
#[derive(Debug, thiserror::Error)]
pub enum WhatIfError {
    /// The log cannot be replayed at all.
    #[error(transparent)]
    Log(#[from] ReplayError),
    /// The what-if configuration does not load (its error names the file and the field).
    #[error("what-if configuration {source}")]
    Config {
        /// The loader's error.
        source: Box<LoadError>,
    },
    /// The what-if configuration is refused by the firmware.
    #[error("what-if configuration {}: refused by the firmware: {source}", path.display())]
    Refused {
        /// The configuration file.
        path: PathBuf,
        /// Which field and value.
        source: ConfigError,
    },
    /// The what-if configuration describes other drives than the log's.
    #[error(
        "what-if configuration {} cannot replay {}: {source}",
        config.display(),
        log.display()
    )]
    Incompatible {
        /// The log file.
        log: PathBuf,
        /// The configuration file.
        config: PathBuf,
        /// What differs.
        source: Box<Incompatible>,
    },
    /// The log's time line has a gap too long to replay.
    #[error("{}: {source}", log.display())]
    TimeGap {
        /// The log file.
        log: PathBuf,
        /// The gap.
        source: TimeGap,
    },
}

/// A configuration field that the what-if changes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ConfigChange {
    /// Dotted field, e.g. `gains.kp`.
    pub field: String,
    /// The logged value (TOML; `None`: not in the logged configuration).
    pub logged: Option<String>,
    /// The what-if value (TOML; `None`: not in the what-if configuration).
    pub what_if: Option<String>,
}

/// The fields in which two configurations differ, in field order.
#[must_use]
pub fn config_changes(logged: &Config, what_if: &Config) -> Vec<ConfigChange> {
    // Through the TOML text, so that an f32 prints as written (1.2, not 1.2000000476837158).
    fn flatten(prefix: &str, value: &toml::Value, out: &mut BTreeMap<String, String>) {
        match value {
            toml::Value::Table(t) => {
                for (k, v) in t {
                    let key = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    flatten(&key, v, out);
                }
            }
            other => {
                out.insert(prefix.to_string(), other.to_string());
            }
        }
    }
    let fields = |c: &Config| {
        let mut out = BTreeMap::new();
        if let Ok(t) = c.to_toml_string().parse::<toml::Table>() {
            flatten("", &toml::Value::Table(t), &mut out);
        }
        out
    };
    let (a, b) = (fields(logged), fields(what_if));
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| ConfigChange {
            field: k.clone(),
            logged: a.get(k).cloned(),
            what_if: b.get(k).cloned(),
        })
        .collect()
}

/// The first outbound frame where the what-if and the log differ.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct FirstDifference {
    /// Index in the outbound stream.
    pub index: usize,
    /// Step time, s: the earlier of the two frames'.
    pub t_s: String,
    /// The logged frame (`None`: the log has no more).
    pub logged: Option<ReportFrame>,
    /// The what-if core's frame (`None`: it sent no more).
    pub what_if: Option<ReportFrame>,
}

/// One arbitration id's frames, logged against what-if.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct IdComparison {
    /// The arbitration id, hex (`0x200`; 8 digits for an extended id).
    pub id: String,
    /// The message, as the firmware's codecs name it (`C620/C610 current ESC 1-4`,
    /// `Set_Input_Vel node 2`, `STATUS`...).
    pub message: String,
    /// Frames in the log.
    pub logged: usize,
    /// Frames the what-if core sent.
    pub what_if: usize,
    /// Pairs (same step, same place in it) whose data differ.
    pub changed: usize,
    /// Logged frames the what-if core did not send at that step.
    pub only_logged: usize,
    /// Frames the what-if core sent that the log does not have at that step.
    pub only_what_if: usize,
}

impl IdComparison {
    /// Frames that differ: changed, or without a partner.
    #[must_use]
    pub const fn differ(&self) -> usize {
        self.changed + self.only_logged + self.only_what_if
    }
}

/// The difference of two setpoint series, each held from one command to the next.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SeriesDiff {
    /// Times (either side sent a command, both had one) at which the difference was taken.
    pub samples: usize,
    /// Largest |what-if − logged|.
    pub max_abs_difference: f64,
    /// When the largest difference was first reached, s (`None`: no difference).
    pub t_max_difference_s: Option<String>,
    /// RMS of what-if − logged over the samples.
    pub rms_difference: f64,
}

/// Compares two series of `(t_ns, value)` in time order, each held from one value to the
/// next: at every time either has a value, once both have one, the difference `b - a`.
#[must_use]
pub fn compare_series(a: &[(u64, f64)], b: &[(u64, f64)]) -> SeriesDiff {
    let (mut i, mut j) = (0, 0);
    let (mut va, mut vb) = (None, None);
    let mut out = SeriesDiff {
        samples: 0,
        max_abs_difference: 0.0,
        t_max_difference_s: None,
        rms_difference: 0.0,
    };
    let mut sum_sq = 0.0;
    let mut t_max = None;
    loop {
        let t = match (a.get(i), b.get(j)) {
            (Some(x), Some(y)) => x.0.min(y.0),
            (Some(x), None) => x.0,
            (None, Some(y)) => y.0,
            (None, None) => break,
        };
        while let Some(&(ta, v)) = a.get(i)
            && ta <= t
        {
            va = Some(v);
            i += 1;
        }
        while let Some(&(tb, v)) = b.get(j)
            && tb <= t
        {
            vb = Some(v);
            j += 1;
        }
        if let (Some(x), Some(y)) = (va, vb) {
            let d = y - x;
            out.samples += 1;
            sum_sq += d * d;
            if d.abs() > out.max_abs_difference {
                out.max_abs_difference = d.abs();
                t_max = Some(t);
            }
        }
    }
    if out.samples > 0 {
        out.rms_difference = (sum_sq / out.samples as f64).sqrt();
    }
    out.t_max_difference_s = t_max.map(|t: u64| format!("{:.6}", t as f64 * 1e-9));
    out
}

/// One wheel's setpoints, logged against what-if.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WheelSetpoints {
    /// `FL`, `FR`, `RL` or `RR`.
    pub wheel: &'static str,
    /// Commands in the log.
    pub logged_commands: usize,
    /// Commands the what-if core sent.
    pub what_if_commands: usize,
    /// Largest |logged setpoint|.
    pub max_abs_logged: f64,
    /// Largest |what-if setpoint|.
    pub max_abs_what_if: f64,
    /// The difference what-if − logged.
    #[serde(flatten)]
    pub difference: SeriesDiff,
}

/// One setpoint quantity of the drive commands, per wheel.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SetpointComparison {
    /// What it is: `motor current` (DJI), `motor velocity` or `torque feed-forward` (ODrive).
    pub quantity: &'static str,
    /// Its unit, as the codec gives it: `A`, `rev/s`, `Nm`.
    pub unit: &'static str,
    /// FL, FR, RL, RR.
    pub wheels: Vec<WheelSetpoints>,
}

/// A state change: the state and fault from that time on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct StateChange {
    /// Step time, s.
    pub t_s: String,
    /// `Disabled`, `Enabled`, `Fault` or `Estop`.
    pub state: String,
    /// The fault (or the last watchdog stop's reason): `None`, `MotorStale`, ...
    pub fault: String,
    #[serde(skip)]
    key: (u64, RobotState, Fault),
}

impl StateChange {
    fn new(t_ns: u64, state: RobotState, fault: Fault) -> Self {
        Self {
            t_s: format!("{:.6}", t_ns as f64 * 1e-9),
            state: state.to_string(),
            fault: fault.to_string(),
            key: (t_ns, state, fault),
        }
    }
}

impl fmt::Display for StateChange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} s {} (fault {})", self.t_s, self.state, self.fault)
    }
}

/// State changes, logged against what-if.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct StateComparison {
    /// Changes in the logged `STATUS` frames (the first frame counts as one).
    pub logged: Vec<StateChange>,
    /// Changes in the what-if core's `STATUS` frames.
    pub what_if: Vec<StateChange>,
    /// Logged changes the what-if does not have (same time, state and fault).
    pub only_logged: Vec<StateChange>,
    /// What-if changes the log does not have: e.g. a fault that occurs only in the what-if.
    pub only_what_if: Vec<StateChange>,
    /// The what-if core's own changes, at the step they happen (`STATUS` frames are sent at
    /// `timing.status_hz` only), from its initial state on.
    pub what_if_core: Vec<StateChange>,
}

/// The outcome of a what-if. Serialises to the JSON of `hostsim replay LOG --config FILE
/// --json` (which adds the file names and the verdict).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WhatIfReport {
    /// Always `true`: see [`OPEN_LOOP_NOTE`].
    pub open_loop: bool,
    /// The configuration fields the what-if changes.
    pub changes: Vec<ConfigChange>,
    /// Steps run (the logged schedule: recorded steps or the period grid).
    pub steps: u64,
    /// Inbound frames fed.
    pub fed: usize,
    /// Outbound frames in the log.
    pub logged_frames: usize,
    /// Outbound frames the what-if core sent.
    pub what_if_frames: usize,
    /// The outbound streams are equal, frame for frame and step for step.
    pub identical: bool,
    /// The first difference, if any.
    pub first_difference: Option<FirstDifference>,
    /// Per arbitration id, in id order.
    pub by_id: Vec<IdComparison>,
    /// The drive setpoints per wheel.
    pub setpoints: Vec<SetpointComparison>,
    /// State changes.
    pub states: StateComparison,
    /// What was read from the log ([`what_if_mcap`] sets it).
    #[serde(skip)]
    pub read: Option<ReadReport>,
}

/// Replays an MCAP log's inbound frames through a core built from the configuration file
/// `config` instead of the logged one, and compares its outbound frames with the logged ones
/// (see `docs/simulator.md`, section "What-if replay"). A damaged log is replayed up to its
/// cut-off, as [`crate::replay::replay_mcap`] does; [`WhatIfReport::read`] says so.
///
/// # Errors
/// [`WhatIfError`]: the log cannot be replayed, the configuration does not load or is
/// refused (naming the file and the field), or it describes other drives ([`Incompatible`]).
pub fn what_if_mcap(log: &Path, config: &Path) -> Result<WhatIfReport, WhatIfError> {
    let input = open_mcap(log)?;
    let what_if = Config::from_toml_file(config).map_err(|source| WhatIfError::Config {
        source: Box::new(source),
    })?;
    let mut report = what_if_frames(&input.config, &what_if, &input.rx, &input.tx, &input.steps)
        .map_err(|e| match e {
            WhatIfRunError::Incompatible(source) => WhatIfError::Incompatible {
                log: log.to_path_buf(),
                config: config.to_path_buf(),
                source: Box::new(source),
            },
            WhatIfRunError::Refused(source) => WhatIfError::Refused {
                path: config.to_path_buf(),
                source,
            },
            WhatIfRunError::TimeGap(source) => WhatIfError::TimeGap {
                log: log.to_path_buf(),
                source,
            },
        })?;
    report.read = Some(input.content.read);
    Ok(report)
}

/// The what-if of `what_if` against a log of `logged`: `rx` fed through a core built from
/// `what_if`, stepped at `steps` (or, if empty, on its period grid), its frames compared
/// with `tx`.
///
/// # Errors
/// [`WhatIfRunError`] if the configurations drive other motors ([`check_compatible`]), or
/// `steps` is recorded and the control rates differ, or the firmware refuses `what_if`, or
/// the frames' time line has a gap too long to replay.
pub fn what_if_frames(
    logged: &Config,
    what_if: &Config,
    rx: &[TimedFrame],
    tx: &[TimedFrame],
    steps: &[StepTime],
) -> Result<WhatIfReport, WhatIfRunError> {
    check_compatible(logged, what_if)?;
    let (hz0, hz1) = (logged.timing.control_hz, what_if.timing.control_hz);
    if !steps.is_empty() && hz0 != hz1 {
        return Err(Incompatible {
            field: "timing.control_hz",
            logged: hz0.to_string(),
            what_if: hz1.to_string(),
            why: "the log records its step times (a runner's log) and the core is stepped at \
                  them, so its period must be the logged one",
        }
        .into());
    }
    let mut ctl = Controller::new(what_if)?;
    let schedule = step_schedule(ctl.period_micros() * 1000, rx, tx, steps)?;

    let mut sent: Vec<TimedFrame> = Vec::with_capacity(tx.len());
    let mut steps_run = 0u64;
    let mut core = vec![StateChange::new(0, ctl.state(), ctl.fault())];
    let logged_id = logged.id();
    // The logged saves' ends are not given: a what-if's core need not ask for the same saves.
    let inputs = Inputs { rx, saves: &[] };
    let fed = run_schedule(&mut ctl, inputs, schedule, |step, frames, ctl| {
        sent.extend(frames.iter().map(|&frame| TimedFrame {
            t_ns: step.t_ns,
            frame: with_config_id(frame, logged_id),
        }));
        steps_run += 1;
        if core.last().map(|c| (c.key.1, c.key.2)) != Some((ctl.state(), ctl.fault())) {
            core.push(StateChange::new(step.t_ns, ctl.state(), ctl.fault()));
        }
        ControlFlow::Continue(())
    });

    // As the log's: by step time, then wire order (stable). Only a step at the time of the
    // one before it (a runner's shutdown right after its last step) is not in that order yet.
    sent.sort_by_key(|f| (f.t_ns, wire_order(&f.frame)));
    let first_difference = first_difference(tx, &sent);
    let (logged_states, what_if_states) = (status_changes(tx), status_changes(&sent));
    let only = |a: &[StateChange], b: &[StateChange]| -> Vec<StateChange> {
        a.iter()
            .filter(|c| !b.iter().any(|d| d.key == c.key))
            .cloned()
            .collect()
    };
    Ok(WhatIfReport {
        open_loop: true,
        changes: config_changes(logged, what_if),
        steps: steps_run,
        fed,
        logged_frames: tx.len(),
        what_if_frames: sent.len(),
        identical: first_difference.is_none(),
        first_difference,
        by_id: by_id(logged, tx, &sent),
        setpoints: setpoints(logged, tx, &sent),
        states: StateComparison {
            only_logged: only(&logged_states, &what_if_states),
            only_what_if: only(&what_if_states, &logged_states),
            logged: logged_states,
            what_if: what_if_states,
            what_if_core: core,
        },
        read: None,
    })
}

/// A `HEARTBEAT` with the logged configuration's id in place of the what-if's, which differs
/// by construction (the id names the configuration); any other frame as it is.
fn with_config_id(frame: CanFrame, id: u16) -> CanFrame {
    match Telemetry::decode(&frame) {
        Ok(Telemetry::Heartbeat(h)) => {
            Telemetry::Heartbeat(firmware::protocol::robot::Heartbeat { config_id: id, ..h })
                .to_can_frame()
        }
        _ => frame,
    }
}

fn first_difference(logged: &[TimedFrame], what_if: &[TimedFrame]) -> Option<FirstDifference> {
    let n = logged.len().max(what_if.len());
    (0..n).find_map(|index| {
        let (a, b) = (logged.get(index), what_if.get(index));
        (a != b).then(|| {
            let t_ns = a.into_iter().chain(b).map(|f| f.t_ns).min().unwrap_or(0);
            FirstDifference {
                index,
                t_s: format!("{:.6}", t_ns as f64 * 1e-9),
                logged: a.map(ReportFrame::new),
                what_if: b.map(ReportFrame::new),
            }
        })
    })
}

/// The arbitration id in hex: 3 digits for a standard id, 8 for an extended one.
fn id_text(frame: &CanFrame) -> String {
    use embedded_can::{Frame as _, Id};
    match frame.id() {
        Id::Standard(id) => format!("0x{:03X}", id.as_raw()),
        Id::Extended(id) => format!("0x{:08X}", id.as_raw()),
    }
}

/// The message a frame the firmware sends is, as its codec names it.
fn message_name(config: &Config, frame: &CanFrame) -> String {
    if let Ok(t) = Telemetry::decode(frame) {
        return t.def().name.to_string();
    }
    match config.drive {
        Drive::Dji { model, .. } => dji::CurrentCommand::decode(frame, model).map_or_else(
            |_| "not a firmware frame".to_string(),
            |c| c.group.def().name.to_string(),
        ),
        Drive::Odrive { .. } => odrive::Command::decode(frame).map_or_else(
            |_| "not a firmware frame".to_string(),
            |c| format!("{} node {}", c.msg.def().name, c.node.get()),
        ),
        Drive::Cia402(_) => canopen::decode(frame).map_or_else(
            |_| "not a firmware frame".to_string(),
            |m| match m.node() {
                Some(node) => format!("{} node {}", m.def().name, node.get()),
                None => m.def().name.to_string(),
            },
        ),
    }
}

/// The frames of both streams (each in `(t_ns, wire_order)` order) by arbitration id,
/// paired in one pass: in constant memory per id, whatever the log's length.
fn by_id(config: &Config, logged: &[TimedFrame], what_if: &[TimedFrame]) -> Vec<IdComparison> {
    let key = |f: &TimedFrame| (f.t_ns, wire_order(&f.frame));
    let mut ids: BTreeMap<u64, IdComparison> = BTreeMap::new();
    let (mut i, mut j) = (0, 0);
    loop {
        // The next (step time, id) in either stream, and each stream's run of frames with it.
        let next = match (logged.get(i), what_if.get(j)) {
            (Some(a), Some(b)) => key(a).min(key(b)),
            (Some(a), None) => key(a),
            (None, Some(b)) => key(b),
            (None, None) => break,
        };
        let run = |stream: &[TimedFrame], from: usize| {
            stream[from..].iter().take_while(|f| key(f) == next).count()
        };
        let (a, b) = (
            &logged[i..i + run(logged, i)],
            &what_if[j..j + run(what_if, j)],
        );
        (i, j) = (i + a.len(), j + b.len());
        let first = a.first().or(b.first()).map(|f| f.frame);
        let Some(first) = first else { break };
        let c = ids.entry(next.1).or_insert_with(|| IdComparison {
            id: id_text(&first),
            message: message_name(config, &first),
            logged: 0,
            what_if: 0,
            changed: 0,
            only_logged: 0,
            only_what_if: 0,
        });
        c.logged += a.len();
        c.what_if += b.len();
        for k in 0..a.len().max(b.len()) {
            match (a.get(k), b.get(k)) {
                (Some(x), Some(y)) if x.frame != y.frame => c.changed += 1,
                (Some(_), None) => c.only_logged += 1,
                (None, Some(_)) => c.only_what_if += 1,
                _ => {}
            }
        }
    }
    ids.into_values().collect()
}

/// The per-wheel setpoint series of one side: `[quantity][wheel]` of `(t_ns, value)`.
type Series = Vec<[Vec<(u64, f64)>; 4]>;

/// The setpoint quantities of `config`'s drive, with their units.
fn quantities(config: &Config) -> &'static [(&'static str, &'static str)] {
    match config.drive {
        Drive::Dji { .. } => &[("motor current", "A")],
        Drive::Odrive { .. } => &[("motor velocity", "rev/s"), ("torque feed-forward", "Nm")],
        Drive::Cia402(_) => &[("target velocity", "drive units")],
    }
}

/// Decodes the drive commands of `stream` into setpoint series, with the firmware's codecs.
fn setpoint_series(config: &Config, stream: &[TimedFrame]) -> Series {
    let mut out: Series = quantities(config)
        .iter()
        .map(|_| Default::default())
        .collect();
    match config.drive {
        Drive::Dji { model, esc_ids, .. } => {
            let places: [Option<dji::EscId>; 4] = esc_ids.map(dji::EscId::new);
            for f in stream {
                let Ok(c) = dji::CurrentCommand::decode(&f.frame, model) else {
                    continue;
                };
                let amps = c.amps();
                for (wheel, esc) in places.iter().enumerate() {
                    if let Some(esc) = esc
                        && esc.group() == c.group
                    {
                        out[0][wheel].push((f.t_ns, f64::from(amps[esc.slot()])));
                    }
                }
            }
        }
        Drive::Odrive { node_ids, .. } => {
            for f in stream {
                let Ok(odrive::Addressed {
                    node,
                    msg: odrive::Command::SetInputVel { vel, torque_ff },
                }) = odrive::Command::decode(&f.frame)
                else {
                    continue;
                };
                if let Some(wheel) = node_ids.iter().position(|&n| n == node.get()) {
                    out[0][wheel].push((f.t_ns, f64::from(vel)));
                    out[1][wheel].push((f.t_ns, f64::from(torque_ff)));
                }
            }
        }
        Drive::Cia402(Cia402Drive { node_ids, axes, .. }) => {
            for f in stream {
                // RPDO1 carries axis 0 or 1, RPDO3 axis 2.
                let (node, second, target) = match canopen::decode(&f.frame) {
                    Ok(canopen::Message::Rpdo1 { node, target, .. }) => (node, false, target),
                    Ok(canopen::Message::Rpdo3 { node, target }) => (node, true, target),
                    _ => continue,
                };
                for (wheel, (&n, &axis)) in node_ids.iter().zip(&axes).enumerate() {
                    if n == node.get() && (axis == 2) == second {
                        out[0][wheel].push((f.t_ns, f64::from(target)));
                    }
                }
            }
        }
    }
    out
}

fn setpoints(
    config: &Config,
    logged: &[TimedFrame],
    what_if: &[TimedFrame],
) -> Vec<SetpointComparison> {
    let (a, b) = (
        setpoint_series(config, logged),
        setpoint_series(config, what_if),
    );
    let max_abs = |s: &[(u64, f64)]| s.iter().fold(0.0f64, |m, &(_, v)| m.max(v.abs()));
    quantities(config)
        .iter()
        .zip(a.iter().zip(&b))
        .map(|(&(quantity, unit), (a, b))| SetpointComparison {
            quantity,
            unit,
            wheels: (0..4)
                .map(|w| WheelSetpoints {
                    wheel: WHEELS[w],
                    logged_commands: a[w].len(),
                    what_if_commands: b[w].len(),
                    max_abs_logged: max_abs(&a[w]),
                    max_abs_what_if: max_abs(&b[w]),
                    difference: compare_series(&a[w], &b[w]),
                })
                .collect(),
        })
        .collect()
}

/// The changes of (state, fault) in a stream's `STATUS` frames; the first one counts.
fn status_changes(stream: &[TimedFrame]) -> Vec<StateChange> {
    let mut out: Vec<StateChange> = Vec::new();
    for f in stream {
        if let Ok(Telemetry::Status(s)) = Telemetry::decode(&f.frame)
            && out.last().map(|c| (c.key.1, c.key.2)) != Some((s.state, s.fault))
        {
            out.push(StateChange::new(f.t_ns, s.state, s.fault));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn series_are_held_between_commands_and_compared_where_either_changes() {
        // a: 1 from 0 ms, 2 from 10 ms; b: 4 from 5 ms. At 0 only a has a value (no
        // sample); at 5 ms: 4 - 1 = 3; at 10 ms: 4 - 2 = 2.
        let d = compare_series(&[(0, 1.0), (10_000_000, 2.0)], &[(5_000_000, 4.0)]);
        assert_eq!(d.samples, 2);
        assert_eq!(d.max_abs_difference, 3.0);
        assert_eq!(d.t_max_difference_s.as_deref(), Some("0.005000"));
        assert_eq!(d.rms_difference, (13.0f64 / 2.0).sqrt());
        // Two values at one time: the last one holds. The first time of the largest
        // difference is kept.
        let d = compare_series(
            &[(1_000_000, 0.0), (2_000_000, 5.0), (2_000_000, 1.0)],
            &[(1_000_000, -1.0), (3_000_000, 2.0)],
        );
        assert_eq!(d.samples, 3);
        assert_eq!(d.max_abs_difference, 2.0);
        assert_eq!(d.t_max_difference_s.as_deref(), Some("0.002000"));
        // Equal series, and empty ones: no difference, no time.
        let same = compare_series(&[(0, 3.0), (7, -3.0)], &[(0, 3.0), (7, -3.0)]);
        assert_eq!((same.samples, same.max_abs_difference), (2, 0.0));
        assert_eq!((same.t_max_difference_s, same.rms_difference), (None, 0.0));
        assert_eq!(compare_series(&[], &[(0, 1.0)]).samples, 0);
    }

    #[test]
    fn only_the_fields_that_differ_are_changes() {
        let a = Config::dji_m3508_example();
        assert!(config_changes(&a, &a).is_empty());
        let mut b = a;
        b.gains.ki = 45.5;
        b.limits.max_current = 8.0;
        let fields: Vec<_> = config_changes(&a, &b)
            .into_iter()
            .map(|c| (c.field, c.logged, c.what_if))
            .collect();
        let s = |v: &str| Some(v.to_string());
        assert_eq!(
            fields,
            [
                ("gains.ki".to_string(), s("30.0"), s("45.5")),
                ("limits.max_current".to_string(), s("16.0"), s("8.0")),
            ]
        );
    }
}
