//! Small dense linear algebra for the per-pixel fit: a symmetric positive definite system
//! by Cholesky, and the two-term non-negative least squares of the albedos.

/// Solve A x = b for symmetric positive definite `a` (N ≤ 8), or `None` if it is not.
pub(super) fn solve_spd<const N: usize>(a: &[[f64; N]; N], b: &[f64; N]) -> Option<[f64; N]> {
    let mut l = [[0.0; N]; N];
    for i in 0..N {
        for j in 0..=i {
            let mut s = a[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                if s <= 0.0 || !s.is_finite() {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    let mut y = [0.0; N];
    for i in 0..N {
        let s: f64 = (0..i).map(|k| l[i][k] * y[k]).sum();
        y[i] = (b[i] - s) / l[i][i];
    }
    let mut x = [0.0; N];
    for i in (0..N).rev() {
        let s: f64 = (i + 1..N).map(|k| l[k][i] * x[k]).sum();
        x[i] = (y[i] - s) / l[i][i];
    }
    Some(x)
}

/// The non-negative (a, b) minimising Σ wₖ (a uₖ + b vₖ − yₖ)², from the sums
/// (Σwu², Σwuv, Σwv², Σwuy, Σwvy).
pub(super) fn nonnegative_pair(uu: f64, uv: f64, vv: f64, uy: f64, vy: f64) -> (f64, f64) {
    let det = uu * vv - uv * uv;
    if det > 1e-12 * (uu * vv).max(1e-300) {
        let a = (uy * vv - vy * uv) / det;
        let b = (vy * uu - uy * uv) / det;
        if a >= 0.0 && b >= 0.0 {
            return (a, b);
        }
    }
    // One term alone: whichever leaves the smaller residual (Σwy² is common to both).
    let a_only = if uu > 0.0 { (uy / uu).max(0.0) } else { 0.0 };
    let b_only = if vv > 0.0 { (vy / vv).max(0.0) } else { 0.0 };
    let gain_a = a_only * uy;
    let gain_b = b_only * vy;
    if gain_a >= gain_b {
        (a_only, 0.0)
    } else {
        (0.0, b_only)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cholesky_solves_a_small_system() {
        let a = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let x = [1.0, -2.0, 0.5];
        let b = [0, 1, 2].map(|i| (0..3).map(|j| a[i][j] * x[j]).sum::<f64>());
        let got = solve_spd(&a, &b).unwrap();
        for k in 0..3 {
            assert!((got[k] - x[k]).abs() < 1e-12);
        }
        assert!(solve_spd(&[[1.0, 2.0], [2.0, 1.0]], &[1.0, 1.0]).is_none());
    }

    #[test]
    fn a_negative_term_is_dropped() {
        // y = 2u exactly, v unrelated and anti-correlated: b would come out negative.
        let (u, v) = ([1.0, 2.0, 3.0], [3.0, 1.0, 0.5]);
        let y = u.map(|x| 2.0 * x - 0.1);
        let s = |p: &[f64; 3], q: &[f64; 3]| (0..3).map(|k| p[k] * q[k]).sum::<f64>();
        let (a, b) = nonnegative_pair(s(&u, &u), s(&u, &v), s(&v, &v), s(&u, &y), s(&v, &y));
        assert!(a > 0.0 && b >= 0.0);
    }
}
