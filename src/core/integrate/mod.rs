//! Heights from normals: gradients `p = −nx/nz`, `q = −ny/nz`, then one of several
//! integrators.
//!
//! Frame: arrays are `[row, col]`; x = column (right), y = row (down), z towards the camera.
//! `p = dz/dx` (along columns), `q = dz/dy` (along rows); heights are in pixel units.
//!
//! Discretisation of `poisson` (and of [`curl`]): the height difference across the edge
//! between two 4-adjacent pixels is the slope of the mean of their two normals — the two
//! gradient samples averaged with weights `n_z` (`poisson::edge_slope`). On gentle slopes
//! that is the trapezoidal rule (`z[r][c+1] − z[r][c] = (p[r][c] + p[r][c+1]) / 2`, which
//! `frankot-chellappa` uses in its spectral form); near a silhouette, where `p ~ 1/n_z`
//! grows without bound, the plain mean overshoots by pixels per edge while the mean normal
//! gives the chord of the local circle. Both are second-order accurate where the one-sided
//! `path` rule is first-order.
//!
//! | method | domain | solver | cost |
//! |---|---|---|---|
//! | `path` | mask, one path per pixel | running sums (the seed's) | O(N), poor |
//! | `frankot-chellappa` | full periodic frame, 0 off mask | FFT projection | O(N log N) |
//! | `poisson` | mask only (Neumann) | DCT on a full mask, else multigrid-PCG | ≈ O(N) |

mod bilateral;
mod components;
mod crop;
mod fourier;
mod multigrid;
mod path;
pub mod perspective;
mod poisson;

use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;

use self::components::Components;
use self::multigrid::{MaskStencil, WeightStencil};
use self::poisson::{largest_change, solve_masked};
use super::camera::Pinhole;
use super::contiguous;
use super::histogram::nth_nonnegative;
use super::options::Integration;
use super::progress::{Halt, NEVER};

/// Smallest `nz` used when forming gradients. Grazing (or back-facing) normals would give
/// unbounded slopes; clamping `nz ≥ 0.05` bounds `|p|, |q| ≤ √(1 − 0.05²)/0.05 ≈ 20`
/// (a surface angle of ~87°), which keeps one bad pixel from dominating the solve.
pub const MIN_NZ: f32 = 0.05;

pub use self::multigrid::MIN_EDGE_WEIGHT;

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

/// Heights in pixel units from gradients, over the mask; off-mask pixels get the lowest
/// height on the mask; an empty mask gives all zeros.
///
/// Offsets (before the background fill): `poisson` sets each connected component's mean
/// height to 0 (components are independent surfaces); `frankot-chellappa` has zero mean over
/// the whole frame; `path` starts at 0 in the top-left corner.
pub fn integrate(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    method: Integration,
) -> Array2<f32> {
    integrate_until(p, q, mask, method, NEVER)
}

/// [`integrate`], stopping early (with meaningless heights) once `halt` says stop.
pub fn integrate_until(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    method: Integration,
    halt: Halt,
) -> Array2<f32> {
    let (h, w) = mask.dim();
    assert_eq!(p.dim(), (h, w));
    assert_eq!(q.dim(), (h, w));
    let m = contiguous(mask.view());
    if !m.iter().any(|&v| v) {
        return Array2::zeros((h, w));
    }
    let z = match method {
        Integration::RobustPoisson => {
            let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
            robust_poisson(&ps, &qs, &m, h, w, None, halt)
        }
        Integration::Bilateral => {
            let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
            bilateral_heights(&ps, &qs, &m, h, w, None, halt)
        }
        // Without a confidence map every pixel weighs the same: plain `poisson`.
        Integration::Poisson | Integration::WeightedPoisson => {
            // Only gradients between mask pixels are read.
            let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
            poisson_heights(&ps, &qs, &m, h, w, None, halt)
        }
        Integration::Path | Integration::FrankotChellappa => {
            // Gradients off the mask (and non-finite ones) count as 0.
            let masked = |a: &Array2<f32>| -> Vec<f32> {
                let mut v = contiguous(a.view()).into_owned();
                v.par_iter_mut().zip(m.par_iter()).for_each(|(v, &m)| {
                    if !m || !v.is_finite() {
                        *v = 0.0;
                    }
                });
                v
            };
            let (ps, qs) = (masked(p), masked(q));
            if method == Integration::Path {
                path::integrate(&ps, &qs, &m, h, w)
            } else {
                fourier::frankot_chellappa(&ps, &qs, h, w)
            }
        }
    };
    finish(z, &m, h, w)
}

/// Heights by `method`, where `weighted-poisson`, `robust-poisson` and `bilateral` take their weights
/// from `confidence` (the solver's per-pixel reliability) and every other method ignores
/// them. The iterative solvers stop early (with meaningless heights) once `halt` says stop.
pub fn integrate_with_confidence(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    method: Integration,
    confidence: &Array2<f32>,
    halt: Halt,
) -> Array2<f32> {
    let solver: WeightedSolver = match method {
        Integration::WeightedPoisson => poisson_heights,
        Integration::RobustPoisson => robust_poisson,
        Integration::Bilateral => bilateral_heights,
        _ => return integrate_until(p, q, mask, method, halt),
    };
    weighted_on_mask(p, q, mask, confidence, solver, halt)
}

/// Elements per rayon task in this module's whole-frame passes.
const CHUNK: usize = 1 << 16;
/// Most re-weighting rounds of `robust-poisson` after its first (weighted) solve.
const IRLS_ROUNDS: usize = 4;
/// Smallest residual scale, in pixels per edge, below which `robust-poisson` lets nothing
/// go: height errors that small are noise, not depth steps.
const MIN_BREAK: f32 = 0.05;
/// Edges whose residuals `robust-poisson`'s τ is taken from, about (all of them up to
/// twice this; past that, those of evenly spaced rows): the median of 2²⁰ residuals is
/// within a fraction of a percent of the whole frame's (τ's role is a scale, not a precise
/// value), and a 2048² frame has 8 times as many.
const TAU_SAMPLE: usize = 1 << 20;
/// Re-weighting stops once a round moves no height by more than this many pixels: ten
/// times below the ~0.1 px integration is judged by, and later rounds move less still
/// (2048² rendered sphere, largest change per round: 0.050, 0.005, 0.0013, 0.0003 px).
/// Surfaces with depth steps or wrong normals (the seed dog: 3.9, 2.7, 2.2, 1.9 px) keep
/// every round.
const SETTLED: f32 = 0.01;

/// Iteratively reweighted least squares with Cauchy weights on the edge equations
/// `z_j − z_i = g_ij`: each round, an edge's weight is its base weight (confidence, or 1)
/// over `1 + (r/τ)²`, `r` its residual and `τ` three robust standard deviations of the
/// residuals (of at least [`TAU_SAMPLE`] of them; floored at [`MIN_BREAK`]). Edges across
/// a depth step, or next to a wrong normal, carry residuals far beyond τ and stop pulling
/// their neighbours.
fn robust_poisson(
    p: &[f32],
    q: &[f32],
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
    halt: Halt,
) -> Vec<f32> {
    irls(p, q, mask, h, w, weights, SETTLED, halt).0
}

/// [`bilateral::integrate`]'s heights.
fn bilateral_heights(
    p: &[f32],
    q: &[f32],
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
    halt: Halt,
) -> Vec<f32> {
    let (z, rounds) = bilateral::integrate(p, q, None, mask, h, w, weights, halt);
    tracing::debug!(rounds, "bilateral integration");
    z
}

/// [`robust_poisson`], stopping once a round moves no height by more than `settled`
/// pixels; also returns the re-weighting rounds it ran.
#[allow(clippy::too_many_arguments)]
fn irls(
    p: &[f32],
    q: &[f32],
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
    settled: f32,
    halt: Halt,
) -> (Vec<f32>, usize) {
    let comps = Components::new(mask, h, w);
    // The first round solves with the base weights. Later rounds form them a row at a
    // time: held beside those rounds' own weights, they would add two maps to the peak.
    let (bx, by) = multigrid::edge_weights(mask, weights, h, w, MIN_EDGE_WEIGHT);
    let mut z = solve_masked(&WeightStencil::new(h, w, bx, by), p, q, &comps, None, halt);
    let edges = Edges {
        mask,
        weights,
        p,
        q,
        w,
    };
    // The previous round's heights, to see how far this round moved them (one more
    // height map in memory, 4 bytes a pixel).
    let mut previous: Vec<f32> = Vec::new();
    // Past 2 × TAU_SAMPLE edges, τ's median comes from every `stride`-th row.
    let stride = ((2 * h * w) / TAU_SAMPLE).max(1);
    let mut round = 0;
    loop {
        if round == IRLS_ROUNDS || halt() {
            comps.remove_means(&mut z);
            return (z, round);
        }
        round += 1;
        let tau = edges
            .median_abs_residual(&z, stride)
            .map_or(MIN_BREAK, |mad| (3.0 * 1.4826 * mad).max(MIN_BREAK));
        // Where the new weights leave the heights a solution (the smooth surfaces this
        // default meets: the weights hardly vary), the round's solve would return them
        // unchanged: stop before forming its operator and multigrid hierarchy.
        if settled >= 0.0 && edges.reweighted_rel_residual(&z, tau) <= poisson::TOL {
            comps.remove_means(&mut z);
            return (z, round);
        }
        let (wx, wy) = edges.reweighted(&z, tau);
        let st = WeightStencil::new(h, w, wx, wy);
        previous.clone_from(&z);
        // Each round's solve starts from the previous heights, which the new weights change
        // only where residuals were large (all rounds on the 2048² sphere: 13 CG iterations
        // instead of 30).
        z = solve_masked(&st, p, q, &comps, Some(z), halt);
        if largest_change(&z, &previous, mask) <= settled {
            comps.remove_means(&mut z);
            return (z, round);
        }
    }
}

/// A re-weighting round's weight for an edge of base weight `base` and residual `r`; 0
/// where the base weight is (no edge), whatever `r` holds there.
#[inline(always)]
fn cauchy_weight(base: f32, r: f32, tau: f32) -> f32 {
    let t = r / tau;
    let wt = (base / (1.0 + t * t)).max(MIN_EDGE_WEIGHT);
    if base > 0.0 { wt } else { 0.0 }
}

/// The edge equations `z_j − z_i = g_ij` of [`irls`]: the mask and pixel weights their
/// base weights come from ([`multigrid::edge_weights`]), and the gradients their slopes
/// come from ([`poisson::EdgeSlopes`]), both formed a row at a time in each pass.
struct Edges<'a> {
    mask: &'a [bool],
    weights: Option<&'a [f32]>,
    p: &'a [f32],
    q: &'a [f32],
    w: usize,
}

/// One row of [`Edges`] at some heights: the base weights of its east (`base[0]`, step 1)
/// and south (`base[1]`, step `w`) edges, its slopes, and `res[0]` / `res[1]` the
/// residuals `z_j − z_i − g_ij` of those edges (meaningless where there is no edge: every
/// reader looks at the base weight first).
struct EdgeRow {
    base: [Vec<f32>; 2],
    slopes: poisson::EdgeSlopes,
    res: [Vec<f32>; 2],
}

impl EdgeRow {
    fn new(w: usize) -> Self {
        Self {
            base: [vec![0.0; w], vec![0.0; w]],
            slopes: poisson::EdgeSlopes::new(w),
            res: [vec![0.0; w], vec![0.0; w]],
        }
    }
}

impl Edges<'_> {
    fn rows(&self) -> usize {
        self.p.len() / self.w.max(1)
    }

    /// Row `r`'s base weights, slopes and residuals at heights `z` into `e`.
    fn load(&self, e: &mut EdgeRow, z: &[f32], r: usize) {
        let (w, i) = (self.w, r * self.w);
        let [bx, by] = &mut e.base;
        bx.fill(0.0);
        by.fill(0.0);
        let (h, floor) = (self.rows(), MIN_EDGE_WEIGHT);
        multigrid::edge_weight_row(self.mask, self.weights, h, floor, r, bx, by);
        e.slopes.load(self.p, self.q, bx, by, r);
        let (gx, gy) = (&e.slopes.east[..w], &e.slopes.south[..w]);
        let [east, south] = &mut e.res;
        let (east, south, zr) = (&mut east[..w], &mut south[..w], &z[i..i + w]);
        for c in 0..w.saturating_sub(1) {
            east[c] = zr[c + 1] - zr[c] - gx[c];
        }
        if let Some(last) = east.last_mut() {
            *last = 0.0;
        }
        match z.get(i + w..i + 2 * w) {
            Some(zb) => {
                for c in 0..w {
                    south[c] = zb[c] - zr[c] - gy[c];
                }
            }
            None => south.fill(0.0),
        }
    }

    /// The median `|residual|` over the edges of every `stride`-th row (east edges and
    /// south ones alike); `None` without edges there.
    fn median_abs_residual(&self, z: &[f32], stride: usize) -> Option<f32> {
        let w = self.w;
        let sample: Vec<f32> = (0..self.rows().div_ceil(stride))
            .into_par_iter()
            .map_init(
                || EdgeRow::new(w),
                |e, k| -> Vec<f32> {
                    let r = k * stride;
                    self.load(e, z, r);
                    let kept = |(b, v): (&f32, &f32)| (*b > 0.0).then_some(v.abs());
                    let [bx, by] = &e.base;
                    let east = bx.iter().zip(&e.res[0]).filter_map(kept);
                    east.chain(by.iter().zip(&e.res[1]).filter_map(kept))
                        .collect()
                },
            )
            .flatten_iter()
            .collect();
        nth_nonnegative(sample.len(), |t| Some(sample[t]), |edges| edges / 2)
    }

    /// The re-weighted edge weights at heights `z` ([`cauchy_weight`]; 0 where there is no
    /// edge): east edges, then south ones.
    fn reweighted(&self, z: &[f32], tau: f32) -> (Vec<f32>, Vec<f32>) {
        let (w, n) = (self.w, self.p.len());
        let (mut wx, mut wy) = (vec![0f32; n], vec![0f32; n]);
        if w == 0 {
            return (wx, wy);
        }
        (wx.par_chunks_mut(w).zip(wy.par_chunks_mut(w)))
            .enumerate()
            .for_each_init(
                || EdgeRow::new(w),
                |e, (r, (wx, wy))| {
                    self.load(e, z, r);
                    let [bx, by] = &e.base;
                    for (out, base, res) in [(wx, bx, &e.res[0]), (wy, by, &e.res[1])] {
                        for c in 0..w {
                            out[c] = cauchy_weight(base[c], res[c], tau);
                        }
                    }
                },
            );
        (wx, wy)
    }

    /// `‖b − A z‖ / ‖b‖` for the system whose edge weights are [`cauchy_weight`]s of the
    /// residuals at `z`, summed edge by edge without forming it: per pixel, `A z − b` is
    /// the weighted residuals of the edges leaving it minus those of the edges entering it.
    fn reweighted_rel_residual(&self, z: &[f32], tau: f32) -> f64 {
        let w = self.w;
        if w == 0 {
            return 0.0;
        }
        let h = self.rows();
        // Per row, (weight × residual, weight × slope) of its east edges and of its south
        // ones; 0 where there is no edge.
        let terms = |e: &EdgeRow, east: &mut [Vec<f32>; 2], south: &mut [Vec<f32>; 2]| {
            let [bx, by] = &e.base;
            let g = [&e.slopes.east, &e.slopes.south];
            for (k, base, out) in [(0, bx, east), (1, by, south)] {
                let (res, g) = (&e.res[k][..w], &g[k][..w]);
                let [wr, wg] = out;
                for c in 0..w {
                    let wt = cauchy_weight(base[c], res[c], tau);
                    (wr[c], wg[c]) = (wt * res[c], wt * g[c]);
                }
            }
        };
        // Bands of rows, each edge formed once: a row's east edges, and the south edges of
        // the row and of the one above. Band sums are added in order, each over four lanes
        // of columns: the same answer on every run and machine.
        const ROWS: usize = 16;
        const LANES: usize = 4;
        let sums: Vec<[f64; 2]> = (0..h.div_ceil(ROWS))
            .into_par_iter()
            .map_init(
                || {
                    let row = || [vec![0f32; w], vec![0f32; w]];
                    (EdgeRow::new(w), row(), row(), row())
                },
                |(e, east, south, north), band| {
                    let (r0, r1) = (band * ROWS, ((band + 1) * ROWS).min(h));
                    match r0.checked_sub(1) {
                        Some(above) => {
                            self.load(e, z, above);
                            terms(e, east, north);
                        }
                        None => north.iter_mut().for_each(|v| v.fill(0.0)),
                    }
                    let mut acc = [[0f64; LANES]; 2];
                    for r in r0..r1 {
                        self.load(e, z, r);
                        terms(e, east, south);
                        // A z − b at each pixel: edges leaving it minus edges entering it.
                        for (k, acc) in acc.iter_mut().enumerate() {
                            let (ea, so, no) = (&east[k][..w], &south[k][..w], &north[k][..w]);
                            for c in 0..w {
                                let west = if c > 0 { ea[c - 1] } else { 0.0 };
                                let v = ea[c] + so[c] - west - no[c];
                                acc[c % LANES] += f64::from(v) * f64::from(v);
                            }
                        }
                        std::mem::swap(south, north);
                    }
                    acc.map(|a| a.iter().sum::<f64>())
                },
            )
            .collect();
        let [rr, bb] = sums
            .iter()
            .fold([0.0; 2], |a, b| [a[0] + b[0], a[1] + b[1]]);
        if bb > 0.0 { (rr / bb).sqrt() } else { 0.0 }
    }
}

/// Log-depth `ζ = −fx ln D` ([`perspective`]) from camera-frame `normals` under `camera`
/// by `method`, weighted by `confidence` where the method takes weights (as
/// [`integrate_with_confidence`]); [`perspective::depth_from_log`] turns it into depth.
/// `bilateral` weighs each pixel's equations by its normal's `n_z²`
/// ([`perspective::facing`]).
pub fn integrate_log_depth(
    normals: &Array3<f32>,
    mask: &Array2<bool>,
    camera: &Pinhole,
    method: Integration,
    confidence: Option<&Array2<f32>>,
    halt: Halt,
) -> Array2<f32> {
    let (p, q) = perspective::log_depth_gradients(normals, mask, camera);
    match (method, confidence) {
        (Integration::Bilateral, _) => {
            let (h, w) = mask.dim();
            let m = contiguous(mask.view());
            let facing = perspective::facing(normals, mask);
            let (ps, qs, fs) = (
                contiguous(p.view()),
                contiguous(q.view()),
                contiguous(facing.view()),
            );
            let wt = confidence.map(|c| contiguous(c.view()));
            let (z, rounds) =
                bilateral::integrate(&ps, &qs, Some(&fs), &m, h, w, wt.as_deref(), halt);
            tracing::debug!(rounds, "bilateral integration (perspective)");
            finish(z, &m, h, w)
        }
        (_, Some(c)) => integrate_with_confidence(&p, &q, mask, method, c, halt),
        (_, None) => integrate_until(&p, &q, mask, method, halt),
    }
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
    weighted_on_mask(p, q, mask, weights, poisson_heights, NEVER)
}

/// A weighted mask-aware solver over row-major slices, behind the arrays' checks.
type WeightedSolver = fn(&[f32], &[f32], &[bool], usize, usize, Option<&[f32]>, Halt) -> Vec<f32>;

fn weighted_on_mask(
    p: &Array2<f32>,
    q: &Array2<f32>,
    mask: &Array2<bool>,
    weights: &Array2<f32>,
    solve: WeightedSolver,
    halt: Halt,
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
    let z = solve(&ps, &qs, &m, h, w, Some(&wt), halt);
    finish(z, &m, h, w)
}

/// Poisson heights, each mask component shifted to zero mean.
fn poisson_heights(
    p: &[f32],
    q: &[f32],
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
    halt: Halt,
) -> Vec<f32> {
    let comps = Components::new(mask, h, w);
    let mut z = match weights {
        None if mask.iter().all(|&m| m) => {
            let st = MaskStencil::new(mask, h, w);
            poisson::solve_dct(poisson::rhs(&st, p, q), h, w)
        }
        None => solve_masked(&MaskStencil::new(mask, h, w), p, q, &comps, None, halt),
        Some(wt) => solve_masked(
            &WeightStencil::from_pixel_weights(mask, wt, h, w, MIN_EDGE_WEIGHT),
            p,
            q,
            &comps,
            None,
            halt,
        ),
    };
    comps.remove_means(&mut z);
    z
}

/// Off-mask pixels := the lowest height on the mask.
fn finish(mut z: Vec<f32>, mask: &[bool], h: usize, w: usize) -> Array2<f32> {
    let low = z
        .par_chunks(CHUNK)
        .zip(mask.par_chunks(CHUNK))
        .map(|(z, m)| {
            z.iter()
                .zip(m)
                .map(|(&v, &m)| if m && v.is_finite() { v } else { f32::INFINITY })
                .fold(f32::INFINITY, f32::min)
        })
        .reduce(|| f32::INFINITY, f32::min);
    let low = if low.is_finite() { low } else { 0.0 };
    z.par_chunks_mut(CHUNK)
        .zip(mask.par_chunks(CHUNK))
        .for_each(|(z, m)| {
            for (v, &m) in z.iter_mut().zip(m) {
                if !m || !v.is_finite() {
                    *v = low;
                }
            }
        });
    Array2::from_shape_vec((h, w), z).expect("shape matches")
}

#[cfg(test)]
mod tests;
