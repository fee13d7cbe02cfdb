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
use super::refine::{Pixels, fit_bands};
use super::scale::stride_for;
use super::shrink::{factor_for, shrink, shrink_mask};
use super::surface::{Iteration, NearSettings, NearSurface};
use crate::core::InputError;
use crate::core::bands::Stack;
use crate::core::integrate::{self, perspective};
use crate::core::progress::Halt;

/// Full-resolution passes: at least two (the first's change is against the shrunk
/// grid's normals, not a measure of the full resolution's), at most four.
const FULL_PASSES: std::ops::RangeInclusive<usize> = 2..=4;
/// They stop once the normals move less than this on average (degrees): each costs as
/// much as the alternation.
const FULL_TOLERANCE_DEG: f64 = 0.05;
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
        None => lit(&shrunk.planes, dark),
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
    let mut albedo = Array2::zeros((h, w));
    let mut residual = Array2::zeros((h, w));
    let mut settled = false;
    for pass in 1..=*FULL_PASSES.end() {
        if halt() {
            break;
        }
        let fits = fit_bands(stack, &scene, &depth, (&mut full, pixels), stride, halt)?;
        pixels = Pixels::Masked;
        let (normals, a) = split(&fits.g, &full);
        let (mean, p95) = changes(&previous, &normals, &full);
        let zeta = integrate::integrate_log_depth(
            &normals,
            &full,
            &settings.camera,
            settings.integration,
            None,
            halt,
        );
        let relative = perspective::depth_from_log(&zeta, &full, &settings.camera, None);
        let (p, q) = perspective::log_depth_gradients(&normals, &full, &settings.camera);
        let (label, sizes) = pieces(&zeta, &p, &q, &full);
        (depth, scale) = fits
            .observed
            .place(&scene, &relative, (&label, &sizes), scale);
        iterations.push(Iteration {
            grid: [w, h],
            median_depth: scale,
            mean_change_deg: mean,
            p95_change_deg: p95,
        });
        previous = normals;
        albedo = a;
        residual = fits.residual;
        settled = pass >= *FULL_PASSES.start() && mean < FULL_TOLERANCE_DEG;
        if settled {
            break;
        }
    }
    Ok(NearSurface {
        normals: previous,
        albedo,
        depth,
        residual,
        mask: full,
        iterations,
        converged: coarse.converged && settled,
        intensities: coarse.intensities,
    })
}

/// Pixels with at least three observations above `dark`.
fn lit(planes: &[Array2<u16>], dark: u16) -> Array2<bool> {
    let dim = planes.first().map_or((0, 0), |p| p.dim());
    Array2::from_shape_fn(dim, |p| {
        planes.iter().filter(|plane| plane[p] > dark).count() >= 3
    })
}

/// The shrunk grid's normals at full resolution, each block's over its pixels.
fn enlarge_normals(normals: &Array3<f32>, factor: usize, (h, w): (usize, usize)) -> Array3<f32> {
    let mut big = Array3::zeros((h, w, 3));
    Zip::indexed(big.lanes_mut(Axis(2))).for_each(|(r, c), mut n| {
        n.assign(&normals.slice(ndarray::s![r / factor, c / factor, ..]));
    });
    big
}
