//! What a run produces: the recovered maps and the numbers that go into `result.json`.

use std::time::Instant;

use ndarray::{Array2, Array3};
use serde::Serialize;

use super::camera::Pinhole;
use super::intensities::Estimated;
use super::lights::Light;
use super::options::Options;
use super::progress::Stage;
use super::reflectance::Material;

/// Everything recovered from one image set. Arrays are indexed `[row, col]`; the frame is
/// the seed's: x = column (right), y = row (down), z towards the camera.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    pub width: usize,
    pub height: usize,
    pub lights: Vec<Light>,
    /// Albedo in [0, 1] (clamped), 0 off the mask.
    pub albedo: Array2<f32>,
    /// Per-channel albedo `(rows, cols, 3)` when the inputs were colour.
    pub albedo_rgb: Option<Array3<f32>>,
    /// The `glossy` solver's specular albedo, roughness and where the lobe was kept (0
    /// and false off the mask); `albedo` is then the diffuse albedo.
    pub gloss: Option<Gloss>,
    /// Unit normals `(rows, cols, 3)`, all zero off the mask.
    pub normals: Array3<f32>,
    pub mask: Array2<bool>,
    /// Heights in pixel units, off the mask the lowest height on it; or, under a camera
    /// (`report.options.camera`), depth along the optical axis, NaN off the mask.
    pub heights: Array2<f32>,
    /// Integrability residual dp/dy − dq/dx, 0 off the mask.
    pub curl: Array2<f32>,
    /// Per-pixel reliability in [0, 1], 0 off the mask.
    pub confidence: Array2<f32>,
    /// Mask pixels with fewer than 3 usable observations (their normals are a fallback).
    pub unreliable: Array2<bool>,
    pub report: Report,
}

/// The lobe model's maps over the whole image: specular albedo, roughness (GGX's for both
/// lobe families), where the lobe was kept (elsewhere the pixel is Lambertian: both maps
/// 0) and where the kept lobe is Beckmann's rather than GGX's
/// ([`Facets`](crate::core::reflectance::Facets)), with the fit's RMS residual there under
/// the lobe model and under the Lambertian fit it replaced (over the same observations:
/// lit and not clipped).
#[derive(Debug, Clone)]
pub struct Gloss {
    pub specular: Array2<f32>,
    pub roughness: Array2<f32>,
    pub used: Array2<bool>,
    pub beckmann: Array2<bool>,
    pub residual: Array2<f32>,
    pub lambertian_residual: Array2<f32>,
    /// The lobe the pixels shared, where the sample held enough lobes for one.
    pub material: Option<Material>,
}

impl Gloss {
    /// Bytes per pixel of the maps (a `glossy` job holds them beside the solve's).
    pub const BYTES_PER_PIXEL: u64 = 18;

    pub fn zeros(rows: usize, cols: usize) -> Self {
        Self {
            specular: Array2::zeros((rows, cols)),
            roughness: Array2::zeros((rows, cols)),
            used: Array2::from_elem((rows, cols), false),
            beckmann: Array2::from_elem((rows, cols), false),
            residual: Array2::zeros((rows, cols)),
            lambertian_residual: Array2::zeros((rows, cols)),
            material: None,
        }
    }

    /// The RMS of the per-pixel RMS `residual` (one of this gloss's residual maps) over
    /// the pixels whose lobe was kept; None where it was kept nowhere.
    pub fn rms(&self, residual: &Array2<f32>) -> Option<f64> {
        let (mut sum, mut n) = (0.0, 0usize);
        for (&e, _) in residual.iter().zip(&self.used).filter(|(_, u)| **u) {
            sum += (e as f64).powi(2);
            n += 1;
        }
        (n > 0).then(|| (sum / n as f64).sqrt())
    }
}

impl Reconstruction {
    /// The camera the surface is depth under; None for orthographic heights.
    pub fn camera(&self) -> Option<&Pinhole> {
        self.report.options.camera.as_ref()
    }
}

impl Report {
    /// The surface's range over the mask, heights or depth, `(0, 0)` for an empty mask.
    pub fn surface_range(&self) -> (f32, f32) {
        let [min, max] = if self.options.camera.is_some() {
            [self.depth_min, self.depth_max]
        } else {
            [self.height_min, self.height_max]
        };
        (min.unwrap_or(0.0), max.unwrap_or(0.0))
    }
}

/// The numbers that go into `result.json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Report {
    pub width: usize,
    pub height: usize,
    pub light_count: usize,
    pub lights: Vec<LightSummary>,
    pub options: Options,
    pub light_condition_number: f64,
    pub timings_ms: Vec<Timing>,
    /// Height range over the mask, pixels (orthographic; `height.png` spans it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_min: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_max: Option<f32>,
    /// Depth range over the mask (under a camera; `depth.png` spans it, near = bright).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_min: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_max: Option<f32>,
    pub integrability_rms: f64,
    pub reprojection_rms: f64,
    pub clamped_albedo_pixels: usize,
    pub background_pixels: usize,
    pub object_pixels: usize,
    /// Mean confidence over the mask.
    pub confidence_mean: f64,
    /// Mean number of observations kept per mask pixel.
    pub inliers_mean: f64,
    /// Mask pixels with fewer than 3 usable observations.
    pub unreliable_pixels: usize,
    /// Camera black level the robust solver estimated and removed.
    pub black_level: Option<f32>,
    /// Image noise σ the robust solver estimated.
    pub noise_sigma: Option<f32>,
    /// What the caller should know about how far to trust this result (e.g. most pixels
    /// fell back to least squares); empty when nothing stood out.
    pub warnings: Vec<String>,
    /// Names of the files written (filled in by [`run`]).
    pub artifacts: Vec<String>,
    /// The mask file used, if any (e.g. a folder's `mask.png`).
    pub mask_file: Option<String>,
    /// The lights' relative intensities (mean 1) estimated from the object, with
    /// `intensities: estimate`; `lights.json` is then the table with them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimated_intensities: Option<Vec<Estimated>>,
    /// With the `glossy` solver: the object pixels whose lobe model was kept (the rest
    /// are Lambertian); `specular.png` and `roughness.png` map them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub glossy_pixels: Option<usize>,
    /// With the `glossy` solver: the RMS residual over those pixels' lit, unclipped
    /// observations under the lobe model, and under the Lambertian fit it replaced there
    /// (what the lobe explains is the difference).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub glossy_residual_rms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub glossy_lambertian_rms: Option<f64>,
    /// With the `glossy` solver: the lobe the object's pixels shared (fitted at a sample
    /// of them), absent where the sample held too few lobes and each pixel fitted its own.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub glossy_material: Option<Material>,
    /// With the `holdout_lights` option: how well the solver predicts images it was not
    /// given (see `core::holdout`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub holdout: Option<HoldoutScore>,
    /// What intake ignored or chose on the caller's behalf (unnamed images, an unused
    /// `mask.png`, …).
    pub notes: Vec<String>,
}

/// How well one solver's reconstructions predicted the left-out images.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HoldoutScore {
    /// Median over the left-out observations of |s·predicted − observed| / observed, `s`
    /// the left-out image's fitted intensity scale.
    pub median_relative: f64,
    pub mean_relative: f64,
    /// The median with the table's intensities as they are (`s` = 1).
    pub median_relative_table: f64,
    /// Left-out observations scored (object pixels, neither clipped nor dark).
    pub observations: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct LightSummary {
    pub name: String,
    /// Unit direction in the project's frame (x right, y down the rows, z to the camera).
    pub direction: [f64; 3],
    /// The scalar intensity the solve used.
    pub intensity: f64,
    /// The per-channel intensities the table gave, if it gave them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub intensity_rgb: Option<[f64; 3]>,
}

/// Wall-clock time of one stage.
#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    pub stage: &'static str,
    pub ms: f64,
}

impl Timing {
    pub(crate) fn new(stage: Stage, start: Instant) -> Self {
        Self {
            stage: stage.as_str(),
            ms: start.elapsed().as_secs_f64() * 1e3,
        }
    }
}
