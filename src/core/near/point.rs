//! One pixel's fit on the current surface: its light vectors from the surface point on
//! its ray ([`super::model`]), then the robust fit ([`super::pixel`]).

use super::model::light_vectors;
use super::pixel::{Fit, fit};
use crate::core::camera::Pinhole;
use crate::core::lights::Light;

/// Observations at or below this fraction of a pixel's brightest are shadow.
const DARK_FRACTION: f32 = 0.01;
/// The outlier test never trusts deviations below this (a fraction of full scale).
const NOISE_FLOOR: f32 = 0.004;

/// One thread's buffers for [`Scene::fit`].
pub struct Scratch {
    /// The pixel's observations in [0, 1], one per light: the caller fills them.
    pub obs: Vec<f32>,
    /// Its light vectors on the surface point.
    pub lights: Vec<[f32; 3]>,
    /// Which observations the fit kept.
    pub keep: Vec<bool>,
}

impl Scratch {
    pub fn new(n: usize) -> Self {
        Self {
            obs: vec![0.0; n],
            lights: vec![[0.0; 3]; n],
            keep: vec![false; n],
        }
    }
}

/// How a fit sees the scene: the lights, the camera whose pixels are fitted, and the
/// working distance the irradiance is relative to.
pub struct Scene<'a> {
    pub lights: &'a [Light],
    pub camera: &'a Pinhole,
    pub reference: f64,
}

impl Scene<'_> {
    /// The fit of pixel `(row, col)`, whose observations are in `s.obs`, with its
    /// surface point at depth `depth`.
    pub fn fit(&self, (row, col): (usize, usize), depth: f64, s: &mut Scratch) -> Fit {
        let x = self.camera.unproject(col as f64, row as f64, depth);
        light_vectors(self.lights, x, self.reference, &mut s.lights);
        let brightest = s.obs.iter().copied().fold(0f32, f32::max);
        let dark = (DARK_FRACTION * brightest).max(1.0 / 65535.0);
        fit(&s.lights, &s.obs, dark, NOISE_FLOOR, &mut s.keep)
    }
}
