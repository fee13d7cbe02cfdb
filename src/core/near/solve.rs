//! The near-light solve of a set read in bands: the alternation ([`super::alternate`]) on
//! the images shrunk to about [`NearSettings::coarse_pixels`], then passes at full
//! resolution, each fitting every pixel on the last surface, integrating the normals and
//! placing the surface by the lights ([`super::scale`]).
//!
//! - An LED's direction and irradiance change slowly with the surface point, so the
//!   shrunk surface, enlarged, gives every pixel light vectors close to its own; the
//!   next passes fit on the full-resolution surface, which has what the shrunk grid
//!   could not see: fine relief, and the depth steps that blocks straddling them blur
//!   (the shrunk grid may not even see two pieces there).
//! - Images within the budget are solved whole by the alternation; in either case the
//!   images are read in bands and never held whole.

use ndarray::{Array2, Array3, ArrayView2, Axis, Zip};

use super::alternate::alternate;
use super::enlarge::enlarge;
use super::maps::{changes, split};
use super::pieces::pieces;
use super::point::Scene;
use super::refine::{Fits, Pass, Pixels, fit_bands, lit};
use super::scale::{Observed, stride_for};
use super::shrink::{factor_for, shrink, shrink_mask};
use super::surface::{Iteration, NearSettings, NearSurface};
use crate::core::bands::Stack;
use crate::core::camera::Pinhole;
use crate::core::error::InputError;
use crate::core::integrate::{self, perspective};
use crate::core::progress::Halt;

/// Full-resolution passes, at most. After the first, a pass refits only the pixels
/// whose surface point [moved](MOVED); the passes stop when none did, or once a refit
/// moves the normals less than [`FULL_TOLERANCE_DEG`] on average, leaving the surface
/// where it is (the first's change is against the shrunk grid's normals, no measure of
/// the full resolution's).
const MAX_FULL_PASSES: usize = 4;
const FULL_TOLERANCE_DEG: f64 = 0.05;
/// A surface point moved when its light vectors turn or dim by more than
/// [`FULL_TOLERANCE_DEG`] (relative, in radians): a move of δ changes a light's direction
/// by up to δ/r and its falloff by 2δ/r, r the distance to the nearest light.
const MOVED: f64 = FULL_TOLERANCE_DEG * std::f64::consts::PI / 180.0;
/// A pixel is lit when its observation is above this fraction of the set's brightest.
const LIT_FRACTION: u16 = 100;

/// Solve `stack` (lights with positions) on the caller's `mask`, else on the pixels
/// with three lit observations. Once `halt` says stop, returns what it has.
pub fn solve(
    stack: &mut dyn Stack,
    mask: Option<&Array2<bool>>,
    settings: &NearSettings,
    halt: Halt,
) -> Result<NearSurface, InputError> {
    let (w, h) = (stack.info().width, stack.info().height);
    let factor = factor_for(w, h, settings.coarse_pixels);
    let shrunk = shrink(stack, factor, &settings.camera, halt)?;
    let dark = (shrunk.peak / LIT_FRACTION).max(1);
    let small_mask = match mask {
        Some(m) => shrink_mask(m, factor),
        None => lit_blocks(&shrunk.planes, dark),
    };
    let planes: Vec<ArrayView2<u16>> = shrunk.planes.iter().map(|p| p.view()).collect();
    let mut lights = stack.info().lights.clone();
    let small = NearSettings {
        camera: shrunk.camera,
        ..settings.clone()
    };
    let coarse = alternate(&planes, &lights, &small_mask, &small, halt);
    drop(planes);
    drop(shrunk);
    if factor == 1 {
        return Ok(coarse);
    }
    if let Some(e) = &coarse.intensities {
        for (l, &i) in lights.iter_mut().zip(e) {
            l.intensity = i;
        }
    }
    let mut depth = enlarge(&coarse.depth, factor, (h, w));
    let mut previous = enlarge_normals(&coarse.normals, factor, (h, w));
    let mut full = mask
        .cloned()
        .unwrap_or_else(|| Array2::from_elem((h, w), false));
    let mut pixels = match mask {
        Some(_) => Pixels::Masked,
        None => Pixels::Lit { dark },
    };
    let scene = Scene {
        lights: &lights,
        camera: &settings.camera,
        reference: settings.distance,
    };
    let stride = stride_for(w * h);
    let mut scale = coarse
        .iterations
        .last()
        .map_or(settings.distance, |i| i.median_depth);
    let mut iterations = coarse.iterations;
    let mut fits = Fits::zeros(h, w);
    let mut observed = Observed::new(lights.len());
    let mut moved: Option<Array2<bool>> = None;
    let mut albedo = Array2::zeros((h, w));
    let mut settled = false;
    for pass in 1..=MAX_FULL_PASSES {
        if halt() {
            break;
        }
        let on = Pass {
            scene: &scene,
            depth: &depth,
            only: moved.as_ref(),
        };
        // The observations do not change between passes: the first keeps its sample.
        let sampling = (pass == 1).then_some((&mut observed, stride));
        fit_bands(stack, &on, (&mut full, pixels), &mut fits, sampling, halt)?;
        pixels = Pixels::Masked;
        let (normals, a) = split(&fits.g, &full);
        let (mean, p95) = changes(&previous, &normals, &full);
        (previous, albedo) = (normals, a);
        let mut iteration = Iteration {
            grid: [w, h],
            median_depth: scale,
            mean_change_deg: mean,
            p95_change_deg: p95,
        };
        // A refit that barely moved the normals leaves the surface where it is.
        if pass > 1 && mean < FULL_TOLERANCE_DEG {
            iterations.push(iteration);
            settled = true;
            break;
        }
        let (p, q) = perspective::log_depth_gradients(&previous, &full, &settings.camera);
        // The depth placed so far holds the steps the lights found.
        let placed = perspective::log_from_depth(&depth, &full, &settings.camera);
        let given = integrate::Given {
            slopes: Some((&p, &q)),
            start: Some(&placed),
        };
        let surface = integrate::integrate_log_depth(
            &previous,
            &full,
            &settings.camera,
            settings.integration,
            None,
            given,
            halt,
        );
        drop(placed);
        let relative = perspective::depth_from_log(&surface.zeta, &full, &settings.camera, None);
        let (label, sizes) = pieces(&surface, &p, &q, &full);
        drop((surface, p, q));
        let (next, s) = observed.place(&scene, &relative, (&label, &sizes), scale);
        drop((relative, label));
        let reach = nearest_light(&scene, &observed, &next);
        let far_moved = moved_points(&depth, &next, &full, &settings.camera, reach);
        (depth, scale) = (next, s);
        iteration.median_depth = scale;
        iterations.push(iteration);
        if !far_moved.iter().any(|m| *m) {
            settled = true;
            break;
        }
        moved = Some(far_moved);
    }
    Ok(NearSurface {
        normals: previous,
        albedo,
        depth,
        residual: fits.residual,
        mask: full,
        iterations,
        converged: coarse.converged && settled,
        intensities: coarse.intensities,
    })
}

/// The distance from the surface `depth` to its nearest light, over the sampled pixels.
fn nearest_light(scene: &Scene<'_>, observed: &Observed, depth: &Array2<f32>) -> f64 {
    let positions: Vec<[f64; 3]> = (scene.lights.iter())
        .filter_map(|l| l.emitter.map(|e| e.position))
        .collect();
    let mut nearest = f64::INFINITY;
    for &(r, c) in observed.pixels() {
        if !depth[[r, c]].is_finite() {
            continue;
        }
        let x = scene
            .camera
            .unproject(c as f64, r as f64, f64::from(depth[[r, c]]));
        for p in &positions {
            let d = (0..3).map(|k| (p[k] - x[k]).powi(2)).sum::<f64>().sqrt();
            nearest = nearest.min(d);
        }
    }
    nearest
}

/// The mask pixels whose surface point moves between `from` and `to` by more than
/// [`MOVED`] of `reach` (a third of it: direction and falloff together).
fn moved_points(
    from: &Array2<f32>,
    to: &Array2<f32>,
    mask: &Array2<bool>,
    camera: &Pinhole,
    reach: f64,
) -> Array2<bool> {
    let limit = MOVED * reach / 3.0;
    Zip::indexed(from)
        .and(to)
        .and(mask)
        .map_collect(|(r, c), &a, &b, &m| {
            let ray = camera.ray(c as f64, r as f64);
            let length = (ray[0] * ray[0] + ray[1] * ray[1] + 1.0).sqrt();
            // A point that became unknown (NaN) moved too.
            let step = f64::from((b - a).abs()) * length;
            m && (step > limit || step.is_nan())
        })
}

/// The [`lit`] pixels of the shrunk planes.
fn lit_blocks(planes: &[Array2<u16>], dark: u16) -> Array2<bool> {
    let dim = planes.first().map_or((0, 0), |p| p.dim());
    Array2::from_shape_fn(dim, |p| lit(planes.iter().map(|plane| plane[p]), dark))
}

/// The shrunk grid's normals at full resolution, each block's over its pixels.
fn enlarge_normals(normals: &Array3<f32>, factor: usize, (h, w): (usize, usize)) -> Array3<f32> {
    let mut big = Array3::zeros((h, w, 3));
    Zip::indexed(big.lanes_mut(Axis(2))).for_each(|(r, c), mut n| {
        n.assign(&normals.slice(ndarray::s![r / factor, c / factor, ..]));
    });
    big
}
