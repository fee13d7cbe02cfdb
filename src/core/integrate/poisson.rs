//! Least-squares (Poisson) integration on the mask.
//!
//! Unknowns: one height per mask pixel. Equations: for every pair of 4-adjacent mask pixels
//! `i → j` (j to the east or south of i), `z_j − z_i = g_ij`, with `g` the slope of the mean
//! of the two pixels' normals ([`edge_slope`]): the trapezoidal rule on gentle slopes, exact
//! chords on spherical ones. Optionally each equation has a weight `w_ij`.
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
//!   ([`super::multigrid`]), stopping at `‖r‖ ≤ TOL ‖b‖` ([`TOL`] = 2e-4, chosen by the
//!   height error it leaves) or [`MAX_ITER`] iterations.

use super::components::Components;
use super::fourier::transpose;
use super::multigrid::{self, Hierarchy, Stencil};
use crate::core::progress::Halt;
use rayon::prelude::*;
use rustdct::TransformType2And3;
use rustdct::algorithm::Type2And3ConvertToFft;
use rustdct::rustfft::FftPlanner;
use std::f64::consts::PI;
use std::sync::Arc;

/// Relative residual `‖r‖ / ‖b‖` at which CG stops, chosen by the height error it leaves
/// against a solve converged to 3e-7 (`tests::pcg_error_by_iteration`, 2048²):
///
/// | problem | iterations at 2e-4 (at 1e-6) | height error RMS / max |
/// |---|---|---|
/// | hemisphere on a disc mask | 5 (8) | 0.0014 / 0.005 px |
/// | rendered sphere set (`photostereo render`), auto mask | 5 (8) | 0.0012 / 0.006 px |
/// | bumps, full frame (masked solver) | 6 (8) | 0.00001 / 0.0001 px |
/// | hemisphere, disc with 10% random holes | 10 (19) | 0.0007 / 0.17 px |
///
/// That is far below the ~0.1 px the integrators' accuracy is judged by (discretisation
/// and normal noise); the iterations a 1e-6 tolerance adds cost ~40% of the solve (the
/// holey mask's 0.17 px maximum is local: its RMS is 0.0007 px). Against the rendered
/// set's true depth, `photostereo evaluate` gives 0.003 px RMS with the `weighted` solver's
/// normals (0.000 at 1e-6). One iteration less (1e-3) would leave ~0.008 px RMS.
pub(super) const TOL: f64 = 2e-4;
/// Hard cap on CG iterations (solid masks need ~5, ragged ones a dozen or two; this only
/// bounds the time on pathological inputs).
pub(super) const MAX_ITER: usize = 200;
/// A re-weighting round's solve (`robust-poisson`, `bilateral`) also stops once its
/// residual is this fraction of the residual its warm start leaves under the round's new
/// weights (an inexact Newton step): the next round changes the weights again, so solving
/// further than the change the round answers is wasted. `robust-poisson`'s rounds on the
/// 2048² sphere in front of a plane (`photostereo bench --integrators`) took 4 / 7 / 12 /
/// 21 CG iterations instead of 8 / 12 / 20 / 36, and 6 / 10 / 27 / 62 instead of 12 / 20 /
/// 41 / 99 under its camera, for the same depth errors within 0.3 % on every rendered set
/// and on DiLiGenT's objects (`photostereo evaluate res`, `tests/core/depth_real.rs`,
/// `tests/core/depth_steps.rs`).
pub(super) const ROUND_FORCING: f64 = 0.1;
/// Elements per rayon task in vector operations.
const CHUNK: usize = 1 << 14;

pub(super) fn finite(v: f32) -> f32 {
    if v.is_finite() { v } else { 0.0 }
}

/// Height difference across the edge from pixel `a` to pixel `b` (gradients `[p, q]`),
/// along component `k` (0 = p, x; 1 = q, y): the slope of the mean of the two unit normals,
/// which is the two slopes averaged with weights `n_z = 1/√(1 + p² + q²)`.
///
/// For a circular arc this is the chord's slope exactly (the chord is perpendicular to the
/// bisector of the two radii), so steep silhouettes — where `p` grows like `1/n_z` and the
/// plain mean of the slopes (trapezoidal rule) overshoots by whole pixels per edge — are
/// integrated without bias; on gentle slopes `n_z ≈ 1` and it is the trapezoidal rule
/// (second order either way).
#[cfg(test)]
pub(super) fn edge_slope(a: [f32; 2], b: [f32; 2], k: usize) -> f32 {
    weighted_slope(normal_z(a[0], a[1]), a[k], normal_z(b[0], b[1]), b[k])
}

/// The weight `n_z = 1/√(1 + p² + q²)` of a pixel in [`edge_slope`].
#[inline(always)]
pub(super) fn normal_z(p: f32, q: f32) -> f32 {
    1.0 / (1.0 + p * p + q * q).sqrt()
}

/// [`edge_slope`] from the two pixels' weights `wa`, `wb` ([`normal_z`]) and slopes `ga`,
/// `gb` along the edge; bit-identical to it, for kernels that form each weight once.
#[inline(always)]
pub(super) fn weighted_slope(wa: f32, ga: f32, wb: f32, gb: f32) -> f32 {
    let v = (wa * ga + wb * gb) / (wa + wb);
    if v.is_finite() { v } else { 0.0 }
}

/// Right-hand side `b` of the normal equations for the operator `st` (non-finite gradients
/// count as 0).
pub(super) fn rhs<S: Stencil>(st: &S, p: &[f32], q: &[f32]) -> Vec<f32> {
    let (h, w) = st.dims();
    let mut b = vec![0f32; h * w];
    if h * w == 0 {
        return b;
    }
    // Bands of rows, so that each vertical edge (shared by two rows) is formed once.
    let rows = h.div_ceil(4 * rayon::current_num_threads()).max(8);
    b.par_chunks_mut(rows * w)
        .enumerate()
        .for_each(|(k, band)| rhs_band(st, p, q, k * rows, band, &mut RhsScratch::new(w)));
    b
}

/// The [`edge_slope`]s of one row's edges, each pixel's weight formed once: `east[c]` of
/// the edge from `(r, c)` to `(r, c + 1)`, `south[c]` of the one to `(r + 1, c)`, where
/// that edge's weight is positive; 0 elsewhere. Formed row by row where they are used, so
/// that no whole-frame slope map is stored or swept.
pub(super) struct EdgeSlopes {
    cur: SlopeRow,
    below: SlopeRow,
    /// The row `below` holds, so that rows taken in order form each pixel's weight once.
    held: Option<usize>,
    pub(super) east: Vec<f32>,
    pub(super) south: Vec<f32>,
}

impl EdgeSlopes {
    pub(super) fn new(w: usize) -> Self {
        Self {
            cur: SlopeRow::new(w),
            below: SlopeRow::new(w),
            held: None,
            east: vec![0.0; w],
            south: vec![0.0; w],
        }
    }

    /// Row `r`'s slopes, from the gradients `p`, `q` and the edge weights `bx`, `by` (row
    /// `r` of each; a positive weight means the neighbour exists).
    pub(super) fn load(&mut self, p: &[f32], q: &[f32], bx: &[f32], by: &[f32], r: usize) {
        let w = self.east.len();
        let h = p.len() / w.max(1);
        if self.held == Some(r) {
            std::mem::swap(&mut self.cur, &mut self.below);
        } else {
            self.cur.load(p, q, r);
        }
        self.held = (r + 1 < h).then(|| {
            self.below.load(p, q, r + 1);
            r + 1
        });
        let Self {
            cur,
            below,
            east,
            south,
            ..
        } = self;
        let (bx, by, east, south) = (&bx[..w], &by[..w], &mut east[..w], &mut south[..w]);
        // Every slope is formed and the missing edges' are dropped, so the loops have no
        // branch (past the last row, `below` holds stale finite values).
        for c in 0..w.saturating_sub(1) {
            let v = weighted_slope(cur.nz[c], cur.p[c], cur.nz[c + 1], cur.p[c + 1]);
            east[c] = if bx[c] > 0.0 { v } else { 0.0 };
        }
        if let Some(last) = east.last_mut() {
            *last = 0.0;
        }
        for c in 0..w {
            let v = weighted_slope(cur.nz[c], cur.q[c], below.nz[c], below.q[c]);
            south[c] = if by[c] > 0.0 { v } else { 0.0 };
        }
    }
}

/// One image row as [`rhs_band`] reads it: finite slopes and their weights.
struct SlopeRow {
    p: Vec<f32>,
    q: Vec<f32>,
    nz: Vec<f32>,
}

impl SlopeRow {
    fn new(w: usize) -> Self {
        Self {
            p: vec![0.0; w],
            q: vec![0.0; w],
            nz: vec![0.0; w],
        }
    }

    #[inline(always)]
    fn load(&mut self, p: &[f32], q: &[f32], r: usize) {
        let w = self.p.len();
        let (p, q) = (&p[r * w..(r + 1) * w], &q[r * w..(r + 1) * w]);
        let (sp, sq, nz) = (&mut self.p[..w], &mut self.q[..w], &mut self.nz[..w]);
        for c in 0..w {
            let (pc, qc) = (finite(p[c]), finite(q[c]));
            (sp[c], sq[c], nz[c]) = (pc, qc, normal_z(pc, qc));
        }
    }
}

/// Row buffers of [`rhs_band`].
struct RhsScratch {
    cur: SlopeRow,
    next: SlopeRow,
    /// Edge gradient × weight, shifted by one: `gx[c + 1]` is the edge `c → c + 1`.
    gx: Vec<f32>,
    /// Weighted vertical edge gradients above and below the current row.
    up: Vec<f32>,
    down: Vec<f32>,
    east: Vec<f32>,
    south: Vec<f32>,
}

impl RhsScratch {
    fn new(w: usize) -> Self {
        let v = || vec![0f32; w];
        Self {
            cur: SlopeRow::new(w),
            next: SlopeRow::new(w),
            gx: vec![0f32; w + 1],
            up: v(),
            down: v(),
            east: v(),
            south: v(),
        }
    }
}

multiversion! {
    fn rhs_band<S: Stencil>(
        st: &S, p: &[f32], q: &[f32], r0: usize, out: &mut [f32], s: &mut RhsScratch,
    ) -> () => rhs_band_body
}

/// Weighted gradients `g` of the vertical edges from row `top` to row `bottom`.
#[inline(always)]
fn vertical_edges(top: &SlopeRow, bottom: &SlopeRow, weight: &[f32], g: &mut [f32]) {
    let w = g.len();
    let (t, b, weight) = (&top.nz[..w], &bottom.nz[..w], &weight[..w]);
    let (tq, bq) = (&top.q[..w], &bottom.q[..w]);
    for c in 0..w {
        g[c] = weight[c] * weighted_slope(t[c], tq[c], b[c], bq[c]);
    }
}

/// Rows `r0..` of `b` (as many as `out` holds). Weighted edge gradients are formed once per
/// edge in f32 (both end pixels see the same value, so `b` is an exact divergence); their
/// differences are taken in f64.
#[inline(always)]
fn rhs_band_body<S: Stencil>(
    st: &S,
    p: &[f32],
    q: &[f32],
    r0: usize,
    out: &mut [f32],
    s: &mut RhsScratch,
) {
    let (h, w) = st.dims();
    let RhsScratch {
        cur,
        next,
        gx,
        up,
        down,
        east,
        south,
    } = s;
    cur.load(p, q, r0);
    match r0.checked_sub(1) {
        Some(a) => {
            next.load(p, q, a);
            st.edge_row(a, east, south);
            vertical_edges(next, cur, south, up);
        }
        None => up.fill(0.0),
    }
    for (r, out) in (r0..).zip(out.chunks_mut(w)) {
        if r + 1 < h {
            next.load(p, q, r + 1);
            st.edge_row(r, east, south);
            vertical_edges(cur, next, south, down);
        } else {
            st.edge_row(r, east, south);
            down.fill(0.0);
        }
        for c in 0..w.saturating_sub(1) {
            let v = weighted_slope(cur.nz[c], cur.p[c], cur.nz[c + 1], cur.p[c + 1]);
            gx[c + 1] = east[c] * v;
        }
        for c in 0..w {
            let s =
                f64::from(gx[c]) - f64::from(gx[c + 1]) + (f64::from(up[c]) - f64::from(down[c]));
            out[c] = s as f32;
        }
        std::mem::swap(cur, next);
        std::mem::swap(up, down);
    }
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
    // rustdct's planner picks a scalar split-radix algorithm for power-of-two lengths; its
    // FFT-based algorithm over rustfft's SIMD FFT measured ~1.4× faster at 2048².
    let mut fft = FftPlanner::new();
    let mut plan = |n: usize| -> Arc<dyn TransformType2And3<f32>> {
        Arc::new(Type2And3ConvertToFft::new(fft.plan_fft_forward(n)))
    };
    let pw = plan(w);
    let ph = if h == w { Arc::clone(&pw) } else { plan(h) };
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
    /// The relative residual it stopped for: the tolerance, or the forcing term's bound
    /// when that is higher.
    pub target: f64,
}

/// `n` zeros, written in parallel. A zeroed allocation (`vec![0.0; n]`) comes as untouched
/// pages: reading one maps the shared zero page, and the first write after that faults
/// again for a copy-on-write with a TLB shootdown to the other CPUs, page by page.
fn written_zeros(n: usize) -> Vec<f32> {
    (0..n).into_par_iter().map(|_| 0.0).collect()
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    multigrid::ordered_sum(
        a.par_chunks(CHUNK)
            .zip(b.par_chunks(CHUNK))
            .map(|(a, b)| multigrid::dot_f64(a, b)),
    )
}

/// Conjugate gradients on `A z = b` (b already orthogonal to the null space), preconditioned
/// by a multigrid V-cycle. Storage: the solution, the residual, the search direction and one
/// shared vector for `M r` / `A p`, all f32; dot products in f64. Stops early, with the
/// iterate it has, once `halt` says stop.
#[cfg(test)]
pub(super) fn solve_pcg<S: Stencil>(st: &S, b: Vec<f32>, halt: Halt) -> (Vec<f32>, PcgStats) {
    solve_pcg_until(st, b, TOL, MAX_ITER, halt)
}

/// [`solve_pcg`] with an explicit stopping rule: `‖r‖ ≤ tol ‖b‖` or `max_iter` iterations.
#[cfg(test)]
pub(super) fn solve_pcg_until<S: Stencil>(
    st: &S,
    b: Vec<f32>,
    tol: f64,
    max_iter: usize,
    halt: Halt,
) -> (Vec<f32>, PcgStats) {
    pcg(st, b, None, Stop::at(tol, max_iter), halt, None)
}

/// [`solve_pcg`] from an initial guess `x0` (0 on inactive cells), e.g. the previous
/// round's heights in a re-weighting loop. CG runs on the residual `b − A x0` with the
/// same stopping rule, relative to `‖b‖`: the answer is as accurate as from 0, and a
/// guess already within the tolerance costs one operator application.
#[cfg(test)]
pub(super) fn solve_pcg_from<S: Stencil>(
    st: &S,
    b: Vec<f32>,
    x0: Vec<f32>,
    halt: Halt,
) -> (Vec<f32>, PcgStats) {
    assert_eq!(
        x0.len(),
        b.len(),
        "initial guess and right-hand side differ in size"
    );
    pcg(st, b, Some(x0), Stop::FULL, halt, None)
}

/// Preconditioned CG on `st x = b`, preconditioned by `hier` when given (built for an
/// operator close to `st`: still symmetric positive definite, so CG converges, in more
/// iterations the further the two are apart), else by a hierarchy built for `st`.
fn pcg<S: Stencil>(
    st: &S,
    b: Vec<f32>,
    x0: Option<Vec<f32>>,
    stop: Stop,
    halt: Halt,
    hier: Option<&mut Hierarchy>,
) -> (Vec<f32>, PcgStats) {
    let Stop { tol, max_iter, .. } = stop;
    let n = b.len();
    let mut r = b;
    let bnorm = dot(&r, &r).sqrt();
    let mut stats = PcgStats {
        iterations: 0,
        rel_residual: 0.0,
        levels: 0,
        target: tol,
    };
    if bnorm == 0.0 || !bnorm.is_finite() {
        return (vec![0.0; n], stats);
    }
    let mut own = None;
    let hier = match hier {
        Some(h) => h,
        None => own.insert(Hierarchy::new(st)),
    };
    stats.levels = hier.depth();
    stats.rel_residual = 1.0;
    // x and p are read before they are written: zero them by writing, not with calloc.
    let mut p = written_zeros(n);
    let mut zq = vec![0f32; n]; // M r, then A p: written first
    let mut x = match x0 {
        None => written_zeros(n),
        Some(mut x) => {
            // r = b − A x0, with A x0 from the fused direction kernel (α = β = 0: p ← x0,
            // zq ← A p, x untouched); p is zeroed again for the first direction.
            zq.copy_from_slice(&x);
            hier.direction_apply(st, &mut zq, &mut p, &mut x, 0.0, 0.0);
            p.par_chunks_mut(CHUNK).for_each(|p| p.fill(0.0));
            r.par_chunks_mut(CHUNK)
                .zip(zq.par_chunks(CHUNK))
                .for_each(|(r, ax)| r.iter_mut().zip(ax).for_each(|(r, &ax)| *r -= ax));
            stats.rel_residual = dot(&r, &r).sqrt() / bnorm;
            if stats.rel_residual <= tol {
                return (x, stats);
            }
            x
        }
    };
    let mut rz = hier.apply(st, &r, &mut zq);
    // The update x += α p of each step is applied lazily, by the next direction update
    // (which reads p anyway), or after the loop.
    let (mut alpha, mut beta) = (0.0f32, 0.0f32);
    // The warm start's residual (1 from 0) sets the forcing term's bound.
    stats.target = tol.max(stop.forcing * stats.rel_residual);
    let stop_sq = (stats.target * bnorm).powi(2);
    while stats.iterations < max_iter && !halt() {
        if !(rz > 0.0 && rz.is_finite()) {
            break;
        }
        // x += α p_old; p = z + β p_old; zq = A p.
        let pap = hier.direction_apply(st, &mut zq, &mut p, &mut x, alpha, beta);
        alpha = 0.0;
        if !(pap > 0.0 && pap.is_finite()) {
            break;
        }
        stats.iterations += 1;
        alpha = (rz / pap) as f32;
        // r -= α A p; zq = M r unless converged.
        let last = stats.iterations == max_iter;
        let (rr, rz_new) = hier.step(st, &mut r, &mut zq, alpha, |rr| rr <= stop_sq || last);
        stats.rel_residual = rr.sqrt() / bnorm;
        let Some(rz_new) = rz_new else { break };
        beta = (rz_new / rz) as f32;
        rz = rz_new;
    }
    if alpha != 0.0 {
        x.par_chunks_mut(CHUNK)
            .zip(p.par_chunks(CHUNK))
            .for_each(|(x, p)| x.iter_mut().zip(p).for_each(|(x, &p)| *x += alpha * p));
    }
    (x, stats)
}

/// The masked solve, from 0 or from `start` (a previous solution on the same mask),
/// stopping as `stop` says.
pub(super) fn solve_masked<S: multigrid::Stencil>(
    st: &S,
    p: &[f32],
    q: &[f32],
    comps: &Components,
    start: Option<Vec<f32>>,
    stop: Stop,
    halt: Halt,
) -> Vec<f32> {
    solve_rhs(st, rhs(st, p, q), comps, (start, None), stop, halt)
}

/// When a CG solve stops: once `‖r‖ ≤ tol ‖b‖`, after `max_iter` iterations, or once the
/// residual is `forcing` × the warm start's (an inexact solve, as in inexact Newton: a
/// re-weighting round whose weights will change again need not be solved further than
/// the change it answers; 0 never stops early).
#[derive(Debug, Clone, Copy)]
pub(super) struct Stop {
    pub(super) tol: f64,
    pub(super) max_iter: usize,
    pub(super) forcing: f64,
}

impl Stop {
    /// At [`TOL`] or after [`MAX_ITER`] iterations: a solve whose answer is final.
    pub(super) const FULL: Stop = Stop::at(TOL, MAX_ITER);

    /// At a relative residual of `tol` or after `max_iter` iterations.
    pub(super) const fn at(tol: f64, max_iter: usize) -> Self {
        Self {
            tol,
            max_iter,
            forcing: 0.0,
        }
    }
}

/// [`solve_masked`] of a right-hand side `b` formed by the caller, from `start` when
/// given, preconditioned by a kept hierarchy when given ([`pcg`]), stopping as `stop`
/// says.
pub(super) fn solve_rhs<S: multigrid::Stencil>(
    st: &S,
    mut b: Vec<f32>,
    comps: &Components,
    (start, hier): (Option<Vec<f32>>, Option<&mut Hierarchy>),
    stop: Stop,
    halt: Halt,
) -> Vec<f32> {
    // b sums to 0 on each component in exact arithmetic; remove the round-off so that the
    // singular system is consistent.
    comps.remove_means(&mut b);
    let (z, stats) = pcg(st, b, start, stop, halt, hier);
    if stats.rel_residual > stats.target && stats.iterations < stop.max_iter && !halt() {
        tracing::warn!(
            iterations = stats.iterations,
            rel_residual = stats.rel_residual,
            "poisson: CG stopped before reaching its tolerance"
        );
    } else {
        tracing::debug!(
            iterations = stats.iterations,
            rel_residual = stats.rel_residual,
            levels = stats.levels,
            "poisson: multigrid-preconditioned CG"
        );
    }
    z
}

/// Largest `|a − b|` over the mask; NaN counts as a change past any bound.
pub(super) fn largest_change(a: &[f32], b: &[f32], mask: &[bool]) -> f32 {
    let change = |a: f32, b: f32, m: bool| match (a - b).abs() {
        _ if !m => 0.0,
        d if d.is_nan() => f32::INFINITY,
        d => d,
    };
    (a.par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .zip(mask.par_chunks(CHUNK)))
    .map(|((a, b), m)| {
        (a.iter().zip(b).zip(m))
            .map(|((&a, &b), &m)| change(a, b, m))
            .fold(0.0, f32::max)
    })
    .reduce(|| 0.0, f32::max)
}
