//! What [`calibrate`](super::calibrate) returns: the per-axis fits, the logged and fitted
//! `[geometry]` values with their standard errors, the pods' fits, and their rendering for
//! people (`Display`) and for a configuration file (the lines to paste).

use std::fmt;

use firmware::Config;
use firmware::config::Geometry;
use serde::Serialize;

use super::pods::{self, PodFit};
use drivelog::ReadReport;

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

impl GeometryValues {
    /// The values of `geometry`, as f64; `None` for a general layout (no lx, ly, radius).
    #[must_use]
    pub fn of(geometry: &Geometry) -> Option<Self> {
        let Geometry::Standard {
            lx,
            ly,
            wheel_radius,
            ..
        } = *geometry
        else {
            return None;
        };
        let k = geometry.effectiveness();
        Some(Self {
            lx: f64::from(lx),
            ly: f64::from(ly),
            wheel_radius: f64::from(wheel_radius),
            forward_effectiveness: f64::from(k.kx),
            lateral_effectiveness: f64::from(k.ky),
            yaw_effectiveness: f64::from(k.kw),
        })
    }
}

/// What [`calibrate`](super::calibrate) found.
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
