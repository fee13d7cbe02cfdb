//! Heights by method: the entry points ([`integrate`] and its variants) check the arrays,
//! run the method chosen over row-major slices (each weighted solver behind one
//! signature) and give the pixels off the mask the lowest height on it.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::bilateral::{self, Cuts};
use super::components::Components;
use super::multigrid::{MIN_EDGE_WEIGHT, MaskStencil, WeightStencil};
use super::poisson::{self, Stop, solve_masked};
use super::robust_poisson::robust_poisson;
use super::{fourier, path, perspective};
use crate::core::arrays::contiguous;
use crate::core::camera::Pinhole;
use crate::core::options::Integration;
use crate::core::progress::{Halt, NEVER};

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

/// [`integrate_log_depth`]'s result.
pub struct LogDepth {
    /// `ζ = −fx ln D`, pixels.
    pub zeta: Array2<f32>,
    /// The depth steps the method kept, when it keeps any (`bilateral`).
    pub cuts: Option<Cuts>,
}

/// What [`integrate_log_depth`] may be given beside the normals.
#[derive(Default)]
pub struct Given<'a> {
    /// The normals' log-depth gradients ([`perspective::log_depth_gradients`]), for a
    /// caller that keeps them; formed from the normals when None.
    pub slopes: Option<(&'a Array2<f32>, &'a Array2<f32>)>,
    /// `ζ` that already holds the surface's steps (the last integration's, placed by other
    /// evidence): `bilateral` starts from it. Finite on the mask.
    pub start: Option<&'a Array2<f32>>,
}

/// Log-depth `ζ = −fx ln D` ([`perspective`]) from camera-frame `normals` under `camera`
/// by `method`, weighted by `confidence` where the method takes weights (as
/// [`integrate_with_confidence`]); [`perspective::depth_from_log`] turns it into depth.
/// `bilateral` weighs each pixel by its normal's facing ([`perspective::Facing`]).
pub fn integrate_log_depth(
    normals: &Array3<f32>,
    mask: &Array2<bool>,
    camera: &Pinhole,
    method: Integration,
    confidence: Option<&Array2<f32>>,
    given: Given<'_>,
    halt: Halt,
) -> LogDepth {
    let formed;
    let (p, q) = match given.slopes {
        Some(slopes) => slopes,
        None => {
            formed = perspective::log_depth_gradients(normals, mask, camera);
            (&formed.0, &formed.1)
        }
    };
    match (method, confidence) {
        (Integration::Bilateral, _) => {
            let (h, w) = mask.dim();
            let m = contiguous(mask.view());
            let facing = perspective::facing(normals, mask, camera);
            let (ps, qs) = (contiguous(p.view()), contiguous(q.view()));
            let wt = confidence.map(|c| contiguous(c.view()));
            let start = given.start.map(|s| contiguous(s.view()));
            let done = bilateral::integrate(
                &ps,
                &qs,
                Some(facing),
                &m,
                h,
                w,
                wt.as_deref(),
                start.as_deref(),
                halt,
            );
            tracing::debug!(rounds = done.rounds, "bilateral integration (perspective)");
            LogDepth {
                zeta: finish(done.z, &m, h, w),
                cuts: Some(done.cuts),
            }
        }
        (_, Some(c)) => LogDepth {
            zeta: integrate_with_confidence(p, q, mask, method, c, halt),
            cuts: None,
        },
        (_, None) => LogDepth {
            zeta: integrate_until(p, q, mask, method, halt),
            cuts: None,
        },
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
    let done = bilateral::integrate(p, q, None, mask, h, w, weights, None, halt);
    tracing::debug!(rounds = done.rounds, "bilateral integration");
    done.z
}

/// Poisson heights, each mask component shifted to zero mean.
pub(super) fn poisson_heights(
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
        None => solve_masked(
            &MaskStencil::new(mask, h, w),
            p,
            q,
            &comps,
            None,
            Stop::FULL,
            halt,
        ),
        Some(wt) => solve_masked(
            &WeightStencil::from_pixel_weights(mask, wt, h, w, MIN_EDGE_WEIGHT),
            p,
            q,
            &comps,
            None,
            Stop::FULL,
            halt,
        ),
    };
    comps.remove_means(&mut z);
    z
}

/// Elements per rayon task in this module's whole-frame passes.
const CHUNK: usize = 1 << 16;

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
