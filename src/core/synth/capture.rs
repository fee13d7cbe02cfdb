//! How a rendered capture departs from the ideal one ([`Capture`]): the camera's
//! exposure, offset, noise and bit depth, the material's lobes, the lights' size and
//! colours, cast shadows and interreflection.

use super::brdf::{Diffuse, Specular};
use super::sensor::Exposure;
use super::transport::AreaLight;

/// How the lights, the camera and the material depart from the ideal capture (unit point
/// lights, Lambertian, no shadows cast, exact values).
#[derive(Debug, Clone)]
pub struct Capture {
    pub bit_depth: u8,
    /// Added to every pixel (ambient light + sensor offset), as a fraction of full scale.
    pub black_level: f64,
    /// Standard deviation of additive Gaussian (read) noise, fraction of full scale.
    pub noise_sigma: f64,
    /// Electrons at full scale, for photon shot noise (σ = sqrt(signal / full well));
    /// None for no shot noise.
    pub full_well: Option<f64>,
    pub exposure: Exposure,
    pub specular: Option<Specular>,
    /// The specular lobe's colour per channel (a metal's tinted highlights; a dielectric's
    /// are white, [1, 1, 1]). A gray scene uses the first.
    pub specular_tint: [f64; 3],
    /// The diffuse base: Lambertian, or rough (Oren–Nayar).
    pub diffuse: Diffuse,
    pub cast_shadows: bool,
    /// Lights of finite size (soft shadows); None for point lights.
    pub area_light: Option<AreaLight>,
    /// One bounce of interreflection traced with this many rays per pixel; None for none.
    pub bounce_rays: Option<usize>,
    /// Per-light RGB intensities (one per light, written as `name, x, y, z, r, g, b`
    /// rows); None for unit white lights.
    pub light_colours: Option<Vec<[f64; 3]>>,
    pub seed: u64,
}

impl Default for Capture {
    fn default() -> Self {
        Self {
            bit_depth: 16,
            black_level: 0.0,
            noise_sigma: 0.0,
            full_well: None,
            exposure: Exposure::Gain(1.0),
            specular: None,
            specular_tint: [1.0; 3],
            diffuse: Diffuse::Lambert,
            cast_shadows: false,
            area_light: None,
            bounce_rays: None,
            light_colours: None,
            seed: 1,
        }
    }
}
