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

mod conditioning;
#[cfg(test)]
mod tests;

use conditioning::{
    check_inverse, classify, inverse3, max_condition, pair_condition, rms_distance, scale_solver,
    unrepresentable,
};

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

    /// The localizer, once what `T` holds of `solver` is found to invert the model:
    /// `inverse` is the rounded solver scaled back and the scaled model it must invert (see
    /// [`check_inverse`]).
    fn checked(
        pods: [PodGeometry<T>; N],
        model: [[T; 3]; N],
        solver: [[T; 3]; 3],
        inverse: (&[[f64; 3]; 3], &[[f64; 3]; 3]),
        condition: f64,
    ) -> Result<Self, PodLayoutError> {
        check_inverse::<T>(inverse.0, inverse.1, condition)?;
        Ok(Self {
            pods,
            model,
            solver,
            condition: T::lit(condition),
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
        Self::checked(pods, model, solver, (&back, &scaled), condition)
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
        let rows = Self::rows(&pods)?;
        let (scaled, length) = (rows.scaled, rows.length);
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
        Self::checked(pods, rows.model, solver, (&back, &map), condition)
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
