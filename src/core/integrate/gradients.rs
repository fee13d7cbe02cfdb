//! The slopes the integrators take, from normals ([`gradients`]), and how far a slope
//! field is from integrable ([`curl`]), discretised as `poisson` sees it.

use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;

use super::poisson;
use crate::core::arrays::contiguous;

/// Smallest `nz` used when forming gradients. Grazing (or back-facing) normals would give
/// unbounded slopes; clamping `nz ≥ 0.05` bounds `|p|, |q| ≤ √(1 − 0.05²)/0.05 ≈ 20`
/// (a surface angle of ~87°), which keeps one bad pixel from dominating the solve.
pub const MIN_NZ: f32 = 0.05;

/// Gradients `(p, q) = (dz/dx, dz/dy) = (−nx/nz, −ny/nz)` from normals, zero off the mask.
///
/// Normals are renormalised first, `nz` is clamped to at least [`MIN_NZ`] (slopes ≤ ~20);
/// zero-length or non-finite normals give zero gradients.
pub fn gradients(normals: &Array3<f32>, mask: &Array2<bool>) -> (Array2<f32>, Array2<f32>) {
    let (h, w) = mask.dim();
    assert_eq!(normals.dim(), (h, w, 3), "normals must be (rows, cols, 3)");
    let mut p = Array2::zeros((h, w));
    let mut q = Array2::zeros((h, w));
    let (mask, normals) = (contiguous(mask.view()), contiguous(normals.view()));
    // Row slices, split into x, y, z lanes so the divisions vectorise: through ndarray's
    // per-pixel lane views this pass cost as much as the curl.
    (p.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(q.axis_iter_mut(Axis(0)).into_par_iter())
        .enumerate()
        .for_each_init(
            || [vec![0f32; w], vec![0f32; w], vec![0f32; w]],
            |[nx, ny, nz], (r, (mut p, mut q))| {
                let fresh = "a row of a fresh array is contiguous";
                let (p, q) = (
                    p.as_slice_mut().expect(fresh),
                    q.as_slice_mut().expect(fresh),
                );
                let n = &normals[r * w * 3..(r + 1) * w * 3];
                for (((x, y), z), n) in nx
                    .iter_mut()
                    .zip(ny.iter_mut())
                    .zip(nz.iter_mut())
                    .zip(n.chunks_exact(3))
                {
                    (*x, *y, *z) = (n[0], n[1], n[2]);
                }
                gradient_row(nx, ny, nz, &mask[r * w..(r + 1) * w], p, q);
            },
        );
    (p, q)
}

multiversion! {
    fn gradient_row(
        nx: &[f32], ny: &[f32], nz: &[f32], m: &[bool], p: &mut [f32], q: &mut [f32],
    ) -> () => gradient_row_body
}

/// One row of [`gradients`]: every pixel is computed and the ones off the mask (or with
/// an unusable normal) get 0, so the loop has no branch.
#[inline(always)]
fn gradient_row_body(nx: &[f32], ny: &[f32], nz: &[f32], m: &[bool], p: &mut [f32], q: &mut [f32]) {
    let lanes = nx.iter().zip(ny).zip(nz).zip(m);
    for (((((&nx, &ny), &nz), &m), p), q) in lanes.zip(p.iter_mut()).zip(q.iter_mut()) {
        let len = (nx * nx + ny * ny + nz * nz).sqrt();
        let usable = m & len.is_finite() & (len != 0.0);
        let nz = (nz / len).max(MIN_NZ);
        *p = if usable { -nx / len / nz } else { 0.0 };
        *q = if usable { -ny / len / nz } else { 0.0 };
    }
}

/// Integrability residual `dp/dy − dq/dx` of the gradient field, discretised exactly as
/// `poisson` sees it: the circulation of the edge gradients around the unit square whose
/// top-left pixel is `(r, c)`,
/// `(gx[r+1][c] − gx[r][c]) − (gy[r][c+1] − gy[r][c])` with `gx`, `gy` the edge slopes.
/// It is zero for any discretely integrable field; 0 where any of the four pixels is off
/// the mask (or outside the frame).
pub fn curl(p: &Array2<f32>, q: &Array2<f32>, mask: &Array2<bool>) -> Array2<f32> {
    let (h, w) = mask.dim();
    assert_eq!(p.dim(), (h, w));
    assert_eq!(q.dim(), (h, w));
    let mut out = vec![0f32; h * w];
    if h < 2 || w < 2 {
        return Array2::from_shape_vec((h, w), out).expect("shape matches");
    }
    let (p, q, m) = (
        contiguous(p.view()),
        contiguous(q.view()),
        contiguous(mask.view()),
    );
    out.par_chunks_mut(w).take(h - 1).enumerate().for_each_init(
        || [(); 2].map(|_| vec![0f32; w]),
        |[na, nb], (r, o)| curl_row(&p, &q, &m, r, [na, nb], o),
    );
    Array2::from_shape_vec((h, w), out).expect("shape matches")
}

multiversion! {
    fn curl_row<M: AsRef<[bool]>>(
        p: &[f32], q: &[f32], m: &M, r: usize, nz: [&mut Vec<f32>; 2], o: &mut [f32],
    ) -> () => curl_row_body
}

/// Row `r` of [`curl`]; `nz` receives the weights ([`poisson::normal_z`]) of rows `r` and
/// `r + 1`, formed once per pixel (vectorised) rather than once per edge end.
#[inline(always)]
fn curl_row_body<M: AsRef<[bool]>>(
    p: &[f32],
    q: &[f32],
    m: &M,
    r: usize,
    nz: [&mut Vec<f32>; 2],
    o: &mut [f32],
) {
    use self::poisson::{normal_z, weighted_slope};
    let (m, w) = (m.as_ref(), o.len());
    let (i, j) = (r * w, (r + 1) * w);
    let [na, nb] = nz;
    let (pa, pb, qa, qb) = (&p[i..i + w], &p[j..j + w], &q[i..i + w], &q[j..j + w]);
    for (n, p, q) in [(&mut *na, pa, qa), (&mut *nb, pb, qb)] {
        let n = &mut n[..w];
        for c in 0..w {
            n[c] = normal_z(p[c], q[c]);
        }
    }
    let (ma, mb) = (&m[i..i + w], &m[j..j + w]);
    for c in 0..w - 1 {
        if ma[c] && ma[c + 1] && mb[c] && mb[c + 1] {
            let dpy = weighted_slope(nb[c], pb[c], nb[c + 1], pb[c + 1])
                - weighted_slope(na[c], pa[c], na[c + 1], pa[c + 1]);
            let dqx = weighted_slope(na[c + 1], qa[c + 1], nb[c + 1], qb[c + 1])
                - weighted_slope(na[c], qa[c], nb[c], qb[c]);
            o[c] = dpy - dqx;
        }
    }
}
