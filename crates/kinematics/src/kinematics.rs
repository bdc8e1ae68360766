//! Wheel geometry and the inverse / forward wheel maps.
//!
//! [`WheelGeometry`] is one wheel: its centre, axle angle α, roller angle δ and radius.
//! [`MecanumKinematics`] stacks one row per wheel into the inverse map `J` (N × 3), refuses a
//! layout it cannot invert, and computes the least-squares forward map `J⁺` once, at
//! construction; the residual of the forward map is the wheels' disagreement (slip, a bad
//! encoder, a wrong radius). [`Effectiveness`] is the per-axis slip model folded into both
//! maps. Every per-step method computes in `T` alone.
//!
//! The derivation (Gfrerrer 2008, eq. 16 and Theorem 2), how `J⁺` is computed (in `f64`, by
//! Householder QR) and how the effectiveness factors enter the maps are in the crate's
//! `README.md`, section "Wheel maps" ([crate documentation](crate#wheel-maps)).

use nalgebra::{Matrix3, SMatrix, Vector3};

use crate::error::{Axis, GeometryError};
use crate::real::Real;
use crate::types::{ChassisVelocity, Twist2, WheelDeltas, WheelSpeeds};

/// The geometry of one mecanum wheel, in the body frame (x forward, y left).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelGeometry<T> {
    /// Wheel centre x, m.
    pub x: T,
    /// Wheel centre y, m.
    pub y: T,
    /// Angle α of the wheel's axle from the body x axis, rad. A conventional wheel whose
    /// positive rotation rolls the robot forward has α = π/2 (axle pointing left).
    pub axle_angle: T,
    /// Angle δ between the axle and the axis of the roller in contact with the ground, rad
    /// (±π/4 for common wheels). Its sign tells a left-handed from a right-handed wheel.
    pub roller_angle: T,
    /// Wheel radius, m (to the roller surface).
    pub radius: T,
}

impl<T: Real> WheelGeometry<T> {
    /// One wheel from its centre (m), axle angle (rad), roller angle (rad) and radius (m).
    #[must_use]
    pub const fn new(x: T, y: T, axle_angle: T, roller_angle: T, radius: T) -> Self {
        Self {
            x,
            y,
            axle_angle,
            roller_angle,
            radius,
        }
    }

    /// This wheel's row of the inverse map (Gfrerrer 2008, eq. 16), or why it has none.
    ///
    /// The trigonometry is done in `T` (libm), the products and the quotient in `f64`, so the
    /// row is rounded to `T` once, in [`MecanumKinematics::new`], where an overflow or
    /// underflow is detected.
    fn inverse_row(&self, wheel: usize) -> Result<[f64; 3], GeometryError> {
        for (field, v) in [
            ("x", self.x),
            ("y", self.y),
            ("axle_angle", self.axle_angle),
            ("roller_angle", self.roller_angle),
            ("radius", self.radius),
        ] {
            if !v.finite() {
                return Err(GeometryError::NonFinite { wheel, field });
            }
        }
        if self.radius <= T::zero() {
            return Err(GeometryError::NonPositiveRadius {
                wheel,
                radius: self.radius.to_f64(),
            });
        }
        let sin_delta = self.roller_angle.sin_cos_libm().0;
        // A roller within √ε of the axle (|sin δ| < √ε: 1.5e-8 rad in f64, 3.5e-4 rad in
        // f32) gives wheel speeds beyond any motor.
        if sin_delta.abs() < T::EPSILON.sqrt_libm() {
            return Err(GeometryError::RollerParallelToAxle {
                wheel,
                roller_angle: self.roller_angle.to_f64(),
            });
        }
        let (s, c) = (self.axle_angle + self.roller_angle).sin_cos_libm();
        let (s, c) = (s.to_f64(), c.to_f64());
        let (x, y) = (self.x.to_f64(), self.y.to_f64());
        let k = -1.0 / (self.radius.to_f64() * sin_delta.to_f64());
        Ok([k * c, k * s, k * (x * s - y * c)])
    }
}

/// The largest effectiveness factor accepted (see [`Effectiveness`]): 1.5.
///
/// A factor above 1 says the robot moves *more* than its wheels imply (an effective wheel
/// radius or lever arm larger than configured); beyond 1.5 it is a configuration error
/// rather than a calibration.
pub const MAX_EFFECTIVENESS: f64 = 1.5;

/// Per-axis effectiveness of the wheels: the fraction of the body motion the wheels imply
/// that the robot really makes, along x (forward), y (left) and in yaw. Dimensionless, each in
/// `(0, MAX_EFFECTIVENESS]`; `1` (the default) is the ideal, slip-free model.
///
/// Plain data: [`MecanumKinematics::with_effectiveness`] and
/// [`MecanumKinematics::standard_with_effectiveness`] check it ([`check`](Self::check)).
/// See the [crate documentation](crate#effectiveness-slip-aware-maps) for how it enters the
/// maps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Effectiveness<T> {
    /// Forward (x) factor: body x velocity made per unit the wheels imply.
    pub kx: T,
    /// Lateral (y) factor: body y velocity made per unit the wheels imply (a strafe on
    /// mecanum rollers: typically 0.7 to 0.8).
    pub ky: T,
    /// Yaw factor: yaw rate made per unit the wheels imply.
    pub kw: T,
}

impl<T: Real> Effectiveness<T> {
    /// Factors for x (forward), y (left) and yaw, unchecked.
    #[must_use]
    pub const fn new(kx: T, ky: T, kw: T) -> Self {
        Self { kx, ky, kw }
    }

    /// `k = (1, 1, 1)`: the ideal model, the robot makes exactly what its wheels imply.
    #[must_use]
    pub fn ideal() -> Self {
        Self::new(T::one(), T::one(), T::one())
    }

    /// `true` if every factor is exactly 1.
    #[must_use]
    pub fn is_ideal(&self) -> bool {
        self.as_array() == [T::one(); 3]
    }

    /// The factors in axis order (x, y, yaw).
    #[must_use]
    pub const fn as_array(&self) -> [T; 3] {
        [self.kx, self.ky, self.kw]
    }

    /// Checks that every factor is finite and in `(0, MAX_EFFECTIVENESS]`.
    ///
    /// # Errors
    /// [`GeometryError::Effectiveness`] naming the first axis out of range (x, y, yaw) and its
    /// value.
    pub fn check(&self) -> Result<(), GeometryError> {
        for (axis, k) in Axis::ALL.into_iter().zip(self.as_array()) {
            // Written so that NaN fails.
            let in_range = k > T::zero() && k <= T::lit(MAX_EFFECTIVENESS);
            if !in_range {
                return Err(GeometryError::Effectiveness {
                    axis,
                    value: k.to_f64(),
                });
            }
        }
        Ok(())
    }
}

impl<T: Real> Default for Effectiveness<T> {
    /// [`Effectiveness::ideal`].
    fn default() -> Self {
        Self::ideal()
    }
}

/// Inverse and forward kinematics of an `N`-wheel mecanum chassis (`N >= 3`, checked at
/// compile time).
///
/// Construction validates the layout and precomputes both maps; every method after that is a
/// pure `&self` matrix product with no allocation and no hidden state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MecanumKinematics<T: Real, const N: usize> {
    wheels: [WheelGeometry<T>; N],
    effectiveness: Effectiveness<T>,
    /// Inverse map as applied, `J diag(k)⁻¹`: commanded body twist (vx, vy, wz) to wheel speeds.
    inverse: SMatrix<T, N, 3>,
    /// Forward map as applied, `diag(k) J⁺`, with `J⁺ = (JᵀJ)⁻¹Jᵀ` the least-squares inverse
    /// (computed by QR in `f64`, scaled and rounded to `T`).
    forward: SMatrix<T, 3, N>,
    condition: T,
}

impl<T: Real, const N: usize> MecanumKinematics<T, N> {
    /// The kinematics of a general layout, one [`WheelGeometry`] per wheel (Gfrerrer 2008, eq. 16).
    ///
    /// # Errors
    /// [`GeometryError`] for a non-finite parameter, a non-positive radius, a roller within
    /// `√ε` of its axle (`|sin δ| < √ε`: 1.5e-8 rad in `f64`, 3.5e-4 rad in `f32`), a layout
    /// whose roller axes are concurrent or parallel (rank < 3) or so nearly that the
    /// condition number exceeds [`max_condition_number`](Self::max_condition_number)
    /// ([`Singular`](GeometryError::Singular)), or a layout whose numbers overflow or
    /// underflow `T` ([`Unrepresentable`](GeometryError::Unrepresentable)).
    pub fn new(wheels: [WheelGeometry<T>; N]) -> Result<Self, GeometryError> {
        Self::with_effectiveness(wheels, Effectiveness::ideal())
    }

    /// As [`new`](Self::new), with per-axis [`Effectiveness`] factors (the slip-aware maps,
    /// see the [crate documentation](crate#effectiveness-slip-aware-maps)). With
    /// [`Effectiveness::ideal`] it is [`new`](Self::new), bit for bit.
    ///
    /// # Errors
    /// As [`new`](Self::new); [`GeometryError::Effectiveness`] for a factor that is not finite
    /// or not in `(0, MAX_EFFECTIVENESS]`, naming the axis;
    /// [`Unrepresentable`](GeometryError::Unrepresentable) if a factor, though in range,
    /// makes an entry of the maps overflow or underflow `T` (e.g. `1e-39` in `f32`).
    pub fn with_effectiveness(
        wheels: [WheelGeometry<T>; N],
        effectiveness: Effectiveness<T>,
    ) -> Result<Self, GeometryError> {
        let mut inverse = SMatrix::<f64, N, 3>::zeros();
        for (i, wheel) in wheels.iter().enumerate() {
            let row = wheel.inverse_row(i)?;
            for (j, v) in row.into_iter().enumerate() {
                inverse[(i, j)] = v;
            }
        }
        effectiveness.check()?;
        Self::from_rows(wheels, &inverse, effectiveness)
    }

    /// The largest condition number accepted (see
    /// [`condition_number`](Self::condition_number)): `1 / (8 √ε)` of `T`, about 362 in
    /// `f32` and 8.4e6 in `f64`.
    ///
    /// Beyond it the smallest singular value of the wheel map is, squared, within `64 ε` of
    /// the largest: the layout is singular to within the type's precision, and the forward
    /// map (accurate to a few `condition · ε`) would lose more than about 4e-5 (`f32`) or
    /// 2e-9 (`f64`) relative. The decision is made in `f64` from `J` as rounded to `T`, so it
    /// is the same on every target.
    #[must_use]
    pub fn max_condition_number() -> T {
        T::lit(max_condition(T::EPSILON.to_f64()))
    }

    /// Completes construction from the validated rows of the inverse map (in `f64`) and
    /// checked factors: rounds the rows to `T`, checks the rank, computes the conditioning
    /// figure and the least-squares forward map (in `f64`, see the
    /// [crate documentation](crate#wheel-maps)), then folds the factors into both maps.
    fn from_rows(
        wheels: [WheelGeometry<T>; N],
        rows: &SMatrix<f64, N, 3>,
        effectiveness: Effectiveness<T>,
    ) -> Result<Self, GeometryError> {
        const { assert!(N >= 3, "a mecanum layout needs at least three wheels") };
        let eps = T::EPSILON.to_f64();
        // Scale the yaw column by a characteristic length (RMS wheel distance from the
        // centre) so the conditioning figure has no units and does not change with them.
        let length = rms_distance(&wheels);

        // The map as `inverse` will apply it, rounded to T once. A finite layout can still
        // overflow T (or f64) or underflow it to a few digits or zero: compare, with the
        // columns scaled as for the condition number, relative to the largest entry.
        let inverse = round_faithfully(rows, |_, k| if k == 2 { 1.0 / length } else { 1.0 })?;
        let j = inverse.map(Real::to_f64);
        let mut scaled = j;
        for i in 0..N {
            scaled[(i, 2)] /= length;
        }
        // And everything by a power of two (exact) to unit magnitude, so that neither the
        // products below nor the QR overflow or underflow for any finite layout.
        let (_, exponent) = libm::frexp(scaled.amax());
        let unit = scaled.map(|v| libm::scalbn(v, -exponent));

        let (lo, hi) = symmetric_eigen_range(&(unit.transpose() * unit));
        // Rank < 3 within the precision of T: the smallest eigenvalue of JᵀJ (a singular value
        // squared) is lost in the noise of the largest.
        let full_rank = lo > hi * 64.0 * eps;
        if !full_rank {
            let condition = if lo > 0.0 {
                libm::sqrt(hi / lo)
            } else {
                f64::INFINITY
            };
            return Err(GeometryError::Singular { condition });
        }
        let condition = libm::sqrt(hi / lo);

        // J⁺ = D (J D)⁺ with D = diag(1, 1, 1/length), and (J D)⁺ = 2^-e (2^-e J D)⁺.
        let mut forward_f64 = least_squares_inverse(&unit).map(|v| libm::scalbn(v, -exponent));
        for k in 0..N {
            forward_f64[(2, k)] /= length;
        }
        let forward = forward_f64.map(T::lit);

        // What T can hold of it: every entry finite, and J⁺ J = I to the accuracy the
        // conditioning allows (an entry rounded to zero or to few digits fails this).
        let deviation = identity_deviation(&forward.map(Real::to_f64), &j, length);
        #[allow(clippy::cast_precision_loss)]
        let tolerance = 32.0 * N as f64 * condition * eps;
        let inverts = deviation <= tolerance;
        if !inverts {
            return Err(unrepresentable(deviation));
        }

        // The factors, folded in f64 and rounded once: J diag(k)⁻¹ from the exact rows,
        // diag(k) J⁺ from the f64 forward map. k = 1 leaves every bit as it is (x / 1 and
        // x · 1 are exact), so the ideal maps are the ones checked above.
        let (inverse, forward) = if effectiveness.is_ideal() {
            (inverse, forward)
        } else {
            let k = effectiveness.as_array().map(Real::to_f64);
            let mut scaled_rows = *rows;
            for i in 0..N {
                for (j, kj) in k.iter().enumerate() {
                    scaled_rows[(i, j)] /= kj;
                }
            }
            let mut scaled_forward = forward_f64;
            for (i, ki) in k.iter().enumerate() {
                for col in 0..N {
                    scaled_forward[(i, col)] *= ki;
                }
            }
            // Judged with the factors divided out again (and the yaw column or row scaled as
            // above): an entry the factor pushed beyond T, or into its subnormals, fails.
            let yaw = |i: usize, s: f64| if i == 2 { s } else { 1.0 };
            let inverse = round_faithfully(&scaled_rows, |_, j| k[j] * yaw(j, 1.0 / length))?;
            let forward = round_faithfully(&scaled_forward, |i, _| yaw(i, length) / k[i])?;
            (inverse, forward)
        };
        Ok(Self {
            wheels,
            effectiveness,
            inverse,
            forward,
            condition: T::lit(condition),
        })
    }

    /// The wheel geometry this map was built from.
    #[must_use]
    pub const fn wheels(&self) -> &[WheelGeometry<T>; N] {
        &self.wheels
    }

    /// The per-axis effectiveness factors folded into the maps (ideal unless built with
    /// [`with_effectiveness`](Self::with_effectiveness) or
    /// [`standard_with_effectiveness`](MecanumKinematics::standard_with_effectiveness)).
    #[must_use]
    pub const fn effectiveness(&self) -> Effectiveness<T> {
        self.effectiveness
    }

    /// The inverse map as applied (N × 3): wheel speeds (rad/s) = `J diag(k)⁻¹` · (vx, vy, wz),
    /// `J` itself with the ideal factors.
    #[must_use]
    pub const fn inverse_matrix(&self) -> &SMatrix<T, N, 3> {
        &self.inverse
    }

    /// The forward map as applied (3 × N): `diag(k) J⁺`, the least-squares inverse `J⁺`
    /// itself with the ideal factors.
    #[must_use]
    pub const fn forward_matrix(&self) -> &SMatrix<T, 3, N> {
        &self.forward
    }

    /// Condition number of the wheel map (≥ 1; 1 is ideal), with the yaw column scaled by the
    /// RMS wheel distance from the centre so the figure is dimensionless. Computed in `f64`
    /// at construction; never above [`max_condition_number`](Self::max_condition_number).
    ///
    /// It bounds how much a relative error in wheel speeds (encoder noise, slip) is amplified
    /// in the body velocity. The standard square layout with 45° rollers has `√2`;
    /// values far above 10 mean a badly conditioned layout.
    #[must_use]
    pub const fn condition_number(&self) -> T {
        self.condition
    }

    /// Inverse kinematics: the wheel speeds that move the body with `velocity` (with the
    /// [`effectiveness`](Self::effectiveness) factors: the ideal wheel speeds of
    /// `velocity / k`).
    #[must_use]
    #[inline]
    pub fn inverse(&self, velocity: ChassisVelocity<T>) -> WheelSpeeds<T, N> {
        let w = self.inverse * Vector3::new(velocity.vx, velocity.vy, velocity.wz);
        WheelSpeeds(w.into())
    }

    /// Inverse kinematics for a rotation about `(cx, cy)` (body frame, m) instead of the
    /// body origin: `velocity` is the twist of the point `(cx, cy)`.
    ///
    /// With only `wz` set the chassis spins about that point, e.g. about one wheel.
    #[must_use]
    pub fn inverse_about(&self, velocity: ChassisVelocity<T>, cx: T, cy: T) -> WheelSpeeds<T, N> {
        // Velocity of the origin: v_o = v_c + ω × (o - c) = v_c + (ω c_y, -ω c_x).
        self.inverse(ChassisVelocity::new(
            velocity.vx + velocity.wz * cy,
            velocity.vy - velocity.wz * cx,
            velocity.wz,
        ))
    }

    /// Forward kinematics: the body velocity that best explains `speeds` (least squares),
    /// times the [`effectiveness`](Self::effectiveness) factors.
    #[must_use]
    #[inline]
    pub fn forward(&self, speeds: &WheelSpeeds<T, N>) -> ChassisVelocity<T> {
        let v = self.solve(&speeds.0);
        ChassisVelocity::new(v.x, v.y, v.z)
    }

    /// Forward kinematics and the residual: per wheel, the measured speed minus the speed the
    /// fitted body velocity implies (rad/s). Zero when the wheels agree; its size is the slip
    /// signal. With exactly three wheels it is always zero. The effectiveness factors cancel
    /// in it: it is a property of the wheels, the same for any `k`.
    #[must_use]
    pub fn forward_with_residual(
        &self,
        speeds: &WheelSpeeds<T, N>,
    ) -> (ChassisVelocity<T>, WheelSpeeds<T, N>) {
        let v = self.forward(speeds);
        let fitted = self.inverse(v);
        let mut residual = speeds.0;
        for (r, f) in residual.iter_mut().zip(fitted.0) {
            *r -= f;
        }
        (v, WheelSpeeds(residual))
    }

    /// Each wheel's speed as the *other* wheels imply it: the body velocity fitted to every
    /// wheel but `i`, mapped back to wheel `i` (rad/s). `None` where the other wheels do not
    /// determine it (three wheels, or a layout where wheel `i` alone constrains a direction).
    ///
    /// This is the leave-one-out prediction of least squares, `w_i − r_i / (1 − h_ii)` with
    /// `r` the residual of [`forward_with_residual`](Self::forward_with_residual) and `h_ii`
    /// the diagonal of `J J⁺`, so no matrix is refitted. With four wheels it is exactly the
    /// speed the three others force (standard layout: `FL + FR = RL + RR`). A wheel whose
    /// sensor reads nothing while the others move shows up as a large gap between its own
    /// speed and this one.
    #[must_use]
    pub fn implied_by_others(&self, speeds: &WheelSpeeds<T, N>) -> [Option<T>; N] {
        let (_, residual) = self.forward_with_residual(speeds);
        core::array::from_fn(|i| {
            let mut leverage = T::zero();
            for k in 0..3 {
                leverage += self.inverse[(i, k)] * self.forward[(k, i)];
            }
            // 1 - h_ii is in [0, 1]; near 0 the others say (almost) nothing about wheel i.
            let free = T::one() - leverage;
            (free > T::lit(1e-3)).then(|| speeds.0[i] - residual.0[i] / free)
        })
    }

    /// Forward kinematics of one step: the body displacement (in the body frame at the start
    /// of the step) that best explains the wheel angle increments, times the
    /// [`effectiveness`](Self::effectiveness) factors.
    #[must_use]
    #[inline]
    pub fn displacement(&self, deltas: &WheelDeltas<T, N>) -> Twist2<T> {
        let v = self.solve(&deltas.0);
        Twist2::new(v.x, v.y, v.z)
    }

    #[inline]
    fn solve(&self, wheels: &[T; N]) -> Vector3<T> {
        self.forward * SMatrix::<T, N, 1>::from_column_slice(wheels)
    }
}

impl<T: Real> MecanumKinematics<T, 4> {
    /// The standard four-wheel layout (the usual matrix form): wheels at `(±lx, ±ly)` in the order
    /// FL, FR, RL, RR, radius `r`, 45° rollers pointing to the centre seen from above.
    ///
    /// ```text
    /// FL = (vx - vy - (lx+ly) wz) / r      FR = (vx + vy + (lx+ly) wz) / r
    /// RL = (vx + vy - (lx+ly) wz) / r      RR = (vx - vy + (lx+ly) wz) / r
    /// ```
    ///
    /// The rows are filled in exactly; the geometry recorded is the equivalent general one
    /// (α = 90°, δ = +45° for FL and RR, −45° for FR and RL).
    ///
    /// `lx` and `ly` are distances, so `>= 0`; one of them may be zero (wheels on an axis), not
    /// both.
    ///
    /// # Errors
    /// [`GeometryError`] if a value is not finite, `r <= 0`, `lx < 0` or `ly < 0`
    /// ([`NegativeDistance`](GeometryError::NegativeDistance): a sign slip would silently
    /// reverse the yaw direction), `lx + ly == 0` (no yaw authority: singular), or the values
    /// overflow `T` ([`Unrepresentable`](GeometryError::Unrepresentable)).
    pub fn standard(lx: T, ly: T, r: T) -> Result<Self, GeometryError> {
        Self::standard_with_effectiveness(lx, ly, r, Effectiveness::ideal())
    }

    /// As [`standard`](Self::standard), with per-axis [`Effectiveness`] factors (the
    /// slip-aware maps, see the [crate documentation](crate#effectiveness-slip-aware-maps)):
    /// `FL = (vx/kx − vy/ky − (lx+ly) wz/kw) / r`, and so on. With [`Effectiveness::ideal`] it
    /// is [`standard`](Self::standard), bit for bit.
    ///
    /// # Errors
    /// As [`standard`](Self::standard), and as
    /// [`with_effectiveness`](Self::with_effectiveness) for the factors.
    pub fn standard_with_effectiveness(
        lx: T,
        ly: T,
        r: T,
        effectiveness: Effectiveness<T>,
    ) -> Result<Self, GeometryError> {
        let q = T::PI * T::lit(0.25);
        let axle = q + q;
        let wheels = [
            WheelGeometry::new(lx, ly, axle, q, r),
            WheelGeometry::new(lx, -ly, axle, -q, r),
            WheelGeometry::new(-lx, ly, axle, -q, r),
            WheelGeometry::new(-lx, -ly, axle, q, r),
        ];
        for (i, w) in wheels.iter().enumerate() {
            // Validation only: the rows are the exact ones below.
            w.inverse_row(i)?;
        }
        for (field, value) in [("lx", lx), ("ly", ly)] {
            if value < T::zero() {
                return Err(GeometryError::NegativeDistance {
                    field,
                    value: value.to_f64(),
                });
            }
        }
        let k = (lx + ly).to_f64();
        #[rustfmt::skip]
        let rows = SMatrix::<f64, 4, 3>::new(
            1.0, -1.0, -k,
            1.0,  1.0,  k,
            1.0,  1.0, -k,
            1.0, -1.0,  k,
        ) / r.to_f64();
        effectiveness.check()?;
        Self::from_rows(wheels, &rows, effectiveness)
    }
}

/// [`GeometryError::Unrepresentable`], NaN reported as infinite.
fn unrepresentable(deviation: f64) -> GeometryError {
    GeometryError::Unrepresentable {
        deviation: if deviation.is_nan() {
            f64::INFINITY
        } else {
            deviation
        },
    }
}

/// `exact` rounded to `T`, if that loses at most `ε` of `T` relative to the largest entry,
/// each entry weighed by `weight(row, column)` (finite and positive); else
/// [`GeometryError::Unrepresentable`]. Fails on an entry that overflows (or is already
/// infinite or NaN), and on one rounded to zero or to a few digits of a subnormal while it
/// matters at the scale of the others.
fn round_faithfully<T: Real, const R: usize, const C: usize>(
    exact: &SMatrix<f64, R, C>,
    weight: impl Fn(usize, usize) -> f64,
) -> Result<SMatrix<T, R, C>, GeometryError> {
    let rounded = exact.map(T::lit);
    let mut worst = 0.0_f64;
    let mut largest = 0.0_f64;
    for i in 0..R {
        for j in 0..C {
            let w = weight(i, j);
            let e = libm::fabs(rounded[(i, j)].to_f64() - exact[(i, j)]) * w;
            // `max` would drop a NaN.
            worst = if e > worst || e.is_nan() { e } else { worst };
            largest = largest.max(libm::fabs(exact[(i, j)]) * w);
        }
    }
    let deviation = worst / largest;
    // Written so that NaN (an overflow) is refused.
    let fits = deviation <= T::EPSILON.to_f64();
    if fits {
        Ok(rounded)
    } else {
        Err(unrepresentable(deviation))
    }
}

/// `1 / (8 √ε)`: the largest condition number accepted for a type of machine epsilon `eps`.
fn max_condition(eps: f64) -> f64 {
    1.0 / libm::sqrt(64.0 * eps)
}

/// RMS distance of the wheel centres from the body origin, m, in `f64` (scaled by the
/// largest coordinate, so it neither overflows nor underflows); 1 if all are at the origin.
fn rms_distance<T: Real, const N: usize>(wheels: &[WheelGeometry<T>; N]) -> f64 {
    let big = wheels.iter().fold(0.0_f64, |m, w| {
        m.max(libm::fabs(w.x.to_f64()))
            .max(libm::fabs(w.y.to_f64()))
    });
    if !(big > 0.0 && big.is_finite()) {
        return 1.0;
    }
    let sum = wheels.iter().fold(0.0, |s, w| {
        let (x, y) = (w.x.to_f64() / big, w.y.to_f64() / big);
        s + x * x + y * y
    });
    #[allow(clippy::cast_precision_loss)]
    let mean = sum / N as f64;
    big * libm::sqrt(mean)
}

/// The least-squares inverse `A⁺` of a full-rank `N × 3` matrix, by Householder QR:
/// `A = Q R`, `A⁺ = R⁻¹ Qᵀ`. Its error is a few `cond(A) · ε`, where the normal equations
/// `(AᵀA)⁻¹Aᵀ` give `cond(A)² · ε`. Column `k` of `A⁺` is the least-squares solution for the
/// unit vector `e_k`.
///
/// Written out rather than `nalgebra::QR`: for a generic `N` that needs
/// `Const<N>: DimMin<Const<3>>` bounds (a typenum conversion), which would leak into every
/// public constructor's signature.
fn least_squares_inverse<const N: usize>(a: &SMatrix<f64, N, 3>) -> SMatrix<f64, 3, N> {
    let mut r = *a;
    // Householder vector k in column k, rows k..N; H_k = I - 2 v vᵀ / vᵀv.
    let mut v = SMatrix::<f64, N, 3>::zeros();
    let mut vv = [0.0_f64; 3];
    for k in 0..3 {
        let norm = libm::sqrt((k..N).fold(0.0, |s, i| s + r[(i, k)] * r[(i, k)]));
        // The sign that avoids cancellation in v_k = x_k - alpha.
        let alpha = if r[(k, k)] >= 0.0 { -norm } else { norm };
        for i in k..N {
            v[(i, k)] = r[(i, k)];
        }
        v[(k, k)] -= alpha;
        vv[k] = (k..N).fold(0.0, |s, i| s + v[(i, k)] * v[(i, k)]);
        if vv[k] == 0.0 {
            continue;
        }
        for col in k..3 {
            let f = 2.0 * (k..N).fold(0.0, |s, i| s + v[(i, k)] * r[(i, col)]) / vv[k];
            for i in k..N {
                r[(i, col)] -= f * v[(i, k)];
            }
        }
    }
    let mut pinv = SMatrix::<f64, 3, N>::zeros();
    for col in 0..N {
        // y = Qᵀ e_col = H_2 H_1 H_0 e_col.
        let mut y = [0.0_f64; N];
        y[col] = 1.0;
        for k in 0..3 {
            if vv[k] == 0.0 {
                continue;
            }
            let f = 2.0 * (k..N).fold(0.0, |s, i| s + v[(i, k)] * y[i]) / vv[k];
            for i in k..N {
                y[i] -= f * v[(i, k)];
            }
        }
        // R z = y[0..3], back substitution (R upper triangular, non-singular at full rank).
        let z2 = y[2] / r[(2, 2)];
        let z1 = (y[1] - r[(1, 2)] * z2) / r[(1, 1)];
        let z0 = (y[0] - r[(0, 1)] * z1 - r[(0, 2)] * z2) / r[(0, 0)];
        pinv[(0, col)] = z0;
        pinv[(1, col)] = z1;
        pinv[(2, col)] = z2;
    }
    pinv
}

/// `max |F J − I|` with the yaw column of `J` (row of `F`) scaled by `length`, as for the
/// condition number; NaN or infinite if an entry of `F` is not finite.
fn identity_deviation<const N: usize>(
    forward: &SMatrix<f64, 3, N>,
    inverse: &SMatrix<f64, N, 3>,
    length: f64,
) -> f64 {
    let mut worst = 0.0_f64;
    for i in 0..3 {
        for j in 0..3 {
            let mut s = 0.0;
            for k in 0..N {
                s += forward[(i, k)] * inverse[(k, j)];
            }
            if i == 2 && j != 2 {
                s *= length;
            } else if j == 2 && i != 2 {
                s /= length;
            }
            let e = libm::fabs(s - if i == j { 1.0 } else { 0.0 });
            // `max` would drop a NaN.
            worst = if e > worst || e.is_nan() { e } else { worst };
        }
    }
    worst
}

/// The smallest and largest eigenvalue of a symmetric 3×3 matrix, by cyclic Jacobi rotations.
///
/// Jacobi is accurate to a few ulps of the largest eigenvalue for every eigenvalue, repeated
/// ones included (the closed-form trigonometric solution loses half the digits there), and
/// needs only arithmetic and `sqrt`, which are correctly rounded on every target: the figure
/// and the rank decision are the same on the host and the MCU.
fn symmetric_eigen_range<T: Real>(a: &Matrix3<T>) -> (T, T) {
    let mut m = *a;
    let two = T::lit(2.0);
    for _sweep in 0..32 {
        let off = m[(0, 1)] * m[(0, 1)] + m[(0, 2)] * m[(0, 2)] + m[(1, 2)] * m[(1, 2)];
        let diag = m[(0, 0)] * m[(0, 0)] + m[(1, 1)] * m[(1, 1)] + m[(2, 2)] * m[(2, 2)];
        let converged = off <= diag * T::EPSILON * T::EPSILON;
        if converged {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            let apq = m[(p, q)];
            if apq == T::zero() {
                continue;
            }
            // Rotation that zeroes m[(p, q)] (Golub & Van Loan, Algorithm 8.4.1).
            let theta = (m[(q, q)] - m[(p, p)]) / (two * apq);
            let root = (theta * theta + T::one()).sqrt_libm();
            let t = if theta >= T::zero() {
                T::one() / (theta + root)
            } else {
                -T::one() / (-theta + root)
            };
            let c = T::one() / (t * t + T::one()).sqrt_libm();
            let s = t * c;
            let mut rot = Matrix3::identity();
            rot[(p, p)] = c;
            rot[(q, q)] = c;
            rot[(p, q)] = s;
            rot[(q, p)] = -s;
            m = rot.transpose() * m * rot;
            m[(p, q)] = T::zero();
            m[(q, p)] = T::zero();
        }
    }
    let (d0, d1, d2) = (m[(0, 0)], m[(1, 1)], m[(2, 2)]);
    (d0.min(d1).min(d2), d0.max(d1).max(d2))
}
