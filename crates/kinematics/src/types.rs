//! Value types with units: body velocities, per-wheel quantities, displacements and poses.
//!
//! All are plain `Copy` data with public fields; the units are in the field docs. Wheel
//! arrays are in layout order, which for the standard 4-wheel layout is FL, FR, RL, RR.

use crate::real::{Real, wrap_angle};

/// A body velocity (twist rate) in the body frame: x forward, y left, yaw counter-clockwise.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ChassisVelocity<T> {
    /// Forward speed, m/s.
    pub vx: T,
    /// Leftward speed, m/s.
    pub vy: T,
    /// Yaw rate, rad/s, counter-clockwise seen from above.
    pub wz: T,
}

impl<T: Real> ChassisVelocity<T> {
    /// A body velocity from its components (m/s, m/s, rad/s).
    #[must_use]
    pub const fn new(vx: T, vy: T, wz: T) -> Self {
        Self { vx, vy, wz }
    }

    /// The body displacement after moving at this velocity for `dt` seconds.
    #[must_use]
    pub fn times(self, dt: T) -> Twist2<T> {
        Twist2::new(self.vx * dt, self.vy * dt, self.wz * dt)
    }

    /// `true` if every component is finite.
    #[must_use]
    pub fn is_finite(&self) -> bool {
        self.vx.finite() && self.vy.finite() && self.wz.finite()
    }
}

macro_rules! per_wheel {
    ($(#[$doc:meta])* $name:ident, $unit:literal) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq)]
        pub struct $name<T, const N: usize>(
            #[doc = concat!("One value per wheel in layout order, ", $unit, ".")] pub [T; N],
        );

        impl<T: Real, const N: usize> $name<T, N> {
            /// All wheels zero.
            #[must_use]
            pub fn zero() -> Self {
                Self([T::zero(); N])
            }

            /// The values in layout order.
            #[must_use]
            pub const fn as_array(&self) -> &[T; N] {
                &self.0
            }

            /// The largest magnitude over all wheels (NaN entries are skipped).
            #[must_use]
            pub fn max_abs(&self) -> T {
                self.0.iter().fold(T::zero(), |m, &w| {
                    let a = w.abs();
                    if a > m { a } else { m }
                })
            }

            /// Root mean square over the wheels.
            #[must_use]
            pub fn rms(&self) -> T {
                let sum = self.0.iter().fold(T::zero(), |s, &w| s + w * w);
                (sum / T::lit(N as f64)).sqrt_libm()
            }
        }

        impl<T: Real> $name<T, 4> {
            #[doc = concat!("Four wheels in the order FL, FR, RL, RR, ", $unit, ".")]
            #[must_use]
            pub const fn new(fl: T, fr: T, rl: T, rr: T) -> Self {
                Self([fl, fr, rl, rr])
            }
            /// Front left.
            #[must_use]
            pub const fn fl(&self) -> T {
                self.0[0]
            }
            /// Front right.
            #[must_use]
            pub const fn fr(&self) -> T {
                self.0[1]
            }
            /// Rear left.
            #[must_use]
            pub const fn rl(&self) -> T {
                self.0[2]
            }
            /// Rear right.
            #[must_use]
            pub const fn rr(&self) -> T {
                self.0[3]
            }
        }
    };
}

per_wheel!(
    /// Wheel angular speeds, rad/s; positive rolls the robot forward.
    WheelSpeeds,
    "rad/s"
);

per_wheel!(
    /// Wheel angle increments over one step, rad; positive rolls the robot forward.
    WheelDeltas,
    "rad"
);

impl<T: Real, const N: usize> WheelSpeeds<T, N> {
    /// Scales all wheels by one factor so that none exceeds `max_speed` in magnitude.
    ///
    /// One common factor keeps the ratios between the wheels, so the direction of travel and
    /// the centre of rotation are kept; only the overall speed drops (as FTC mecanum tutorials do,
    /// "power normalisation"). Wheels already within the limit are returned unchanged.
    ///
    /// The limit holds for every output, always: the factor `max_speed / peak` is rounded,
    /// so each scaled wheel is also limited to `[-max_speed, max_speed]` (which moves the
    /// peak wheel by at most one ulp, onto the limit). Two inputs stop every wheel (all
    /// zero, a safe stop) rather than command something unintended:
    ///
    /// - a limit that is zero, negative or NaN;
    /// - any wheel that is NaN or infinite: there is no finite factor that scales it, and the
    ///   other wheels' speeds mean nothing without it.
    #[must_use]
    pub fn desaturate(self, max_speed: T) -> Self {
        // Written so that NaN takes the stop branch.
        let positive = max_speed > T::zero();
        if !positive || !self.0.iter().all(|w| w.finite()) {
            return Self::zero();
        }
        let peak = self.max_abs();
        if peak > max_speed {
            let k = max_speed / peak;
            // `min`/`max`, not `clamp`: no panic path (and no float formatting) on the MCU.
            Self(self.0.map(|w| (w * k).min(max_speed).max(-max_speed)))
        } else {
            self
        }
    }

    /// The angle increments after turning at these speeds for `dt` seconds.
    #[must_use]
    pub fn times(self, dt: T) -> WheelDeltas<T, N> {
        WheelDeltas(self.0.map(|w| w * dt))
    }
}

/// A body displacement over one step, in the body frame at the start of the step: the
/// element of se(2) that the SE(2) exponential turns into a pose change.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Twist2<T> {
    /// Forward displacement, m.
    pub dx: T,
    /// Leftward displacement, m.
    pub dy: T,
    /// Heading change, rad, counter-clockwise.
    pub dtheta: T,
}

impl<T: Real> Twist2<T> {
    /// A displacement from its components (m, m, rad).
    #[must_use]
    pub const fn new(dx: T, dy: T, dtheta: T) -> Self {
        Self { dx, dy, dtheta }
    }
}

/// A planar pose: position in the odometry frame and heading of the body x axis.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pose2<T> {
    /// Position along the odometry frame's x axis, m.
    pub x: T,
    /// Position along the odometry frame's y axis, m.
    pub y: T,
    /// Heading, rad, counter-clockwise from the odometry x axis, kept in `[-π, π]`.
    pub heading: T,
}

impl<T: Real> Pose2<T> {
    /// A pose from its components; the heading is wrapped to `[-π, π]`.
    #[must_use]
    pub fn new(x: T, y: T, heading: T) -> Self {
        Self {
            x,
            y,
            heading: wrap_angle(heading),
        }
    }

    /// The pose reached by moving along `twist` (given in this pose's body frame) on the arc
    /// of constant velocity: `self · exp(twist)` on SE(2).
    ///
    /// Exact for any step size, not a first-order (Euler) update. The arc's chord has length
    /// `|(dx, dy)| · sinc(dθ/2)` and points along the mean heading `heading + dθ/2`, which is
    /// the closed form of the SE(2) exponential written so that it needs one `sin_cos` and
    /// one `sin` and suffers no cancellation near `dθ = 0` (a series is used below 1e-3 rad).
    ///
    /// A zero displacement (a step in which no wheel turned) skips the trigonometry when
    /// that gives the same bits: with `x`, `y` finite and non-zero and a finite heading, the
    /// terms added to `x` and `y` are zeros, which leave them exactly as they are.
    #[must_use]
    #[inline]
    pub fn exp(self, twist: Twist2<T>) -> Self {
        let zero = T::zero();
        if twist.dx == zero
            && twist.dy == zero
            && twist.dtheta == zero
            && self.x != zero
            && self.y != zero
            && self.x.finite()
            && self.y.finite()
            && self.heading.finite()
        {
            return Self {
                x: self.x,
                y: self.y,
                heading: wrap_angle(self.heading + twist.dtheta),
            };
        }
        self.exp_arc(twist)
    }

    /// The body displacement that [`exp`](Self::exp) turns into this pose from the origin:
    /// the SE(2) logarithm, `Pose2::default().exp(p.log()) == p` (within rounding).
    ///
    /// With [`relative`](Self::relative) it gives the increment of a motion between two poses
    /// in the body frame of the first, the arc of constant body velocity that joins them:
    /// `a.relative(b).log()`. The heading is in `[-π, π]`, so the displacement is the one
    /// that turns by less than half a turn either way.
    #[must_use]
    pub fn log(self) -> Twist2<T> {
        let half = self.heading * T::lit(0.5);
        let (sin_h, cos_h) = half.sin_cos_libm();
        let sinc_half = sinc(half);
        Twist2::new(
            (cos_h * self.x + sin_h * self.y) / sinc_half,
            (cos_h * self.y - sin_h * self.x) / sinc_half,
            self.heading,
        )
    }

    /// `to` seen from this pose, `self⁻¹ · to` on SE(2): its position in this pose's body
    /// frame and the heading change from this pose to it (wrapped to `[-π, π]`).
    #[must_use]
    pub fn relative(self, to: Self) -> Self {
        let (sin_t, cos_t) = self.heading.sin_cos_libm();
        let (dx, dy) = (to.x - self.x, to.y - self.y);
        Self::new(
            cos_t * dx + sin_t * dy,
            cos_t * dy - sin_t * dx,
            to.heading - self.heading,
        )
    }

    /// [`exp`](Self::exp) by the closed form: kept out of line, so that inlining `exp` only
    /// brings the zero-step test into the caller.
    #[inline(never)]
    fn exp_arc(self, twist: Twist2<T>) -> Self {
        let half = twist.dtheta * T::lit(0.5);
        let (sin_mid, cos_mid) = (self.heading + half).sin_cos_libm();
        let sinc_half = sinc(half);
        let dx = twist.dx * sinc_half;
        let dy = twist.dy * sinc_half;
        Self {
            x: self.x + cos_mid * dx - sin_mid * dy,
            y: self.y + sin_mid * dx + cos_mid * dy,
            heading: wrap_angle(self.heading + twist.dtheta),
        }
    }
}

/// `sin(h) / h`, by its series below 1e-3 rad.
#[inline]
fn sinc<T: Real>(h: T) -> T {
    if h.abs() < T::lit(1e-3) {
        // sin(h)/h = 1 - h²/6 + h⁴/120 - …; the next term, h⁶/5040, is below 2e-22.
        let h2 = h * h;
        T::one() - h2 / T::lit(6.0) * (T::one() - h2 / T::lit(20.0))
    } else {
        h.sin_cos_libm().0 / h
    }
}
