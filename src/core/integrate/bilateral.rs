//! Bilateral normal integration: least squares on the mask whose edges are re-weighted
//! from the current surface so that depth steps are kept (after Cao et al., "Bilateral
//! Normal Integration", ECCV 2022).
//!
//! At each pixel and along each axis the surface is continuous with at most one side: the
//! one whose height difference is smaller. With `F` and `B` the pixel's forward and
//! backward height differences (times its `n_z`, so steep but smooth slopes compare as
//! gentle ones), the backward side gets `s = σ(k (F² − B²))` and the forward side `1 − s`
//! of the pixel's say; an edge's weight is the sum of what its two end pixels give it: 1
//! on a smooth surface (½ + ½), ~0 across a step (both ends turn away from it), and
//! anything between. Each round solves the weighted Poisson system ([`super::poisson`])
//! from the previous heights; rounds stop once no height moves by more than
//! [`SETTLED`] pixels.
//!
//! Unlike the published method, which gives each pixel a forward and a backward equation
//! from its own normal, an edge here has one equation whose slope is that of the mean of
//! its two normals (the chord rule of [`super::poisson`]), weighted by the sum above; the
//! two agree on smooth surfaces and the chord rule is exact on spheres.

use rayon::prelude::*;

use super::components::Components;
use super::multigrid::{self, MIN_EDGE_WEIGHT, WeightStencil};
use super::poisson::{largest_change, normal_z, solve_masked};
use crate::core::progress::Halt;

/// Sharpness `k` of the sigmoid that decides which side a pixel is continuous with, per
/// squared pixel of height difference: 2 (the published default) turns a pixel fully to one
/// side once its two differences differ by about a pixel.
const SHARPNESS: f32 = 2.0;
/// Most re-weighting rounds after the first (unweighted) solve.
const MAX_ROUNDS: usize = 30;
/// Rounds stop once none moves a height by more than this many pixels.
const SETTLED: f32 = 0.01;

/// Heights from gradients `p`, `q` on `mask` (row-major, `h × w`), with optional per-pixel
/// confidence `weights` as the base weights; each mask component's mean height is 0.
/// Stops early (meaningless heights) once `halt` says stop. Also returns the rounds run.
pub(super) fn integrate(
    p: &[f32],
    q: &[f32],
    mask: &[bool],
    h: usize,
    w: usize,
    weights: Option<&[f32]>,
    halt: Halt,
) -> (Vec<f32>, usize) {
    let comps = Components::new(mask, h, w);
    let (bx, by) = multigrid::edge_weights(mask, weights, h, w, MIN_EDGE_WEIGHT);
    let first = WeightStencil::new(h, w, bx.clone(), by.clone());
    let mut z = solve_masked(&first, p, q, &comps, None, halt);
    drop(first);
    let nz: Vec<f32> = p.par_iter().zip(q).map(|(&p, &q)| normal_z(p, q)).collect();
    let mut previous = Vec::new();
    let mut rounds = 0;
    while rounds < MAX_ROUNDS && !halt() {
        rounds += 1;
        let (wx, wy) = weights_at(&z, &nz, &bx, &by, h, w);
        previous.clone_from(&z);
        z = solve_masked(
            &WeightStencil::new(h, w, wx, wy),
            p,
            q,
            &comps,
            Some(z),
            halt,
        );
        if largest_change(&z, &previous, mask) <= SETTLED {
            break;
        }
    }
    comps.remove_means(&mut z);
    (z, rounds)
}

/// `σ(k (F² − B²))`: the share of a pixel's say that goes to its backward edge.
#[inline(always)]
fn backward_share(forward: f32, backward: f32) -> f32 {
    let t = SHARPNESS * (forward * forward - backward * backward);
    1.0 / (1.0 + (-t).exp())
}

/// The edge weights at heights `z`: east edges (`wx`), then south ones (`wy`), each its
/// base weight (`bx`, `by`; 0 where there is no edge) times the shares its two ends give it,
/// floored at [`MIN_EDGE_WEIGHT`] where the edge exists.
fn weights_at(
    z: &[f32],
    nz: &[f32],
    bx: &[f32],
    by: &[f32],
    h: usize,
    w: usize,
) -> (Vec<f32>, Vec<f32>) {
    let n = h * w;
    let (mut wx, mut wy) = (vec![0f32; n], vec![0f32; n]);
    if n == 0 {
        return (wx, wy);
    }
    let edge = |base: f32, shares: f32| {
        if base > 0.0 {
            (base * shares).max(MIN_EDGE_WEIGHT)
        } else {
            0.0
        }
    };
    // Along rows: a pixel's backward share needs only its own row.
    wx.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0f32; w],
        |back, (r, out)| {
            let (zr, nr, br) = (&z[r * w..][..w], &nz[r * w..][..w], &bx[r * w..][..w]);
            for c in 0..w {
                let f = if br[c] > 0.0 { zr[c + 1] - zr[c] } else { 0.0 };
                let b = if c > 0 && br[c - 1] > 0.0 {
                    zr[c] - zr[c - 1]
                } else {
                    0.0
                };
                back[c] = backward_share(nr[c] * f, nr[c] * b);
            }
            for c in 0..w.saturating_sub(1) {
                out[c] = edge(br[c], 1.0 - back[c] + back[c + 1]);
            }
        },
    );
    // Along columns: a pixel's backward share needs the rows above and below.
    let share_y = |r: usize, c: usize| {
        let i = r * w + c;
        let f = if by[i] > 0.0 { z[i + w] - z[i] } else { 0.0 };
        let b = if r > 0 && by[i - w] > 0.0 {
            z[i] - z[i - w]
        } else {
            0.0
        };
        backward_share(nz[i] * f, nz[i] * b)
    };
    wy.par_chunks_mut(w).enumerate().for_each(|(r, out)| {
        if r + 1 == h {
            return;
        }
        let br = &by[r * w..][..w];
        for c in 0..w {
            if br[c] > 0.0 {
                out[c] = edge(br[c], 1.0 - share_y(r, c) + share_y(r + 1, c));
            }
        }
    });
    (wx, wy)
}
