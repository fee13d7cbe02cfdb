//! The near-light reconstruction: per-pixel light vectors from the current surface, the
//! per-pixel fit ([`super::fit`]), the perspective integration of its normals, and the
//! surface's scale, in turn until the normals stop moving.
//!
//! - The first surface is the plane at the working distance.
//! - Integration gives depth up to one scale (`depth_from_log`); unlike distant lights,
//!   near lights fix it: moving the surface along the rays changes every pixel's light
//!   directions and falloff differently, and only the true distance lets one `ρ n`
//!   explain all of a pixel's observations. The scale is the one whose fits leave the
//!   smallest residual over a sample of the mask (golden-section search on its logarithm).
//!   Pieces that depth steps separate ([`super::pieces`]) get their own scale: the
//!   integration cannot say how far apart they are, the lights can.

use ndarray::{Array2, Array3, ArrayView2, Axis, Zip};
use rayon::prelude::*;

use super::intensities::Gram;
use super::model::light_vectors;
use super::pieces::pieces;
use super::pixel::fit;
use crate::core::camera::Pinhole;
use crate::core::integrate::{self, perspective};
use crate::core::lights::Light;
use crate::core::options::Integration;
use crate::core::progress::Halt;

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
        }
    }
}

/// One alternation: the surface it solved on and how far the normals moved.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Iteration {
    /// Median depth over the mask of the surface integrated after the solve.
    pub median_depth: f64,
    /// Mean and 95th-percentile angle between this solve's normals and the last one's
    /// (the first: against the normals facing the camera), degrees.
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
    pub iterations: Vec<Iteration>,
    /// Whether the normals stopped moving within the iterations allowed.
    pub converged: bool,
    /// The lights' intensities estimated (mean 1), when asked for.
    pub intensities: Option<Vec<f64>>,
}

/// Observations at or below this fraction of a pixel's brightest are shadow.
const DARK_FRACTION: f32 = 0.01;
/// The outlier test never trusts deviations below this (a fraction of full scale).
const NOISE_FLOOR: f32 = 0.004;
/// Pixels the scale search samples (about).
const SCALE_SAMPLES: usize = 20_000;
/// The scale search brackets the current scale within this factor either way.
const SCALE_BRACKET: f64 = 2.0;
const SCALE_STEPS: usize = 40;
/// Re-estimations of the intensities before the first solve, and before each other.
const FIRST_INTENSITY_ROUNDS: usize = 3;
const INTENSITY_ROUNDS: usize = 1;
/// Pieces of the surface at least this fraction of the mask get their own scale; the
/// others keep the whole surface's.
const MIN_PIECE: f64 = 0.02;

/// Solve `planes` (one per light, values 0..=65535 for [0, 1]) under near `lights` on
/// `mask`. Once `halt` says stop, returns what it has.
pub fn solve(
    planes: &[ArrayView2<u16>],
    lights: &[Light],
    mask: &Array2<bool>,
    settings: &NearSettings,
    halt: Halt,
) -> NearSurface {
    let dim = mask.dim();
    let mut depth = Array2::from_shape_fn(dim, |p| {
        if mask[p] {
            settings.distance as f32
        } else {
            f32::NAN
        }
    });
    let mut previous = Array3::<f32>::zeros((dim.0, dim.1, 3));
    previous.index_axis_mut(Axis(2), 2).fill(1.0);
    let mut iterations = Vec::new();
    let mut converged = false;
    let mut scale = settings.distance;
    let mut lights = lights.to_vec();
    loop {
        if settings.estimate_intensities {
            let rounds = if iterations.is_empty() {
                FIRST_INTENSITY_ROUNDS
            } else {
                INTENSITY_ROUNDS
            };
            for _ in 0..rounds {
                let pass = Pass {
                    planes,
                    lights: &lights,
                    mask,
                    settings,
                };
                let next = pass.intensities(&depth);
                for (l, e) in lights.iter_mut().zip(next) {
                    l.intensity = e;
                }
            }
        }
        let pass = Pass {
            planes,
            lights: &lights,
            mask,
            settings,
        };
        let (g, residual) = pass.fit_all(&depth);
        let (normals, albedo) = split(&g, mask);
        let (mean, p95) = changes(&previous, &normals, mask);
        let zeta = integrate::integrate_log_depth(
            &normals,
            mask,
            &settings.camera,
            settings.integration,
            None,
            halt,
        );
        let relative = perspective::depth_from_log(&zeta, mask, &settings.camera, None);
        scale = pass.best_scale(&relative, scale, |_, _| true);
        depth = relative.mapv(|d| (f64::from(d) * scale) as f32);
        let (p, q) = perspective::log_depth_gradients(&normals, mask, &settings.camera);
        let (label, sizes) = pieces(&zeta, &p, &q, mask);
        let smallest = (MIN_PIECE * sizes.iter().sum::<usize>() as f64) as usize;
        for (id, _) in sizes.iter().enumerate().filter(|(_, n)| **n >= smallest) {
            if sizes.len() == 1 {
                break;
            }
            let own = pass.best_scale(&relative, scale, |r, c| label[[r, c]] == id);
            Zip::from(&mut depth)
                .and(&relative)
                .and(&label)
                .for_each(|d, &rel, &l| {
                    if l == id {
                        *d = (f64::from(rel) * own) as f32;
                    }
                });
        }
        iterations.push(Iteration {
            median_depth: scale,
            mean_change_deg: mean,
            p95_change_deg: p95,
        });
        previous = normals;
        if mean < settings.tolerance_deg {
            converged = true;
        }
        if converged || iterations.len() >= settings.max_iterations || halt() {
            return NearSurface {
                normals: previous,
                albedo,
                depth,
                residual,
                iterations,
                converged,
                intensities: (settings.estimate_intensities)
                    .then(|| lights.iter().map(|l| l.intensity).collect()),
            };
        }
    }
}

/// One pass over the images on a given surface.
struct Pass<'a> {
    planes: &'a [ArrayView2<'a, u16>],
    lights: &'a [Light],
    mask: &'a Array2<bool>,
    settings: &'a NearSettings,
}

impl Pass<'_> {
    /// Every mask pixel's `g` and RMS on the surface `depth`.
    fn fit_all(&self, depth: &Array2<f32>) -> (Array3<f32>, Array2<f32>) {
        let (h, w) = self.mask.dim();
        let mut g = Array3::<f32>::zeros((h, w, 3));
        let mut rms = Array2::<f32>::zeros((h, w));
        (g.outer_iter_mut().into_par_iter())
            .zip(rms.outer_iter_mut().into_par_iter())
            .enumerate()
            .for_each(|(r, (mut g, mut rms))| {
                let mut scratch = Scratch::new(self.lights.len());
                for c in 0..w {
                    if !self.mask[[r, c]] {
                        continue;
                    }
                    let f = self.fit_at(r, c, f64::from(depth[[r, c]]), &mut scratch);
                    for k in 0..3 {
                        g[[c, k]] = f.0[k];
                    }
                    rms[c] = f.1;
                }
            });
        (g, rms)
    }

    /// The fit of pixel `(r, c)` with its surface point at depth `d`.
    fn fit_at(&self, r: usize, c: usize, d: f64, s: &mut Scratch) -> ([f32; 3], f32) {
        for (o, p) in s.obs.iter_mut().zip(self.planes) {
            *o = f32::from(p[[r, c]]) / 65535.0;
        }
        let x = self.settings.camera.unproject(c as f64, r as f64, d);
        light_vectors(self.lights, x, self.settings.distance, &mut s.lights);
        let brightest = s.obs.iter().copied().fold(0f32, f32::max);
        let dark = (DARK_FRACTION * brightest).max(1.0 / 65535.0);
        let f = fit(&s.lights, &s.obs, dark, NOISE_FLOOR, &mut s.keep);
        (f.g, f.rms)
    }

    /// The lights' relative intensities (mean 1) that the sampled pixels' observations
    /// say, given the surface `depth` and the observations each pixel's fit under the
    /// current intensities keeps ([`Gram`]); the current ones when that says nothing.
    fn intensities(&self, depth: &Array2<f32>) -> Vec<f64> {
        let sample = self.sample(depth, |_, _| true);
        let n = self.lights.len();
        let gram = sample
            .par_chunks(256)
            .map(|chunk| {
                let mut scratch = Scratch::new(n);
                let mut gram = Gram::new(n);
                let mut unit = vec![[0f32; 3]; n];
                for &(r, c, d) in chunk {
                    self.fit_at(r, c, d, &mut scratch);
                    for ((u, l), light) in unit.iter_mut().zip(&scratch.lights).zip(self.lights) {
                        let e = light.intensity as f32;
                        *u = l.map(|v| v / e);
                    }
                    gram.add(&unit, &scratch.obs, &scratch.keep);
                }
                gram
            })
            .reduce(|| Gram::new(n), Gram::merge);
        let current: Vec<f64> = self.lights.iter().map(|l| l.intensity).collect();
        gram.intensities(&current).unwrap_or(current)
    }

    /// About [`SCALE_SAMPLES`] mask pixels that `select` takes, on a regular grid, with
    /// their `depth`.
    fn sample(
        &self,
        depth: &Array2<f32>,
        select: impl Fn(usize, usize) -> bool,
    ) -> Vec<(usize, usize, f64)> {
        let (h, w) = self.mask.dim();
        let on = (self.mask.indexed_iter())
            .filter(|((r, c), m)| **m && select(*r, *c))
            .count()
            .max(1);
        let stride = ((on as f64 / SCALE_SAMPLES as f64).sqrt().ceil() as usize).max(1);
        (0..h)
            .step_by(stride)
            .flat_map(|r| (0..w).step_by(stride).map(move |c| (r, c)))
            .filter(|&(r, c)| self.mask[[r, c]] && depth[[r, c]].is_finite() && select(r, c))
            .map(|(r, c)| (r, c, f64::from(depth[[r, c]])))
            .collect()
    }

    /// The scale of `relative` (median depth 1) whose fits leave the smallest squared
    /// residual over a sample of the mask's pixels that `select` takes, searched around
    /// `current`.
    fn best_scale(
        &self,
        relative: &Array2<f32>,
        current: f64,
        select: impl Fn(usize, usize) -> bool,
    ) -> f64 {
        let sample = self.sample(relative, select);
        if sample.is_empty() {
            return current;
        }
        let cost = |t: f64| -> f64 {
            let s = t.exp();
            sample
                .par_chunks(256)
                .map(|chunk| {
                    let mut scratch = Scratch::new(self.lights.len());
                    chunk
                        .iter()
                        .map(|&(r, c, d)| {
                            let (_, rms) = self.fit_at(r, c, d * s, &mut scratch);
                            f64::from(rms) * f64::from(rms)
                        })
                        .sum::<f64>()
                })
                .sum()
        };
        golden_min(
            cost,
            current.ln() - SCALE_BRACKET.ln(),
            current.ln() + SCALE_BRACKET.ln(),
            SCALE_STEPS,
        )
        .exp()
    }
}

struct Scratch {
    obs: Vec<f32>,
    lights: Vec<[f32; 3]>,
    keep: Vec<bool>,
}

impl Scratch {
    fn new(n: usize) -> Self {
        Self {
            obs: vec![0.0; n],
            lights: vec![[0.0; 3]; n],
            keep: vec![false; n],
        }
    }
}

/// The minimum of `f` on `[a, b]` by golden-section search (`steps` shrinkings).
fn golden_min(f: impl Fn(f64) -> f64, mut a: f64, mut b: f64, steps: usize) -> f64 {
    let ratio = (5f64.sqrt() - 1.0) / 2.0;
    let mut x1 = b - ratio * (b - a);
    let mut x2 = a + ratio * (b - a);
    let (mut f1, mut f2) = (f(x1), f(x2));
    for _ in 0..steps {
        if f1 <= f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - ratio * (b - a);
            f1 = f(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + ratio * (b - a);
            f2 = f(x2);
        }
    }
    (a + b) / 2.0
}

/// Unit normals and albedo from `g`, zero off the mask and where `g` is zero.
fn split(g: &Array3<f32>, mask: &Array2<bool>) -> (Array3<f32>, Array2<f32>) {
    let mut normals = Array3::<f32>::zeros(g.dim());
    let mut albedo = Array2::<f32>::zeros(mask.dim());
    Zip::from(normals.lanes_mut(Axis(2)))
        .and(&mut albedo)
        .and(g.lanes(Axis(2)))
        .and(mask)
        .for_each(|mut n, a, g, &m| {
            let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
            if m && len > 0.0 {
                *a = len;
                for k in 0..3 {
                    n[k] = g[k] / len;
                }
            }
        });
    (normals, albedo)
}

/// Mean and 95th-percentile angle (degrees) between two normal maps over the mask.
fn changes(a: &Array3<f32>, b: &Array3<f32>, mask: &Array2<bool>) -> (f64, f64) {
    let mut angles: Vec<f64> = Vec::new();
    Zip::from(a.lanes(Axis(2)))
        .and(b.lanes(Axis(2)))
        .and(mask)
        .for_each(|a, b, &m| {
            if m {
                let d = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0);
                angles.push(f64::from(d).acos().to_degrees());
            }
        });
    if angles.is_empty() {
        return (0.0, 0.0);
    }
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    let k = (angles.len() * 95 / 100).min(angles.len() - 1);
    let p95 = *angles.select_nth_unstable_by(k, f64::total_cmp).1;
    (mean, p95)
}
