//! The pre-pass: the set's black level and noise σ from its sampled pixels, fitted with
//! the same robust fit as the solve ([`CaptureEstimate`]).

use super::fit::{Buffers, Model, SATURATED, dot, gather, median, norm, plane_rows};
use crate::core::bands::{InMemory, Samples, Stack};
use crate::core::intake::ImageSet;
use crate::core::lights::Light;

/// What the pre-pass learned about the capture.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct CaptureEstimate {
    /// Offset added to every pixel (ambient + sensor), in [0, 1] units.
    pub black_level: f32,
    /// Standard deviation of the noise, in [0, 1] units.
    pub noise_sigma: f32,
    /// Median lit observation, black level removed: the scale the two above are judged
    /// against.
    pub lit_median: f32,
}

/// Estimate black level and noise of a set in memory (see [`estimate_from`]).
pub fn estimate(set: &ImageSet) -> CaptureEstimate {
    let stack = InMemory::new(set);
    estimate_from(
        &scaled(&set.lights),
        quantum(set.bit_depth),
        stack.samples(),
        set.width,
    )
}

pub(super) fn scaled(lights: &[Light]) -> Vec<[f32; 3]> {
    lights
        .iter()
        .map(|l| l.scaled().map(|v| v as f32))
        .collect()
}

/// Estimate black level and noise from the sampled pixels (about 12 000, on a grid of
/// rows and columns `samples.stride` apart).
pub(super) fn estimate_from(
    lights: &[[f32; 3]],
    quantum: f32,
    samples: &Samples,
    width: usize,
) -> CaptureEstimate {
    let n = lights.len();
    let stride = samples.stride;
    let sampled = samples.planes.first().map_or(0, |p| p.len() / width.max(1));
    let mut black = 0.0f32;
    let mut sigma = quantum;
    let mut lit_median = 0.0f32;
    // Two rounds: the first fit is biased by the unknown black level, the second is not.
    for _ in 0..2 {
        let model = Model::new(lights.to_vec(), black, sigma, quantum);
        let (mut shadow, mut resid, mut lit) = (Vec::new(), Vec::new(), Vec::new());
        let (mut obs, mut b) = (vec![0f32; n], Buffers::new(n));
        let planes: Vec<&[u16]> = samples.planes.iter().map(|p| p.as_slice()).collect();
        for r in 0..sampled {
            let rows = plane_rows(&planes, width, r);
            for c in (stride / 2..width).step_by(stride) {
                gather(&rows, c, &mut obs);
                // The same robust fit as the solve: a plain fit here would let highlights
                // drag g, and with it every residual and every "shadowed" observation.
                let fit = model.judged(&obs, &mut b);
                if !fit.reliable {
                    continue;
                }
                let y = &b.y;
                let g = fit.g;
                let rho = norm(g) * model.light_scale;
                for (i, l) in lights.iter().enumerate() {
                    let pred = dot(g, *l);
                    if pred < -0.1 * rho {
                        shadow.push(obs[i]);
                    } else if pred > 0.1 * rho && obs[i] < SATURATED {
                        resid.push((y[i] - pred).abs());
                        lit.push(y[i]);
                    }
                }
            }
        }
        if shadow.len() >= 50 {
            black = median(&mut shadow);
        }
        if !lit.is_empty() {
            lit_median = median(&mut lit);
        }
        if resid.len() >= 50 {
            // MAD → σ, corrected for the 3 fitted parameters.
            let dof = ((n as f32) / (n as f32 - 3.0).max(1.0)).sqrt();
            sigma = (1.4826 * median(&mut resid) * dof).max(quantum);
        }
    }
    CaptureEstimate {
        black_level: black,
        noise_sigma: sigma,
        lit_median,
    }
}

/// The standard deviation of rounding to the set's integer levels (one level / √12): the
/// noise no capture can be below, and the only intensity-unit constant in this solver.
pub(super) fn quantum(bit_depth: u8) -> f32 {
    let level = if bit_depth <= 8 {
        1.0 / 255.0
    } else {
        1.0 / 65535.0
    };
    level / 12f32.sqrt()
}
