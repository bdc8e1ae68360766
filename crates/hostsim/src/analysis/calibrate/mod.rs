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
//!
//! The parts: `read` takes the log apart, `windows` cuts it into the fit's windows, `fit`
//! solves for the corrections and the refined values, `pods` fits the tracking pods, `report`
//! holds and renders the result, `error` names the refusals.

use std::path::Path;

use firmware::Config;
use kinematics::Twist2;

mod error;
mod fit;
mod pods;
mod read;
mod report;
mod windows;

pub use error::{CalibrateError, MissingMotion};
pub use pods::{PodFit, PodValues};
pub use report::{AxisFit, Calibration, Estimate, GeometryValues};

use read::Track;
use windows::{Window, pod_windows, steady_windows, wheel_odometry, windows};

/// The default reference: the simulator's ground truth.
pub const GROUND_TRUTH: &str = "/ground_truth/odom";

/// The least forward travel, and sideways travel, a log must have, m.
pub const MIN_TRAVEL_M: f64 = 0.5;

/// The least turning a log must have, rad (one turn).
pub const MIN_TURN_RAD: f64 = std::f64::consts::TAU;

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

/// Calibrates from the log at `path` (see `docs/simulator.md`, section "Calibration").
///
/// # Errors
/// [`CalibrateError`] naming what is missing or wrong; a damaged log is not an error (it is
/// calibrated from its complete part: [`Calibration::read`]).
pub fn calibrate(path: &Path, options: &Options) -> Result<Calibration, CalibrateError> {
    let bytes = drivelog::read::read_log_file(path)
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
    let (d, read) = read::read_log(bytes, reference)?;
    let text = d.config.as_deref().ok_or(CalibrateError::NoConfig)?;
    let config = Config::from_toml_str(text).map_err(|e| CalibrateError::Config(e.to_string()))?;
    let logged = GeometryValues::of(&config.geometry).ok_or(CalibrateError::GeneralLayout)?;
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
        return Err(no_overlap(
            reference,
            moving.len(),
            options.window_s,
            &track,
            &reference_track,
        ));
    }
    let travel = fit::travel(&moving);
    let configured_pods = config.odometry.pods;
    let pod_windows = pod_windows(configured_pods.len(), &d.joints, &steady)?;
    check_motion(travel, configured_pods.as_slice(), &pod_windows)?;
    let axes = fit::axes(&moving, travel)?;
    let fitted = fit::geometry(&logged, &axes);
    let pod_fits = pods::fit(configured_pods.as_slice(), &pod_windows)?;
    let calibrated = fit::refined_config(config, &fitted.values, &pod_fits)?;
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
        fitted: fitted.values,
        wheel_radius: fitted.wheel_radius,
        lx_plus_ly: fitted.lx_plus_ly,
        lateral_effectiveness: fitted.lateral_effectiveness,
        pods: pod_fits,
        config: calibrated,
        read,
    })
}

/// The refusal of a log whose odometry and reference overlap in fewer than three windows.
fn no_overlap(
    reference: &str,
    windows: usize,
    window_s: f64,
    odometry: &Track,
    reference_track: &Track,
) -> CalibrateError {
    let span = |t: &Track| match (t.first(), t.last()) {
        (Some(a), Some(b)) => format!("{:.3}..{:.3} s", a.0 as f64 * 1e-9, b.0 as f64 * 1e-9),
        _ => "none".to_string(),
    };
    CalibrateError::NoOverlap {
        topic: reference.to_string(),
        windows,
        window_s,
        odometry: span(odometry),
        reference: span(reference_track),
    }
}

/// Refuses a log without the motion a value needs: the body's `travel` along each axis over
/// the fit's windows, and each pod's along and across its direction.
///
/// # Errors
/// [`CalibrateError::MissingMotion`] naming every motion that is short.
fn check_motion(
    travel: [f64; 3],
    configured_pods: &[firmware::config::PodConfig],
    pod_windows: &[pods::PodWindow],
) -> Result<(), CalibrateError> {
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
    missing.extend(pods::missing(configured_pods, pod_windows));
    if !missing.is_empty() {
        return Err(CalibrateError::MissingMotion(missing));
    }
    Ok(())
}
