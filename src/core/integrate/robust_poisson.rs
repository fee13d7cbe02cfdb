//! `robust-poisson`: iteratively reweighted least squares with Cauchy weights on the edge
//! equations ([`irls`]), over the edges' base weights, slopes and residuals formed a row
//! at a time ([`Edges`], [`EdgeRow`]).

use rayon::prelude::*;

use super::components::Components;
use super::multigrid::{self, MIN_EDGE_WEIGHT, WeightStencil};
use super::poisson::{self, MAX_ITER, ROUND_FORCING, Stop, TOL, largest_change, solve_masked};
use crate::core::histogram::nth_nonnegative;
use crate::core::progress::Halt;

/// Most re-weighting rounds of `robust-poisson` after its first (weighted) solve.
pub(super) const IRLS_ROUNDS: usize = 4;
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
pub(super) const SETTLED: f32 = 0.01;
/// How a re-weighting round's solve stops: at the Poisson solver's [`TOL`], or once its
/// residual is [`ROUND_FORCING`] × its warm start's (the next round changes the weights).
const ROUND_STOP: Stop = Stop {
    tol: TOL,
    max_iter: MAX_ITER,
    forcing: ROUND_FORCING,
};

/// Iteratively reweighted least squares with Cauchy weights on the edge equations
/// `z_j − z_i = g_ij`: each round, an edge's weight is its base weight (confidence, or 1)
/// over `1 + (r/τ)²`, `r` its residual and `τ` three robust standard deviations of the
/// residuals (of at least [`TAU_SAMPLE`] of them; floored at [`MIN_BREAK`]). Edges across
/// a depth step, or next to a wrong normal, carry residuals far beyond τ and stop pulling
/// their neighbours.
pub(super) fn robust_poisson(
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

/// [`robust_poisson`], stopping once a round moves no height by more than `settled`
/// pixels; also returns the re-weighting rounds it ran.
#[allow(clippy::too_many_arguments)]
pub(super) fn irls(
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
    let mut z = solve_masked(
        &WeightStencil::new(h, w, bx, by),
        p,
        q,
        &comps,
        None,
        Stop::FULL,
        halt,
    );
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
        // instead of 30), and stops at a tenth of their residual (inexact, ROUND_STOP).
        z = solve_masked(&st, p, q, &comps, Some(z), ROUND_STOP, halt);
        if largest_change(&z, &previous, mask) <= settled {
            comps.remove_means(&mut z);
            return (z, round);
        }
    }
}

/// A re-weighting round's weight for an edge of base weight `base` and residual `r`; 0
/// where the base weight is (no edge), whatever `r` holds there.
#[inline(always)]
pub(super) fn cauchy_weight(base: f32, r: f32, tau: f32) -> f32 {
    let t = r / tau;
    let wt = (base / (1.0 + t * t)).max(MIN_EDGE_WEIGHT);
    if base > 0.0 { wt } else { 0.0 }
}

/// The edge equations `z_j − z_i = g_ij` of [`irls`]: the mask and pixel weights their
/// base weights come from ([`multigrid::edge_weights`]), and the gradients their slopes
/// come from ([`poisson::EdgeSlopes`]), both formed a row at a time in each pass.
pub(super) struct Edges<'a> {
    pub(super) mask: &'a [bool],
    pub(super) weights: Option<&'a [f32]>,
    pub(super) p: &'a [f32],
    pub(super) q: &'a [f32],
    pub(super) w: usize,
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
    pub(super) fn median_abs_residual(&self, z: &[f32], stride: usize) -> Option<f32> {
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
    pub(super) fn reweighted(&self, z: &[f32], tau: f32) -> (Vec<f32>, Vec<f32>) {
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
    pub(super) fn reweighted_rel_residual(&self, z: &[f32], tau: f32) -> f64 {
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
