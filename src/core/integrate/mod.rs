//! Heights from normals: gradients `p = −nx/nz`, `q = −ny/nz`, then one of several
//! integrators.
//!
//! Frame: arrays are `[row, col]`; x = column (right), y = row (down), z towards the camera.
//! `p = dz/dx` (along columns), `q = dz/dy` (along rows); heights are in pixel units.
//!
//! Discretisation shared by `poisson` and `frankot-chellappa` (and by [`curl`]): the height
//! difference across the edge between two 4-adjacent pixels is the mean of their two
//! gradient samples (`z[r][c+1] − z[r][c] = (p[r][c] + p[r][c+1]) / 2`), i.e. the
//! trapezoidal rule — second-order accurate where the one-sided `path` rule is first-order.
//!
//! | method | domain | solver | cost |
//! |---|---|---|---|
//! | `path` | mask, one path per pixel | running sums (the seed's) | O(N), poor |
//! | `frankot-chellappa` | full periodic frame, 0 off mask | FFT projection | O(N log N) |
//! | `poisson` | mask only (Neumann) | DCT on a full mask, else multigrid-PCG | ≈ O(N) |

mod components;
mod fourier;
mod multigrid;
mod path;
mod poisson;

use ndarray::{Array2, Array3, ArrayView2, Axis, Zip};
use std::borrow::Cow;

use self::components::Components;
use self::multigrid::{MaskStencil, WeightStencil};
use super::options::Integration;

/// Smallest `nz` used when forming gradients. Grazing (or back-facing) normals would give
/// unbounded slopes; clamping `nz ≥ 0.05` bounds `|p|, |q| ≤ √(1 − 0.05²)/0.05 ≈ 20`
/// (a surface angle of ~87°), which keeps one bad pixel from dominating the solve.
pub const MIN_NZ: f32 = 0.05;

/// Lower bound of an edge weight in [`integrate_weighted`]: zero-confidence pixels stay
/// connected (so the answer is well defined) but barely constrain the surface.
pub const MIN_EDGE_WEIGHT: f32 = 1e-3;

/// Gradients `(p, q) = (dz/dx, dz/dy) = (−nx/nz, −ny/nz)` from normals, zero off the mask.
///
/// Normals are renormalised first, `nz` is clamped to at least [`MIN_NZ`] (slopes ≤ ~20);
/// zero-length or non-finite normals give zero gradients.
pub fn gradients(normals: &Array3<f32>, mask: &Array2<bool>) -> (Array2<f32>, Array2<f32>) {
    let (h, w) = mask.dim();
    assert_eq!(normals.dim(), (h, w, 3), "normals must be (rows, cols, 3)");
    let mut p = Array2::zeros((h, w));
    let mut q = Array2::zeros((h, w));
    Zip::from(&mut p)
        .and(&mut q)
        .and(normals.lanes(Axis(2)))
        .and(mask)
        .par_for_each(|p, q, n, &m| {
            let (nx, ny, nz) = (n[0], n[1], n[2]);
            let len = (nx * nx + ny * ny + nz * nz).sqrt();
            if !m || !len.is_finite() || len == 0.0 {
                return;
            }
            let nz = (nz / len).max(MIN_NZ);
            *p = -nx / len / nz;
            *q = -ny / len / nz;
        });
    (p, q)
}

/// Integrability residual `dp/dy − dq/dx` of the gradient field, discretised exactly as the
/// integrators see it: the circulation of the edge gradients around the unit square whose
/// top-left pixel is `(r, c)`,
/// `(gx[r+1][c] − gx[r][c]) − (gy[r][c+1] − gy[r][c])` with `gx`, `gy` the edge means.
/// It is zero for any discretely integrable field; 0 where any of the four pixels is off
/// the mask (or outside the frame).
pub fn curl(p: &Array2<f32>, q: &Array2<f32>, mask: &Array2<bool>) -> Array2<f32> {
    let (h, w) = mask.dim();
    assert_eq!(p.dim(), (h, w));
    assert_eq!(q.dim(), (h, w));
    Array2::from_shape_fn((h, w), |(r, c)| {
        if r + 1 >= h
            || c + 1 >= w
            || !(mask[(r, c)] && mask[(r, c + 1)] && mask[(r + 1, c)] && mask[(r + 1, c + 1)])
        {
            return 0.0;
        }
        let dpy = (p[(r + 1, c)] + p[(r + 1, c + 1)]) - (p[(r, c)] + p[(r, c + 1)]);
        let dqx = (q[(r, c + 1)] + q[(r + 1, c + 1)]) - (q[(r, c)] + q[(r + 1, c)]);
        0.5 * (dpy - dqx)
    })
}

/// Heights in pixel units from gradients, over the mask; off-mask pixels get the lowest
/// height on the mask; an empty mask gives all zeros.
///
/// Offsets: `poisson` sets each connected component's mean height to 0 (components are
/// independent surfaces); `frankot-chellappa` has zero mean over the whole frame; `path`
/// starts at 0 in the top-left corner.
pub fn integrate(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    method: Integration,
) -> Array2<f32> {
    let (h, w) = mask.dim();
    assert_eq!(p.dim(), (h, w));
    assert_eq!(q.dim(), (h, w));
    let m = contiguous(mask.view());
    if !m.iter().any(|&v| v) {
        return Array2::zeros((h, w));
    }
    // Gradients off the mask are ignored (`poisson`, `path`) or taken as 0 (`frankot-chellappa`).
    let masked = |a: &Array2<f32>| -> Vec<f32> {
        a.iter()
            .zip(mask.iter())
            .map(|(&v, &m)| if m && v.is_finite() { v } else { 0.0 })
            .collect()
    };
    let (ps, qs) = (masked(p), masked(q));
    let z = match method {
        Integration::Path => path::integrate(&ps, &qs, &m, h, w),
        Integration::FrankotChellappa => fourier::frankot_chellappa(&ps, &qs, h, w),
        Integration::Poisson => poisson_heights(&ps, &qs, &m, h, w, None),
    };
    finish(z, &m, h, w)
}

/// Weighted least-squares Poisson integration: as `poisson`, but the equation on the edge
/// between pixels `i` and `j` has weight `max((w_i + w_j)/2, MIN_EDGE_WEIGHT)` with the
/// per-pixel weights clamped to `[0, 1]` (e.g. a confidence map; non-finite → 0). Low
/// confidence regions then follow their neighbours instead of their own gradients.
pub fn integrate_weighted(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    weights: &Array2<f32>,
) -> Array2<f32> {
    let (h, w) = mask.dim();
    assert_eq!(p.dim(), (h, w));
    assert_eq!(q.dim(), (h, w));
    assert_eq!(weights.dim(), (h, w));
    let m = contiguous(mask.view());
    if !m.iter().any(|&v| v) {
        return Array2::zeros((h, w));
    }
    let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
    let wt = contiguous(weights.view());
    let z = poisson_heights(&ps, &qs, &m, h, w, Some(&wt));
    finish(z, &m, h, w)
}

/// Row-major data of a 2-D view (borrowed when already contiguous).
fn contiguous<T: Clone>(a: ArrayView2<'_, T>) -> Cow<'_, [T]> {
    match a.to_slice() {
        Some(s) => Cow::Borrowed(s),
        None => Cow::Owned(a.iter().cloned().collect()),
    }
}

/// Poisson heights, each mask component shifted to zero mean.
fn poisson_heights(
    p: &[f32],
    q: &[f32],
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
) -> Vec<f32> {
    let comps = Components::new(mask, h, w);
    let mut z = match weights {
        None if mask.iter().all(|&m| m) => {
            let st = MaskStencil::new(mask, h, w);
            poisson::solve_dct(poisson::rhs(&st, p, q), h, w)
        }
        None => solve_masked(&MaskStencil::new(mask, h, w), p, q, &comps),
        Some(wt) => solve_masked(
            &WeightStencil::from_pixel_weights(mask, wt, h, w, MIN_EDGE_WEIGHT),
            p,
            q,
            &comps,
        ),
    };
    comps.remove_means(&mut z);
    z
}

fn solve_masked<S: multigrid::Stencil>(
    st: &S,
    p: &[f32],
    q: &[f32],
    comps: &Components,
) -> Vec<f32> {
    let mut b = poisson::rhs(st, p, q);
    // b sums to 0 on each component in exact arithmetic; remove the round-off so that the
    // singular system is consistent.
    comps.remove_means(&mut b);
    let (z, stats) = poisson::solve_pcg(st, b);
    tracing::debug!(
        iterations = stats.iterations,
        rel_residual = stats.rel_residual,
        levels = stats.levels,
        "poisson: multigrid-preconditioned CG"
    );
    z
}

/// Off-mask pixels := the lowest height on the mask.
fn finish(mut z: Vec<f32>, mask: &[bool], h: usize, w: usize) -> Array2<f32> {
    let low = z
        .iter()
        .zip(mask)
        .filter(|&(v, &m)| m && v.is_finite())
        .map(|(&v, _)| v)
        .fold(f32::INFINITY, f32::min);
    let low = if low.is_finite() { low } else { 0.0 };
    for (v, &m) in z.iter_mut().zip(mask) {
        if !m || !v.is_finite() {
            *v = low;
        }
    }
    Array2::from_shape_vec((h, w), z).expect("shape matches")
}

#[cfg(test)]
mod tests;
