//! Bilateral normal integration (after Cao et al., "Bilateral Normal Integration", ECCV
//! 2022): least squares whose equations are re-weighted from the current surface so that
//! depth steps are kept where the normals say the surface breaks.
//!
//! Each pixel `i` says, along each axis, that its forward and its backward neighbour lie on
//! its tangent plane: `z_j − z_i = g_i` (its own slope `g_i`) with weight `a_i f_i`
//! forward and `a_i (1 − f_i)` backward. `a_i = n_z²` (under a camera the square of the
//! smaller of `n_z` and the cosine to the ray, [`super::perspective::Facing`]) makes these
//! the normal-form equations `n_z Δz + n_x = 0`, which stay well posed at grazing
//! slopes; `f_i = σ(k s_i (B_i² − F_i²))`, with `F_i`, `B_i` the current forward and
//! backward height differences and `s_i = n_z²`, gives the pixel to the side it is
//! continuous with (the smaller step): ½ and ½ on a smooth surface, ~1 and ~0 beside a
//! step. Summed per edge, the two end pixels' equations are one: weight `W = a_i f_i +
//! a_j (1 − f_j)` and slope the `W`-weighted mean of `g_i` and `g_j` — the trapezoidal
//! rule on a smooth surface, nothing across a step (both ends turn away from it). The
//! edges both of whose ends turned away are the steps the integration kept ([`Cuts`]).
//!
//! Rounds alternate a weighted Poisson solve ([`super::poisson`], warm-started) with the
//! re-weighting until the energy changes by less than [`ENERGY_TOL`] (relative). The
//! energy is not convex, and where pieces of the surface are cut off from each other by
//! steps all round (several objects at different depths) the rounds can settle in a
//! minimum whose pieces sit at the wrong depths. The sigmoid therefore starts soft and is
//! sharpened to `k` over the first rounds (graduated non-convexity): large steps are cut
//! first, while the pieces still pull on each other, and smaller ones after. Each
//! round's solve is inexact (a forcing term, [`ROUND_FORCING`]): solving weights that the next
//! round changes anyway further than that change is wasted. The solve runs on the mask's
//! bounding box ([`super::crop`]).

use rayon::prelude::*;

use super::components::Components;
use super::crop::Crop;
use super::multigrid::{self, Bands, Hierarchy, MIN_EDGE_WEIGHT, WeightStencil};
use super::perspective::Facing;
use super::poisson::{ROUND_FORCING, Stop, solve_rhs};
use crate::core::arrays::contiguous;
use crate::core::progress::Halt;

/// Sharpness `k` of the sigmoid, per squared pixel of (n_z-scaled) height difference: the
/// published default, which turns a pixel fully to one side once its two differences
/// differ by about a pixel.
const SHARPNESS: f32 = 2.0;
/// Rounds over which the sigmoid is sharpened, doubling each round from
/// `SHARPNESS / 2^SOFT_ROUNDS` to [`SHARPNESS`]; the energy is compared only after them.
const SOFT_ROUNDS: usize = 5;
/// Most rounds (solve, then re-weight).
const MAX_ROUNDS: usize = 150;
/// Rounds stop once the energy changes by less than this fraction.
const ENERGY_TOL: f64 = 1e-5;
/// Smallest edge weight, relative to a smooth edge facing the camera (1): an edge across a
/// step keeps this much, so that the mask's connectivity (and the solve's null space)
/// never depends on the weights. It must be tiny: a region cut off by steps all round
/// (an object in front of another) is pulled by what leaks through its cuts, and on
/// DiLiGenT's objects a floor of 1e-4 cost nearly twice the depth error of 1e-9 (cat 0.134
/// vs 0.075 mm, harvest 3.5 vs 1.84 mm, measured with the sigmoid at full sharpness from
/// the first round; `tests/core/depth_real.rs`).
const CUT_FLOOR: f32 = 1e-9;
/// Relative residual below which a round's solve never goes, and its most CG iterations:
/// near-cut edges make the system stiff, and a solve stopped at the Poisson solver's 2e-4
/// leaves errors the re-weighting then amplifies.
const SOLVE_TOL: f64 = 1e-6;
const MAX_ITER: usize = 200;
/// An edge is cut when both its ends give it less than this share.
const CUT_SHARE: f32 = 0.1;
/// How each round's solve stops: at [`SOLVE_TOL`], or once its residual is
/// [`ROUND_FORCING`] × the residual the previous round's heights leave under the new
/// weights. On DiLiGenT's objects a tenth takes 20–40 % of the CG iterations of solving
/// each round to [`SOLVE_TOL`], for the same depth error on cat and pot2
/// (`tests/core/depth_real.rs`; harvest's depends on which minimum the rounds reach,
/// above).
const ROUND_STOP: Stop = Stop {
    tol: SOLVE_TOL,
    max_iter: MAX_ITER,
    forcing: ROUND_FORCING,
};

/// The depth steps an integration kept, as edges of the row-major `h × w` frame: `east[i]`
/// for the edge from pixel `i` to `i + 1`, `south[i]` to `i + w`.
#[derive(Debug, Clone)]
pub struct Cuts {
    pub east: Vec<bool>,
    pub south: Vec<bool>,
}

/// What [`integrate`] gives: heights, the rounds run, and the steps kept.
pub(super) struct Integrated {
    pub(super) z: Vec<f32>,
    pub(super) rounds: usize,
    pub(super) cuts: Cuts,
}

/// Heights from gradients `p`, `q` on `mask` (row-major, `h × w`), with each pixel's
/// facing weights ([`Facing`]: `a` for its equations, `s` for its sides; from the
/// gradients when None: both `1 / (1 + p² + q²)`, the orthographic `n_z²`) and
/// optional per-pixel confidence `weights` scaling its equations; each mask component's
/// mean height is 0, and pixels off the mask hold 0. A `start` (heights) that already
/// holds the surface's steps, e.g. the last integration's placed by other evidence, sets
/// the first shares at full sharpness in place of the soft rounds. Stops early
/// (meaningless heights) once `halt` says stop.
#[allow(clippy::too_many_arguments)]
pub(super) fn integrate(
    p: &[f32],
    q: &[f32],
    facing: Option<Facing>,
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
    start: Option<&[f32]>,
    halt: Halt,
) -> Integrated {
    let Some(crop) = Crop::of_mask(mask, h, w) else {
        return Integrated {
            z: vec![0.0; h * w],
            rounds: 0,
            cuts: Cuts {
                east: vec![false; h * w],
                south: vec![false; h * w],
            },
        };
    };
    // The frame-sized weights are dropped once cut: the solve is the peak.
    let (a, s) = match facing {
        Some(f) => (
            crop.cut(&contiguous(f.equations.view())),
            crop.cut(&contiguous(f.sides.view())),
        ),
        None => {
            let a: Vec<f32> = (crop.cut(p).iter().zip(crop.cut(q)))
                .map(|(&p, q)| 1.0 / (1.0 + p * p + q * q))
                .collect();
            (a.clone(), a)
        }
    };
    let window = Window {
        p: crop.cut(p),
        q: crop.cut(q),
        a,
        s,
        mask: crop.cut(mask),
        h: crop.h,
        w: crop.w,
    };
    let confidence = weights.map(|wt| crop.cut(wt));
    let start = start.map(|s| crop.cut(s));
    let (z, rounds, shares) = window.integrate(confidence.as_deref(), start, halt);
    let (east, south) = window.cuts(&shares);
    Integrated {
        z: crop.paste(&z, h, 0.0),
        rounds,
        cuts: Cuts {
            east: crop.paste(&east, h, false),
            south: crop.paste(&south, h, false),
        },
    }
}

/// The problem on the mask's bounding box.
struct Window {
    p: Vec<f32>,
    q: Vec<f32>,
    /// Facing weights of each pixel's equations and of its sides.
    a: Vec<f32>,
    s: Vec<f32>,
    mask: Vec<bool>,
    h: usize,
    w: usize,
}

/// Each pixel's forward share `f` along x and along y.
struct Shares {
    x: Vec<f32>,
    y: Vec<f32>,
}

impl Window {
    /// Heights, the rounds run, and the shares the last heights give.
    fn integrate(
        &self,
        confidence: Option<&[f32]>,
        start: Option<Vec<f32>>,
        halt: Halt,
    ) -> (Vec<f32>, usize, Shares) {
        let (h, w) = (self.h, self.w);
        let comps = Components::new(&self.mask, h, w);
        // Base edge weights: 0 where there is no edge, else the confidence (1 without).
        let (bx, by) = multigrid::edge_weights(&self.mask, confidence, h, w, MIN_EDGE_WEIGHT);
        let mut shares = Shares {
            x: vec![0.5; h * w],
            y: vec![0.5; h * w],
        };
        // The sharpness schedule's round: past the soft ones from a start.
        let mut round = 0;
        if let Some(s) = &start {
            self.reweigh(s, &mut shares, &bx, &by, SHARPNESS);
            round = SOFT_ROUNDS;
        }
        let mut z = start;
        let mut last_energy: Option<f64> = None;
        let mut rounds = 0;
        let mut kept: Option<Hierarchy> = None;
        let mut spare: Option<(Vec<f32>, Vec<f32>)> = None;
        while rounds < MAX_ROUNDS && !halt() {
            rounds += 1;
            round += 1;
            // The edge weights are written into the last round's vectors: fresh
            // frame-sized ones would page-fault on their first write every round.
            let (mut wx, mut wy) = spare
                .take()
                .unwrap_or_else(|| (vec![0.0; h * w], vec![0.0; h * w]));
            let mut b = vec![0f32; h * w];
            self.assemble(&shares, (&bx, &by), &mut wx, &mut wy, &mut b);
            let st = WeightStencil::new(h, w, wx, wy);
            // The first sharp round's hierarchy preconditions the later rounds' solves: their
            // weights differ from its on few edges, it stays symmetric positive definite
            // (so CG converges), and building one costs about ten CG iterations here (the
            // coarsest level's dense factorisation). On DiLiGenT's objects the later rounds
            // took no more iterations in all with it than with one built each round (pot2
            // 437 against 448), and pot2's integration 0.32 s instead of 0.52.
            let hier = match &mut kept {
                Some(h) if round > SOFT_ROUNDS + 1 => h,
                _ => kept.insert(Hierarchy::new(&st)),
            };
            let start = (z.take(), Some(hier));
            let mut next = solve_rhs(&st, b, &comps, start, ROUND_STOP, halt);
            spare = Some(st.into_weights());
            comps.remove_means(&mut next);
            let energy = self.reweigh(&next, &mut shares, &bx, &by, sharpness(round));
            z = Some(next);
            let sharp = round > SOFT_ROUNDS;
            if sharp && last_energy.is_some_and(|e| (e - energy).abs() <= ENERGY_TOL * e) {
                break;
            }
            last_energy = Some(energy);
        }
        (z.unwrap_or_else(|| vec![0.0; h * w]), rounds, shares)
    }

    /// The edges east and south of each pixel that both ends turn away from under `shares`.
    fn cuts(&self, shares: &Shares) -> (Vec<bool>, Vec<bool>) {
        let (h, w) = (self.h, self.w);
        let cut = |f: &[f32], i: usize, step: usize| {
            let j = i + step;
            self.mask[i] && self.mask[j] && f[i] < CUT_SHARE && 1.0 - f[j] < CUT_SHARE
        };
        let east = (0..h * w)
            .map(|i| i % w + 1 < w && cut(&shares.x, i, 1))
            .collect();
        let south = (0..h * w)
            .map(|i| i / w + 1 < h && cut(&shares.y, i, w))
            .collect();
        (east, south)
    }

    /// One round's weighted Poisson system under `shares`: the weights of the edges east
    /// (`wx`) and south (`wy`) of each pixel ([`edge`]) and the right-hand side `b`, the
    /// divergence of their fluxes (`b_i = Σ_{edges into i} flux − Σ_{edges out of i}
    /// flux`). One pass over the multigrid's bands of rows, each band first forming the
    /// south fluxes of the row above it: one read of the inputs, no flux maps.
    fn assemble(
        &self,
        shares: &Shares,
        (bx, by): (&[f32], &[f32]),
        wx: &mut [f32],
        wy: &mut [f32],
        b: &mut [f32],
    ) {
        let (h, w) = (self.h, self.w);
        let rows = Bands::new(h, w).rows;
        (wx.par_chunks_mut(rows * w).zip(wy.par_chunks_mut(rows * w)))
            .zip(b.par_chunks_mut(rows * w))
            .enumerate()
            .for_each(|(k, ((wxb, wyb), bb))| {
                let r0 = k * rows;
                let [mut fx, mut above, mut fy, mut sink] = [(); 4].map(|_| vec![0f32; w]);
                if r0 > 0 {
                    self.south_row(&shares.y, by, r0 - 1, &mut sink, &mut above);
                }
                let band = wxb
                    .chunks_mut(w)
                    .zip(wyb.chunks_mut(w))
                    .zip(bb.chunks_mut(w));
                for (j, ((wxr, wyr), br)) in band.enumerate() {
                    let r = r0 + j;
                    self.east_row(&shares.x, bx, r, wxr, &mut fx);
                    self.south_row(&shares.y, by, r, wyr, &mut fy);
                    for c in 0..w {
                        let mut v = -fx[c] - fy[c];
                        if c > 0 {
                            v += fx[c - 1];
                        }
                        if r > 0 {
                            v += above[c];
                        }
                        br[c] = v;
                    }
                    std::mem::swap(&mut above, &mut fy);
                }
            });
    }

    /// Row `r`'s east edges under the forward shares `f`: weights into `wr`, fluxes into `fr`.
    fn east_row(&self, f: &[f32], base: &[f32], r: usize, wr: &mut [f32], fr: &mut [f32]) {
        let w = self.w;
        let i = r * w;
        let (a, g, f, base) = (
            &self.a[i..i + w],
            &self.p[i..i + w],
            &f[i..i + w],
            &base[i..i + w],
        );
        for c in 0..w - 1 {
            (wr[c], fr[c]) = edge(base[c], (a[c], f[c], g[c]), (a[c + 1], f[c + 1], g[c + 1]));
        }
        (wr[w - 1], fr[w - 1]) = (0.0, 0.0);
    }

    /// Row `r`'s south edges under the forward shares `f`: weights into `wr`, fluxes into
    /// `fr` (none below the last row).
    fn south_row(&self, f: &[f32], base: &[f32], r: usize, wr: &mut [f32], fr: &mut [f32]) {
        let w = self.w;
        if r + 1 >= self.h {
            wr.fill(0.0);
            fr.fill(0.0);
            return;
        }
        let (i, j) = (r * w, (r + 1) * w);
        let (a0, a1) = (&self.a[i..i + w], &self.a[j..j + w]);
        let (g0, g1) = (&self.q[i..i + w], &self.q[j..j + w]);
        let (f0, f1) = (&f[i..i + w], &f[j..j + w]);
        let base = &base[i..i + w];
        for c in 0..w {
            (wr[c], fr[c]) = edge(base[c], (a0[c], f0[c], g0[c]), (a1[c], f1[c], g1[c]));
        }
    }

    /// New forward shares at heights `z` under the sigmoid's sharpness `k`, in place;
    /// returns the energy of `z` under the shares it was solved with.
    fn reweigh(&self, z: &[f32], shares: &mut Shares, bx: &[f32], by: &[f32], k: f32) -> f64 {
        let w = self.w;
        let facing = (&self.a[..], &self.s[..]);
        let ex = reweigh_axis(z, facing, &self.p, &mut shares.x, bx, (1, w), k);
        let ey = reweigh_axis(z, facing, &self.q, &mut shares.y, by, (w, w), k);
        ex + ey
    }
}

/// The sigmoid's sharpness after round `round` (from 1): [`SHARPNESS`] halved once for each
/// of the [`SOFT_ROUNDS`] not yet run.
fn sharpness(round: usize) -> f32 {
    let soft = SOFT_ROUNDS.saturating_sub(round);
    SHARPNESS / (1u32 << soft) as f32
}

/// [`Window::reweigh`] along one axis (`(step, w)`: step 1 for x, `w` for y, on a grid
/// `w` wide; `base` the edges' base weights from each pixel to `i + step`; `(a, s)` the
/// facing weights) under the sigmoid's sharpness `k`.
fn reweigh_axis(
    z: &[f32],
    (a, s): (&[f32], &[f32]),
    g: &[f32],
    f: &mut [f32],
    base: &[f32],
    (step, w): (usize, usize),
    k: f32,
) -> f64 {
    let rows: Vec<f64> = f
        .par_chunks_mut(w)
        .enumerate()
        .map(|(r, row)| {
            let mut energy = 0f64;
            for (c, f) in row.iter_mut().enumerate() {
                let i = r * w + c;
                let fwd = (base[i] > 0.0).then(|| (base[i], z[i + step] - z[i]));
                let back = (i >= step && base[i - step] > 0.0 && (step != 1 || c > 0))
                    .then(|| (base[i - step], z[i] - z[i - step]));
                let (ff, bb) = (fwd.map_or(0.0, |e| e.1), back.map_or(0.0, |e| e.1));
                let term = |e: Option<(f32, f32)>, share: f32| {
                    e.map_or(0.0, |(b, d)| {
                        f64::from(b * share * a[i]) * f64::from(d - g[i]).powi(2)
                    })
                };
                energy += term(fwd, *f) + term(back, 1.0 - *f);
                *f = sigmoid(k * s[i] * (bb * bb - ff * ff));
            }
            energy
        })
        .collect();
    multigrid::ordered_sum(rows.into_par_iter())
}

/// Weight and flux of an edge of base weight `base` between pixels `i` and `j` (facing
/// weight, forward share and slope of each): `W = base (a_i f_i + a_j (1 − f_j))`, floored
/// at [`CUT_FLOOR`] × `base`, its slope the mean of `g_i` and `g_j` weighted by the two
/// terms (their plain mean where both are ~0); nothing where `base` is 0 (no edge).
#[inline(always)]
fn edge(base: f32, (ai, fi, gi): (f32, f32, f32), (aj, fj, gj): (f32, f32, f32)) -> (f32, f32) {
    let (ti, tj) = (ai * fi, aj * (1.0 - fj));
    let sum = ti + tj;
    let slope = if sum > 1e-12 {
        (ti * gi + tj * gj) / sum
    } else {
        0.5 * (gi + gj)
    };
    let weight = base * sum.max(CUT_FLOOR);
    if base > 0.0 {
        (weight, weight * slope)
    } else {
        (0.0, 0.0)
    }
}

#[inline(always)]
fn sigmoid(t: f32) -> f32 {
    1.0 / (1.0 + (-t).exp())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::progress::NEVER;

    /// On a smooth surface (a paraboloid) every pixel stays continuous with both sides and
    /// the heights are Poisson's: second-order accurate.
    #[test]
    fn a_smooth_surface_keeps_its_shape() {
        let (h, w) = (40, 40);
        let f = |r: f32, c: f32| 0.01 * ((r - 20.0).powi(2) + (c - 20.0).powi(2));
        let p: Vec<f32> = (0..h * w).map(|i| 0.02 * ((i % w) as f32 - 20.0)).collect();
        let q: Vec<f32> = (0..h * w).map(|i| 0.02 * ((i / w) as f32 - 20.0)).collect();
        let mask = vec![true; h * w];
        let z = integrate(&p, &q, None, &mask, h, w, None, None, NEVER).z;
        let mean_truth = (0..h * w)
            .map(|i| f((i / w) as f32, (i % w) as f32))
            .sum::<f32>()
            / (h * w) as f32;
        let worst = (0..h * w)
            .map(|i| (z[i] - (f((i / w) as f32, (i % w) as f32) - mean_truth)).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-2, "largest height error {worst} px");
    }
}
