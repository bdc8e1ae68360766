//! `hostsim calibrate`: the wheel radius, lx + ly and lateral effectiveness that make the
//! odometry match a reference pose, fitted by least squares from a log; and, for a robot
//! with tracking pods, each pod's radius, direction and lever ([`PodFit`]).
//!
//! [`calibrate`] (a file) and [`calibrate_bytes`] take a log and [`Options`] (the reference
//! pose channel, by default [`GROUND_TRUTH`], and the fit's window) and return a
//! [`Calibration`]: per-axis corrections with their standard errors, the pods' fits, and the
//! refined configuration values. A log without enough steady motion (at least
//! [`MIN_TRAVEL_M`] forward and sideways, [`MIN_TURN_RAD`] of turning; for each pod, as much
//! travel along and across its direction and as much turning) is refused with a
//! [`CalibrateError`] naming the missing motion (and the pod).
//!
//! The model, the fit, the convention the fitted values follow (effective radius and
//! lx + ly), the pods' model and the refusals are specified in `docs/simulator.md`, section
//! "Calibration".

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

use firmware::Config;
use firmware::config::{Geometry, PODS_MAX, Pods};
use kinematics::{Effectiveness, MecanumKinematics, Pose2, Twist2, WheelDeltas};
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use crate::log::msg::{self, decode};
use crate::log::{ReadReport, for_each_message};

mod pods;

pub use pods::{PodFit, PodValues};

/// The default reference: the simulator's ground truth.
pub const GROUND_TRUTH: &str = "/ground_truth/odom";

/// The least forward travel, and sideways travel, a log must have, m.
pub const MIN_TRAVEL_M: f64 = 0.5;

/// The least turning a log must have, rad (one turn).
pub const MIN_TURN_RAD: f64 = std::f64::consts::TAU;

/// A window enters the fit if the odometry moves at least this fast in it (m/s, or rad/s).
const MOVING: f64 = 5e-3;

/// A window is steady if its neighbours' increments differ from its own by at most this
/// fraction of it, plus [`STEADY_FLOOR`].
const STEADY_RELATIVE: f64 = 0.02;

/// The absolute part of the steadiness bound, per second of window (m/s, or rad/s).
const STEADY_FLOOR: f64 = 2e-3;

/// The longest gap between two samples a window may span, ns: a longer one (a tracker that
/// lost the robot, a paused log) starts a new window after it.
const MAX_GAP_NS: u64 = 250_000_000;

/// How [`calibrate`] reads a log.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// The reference pose topic ([`GROUND_TRUTH`] by default).
    pub reference: String,
    /// Window length, s.
    pub window_s: f64,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            reference: GROUND_TRUTH.to_string(),
            window_s: 0.1,
        }
    }
}

/// A motion the log lacks, for a value it then cannot determine.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MissingMotion {
    /// What is missing (`forward travel`, `strafe`, `rotation`). For a pod, the body motion
    /// that gives the travel along or across its direction: the nearer body axis.
    pub motion: &'static str,
    /// How much of it the log has (m, or rad for rotation). For a pod, the reference's
    /// travel along (`radius`) or across (`direction_deg`) the pod's configured direction.
    pub have: f64,
    /// How much it needs.
    pub need: f64,
    /// The value it cannot fit (a pod's: `radius`, `direction_deg`, `lever`).
    pub value: &'static str,
    /// The pod (its index in the configuration), for a pod's value.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pod: Option<usize>,
}

impl fmt::Display for MissingMotion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(pod) = self.pod {
            return pods::describe(self, pod, f);
        }
        match self.motion {
            "rotation" => write!(
                f,
                "no rotation in this log ({:.1}° of turning at a steady speed, needs >= {:.0}°): \
                 cannot fit {}; spin on the spot both ways",
                self.have.to_degrees(),
                self.need.to_degrees(),
                self.value
            ),
            "strafe" => write!(
                f,
                "no strafe in this log ({:.2} m of lateral travel at a steady speed, needs >= \
                 {:.1} m): cannot fit {}; drive sideways both ways",
                self.have, self.need, self.value
            ),
            _ => write!(
                f,
                "no forward travel in this log ({:.2} m at a steady speed, needs >= {:.1} m): \
                 cannot fit {}; drive forward and back",
                self.have, self.need, self.value
            ),
        }
    }
}

/// Why a log could not be calibrated. Each names what is missing or wrong.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// The file could not be read, or is not MCAP.
    #[error("{0}")]
    Read(String),
    /// No configuration in the metadata.
    #[error(
        "the log has no drive configuration (metadata `mecanum_drive`, key `config`): the \
         odometry's model is unknown"
    )]
    NoConfig,
    /// The logged configuration does not load.
    #[error("the log's configuration: {0}")]
    Config(String),
    /// A general wheel layout: no lx + ly to fit.
    #[error(
        "the log's configuration has geometry.layout = \"general\": calibration fits the \
         standard layout's wheel_radius and lx + ly"
    )]
    GeneralLayout,
    /// No message on the reference topic.
    #[error(
        "no reference poses: the log has no topic {topic:?} (pose topics in it: {available}); \
         name one with --reference",
        available = if available.is_empty() { "none".to_string() } else { available.join(", ") }
    )]
    NoReference {
        /// The topic asked for.
        topic: String,
        /// The log's topics of a pose type.
        available: Vec<String>,
    },
    /// The reference topic's type is not a pose.
    #[error(
        "reference {topic:?} is a {schema}, not a pose: use a geometry_msgs/msg/PoseStamped or \
         nav_msgs/msg/Odometry topic"
    )]
    ReferenceType {
        /// The topic.
        topic: String,
        /// Its type.
        schema: String,
    },
    /// A message could not be decoded.
    #[error("{topic} at {t_s:.3} s: {reason}")]
    Decode {
        /// The topic.
        topic: String,
        /// Its log time, s.
        t_s: f64,
        /// The decoder's error.
        reason: String,
    },
    /// The configuration has tracking pods, the log's `/joint_states` not their angles.
    #[error(
        "the log's configuration has {pods} tracking pods, but its /joint_states carry no \
         angle of pod{missing} (joints pod0, pod1...): the pods cannot be fitted"
    )]
    NoPodAngles {
        /// Pods configured.
        pods: usize,
        /// The first pod without angles.
        missing: usize,
    },
    /// No odometry: neither wheel angles nor `/odom`.
    #[error("the log has no /joint_states with the wheels fl, fr, rl, rr and no /odom")]
    NoOdometry,
    /// The odometry and the reference do not overlap in time.
    #[error(
        "the reference {topic} and the odometry overlap in {windows} windows of {window_s} s \
         (log times: odometry {odometry}, reference {reference}): nothing to fit"
    )]
    NoOverlap {
        /// The reference topic.
        topic: String,
        /// Windows found.
        windows: usize,
        /// Window length.
        window_s: f64,
        /// The odometry's time span.
        odometry: String,
        /// The reference's time span.
        reference: String,
    },
    /// The log's motion cannot determine one or more values.
    #[error(
        "{}; as the built-in `calibration` scenario does (hostsim run calibration)",
        .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
    )]
    MissingMotion(Vec<MissingMotion>),
    /// The reference moves against the odometry along an axis: another body frame.
    #[error(
        "the reference moves against the odometry along {axis} (correction {correction:.3}): \
         is its body frame the robot's (x forward, y left, yaw counter-clockwise)?"
    )]
    Opposed {
        /// The axis.
        axis: &'static str,
        /// The fitted correction.
        correction: f64,
    },
    /// The fitted configuration is refused by the firmware's validation.
    #[error("the fitted configuration is not valid: {0}")]
    Refused(String),
    /// `window_s` out of range.
    #[error("--window = {0}: expected a window in [0.01, 10] s")]
    Window(f64),
}

/// One axis's fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AxisFit {
    /// `forward`, `lateral` or `yaw`.
    pub axis: &'static str,
    /// The odometry's travel along it over the windows (sum of |increment|), m or rad.
    pub travel: f64,
    /// Correction of the logged model: reference increment per odometry increment.
    pub correction: f64,
    /// Its standard error.
    pub stderr: f64,
    /// RMS of the per-window residuals, m or rad.
    pub residual_rms: f64,
}

/// A fitted value with its standard error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Estimate {
    /// The value.
    pub value: f64,
    /// Its standard error.
    pub stderr: f64,
}

/// The `[geometry]` values of a standard layout.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GeometryValues {
    /// m.
    pub lx: f64,
    /// m.
    pub ly: f64,
    /// m.
    pub wheel_radius: f64,
    /// Dimensionless.
    pub forward_effectiveness: f64,
    /// Dimensionless.
    pub lateral_effectiveness: f64,
    /// Dimensionless.
    pub yaw_effectiveness: f64,
}

/// What [`calibrate`] found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Calibration {
    /// Where the odometry came from: `/joint_states` (recomputed) or `/odom`.
    pub odometry: &'static str,
    /// Odometry samples read.
    pub odometry_samples: usize,
    /// The reference topic.
    pub reference: String,
    /// Its type.
    pub reference_type: String,
    /// Reference samples read.
    pub reference_samples: usize,
    /// Window length, s.
    pub window_s: f64,
    /// Windows formed (the odometry's samples that have a reference pose).
    pub windows: usize,
    /// Windows that entered the fit: moving at a steady speed.
    pub moving_windows: usize,
    /// Per axis: forward, lateral, yaw.
    pub axes: [AxisFit; 3],
    /// The logged configuration's values.
    pub logged: GeometryValues,
    /// The fitted values (rounded as written: lengths to the µm, factors to 1e-5).
    pub fitted: GeometryValues,
    /// Fitted effective wheel radius, m.
    pub wheel_radius: Estimate,
    /// Fitted effective lx + ly, m.
    pub lx_plus_ly: Estimate,
    /// Fitted lateral effectiveness.
    pub lateral_effectiveness: Estimate,
    /// Each tracking pod's fit, in the configuration's order (none without pods).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub pods: Vec<PodFit>,
    /// The logged configuration with the fitted `[geometry]` (and pods).
    #[serde(skip)]
    pub config: Config,
    /// What was read, and where the log is damaged if it is.
    #[serde(skip)]
    pub read: ReadReport,
}

impl Calibration {
    /// The `[geometry]` lines to paste into a configuration.
    #[must_use]
    pub fn geometry_lines(&self) -> String {
        let f = &self.fitted;
        // As f32, the configuration's type: the shortest text that reads back the same.
        let v = |x: f64| x as f32;
        format!(
            "[geometry]\nlayout = \"standard\"\nlx = {:?}\nly = {:?}\nwheel_radius = {:?}\n\
             forward_effectiveness = {:?}\nlateral_effectiveness = {:?}\n\
             yaw_effectiveness = {:?}\n",
            v(f.lx),
            v(f.ly),
            v(f.wheel_radius),
            v(f.forward_effectiveness),
            v(f.lateral_effectiveness),
            v(f.yaw_effectiveness)
        )
    }

    /// The `[[odometry.pods]]` tables to paste into a configuration (empty without pods):
    /// the fitted radius and direction, the configured contact point moved across the
    /// pod's line of action to the fitted lever, `counts_per_turn` as configured.
    #[must_use]
    pub fn pod_lines(&self) -> String {
        pods::lines(&self.pods)
    }
}

impl fmt::Display for Calibration {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "odometry: {} ({} samples, recomputed with the logged configuration); reference: \
             {} ({}, {} samples)",
            self.odometry,
            self.odometry_samples,
            self.reference,
            self.reference_type,
            self.reference_samples
        )?;
        writeln!(
            f,
            "{} windows of {} s, {} moving at a steady speed (the fit's)",
            self.windows, self.window_s, self.moving_windows
        )?;
        writeln!(
            f,
            "  {:<8} {:>11} {:>22} {:>26}",
            "axis", "travel", "correction ± s.e.", "residual (RMS per window)"
        )?;
        for a in &self.axes {
            let (travel, residual) = if a.axis == "yaw" {
                (
                    format!("{:.1}°", a.travel.to_degrees()),
                    format!("{:.3} mrad", a.residual_rms * 1e3),
                )
            } else {
                (
                    format!("{:.3} m", a.travel),
                    format!("{:.3} mm", a.residual_rms * 1e3),
                )
            };
            writeln!(
                f,
                "  {:<8} {:>11} {:>13.5} ± {:<7.1e} {:>25}",
                a.axis, travel, a.correction, a.stderr, residual
            )?;
        }
        let (l, x) = (&self.logged, self);
        writeln!(f, "fitted (logged -> fitted ± standard error):")?;
        writeln!(
            f,
            "  wheel_radius           {:.6} m -> {:.6} m ± {:.1e} m  (effective, with \
             forward_effectiveness = 1)",
            l.wheel_radius, x.wheel_radius.value, x.wheel_radius.stderr
        )?;
        writeln!(
            f,
            "  lx + ly                {:.6} m -> {:.6} m ± {:.1e} m  (effective, with \
             yaw_effectiveness = 1)",
            l.lx + l.ly,
            x.lx_plus_ly.value,
            x.lx_plus_ly.stderr
        )?;
        writeln!(
            f,
            "  lateral_effectiveness  {:.5} -> {:.5} ± {:.1e}",
            l.lateral_effectiveness, x.lateral_effectiveness.value, x.lateral_effectiveness.stderr
        )?;
        if !self.pods.is_empty() {
            pods::report(&self.pods, f)?;
        }
        writeln!(f, "paste into the configuration:")?;
        let lines = self.geometry_lines() + &self.pod_lines();
        f.write_str(lines.trim_end_matches('\n'))
    }
}

/// A pose track: log time (ns) and pose, in time order.
type Track = Vec<(u64, Pose2<f64>)>;

/// One `/joint_states` sample: its log time, the wheel angles and the pods' (rad).
#[derive(Debug, Clone, Copy)]
struct Joints {
    t: u64,
    wheels: [f64; 4],
    pods: [Option<f64>; PODS_MAX],
}

/// What a log holds for calibration.
#[derive(Default)]
struct LogData {
    config: Option<String>,
    joints: Vec<Joints>,
    odom: Track,
    reference: Track,
    reference_type: Option<String>,
    /// Topic -> schema of every channel with a pose type.
    pose_topics: BTreeMap<String, String>,
    error: Option<CalibrateError>,
}

/// Calibrates from the log at `path` (see `docs/simulator.md`, section "Calibration").
///
/// # Errors
/// [`CalibrateError`] naming what is missing or wrong; a damaged log is not an error (it is
/// calibrated from its complete part: [`Calibration::read`]).
pub fn calibrate(path: &Path, options: &Options) -> Result<Calibration, CalibrateError> {
    let bytes = crate::log::read::read_log_file(path)
        .map_err(|e| CalibrateError::Read(format!("cannot read {}: {e}", path.display())))?;
    calibrate_bytes(&bytes, options).map_err(|e| match e {
        CalibrateError::Read(m) => CalibrateError::Read(format!("{}: {m}", path.display())),
        other => other,
    })
}

/// [`calibrate`] on a log's bytes.
///
/// # Errors
/// As [`calibrate`].
pub fn calibrate_bytes(bytes: &[u8], options: &Options) -> Result<Calibration, CalibrateError> {
    if !(options.window_s.is_finite() && (0.01..=10.0).contains(&options.window_s)) {
        return Err(CalibrateError::Window(options.window_s));
    }
    let reference = options.reference.as_str();
    let mut d = LogData::default();
    let read = for_each_message(
        bytes,
        |m| {
            if d.error.is_some() {
                return;
            }
            let fail = |reason: String| CalibrateError::Decode {
                topic: m.topic.to_string(),
                t_s: m.log_time as f64 * 1e-9,
                reason,
            };
            let is_pose = matches!(
                m.schema,
                "nav_msgs/msg/Odometry" | "geometry_msgs/msg/PoseStamped"
            );
            if is_pose && !d.pose_topics.contains_key(m.topic) {
                d.pose_topics
                    .insert(m.topic.to_string(), m.schema.to_string());
            }
            if m.topic == reference {
                d.reference_type = Some(m.schema.to_string());
                let pose = match m.schema {
                    "nav_msgs/msg/Odometry" => {
                        decode::<msg::Odometry>(m.data).map(|o| o.pose.pose.to_planar())
                    }
                    "geometry_msgs/msg/PoseStamped" => {
                        decode::<msg::PoseStamped>(m.data).map(|p| p.pose.to_planar())
                    }
                    other => {
                        d.error = Some(CalibrateError::ReferenceType {
                            topic: reference.to_string(),
                            schema: other.to_string(),
                        });
                        return;
                    }
                };
                match pose {
                    Ok([x, y, yaw]) => d.reference.push((m.log_time, Pose2::new(x, y, yaw))),
                    Err(e) => d.error = Some(fail(e.to_string())),
                }
                // The reference may be /odom itself; it is then also the odometry below.
            }
            match m.topic {
                "/joint_states" => match decode::<msg::JointState>(m.data) {
                    Ok(j) => {
                        let angle = |name: &str| {
                            let i = j.name.iter().position(|n| n == name)?;
                            j.position.get(i).copied()
                        };
                        let [fl, fr, rl, rr] = crate::log::WHEEL_NAMES.map(angle);
                        if let (Some(fl), Some(fr), Some(rl), Some(rr)) = (fl, fr, rl, rr) {
                            d.joints.push(Joints {
                                t: m.log_time,
                                wheels: [fl, fr, rl, rr],
                                pods: crate::log::POD_NAMES.map(angle),
                            });
                        }
                    }
                    Err(e) => d.error = Some(fail(e.to_string())),
                },
                "/odom" => match decode::<msg::Odometry>(m.data) {
                    Ok(o) => {
                        let [x, y, yaw] = o.pose.pose.to_planar();
                        d.odom.push((m.log_time, Pose2::new(x, y, yaw)));
                    }
                    Err(e) => d.error = Some(fail(e.to_string())),
                },
                _ => {}
            }
        },
        |name, kv| {
            if name == crate::log::METADATA_NAME {
                d.config = kv.get("config").cloned();
            }
        },
    )
    .map_err(|e| CalibrateError::Read(format!("not a readable MCAP file: {e}")))?;
    if crate::replay::is_old_layout(&read) {
        return Err(CalibrateError::Read(crate::replay::OLD_LAYOUT.to_string()));
    }
    if let Some(e) = d.error {
        return Err(e);
    }
    let text = d.config.as_deref().ok_or(CalibrateError::NoConfig)?;
    let config = Config::from_toml_str(text).map_err(|e| CalibrateError::Config(e.to_string()))?;
    let Geometry::Standard {
        lx,
        ly,
        wheel_radius,
        ..
    } = config.geometry
    else {
        return Err(CalibrateError::GeneralLayout);
    };
    let k0 = config.geometry.effectiveness();
    let logged = GeometryValues {
        lx: f64::from(lx),
        ly: f64::from(ly),
        wheel_radius: f64::from(wheel_radius),
        forward_effectiveness: f64::from(k0.kx),
        lateral_effectiveness: f64::from(k0.ky),
        yaw_effectiveness: f64::from(k0.kw),
    };
    if d.reference.is_empty() {
        return Err(CalibrateError::NoReference {
            topic: reference.to_string(),
            available: d.pose_topics.keys().cloned().collect(),
        });
    }
    let (odometry, track) = if d.joints.len() >= 2 {
        ("/joint_states", wheel_odometry(&logged, &d.joints)?)
    } else if d.odom.len() >= 2 {
        ("/odom", d.odom)
    } else {
        return Err(CalibrateError::NoOdometry);
    };
    let mut reference_track = d.reference;
    reference_track.sort_by_key(|(t, _)| *t);
    let all = windows(&track, &reference_track, options.window_s);
    let steady: Vec<&Window> = steady_windows(&all, options.window_s).collect();
    let moving: Vec<(Twist2<f64>, Twist2<f64>)> =
        steady.iter().map(|w| (w.odometry, w.reference)).collect();
    if moving.len() < 3 {
        let span = |t: &Track| match (t.first(), t.last()) {
            (Some(a), Some(b)) => format!("{:.3}..{:.3} s", a.0 as f64 * 1e-9, b.0 as f64 * 1e-9),
            _ => "none".to_string(),
        };
        return Err(CalibrateError::NoOverlap {
            topic: reference.to_string(),
            windows: moving.len(),
            window_s: options.window_s,
            odometry: span(&track),
            reference: span(&reference_track),
        });
    }
    let component = |t: &Twist2<f64>, axis: usize| [t.dx, t.dy, t.dtheta][axis];
    let travel: [f64; 3] =
        core::array::from_fn(|axis| moving.iter().map(|(o, _)| component(o, axis).abs()).sum());
    let configured_pods = config.odometry.pods;
    let pod_windows = pod_windows(configured_pods.len(), &d.joints, &steady)?;
    let mut missing: Vec<MissingMotion> = [
        ("forward travel", MIN_TRAVEL_M, "wheel_radius"),
        ("strafe", MIN_TRAVEL_M, "lateral_effectiveness"),
        ("rotation", MIN_TURN_RAD, "lx + ly"),
    ]
    .into_iter()
    .zip(travel)
    .filter(|((_, need, _), have)| have < need)
    .map(|((motion, need, value), have)| MissingMotion {
        motion,
        have,
        need,
        value,
        pod: None,
    })
    .collect();
    missing.extend(pods::missing(configured_pods.as_slice(), &pod_windows));
    if !missing.is_empty() {
        return Err(CalibrateError::MissingMotion(missing));
    }
    let names = ["forward", "lateral", "yaw"];
    let mut axes = [AxisFit {
        axis: "",
        travel: 0.0,
        correction: 0.0,
        stderr: 0.0,
        residual_rms: 0.0,
    }; 3];
    for (axis, fit) in axes.iter_mut().enumerate() {
        let x = DMatrix::from_iterator(
            moving.len(),
            1,
            moving.iter().map(|(o, _)| component(o, axis)),
        );
        let y =
            DVector::from_iterator(moving.len(), moving.iter().map(|(_, r)| component(r, axis)));
        let ls = least_squares(&x, &y).ok_or_else(|| {
            CalibrateError::Refused(format!("the {} fit is singular", names[axis]))
        })?;
        *fit = AxisFit {
            axis: names[axis],
            travel: travel[axis],
            correction: ls.coefficients[0],
            stderr: ls.stderr[0],
            residual_rms: ls.residual_rms,
        };
        if fit.correction <= 0.0 {
            return Err(CalibrateError::Opposed {
                axis: names[axis],
                correction: fit.correction,
            });
        }
    }
    let [ax, ay, aw] = axes.map(|a| a.correction);
    let [rx, ry, rw] = axes.map(|a| a.stderr / a.correction);
    let l0 = logged.lx + logged.ly;
    let radius = logged.wheel_radius * logged.forward_effectiveness * ax;
    let sum = l0 * logged.forward_effectiveness * ax / (logged.yaw_effectiveness * aw);
    let lateral = logged.lateral_effectiveness * ay / (logged.forward_effectiveness * ax);
    let round = |x: f64, step: f64| (x / step).round() * step;
    let fitted = GeometryValues {
        lx: round(sum * logged.lx / l0, 1e-6),
        ly: round(sum * logged.ly / l0, 1e-6),
        wheel_radius: round(radius, 1e-6),
        forward_effectiveness: 1.0,
        lateral_effectiveness: round(lateral, 1e-5),
        yaw_effectiveness: 1.0,
    };
    let pod_fits = pods::fit(configured_pods.as_slice(), &pod_windows)?;
    let mut calibrated = config;
    if !pod_fits.is_empty() {
        calibrated.odometry.pods = Pods::new(&pods::refined(&pod_fits))
            .ok_or_else(|| CalibrateError::Refused("more pods than the robot carries".into()))?;
    }
    calibrated.geometry = Geometry::Standard {
        lx: fitted.lx as f32,
        ly: fitted.ly as f32,
        wheel_radius: fitted.wheel_radius as f32,
        forward_effectiveness: 1.0,
        lateral_effectiveness: fitted.lateral_effectiveness as f32,
        yaw_effectiveness: 1.0,
    };
    calibrated
        .validate()
        .map_err(|e| CalibrateError::Refused(e.to_string()))?;
    Ok(Calibration {
        odometry,
        odometry_samples: track.len(),
        reference: reference.to_string(),
        reference_type: d.reference_type.unwrap_or_default(),
        reference_samples: reference_track.len(),
        window_s: options.window_s,
        windows: all.len(),
        moving_windows: moving.len(),
        axes,
        logged,
        fitted,
        wheel_radius: Estimate {
            value: radius,
            stderr: radius * rx,
        },
        lx_plus_ly: Estimate {
            value: sum,
            stderr: sum * rx.hypot(rw),
        },
        lateral_effectiveness: Estimate {
            value: lateral,
            stderr: lateral * ry.hypot(rx),
        },
        pods: pod_fits,
        config: calibrated,
        read,
    })
}

/// The pods' windows: for each of the fit's windows, the reference's increment and each of
/// the `pods` configured pods' angle increments, from the `/joint_states` samples at the
/// window's ends (the windows' ends are those samples' times). None without pods.
///
/// # Errors
/// [`CalibrateError::NoPodAngles`] if the samples lack a pod's angle.
fn pod_windows(
    pods: usize,
    joints: &[Joints],
    steady: &[&Window],
) -> Result<Vec<pods::PodWindow>, CalibrateError> {
    if pods == 0 {
        return Ok(Vec::new());
    }
    let no_angles = |missing| CalibrateError::NoPodAngles { pods, missing };
    let Some(first) = joints.first() else {
        return Err(no_angles(0));
    };
    if let Some(missing) = (0..pods).find(|&i| first.pods[i].is_none()) {
        return Err(no_angles(missing));
    }
    let at = |t: u64| {
        let i = joints.partition_point(|j| j.t < t);
        joints.get(i).filter(|j| j.t == t)
    };
    Ok(steady
        .iter()
        .filter_map(|w| {
            let (j0, j1) = (at(w.t0)?, at(w.t1)?);
            let angles = (0..pods)
                .map(|i| Some(j1.pods[i]? - j0.pods[i]?))
                .collect::<Option<Vec<f64>>>()?;
            Some(pods::PodWindow {
                reference: w.reference,
                angles,
            })
        })
        .collect())
}

/// The odometry of the logged configuration recomputed from the wheel angles: each sample's
/// increments through the forward kinematics (effectiveness included) and the SE(2)
/// exponential, as the firmware integrates them.
fn wheel_odometry(g: &GeometryValues, joints: &[Joints]) -> Result<Track, CalibrateError> {
    let k = Effectiveness::new(
        g.forward_effectiveness,
        g.lateral_effectiveness,
        g.yaw_effectiveness,
    );
    let map = MecanumKinematics::standard_with_effectiveness(g.lx, g.ly, g.wheel_radius, k)
        .map_err(|e| CalibrateError::Config(e.to_string()))?;
    let mut pose = Pose2::default();
    let mut track = Vec::with_capacity(joints.len());
    let mut last = joints[0].wheels;
    for j in joints {
        let d: [f64; 4] = core::array::from_fn(|i| j.wheels[i] - last[i]);
        pose = pose.exp(map.displacement(&WheelDeltas::new(d[0], d[1], d[2], d[3])));
        last = j.wheels;
        track.push((j.t, pose));
    }
    Ok(track)
}

/// The reference pose at `t_ns`, interpolated on SE(2) between the samples around it; `None`
/// outside the samples or across a gap longer than [`MAX_GAP_NS`].
fn interpolate(track: &Track, t_ns: u64) -> Option<Pose2<f64>> {
    let i = track.partition_point(|(t, _)| *t < t_ns);
    let (t1, p1) = *track.get(i)?;
    if t1 == t_ns {
        return Some(p1);
    }
    let (t0, p0) = *track.get(i.checked_sub(1)?)?;
    if t1 - t0 > MAX_GAP_NS {
        return None;
    }
    let s = (t_ns - t0) as f64 / (t1 - t0) as f64;
    let u = p0.relative(p1).log();
    Some(p0.exp(Twist2::new(u.dx * s, u.dy * s, u.dtheta * s)))
}

/// One window: its start and end (log time, ns) and the body-frame increments over it.
#[derive(Debug, Clone, Copy)]
struct Window {
    t0: u64,
    t1: u64,
    odometry: Twist2<f64>,
    reference: Twist2<f64>,
}

/// The windows of the fit: those in which the odometry moves ([`MOVING`]) at a steady
/// speed, its increment within [`STEADY_RELATIVE`] (plus [`STEADY_FLOOR`]) of both
/// neighbours' on every axis. Constant factors describe the steady slip; the transients of
/// a start or a stop (the body lagging the wheels while it accelerates, sliding on after
/// they stop, the velocity loop's ringing) come and go and would bias the fit by how much
/// starting and stopping the log has.
fn steady_windows(all: &[Window], window_s: f64) -> impl Iterator<Item = &Window> {
    let floor = STEADY_FLOOR * window_s;
    let moving = MOVING * window_s;
    let parts = |t: &Twist2<f64>| [t.dx, t.dy, t.dtheta];
    all.windows(3).filter_map(move |w| {
        let (before, this, after) = (&w[0], &w[1], &w[2]);
        let contiguous = before.t1 == this.t0 && this.t1 == after.t0;
        let u = parts(&this.odometry);
        let close = |other: &Window| {
            parts(&other.odometry)
                .iter()
                .zip(u)
                .all(|(v, u)| (v - u).abs() <= STEADY_RELATIVE * u.abs() + floor)
        };
        let moves = u[0].hypot(u[1]) > moving || u[2].abs() > moving;
        (contiguous && moves && close(before) && close(after)).then_some(this)
    })
}

/// Consecutive windows of `window_s` over the odometry samples that have a reference pose:
/// each window's (odometry, reference) body-frame increments.
fn windows(odometry: &Track, reference: &Track, window_s: f64) -> Vec<Window> {
    let window_ns = (window_s * 1e9).round() as u64;
    let samples: Vec<(u64, Pose2<f64>, Pose2<f64>)> = odometry
        .iter()
        .filter_map(|&(t, o)| Some((t, o, interpolate(reference, t)?)))
        .collect();
    let mut out = Vec::new();
    let mut start = 0;
    for i in 1..samples.len() {
        let (t, o, r) = samples[i];
        if t - samples[i - 1].0 > MAX_GAP_NS {
            start = i;
            continue;
        }
        let (t0, o0, r0) = samples[start];
        if t - t0 >= window_ns {
            out.push(Window {
                t0,
                t1: t,
                odometry: o0.relative(o).log(),
                reference: r0.relative(r).log(),
            });
            start = i;
        }
    }
    out
}

/// A least-squares solution.
struct LeastSquares {
    coefficients: DVector<f64>,
    stderr: DVector<f64>,
    /// The coefficients' covariance `σ² (XᵀX)⁻¹`.
    covariance: DMatrix<f64>,
    residual_rms: f64,
}

/// Least squares `y ≈ X β` (SVD): the coefficients, their covariance and standard errors
/// (`σ² (XᵀX)⁻¹`, `σ²` the residual variance with `n − p` degrees of freedom) and the RMS
/// residual. `None` with no more rows than columns or a singular design.
fn least_squares(x: &DMatrix<f64>, y: &DVector<f64>) -> Option<LeastSquares> {
    let (n, p) = x.shape();
    if n <= p {
        return None;
    }
    let coefficients = x.clone().svd(true, true).solve(y, 1e-12).ok()?;
    let residual = y - x * &coefficients;
    let rss = residual.norm_squared();
    let variance = rss / (n - p) as f64;
    let covariance = (x.transpose() * x).try_inverse()? * variance;
    let stderr = covariance.diagonal().map(f64::sqrt);
    Some(LeastSquares {
        coefficients,
        stderr,
        covariance,
        residual_rms: (rss / n as f64).sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn least_squares_gives_the_textbook_standard_error() {
        // y = 2x + e with e = ±0.1 alternating over x = 1..=4.
        let x = DMatrix::from_column_slice(4, 1, &[1.0, 2.0, 3.0, 4.0]);
        let y = DVector::from_column_slice(&[2.1, 3.9, 6.1, 7.9]);
        let ls = least_squares(&x, &y).unwrap();
        // β = Σxy / Σx² = 59.8 / 30; residuals from it; s.e. = sqrt(RSS / 3 / 30).
        let beta = 59.8 / 30.0;
        let rss: f64 = [(1.0f64, 2.1f64), (2.0, 3.9), (3.0, 6.1), (4.0, 7.9)]
            .iter()
            .map(|(x, y)| (y - beta * x).powi(2))
            .sum();
        assert!((ls.coefficients[0] - beta).abs() < 1e-12);
        assert!((ls.stderr[0] - (rss / 3.0 / 30.0).sqrt()).abs() < 1e-12);
        assert!((ls.residual_rms - (rss / 4.0).sqrt()).abs() < 1e-12);
        assert!(least_squares(&x.rows(0, 1).into_owned(), &y.rows(0, 1).into_owned()).is_none());
    }

    #[test]
    fn interpolation_follows_the_arc_and_refuses_gaps() {
        let p0 = Pose2::new(1.0, 2.0, 0.5);
        let step = Twist2::new(0.2, -0.1, 0.4);
        let p1 = p0.exp(step);
        let track = vec![(1_000, p0), (2_000, p1), (2_000 + MAX_GAP_NS + 1, p1)];
        let mid = interpolate(&track, 1_500).unwrap();
        let half = p0.exp(Twist2::new(0.1, -0.05, 0.2));
        assert!((mid.x - half.x).abs() < 1e-12 && (mid.y - half.y).abs() < 1e-12);
        assert!((mid.heading - half.heading).abs() < 1e-12);
        assert_eq!(interpolate(&track, 1_000), Some(p0));
        assert_eq!(interpolate(&track, 999), None);
        assert_eq!(interpolate(&track, 3_000), None);
    }
}
