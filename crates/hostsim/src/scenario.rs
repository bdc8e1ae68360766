//! Scenarios: what the host does and what goes wrong, on a timeline.
//!
//! A scenario is a list of timed host [`Action`]s (enable, twist setpoints, e-stop, silence)
//! and timed [`FaultSpec`]s (bus faults, a stuck encoder, a motor offline, a host sending
//! non-finite twists or repeating one twist frame), plus the drive
//! configuration and a seed. While a twist setpoint is active and the host is not silent,
//! the host streams `TWIST_CMD` frames at `command_hz`, as a teleoperation or navigation
//! stack would.
//!
//! Scenarios are written in TOML or taken from the built-ins ([`Scenario::builtin`]). This
//! one drives forward, loses a fifth of the host's frames for half a second (the watchdog
//! rides it out), then goes silent, and the watchdog stops the robot (a test runs it as
//! written):
//!
//! ```toml
//! name = "forward and stop"
//! duration_s = 4.0
//! seed = 1
//! command_hz = 50.0
//! config = "config/dji_m3508.toml"   # optional, relative to the scenario file
//!
//! [[actions]]
//! at_s = 0.05
//! enable = true
//!
//! [[actions]]
//! at_s = 0.1
//! twist = [0.5, 0.0, 0.0]   # vx m/s, vy m/s, wz rad/s (body frame)
//!
//! [[actions]]
//! at_s = 2.0
//! silence = true            # the host stops sending: the watchdog must stop the robot
//!
//! [[faults]]
//! kind = "drop"             # drop | burst | delay | corrupt | stuck_encoder | motor_offline
//!                           # | non_finite_twist | repeated_twist
//! from_s = 1.0
//! until_s = 1.5
//! rate = 0.2                # drop, corrupt
//! sender = "host"           # optional: controller | drives | host | imu
//! ```
//!
//! The simulated robot is the one the drive configuration describes, unless the scenario
//! says otherwise in a `[plant]` table ([`PlantSpec`]): a real robot's wheels are not quite
//! the configured size, and its rollers slip. Each key is optional; `hostsim run --config`
//! then changes only what the firmware believes, not the robot:
//!
//! ```toml
//! [plant]
//! wheel_radius = 0.07752    # m, true wheel radius
//! lx = 0.194                # m, true centre-to-wheel distances (standard layout only)
//! ly = 0.1746
//! roller_drag = 0.17647     # ε in [0, 1): a pure strafe makes (1 − ε)/(1 + ε) of the command
//! mass_kg = 22.0            # true mass
//! flip = [1]                # wheels (0 FL, 1 FR, 2 RL, 3 RR) whose motor is mounted the other way
//! swap = [[0, 2]]           # pairs of wheels whose drives answer to each other's ids
//! lifted = false            # true: on blocks, no wheel touches the ground
//! ```
//!
//! `flip` and `swap` build a miswired robot (the firmware still believes its configuration);
//! an action `wheel_test = { wheel = 0, speed = 3.0, duration_ms = 1000 }` sends the
//! bring-up check's `WHEEL_TEST` ([`crate::bringup`]).
//!
//! An optional `[imu]` table puts an IMU node on the bus that sends the robot protocol's
//! `IMU_YAW_RATE` from the plant's true yaw rate (see [`crate::imu`]; a configuration with
//! `[odometry] heading_source = "gyro"` uses it). Without the table there is none:
//!
//! ```toml
//! [imu]
//! rate_hz = 200.0           # default 200
//! bias_deg_s = 0.1          # default 0.1, constant
//! noise_density = 0.005     # °/s/√Hz, white rate noise; default 0.005
//! enabled = true            # default true
//! ```
//!
//! A `burst` fault with `sender = "imu"` silences it.

use std::path::{Path, PathBuf};

use firmware::Config;
use serde::Deserialize;

use crate::bus::{Fault, FaultKind, Node};
use crate::plant::{ChassisParams, ParamError};

/// What the host does at a moment.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Action {
    /// When, s of simulated time.
    pub at_s: f64,
    /// Send `MODE_CMD enable`.
    #[serde(default)]
    pub enable: bool,
    /// Send `MODE_CMD disable`.
    #[serde(default)]
    pub disable: bool,
    /// Send `MODE_CMD reset`.
    #[serde(default)]
    pub reset: bool,
    /// Send `ESTOP`.
    #[serde(default)]
    pub estop: bool,
    /// Send a `STATUS_REQ`.
    #[serde(default)]
    pub status_request: bool,
    /// New twist setpoint `[vx, vy, wz]` (m/s, m/s, rad/s), streamed from now on.
    #[serde(default)]
    pub twist: Option<[f32; 3]>,
    /// Stop streaming twist commands (the setpoint is kept for a later `resume`).
    #[serde(default)]
    pub silence: bool,
    /// Resume streaming.
    #[serde(default)]
    pub resume: bool,
    /// Send a `WHEEL_TEST` (the bring-up check; a disabled robot runs it).
    #[serde(default)]
    pub wheel_test: Option<WheelTestSpec>,
}

/// A `WHEEL_TEST` as a scenario writes it: `wheel_test = { wheel = 0, speed = 3.0,
/// duration_ms = 1000 }`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WheelTestSpec {
    /// The wheel, 0..=3 (FL, FR, RL, RR).
    pub wheel: u8,
    /// Wheel speed setpoint, rad/s, robot-forward positive, `|speed| <= 10`.
    pub speed: f32,
    /// How long, ms, 1..=3000.
    pub duration_ms: u16,
}

impl Action {
    /// An action at `at_s` that does nothing yet; set one field.
    #[must_use]
    pub const fn at(at_s: f64) -> Self {
        Self {
            at_s,
            enable: false,
            disable: false,
            reset: false,
            estop: false,
            status_request: false,
            twist: None,
            silence: false,
            resume: false,
            wheel_test: None,
        }
    }

    /// A twist setpoint at `at_s`.
    #[must_use]
    pub const fn twist(at_s: f64, vx: f32, vy: f32, wz: f32) -> Self {
        let mut a = Self::at(at_s);
        a.twist = Some([vx, vy, wz]);
        a
    }
}

/// A fault on the timeline, as written in a scenario.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultSpec {
    /// `drop`, `burst`, `delay`, `corrupt`, `stuck_encoder`, `motor_offline`,
    /// `non_finite_twist` or `repeated_twist`.
    pub kind: FaultName,
    /// Start, s.
    pub from_s: f64,
    /// End, s (exclusive).
    pub until_s: f64,
    /// Probability for `drop` and `corrupt`.
    #[serde(default)]
    pub rate: Option<f64>,
    /// Extra latency for `delay`, ms.
    #[serde(default)]
    pub delay_ms: Option<f64>,
    /// Sender the bus fault applies to (all if absent).
    #[serde(default)]
    pub sender: Option<SenderName>,
    /// Wheel (0 FL, 1 FR, 2 RL, 3 RR) for `stuck_encoder` and `motor_offline`.
    #[serde(default)]
    pub wheel: Option<usize>,
}

/// Fault kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultName {
    /// Random frame loss.
    Drop,
    /// Total frame loss.
    Burst,
    /// Extra delivery latency.
    Delay,
    /// A flipped data byte.
    Corrupt,
    /// A wheel's encoder stops changing while the wheel turns.
    StuckEncoder,
    /// A drive is off: it sends nothing and drives nothing (the wheel coasts).
    MotorOffline,
    /// Besides its own stream, the host sends `TWIST_CMD` frames whose values are not finite
    /// numbers (see [`crate::host::non_finite_twist_frames`]), once per command period.
    NonFiniteTwist,
    /// The host's stream stops incrementing `TWIST_CMD.seq`: each frame it sends is its last
    /// one before the fault, unchanged (a stuck host, USB adapter or gateway repeating one
    /// frame), whatever its setpoint; afterwards it sends fresh frames again.
    RepeatedTwist,
}

impl FaultName {
    /// The name a scenario file uses (`stuck_encoder`).
    #[must_use]
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Drop => "drop",
            Self::Burst => "burst",
            Self::Delay => "delay",
            Self::Corrupt => "corrupt",
            Self::StuckEncoder => "stuck_encoder",
            Self::MotorOffline => "motor_offline",
            Self::NonFiniteTwist => "non_finite_twist",
            Self::RepeatedTwist => "repeated_twist",
        }
    }
}

/// Bus nodes as named in scenarios.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SenderName {
    /// The firmware core.
    Controller,
    /// The motor drives.
    Drives,
    /// The commanding host.
    Host,
    /// The IMU node (`[imu]`).
    Imu,
}

impl From<SenderName> for Node {
    fn from(s: SenderName) -> Self {
        match s {
            SenderName::Controller => Self::Controller,
            SenderName::Drives => Self::Drives,
            SenderName::Host => Self::Host,
            SenderName::Imu => Self::Imu,
        }
    }
}

/// A plant-side fault: which wheel, when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelFault {
    /// Stuck encoder or offline.
    pub kind: FaultName,
    /// Wheel index.
    pub wheel: usize,
    /// Start, µs.
    pub from_us: u64,
    /// End, µs.
    pub until_us: u64,
}

impl WheelFault {
    /// Whether the fault is active at `t_us`.
    #[must_use]
    pub const fn active(&self, t_us: u64) -> bool {
        self.from_us <= t_us && t_us < self.until_us
    }
}

/// A host-side fault: what the commanding node sends wrong, when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HostFault {
    /// What it sends (`NonFiniteTwist`, `RepeatedTwist`).
    pub kind: FaultName,
    /// Start, µs.
    pub from_us: u64,
    /// End, µs.
    pub until_us: u64,
}

impl HostFault {
    /// Whether the fault is active at `t_us`.
    #[must_use]
    pub const fn active(&self, t_us: u64) -> bool {
        self.from_us <= t_us && t_us < self.until_us
    }
}

/// The simulated robot where it differs from the drive configuration (a scenario's `[plant]`
/// table): its true wheel radius, wheel positions and roller drag. `None` keeps the value the
/// configuration (geometry) or the plant's defaults (roller drag, [`ChassisParams`]) give.
#[derive(Debug, Clone, PartialEq, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct PlantSpec {
    /// True wheel radius, m, in `(0, 1]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wheel_radius: Option<f64>,
    /// True distance from the centre to the wheels along x, m, in `(0, 5]` (standard layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lx: Option<f64>,
    /// True distance from the centre to the wheels along y, m, in `(0, 5]` (standard layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ly: Option<f64>,
    /// Roller drag `ε` ([`ChassisParams::roller_drag`]) in `[0, 1)`: a pure strafe settles at
    /// `(1 − ε)/(1 + ε)` of the command (default 1/7: 75 %).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roller_drag: Option<f64>,
    /// True mass of the robot, kg, in `(0, 1000]`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mass_kg: Option<f64>,
    /// Wheels (indices 0..=3: FL, FR, RL, RR) whose motor is mounted the other way than the
    /// configuration's `drive.inverted` says: a miswired robot.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub flip: Vec<usize>,
    /// Pairs of wheels whose drives answer to each other's ids (`drive.esc_ids` or
    /// `drive.node_ids`): drives wired to the wrong wheels. Applied in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub swap: Vec<[usize; 2]>,
    /// The robot on blocks, wheels off the ground (the bring-up check): no wheel touches the
    /// ground, the body stays where it is.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub lifted: bool,
}

impl PlantSpec {
    /// `true` if it changes nothing.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// The robot of the DJI example configuration, every value given: lx 0.20 m, ly 0.18 m,
    /// wheel radius 0.076 m (as the configuration's `f32` values), roller drag 1/7 (the
    /// built-in `calibration` scenario's, so that `--config` changes only what the firmware
    /// believes).
    #[must_use]
    pub fn dji_m3508_example() -> Self {
        let c = ChassisParams::from_config(&Config::dji_m3508_example());
        let w = c.wheels[0];
        Self {
            wheel_radius: Some(w.radius),
            lx: Some(w.x),
            ly: Some(w.y),
            roller_drag: Some(c.roller_drag),
            ..Self::default()
        }
    }

    /// The first value out of its range: its field as a scenario file names it, the value and
    /// what is expected.
    #[must_use]
    pub fn first_invalid(&self) -> Option<(&'static str, f64, &'static str)> {
        let length = |v: f64, max: f64| v > 0.0 && v <= max;
        [
            (
                "plant.wheel_radius",
                self.wheel_radius,
                length(self.wheel_radius.unwrap_or(1.0), 1.0),
                "a radius in (0, 1] m",
            ),
            (
                "plant.lx",
                self.lx,
                length(self.lx.unwrap_or(1.0), 5.0),
                "a distance in (0, 5] m",
            ),
            (
                "plant.ly",
                self.ly,
                length(self.ly.unwrap_or(1.0), 5.0),
                "a distance in (0, 5] m",
            ),
            (
                "plant.roller_drag",
                self.roller_drag,
                (0.0..1.0).contains(&self.roller_drag.unwrap_or(0.0)),
                "a roller drag in [0, 1)",
            ),
            (
                "plant.mass_kg",
                self.mass_kg,
                length(self.mass_kg.unwrap_or(1.0), 1000.0),
                "a mass in (0, 1000] kg",
            ),
        ]
        .into_iter()
        .find_map(|(field, value, ok, expected)| Some((field, value?, expected)).filter(|_| !ok))
        .or_else(|| self.invalid_wiring())
    }

    /// The first wiring entry that is not acceptable, as [`Self::first_invalid`] names it.
    #[allow(clippy::cast_precision_loss)] // wheel indices
    fn invalid_wiring(&self) -> Option<(&'static str, f64, &'static str)> {
        const WHEEL: &str = "a wheel index 0..=3 (FL, FR, RL, RR)";
        for (k, &w) in self.flip.iter().enumerate() {
            if w > 3 {
                return Some(("plant.flip", w as f64, WHEEL));
            }
            if self.flip[..k].contains(&w) {
                return Some(("plant.flip", w as f64, "each wheel at most once"));
            }
        }
        for &[a, b] in &self.swap {
            if let Some(w) = [a, b].into_iter().find(|&w| w > 3) {
                return Some(("plant.swap", w as f64, WHEEL));
            }
            if a == b {
                return Some(("plant.swap", a as f64, "two different wheels"));
            }
        }
        None
    }

    /// The drive ids of the plant's wheels (its ESC or node id per wheel), given the
    /// configured ones: `configured` with [`Self::swap`] applied.
    #[must_use]
    pub fn wired_ids<T: Copy>(&self, configured: [T; 4]) -> [T; 4] {
        let mut ids = configured;
        for &[a, b] in &self.swap {
            if a < 4 && b < 4 {
                ids.swap(a, b);
            }
        }
        ids
    }

    /// How the plant's motors are mounted, given the configured `drive.inverted`: with
    /// [`Self::flip`] applied.
    #[must_use]
    pub fn wired_inverted(&self, configured: [bool; 4]) -> [bool; 4] {
        let mut inverted = configured;
        for &w in &self.flip {
            if let Some(i) = inverted.get_mut(w) {
                *i = !*i;
            }
        }
        inverted
    }

    /// Applies the values to a chassis built from a configuration.
    ///
    /// # Errors
    /// [`ParamError`] naming a value out of its range ([`Self::first_invalid`]), or `plant.lx`
    /// or `plant.ly` if the chassis is not the standard layout (wheels at `(±lx, ±ly)`).
    pub fn apply(&self, chassis: &mut ChassisParams) -> Result<(), ParamError> {
        if let Some((field, value, expected)) = self.first_invalid() {
            return Err(ParamError::new(field, value, expected));
        }
        let standard = {
            let w = &chassis.wheels;
            w.iter()
                .all(|g| g.x.abs() == w[0].x.abs() && g.y.abs() == w[0].y.abs())
        };
        for (field, value) in [("plant.lx", self.lx), ("plant.ly", self.ly)] {
            if let (Some(v), false) = (value, standard) {
                return Err(ParamError::new(
                    field,
                    v,
                    "a configuration with the standard layout (wheels at ±lx, ±ly)",
                ));
            }
        }
        for w in &mut chassis.wheels {
            if let Some(r) = self.wheel_radius {
                w.radius = r;
            }
            if let Some(lx) = self.lx {
                w.x = lx.copysign(w.x);
            }
            if let Some(ly) = self.ly {
                w.y = ly.copysign(w.y);
            }
        }
        if let Some(eps) = self.roller_drag {
            chassis.roller_drag = eps;
        }
        if let Some(m) = self.mass_kg {
            chassis.mass = m;
        }
        Ok(())
    }
}

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
    pub imu: Option<crate::imu::ImuParams>,
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
    /// Malformed TOML, unknown field or wrong type.
    #[error("scenario {path}: {source}")]
    Toml {
        /// The file.
        path: PathBuf,
        /// Parser error with line and column.
        source: toml::de::Error,
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
    #[error("scenario {path}: {field} = {value}: {expected}")]
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
    #[error("scenario {path}: {field} = {value}: not used by a \"{kind}\" fault (it takes {uses})", kind = kind.as_str())]
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
    #[error("no built-in scenario {0:?}; built-ins: {names}", names = Scenario::BUILTINS.join(", "))]
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
    imu: Option<crate::imu::ImuParams>,
}

const fn default_command_hz() -> f64 {
    50.0
}

fn secs_to_us(s: f64) -> u64 {
    (s * 1e6).round().max(0.0) as u64
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
        if path.extension().is_some_and(|e| e == "toml") || path.is_file() {
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
        let text = std::fs::read_to_string(path).map_err(|source| ScenarioError::Io {
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

    /// [`Self::from_toml`], with `config` (if given) in place of the text's `config`.
    ///
    /// # Errors
    /// [`ScenarioError`] naming the field and the value.
    pub fn from_toml_with_config(
        text: &str,
        path: &Path,
        config: Option<Config>,
    ) -> Result<Self, ScenarioError> {
        let file: ScenarioFile = toml::from_str(text).map_err(|source| ScenarioError::Toml {
            path: path.to_path_buf(),
            source,
        })?;
        let invalid = |field: &str, value: String, expected| ScenarioError::Invalid {
            path: path.to_path_buf(),
            field: field.to_string(),
            value,
            expected,
        };
        if !(file.duration_s.is_finite() && file.duration_s > 0.0 && file.duration_s <= 86_400.0) {
            return Err(invalid(
                "duration_s",
                file.duration_s.to_string(),
                "a duration in (0, 86400] s",
            ));
        }
        if let Some(name) = &file.name
            && name.trim().is_empty()
        {
            return Err(invalid(
                "name",
                format!("{name:?}"),
                "a name (it names the log and the plot), or no `name` for the file's stem",
            ));
        }
        if !(file.command_hz.is_finite() && file.command_hz > 0.0 && file.command_hz <= 1000.0) {
            return Err(invalid(
                "command_hz",
                file.command_hz.to_string(),
                "a rate in (0, 1000] Hz",
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
        for (i, a) in file.actions.iter().enumerate() {
            if !(a.at_s.is_finite() && a.at_s >= 0.0) {
                return Err(invalid(
                    &format!("actions[{i}].at_s"),
                    a.at_s.to_string(),
                    "a time >= 0 s",
                ));
            }
            if a.at_s >= file.duration_s {
                return Err(invalid(
                    &format!("actions[{i}].at_s"),
                    a.at_s.to_string(),
                    "a time before duration_s (a later action would never happen)",
                ));
            }
            let does = |set: bool, what: &'static str| set.then_some(what);
            let commands: Vec<&str> = [
                does(a.enable, "enable"),
                does(a.disable, "disable"),
                does(a.reset, "reset"),
                does(a.estop, "estop"),
                does(a.status_request, "status_request"),
                does(a.twist.is_some(), "twist"),
                does(a.silence, "silence"),
                does(a.resume, "resume"),
                does(a.wheel_test.is_some(), "wheel_test"),
            ]
            .into_iter()
            .flatten()
            .collect();
            let contradicts = |x, y| commands.contains(&x) && commands.contains(&y);
            if commands.is_empty()
                || contradicts("enable", "disable")
                || contradicts("silence", "resume")
            {
                return Err(invalid(
                    &format!("actions[{i}]"),
                    format!("{{{}}}", commands.join(", ")),
                    "at least one of enable, disable, reset, estop, status_request, twist, \
                     silence, resume, wheel_test, and not both enable and disable or silence \
                     and resume",
                ));
            }
            if let Some(t) = a.twist
                && t.iter().any(|v| !v.is_finite())
            {
                return Err(invalid(
                    &format!("actions[{i}].twist"),
                    format!("{t:?}"),
                    "finite numbers",
                ));
            }
            if let Some(t) = a.wheel_test {
                // The protocol's ranges (WHEEL_TEST in the robot DBC): the codec would clamp.
                for (field, value, ok, expected) in [
                    (
                        "wheel",
                        f64::from(t.wheel),
                        t.wheel <= 3,
                        "a wheel index 0..=3",
                    ),
                    (
                        "speed",
                        f64::from(t.speed),
                        t.speed.is_finite() && t.speed.abs() <= 10.0,
                        "a wheel speed in [-10, 10] rad/s",
                    ),
                    (
                        "duration_ms",
                        f64::from(t.duration_ms),
                        (1..=3000).contains(&t.duration_ms),
                        "1 to 3000 ms",
                    ),
                ] {
                    if !ok {
                        return Err(invalid(
                            &format!("actions[{i}].wheel_test.{field}"),
                            value.to_string(),
                            expected,
                        ));
                    }
                }
            }
        }
        if let Some((key, value, expected)) = file.imu.as_ref().and_then(|i| i.invalid()) {
            return Err(invalid(&format!("imu.{key}"), value.to_string(), expected));
        }
        let mut bus_faults = Vec::new();
        let mut wheel_faults = Vec::new();
        let mut host_faults = Vec::new();
        for (i, f) in file.faults.iter().enumerate() {
            if !(f.from_s.is_finite()
                && f.until_s.is_finite()
                && 0.0 <= f.from_s
                && f.from_s < f.until_s)
            {
                return Err(invalid(
                    &format!("faults[{i}].from_s..until_s"),
                    format!("{}..{}", f.from_s, f.until_s),
                    "0 <= from_s < until_s",
                ));
            }
            if f.from_s >= file.duration_s {
                return Err(invalid(
                    &format!("faults[{i}].from_s"),
                    f.from_s.to_string(),
                    "a time before duration_s (a later fault would never happen)",
                ));
            }
            // A field another kind uses is a mistake (a `wheel` on a `drop` fault would
            // otherwise drop every frame, not one wheel's).
            let (rate_used, delay_used, sender_used, wheel_used, uses) = match f.kind {
                FaultName::Drop | FaultName::Corrupt => (true, false, true, false, "rate, sender"),
                FaultName::Burst => (false, false, true, false, "sender"),
                FaultName::Delay => (false, true, true, false, "delay_ms, sender"),
                FaultName::StuckEncoder | FaultName::MotorOffline => {
                    (false, false, false, true, "wheel")
                }
                FaultName::NonFiniteTwist | FaultName::RepeatedTwist => {
                    (false, false, false, false, "no other field")
                }
            };
            for (field, given, used) in [
                ("rate", f.rate.map(|x| x.to_string()), rate_used),
                ("delay_ms", f.delay_ms.map(|x| x.to_string()), delay_used),
                ("sender", f.sender.map(|x| format!("{x:?}")), sender_used),
                ("wheel", f.wheel.map(|x| x.to_string()), wheel_used),
            ] {
                if let (Some(value), false) = (given, used) {
                    return Err(ScenarioError::UnusedField {
                        path: path.to_path_buf(),
                        field: format!("faults[{i}].{field}"),
                        value,
                        kind: f.kind,
                        uses,
                    });
                }
            }
            let (from_us, until_us) = (secs_to_us(f.from_s), secs_to_us(f.until_s));
            let rate = |f: &FaultSpec| match f.rate {
                Some(r) if (0.0..=1.0).contains(&r) => Ok(r),
                other => Err(invalid(
                    &format!("faults[{i}].rate"),
                    given(other),
                    "a probability in 0..=1",
                )),
            };
            let kind = match f.kind {
                FaultName::Drop => Some(FaultKind::Drop { rate: rate(f)? }),
                FaultName::Corrupt => Some(FaultKind::Corrupt { rate: rate(f)? }),
                FaultName::Burst => Some(FaultKind::Burst),
                FaultName::Delay => match f.delay_ms {
                    Some(ms) if ms.is_finite() && (0.0..=10_000.0).contains(&ms) => {
                        Some(FaultKind::Delay {
                            micros: (ms * 1000.0).round() as u64,
                        })
                    }
                    other => {
                        return Err(invalid(
                            &format!("faults[{i}].delay_ms"),
                            given(other),
                            "a delay in 0..=10000 ms",
                        ));
                    }
                },
                FaultName::StuckEncoder
                | FaultName::MotorOffline
                | FaultName::NonFiniteTwist
                | FaultName::RepeatedTwist => None,
            };
            if matches!(f.kind, FaultName::NonFiniteTwist | FaultName::RepeatedTwist) {
                host_faults.push(HostFault {
                    kind: f.kind,
                    from_us,
                    until_us,
                });
                continue;
            }
            match kind {
                Some(kind) => bus_faults.push(Fault {
                    kind,
                    from_us,
                    until_us,
                    sender: f.sender.map(Node::from),
                }),
                None => match f.wheel {
                    Some(wheel) if wheel < 4 => wheel_faults.push(WheelFault {
                        kind: f.kind,
                        wheel,
                        from_us,
                        until_us,
                    }),
                    other => {
                        return Err(invalid(
                            &format!("faults[{i}].wheel"),
                            given(other),
                            "a wheel index 0..=3 (FL, FR, RL, RR)",
                        ));
                    }
                },
            }
        }
        if let Some((field, value, expected)) = file.plant.first_invalid() {
            return Err(invalid(field, value.to_string(), expected));
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
        })
    }

    /// A built-in scenario on the DJI example chassis. See [`Scenario::BUILTINS`].
    ///
    /// - `square`: 1 m sides at 0.5 m/s, driving forward, left, back and right without
    ///   turning (the mecanum party trick).
    /// - `circle`: 0.5 m/s forward while turning at 0.5 rad/s, one full turn.
    /// - `strafe`: 0.5 m/s to the left for 3 s, then back.
    /// - `spin`: two turns on the spot at 1.5 rad/s.
    /// - `figure-eight`: a left circle then a right circle.
    /// - `compass`: the eight compass directions of Table I of Tlale and de Villiers in
    ///   turn, 1.5 s each.
    /// - `watchdog`: drive forward, then go silent: the firmware must stop and disable.
    /// - `calibration`: the motion `hostsim calibrate` needs, each leg both ways with a
    ///   0.5 s stop between legs: 1 s standing still, 1 m forward and back at 0.5 m/s, 1 m
    ///   (commanded) left and right at 0.5 m/s, one turn each way at 1.5 rad/s. Its robot is
    ///   fixed ([`PlantSpec::dji_m3508_example`]), so a run with a calibrated `--config`
    ///   changes only what the firmware believes.
    ///
    /// # Errors
    /// [`ScenarioError::UnknownBuiltin`] with the list of names.
    pub fn builtin(name: &str) -> Result<Self, ScenarioError> {
        let mut actions = vec![Action {
            enable: true,
            ..Action::at(0.05)
        }];
        let mut t = 0.1;
        let leg = |actions: &mut Vec<Action>, t: &mut f64, dur: f64, vx: f32, vy: f32, wz: f32| {
            actions.push(Action::twist(*t, vx, vy, wz));
            *t += dur;
        };
        let tau = std::f64::consts::TAU;
        match name {
            "square" => {
                for (vx, vy) in [(0.5, 0.0), (0.0, 0.5), (-0.5, 0.0), (0.0, -0.5)] {
                    leg(&mut actions, &mut t, 2.0, vx, vy, 0.0);
                }
            }
            "circle" => leg(&mut actions, &mut t, tau / 0.5, 0.5, 0.0, 0.5),
            "strafe" => {
                leg(&mut actions, &mut t, 3.0, 0.0, 0.5, 0.0);
                leg(&mut actions, &mut t, 3.0, 0.0, -0.5, 0.0);
            }
            "spin" => leg(&mut actions, &mut t, 2.0 * tau / 1.5, 0.0, 0.0, 1.5),
            "figure-eight" => {
                leg(&mut actions, &mut t, tau / 0.6, 0.4, 0.0, 0.6);
                leg(&mut actions, &mut t, tau / 0.6, 0.4, 0.0, -0.6);
            }
            "compass" => {
                let s = std::f32::consts::FRAC_1_SQRT_2 * 0.5;
                for (vx, vy) in [
                    (0.5, 0.0),
                    (s, -s),
                    (0.0, -0.5),
                    (-s, -s),
                    (-0.5, 0.0),
                    (-s, s),
                    (0.0, 0.5),
                    (s, s),
                ] {
                    leg(&mut actions, &mut t, 1.5, vx, vy, 0.0);
                }
            }
            "calibration" => {
                leg(&mut actions, &mut t, 1.0, 0.0, 0.0, 0.0);
                let turn = tau / 1.5;
                for (dur, vx, vy, wz) in [
                    (2.0, 0.5, 0.0, 0.0),
                    (2.0, -0.5, 0.0, 0.0),
                    (2.0, 0.0, 0.5, 0.0),
                    (2.0, 0.0, -0.5, 0.0),
                    (turn, 0.0, 0.0, 1.5),
                    (turn, 0.0, 0.0, -1.5),
                ] {
                    leg(&mut actions, &mut t, dur, vx, vy, wz);
                    leg(&mut actions, &mut t, 0.5, 0.0, 0.0, 0.0);
                }
            }
            "watchdog" => {
                leg(&mut actions, &mut t, 1.0, 0.8, 0.0, 0.0);
                actions.push(Action {
                    silence: true,
                    ..Action::at(t)
                });
                t += 1.5;
            }
            other => return Err(ScenarioError::UnknownBuiltin(other.to_string())),
        }
        if name != "watchdog" {
            leg(&mut actions, &mut t, 1.0, 0.0, 0.0, 0.0);
        }
        let plant = if name == "calibration" {
            PlantSpec::dji_m3508_example()
        } else {
            PlantSpec::default()
        };
        Ok(Self {
            name: name.to_string(),
            duration_s: t,
            seed: 1,
            command_hz: 50.0,
            config: Config::dji_m3508_example(),
            actions,
            bus_faults: Vec::new(),
            wheel_faults: Vec::new(),
            host_faults: Vec::new(),
            plant,
            imu: None,
        })
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
}

/// A field's value for an error message: as written, or `(missing)`.
fn given<T: std::fmt::Display>(value: Option<T>) -> String {
    value.map_or_else(|| "(missing)".to_owned(), |v| v.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtins_exist_and_end_after_their_last_action() {
        for name in Scenario::BUILTINS {
            let s = Scenario::builtin(name).unwrap();
            let last = s.actions.last().unwrap().at_s;
            assert!(s.duration_s >= last, "{name}");
        }
        let e = Scenario::builtin("nope").unwrap_err().to_string();
        assert!(e.contains("square") && e.contains("nope"), "{e}");
    }

    #[test]
    fn toml_scenario_parses_and_validates() {
        let text = r#"
            duration_s = 3.0
            seed = 9
            [[actions]]
            at_s = 0.1
            enable = true
            [[actions]]
            at_s = 0.2
            twist = [0.5, 0.0, 0.1]
            [[faults]]
            kind = "drop"
            rate = 0.25
            from_s = 1.0
            until_s = 2.0
            sender = "drives"
            [[faults]]
            kind = "stuck_encoder"
            wheel = 2
            from_s = 0.5
            until_s = 0.7
            [[faults]]
            kind = "non_finite_twist"
            from_s = 1.5
            until_s = 1.6
            [[faults]]
            kind = "repeated_twist"
            from_s = 2.0
            until_s = 2.5
        "#;
        let s = Scenario::from_toml(text, Path::new("x.toml")).unwrap();
        assert_eq!((s.name.as_str(), s.seed, s.actions.len()), ("x", 9, 2));
        assert_eq!(s.bus_faults[0].kind, FaultKind::Drop { rate: 0.25 });
        assert_eq!(s.bus_faults[0].sender, Some(Node::Drives));
        assert_eq!(
            (s.wheel_faults[0].wheel, s.wheel_faults[0].from_us),
            (2, 500_000)
        );
        assert_eq!(
            s.host_faults,
            [
                HostFault {
                    kind: FaultName::NonFiniteTwist,
                    from_us: 1_500_000,
                    until_us: 1_600_000
                },
                HostFault {
                    kind: FaultName::RepeatedTwist,
                    from_us: 2_000_000,
                    until_us: 2_500_000
                }
            ]
        );
        assert!(s.host_faults[1].active(2_000_000) && !s.host_faults[1].active(2_500_000));
        assert_eq!(s.bus_faults.len(), 1);

        for (bad, field) in [
            ("duration_s = -1.0", "duration_s"),
            ("name = \" \"\nduration_s = 1.0", "name = \" \": a name"),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"drop\"\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].rate = (missing): a probability",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"corrupt\"\nrate = 2.0\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].rate = 2: a probability",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"motor_offline\"\nwheel = 4\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].wheel = 4: a wheel index",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"delay\"\ndelay_ms = -5.0\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].delay_ms = -5: a delay",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"burst\"\nfrom_s = 2.0\nuntil_s = 1.0",
                "from_s",
            ),
            ("duration_s = 1.0\n[[actions]]\nat_s = -0.5", "at_s"),
            (
                "duration_s = 1.0\n[[actions]]\nat_s = 1.0\nenable = true",
                "actions[0].at_s = 1: a time before duration_s",
            ),
            (
                "duration_s = 1.0\n[[actions]]\nat_s = 0.5",
                "actions[0] = {}: at least one of",
            ),
            (
                "duration_s = 1.0\n[[actions]]\nat_s = 0.5\nenable = true\ndisable = true",
                "actions[0] = {enable, disable}",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"burst\"\nfrom_s = 1.5\nuntil_s = 2.0",
                "faults[0].from_s = 1.5: a time before duration_s",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"drop\"\nrate = 0.5\nwheel = 2\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].wheel = 2: not used by a \"drop\" fault (it takes rate, sender)",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"stuck_encoder\"\nwheel = 1\nrate = 0.5\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].rate = 0.5: not used by a \"stuck_encoder\" fault (it takes wheel)",
            ),
            (
                "duration_s = 1.0\n[[faults]]\nkind = \"repeated_twist\"\nwheel = 1\nfrom_s = 0.0\nuntil_s = 1.0",
                "faults[0].wheel = 1: not used by a \"repeated_twist\" fault (it takes no other field)",
            ),
        ] {
            let e = Scenario::from_toml(bad, Path::new("bad.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(field) && e.contains("bad.toml"), "{bad}: {e}");
        }
        let e = Scenario::from_toml("duration_s = 1.0\nwarp = 9", Path::new("w.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("warp"), "{e}");
    }

    #[test]
    fn a_wheel_test_action_parses_and_its_ranges_are_checked() {
        let text = "duration_s = 2.0\n[[actions]]\nat_s = 0.1\n\
                    wheel_test = { wheel = 2, speed = -3.0, duration_ms = 500 }";
        let s = Scenario::from_toml(text, Path::new("t.toml")).unwrap();
        let t = s.actions[0].wheel_test.unwrap();
        assert_eq!((t.wheel, t.speed, t.duration_ms), (2, -3.0, 500));
        for (table, needle) in [
            (
                "wheel = 4, speed = 3.0, duration_ms = 500",
                "actions[0].wheel_test.wheel = 4",
            ),
            (
                "wheel = 0, speed = 11.0, duration_ms = 500",
                "actions[0].wheel_test.speed = 11",
            ),
            (
                "wheel = 0, speed = 3.0, duration_ms = 0",
                "actions[0].wheel_test.duration_ms = 0",
            ),
        ] {
            let text =
                format!("duration_s = 2.0\n[[actions]]\nat_s = 0.1\nwheel_test = {{ {table} }}");
            let e = Scenario::from_toml(&text, Path::new("t.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{table}: {e}");
        }
    }

    #[test]
    fn plant_wiring_parses_and_a_bad_wheel_is_named() {
        let text = "duration_s = 1.0\n[plant]\nflip = [1]\nswap = [[0, 2], [2, 3]]\nlifted = true";
        let s = Scenario::from_toml(text, Path::new("w.toml")).unwrap();
        assert_eq!((s.plant.flip.as_slice(), s.plant.lifted), (&[1][..], true));
        // FL <-> RL, then RL <-> RR: RL is on FL's id... applied in order.
        assert_eq!(s.plant.wired_ids([1u8, 2, 3, 4]), [3, 2, 4, 1]);
        assert_eq!(
            s.plant.wired_inverted([false, true, false, true]),
            [false, false, false, true]
        );
        for (table, needle) in [
            ("flip = [4]", "plant.flip = 4: a wheel index 0..=3"),
            ("flip = [1, 1]", "plant.flip = 1: each wheel at most once"),
            ("swap = [[2, 2]]", "plant.swap = 2: two different wheels"),
            ("swap = [[0, 7]]", "plant.swap = 7: a wheel index 0..=3"),
        ] {
            let text = format!("duration_s = 1.0\n[plant]\n{table}");
            let e = Scenario::from_toml(&text, Path::new("w.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{table}: {e}");
        }
    }

    #[test]
    fn plant_table_parses_validates_and_changes_only_the_robot() {
        let text =
            "duration_s = 1.0\n[plant]\nwheel_radius = 0.0775\nlx = 0.194\nroller_drag = 0.2";
        let s = Scenario::from_toml(text, Path::new("p.toml")).unwrap();
        assert_eq!(
            s.plant,
            PlantSpec {
                wheel_radius: Some(0.0775),
                lx: Some(0.194),
                ly: None,
                roller_drag: Some(0.2),
                ..PlantSpec::default()
            }
        );
        let mut chassis = ChassisParams::from_config(&s.config);
        s.plant.apply(&mut chassis).unwrap();
        let xs: Vec<[f64; 3]> = chassis
            .wheels
            .iter()
            .map(|w| [w.x, w.y, w.radius])
            .collect();
        // ly stays the configuration's (an f32).
        let ly = f64::from(0.18f32);
        assert_eq!(
            xs,
            [
                [0.194, ly, 0.0775],
                [0.194, -ly, 0.0775],
                [-0.194, ly, 0.0775],
                [-0.194, -ly, 0.0775]
            ]
        );
        assert_eq!(chassis.roller_drag, 0.2);
        // The firmware's configuration is the file's (the DJI example), untouched.
        assert_eq!(s.config, Config::dji_m3508_example());

        for (bad, want) in [
            (
                "wheel_radius = 0.0",
                "plant.wheel_radius = 0: a radius in (0, 1] m",
            ),
            ("lx = -0.2", "plant.lx = -0.2: a distance in (0, 5] m"),
            ("ly = nan", "plant.ly = NaN: a distance in (0, 5] m"),
            (
                "roller_drag = 1.0",
                "plant.roller_drag = 1: a roller drag in [0, 1)",
            ),
            ("mass = 3.0", "unknown field `mass`"),
        ] {
            let text = format!("duration_s = 1.0\n[plant]\n{bad}");
            let e = Scenario::from_toml(&text, Path::new("bad.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(want) && e.contains("bad.toml"), "{bad}: {e}");
        }

        // lx and ly are the standard layout's: another layout is refused, naming the field.
        let mut general = ChassisParams::default();
        general.wheels[0].x = 0.3;
        let e = PlantSpec {
            ly: Some(0.2),
            ..PlantSpec::default()
        }
        .apply(&mut general)
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("plant.ly = 0.2") && e.contains("standard layout"),
            "{e}"
        );

        // The calibration built-in fixes its robot to the example's.
        let c = Scenario::builtin("calibration").unwrap();
        assert_eq!(c.plant, PlantSpec::dji_m3508_example());
        assert_eq!(c.plant.lx, Some(f64::from(0.20f32)));
        assert!(Scenario::builtin("square").unwrap().plant.is_empty());
    }

    #[test]
    fn fault_names_are_the_ones_a_file_uses() {
        use FaultName::*;
        for kind in [
            Drop,
            Burst,
            Delay,
            Corrupt,
            StuckEncoder,
            MotorOffline,
            NonFiniteTwist,
            RepeatedTwist,
        ] {
            let parsed: FaultName =
                serde::de::Deserialize::deserialize(serde::de::value::StrDeserializer::<
                    serde::de::value::Error,
                >::new(kind.as_str()))
                .unwrap();
            assert_eq!(parsed, kind);
        }
    }
}
