//! What the near-light solve takes and gives.

use ndarray::{Array2, Array3};

use crate::core::camera::Pinhole;
use crate::core::options::Integration;

/// The alternation's grid: 256², a small cost next to one pass over 2048² images; the
/// light vectors its surface gives are close enough to the full resolution's that the
/// first full pass leaves few pixels to refit.
pub const COARSE_PIXELS: usize = 256 * 256;

/// How a near-light set is solved.
#[derive(Debug, Clone)]
pub struct NearSettings {
    pub camera: Pinhole,
    /// The working distance along the optical axis, in the positions' unit: the first
    /// surface, and the reference of the irradiance (`model`).
    pub distance: f64,
    pub integration: Integration,
    /// Most alternations of solve and integration.
    pub max_iterations: usize,
    /// They stop once the normals move by less than this on average (degrees).
    pub tolerance_deg: f64,
    /// Estimate each light's relative intensity from the object (semi-calibrated): the
    /// lights' own intensities are only the starting point.
    pub estimate_intensities: bool,
    /// The alternation runs on the images shrunk to about this many pixels; the full
    /// resolution is then fitted on the surface it found ([`super::solve`]).
    pub coarse_pixels: usize,
}

impl NearSettings {
    pub fn new(camera: Pinhole, distance: f64) -> Self {
        Self {
            camera,
            distance,
            integration: Integration::default(),
            max_iterations: 12,
            tolerance_deg: 0.01,
            estimate_intensities: false,
            coarse_pixels: COARSE_PIXELS,
        }
    }
}

/// One alternation: the surface it solved on and how far the normals moved.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Iteration {
    /// The width and height of the grid it solved on: the images shrunk, or whole.
    pub grid: [usize; 2],
    /// Median depth over the mask of the surface integrated after the solve.
    pub median_depth: f64,
    /// Mean and 95th-percentile angle between this solve's normals and the last one's
    /// (the first: against the normals facing the camera; the first at full resolution:
    /// against the shrunk grid's last, enlarged), degrees.
    pub mean_change_deg: f64,
    pub p95_change_deg: f64,
}

/// What the near-light solve recovered.
#[derive(Debug, Clone)]
pub struct NearSurface {
    /// Unit camera-frame normals, zero off the mask and where a fit failed.
    pub normals: Array3<f32>,
    pub albedo: Array2<f32>,
    /// Metric depth along the optical axis (the positions' unit), NaN off the mask.
    pub depth: Array2<f32>,
    /// RMS of (observed − re-rendered) over each pixel's kept observations.
    pub residual: Array2<f32>,
    /// The pixels solved: the caller's mask, else those with three lit observations.
    pub mask: Array2<bool>,
    pub iterations: Vec<Iteration>,
    /// Whether the normals stopped moving within the iterations allowed.
    pub converged: bool,
    /// The lights' intensities estimated (mean 1), when asked for.
    pub intensities: Option<Vec<f64>>,
}
