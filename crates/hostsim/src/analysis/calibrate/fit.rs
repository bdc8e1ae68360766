//! The fit: per axis, the reference's increments against the odometry's by least squares,
//! and from the three corrections the refined `[geometry]` values and configuration.

use firmware::Config;
use firmware::config::{Geometry, Pods};
use kinematics::Twist2;
use nalgebra::{DMatrix, DVector};

use super::{AxisFit, CalibrateError, Estimate, GeometryValues, PodFit, pods};

/// The windows' (odometry, reference) body-frame increments.
pub(super) type Increments = [(Twist2<f64>, Twist2<f64>)];

/// Component `axis` (0 forward, 1 lateral, 2 yaw) of `t`.
fn component(t: &Twist2<f64>, axis: usize) -> f64 {
    [t.dx, t.dy, t.dtheta][axis]
}

/// The odometry's travel along each axis over the windows (sum of |increment|), m or rad.
pub(super) fn travel(moving: &Increments) -> [f64; 3] {
    core::array::from_fn(|axis| moving.iter().map(|(o, _)| component(o, axis).abs()).sum())
}

/// Each axis's correction of the logged model (reference increment per odometry
/// increment), with its standard error and residual.
///
/// # Errors
/// [`CalibrateError::Refused`] for a singular fit, [`CalibrateError::Opposed`] for a
/// reference that moves against the odometry.
pub(super) fn axes(moving: &Increments, travel: [f64; 3]) -> Result<[AxisFit; 3], CalibrateError> {
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
    Ok(axes)
}

/// The refined `[geometry]`: the values as written and the estimates they are rounded from.
pub(super) struct Fitted {
    /// Rounded as written: lengths to the µm, factors to 1e-5.
    pub values: GeometryValues,
    pub wheel_radius: Estimate,
    pub lx_plus_ly: Estimate,
    pub lateral_effectiveness: Estimate,
}

/// The `[geometry]` the per-axis corrections `axes` give from the `logged` values, with
/// forward and yaw effectiveness 1 (`docs/simulator.md`, section "Calibration").
pub(super) fn geometry(logged: &GeometryValues, axes: &[AxisFit; 3]) -> Fitted {
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
    Fitted {
        values: fitted,
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
    }
}

/// The logged `config` with the `fitted` geometry and the pods' fits, validated.
///
/// # Errors
/// [`CalibrateError::Refused`] if the firmware's validation refuses it.
pub(super) fn refined_config(
    config: Config,
    fitted: &GeometryValues,
    pod_fits: &[PodFit],
) -> Result<Config, CalibrateError> {
    let mut calibrated = config;
    if !pod_fits.is_empty() {
        calibrated.odometry.pods = Pods::new(&pods::refined(pod_fits))
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
    Ok(calibrated)
}

/// A least-squares solution.
pub(super) struct LeastSquares {
    pub(super) coefficients: DVector<f64>,
    pub(super) stderr: DVector<f64>,
    /// The coefficients' covariance `σ² (XᵀX)⁻¹`.
    pub(super) covariance: DMatrix<f64>,
    pub(super) residual_rms: f64,
}

/// Least squares `y ≈ X β` (SVD): the coefficients, their covariance and standard errors
/// (`σ² (XᵀX)⁻¹`, `σ²` the residual variance with `n − p` degrees of freedom) and the RMS
/// residual. `None` with no more rows than columns or a singular design.
pub(super) fn least_squares(x: &DMatrix<f64>, y: &DVector<f64>) -> Option<LeastSquares> {
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
}
