//! The tracking pods' part of `hostsim calibrate`: each pod's radius, direction and lever
//! fitted from its logged wheel angle against the reference's body increments.
//!
//! A pod at `(x, y)` counting up along `φ` on a wheel of radius `r` turns, for a body
//! increment `(dx, dy, dθ)`, by
//!
//! ```text
//! Δα = a dx + b dy + c dθ,    a = cos φ / r,  b = sin φ / r,  c = (x sin φ − y cos φ) / r
//! ```
//!
//! Over the fit's windows this is a linear regression of `Δα` on the reference increments,
//! three unknowns per pod; `r = 1 / √(a² + b²)`, `φ = atan2(b, a)` and the lever
//! `m = c r = x sin φ − y cos φ` (the signed distance of the pod's line of action from the
//! origin) follow, their standard errors propagated to first order from the regression's
//! covariance. Where along its line of action a pod touches the floor changes no count: it
//! is not observable. Specified in `docs/simulator.md`, section "Calibration".

use std::fmt;

use firmware::config::PodConfig;
use kinematics::Twist2;
use nalgebra::{DMatrix, DVector, RowVector3};
use serde::Serialize;

use super::fit::least_squares;
use super::{CalibrateError, Estimate, MIN_TRAVEL_M, MIN_TURN_RAD, MissingMotion};

/// One window of the pods' fit: the reference's body increment and each pod's angle
/// increment over it.
#[derive(Debug, Clone)]
pub(super) struct PodWindow {
    /// The reference's body-frame increment (SE(2) logarithm), m, m, rad.
    pub reference: Twist2<f64>,
    /// Each configured pod's wheel-angle increment, rad, in the configuration's order.
    pub angles: Vec<f64>,
}

/// A pod's `[[odometry.pods]]` values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PodValues {
    /// Contact point, forward, m.
    pub x: f64,
    /// Contact point, leftward, m.
    pub y: f64,
    /// The direction in which it counts up, ° counter-clockwise from forward.
    pub direction_deg: f64,
    /// Wheel radius, m.
    pub radius: f64,
    /// Encoder counts per wheel turn (never fitted: the count's scale is the radius's).
    pub counts_per_turn: u32,
}

impl PodValues {
    fn of(p: &PodConfig) -> Self {
        Self {
            x: f64::from(p.x),
            y: f64::from(p.y),
            direction_deg: f64::from(p.direction_deg),
            radius: f64::from(p.radius),
            counts_per_turn: p.counts_per_turn,
        }
    }

    /// The lever `x sin φ − y cos φ`, m: the signed distance of the pod's line of action
    /// from the origin (positive when a counter-clockwise turn turns the pod forward).
    #[must_use]
    pub fn lever(&self) -> f64 {
        let (s, c) = self.direction_deg.to_radians().sin_cos();
        self.x * s - self.y * c
    }

    /// As the configuration holds it (f32).
    #[allow(clippy::cast_possible_truncation)]
    fn to_config(self) -> PodConfig {
        PodConfig {
            x: self.x as f32,
            y: self.y as f32,
            direction_deg: self.direction_deg as f32,
            radius: self.radius as f32,
            counts_per_turn: self.counts_per_turn,
        }
    }
}

/// One pod's fit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PodFit {
    /// Its index in the configuration (`pod0` in `/joint_states` is 0).
    pub pod: usize,
    /// The reference's travel along the pod's configured direction over the windows (sum of
    /// |increment|), m: what determines its radius.
    pub travel_along: f64,
    /// The reference's travel across it, m: what determines its direction.
    pub travel_across: f64,
    /// The reference's turning, rad: what determines its lever.
    pub turn: f64,
    /// The regression's coefficients `[a, b, c]`: rad/m, rad/m, rad/rad.
    pub coefficients: [f64; 3],
    /// RMS of the per-window residuals, rad of the pod's wheel.
    pub residual_rms: f64,
    /// Fitted radius, m.
    pub radius: Estimate,
    /// Fitted radius over the configured one: how much further the pod rolls per count than
    /// configured (1.01: 1 % further).
    pub scale: Estimate,
    /// Fitted direction, ° (within 180° of the configured one).
    pub direction_deg: Estimate,
    /// Fitted lever `x sin φ − y cos φ`, m.
    pub lever: Estimate,
    /// The configured lever, m.
    pub logged_lever: f64,
    /// The configured values.
    pub logged: PodValues,
    /// The refined values as written (rounded: x and y to the µm, the radius to 0.1 µm, the
    /// direction to 1e-4°): radius and direction fitted, the configured contact point moved
    /// along the fitted line's normal until its lever is the fitted one, counts per turn
    /// unchanged.
    pub fitted: PodValues,
}

/// The motion a pod needs, from its configured direction `φ0` (rad): the body motion along
/// it and across it, named after the nearer body axis.
fn motions(phi0: f64) -> (&'static str, &'static str) {
    if phi0.cos().abs() >= phi0.sin().abs() {
        ("forward travel", "strafe")
    } else {
        ("strafe", "forward travel")
    }
}

/// The reference's travel along and across each pod's configured direction and its turning
/// over `windows`: `[along, across, turn]` per pod.
fn travel(pods: &[PodConfig], windows: &[PodWindow]) -> Vec<[f64; 3]> {
    pods.iter()
        .map(|p| {
            let (s, c) = f64::from(p.direction_deg).to_radians().sin_cos();
            windows.iter().fold([0.0; 3], |acc, w| {
                let u = &w.reference;
                [
                    acc[0] + (c * u.dx + s * u.dy).abs(),
                    acc[1] + (-s * u.dx + c * u.dy).abs(),
                    acc[2] + u.dtheta.abs(),
                ]
            })
        })
        .collect()
}

/// What the windows lack to determine each pod: at least [`MIN_TRAVEL_M`] of the reference's
/// travel along the pod's direction (its radius) and across it (its direction), and
/// [`MIN_TURN_RAD`] of turning (its lever).
pub(super) fn missing(pods: &[PodConfig], windows: &[PodWindow]) -> Vec<MissingMotion> {
    let mut out = Vec::new();
    for (i, (p, [along, across, turn])) in pods.iter().zip(travel(pods, windows)).enumerate() {
        let (along_motion, across_motion) = motions(f64::from(p.direction_deg).to_radians());
        for (motion, have, need, value) in [
            (along_motion, along, MIN_TRAVEL_M, "radius"),
            (across_motion, across, MIN_TRAVEL_M, "direction_deg"),
            ("rotation", turn, MIN_TURN_RAD, "lever"),
        ] {
            if have < need {
                out.push(MissingMotion {
                    motion,
                    have,
                    need,
                    value,
                    pod: Some(i),
                });
            }
        }
    }
    out
}

/// A pod's [`MissingMotion`] as text (`m.pod` is `Some`).
pub(super) fn describe(m: &MissingMotion, pod: usize, f: &mut fmt::Formatter<'_>) -> fmt::Result {
    let advice = match m.motion {
        "rotation" => "spin on the spot both ways",
        "strafe" => "drive sideways both ways",
        _ => "drive forward and back",
    };
    if m.motion == "rotation" {
        write!(
            f,
            "pod {pod}: {:.1}° of turning at a steady speed in this log (needs >= {:.0}°): \
             cannot fit its {}; {advice}",
            m.have.to_degrees(),
            m.need.to_degrees(),
            m.value
        )
    } else {
        let way = if m.value == "radius" {
            "along"
        } else {
            "across"
        };
        write!(
            f,
            "pod {pod}: {:.2} m of travel {way} its direction at a steady speed in this log \
             (needs >= {:.1} m): cannot fit its {}; {advice}",
            m.have, m.need, m.value
        )
    }
}

/// `deg` wrapped into `(-180, 180]`.
fn wrap_deg(deg: f64) -> f64 {
    let w = deg.rem_euclid(360.0);
    if w > 180.0 { w - 360.0 } else { w }
}

/// Fits each pod of `pods` over `windows` (the refusal, [`missing`], has passed).
///
/// # Errors
/// [`CalibrateError::Refused`] for a singular regression.
pub(super) fn fit(
    pods: &[PodConfig],
    windows: &[PodWindow],
) -> Result<Vec<PodFit>, CalibrateError> {
    let n = windows.len();
    let design = DMatrix::from_fn(n, 3, |row, col| {
        let u = &windows[row].reference;
        [u.dx, u.dy, u.dtheta][col]
    });
    // `+ 0.0`: a zero written as `0.0`, never `-0.0`.
    let round = |x: f64, step: f64| (x / step).round() * step + 0.0;
    pods.iter()
        .zip(travel(pods, windows))
        .enumerate()
        .map(|(i, (p, [along, across, turn]))| {
            let y = DVector::from_iterator(n, windows.iter().map(|w| w.angles[i]));
            let ls = least_squares(&design, &y)
                .ok_or_else(|| CalibrateError::Refused(format!("pod {i}'s fit is singular")))?;
            let [a, b, c] = [0, 1, 2].map(|k| ls.coefficients[k]);
            let q = a * a + b * b;
            let r = 1.0 / q.sqrt();
            let phi = b.atan2(a);
            let lever = c * r;
            let r3 = r * r * r;
            // First-order propagation of the coefficients' covariance: √(J Σ Jᵀ).
            let stderr = |j: RowVector3<f64>| (j * &ls.covariance * j.transpose())[(0, 0)].sqrt();
            let se_r = stderr(RowVector3::new(-a * r3, -b * r3, 0.0));
            let se_phi = stderr(RowVector3::new(-b / q, a / q, 0.0));
            let se_lever = stderr(RowVector3::new(-c * a * r3, -c * b * r3, r));
            let logged = PodValues::of(p);
            let direction_deg =
                logged.direction_deg + wrap_deg(phi.to_degrees() - logged.direction_deg);
            // The configured point moved along the fitted line's normal n = (sin φ, −cos φ)
            // until its lever p·n is the fitted one.
            let fitted_deg = round(direction_deg, 1e-4);
            let (s, cs) = fitted_deg.to_radians().sin_cos();
            let shift = lever - (logged.x * s - logged.y * cs);
            let fitted = PodValues {
                x: round(logged.x + shift * s, 1e-6),
                y: round(logged.y - shift * cs, 1e-6),
                direction_deg: fitted_deg,
                radius: round(r, 1e-7),
                counts_per_turn: logged.counts_per_turn,
            };
            Ok(PodFit {
                pod: i,
                travel_along: along,
                travel_across: across,
                turn,
                coefficients: [a, b, c],
                residual_rms: ls.residual_rms,
                radius: Estimate {
                    value: r,
                    stderr: se_r,
                },
                scale: Estimate {
                    value: r / logged.radius,
                    stderr: se_r / logged.radius,
                },
                direction_deg: Estimate {
                    value: direction_deg,
                    stderr: se_phi.to_degrees(),
                },
                lever: Estimate {
                    value: lever,
                    stderr: se_lever,
                },
                logged_lever: logged.lever(),
                logged,
                fitted,
            })
        })
        .collect()
}

/// The configured pods with the fitted values of `fits`.
pub(super) fn refined(fits: &[PodFit]) -> Vec<PodConfig> {
    fits.iter().map(|f| f.fitted.to_config()).collect()
}

/// The `[[odometry.pods]]` tables to paste, in order.
pub(super) fn lines(fits: &[PodFit]) -> String {
    let mut out = String::new();
    for f in fits {
        let p = f.fitted.to_config();
        out.push_str(&format!(
            "[[odometry.pods]]  # pod {}\nx = {:?}\ny = {:?}\ndirection_deg = {:?}\nradius = \
             {:?}\ncounts_per_turn = {}\n",
            f.pod, p.x, p.y, p.direction_deg, p.radius, p.counts_per_turn
        ));
    }
    out
}

/// The pods' part of the report.
pub(super) fn report(fits: &[PodFit], f: &mut fmt::Formatter<'_>) -> fmt::Result {
    writeln!(
        f,
        "pods, from their angles in /joint_states (logged -> fitted ± standard error):"
    )?;
    for p in fits {
        let l = &p.logged;
        writeln!(
            f,
            "  pod {}  radius         {:.7} m -> {:.7} m ± {:.1e} m  (scale {:+.4} % ± {:.4} %)",
            p.pod,
            l.radius,
            p.radius.value,
            p.radius.stderr,
            (p.scale.value - 1.0) * 100.0,
            p.scale.stderr * 100.0
        )?;
        writeln!(
            f,
            "         direction_deg  {:.4}° -> {:.4}° ± {:.4}°",
            l.direction_deg, p.direction_deg.value, p.direction_deg.stderr
        )?;
        writeln!(
            f,
            "         lever          {:.3} mm -> {:.3} mm ± {:.3} mm",
            p.logged_lever * 1e3,
            p.lever.value * 1e3,
            p.lever.stderr * 1e3
        )?;
        writeln!(
            f,
            "         travel along {:.3} m, across {:.3} m, turning {:.1}°; residual {:.3} \
             mrad (RMS per window)",
            p.travel_along,
            p.travel_across,
            p.turn.to_degrees(),
            p.residual_rms * 1e3
        )?;
    }
    writeln!(
        f,
        "  (lever: the distance of the pod's line of action from the origin, x sin φ − y cos \
         φ; where along that line the pod touches is unobservable, so the refined x, y are \
         the configured point moved across the line)"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Windows of exact arcs of known pods, with a deterministic disturbance of ±`noise` rad:
    /// the fit gives the pods back, and the propagated standard errors match the spread.
    #[test]
    fn exact_arcs_give_the_pods_back() {
        let truth = [
            PodConfig {
                x: 0.01,
                y: 0.11,
                direction_deg: 0.4,
                radius: 0.0243,
                counts_per_turn: 2000,
            },
            PodConfig {
                x: 0.12,
                y: 0.003,
                direction_deg: 90.6,
                radius: 0.0238,
                counts_per_turn: 2000,
            },
        ];
        let mut windows = Vec::new();
        let mut k = 0.0f64;
        for u in [
            Twist2::new(0.05, 0.0, 0.0),
            Twist2::new(-0.05, 0.0, 0.0),
            Twist2::new(0.0, 0.035, 0.0),
            Twist2::new(0.0, -0.035, 0.0),
            Twist2::new(0.0, 0.0, 0.2),
            Twist2::new(0.0, 0.0, -0.2),
        ] {
            for _ in 0..20 {
                k += 1.0;
                let wobble = 1e-6 * (k * 1.7).sin();
                let angles = truth
                    .iter()
                    .map(|p| {
                        let g = kinematics::PodGeometry {
                            x: f64::from(p.x),
                            y: f64::from(p.y),
                            direction: f64::from(p.direction_deg).to_radians(),
                        };
                        g.arc(u) / f64::from(p.radius) + wobble
                    })
                    .collect();
                windows.push(PodWindow {
                    reference: u,
                    angles,
                });
            }
        }
        let nominal = [
            PodConfig {
                x: 0.0,
                y: 0.11,
                direction_deg: 0.0,
                radius: 0.024,
                counts_per_turn: 2000,
            },
            PodConfig {
                x: 0.12,
                y: 0.0,
                direction_deg: 90.0,
                radius: 0.024,
                counts_per_turn: 2000,
            },
        ];
        assert!(missing(&nominal, &windows).is_empty());
        let fits = fit(&nominal, &windows).unwrap();
        for (f, t) in fits.iter().zip(&truth) {
            let t = PodValues::of(t);
            assert!((f.radius.value - t.radius).abs() < 1e-8, "{f:?}");
            assert!(
                (f.direction_deg.value - t.direction_deg).abs() < 1e-4,
                "{f:?}"
            );
            assert!((f.lever.value - t.lever()).abs() < 1e-6, "{f:?}");
            // The refined point lies on the true line of action.
            assert!((f.fitted.lever() - t.lever()).abs() < 2e-6, "{f:?}");
            for e in [f.radius, f.direction_deg, f.lever] {
                assert!(e.stderr > 0.0 && e.stderr.is_finite(), "{f:?}");
            }
        }
        // Only forward motion: no direction for the forward pod, no radius for the sideways
        // one, no lever for either.
        let forward: Vec<PodWindow> = windows[..40].to_vec();
        let m: Vec<(Option<usize>, &str, &str)> = missing(&nominal, &forward)
            .iter()
            .map(|m| (m.pod, m.motion, m.value))
            .collect();
        assert_eq!(
            m,
            [
                (Some(0), "strafe", "direction_deg"),
                (Some(0), "rotation", "lever"),
                (Some(1), "strafe", "radius"),
                (Some(1), "rotation", "lever"),
            ]
        );
    }

    #[test]
    fn directions_wrap_near_the_configured_one() {
        assert_eq!(wrap_deg(190.0), -170.0);
        assert_eq!(wrap_deg(-190.0), 170.0);
        assert_eq!(wrap_deg(180.0), 180.0);
    }
}
