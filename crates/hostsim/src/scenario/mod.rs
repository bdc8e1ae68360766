//! Scenarios: the data of a run (configuration, timed actions, faults, nodes' parameters).
//!
//! What the host does and what goes wrong, on a timeline.
//!
//! A scenario is a list of timed host [`Action`]s (enable, twist setpoints, e-stop, silence)
//! and timed [`FaultSpec`]s (bus faults, a stuck encoder, a motor offline, a host sending
//! non-finite twists or repeating one twist frame), plus the drive configuration, the
//! simulated robot where it differs from it ([`PlantSpec`]), an optional IMU, optional
//! tracking pods (`[pods]`, [`crate::nodes::pods`]) and a seed.
//! While a twist setpoint is active and the host is not silent, the host streams `TWIST_CMD`
//! frames at `command_hz`, as a teleoperation or navigation stack would.
//!
//! Scenarios are written in TOML (the format, with an example a test runs as written:
//! `docs/scenarios.md`) or taken from the built-ins ([`Scenario::builtin`]).

mod actions;
mod builtin;
mod faults;
mod set;
#[cfg(test)]
mod tests;

use std::path::{Path, PathBuf};

use firmware::Config;
use firmware::input::{TomlError, quote};
use serde::Deserialize;

pub use self::actions::{Action, ParamName, ParamSet, StoreCommand, WheelTestSpec};
pub use self::faults::{FaultName, FaultSpec, NodeFault, SenderName, WheelFault};
pub use self::set::{PLANT_FIELDS, SetError};
use crate::bus::Fault;
use crate::nodes::host::HostFault;
use crate::nodes::plant::PlantSpec;

/// A complete scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    /// Name, for logs and reports.
    pub name: String,
    /// Simulated duration, s.
    pub duration_s: f64,
    /// Seed of every random choice (bus faults).
    pub seed: u64,
    /// Rate of streamed twist commands, Hz.
    pub command_hz: f64,
    /// The drive configuration the firmware and the plant use.
    pub config: Config,
    /// Host actions, sorted by time.
    pub actions: Vec<Action>,
    /// Bus faults.
    pub bus_faults: Vec<Fault>,
    /// Plant faults.
    pub wheel_faults: Vec<WheelFault>,
    /// Host faults.
    pub host_faults: Vec<HostFault>,
    /// The robot where it differs from the configuration (empty: as configured).
    pub plant: PlantSpec,
    /// The IMU node on the plant (`[imu]`), if any.
    pub imu: Option<crate::nodes::imu::ImuParams>,
    /// The tracking-pod node on the plant (`[pods]`), if any: the configuration's pods
    /// (`[[odometry.pods]]`) as they truly are ([`crate::nodes::pods`]).
    pub pods: Option<crate::nodes::pods::PodsParams>,
    /// Faults of the sensor nodes (`pods_silent`).
    pub node_faults: Vec<NodeFault>,
}

/// Why a scenario could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// The file could not be read.
    #[error("cannot read scenario {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// Malformed TOML, unknown field or wrong type. (Not the error's `source`: the parser's
    /// text quotes the file's line raw, and the message shows it quoted.)
    #[error("scenario {path}: {parse}")]
    Toml {
        /// The file.
        path: PathBuf,
        /// Parser error with line and column, and the key it points at.
        parse: Box<TomlError>,
    },
    /// The drive configuration it names is not usable.
    #[error("scenario {path}: {source}")]
    Config {
        /// The scenario file.
        path: PathBuf,
        /// The configuration error.
        source: Box<firmware::config::LoadError>,
    },
    /// A value is out of range.
    #[error("scenario {path}: {field} = {}: {expected}", quote(value))]
    Invalid {
        /// The scenario file.
        path: PathBuf,
        /// Which field.
        field: String,
        /// The value.
        value: String,
        /// What is expected.
        expected: &'static str,
    },
    /// A fault sets a field its kind does not use.
    #[error("scenario {path}: {field} = {}: not used by a \"{kind}\" fault (it takes {uses})", quote(value), kind = kind.as_str())]
    UnusedField {
        /// The scenario file.
        path: PathBuf,
        /// Which field.
        field: String,
        /// The value.
        value: String,
        /// The fault's kind.
        kind: FaultName,
        /// The fields that kind takes, besides `from_s` and `until_s`.
        uses: &'static str,
    },
    /// No built-in of that name.
    #[error("no built-in scenario \"{}\"; built-ins: {names}", quote(.0), names = Scenario::BUILTINS.join(", "))]
    UnknownBuiltin(String),
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioFile {
    name: Option<String>,
    duration_s: f64,
    #[serde(default)]
    seed: u64,
    #[serde(default = "default_command_hz")]
    command_hz: f64,
    config: Option<PathBuf>,
    #[serde(default)]
    actions: Vec<Action>,
    #[serde(default)]
    faults: Vec<FaultSpec>,
    #[serde(default)]
    plant: PlantSpec,
    imu: Option<crate::nodes::imu::ImuParams>,
    pods: Option<crate::nodes::pods::PodsParams>,
}

/// The host's command rates a scenario may ask for, Hz: a command period from 1 ms (the
/// control step) to 100 s.
pub const COMMAND_HZ: std::ops::RangeInclusive<f64> = 0.01..=1000.0;

const fn default_command_hz() -> f64 {
    50.0
}

fn secs_to_us(s: f64) -> u64 {
    (s * 1e6).round().max(0.0) as u64
}

/// The scenario file whose values are checked, for [`ScenarioError::Invalid`].
struct Invalid<'a> {
    path: &'a Path,
}

impl Invalid<'_> {
    /// `field = value` is not `expected`.
    fn at(&self, field: &str, value: String, expected: &'static str) -> ScenarioError {
        ScenarioError::Invalid {
            path: self.path.to_path_buf(),
            field: field.to_string(),
            value,
            expected,
        }
    }
}

impl Scenario {
    /// Names of the built-in scenarios.
    pub const BUILTINS: [&'static str; 8] = [
        "square",
        "circle",
        "strafe",
        "spin",
        "figure-eight",
        "compass",
        "watchdog",
        "calibration",
    ];

    /// Loads a scenario file; a relative `config` path is taken from the file's folder.
    ///
    /// # Errors
    /// [`ScenarioError`] naming the file and what is wrong.
    pub fn from_file(path: &Path) -> Result<Self, ScenarioError> {
        Self::from_file_with_config(path, None)
    }

    /// A scenario file (a `.toml` path, or any existing file), else the built-in of that name
    /// ([`Self::builtin`]); `config`, if given, replaces its configuration (`run --config`).
    /// A folder of a built-in's name (an earlier `--out square`) does not hide the built-in.
    ///
    /// # Errors
    /// [`ScenarioError`]: the file's, or no built-in of that name.
    pub fn load(arg: &str, config: Option<Config>) -> Result<Self, ScenarioError> {
        let path = Path::new(arg);
        // A file by its extension, by being there (a device, a folder: its read says what is
        // wrong), or by its path separator; else the name of a built-in.
        if path.extension().is_some_and(|e| e == "toml") || path.exists() || arg.contains('/') {
            return Self::from_file_with_config(path, config);
        }
        let mut scenario = Self::builtin(arg)?;
        if let Some(config) = config {
            scenario.config = config;
        }
        Ok(scenario)
    }

    /// [`Self::from_file`], with `config` (if given) in place of the file's `config`, which
    /// is then not read at all (`hostsim run --config`).
    ///
    /// # Errors
    /// [`ScenarioError`] naming the file and what is wrong.
    pub fn from_file_with_config(
        path: &Path,
        config: Option<Config>,
    ) -> Result<Self, ScenarioError> {
        let text = firmware::input::read_toml_text(path).map_err(|source| ScenarioError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml_with_config(&text, path, config)
    }

    /// Parses a scenario; `path` names it in errors and anchors a relative `config`.
    ///
    /// # Errors
    /// [`ScenarioError`] naming the field and the value.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, ScenarioError> {
        Self::from_toml_with_config(text, path, None)
    }

    /// Simulated duration, µs.
    #[must_use]
    pub fn duration_us(&self) -> u64 {
        secs_to_us(self.duration_s)
    }

    /// Action times in µs, in order, with the action.
    pub fn timed_actions(&self) -> impl Iterator<Item = (u64, &Action)> {
        self.actions.iter().map(|a| (secs_to_us(a.at_s), a))
    }

    /// [`Self::from_toml`], with `config` (if given) in place of the text's `config`.
    ///
    /// # Errors
    /// [`ScenarioError`] naming the field and the value.
    pub fn from_toml_with_config(
        text: &str,
        path: &Path,
        config: Option<Config>,
    ) -> Result<Self, ScenarioError> {
        let file: ScenarioFile = toml::from_str(text).map_err(|parse| ScenarioError::Toml {
            path: path.to_path_buf(),
            parse: Box::new(TomlError::new(text, parse)),
        })?;
        let invalid = Invalid { path };
        if !(file.duration_s.is_finite() && file.duration_s > 0.0 && file.duration_s <= 86_400.0) {
            return Err(invalid.at(
                "duration_s",
                file.duration_s.to_string(),
                "a duration in (0, 86400] s",
            ));
        }
        if let Some(name) = &file.name
            && name.trim().is_empty()
        {
            return Err(invalid.at(
                "name",
                format!("{name:?}"),
                "a name (it names the log and the plot), or no `name` for the file's stem",
            ));
        }
        // Checked as the host uses it, a period in microseconds: 1e-300 Hz passed `> 0` and
        // made a period past u64, which wrapped the host's command clock (a run without end).
        if !(COMMAND_HZ.contains(&file.command_hz)) {
            return Err(invalid.at(
                "command_hz",
                format!("{:?}", file.command_hz), // 1e-300, not 300 digits
                "a rate in [0.01, 1000] Hz (a command every 1 ms to 100 s)",
            ));
        }
        let config = match (config, &file.config) {
            (Some(config), _) => config,
            (None, None) => Config::dji_m3508_example(),
            (None, Some(p)) => {
                let p = path.parent().unwrap_or(Path::new(".")).join(p);
                Config::from_toml_file(&p).map_err(|source| ScenarioError::Config {
                    path: path.to_path_buf(),
                    source: Box::new(source),
                })?
            }
        };
        actions::check(&file.actions, file.duration_s, &invalid)?;
        if let Some((key, value, expected)) = file.imu.as_ref().and_then(|i| i.invalid()) {
            return Err(invalid.at(&format!("imu.{key}"), value.to_string(), expected));
        }
        let (bus_faults, wheel_faults, host_faults, node_faults) =
            faults::build(&file.faults, file.duration_s, &invalid)?;
        check_pods(file.pods.as_ref(), &config, &file.faults, &invalid)?;
        if !matches!(config.drive, firmware::config::Drive::Cia402(_))
            && let Some((i, f)) = file
                .faults
                .iter()
                .enumerate()
                .find(|(_, f)| f.kind.cia402_only())
        {
            return Err(invalid.at(
                &format!("faults[{i}].kind"),
                format!("{:?}", f.kind.as_str()),
                "a fault of this configuration's drives (stuck_encoder, motor_offline): \
                 drive_silent, drive_reboot, drive_fault, enable_refused, sdo_abort and \
                 drive_bus_off act on CANopen nodes, a protocol = \"cia402\" configuration",
            ));
        }
        if let Some((field, value, expected)) = file.plant.first_invalid() {
            return Err(invalid.at(field, value.to_string(), expected));
        }
        let mut actions = file.actions;
        actions.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
        Ok(Self {
            name: file.name.unwrap_or_else(|| {
                path.file_stem()
                    .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
            }),
            duration_s: file.duration_s,
            seed: file.seed,
            command_hz: file.command_hz,
            config,
            actions,
            bus_faults,
            wheel_faults,
            host_faults,
            plant: file.plant,
            imu: file.imu,
            pods: file.pods,
            node_faults,
        })
    }
}

/// `[pods]` against the configuration's pods, and the `pods_silent` faults against `[pods]`.
fn check_pods(
    pods: Option<&crate::nodes::pods::PodsParams>,
    config: &Config,
    faults: &[FaultSpec],
    invalid: &Invalid<'_>,
) -> Result<(), ScenarioError> {
    let configured = config.odometry.pods.len();
    let Some(pods) = pods else {
        if let Some(i) = faults.iter().position(|f| f.kind == FaultName::PodsSilent) {
            return Err(invalid.at(
                &format!("faults[{i}].kind"),
                "\"pods_silent\"".to_owned(),
                "a fault of the pod node, which needs a [pods] table",
            ));
        }
        return Ok(());
    };
    if let Some((key, value, expected)) = pods.invalid() {
        return Err(invalid.at(&format!("pods.{key}"), value.to_string(), expected));
    }
    if configured == 0 {
        return Err(invalid.at(
            "pods",
            "(a table)".to_owned(),
            "a configuration with [[odometry.pods]]: the simulated pods are the configured \
             ones (place, direction, radius, counts per turn), made true by [[pods.pod]]",
        ));
    }
    if pods.pod.len() > configured {
        return Err(invalid.at(
            "pods.pod",
            format!("{} tables for {configured} configured pods", pods.pod.len()),
            "at most one [[pods.pod]] per pod of [[odometry.pods]], in its order",
        ));
    }
    Ok(())
}

/// A field's value for an error message: as written, or `(missing)`.
fn given<T: std::fmt::Display>(value: Option<T>) -> String {
    value.map_or_else(|| "(missing)".to_owned(), |v| v.to_string())
}
