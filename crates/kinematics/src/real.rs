//! The scalar the crate computes in: `f32` or `f64`, with transcendental functions from libm.
//!
//! nalgebra's own `sin`/`cos`/`sqrt` resolve to std or to libm depending on which features
//! the *whole build* turned on (cargo unifies features, so a std crate elsewhere in the graph
//! switches them for everybody). The methods of [`Real`] always call libm, so a pose computed
//! on the host and on a Cortex-M4 has the same bits. Arithmetic (`+ - * /`) is IEEE 754 on
//! both and needs no help.

use nalgebra::RealField;

mod sealed {
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

/// A floating-point scalar: implemented for `f32` and `f64` only.
///
/// The extra methods are named `*_libm` so that they never collide with nalgebra's
/// [`ComplexField`](nalgebra::ComplexField) methods of the same purpose.
pub trait Real: RealField + Copy + Default + sealed::Sealed {
    /// Machine epsilon of the type.
    const EPSILON: Self;
    /// π, rounded to the type (`f32`: 3.1415927, above π by 8.7e-8).
    const PI: Self;
    /// 2π rounded to the type: the high part of a two-constant (Cody–Waite) split of 2π.
    /// It is exactly `2 PI`, so `x - TAU_HI` is exact for `PI <= x <= 2 TAU_HI` (Sterbenz).
    const TAU_HI: Self;
    /// `2π - TAU_HI` rounded to the type: the low part of the split (`f32`: −1.75e-7,
    /// `f64`: 2.4e-16). `TAU_HI + TAU_LO` is 2π within 7e-15 (`f32`) or 6e-33 (`f64`).
    const TAU_LO: Self;

    /// `(sin x, cos x)` from libm.
    fn sin_cos_libm(self) -> (Self, Self);
    /// `acos x` from libm.
    fn acos_libm(self) -> Self;
    /// `cos x` from libm.
    fn cos_libm(self) -> Self;
    /// `sqrt x` from libm (correctly rounded on every target).
    fn sqrt_libm(self) -> Self;
    /// IEEE `remainder(self, y)`: the value of `self - n y` with `n` the integer nearest `self / y`.
    fn remainder_libm(self, y: Self) -> Self;
    /// Converts an `f64` constant, rounding to nearest for `f32`.
    fn lit(x: f64) -> Self;
    /// Widens to `f64` (exact).
    fn to_f64(self) -> f64;
    /// `true` unless NaN or infinite.
    fn finite(self) -> bool;
}

macro_rules! impl_real {
    ($t:ty, $tau_lo:expr, $sincos:path, $acos:path, $cos:path, $sqrt:path, $rem:path) => {
        impl Real for $t {
            const EPSILON: Self = <$t>::EPSILON;
            const PI: Self = core::f64::consts::PI as $t;
            const TAU_HI: Self = core::f64::consts::TAU as $t;
            const TAU_LO: Self = $tau_lo;

            #[inline]
            fn sin_cos_libm(self) -> (Self, Self) {
                $sincos(self)
            }
            #[inline]
            fn acos_libm(self) -> Self {
                $acos(self)
            }
            #[inline]
            fn cos_libm(self) -> Self {
                $cos(self)
            }
            #[inline]
            fn sqrt_libm(self) -> Self {
                $sqrt(self)
            }
            #[inline]
            fn remainder_libm(self, y: Self) -> Self {
                $rem(self, y)
            }
            #[inline]
            #[allow(clippy::cast_possible_truncation)]
            fn lit(x: f64) -> Self {
                x as $t
            }
            #[inline]
            fn to_f64(self) -> f64 {
                f64::from(self)
            }
            #[inline]
            fn finite(self) -> bool {
                self.is_finite()
            }
        }
    };
}

impl_real!(
    f32,
    -1.748_455_5e-7,
    libm::sincosf,
    libm::acosf,
    libm::cosf,
    libm::sqrtf,
    libm::remainderf
);
impl_real!(
    f64,
    2.449_293_598_294_706_4e-16,
    libm::sincos,
    libm::acos,
    libm::cos,
    libm::sqrt,
    libm::remainder
);

/// Wraps an angle to `[-π, π]` (`±π` both possible at the boundary; `π` is [`Real::PI`]),
/// as an angle in radians reduced by the true 2π, not by 2π rounded to the type.
///
/// Reducing by the rounded 2π (`fl(2π)`, as `remainder(x, 2π)` does) is exact arithmetic
/// but subtracts the wrong period: in `f32`, `fl(2π)` is 1.75e-7 too large, which puts
/// `wrap_angle(1000.0)` 2.8e-5 rad off and drifts a heading by 1.75e-7 rad per turn. Here
/// 2π is split in two constants, `TAU_HI + TAU_LO` ([`Real::TAU_HI`], [`Real::TAU_LO`]):
///
/// - `|x| <= 3π` (every heading plus one step): `(x ∓ TAU_HI) ∓ TAU_LO`. The first
///   subtraction is exact, so the only errors are the rounding of the result (half an ulp)
///   and the 7e-15 (`f32`) by which `TAU_LO` misses `2π − TAU_HI`. Two additions and two
///   compares, in `T` only: cheap on a single-precision FPU such as the Cortex-M4F.
/// - larger `|x|`: `remainder(x, TAU_HI)` (exact) minus `k · TAU_LO` for the `k` turns it
///   removed. The error is one ulp of the result plus about `|x| · 5e-15` (`f32`) or
///   `|x| · 1e-32` (`f64`): an `f32` angle below 10⁵ rad is reduced to within 2e-7 rad.
///   (Beyond 2²⁶ rad in `f32`, 2⁵⁵ in `f64`, the input itself no longer resolves 2π.)
///
/// NaN and infinities give NaN. The same code and the same bits on every target.
#[inline]
#[must_use]
pub fn wrap_angle<T: Real>(angle: T) -> T {
    let pi = T::PI;
    // Written so that NaN takes the reduction (which returns NaN).
    if angle <= pi && angle >= -pi {
        return angle;
    }
    // One turn: `angle ∓ TAU_HI` is exact for PI < |angle| <= 2 TAU_HI (Sterbenz).
    let r = if angle > T::zero() {
        (angle - T::TAU_HI) - T::TAU_LO
    } else {
        (angle + T::TAU_HI) + T::TAU_LO
    };
    if r <= pi && r >= -pi {
        return r;
    }
    wrap_many_turns(angle)
}

/// [`wrap_angle`] for `|angle|` beyond about 3π (or NaN, infinite): out of line, so that the
/// common case inlines to a few instructions.
#[inline(never)]
fn wrap_many_turns<T: Real>(angle: T) -> T {
    let pi = T::PI;
    // Exact: angle - n TAU_HI for the integer n nearest angle / TAU_HI.
    let r = angle.remainder_libm(T::TAU_HI);
    // The turns removed, n, to a relative 2 ε (an integer is not needed: n TAU_LO is small
    // and its relative error is what counts).
    let turns = (angle - r) / T::TAU_HI;
    let r = r - turns * T::TAU_LO;
    // The low part may push a result next to ±π just past it: one more exact turn.
    if r > pi {
        (r - T::TAU_HI) - T::TAU_LO
    } else if r < -pi {
        (r + T::TAU_HI) + T::TAU_LO
    } else {
        r
    }
}
