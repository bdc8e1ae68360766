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
    /// π.
    const PI: Self;

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
    ($t:ty, $sincos:path, $acos:path, $cos:path, $sqrt:path, $rem:path) => {
        impl Real for $t {
            const EPSILON: Self = <$t>::EPSILON;
            const PI: Self = core::f64::consts::PI as $t;

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
    libm::sincosf,
    libm::acosf,
    libm::cosf,
    libm::sqrtf,
    libm::remainderf
);
impl_real!(
    f64,
    libm::sincos,
    libm::acos,
    libm::cos,
    libm::sqrt,
    libm::remainder
);

/// Wraps an angle to `[-π, π]` (IEEE remainder by 2π; `±π` both possible at the boundary).
#[inline]
#[must_use]
pub fn wrap_angle<T: Real>(angle: T) -> T {
    let pi = T::PI;
    if angle > pi || angle < -pi {
        angle.remainder_libm(pi + pi)
    } else {
        angle
    }
}
