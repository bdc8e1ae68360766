//! Wheel geometry and the inverse / forward wheel maps.
//!
//! A mecanum wheel can only push the chassis along the axis of the roller touching the ground;
//! motion along the roller is free. Wheel `i`, centred at `(a_x, a_y)` in the body frame, with
//! its axle at angle `α` from the body x axis, rollers at angle `δ` to the axle and radius `r`,
//! must turn at (seed 000, eq. 16)
//!
//! ```text
//! w_i = -1 / (r sin δ) · [cos(α+δ) vx + sin(α+δ) vy + (a_x sin(α+δ) - a_y cos(α+δ)) wz]
//! ```
//!
//! for the body to move with twist `(vx, vy, wz)`. Stacking one row per wheel gives the
//! inverse map `J` (N × 3). Row `i` is, up to scale, the Plücker coordinates of the line of
//! the roller axis in the ground plane, so `J` has rank 3 unless all roller axes meet in one
//! point or are all parallel (seed 000, Theorem 2). Such layouts are refused at construction.
//!
//! With more than three wheels the forward map is over-determined: the crate uses the
//! least-squares inverse `J⁺ = (JᵀJ)⁻¹Jᵀ`, computed once at construction. What it cannot
//! explain, the residual `w - J J⁺ w`, is a wheel disagreement: slip, a bad encoder or a
//! wrong wheel radius.

use nalgebra::{Matrix3, SMatrix, Vector3};

use crate::error::GeometryError;
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

    /// This wheel's row of the inverse map (seed 000, eq. 16), or why it has none.
    fn inverse_row(&self, wheel: usize) -> Result<[T; 3], GeometryError> {
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
        // A roller within ~1e-6 rad of the axle gives wheel speeds beyond any motor.
        if sin_delta.abs() < T::EPSILON.sqrt_libm() {
            return Err(GeometryError::RollerParallelToAxle {
                wheel,
                roller_angle: self.roller_angle.to_f64(),
            });
        }
        let (s, c) = (self.axle_angle + self.roller_angle).sin_cos_libm();
        let k = -T::one() / (self.radius * sin_delta);
        Ok([k * c, k * s, k * (self.x * s - self.y * c)])
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
    /// Inverse map `J`: body twist (vx, vy, wz) to wheel speeds.
    inverse: SMatrix<T, N, 3>,
    /// Least-squares forward map `J⁺ = (JᵀJ)⁻¹Jᵀ`.
    forward: SMatrix<T, 3, N>,
    condition: T,
}

impl<T: Real, const N: usize> MecanumKinematics<T, N> {
    /// The kinematics of a general layout, one [`WheelGeometry`] per wheel (seed 000, eq. 16).
    ///
    /// # Errors
    /// [`GeometryError`] for a non-finite parameter, a non-positive radius, a roller parallel
    /// to its axle, or a layout whose roller axes are concurrent or parallel (rank < 3).
    pub fn new(wheels: [WheelGeometry<T>; N]) -> Result<Self, GeometryError> {
        let mut inverse = SMatrix::<T, N, 3>::zeros();
        for (i, wheel) in wheels.iter().enumerate() {
            let row = wheel.inverse_row(i)?;
            for (j, v) in row.into_iter().enumerate() {
                inverse[(i, j)] = v;
            }
        }
        Self::from_inverse(wheels, inverse)
    }

    /// Completes construction from a validated inverse map: checks the rank, computes the
    /// conditioning figure and the least-squares forward map.
    fn from_inverse(
        wheels: [WheelGeometry<T>; N],
        inverse: SMatrix<T, N, 3>,
    ) -> Result<Self, GeometryError> {
        const { assert!(N >= 3, "a mecanum layout needs at least three wheels") };

        // Scale the yaw column by a characteristic length (RMS wheel distance from the
        // centre) so the conditioning figure has no units and does not change with them.
        let mean_sq = wheels
            .iter()
            .fold(T::zero(), |s, w| s + w.x * w.x + w.y * w.y)
            / T::lit(N as f64);
        let length = if mean_sq > T::zero() {
            mean_sq.sqrt_libm()
        } else {
            T::one()
        };
        let mut scaled = inverse;
        for i in 0..N {
            scaled[(i, 2)] /= length;
        }
        let (lo, hi) = symmetric_eigen_range(&(scaled.transpose() * scaled));
        // Rank < 3 within rounding: the smallest eigenvalue of JᵀJ (a singular value squared)
        // is lost in the noise of the largest.
        let full_rank = lo > hi * T::lit(64.0) * T::EPSILON;
        if !full_rank {
            let condition = if lo > T::zero() {
                (hi / lo).sqrt_libm().to_f64()
            } else {
                f64::INFINITY
            };
            return Err(GeometryError::Singular { condition });
        }
        let normal: Matrix3<T> = inverse.transpose() * inverse;
        let normal_inv = normal.try_inverse().ok_or(GeometryError::Singular {
            condition: f64::INFINITY,
        })?;
        Ok(Self {
            wheels,
            inverse,
            forward: normal_inv * inverse.transpose(),
            condition: (hi / lo).sqrt_libm(),
        })
    }

    /// The wheel geometry this map was built from.
    #[must_use]
    pub const fn wheels(&self) -> &[WheelGeometry<T>; N] {
        &self.wheels
    }

    /// The inverse map `J` (N × 3): wheel speeds (rad/s) = `J` · (vx, vy, wz).
    #[must_use]
    pub const fn inverse_matrix(&self) -> &SMatrix<T, N, 3> {
        &self.inverse
    }

    /// The least-squares forward map `J⁺` (3 × N).
    #[must_use]
    pub const fn forward_matrix(&self) -> &SMatrix<T, 3, N> {
        &self.forward
    }

    /// Condition number of the wheel map (≥ 1; 1 is ideal), with the yaw column scaled by the
    /// RMS wheel distance from the centre so the figure is dimensionless.
    ///
    /// It bounds how much a relative error in wheel speeds (encoder noise, slip) is amplified
    /// in the body velocity. The standard square layout with 45° rollers has `√2`;
    /// values far above 10 mean a badly conditioned layout.
    #[must_use]
    pub const fn condition_number(&self) -> T {
        self.condition
    }

    /// Inverse kinematics: the wheel speeds that move the body with `velocity`.
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

    /// Forward kinematics: the body velocity that best explains `speeds` (least squares).
    #[must_use]
    #[inline]
    pub fn forward(&self, speeds: &WheelSpeeds<T, N>) -> ChassisVelocity<T> {
        let v = self.solve(&speeds.0);
        ChassisVelocity::new(v.x, v.y, v.z)
    }

    /// Forward kinematics and the residual: per wheel, the measured speed minus the speed the
    /// fitted body velocity implies (rad/s). Zero when the wheels agree; its size is the slip
    /// signal. With exactly three wheels it is always zero.
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
    /// of the step) that best explains the wheel angle increments.
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
    /// The standard four-wheel layout (seed 002): wheels at `(±lx, ±ly)` in the order FL, FR,
    /// RL, RR, radius `r`, 45° rollers pointing to the centre seen from above.
    ///
    /// ```text
    /// FL = (vx - vy - (lx+ly) wz) / r      FR = (vx + vy + (lx+ly) wz) / r
    /// RL = (vx + vy - (lx+ly) wz) / r      RR = (vx - vy + (lx+ly) wz) / r
    /// ```
    ///
    /// The rows are filled in exactly; the geometry recorded is the equivalent general one
    /// (α = 90°, δ = +45° for FL and RR, −45° for FR and RL).
    ///
    /// # Errors
    /// [`GeometryError`] if a value is not finite, `r <= 0`, or `lx + ly == 0` (no yaw
    /// authority: singular).
    pub fn standard(lx: T, ly: T, r: T) -> Result<Self, GeometryError> {
        let q = T::PI * T::lit(0.25);
        let axle = q + q;
        let wheels = [
            WheelGeometry::new(lx, ly, axle, q, r),
            WheelGeometry::new(lx, -ly, axle, -q, r),
            WheelGeometry::new(-lx, ly, axle, -q, r),
            WheelGeometry::new(-lx, -ly, axle, q, r),
        ];
        for (i, w) in wheels.iter().enumerate() {
            w.inverse_row(i)?;
        }
        let k = lx + ly;
        let one = T::one();
        #[rustfmt::skip]
        let inverse = SMatrix::<T, 4, 3>::new(
            one, -one, -k,
            one,  one,  k,
            one,  one, -k,
            one, -one,  k,
        ) / r;
        Self::from_inverse(wheels, inverse)
    }
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
