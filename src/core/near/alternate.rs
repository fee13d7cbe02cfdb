//! The alternation on images in memory: per-pixel light vectors from the current
//! surface, the per-pixel fit ([`super::point`]), the perspective integration of its
//! normals, and the surface placed by the lights ([`super::scale`]), in turn until the
//! normals stop moving. The first surface is the plane at the working distance.

use ndarray::{Array2, Array3, ArrayView2, Axis};
use rayon::prelude::*;

use super::maps::{changes, split};
use super::pieces::pieces;
use super::point::{Scene, Scratch};
use super::scale::{Observed, stride_for};
use super::surface::{Iteration, NearSettings, NearSurface};
use crate::core::integrate::{self, perspective};
use crate::core::intensities::Gram;
use crate::core::lights::Light;
use crate::core::progress::Halt;

/// Re-estimations of the intensities before the first solve, and before each other.
const FIRST_INTENSITY_ROUNDS: usize = 3;
const INTENSITY_ROUNDS: usize = 1;

/// Solve `planes` (one per light, values 0..=65535 for [0, 1]) under near `lights` on
/// `mask`, in memory at their own resolution. Once `halt` says stop, returns what it has.
pub fn alternate(
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
                let next = Pass::new(planes, &lights, mask, settings).intensities(&depth);
                for (l, e) in lights.iter_mut().zip(next) {
                    l.intensity = e;
                }
            }
        }
        let pass = Pass::new(planes, &lights, mask, settings);
        let (g, residual) = pass.fit_all(&depth);
        let (normals, albedo) = split(&g, mask);
        let (mean, p95) = changes(&previous, &normals, mask);
        let (p, q) = perspective::log_depth_gradients(&normals, mask, &settings.camera);
        // After the first placement the lights have said where each piece sits.
        let placed = (!iterations.is_empty())
            .then(|| perspective::log_from_depth(&depth, mask, &settings.camera));
        let given = integrate::Given {
            slopes: Some((&p, &q)),
            start: placed.as_ref(),
        };
        let surface = integrate::integrate_log_depth(
            &normals,
            mask,
            &settings.camera,
            settings.integration,
            None,
            given,
            halt,
        );
        let relative = perspective::depth_from_log(&surface.zeta, mask, &settings.camera, None);
        let (label, sizes) = pieces(&surface, &p, &q, mask);
        let observed = pass.observed(&relative);
        (depth, scale) = observed.place(&pass.scene, &relative, (&label, &sizes), scale);
        iterations.push(Iteration {
            grid: [dim.1, dim.0],
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
                mask: mask.clone(),
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
    scene: Scene<'a>,
    mask: &'a Array2<bool>,
}

impl<'a> Pass<'a> {
    fn new(
        planes: &'a [ArrayView2<'a, u16>],
        lights: &'a [Light],
        mask: &'a Array2<bool>,
        settings: &'a NearSettings,
    ) -> Self {
        let scene = Scene {
            lights,
            camera: &settings.camera,
            reference: settings.distance,
        };
        Self {
            planes,
            scene,
            mask,
        }
    }

    /// Every mask pixel's `g` and RMS on the surface `depth`.
    fn fit_all(&self, depth: &Array2<f32>) -> (Array3<f32>, Array2<f32>) {
        let (h, w) = self.mask.dim();
        let mut g = Array3::<f32>::zeros((h, w, 3));
        let mut rms = Array2::<f32>::zeros((h, w));
        (g.outer_iter_mut().into_par_iter())
            .zip(rms.outer_iter_mut().into_par_iter())
            .enumerate()
            .for_each(|(r, (mut g, mut rms))| {
                let mut scratch = Scratch::new(self.scene.lights.len());
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
        self.observe(r, c, &mut s.obs);
        let f = self.scene.fit((r, c), d, s);
        (f.g, f.rms)
    }

    fn observe(&self, r: usize, c: usize, obs: &mut [f32]) {
        for (o, p) in obs.iter_mut().zip(self.planes) {
            *o = f32::from(p[[r, c]]) / 65535.0;
        }
    }

    /// The observations of the sampled pixels where `depth` is known, for the scale.
    fn observed(&self, depth: &Array2<f32>) -> Observed {
        let mut observed = Observed::new(self.planes.len());
        let mut obs = vec![0f32; self.planes.len()];
        for (r, c, _) in self.sample(depth) {
            self.observe(r, c, &mut obs);
            observed.push((r, c), obs.iter().copied());
        }
        observed
    }

    /// The lights' relative intensities (mean 1) that the sampled pixels' observations
    /// say, given the surface `depth` and the observations each pixel's fit under the
    /// current intensities keeps ([`Gram`]); the current ones when that says nothing.
    fn intensities(&self, depth: &Array2<f32>) -> Vec<f64> {
        let sample = self.sample(depth);
        let lights = self.scene.lights;
        let n = lights.len();
        let gram = Gram::sum_in_runs(n, sample.len(), |run, gram| {
            let mut scratch = Scratch::new(n);
            let mut unit = vec![[0f32; 3]; n];
            for &(r, c, d) in &sample[run] {
                self.fit_at(r, c, d, &mut scratch);
                for ((u, l), light) in unit.iter_mut().zip(&scratch.lights).zip(lights) {
                    let e = light.intensity as f32;
                    *u = l.map(|v| v / e);
                }
                gram.add(&unit, &scratch.obs, &scratch.keep);
            }
        });
        let current: Vec<f64> = lights.iter().map(|l| l.intensity).collect();
        gram.intensities(&current).unwrap_or(current)
    }

    /// About [`super::scale`]'s sample of the mask pixels where `depth` is known, on a
    /// regular grid, with their depth.
    fn sample(&self, depth: &Array2<f32>) -> Vec<(usize, usize, f64)> {
        let (h, w) = self.mask.dim();
        let on = self.mask.iter().filter(|m| **m).count();
        let stride = stride_for(on);
        (0..h)
            .step_by(stride)
            .flat_map(|r| (0..w).step_by(stride).map(move |c| (r, c)))
            .filter(|&(r, c)| self.mask[[r, c]] && depth[[r, c]].is_finite())
            .map(|(r, c)| (r, c, f64::from(depth[[r, c]])))
            .collect()
    }
}
