//! The numerics behind a pod layout's acceptance: the size of the layout, the 3 × 3 inverse
//! and its condition number, why a singular layout is singular, and the check that what `T`
//! holds of the solver still inverts the model.

use super::PodGeometry;
use crate::error::PodLayoutError;
use crate::real::Real;

/// `1 / (8 √ε)`: the largest condition number accepted for a type of machine epsilon `eps`
/// (as for the wheel maps).
pub(super) fn max_condition(eps: f64) -> f64 {
    1.0 / libm::sqrt(64.0 * eps)
}

/// [`PodLayoutError::Unrepresentable`], NaN reported as infinite.
pub(super) fn unrepresentable(deviation: f64) -> PodLayoutError {
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
pub(super) fn rms_distance<T: Real, const N: usize>(pods: &[PodGeometry<T>; N]) -> f64 {
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
pub(super) fn inverse3(m: &[[f64; 3]; 3]) -> ([[f64; 3]; 3], f64) {
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
pub(super) fn pair_condition(a: &[f64; 3], b: &[f64; 3]) -> (f64, f64, f64) {
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
pub(super) fn classify(
    scaled: &[[f64; 3]; 3],
    length: f64,
    condition: f64,
    limit: f64,
) -> PodLayoutError {
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
pub(super) fn scale_solver<T: Real>(solver: &[[T; 3]; 3], length: f64) -> [[f64; 3]; 3] {
    let mut back = solver.map(|r| r.map(Real::to_f64));
    for v in &mut back[2] {
        *v *= length;
    }
    back
}

/// Checks `max |F M − I| <= 32 · 3 · condition · ε` of `T` (the allowance of the wheel maps),
/// with `F` the rounded solver (scaled back) and `M` the scaled model; else
/// [`PodLayoutError::Unrepresentable`].
pub(super) fn check_inverse<T: Real>(
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
