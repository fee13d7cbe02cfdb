//! A quality measure that needs no ground truth: reconstruct from part of the lights and
//! see how well the result predicts the images it was not given. The lights are split
//! into folds (every k-th light); each fold is left out in turn, the rest reconstructed,
//! and the left-out images predicted from the maps (the Lambertian model, or the lobe
//! model where the `glossy` solver kept it). A user can see which solver explains their
//! capture best, on their own capture.
//!
//! A left-out light's intensity is a property of the light, not of the surface, and no
//! reconstruction from the other images can know it: where the table gives none (1 is
//! assumed) a real light's deviation from it would be the same error for every solver,
//! and on a real capture it dominates the score. So each left-out image's intensity is
//! fitted (one scale, the median ratio of observed to predicted) before it is scored;
//! the score as the table says is reported beside it.

use super::error::RunError;
use super::intake::ImageSet;
use super::options::Options;
use super::pipeline;
use super::progress::RunToEnd;
use super::reconstruction::Reconstruction;
use super::reflectance::Fitted;

/// Folds the lights are split into (each left out once).
pub const FOLDS: usize = 4;
/// Observations at or above this are clipped, and below this (black level removed) in
/// shadow or too dark for a relative error to mean anything: both are left out.
const CLIPPED: f64 = 0.995;
const DARK: f64 = 0.02;

/// How well one solver's reconstructions predicted the left-out images.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoldoutScore {
    /// Median over the left-out observations of |s·predicted − observed| / observed, `s`
    /// the left-out image's fitted intensity scale.
    pub median_relative: f64,
    pub mean_relative: f64,
    /// The median with the table's intensities as they are (`s` = 1).
    pub median_relative_table: f64,
    /// Left-out observations scored (object pixels, neither clipped nor dark).
    pub observations: usize,
}

/// Score `opts`' solver on `set` by leaving out each of [`FOLDS`] folds of its lights in
/// turn (every 4th light from the fold's index). Needs at least 3 lights left in each
/// fold's reconstruction.
pub fn holdout(set: &ImageSet, opts: &Options) -> Result<HoldoutScore, RunError> {
    let (mut errors, mut as_table) = (Vec::new(), Vec::new());
    for fold in 0..FOLDS {
        let (kept, left): (Vec<usize>, Vec<usize>) =
            (0..set.lights.len()).partition(|k| k % FOLDS != fold);
        if left.is_empty() {
            continue;
        }
        let part = ImageSet {
            width: set.width,
            height: set.height,
            bit_depth: set.bit_depth,
            lights: kept.iter().map(|&k| set.lights[k].clone()).collect(),
            planes: kept.iter().map(|&k| set.planes[k].clone()).collect(),
            // Colour moments sum over every light; the score is on luminance.
            colour_moments: None,
            mask: set.mask.clone(),
            mask_file: set.mask_file.clone(),
            notes: Vec::new(),
        };
        let rec = pipeline::reconstruct(&part, opts, &mut RunToEnd)?;
        for &k in &left {
            let pairs = predictions(&rec, set, k);
            let scale = intensity_scale(&pairs);
            for &(predicted, observed) in &pairs {
                errors.push((scale * predicted - observed).abs() / observed);
                as_table.push((predicted - observed).abs() / observed);
            }
        }
    }
    let observations = errors.len();
    let mean_relative = errors.iter().sum::<f64>() / observations.max(1) as f64;
    Ok(HoldoutScore {
        median_relative: median(&mut errors),
        mean_relative,
        median_relative_table: median(&mut as_table),
        observations,
    })
}

/// The median of `values`, NaN when there are none.
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The left-out image's intensity relative to the table's: the median ratio of observed
/// to predicted over the pixels predicted clearly lit (1 when there are none).
fn intensity_scale(pairs: &[(f64, f64)]) -> f64 {
    let mut ratios: Vec<f64> = (pairs.iter())
        .filter(|(predicted, _)| *predicted > DARK)
        .map(|(predicted, observed)| observed / predicted)
        .collect();
    let scale = median(&mut ratios);
    if scale.is_finite() { scale } else { 1.0 }
}

/// `rec`'s prediction of image `k` of `set` and what it shows, `(predicted, observed)`,
/// over its object's pixels neither clipped nor dark.
fn predictions(rec: &Reconstruction, set: &ImageSet, k: usize) -> Vec<(f64, f64)> {
    let mut pairs = Vec::new();
    let light = &set.lights[k];
    let black = rec.report.black_level.unwrap_or(0.0) as f64;
    for ((r, c), &inside) in rec.mask.indexed_iter() {
        if !inside {
            continue;
        }
        let raw = set.planes[k][[r, c]] as f64 / 65535.0;
        let observed = raw - black;
        if raw >= CLIPPED || observed < DARK {
            continue;
        }
        let normal = [0, 1, 2].map(|i| rec.normals[[r, c, i]] as f64);
        let mut model = Fitted {
            normal,
            diffuse: rec.albedo[[r, c]] as f64,
            specular: 0.0,
            roughness: 1.0,
        };
        if let Some(g) = rec.gloss.as_ref().filter(|g| g.used[[r, c]]) {
            model.specular = g.specular[[r, c]] as f64;
            model.roughness = g.roughness[[r, c]] as f64;
        }
        pairs.push((model.predict(light.direction, light.intensity), observed));
    }
    pairs
}
