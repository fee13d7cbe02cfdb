//! Least-squares (Poisson) integration on the mask.
//!
//! Unknowns: one height per mask pixel. Equations: for every pair of 4-adjacent mask pixels
//! `i → j` (j to the east or south of i), `z_j − z_i = g_ij`, with `g` the mean of the two
//! gradient samples (`(p_i + p_j)/2` horizontally, `(q_i + q_j)/2` vertically): the
//! trapezoidal rule, second-order accurate. Optionally each equation has a weight `w_ij`.
//!
//! Normal equations: `A z = b` with `A` the (weighted) graph Laplacian of the mask — natural
//! (Neumann) boundaries, no equation ever looks off the mask — and
//! `b_i = Σ_{edges into i} w g − Σ_{edges out of i} w g` (a discrete divergence).
//! `A` is singular with one constant per connected component; `b` is projected onto its
//! range and each component's mean is fixed afterwards by the caller.
//!
//! * Full-frame mask, unit weights: `A` is the Neumann Laplacian, diagonalised by the
//!   DCT-II, so the solve is direct and O(N log N).
//! * Otherwise: conjugate gradients preconditioned by one multigrid V-cycle
//!   ([`super::multigrid`]), stopping at `‖r‖ ≤ 1e-6 ‖b‖` or [`MAX_ITER`] iterations.

use super::fourier::transpose;
use super::multigrid::{self, Hierarchy, Stencil};
use rayon::prelude::*;
use rustdct::{DctPlanner, TransformType2And3};
use std::f64::consts::PI;
use std::sync::Arc;

/// Relative residual at which CG stops.
pub(super) const TOL: f64 = 1e-6;
/// Hard cap on CG iterations (a V-cycle preconditioner needs ~10; this only bounds time on
/// pathological inputs).
pub(super) const MAX_ITER: usize = 200;
/// Elements per rayon task in vector operations.
const CHUNK: usize = 1 << 14;

fn finite(v: f32) -> f64 {
    if v.is_finite() { f64::from(v) } else { 0.0 }
}

/// Right-hand side `b` of the normal equations for the operator `st` (computed in f64,
/// stored in f32).
pub(super) fn rhs<S: Stencil>(st: &S, p: &[f32], q: &[f32]) -> Vec<f32> {
    let (h, w) = st.dims();
    let mut b = vec![0f32; h * w];
    if h * w == 0 {
        return b;
    }
    let gx = |i: usize| 0.5 * (finite(p[i]) + finite(p[i + 1]));
    let gy = |i: usize| 0.5 * (finite(q[i]) + finite(q[i + w]));
    b.par_chunks_mut(w).enumerate().for_each(|(r, row)| {
        for (c, o) in row.iter_mut().enumerate() {
            let [we, ww, ws, wn] = st.weights(r, c);
            let i = r * w + c;
            let mut s = 0.0f64;
            if we > 0.0 {
                s -= f64::from(we) * gx(i);
            }
            if ww > 0.0 {
                s += f64::from(ww) * gx(i - 1);
            }
            if ws > 0.0 {
                s -= f64::from(ws) * gy(i);
            }
            if wn > 0.0 {
                s += f64::from(wn) * gy(i - w);
            }
            *o = s as f32;
        }
    });
    b
}

/// Apply a DCT-II (or III) to every length-`len` row, rows in parallel.
fn rows_dct(plan: &Arc<dyn TransformType2And3<f32>>, data: &mut [f32], len: usize, inverse: bool) {
    let scratch_len = plan.get_scratch_len();
    data.par_chunks_mut(len).with_min_len(8).for_each_init(
        || vec![0f32; scratch_len],
        |scratch, row| {
            if inverse {
                plan.process_dct3_with_scratch(row, scratch);
            } else {
                plan.process_dct2_with_scratch(row, scratch);
            }
        },
    );
}

/// Direct solve of the full-frame Neumann problem `A z = b` (zero-mean solution).
///
/// The DCT-II diagonalises the 1-D Neumann Laplacian with eigenvalues `2 − 2 cos(πk/n)`;
/// rustdct's DCT-III inverts the DCT-II up to a factor `n/2`.
pub(super) fn solve_dct(mut b: Vec<f32>, h: usize, w: usize) -> Vec<f32> {
    let n = h * w;
    if n == 0 {
        return b;
    }
    let mut planner = DctPlanner::new();
    let pw = planner.plan_dct2(w);
    let ph = planner.plan_dct2(h);
    rows_dct(&pw, &mut b, w, false);
    let mut t = vec![0f32; n];
    transpose(&b, h, w, &mut t); // t is w × h: t[l][k], l = x frequency, k = y frequency
    rows_dct(&ph, &mut t, h, false);
    let eig = |len: usize| -> Vec<f64> {
        (0..len)
            .map(|k| 2.0 - 2.0 * (PI * k as f64 / len as f64).cos())
            .collect()
    };
    let (ex, ey) = (eig(w), eig(h));
    t.par_chunks_mut(h).enumerate().for_each(|(l, row)| {
        for (k, v) in row.iter_mut().enumerate() {
            let lam = ex[l] + ey[k];
            *v = if lam > 0.0 {
                (f64::from(*v) / lam) as f32
            } else {
                0.0
            };
        }
    });
    rows_dct(&ph, &mut t, h, true);
    transpose(&t, w, h, &mut b);
    rows_dct(&pw, &mut b, w, true);
    let scale = 4.0 / n as f32;
    b.par_iter_mut().for_each(|v| *v *= scale);
    b
}

/// Convergence record of one CG solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct PcgStats {
    pub iterations: usize,
    pub rel_residual: f64,
    pub levels: usize,
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(a, b)| multigrid::dot_f64(a, b))
        .sum()
}

/// Conjugate gradients on `A z = b` (b already orthogonal to the null space), preconditioned
/// by a multigrid V-cycle. Storage: the solution, the residual, the search direction and one
/// shared vector for `M r` / `A p`, all f32; dot products in f64.
pub(super) fn solve_pcg<S: Stencil>(st: &S, b: Vec<f32>) -> (Vec<f32>, PcgStats) {
    let n = b.len();
    let mut r = b;
    let mut x = vec![0f32; n];
    let bnorm = dot(&r, &r).sqrt();
    let mut stats = PcgStats {
        iterations: 0,
        rel_residual: 0.0,
        levels: 0,
    };
    if bnorm == 0.0 || !bnorm.is_finite() {
        return (x, stats);
    }
    let mut hier = Hierarchy::new(st);
    stats.levels = hier.depth();
    stats.rel_residual = 1.0;
    let mut zq = vec![0f32; n]; // M r, then A p
    let mut p = vec![0f32; n];
    let mut rz = hier.apply(st, &r, &mut zq);
    let mut beta = 0.0f32;
    while stats.iterations < MAX_ITER {
        if !(rz > 0.0 && rz.is_finite()) {
            break;
        }
        let pap = multigrid::direction_apply(st, &mut zq, &mut p, beta); // p = z + βp, zq = A p
        if !(pap > 0.0 && pap.is_finite()) {
            break;
        }
        stats.iterations += 1;
        let alpha = (rz / pap) as f32;
        let rr: f64 = x
            .par_chunks_mut(CHUNK)
            .zip(r.par_chunks_mut(CHUNK))
            .zip(p.par_chunks(CHUNK).zip(zq.par_chunks(CHUNK)))
            .map(|((x, r), (p, ap))| {
                for (x, &p) in x.iter_mut().zip(p) {
                    *x += alpha * p;
                }
                for (r, &ap) in r.iter_mut().zip(ap) {
                    *r -= alpha * ap;
                }
                multigrid::dot_f64(r, r)
            })
            .sum();
        stats.rel_residual = rr.sqrt() / bnorm;
        if stats.rel_residual <= TOL {
            break;
        }
        let rz_new = hier.apply(st, &r, &mut zq); // zq = M r
        beta = (rz_new / rz) as f32;
        rz = rz_new;
    }
    (x, stats)
}
