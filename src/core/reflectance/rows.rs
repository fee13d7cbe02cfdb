//! The lobe fit over a band's rows, after the robust solve has filled them: each pixel
//! whose Lambertian fit leaves bright residuals (a highlight) is fitted with the lobe
//! model, and where the lobe is kept its normal and diffuse albedo replace the robust
//! solve's and its specular albedo and roughness are recorded.

use ndarray::{ArrayViewMut2, Axis, s};
use rayon::prelude::*;

use super::fit::{Fitted, Material, Observation, fit};
use super::lobe::Facets;
use crate::core::bands::SurfaceRows;
use crate::core::lights::Light;
use crate::core::progress::Halt;
use crate::core::reconstruction::Gloss;
use crate::core::vec3::dot;

/// A band's rows of [`Gloss`].
pub struct GlossRows<'a> {
    pub specular: ArrayViewMut2<'a, f32>,
    pub roughness: ArrayViewMut2<'a, f32>,
    pub used: ArrayViewMut2<'a, bool>,
    pub beckmann: ArrayViewMut2<'a, bool>,
    pub residual: ArrayViewMut2<'a, f32>,
    pub lambertian_residual: ArrayViewMut2<'a, f32>,
}

impl<'a> GlossRows<'a> {
    /// Rows `a..b` of `gloss`.
    pub fn of(gloss: &'a mut Gloss, a: usize, b: usize) -> Self {
        Self {
            specular: gloss.specular.slice_mut(s![a..b, ..]),
            roughness: gloss.roughness.slice_mut(s![a..b, ..]),
            used: gloss.used.slice_mut(s![a..b, ..]),
            beckmann: gloss.beckmann.slice_mut(s![a..b, ..]),
            residual: gloss.residual.slice_mut(s![a..b, ..]),
            lambertian_residual: gloss.lambertian_residual.slice_mut(s![a..b, ..]),
        }
    }
}

/// Values at or above this (of full scale) are clipped: left out of the fit.
const CLIPPED: f64 = 0.995;

/// Refit the band's pixels (`planes[k]`: the band's rows of image `k`, `cols` wide) that
/// show a highlight, given the robust solve's rows in `surface`, the images' `black`
/// level and `noise` (σ), with the object's shared `material` if there is one (else
/// each pixel's own). Once `halt` says stop, the rows not yet started are left as the
/// robust solve left them.
#[allow(clippy::too_many_arguments)]
pub fn refine_rows(
    planes: &[&[u16]],
    cols: usize,
    lights: &[Light],
    black: f64,
    noise: f64,
    material: Option<Material>,
    surface: SurfaceRows<'_>,
    gloss: GlossRows<'_>,
    halt: Halt,
) {
    let SurfaceRows {
        mut albedo,
        mut normals,
        ..
    } = surface;
    let GlossRows {
        mut specular,
        mut roughness,
        mut used,
        mut beckmann,
        mut residual,
        mut lambertian_residual,
    } = gloss;
    // A shadow (attached or cast) is darker than this, a highlight brighter than the
    // Lambertian fit by more than `bright`.
    let dark = (3.0 * noise).max(0.002);
    let bright = (5.0 * noise).max(0.01);
    albedo
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(normals.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(specular.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(roughness.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(used.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(beckmann.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(residual.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(lambertian_residual.axis_iter_mut(Axis(0)).into_par_iter())
        .enumerate()
        .for_each(
            |(
                r,
                (
                    (
                        (((((mut a_row, mut n_row), mut s_row), mut r_row), mut u_row), mut b_row),
                        mut e_row,
                    ),
                    mut l_row,
                ),
            )| {
                if halt() {
                    return;
                }
                let mut obs = Vec::with_capacity(lights.len());
                for c in 0..cols {
                    let albedo = a_row[c] as f64;
                    let normal = [0, 1, 2].map(|k| n_row[[c, k]] as f64);
                    if albedo <= 0.0 || normal[2] <= 0.0 {
                        continue;
                    }
                    obs.clear();
                    let mut highlight = false;
                    for (plane, light) in planes.iter().zip(lights) {
                        let raw = plane[r * cols + c] as f64 / 65535.0;
                        if raw >= CLIPPED {
                            continue;
                        }
                        let value = raw - black;
                        if value <= dark {
                            continue;
                        }
                        let lambert =
                            light.intensity * albedo * dot(normal, light.direction).max(0.0);
                        highlight |= value - lambert > bright;
                        obs.push(Observation {
                            light: light.direction,
                            intensity: light.intensity,
                            value,
                        });
                    }
                    if !highlight {
                        continue;
                    }
                    if let Some(f) = fit(&obs, normal, albedo, noise, material) {
                        let lambert = Fitted {
                            normal,
                            diffuse: albedo,
                            specular: 0.0,
                            roughness: 1.0,
                            facets: Facets::Ggx,
                        };
                        e_row[c] = rms(&obs, &f) as f32;
                        l_row[c] = rms(&obs, &lambert) as f32;
                        a_row[c] = f.diffuse as f32;
                        for k in 0..3 {
                            n_row[[c, k]] = f.normal[k] as f32;
                        }
                        s_row[c] = f.specular as f32;
                        r_row[c] = f.roughness as f32;
                        u_row[c] = true;
                        b_row[c] = f.facets == Facets::Beckmann;
                    }
                }
            },
        );
}

/// The RMS of `model`'s residuals over `obs`.
fn rms(obs: &[Observation], model: &Fitted) -> f64 {
    let sum: f64 = (obs.iter())
        .map(|o| (model.predict(o.light, o.intensity) - o.value).powi(2))
        .sum();
    (sum / obs.len().max(1) as f64).sqrt()
}
