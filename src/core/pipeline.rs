//! `reconstruct`: the one path from an [`ImageSet`] to a [`Reconstruction`], shared by the
//! CLI and the job worker.

use ndarray::{Array2, Array3};
use serde::Serialize;

use super::InputError;
use super::intake::ImageSet;
use super::lights::Light;
use super::options::Options;

/// Named stages, reported to a progress callback as they start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    Decode,
    Solve,
    Mask,
    Integrate,
    Outputs,
    Mesh,
}

impl Stage {
    pub fn as_str(self) -> &'static str {
        match self {
            Stage::Decode => "decode",
            Stage::Solve => "solve",
            Stage::Mask => "mask",
            Stage::Integrate => "integrate",
            Stage::Outputs => "outputs",
            Stage::Mesh => "mesh",
        }
    }
}

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
    /// Unit normals `(rows, cols, 3)`, all zero off the mask.
    pub normals: Array3<f32>,
    pub mask: Array2<bool>,
    /// Heights in pixel units; off the mask they equal the lowest height on it.
    pub heights: Array2<f32>,
    /// Integrability residual dp/dy − dq/dx, 0 off the mask.
    pub curl: Array2<f32>,
    /// Per-pixel RMS of (observed − re-rendered) intensity, 0 off the mask.
    pub residual: Array2<f32>,
    pub report: Report,
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
    pub timings_ms: Vec<(String, f64)>,
    pub height_min: f32,
    pub height_max: f32,
    pub integrability_rms: f64,
    pub reprojection_rms: f64,
    pub clamped_albedo_pixels: usize,
    pub background_pixels: usize,
    pub object_pixels: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct LightSummary {
    pub name: String,
    pub direction: [f64; 3],
    pub intensity: f64,
}

/// Why a run stopped without a result.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The inputs or options cannot be reconstructed (the caller's fault).
    #[error(transparent)]
    Input(#[from] InputError),
    /// The progress callback asked to stop.
    #[error("cancelled")]
    Cancelled,
    /// Writing an output failed (the machine's fault: disk full, permissions).
    #[error("writing {path}: {reason}")]
    Output { path: String, reason: String },
}

/// Called as each stage starts; returning `false` cancels the run.
pub type Progress<'a> = &'a mut dyn FnMut(Stage) -> bool;

/// Reconstruct albedo, normals, mask and heights from a decoded image set.
pub fn reconstruct(
    set: &ImageSet,
    opts: &Options,
    progress: Progress,
) -> Result<Reconstruction, RunError> {
    let _ = (set, opts, progress);
    todo!("pipeline under construction")
}

/// Reconstruct and write every requested artifact into `dir` (each written under a
/// temporary name and renamed, `result.json` last). Returns the report.
pub fn run(
    set: &ImageSet,
    opts: &Options,
    dir: &std::path::Path,
    progress: Progress,
) -> Result<Report, RunError> {
    let _ = (set, opts, dir, progress);
    todo!("pipeline under construction")
}
