//! A quality measure that needs no ground truth: reconstruct from part of the lights and
//! see how well the result predicts the images it was not given. The lights are split
//! into folds (every k-th light); each fold is left out in turn, the rest reconstructed,
//! and the left-out images predicted from the maps (the Lambertian model, or the lobe
//! model where the `glossy` solver kept it). A user can see which solver explains their
//! capture best, on their own capture.

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
    /// Median over the left-out observations of |predicted − observed| / observed.
    pub median_relative: f64,
    pub mean_relative: f64,
    /// Left-out observations scored (object pixels, neither clipped nor dark).
    pub observations: usize,
}

/// Score `opts`' solver on `set` by leaving out each of [`FOLDS`] folds of its lights in
/// turn (every 4th light from the fold's index). Needs at least 3 lights left in each
/// fold's reconstruction.
pub fn holdout(set: &ImageSet, opts: &Options) -> Result<HoldoutScore, RunError> {
    let mut errors = Vec::new();
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
            score_image(&rec, set, k, &mut errors);
        }
    }
    let observations = errors.len();
    let mean_relative = errors.iter().sum::<f64>() / observations.max(1) as f64;
    let median_relative = if observations == 0 {
        f64::NAN
    } else {
        let mid = observations / 2;
        *errors.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    Ok(HoldoutScore {
        median_relative,
        mean_relative,
        observations,
    })
}

/// The relative errors of `rec`'s prediction of image `k` of `set`, over its object.
fn score_image(rec: &Reconstruction, set: &ImageSet, k: usize, errors: &mut Vec<f64>) {
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
        let predicted = model.predict(light.direction, light.intensity);
        errors.push((predicted - observed).abs() / observed);
    }
}
