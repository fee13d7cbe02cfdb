//! The robust solver for one set ([`Robust`]): the pre-pass, then each band's rows, the
//! row-wide fast path first and the per-pixel fit for what it leaves; and the confidence
//! a fit earns ([`confidence_of`]).

use ndarray::Axis;
use rayon::prelude::*;

use super::estimate::{CaptureEstimate, estimate_from, quantum, scaled};
use super::fit::{Buffers, Model, gather, norm, plane_rows};
use super::lanes;
use crate::core::bands::{Samples, SurfaceRows};
use crate::core::lights::Light;
use crate::core::progress::Halt;

/// Confidence in [0, 1]: support grows from 3 kept observations (0.25) to 6 or more (1),
/// times a Gaussian fall-off of the kept observations' RMS against the tolerance.
pub fn confidence_of(kept: usize, rms: f32, tolerance: f32) -> f32 {
    let support = ((kept as f32 - 2.0) / 4.0).clamp(0.0, 1.0);
    support * (-(rms / tolerance.max(1e-9)).powi(2)).exp()
}

/// The robust solver for one set: its pre-pass estimate and the model it fits with.
pub struct Robust {
    model: Model,
    pub estimate: CaptureEstimate,
}

impl Robust {
    /// The pre-pass over `samples` (the set's sampled rows, `width` wide).
    pub fn new(lights: &[Light], bit_depth: u8, samples: &Samples, width: usize) -> Self {
        let lights = scaled(lights);
        let quantum = quantum(bit_depth);
        let estimate = estimate_from(&lights, quantum, samples, width);
        let model = Model::new(lights, estimate.black_level, estimate.noise_sigma, quantum);
        Self { model, estimate }
    }

    /// Solve the rows of a band (`planes[k]`: the band's rows of image `k`, `cols` wide)
    /// into `out`; once `halt` says stop, the rows not yet started stay zero.
    pub fn solve_rows(&self, planes: &[&[u16]], cols: usize, out: SurfaceRows<'_>, halt: Halt) {
        let model = &self.model;
        let n = model.lights.len();
        let SurfaceRows {
            mut albedo,
            mut normals,
            mut residual,
            mut confidence,
            mut inliers,
            mut unreliable,
        } = out;
        albedo
            .axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(normals.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(residual.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(confidence.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(inliers.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(unreliable.axis_iter_mut(Axis(0)).into_par_iter())
            .enumerate()
            .for_each(
                |(
                    r,
                    (
                        ((((mut a_row, mut n_row), mut res_row), mut conf_row), mut in_row),
                        mut bad_row,
                    ),
                )| {
                    if halt() {
                        return;
                    }
                    let (mut obs, mut b) = (vec![0f32; n], Buffers::new(n));
                    let rows = plane_rows(planes, cols, r);
                    // Most pixels are settled by the row-wide fast path; the rest, and every
                    // pixel of a set of 4 lights or fewer (nothing to test outliers with),
                    // by the per-pixel fit.
                    let mut settled = Vec::with_capacity(cols);
                    if n > 4 {
                        lanes::settle_row(model, &rows, &mut settled);
                    }
                    for c in 0..cols {
                        let fit = match settled.get(c) {
                            Some(&lanes::Settled::Fit(fit)) => fit,
                            _ => {
                                gather(&rows, c, &mut obs);
                                model.judged(&obs, &mut b)
                            }
                        };
                        let rho = norm(fit.g);
                        a_row[c] = rho;
                        if rho > 0.0 && rho.is_finite() {
                            for k in 0..3 {
                                n_row[[c, k]] = fit.g[k] / rho;
                            }
                        }
                        in_row[c] = fit.inliers as u16;
                        bad_row[c] = !fit.reliable;
                        // Reprojection over every observation, the shadow model included.
                        res_row[c] = (fit.sse_all / n as f32).sqrt();
                        if fit.reliable && fit.inliers >= 3 {
                            let rms = (fit.sse_inliers / fit.inliers as f32).sqrt();
                            conf_row[c] = confidence_of(fit.inliers, rms, model.tol(fit.g));
                        }
                    }
                },
            );
    }
}
