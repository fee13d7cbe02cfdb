//! Distant lights' unknown intensities, from the pre-pass's sampled pixels before the
//! solve ([`Gram`]): the robust fit says which observations of each pixel the Lambertian
//! model explains (shadows, highlights and saturation set aside), those give the
//! intensities, and the fit is redone under them until they settle. A wrong intensity
//! makes its light's observations misfit and set aside, so the first rounds see fewer of
//! them; the rounds after see them again.
//!
//! A highlight the robust fit keeps (one within its tolerance, or one that every pixel of
//! a flat region shares) adds to its light what a brighter light would: so the estimate
//! also leaves out each pixel's observations near the mirror direction (half-vector
//! within [`HIGHLIGHT_CONE_DEG`] of the normal), where a glossy lobe lives.

use super::estimate::{estimate_from, quantum};
use super::fit::{Buffers, Model, dot, gather, norm, plane_rows};
use crate::core::bands::Samples;
use crate::core::intensities::Gram;
use crate::core::lights::Light;

/// Most rounds of fit-then-estimate.
const MAX_ROUNDS: usize = 8;
/// Rounds stop once no intensity moves by more than this fraction.
const SETTLED: f64 = 1e-4;
/// Half-angle of the cone around the normal whose half-vectors the estimate leaves out:
/// a Blinn–Phong lobe of shininess 60 is down to 2 % of its peak at its edge.
const HIGHLIGHT_CONE_DEG: f32 = 20.0;
/// Fewest observations a pixel must keep to say anything about the intensities (three
/// fit any `g` exactly).
const MIN_KEPT: usize = 4;

/// The relative intensities (mean 1) of `lights` (their directions; the table's
/// intensities are only the start) from `samples` (the set's sampled rows, `width` wide);
/// None when the sampled pixels cannot tell them apart (too few normals of different
/// kinds, or a light no pixel explains).
pub fn estimate_intensities(
    lights: &[Light],
    bit_depth: u8,
    samples: &Samples,
    width: usize,
) -> Option<Vec<f64>> {
    let directions: Vec<[f32; 3]> = (lights.iter())
        .map(|l| l.direction.map(|v| v as f32))
        .collect();
    let mean = lights.iter().map(|l| l.intensity).sum::<f64>() / lights.len().max(1) as f64;
    let mut e: Vec<f64> = lights.iter().map(|l| l.intensity / mean).collect();
    let quantum = quantum(bit_depth);
    for _ in 0..MAX_ROUNDS {
        let scaled: Vec<[f32; 3]> = (directions.iter().zip(&e))
            .map(|(d, &e)| d.map(|v| v * e as f32))
            .collect();
        let estimate = estimate_from(&scaled, quantum, samples, width);
        let model = Model::new(scaled, estimate.black_level, estimate.noise_sigma, quantum);
        let next = gram(&model, &directions, samples, width).intensities(&e)?;
        let moved = (next.iter().zip(&e))
            .map(|(a, b)| (a / b - 1.0).abs())
            .fold(0.0, f64::max);
        e = next;
        if moved < SETTLED {
            break;
        }
    }
    Some(e)
}

/// The Gram of the sampled pixels' kept observations under `model`, with the lights'
/// unit-intensity `directions`.
fn gram(model: &Model, directions: &[[f32; 3]], samples: &Samples, width: usize) -> Gram {
    let n = directions.len();
    let stride = samples.stride;
    let sampled = samples.planes.first().map_or(0, |p| p.len() / width.max(1));
    let planes: Vec<&[u16]> = samples.planes.iter().map(|p| p.as_slice()).collect();
    let cone = HIGHLIGHT_CONE_DEG.to_radians().cos();
    Gram::sum_in_runs(n, sampled, |rows, gram| {
        let (mut obs, mut b) = (vec![0f32; n], Buffers::new(n));
        let mut keep = vec![false; n];
        for r in rows {
            let rows = plane_rows(&planes, width, r);
            for c in (stride / 2..width).step_by(stride) {
                gather(&rows, c, &mut obs);
                let fit = model.judged(&obs, &mut b);
                if !fit.reliable || fit.inliers < MIN_KEPT {
                    continue;
                }
                let rho = norm(fit.g);
                let normal = fit.g.map(|v| v / rho);
                for ((k, &out), d) in keep.iter_mut().zip(&b.out).zip(directions) {
                    *k = !out && !glossy(normal, *d, cone);
                }
                gram.add(directions, &b.y, &keep);
            }
        }
    })
}

/// Whether light `d` (unit, towards the light) is within the highlight cone of `normal`:
/// its half-vector with the view (the camera's axis, orthographic) has `n·h > cone`.
fn glossy(normal: [f32; 3], d: [f32; 3], cone: f32) -> bool {
    let h = [d[0], d[1], d[2] + 1.0];
    let len = norm(h);
    len > 0.0 && dot(normal, h) > cone * len
}
