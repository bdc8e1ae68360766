//! Tracking pods ("dead wheels"): the body increment from free-rolling omni wheels.
//!
//! A tracking pod is an unpowered omni wheel with an encoder, sprung onto the floor. Its rollers
//! let it slide freely across its own direction, so it measures one thing: how far its contact
//! point travelled along its direction `u = (cos φ, sin φ)` (φ from the body x axis,
//! counter-clockwise). For a pod at `(x, y)` and a body increment `(dx, dy, dθ)` (body frame at
//! the start of the step) the arc is the contact point's motion `(dx − y dθ, dy + x dθ)`
//! projected on `u`:
//!
//! ```text
//! s = cos φ (dx − y dθ) + sin φ (dy + x dθ) = cos φ dx + sin φ dy + (x sin φ − y cos φ) dθ
//! ```
//!
//! The last coefficient is the moment arm of the pod's line of action about the origin. Three
//! pods give a 3 × 3 system ([`PodLocalizer::three`]); two pods and a heading increment from
//! elsewhere (a gyro) a 2 × 2 one in `(dx, dy)` ([`PodLocalizer::two`]). Both are inverted once,
//! at construction; a step is then 9 or 6 multiply-adds, with no division and no branch. Three
//! pods cannot see every motion if their lines of action are all parallel (a translation
//! across them) or meet in one point (a rotation about it); two, if their directions are parallel.
//!
//! Road Runner's `ThreeDeadWheelLocalizer` (two pods with φ = 0, one with φ = 90°) and
//! `TwoDeadWheelLocalizer` are this model for those layouts, with one sign to mind: its
//! `par0YTicks`, `par1YTicks` and `parYTicks` are **minus** the pods' `y` here. Its formulas
//! invert `par = dx + parY dθ`, while a forward-measuring pod at `y > 0` (left) rolls *back* in
//! a counter-clockwise turn, `par = dx − y dθ`; its tuner fits the value from data, so a left
//! pod gets a negative `parYTicks`. Its `perpXTicks` is the perpendicular pod's `x`, as is.
//!
//! Arcs are in metres: a pod's angle increment (e.g. from an [`Encoder`](crate::Encoder)) times
//! its wheel radius. For motion at constant body velocity over the step the linear model is
//! exact, and so is the pose when the increment is integrated along that arc, which
//! [`Odometry::apply`](crate::Odometry::apply) does:
//!
//! ```
//! use kinematics::{Odometry, PodGeometry, Pose2, ThreePodLocalizer};
//!
//! let half_pi = core::f64::consts::FRAC_PI_2;
//! let pods = ThreePodLocalizer::three([
//!     PodGeometry::new(0.0, 0.15, 0.0),     // left, measuring forward travel
//!     PodGeometry::new(0.0, -0.15, 0.0),    // right, forward
//!     PodGeometry::new(-0.10, 0.0, half_pi), // behind the centre, measuring leftward travel
//! ])?;
//! let mut odometry = Odometry::new(Pose2::default());
//! let pose = odometry.apply(pods.increment([0.010, 0.012, 0.003])); // arcs, m
//! # assert!((pose.heading - (0.010 - 0.012) / -0.30).abs() < 1e-12);
//! # Ok::<(), kinematics::PodLayoutError>(())
//! ```

use crate::error::PodLayoutError;
use crate::real::Real;
use crate::types::Twist2;

/// Where a tracking pod sits and which way it measures, in the body frame (x forward, y left).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PodGeometry<T> {
    /// Contact point x, m.
    pub x: T,
    /// Contact point y, m.
    pub y: T,
    /// Direction φ of positive travel from the body x axis, rad, counter-clockwise: 0 for a
    /// pod that counts up when the robot drives forward, π/2 for one that counts up when it
    /// moves to the left. A pod that counts the other way has φ + π.
    pub direction: T,
}

impl<T: Real> PodGeometry<T> {
    /// A pod at `(x, y)` (m) measuring along `direction` (rad).
    #[must_use]
    pub const fn new(x: T, y: T, direction: T) -> Self {
        Self { x, y, direction }
    }

    /// The forward model: the arc (m) this pod measures when the body moves by `twist`,
    /// `cos φ (dx − y dθ) + sin φ (dy + x dθ)`. One `sin_cos` per call; for a whole layout,
    /// [`PodLocalizer::arcs`] uses the precomputed coefficients.
    #[must_use]
    pub fn arc(&self, twist: Twist2<T>) -> T {
        let (s, c) = self.direction.sin_cos_libm();
        c * (twist.dx - self.y * twist.dtheta) + s * (twist.dy + self.x * twist.dtheta)
    }

    /// Error if a parameter is NaN or infinite.
    fn check(&self, pod: usize) -> Result<(), PodLayoutError> {
        for (field, v) in [("x", self.x), ("y", self.y), ("direction", self.direction)] {
            if !v.finite() {
                return Err(PodLayoutError::NonFinite { pod, field });
            }
        }
        Ok(())
    }
}

/// The body increment from two or three tracking pods, precomputed for their layout.
///
/// Build one with [`three`](PodLocalizer::three) or [`two`](PodLocalizer::two) (aliases
/// [`ThreePodLocalizer`], [`TwoPodLocalizer`]); each step,
/// [`increment`](PodLocalizer::increment) turns the pods' arcs (m, in layout order) into the
/// [`Twist2`] for [`Odometry::apply`](crate::Odometry::apply). Construction validates the
/// layout and inverts its model once (in `f64`, then rounded to `T`); every method after that
/// is a pure `&self` product with no allocation, division or branch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PodLocalizer<T: Real, const N: usize> {
    pods: [PodGeometry<T>; N],
    /// Row i: `(cos φ_i, sin φ_i, x_i sin φ_i − y_i cos φ_i)`, arc = row · (dx, dy, dθ).
    model: [[T; 3]; N],
    /// Twist = `solver` · (s_0, s_1, s_2) for three pods, · (s_0, s_1, dθ) for two.
    solver: [[T; 3]; 3],
    condition: T,
}

/// [`PodLocalizer`] for three pods: the heading increment comes from the pods.
pub type ThreePodLocalizer<T> = PodLocalizer<T, 3>;

/// [`PodLocalizer`] for two pods: the heading increment comes from elsewhere (a gyro).
pub type TwoPodLocalizer<T> = PodLocalizer<T, 2>;

impl<T: Real, const N: usize> PodLocalizer<T, N> {
    /// The pod geometry this localizer was built from.
    #[must_use]
    pub const fn pods(&self) -> &[PodGeometry<T>; N] {
        &self.pods
    }

    /// The model as applied by [`arcs`](Self::arcs): row `i` is
    /// `(cos φ_i, sin φ_i, x_i sin φ_i − y_i cos φ_i)`, so that pod `i`'s arc is the row times
    /// `(dx, dy, dθ)`. The third entry (m) is the moment arm of the pod's line of action about
    /// the origin, computed in `f64` and rounded once.
    #[must_use]
    pub const fn model(&self) -> &[[T; 3]; N] {
        &self.model
    }

    /// The precomputed inverse as applied by [`increment`](PodLocalizer::increment):
    /// `(dx, dy, dθ)` = this matrix times `(s_0, s_1, s_2)` for three pods, times
    /// `(s_0, s_1, dθ)` for two (whose last row is then `(0, 0, 1)`).
    #[must_use]
    pub const fn solver(&self) -> &[[T; 3]; 3] {
        &self.solver
    }

    /// The forward model for the whole layout: the arc (m) each pod measures when the body
    /// moves by `twist` (what a simulator feeds the encoders). `increment` inverts it.
    #[must_use]
    #[inline]
    pub fn arcs(&self, twist: Twist2<T>) -> [T; N] {
        self.model
            .map(|r| r[0] * twist.dx + r[1] * twist.dy + r[2] * twist.dtheta)
    }

    /// Frobenius condition number `‖M‖_F ‖M⁻¹‖_F` of the layout's matrix, computed in `f64`
    /// at construction; never above [`max_condition_number`](Self::max_condition_number).
    ///
    /// For three pods `M` is the 3 × 3 model with its moment-arm column divided by the RMS
    /// distance of the pods from the origin (so the figure has no units); for two, the 2 × 2
    /// matrix of the directions, whose figure is `2 / |sin(φ_1 − φ_0)|` (2 for perpendicular
    /// pods). It is at least `N`, bounds the 2-norm condition number from above and exceeds
    /// it by at most a factor `N`: a relative error in the arcs (noise, slip, a wrong radius)
    /// is amplified at most this much in the increment.
    #[must_use]
    pub const fn condition_number(&self) -> T {
        self.condition
    }

    /// The largest condition number accepted: `1 / (8 √ε)` of `T`, about 362 in `f32` and
    /// 8.4e6 in `f64`, the same limit as
    /// [`MecanumKinematics::max_condition_number`](crate::MecanumKinematics::max_condition_number).
    ///
    /// A 2-norm condition number beyond it means the smallest singular value of the layout's
    /// matrix is, squared, within `64 ε` of the largest: the layout is singular to within the
    /// type's precision, and the increment (accurate to a few `condition · ε`) would lose more
    /// than about 4e-5 (`f32`) or 2e-9 (`f64`) relative. The figure tested, the Frobenius one
    /// ([`condition_number`](Self::condition_number)), is never below the 2-norm one, so the
    /// test errs on the safe side (by at most a factor `N`). For two pods the limit is reached
    /// at `|sin(φ_1 − φ_0)| = 16 √ε`: 5.5e-3 rad (0.32°) in `f32`, 2.4e-7 rad in `f64`.
    /// Unlike `det == 0`, the test is relative: it does not change with the units of the
    /// coordinates, and it refuses what rounding only makes look regular.
    #[must_use]
    pub fn max_condition_number() -> T {
        T::lit(max_condition(T::EPSILON.to_f64()))
    }

    /// Validates the pods and computes the model rows: `(c, s, m)` in `T`, and widened to
    /// `f64` with the moment-arm column divided by `length`, the layout's size (see
    /// [`rms_distance`]).
    fn rows(pods: &[PodGeometry<T>; N]) -> Result<Model<T, N>, PodLayoutError> {
        for (i, pod) in pods.iter().enumerate() {
            pod.check(i)?;
        }
        let length = rms_distance(pods);
        if !length.is_finite() {
            return Err(unrepresentable(f64::INFINITY));
        }
        let eps = T::EPSILON.to_f64();
        let mut model = [[T::zero(); 3]; N];
        let mut scaled = [[0.0_f64; 3]; N];
        for ((pod, row), scaled) in pods.iter().zip(&mut model).zip(&mut scaled) {
            let (s, c) = pod.direction.sin_cos_libm();
            let arm = pod.x.to_f64() * s.to_f64() - pod.y.to_f64() * c.to_f64();
            let rounded = T::lit(arm);
            // What T keeps of the moment arm, at the scale of the layout: an overflow (or an
            // arm already infinite in f64), or an underflow into T's subnormals, fails.
            let error = libm::fabs(rounded.to_f64() - arm) / length;
            let fits = rounded.finite() && error <= eps;
            if !fits {
                return Err(unrepresentable(error));
            }
            *row = [c, s, rounded];
            *scaled = [c.to_f64(), s.to_f64(), rounded.to_f64() / length];
        }
        Ok(Model {
            model,
            scaled,
            length,
        })
    }
}

/// The rows of a validated layout (see [`PodLocalizer::rows`]).
struct Model<T, const N: usize> {
    /// As stored, in `T`.
    model: [[T; 3]; N],
    /// Widened to `f64`, the moment-arm column divided by `length`.
    scaled: [[f64; 3]; N],
    /// RMS distance of the pods from the origin, m (1 if all are at the origin).
    length: f64,
}

impl<T: Real> PodLocalizer<T, 3> {
    /// The localizer for three pods: solves `A (dx, dy, dθ) = (s_0, s_1, s_2)`, with row `i`
    /// of `A` pod `i`'s row of the model (see the [module documentation](self)).
    ///
    /// # Errors
    /// [`PodLayoutError`] for a non-finite parameter
    /// ([`NonFinite`](PodLayoutError::NonFinite), naming the pod and the field), or a layout
    /// whose (scaled) matrix has a condition number above
    /// [`max_condition_number`](Self::max_condition_number): all three directions (nearly)
    /// parallel ([`AllParallel`](PodLayoutError::AllParallel)), or the three lines of action
    /// (nearly) meeting in a point ([`Concurrent`](PodLayoutError::Concurrent), naming it);
    /// or coordinates whose numbers overflow or underflow `T`
    /// ([`Unrepresentable`](PodLayoutError::Unrepresentable)). Two parallel pods and a third
    /// across them (Road Runner's layout) are fine.
    pub fn three(pods: [PodGeometry<T>; 3]) -> Result<Self, PodLayoutError> {
        let Model {
            model,
            scaled,
            length,
        } = Self::rows(&pods)?;
        let limit = max_condition(T::EPSILON.to_f64());
        let (inverse, condition) = inverse3(&scaled);
        let accepted = condition <= limit;
        if !accepted {
            return Err(classify(&scaled, length, condition, limit));
        }
        // A = M D⁻¹ with D = diag(1, 1, 1/length), so A⁻¹ = D M⁻¹: the dθ row over `length`.
        let mut solver = [[T::zero(); 3]; 3];
        for (i, (row, inv)) in solver.iter_mut().zip(inverse).enumerate() {
            let scale = if i == 2 { length } else { 1.0 };
            *row = inv.map(|v| T::lit(v / scale));
        }
        // What T holds of it: D⁻¹ (A⁻¹ rounded) times M must be I to the accuracy the
        // conditioning allows (an entry overflowed, or rounded to zero or a few digits, fails).
        let back = scale_solver(&solver, length);
        check_inverse::<T>(&back, &scaled, condition)?;
        Ok(Self {
            pods,
            model,
            solver,
            condition: T::lit(condition),
        })
    }

    /// The body increment (body frame at the start of the step) from the three pods' arcs
    /// (m, layout order): 9 multiply-adds. NaN or infinite arcs give a NaN or infinite twist.
    #[must_use]
    #[inline]
    pub fn increment(&self, arcs: [T; 3]) -> Twist2<T> {
        let f = &self.solver;
        let [a, b, c] = arcs;
        Twist2::new(
            f[0][0] * a + f[0][1] * b + f[0][2] * c,
            f[1][0] * a + f[1][1] * b + f[1][2] * c,
            f[2][0] * a + f[2][1] * b + f[2][2] * c,
        )
    }
}

impl<T: Real> PodLocalizer<T, 2> {
    /// The localizer for two pods and a heading increment from elsewhere (a gyro): solves
    /// `(cos φ_i, sin φ_i) · (dx, dy) = s_i − dθ (x_i sin φ_i − y_i cos φ_i)` for `i = 0, 1`.
    /// The pods may sit anywhere, even at one point; only their directions matter for
    /// solvability.
    ///
    /// # Errors
    /// [`PodLayoutError`] for a non-finite parameter
    /// ([`NonFinite`](PodLayoutError::NonFinite)), directions (nearly) parallel or
    /// anti-parallel ([`Parallel`](PodLayoutError::Parallel): condition number
    /// `2 / |sin(φ_1 − φ_0)|` above [`max_condition_number`](Self::max_condition_number)),
    /// or coordinates whose numbers overflow or underflow `T`
    /// ([`Unrepresentable`](PodLayoutError::Unrepresentable)).
    pub fn two(pods: [PodGeometry<T>; 2]) -> Result<Self, PodLayoutError> {
        let Model {
            model,
            scaled,
            length,
        } = Self::rows(&pods)?;
        let limit = max_condition(T::EPSILON.to_f64());
        let [[c0, s0, m0], [c1, s1, m1]] = scaled;
        let (condition, cross, dot) = pair_condition(&scaled[0], &scaled[1]);
        let accepted = condition <= limit;
        if !accepted {
            return Err(PodLayoutError::Parallel {
                first: 0,
                second: 1,
                angle: libm::atan2(cross, dot),
                condition,
            });
        }
        // B = [c0 s0; c1 s1], B⁻¹ = [s1 −s0; −c1 c0] / det; the dθ column is −B⁻¹ m.
        let det = cross;
        let b = [[s1 / det, -s0 / det], [-c1 / det, c0 / det]];
        let k = [
            (b[0][0] * m0 + b[0][1] * m1) * length,
            (b[1][0] * m0 + b[1][1] * m1) * length,
        ];
        let solver = [
            [T::lit(b[0][0]), T::lit(b[0][1]), T::lit(-k[0])],
            [T::lit(b[1][0]), T::lit(b[1][1]), T::lit(-k[1])],
            [T::zero(), T::zero(), T::one()],
        ];
        // As for three pods, with the gyro row completing the 3 × 3 map (dx, dy, dθ) ↦
        // (s_0, s_1, dθ). Scaled, `E A D` with `D = diag(1, 1, 1/length)` and
        // `E = diag(1, 1, length)` (dθ in and out measured as `length · dθ`), its inverse is
        // `D⁻¹ F E⁻¹`: the dθ column of the rounded solver over `length`, the last row as is.
        let map = [scaled[0], scaled[1], [0.0, 0.0, 1.0]];
        let mut back = solver.map(|r| r.map(Real::to_f64));
        back[0][2] /= length;
        back[1][2] /= length;
        check_inverse::<T>(&back, &map, condition)?;
        Ok(Self {
            pods,
            model,
            solver,
            condition: T::lit(condition),
        })
    }

    /// The body increment (body frame at the start of the step) from the two pods' arcs (m,
    /// layout order) and the heading increment `dtheta` (rad, counter-clockwise, e.g. the
    /// gyro's yaw change over the step), which is returned as the twist's `dtheta`: 6
    /// multiply-adds. NaN or infinite inputs give a NaN or infinite twist.
    #[must_use]
    #[inline]
    pub fn increment(&self, arcs: [T; 2], dtheta: T) -> Twist2<T> {
        let f = &self.solver;
        let [a, b] = arcs;
        Twist2::new(
            f[0][0] * a + f[0][1] * b + f[0][2] * dtheta,
            f[1][0] * a + f[1][1] * b + f[1][2] * dtheta,
            dtheta,
        )
    }
}

/// `1 / (8 √ε)`: the largest condition number accepted for a type of machine epsilon `eps`
/// (as for the wheel maps).
fn max_condition(eps: f64) -> f64 {
    1.0 / libm::sqrt(64.0 * eps)
}

/// [`PodLayoutError::Unrepresentable`], NaN reported as infinite.
fn unrepresentable(deviation: f64) -> PodLayoutError {
    PodLayoutError::Unrepresentable {
        deviation: if deviation.is_nan() {
            f64::INFINITY
        } else {
            deviation
        },
    }
}

/// RMS distance of the pods from the body origin, m, in `f64` (scaled by the largest
/// coordinate, so it neither overflows nor underflows for `f32`); 1 if all are at the origin.
fn rms_distance<T: Real, const N: usize>(pods: &[PodGeometry<T>; N]) -> f64 {
    let big = pods.iter().fold(0.0_f64, |m, p| {
        m.max(libm::fabs(p.x.to_f64()))
            .max(libm::fabs(p.y.to_f64()))
    });
    if !(big > 0.0 && big.is_finite()) {
        return 1.0;
    }
    let sum = pods.iter().fold(0.0, |s, p| {
        let (x, y) = (p.x.to_f64() / big, p.y.to_f64() / big);
        s + x * x + y * y
    });
    #[allow(clippy::cast_precision_loss)]
    let mean = sum / N as f64;
    big * libm::sqrt(mean)
}

/// The inverse of a 3 × 3 matrix by its adjugate, and its Frobenius condition number
/// (infinite if the determinant is zero or the inverse is not finite). The entries of the
/// scaled model are at most `√3` in magnitude, so nothing overflows.
fn inverse3(m: &[[f64; 3]; 3]) -> ([[f64; 3]; 3], f64) {
    // Cofactor (i, j) from the rows and columns other than i and j, cyclically.
    let cof = |i: usize, j: usize| {
        let (r0, r1) = ((i + 1) % 3, (i + 2) % 3);
        let (c0, c1) = ((j + 1) % 3, (j + 2) % 3);
        m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
    };
    let det = m[0][0] * cof(0, 0) + m[0][1] * cof(0, 1) + m[0][2] * cof(0, 2);
    let mut inverse = [[0.0_f64; 3]; 3];
    if det == 0.0 || !det.is_finite() {
        return (inverse, f64::INFINITY);
    }
    for (i, row) in inverse.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            // The inverse is the transposed cofactor matrix over the determinant.
            *v = cof(j, i) / det;
        }
    }
    let condition = libm::sqrt(frobenius2(m) * frobenius2(&inverse));
    let condition = if condition.is_finite() {
        condition
    } else {
        f64::INFINITY
    };
    (inverse, condition)
}

/// Sum of the squares of the entries.
fn frobenius2<const R: usize>(m: &[[f64; 3]; R]) -> f64 {
    m.iter().flatten().fold(0.0, |s, v| s + v * v)
}

/// Frobenius condition number of the 2 × 2 matrix of two pods' directions, `‖B‖_F² / |det B|`
/// (`‖B⁻¹‖_F = ‖B‖_F / |det B|` for a 2 × 2), infinite when parallel; with `det B` (the cross
/// product of the directions, the sine of the angle between them) and their dot product.
fn pair_condition(a: &[f64; 3], b: &[f64; 3]) -> (f64, f64, f64) {
    let cross = a[0] * b[1] - a[1] * b[0];
    let dot = a[0] * b[0] + a[1] * b[1];
    let norm2 = a[0] * a[0] + a[1] * a[1] + b[0] * b[0] + b[1] * b[1];
    let condition = if cross == 0.0 {
        f64::INFINITY
    } else {
        norm2 / libm::fabs(cross)
    };
    (condition, cross, dot)
}

/// Why a three-pod layout is singular (or nearly). A 3 × 3 model has rank < 3 exactly when
/// some rigid motion is invisible to all three pods: a translation (all directions parallel)
/// or a rotation about a point (the three lines of action meet there). If every pair of pods
/// would be refused as a two-pod layout, the directions are parallel; otherwise the lines meet
/// where the pair crossing at the largest angle meets.
fn classify(scaled: &[[f64; 3]; 3], length: f64, condition: f64, limit: f64) -> PodLayoutError {
    let mut best: Option<(usize, usize, f64, f64)> = None;
    let mut widest = 0.0_f64;
    for (i, j) in [(0, 1), (0, 2), (1, 2)] {
        let (pair, cross, dot) = pair_condition(&scaled[i], &scaled[j]);
        widest = widest.max(libm::atan2(libm::fabs(cross), libm::fabs(dot)));
        let better = best.is_none_or(|(_, _, b, _)| pair < b);
        if better {
            best = Some((i, j, pair, cross));
        }
    }
    match best {
        Some((i, j, pair, cross)) if pair <= limit => {
            // Lines {p : p × u_k = m_k}: s_k x − c_k y = m_k for k = i, j (Cramer's rule).
            let [ci, si, mi] = scaled[i];
            let [cj, sj, mj] = scaled[j];
            let (mi, mj) = (mi * length, mj * length);
            PodLayoutError::Concurrent {
                x: (ci * mj - cj * mi) / cross,
                y: (si * mj - sj * mi) / cross,
                condition,
            }
        }
        _ => PodLayoutError::AllParallel {
            angle: widest,
            condition,
        },
    }
}

/// The solver in `f64` with its dθ row times `length` (`D⁻¹ F`), to compare with the scaled
/// model.
fn scale_solver<T: Real>(solver: &[[T; 3]; 3], length: f64) -> [[f64; 3]; 3] {
    let mut back = solver.map(|r| r.map(Real::to_f64));
    for v in &mut back[2] {
        *v *= length;
    }
    back
}

/// Checks `max |F M − I| <= 32 · 3 · condition · ε` of `T` (the allowance of the wheel maps),
/// with `F` the rounded solver (scaled back) and `M` the scaled model; else
/// [`PodLayoutError::Unrepresentable`].
fn check_inverse<T: Real>(
    f: &[[f64; 3]; 3],
    m: &[[f64; 3]; 3],
    condition: f64,
) -> Result<(), PodLayoutError> {
    let mut worst = 0.0_f64;
    for (i, row) in f.iter().enumerate() {
        let product: [f64; 3] =
            core::array::from_fn(|j| row[0] * m[0][j] + row[1] * m[1][j] + row[2] * m[2][j]);
        for (j, s) in product.into_iter().enumerate() {
            let e = libm::fabs(s - if i == j { 1.0 } else { 0.0 });
            // `max` would drop a NaN.
            worst = if e > worst || e.is_nan() { e } else { worst };
        }
    }
    let tolerance = 96.0 * condition * T::EPSILON.to_f64();
    let fits = worst <= tolerance;
    if fits {
        Ok(())
    } else {
        Err(unrepresentable(worst))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::odometry::Odometry;
    use crate::types::Pose2;
    use core::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

    /// A fixed-seed 64-bit LCG (Knuth's MMIX constants): uniform in `[lo, hi)`.
    struct Lcg(u64);

    impl Lcg {
        fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            #[allow(clippy::cast_precision_loss)]
            let unit = (self.0 >> 11) as f64 / (1_u64 << 53) as f64;
            lo + (hi - lo) * unit
        }

        fn twist(&mut self) -> Twist2<f64> {
            Twist2::new(
                self.uniform(-0.05, 0.05),
                self.uniform(-0.05, 0.05),
                self.uniform(-0.3, 0.3),
            )
        }

        fn pod(&mut self) -> PodGeometry<f64> {
            PodGeometry::new(
                self.uniform(-0.3, 0.3),
                self.uniform(-0.3, 0.3),
                self.uniform(-PI, PI),
            )
        }
    }

    fn pod(x: f64, y: f64, direction: f64) -> PodGeometry<f64> {
        PodGeometry::new(x, y, direction)
    }

    #[allow(clippy::cast_possible_truncation)]
    fn pod32(p: PodGeometry<f64>) -> PodGeometry<f32> {
        PodGeometry::new(p.x as f32, p.y as f32, p.direction as f32)
    }

    fn assert_twist(got: Twist2<f64>, want: Twist2<f64>, tol: f64) {
        let err = (got.dx - want.dx)
            .abs()
            .max((got.dy - want.dy).abs())
            .max((got.dtheta - want.dtheta).abs());
        assert!(err <= tol, "got {got:?}, want {want:?}: error {err:e}");
    }

    // Road Runner's formulas, verbatim from its quickstart (`ThreeDeadWheelLocalizer`,
    // `TwoDeadWheelLocalizer`), in its own parameters.
    fn rr_three(
        par0_y: f64,
        par1_y: f64,
        perp_x: f64,
        par0: f64,
        par1: f64,
        perp: f64,
    ) -> Twist2<f64> {
        Twist2::new(
            (par0_y * par1 - par1_y * par0) / (par0_y - par1_y),
            perp_x / (par0_y - par1_y) * (par1 - par0) + perp,
            (par0 - par1) / (par0_y - par1_y),
        )
    }

    fn rr_two(par_y: f64, perp_x: f64, par: f64, perp: f64, h: f64) -> Twist2<f64> {
        Twist2::new(par - par_y * h, perp - perp_x * h, h)
    }

    /// Road Runner's three-wheel layout in this model: its par y is minus the pod's y.
    fn rr_three_pods(
        par0_y: f64,
        par1_y: f64,
        perp_x: f64,
        xs: [f64; 2],
        perp_y: f64,
    ) -> [PodGeometry<f64>; 3] {
        [
            pod(xs[0], -par0_y, 0.0),
            pod(xs[1], -par1_y, 0.0),
            pod(perp_x, perp_y, FRAC_PI_2),
        ]
    }

    #[test]
    fn forward_model_is_the_rigid_motion_of_the_contact_point() {
        // A pod left of the centre, measuring forward travel, rolls back in a CCW turn.
        let left = pod(0.0, 0.15, 0.0);
        assert!((left.arc(Twist2::new(0.0, 0.0, 0.1)) + 0.015).abs() < 1e-15);
        // One in front, measuring leftward travel, rolls forward (left) in a CCW turn.
        let front = pod(0.1, 0.0, FRAC_PI_2);
        assert!((front.arc(Twist2::new(0.0, 0.0, 0.1)) - 0.01).abs() < 1e-15);

        // First order in the increment: the contact point's displacement projected on u.
        let mut rng = Lcg(7);
        for _ in 0..200 {
            let p = rng.pod();
            let t = rng.twist();
            let small = Twist2::new(t.dx * 1e-4, t.dy * 1e-4, t.dtheta * 1e-4);
            let moved = Pose2::default().exp(small);
            let (s, c) = moved.heading.sin_cos();
            let (px, py) = (
                moved.x + c * p.x - s * p.y - p.x,
                moved.y + s * p.x + c * p.y - p.y,
            );
            let (su, cu) = p.direction.sin_cos();
            let projected = cu * px + su * py;
            // Second-order terms only: `(R(dθ) − I − dθ J) p` and the arc's bend of the
            // translation, about 1e-10 here against first-order arcs of about 1e-5 (a sign
            // slip in the model would be off by the latter).
            let second =
                small.dtheta.powi(2) * 0.5 + small.dtheta.abs() * (small.dx.abs() + small.dy.abs());
            let error = (p.arc(small) - projected).abs();
            assert!(error <= second + 1e-18, "{p:?} {small:?}: {error:e}");
        }
    }

    #[test]
    fn road_runner_three_wheel_formulas_hold() {
        let mut rng = Lcg(1);
        // (par0Y, par1Y, perpX) in metres; the standard layout and skewed ones.
        for (par0_y, par1_y, perp_x) in [
            (0.15, -0.15, -0.10),
            (-0.18, 0.16, 0.07),
            (0.05, 0.20, 0.0),
            (-0.12, -0.02, -0.25),
        ] {
            // Road Runner ignores the pods' other coordinate: so does the model.
            let xs = [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)];
            let perp_y = rng.uniform(-0.2, 0.2);
            let loc = ThreePodLocalizer::three(rr_three_pods(par0_y, par1_y, perp_x, xs, perp_y))
                .unwrap();
            for _ in 0..100 {
                let [par0, par1, perp] = [(); 3].map(|()| rng.uniform(-0.05, 0.05));
                let want = rr_three(par0_y, par1_y, perp_x, par0, par1, perp);
                assert_twist(loc.increment([par0, par1, perp]), want, 1e-12);
                // And the forward model gives back the arcs.
                let arcs = loc.arcs(want);
                for (a, b) in arcs.into_iter().zip([par0, par1, perp]) {
                    assert!((a - b).abs() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn road_runner_par_y_is_minus_the_pod_y() {
        // Taking Road Runner's par0Y/par1Y as the pods' y turns the heading the wrong way:
        // a CCW turn seen by pods at y = +0.15 (left) and −0.15 (right).
        let (par0_y, par1_y, perp_x) = (0.15, -0.15, -0.10);
        let twist = Twist2::new(0.0, 0.0, 0.2);
        let pods = [
            pod(0.0, par0_y, 0.0),
            pod(0.0, par1_y, 0.0),
            pod(perp_x, 0.0, FRAC_PI_2),
        ];
        let loc = ThreePodLocalizer::three(pods).unwrap();
        let [par0, par1, perp] = loc.arcs(twist);
        assert!(par0 < 0.0 && par1 > 0.0, "the left pod rolls back");
        assert_twist(loc.increment([par0, par1, perp]), twist, 1e-15);
        let rr = rr_three(par0_y, par1_y, perp_x, par0, par1, perp);
        assert!((rr.dtheta + 0.2).abs() < 1e-15, "{rr:?}");
        // With the sign mapped (par y = −y), Road Runner agrees.
        let rr = rr_three(-par0_y, -par1_y, perp_x, par0, par1, perp);
        assert_twist(rr, twist, 1e-15);
    }

    #[test]
    fn road_runner_two_wheel_formulas_hold() {
        let mut rng = Lcg(2);
        for (par_y, perp_x) in [(0.15, -0.10), (-0.07, 0.12), (0.0, 0.0), (0.2, 0.2)] {
            let pods = [
                pod(rng.uniform(-0.2, 0.2), -par_y, 0.0),
                pod(perp_x, rng.uniform(-0.2, 0.2), FRAC_PI_2),
            ];
            let loc = TwoPodLocalizer::two(pods).unwrap();
            for _ in 0..100 {
                let [par, perp, h] = [(); 3].map(|()| rng.uniform(-0.05, 0.05));
                let want = rr_two(par_y, perp_x, par, perp, h);
                let got = loc.increment([par, perp], h);
                assert_twist(got, want, 1e-12);
                assert!(got.dtheta.to_bits() == h.to_bits(), "dθ passes through");
            }
        }
    }

    #[test]
    fn road_runner_layout_mounted_at_45_degrees() {
        // Road Runner's layout in a frame B' turned 45° from the body: the pods' positions
        // turned by 45° and their directions too. Its formulas give the twist in B'; turned
        // back, the body twist.
        let (par0_y, par1_y, perp_x) = (0.14, -0.16, -0.09);
        let (s, c) = FRAC_PI_4.sin_cos();
        let turn = |p: PodGeometry<f64>| {
            pod(
                c * p.x - s * p.y,
                s * p.x + c * p.y,
                p.direction + FRAC_PI_4,
            )
        };
        let pods = rr_three_pods(par0_y, par1_y, perp_x, [0.03, -0.05], 0.02).map(turn);
        let loc = ThreePodLocalizer::three(pods).unwrap();
        let mut rng = Lcg(3);
        for _ in 0..100 {
            let [par0, par1, perp] = [(); 3].map(|()| rng.uniform(-0.05, 0.05));
            let t = rr_three(par0_y, par1_y, perp_x, par0, par1, perp);
            let want = Twist2::new(c * t.dx - s * t.dy, s * t.dx + c * t.dy, t.dtheta);
            assert_twist(loc.increment([par0, par1, perp]), want, 1e-12);
        }
    }

    #[test]
    fn pods_at_45_degrees() {
        // Two pods in an X, heading from the gyro: forward, strafe and turn by hand.
        let loc =
            TwoPodLocalizer::two([pod(0.0, 0.1, FRAC_PI_4), pod(0.0, -0.1, -FRAC_PI_4)]).unwrap();
        let h = FRAC_PI_4.cos() * 0.1;
        assert_twist(
            loc.increment([h, h], 0.0),
            Twist2::new(0.1, 0.0, 0.0),
            1e-15,
        );
        assert_twist(
            loc.increment([h, -h], 0.0),
            Twist2::new(0.0, 0.1, 0.0),
            1e-15,
        );
        // A CCW turn of 0.2 rad: the left pod's contact point moves back 0.02 m, the right
        // one's forward.
        let r = FRAC_PI_4.cos() * 0.02;
        assert_twist(
            loc.increment([-r, r], 0.2),
            Twist2::new(0.0, 0.0, 0.2),
            1e-15,
        );
        assert!((loc.condition_number() - 2.0).abs() < 1e-15);

        // Three pods tangent to a circle of 0.1 m, 120° apart (a "kiwi" layout): a turn
        // rolls each pod by 0.1 dθ, and any twist comes back.
        let pods = [90.0_f64, 210.0, 330.0].map(|a| {
            let a = a.to_radians();
            pod(0.1 * a.cos(), 0.1 * a.sin(), a + FRAC_PI_2)
        });
        let loc = ThreePodLocalizer::three(pods).unwrap();
        assert_twist(loc.increment([0.03; 3]), Twist2::new(0.0, 0.0, 0.3), 1e-15);
        let twist = Twist2::new(0.02, -0.04, 0.1);
        assert_twist(loc.increment(loc.arcs(twist)), twist, 1e-15);
    }

    #[test]
    fn round_trip_random_layouts_f64() {
        let mut rng = Lcg(4);
        let (mut three, mut two) = (0, 0);
        for _ in 0..2000 {
            let pods = [rng.pod(), rng.pod(), rng.pod()];
            if let Ok(loc) = ThreePodLocalizer::three(pods) {
                three += 1;
                for _ in 0..10 {
                    let twist = rng.twist();
                    assert_twist(loc.increment(loc.arcs(twist)), twist, 1e-9);
                    // The per-pod model agrees with the precomputed one.
                    for (p, a) in pods.iter().zip(loc.arcs(twist)) {
                        assert!((p.arc(twist) - a).abs() < 1e-15);
                    }
                }
            }
            if let Ok(loc) = TwoPodLocalizer::two([pods[0], pods[1]]) {
                two += 1;
                for _ in 0..10 {
                    let twist = rng.twist();
                    let got = loc.increment(loc.arcs(twist), twist.dtheta);
                    assert_twist(got, twist, 1e-9);
                }
            }
        }
        // Random layouts are almost never singular.
        assert!(three > 1990 && two > 1990, "{three} {two}");
    }

    #[test]
    fn round_trip_random_layouts_f32() {
        let mut rng = Lcg(5);
        let (mut three, mut two) = (0, 0);
        for _ in 0..2000 {
            let pods = [rng.pod(), rng.pod(), rng.pod()].map(pod32);
            let size = rms_distance(&pods);
            // Relative to the size of the twist, yaw as the motion of a point `size` away.
            #[allow(clippy::cast_possible_truncation)]
            let check = |got: Twist2<f32>, want: Twist2<f64>| {
                let scale = want
                    .dx
                    .abs()
                    .max(want.dy.abs())
                    .max(want.dtheta.abs() * size);
                let err = (f64::from(got.dx) - want.dx)
                    .abs()
                    .max((f64::from(got.dy) - want.dy).abs())
                    .max((f64::from(got.dtheta) - want.dtheta).abs() * size);
                assert!(err <= 1e-4 * scale, "{got:?} {want:?}: {:e}", err / scale);
            };
            #[allow(clippy::cast_possible_truncation)]
            let narrow = |t: Twist2<f64>| Twist2::new(t.dx as f32, t.dy as f32, t.dtheta as f32);
            if let Ok(loc) = ThreePodLocalizer::three(pods) {
                three += 1;
                for _ in 0..10 {
                    let twist = narrow(rng.twist());
                    let want = Twist2::new(
                        f64::from(twist.dx),
                        f64::from(twist.dy),
                        f64::from(twist.dtheta),
                    );
                    check(loc.increment(loc.arcs(twist)), want);
                }
            }
            if let Ok(loc) = TwoPodLocalizer::two([pods[0], pods[1]]) {
                two += 1;
                for _ in 0..10 {
                    let twist = narrow(rng.twist());
                    let want = Twist2::new(
                        f64::from(twist.dx),
                        f64::from(twist.dy),
                        f64::from(twist.dtheta),
                    );
                    check(loc.increment(loc.arcs(twist), twist.dtheta), want);
                }
            }
        }
        assert!(three > 1900 && two > 1900, "{three} {two}");
    }

    #[test]
    fn rejects_non_finite_parameters() {
        let ok = pod(0.0, 0.1, 0.0);
        let err = ThreePodLocalizer::three([ok, pod(0.1, f64::NAN, 1.0), ok]).unwrap_err();
        assert_eq!(err, PodLayoutError::NonFinite { pod: 1, field: "y" });
        let err = ThreePodLocalizer::three([ok, ok, pod(0.1, 0.0, f64::INFINITY)]).unwrap_err();
        assert_eq!(
            err,
            PodLayoutError::NonFinite {
                pod: 2,
                field: "direction"
            }
        );
        let err = TwoPodLocalizer::two([pod(f64::NEG_INFINITY, 0.0, 0.0), ok]).unwrap_err();
        assert_eq!(err, PodLayoutError::NonFinite { pod: 0, field: "x" });
    }

    #[test]
    fn rejects_two_parallel_pods() {
        let err = TwoPodLocalizer::two([pod(0.0, 0.1, 0.3), pod(0.2, -0.1, 0.3)]).unwrap_err();
        let PodLayoutError::Parallel {
            first: 0,
            second: 1,
            angle,
            condition,
        } = err
        else {
            panic!("{err:?}")
        };
        assert!(angle.abs() < 1e-15 && condition == f64::INFINITY, "{err:?}");
        // Anti-parallel is parallel too: the angle says which.
        let err = TwoPodLocalizer::two([pod(0.0, 0.1, 0.3), pod(0.2, -0.1, 0.3 + PI)]).unwrap_err();
        let PodLayoutError::Parallel { angle, .. } = err else {
            panic!("{err:?}")
        };
        assert!((angle.abs() - PI).abs() < 1e-12, "{err:?}");
        // The threshold is relative to the type's precision: 1 mrad apart (condition 2000)
        // is refused in f32 (limit 362) and fine in f64 (limit 8.4e6).
        let pods = [pod(0.0, 0.1, 0.0), pod(0.0, -0.1, 1e-3)];
        let loc = TwoPodLocalizer::two(pods).unwrap();
        assert!((loc.condition_number() - 2000.0).abs() < 1e-3);
        let err = TwoPodLocalizer::two(pods.map(pod32)).unwrap_err();
        let PodLayoutError::Parallel {
            angle, condition, ..
        } = err
        else {
            panic!("{err:?}")
        };
        assert!(
            (angle - 1e-3).abs() < 1e-9 && (condition - 2000.0).abs() < 1.0,
            "{err:?}"
        );
        // Just inside the limit in f32: |sin| = 2 / 300.
        let inside = [pod(0.0, 0.1, 0.0), pod(0.0, -0.1, (2.0_f64 / 300.0).asin())];
        assert!(TwoPodLocalizer::two(inside.map(pod32)).is_ok());
        // Two pods at one point, crossing: fine (the heading comes from elsewhere).
        assert!(TwoPodLocalizer::two([pod(0.1, 0.1, 0.0), pod(0.1, 0.1, 2.0)]).is_ok());
    }

    #[test]
    fn rejects_three_parallel_pods() {
        // Parallel, not collinear: the lateral translation is invisible.
        let err =
            ThreePodLocalizer::three([pod(0.0, 0.1, 0.0), pod(0.0, -0.1, 0.0), pod(0.1, 0.0, 0.0)])
                .unwrap_err();
        assert!(
            matches!(err, PodLayoutError::AllParallel { angle, condition }
                if angle == 0.0 && condition == f64::INFINITY),
            "{err:?}"
        );
        // Parallel and collinear; and anti-parallel ones.
        let err =
            ThreePodLocalizer::three([pod(0.0, 0.0, 0.0), pod(0.1, 0.0, 0.0), pod(0.2, 0.0, 0.0)])
                .unwrap_err();
        assert!(matches!(err, PodLayoutError::AllParallel { .. }), "{err:?}");
        let err =
            ThreePodLocalizer::three([pod(0.0, 0.1, 0.0), pod(0.0, -0.1, PI), pod(0.1, 0.0, 0.0)])
                .unwrap_err();
        assert!(
            matches!(err, PodLayoutError::AllParallel { angle, .. } if angle < 1e-15),
            "{err:?}"
        );
        // Nearly parallel (1e-4 rad spread) in f32: the largest angle is reported.
        let pods = [
            pod(0.0, 0.1, 0.0),
            pod(0.0, -0.1, 1e-4),
            pod(0.1, 0.0, -5e-5),
        ];
        let err = ThreePodLocalizer::three(pods.map(pod32)).unwrap_err();
        assert!(
            matches!(err, PodLayoutError::AllParallel { angle, condition }
                if (angle - 1.5e-4).abs() < 1e-8 && condition > 1e3),
            "{err:?}"
        );
    }

    #[test]
    fn rejects_concurrent_pods() {
        // Three lines through (0.05, -0.02): a rotation about it is invisible.
        let (px, py) = (0.05, -0.02);
        let on_line = |t: f64, phi: f64| pod(px + t * phi.cos(), py + t * phi.sin(), phi);
        let pods = [on_line(0.1, 0.2), on_line(-0.15, 1.9), on_line(0.12, 4.0)];
        let err = ThreePodLocalizer::three(pods).unwrap_err();
        let PodLayoutError::Concurrent { x, y, condition } = err else {
            panic!("{err:?}")
        };
        assert!((x - px).abs() < 1e-12 && (y - py).abs() < 1e-12, "{err:?}");
        assert!(condition > 1e12, "{err:?}");
        // Invisible indeed: arcs of a rotation about the point are zero.
        let rotation = Twist2::new(0.3 * py, -0.3 * px, 0.3);
        for p in pods {
            assert!(p.arc(rotation).abs() < 1e-15);
        }

        // Two pods on one line, a third across it: the lines meet where it crosses.
        let err =
            ThreePodLocalizer::three([pod(0.0, 0.1, 0.0), pod(0.2, 0.1, PI), pod(0.1, 0.0, 1.0)])
                .unwrap_err();
        let PodLayoutError::Concurrent { x, y, .. } = err else {
            panic!("{err:?}")
        };
        let want_x = 0.1 + 0.1 / 1.0_f64.tan();
        assert!(
            (x - want_x).abs() < 1e-12 && (y - 0.1).abs() < 1e-12,
            "{err:?}"
        );

        // All three pods at one point: the lines meet there.
        let err =
            ThreePodLocalizer::three([pod(0.1, 0.2, 0.0), pod(0.1, 0.2, 2.0), pod(0.1, 0.2, 4.0)])
                .unwrap_err();
        assert!(
            matches!(err, PodLayoutError::Concurrent { x, y, .. }
                if (x - 0.1).abs() < 1e-12 && (y - 0.2).abs() < 1e-12),
            "{err:?}"
        );

        // Nearly concurrent: the third line misses the point by 10 µm. Refused in f32
        // (condition above 362), fine in f64.
        let pods = [
            on_line(0.1, 0.2),
            on_line(-0.15, 1.9),
            pod(
                px + 0.12 * 4.0_f64.cos(),
                py + 0.12 * 4.0_f64.sin() + 1e-5,
                4.0,
            ),
        ];
        let loc = ThreePodLocalizer::three(pods).unwrap();
        assert!(loc.condition_number() > 1e3 && loc.condition_number() < 1e5);
        let err = ThreePodLocalizer::three(pods.map(pod32)).unwrap_err();
        assert!(
            matches!(err, PodLayoutError::Concurrent { x, y, .. }
                if (x - px).abs() < 1e-6 && (y - py).abs() < 1e-6),
            "{err:?}"
        );
    }

    #[test]
    fn rejects_unrepresentable_layouts() {
        // f32: a moment arm of 4.2e38 m overflows.
        let big = 3e38_f32;
        let pods = [
            PodGeometry::new(big, big, -core::f32::consts::FRAC_PI_4),
            PodGeometry::new(0.0, 0.0, 0.0),
            PodGeometry::new(0.0, 0.0, core::f32::consts::FRAC_PI_2),
        ];
        let err = ThreePodLocalizer::three(pods).unwrap_err();
        assert!(
            matches!(err, PodLayoutError::Unrepresentable { deviation } if deviation.is_infinite()),
            "{err:?}"
        );
        // f32: pods 1e-41 m from the origin (subnormal): the arms lose their digits.
        let tiny = 1e-41_f32;
        let pods = [
            PodGeometry::new(0.0, tiny, 0.0),
            PodGeometry::new(0.0, -tiny, 0.0),
            PodGeometry::new(tiny, 0.0, core::f32::consts::FRAC_PI_2),
        ];
        let err = ThreePodLocalizer::three(pods).unwrap_err();
        assert!(
            matches!(err, PodLayoutError::Unrepresentable { .. }),
            "{err:?}"
        );
        // Scale alone is no problem: the same layout in km or µm is accepted, same figure.
        let base = [
            pod(0.0, 0.15, 0.0),
            pod(0.0, -0.15, 0.0),
            pod(-0.1, 0.0, FRAC_PI_2),
        ];
        let k = ThreePodLocalizer::three(base).unwrap().condition_number();
        for scale in [1e-6, 1e3, 1e30] {
            let scaled = base.map(|p| pod(p.x * scale, p.y * scale, p.direction));
            let c = ThreePodLocalizer::three(scaled).unwrap().condition_number();
            assert!((c - k).abs() < 1e-12 * k, "{scale}: {c} vs {k}");
        }
    }

    #[test]
    fn errors_name_the_pods() {
        extern crate std;
        use std::string::ToString;
        let e = PodLayoutError::NonFinite { pod: 2, field: "x" }.to_string();
        assert_eq!(e, "pod 2: x is not finite");
        let e = TwoPodLocalizer::two([pod(0.0, 0.1, 0.3), pod(0.2, -0.1, 0.3)])
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("pods 0 and 1 are (nearly) parallel"), "{e}");
        let e = PodLayoutError::Concurrent {
            x: 0.5,
            y: -0.25,
            condition: f64::INFINITY,
        }
        .to_string();
        assert!(
            e.contains("(0.5 m, -0.25 m)") && e.contains("rotation"),
            "{e}"
        );
    }

    #[test]
    fn road_runner_layout_condition_and_limits() {
        let loc =
            ThreePodLocalizer::three(rr_three_pods(0.15, -0.15, -0.10, [0.0; 2], 0.0)).unwrap();
        let k = loc.condition_number();
        assert!((3.0..10.0).contains(&k), "{k}");
        assert!((PodLocalizer::<f64, 3>::max_condition_number() - 8.39e6).abs() < 1e4);
        assert!((PodLocalizer::<f32, 2>::max_condition_number() - 362.0).abs() < 0.1);
    }

    #[test]
    fn feeds_odometry() {
        // Pods read a constant-velocity motion in 100 steps; integrated with
        // `Odometry::apply`, the pose is the one of the exact arc.
        let loc =
            ThreePodLocalizer::three(rr_three_pods(0.15, -0.15, -0.10, [0.0; 2], 0.0)).unwrap();
        let step = Twist2::new(0.004, 0.001, 0.015);
        let mut odometry = Odometry::new(Pose2::default());
        for _ in 0..100 {
            odometry.apply(loc.increment(loc.arcs(step)));
        }
        let want = Pose2::default().exp(Twist2::new(0.4, 0.1, 1.5));
        let got = odometry.pose();
        assert!((got.x - want.x).abs() < 1e-12 && (got.y - want.y).abs() < 1e-12);
        assert!((got.heading - want.heading).abs() < 1e-12);
    }
}
