//! The robust per-pixel solve: keep the observations a Lambertian model explains, set
//! aside shadows (too dark), highlights and saturation (too bright), and re-fit.
//!
//! Method: thresholded inlier selection with re-fits (a hard-threshold M-estimator).
//! 1. A global pre-pass on a subsample runs the per-pixel fit below and estimates the
//!    camera's black level (the median of observations the fits put in attached shadow)
//!    and the noise σ (MAD of the residuals of lit observations).
//! 2. Per pixel: subtract the black level, drop observations below 3σ or at saturation,
//!    fit least squares, then set aside, one at a time, the kept observation the fit
//!    misses worst while it misses by more than the tolerance (3σ + 2 % of the pixel's
//!    brightness under a typical light), and re-fit on the observations the fit predicts
//!    lit within the tolerance until the set stops changing. Normal equations are updated
//!    by subtracting the few dropped lights from the precomputed full LᵀL.
//! 3. Judged: fewer than 3 inliers, a fit facing away from the camera (or an exact
//!    3-inlier fit at grazing angle), or one that misses most observations while least
//!    squares explains the median one better: the pixel gets plain least squares over all
//!    its observations and is flagged unreliable.
//!
//! The `lanes` module settles the pixels whose every observation the model explains, a row at a
//! time, before any of this runs per pixel.

use ndarray::Axis;
use rayon::prelude::*;

mod intensities;
mod lanes;

pub use intensities::estimate_intensities;

use super::bands::{InMemory, Samples, Stack, SurfaceRows};
use super::intake::ImageSet;
use super::lambert::{invert3, pseudo_inverse, render_observation};
use super::lights::Light;
use super::progress::Halt;

const SCALE: f32 = 1.0 / 65535.0;
/// Re-fits per pixel at most; the inlier set almost always settles in two.
const MAX_ROUNDS: usize = 6;
/// Model-error allowance relative to the albedo (interreflection, mild gloss).
const RELATIVE_TOLERANCE: f32 = 0.02;
/// Observations at or above this fraction of full scale count as saturated.
const SATURATED: f32 = 0.999;

/// What the pre-pass learned about the capture.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct CaptureEstimate {
    /// Offset added to every pixel (ambient + sensor), in [0, 1] units.
    pub black_level: f32,
    /// Standard deviation of the noise, in [0, 1] units.
    pub noise_sigma: f32,
    /// Median lit observation, black level removed: the scale the two above are judged
    /// against.
    pub lit_median: f32,
}

struct Model {
    lights: Vec<[f32; 3]>,
    /// (LᵀL)⁻¹Lᵀ, per light: least squares over every observation as one sum.
    pinv: Vec<[f32; 3]>,
    /// Each light's outer product lᵢlᵢᵀ, packed (xx, xy, xz, yy, yz, zz).
    outer: Vec<[f64; 6]>,
    /// Σ lᵢlᵢᵀ over every light, packed, and its inverse.
    full: [f64; 6],
    full_inverse: Option<[[f64; 3]; 3]>,
    black: f32,
    dark: f32,
    tolerance: f32,
    /// Mean |lᵢ|: turns |g| into the image units the observations are in.
    light_scale: f32,
}

#[derive(Clone, Copy)]
struct Fit {
    g: [f32; 3],
    inliers: usize,
    reliable: bool,
    /// Σ (observed − re-rendered)² over every observation, and over the kept ones.
    sse_all: f32,
    sse_inliers: f32,
}

impl Model {
    fn new(lights: Vec<[f32; 3]>, black: f32, sigma: f32, quantum: f32) -> Self {
        let outer: Vec<[f64; 6]> = lights.iter().map(packed_outer).collect();
        let mut full = [0.0; 6];
        for o in &outer {
            for k in 0..6 {
                full[k] += o[k];
            }
        }
        let floor = sigma.max(quantum);
        let light_scale = lights.iter().map(|l| norm(*l)).sum::<f32>() / lights.len().max(1) as f32;
        Self {
            pinv: pseudo_inverse(&lights),
            light_scale,
            full_inverse: invert3(&unpack(&full)),
            lights,
            outer,
            full,
            black,
            dark: 3.0 * floor,
            tolerance: 3.0 * floor,
        }
    }

    /// Least squares over the observations not in `out`: the normal matrix is the full
    /// LᵀL minus the few excluded lights' outer products (6 unique entries each).
    fn solve(&self, y: &[f32], out: &[bool]) -> Option<[f32; 3]> {
        let mut m = self.full;
        let mut rhs = [0f32; 3];
        let mut kept = 0;
        for i in 0..self.lights.len() {
            let l = self.lights[i];
            if out[i] {
                let o = &self.outer[i];
                for k in 0..6 {
                    m[k] -= o[k];
                }
            } else {
                kept += 1;
                let v = y[i];
                rhs[0] += v * l[0];
                rhs[1] += v * l[1];
                rhs[2] += v * l[2];
            }
        }
        if kept < 3 {
            return None;
        }
        let inv = if kept == self.lights.len() {
            self.full_inverse?
        } else {
            invert3(&unpack(&m))?
        };
        let rhs = rhs.map(f64::from);
        Some(
            [0, 1, 2]
                .map(|r| (inv[r][0] * rhs[0] + inv[r][1] * rhs[1] + inv[r][2] * rhs[2]) as f32),
        )
    }

    /// The inlier tolerance for a fit `g`: the noise part, plus the model-error
    /// allowance relative to the pixel's brightness under a typical light (in image
    /// units, so neither exposure nor the light table's intensity scale moves it).
    fn tol(&self, g: [f32; 3]) -> f32 {
        self.tolerance + RELATIVE_TOLERANCE * norm(g) * self.light_scale
    }

    fn fit(
        &self,
        obs: &[f32],
        y: &mut [f32],
        out: &mut [bool],
        next: &mut [bool],
        scratch: &mut Vec<f32>,
    ) -> Fit {
        for ((yi, &o), x) in y.iter_mut().zip(obs).zip(out.iter_mut()) {
            *yi = o - self.black;
            *x = *yi <= self.dark || o >= SATURATED;
        }
        let lit = out.iter().filter(|o| !**o).count();
        let Some(mut g) = self.solve(y, out) else {
            // Too few lit observations: plain least squares, flagged.
            out.fill(false);
            let g = self.solve(y, out).unwrap_or([0.0; 3]);
            self.residuals(g, obs, scratch);
            return self.finish(g, false, out, scratch);
        };
        // Backward elimination: while the kept observation the fit explains worst misses
        // by more than the tolerance, set it aside and fit again. Highlights, penumbrae
        // and interreflections go first because they miss the most; one at a time, so a
        // fit dragged by a strong highlight never passes judgement on the good
        // observations. At most half of the lit observations go: past that the set has
        // no majority the model explains, and the re-fits below decide.
        let identifiable = lit > 4;
        if identifiable {
            for _ in 0..lit / 2 {
                let tol = self.tol(g);
                let mut worst = (tol, usize::MAX);
                for (i, l) in self.lights.iter().enumerate() {
                    if !out[i] {
                        let miss = (y[i] - dot(g, *l).max(0.0)).abs();
                        if miss > worst.0 {
                            worst = (miss, i);
                        }
                    }
                }
                if worst.1 == usize::MAX {
                    break;
                }
                out[worst.1] = true;
                match self.solve(y, out) {
                    Some(g2) => g = g2,
                    None => {
                        out[worst.1] = false;
                        break;
                    }
                }
            }
        }
        // Re-fit on the observations the model explains: in the fit where it predicts
        // light; set aside where it predicts shadow (they then cost y², nothing to fit),
        // and, when outliers are identifiable, where the shadow-aware re-rendering
        // misses by more than the tolerance (cast shadows, highlights, penumbrae).
        // With 4 observations or fewer the residual of a least-squares fit has at most
        // one degree of freedom and points the same way whichever one is wrong, so only
        // the shadow model and saturation decide.
        for _ in 0..MAX_ROUNDS {
            let tol = self.tol(g);
            let mut changed = false;
            for (i, l) in self.lights.iter().enumerate() {
                let pred = dot(g, *l);
                let outlier =
                    obs[i] >= SATURATED || (identifiable && (y[i] - pred.max(0.0)).abs() > tol);
                let drop = outlier || pred <= 0.0;
                changed |= drop != out[i];
                next[i] = drop;
            }
            if !changed {
                break;
            }
            match self.solve(y, next) {
                Some(g2) => {
                    g = g2;
                    out.copy_from_slice(next);
                }
                None => break,
            }
        }
        // The iteration stops at a stationary point of the shadow-aware objective, not
        // always the best one: plain least squares over the same non-outlier
        // observations is the other candidate, and the lower objective wins.
        // The objective renders like the camera: shadows black, saturation clipped.
        let tol = self.tol(g);
        self.residuals(g, obs, scratch);
        for (x, r) in next.iter_mut().zip(scratch.iter()) {
            *x = identifiable && r.abs() > tol;
        }
        if next != out
            && let Some(g_ls) = self.solve(y, next)
        {
            let cost = |r: &[f32]| -> f32 {
                r.iter()
                    .zip(next.iter())
                    .filter(|(_, s)| !**s)
                    .map(|(v, _)| v * v)
                    .sum()
            };
            let before = cost(scratch);
            self.residuals(g_ls, obs, scratch);
            if cost(scratch) < before {
                g = g_ls;
                out.copy_from_slice(next);
            } else {
                self.residuals(g, obs, scratch);
            }
        }
        self.finish(g, true, out, scratch)
    }

    /// [`Model::fit`], then judged: a fit no visible surface can have, or one that
    /// misses most observations by more than the tolerance and explains the pixel's
    /// typical observation worse than plain least squares over all of them (median
    /// absolute residual, shadows rendered black), is replaced by that least-squares fit
    /// and flagged. This is what keeps the robust solve from ever
    /// doing worse than `l2` where its model does not hold.
    fn judged(&self, obs: &[f32], b: &mut Buffers) -> Fit {
        let fit = self.fit(obs, &mut b.y, &mut b.out, &mut b.next, &mut b.r);
        if !fit.reliable {
            return fit;
        }
        if implausible(fit.g, fit.inliers) {
            return self.fallback(obs, &b.y, &mut b.out, &mut b.r);
        }
        if fit.inliers == obs.len() {
            return fit; // nothing set aside: already least squares
        }
        let robust = median_abs(&mut b.r);
        if robust <= self.tol(fit.g) {
            return fit; // most observations fit within the tolerance: trusted
        }
        let plain = self.solve(&b.y, vec_false(&mut b.next)).unwrap_or([0.0; 3]);
        self.residuals(plain, obs, &mut b.spare);
        if median_abs(&mut b.spare) < robust {
            return self.fallback(obs, &b.y, &mut b.out, &mut b.r);
        }
        fit
    }

    /// Plain least squares over every observation (black level removed), flagged
    /// unreliable: for pixels whose robust fit cannot be trusted.
    fn fallback(&self, obs: &[f32], y: &[f32], out: &mut [bool], r: &mut Vec<f32>) -> Fit {
        out.fill(false);
        let g = self.solve(y, out).unwrap_or([0.0; 3]);
        self.residuals(g, obs, r);
        self.finish(g, false, out, r)
    }

    /// Observed minus re-rendered, per light, into `r`.
    fn residuals(&self, g: [f32; 3], obs: &[f32], r: &mut Vec<f32>) {
        r.clear();
        r.extend(
            self.lights
                .iter()
                .zip(obs)
                .map(|(l, &o)| o - render_observation(g, *l, self.black)),
        );
    }

    fn finish(&self, g: [f32; 3], reliable: bool, out: &[bool], r: &[f32]) -> Fit {
        let (mut sse_all, mut sse_inliers, mut inliers) = (0.0, 0.0, 0);
        for (v, &dropped) in r.iter().zip(out) {
            sse_all += v * v;
            if !dropped {
                sse_inliers += v * v;
                inliers += 1;
            }
        }
        Fit {
            g,
            inliers: if reliable { inliers } else { 0 },
            reliable,
            sse_all,
            sse_inliers,
        }
    }
}

/// A fit no surface seen by the camera can have: facing away from it, or, when exactly 3
/// observations were kept (an exact solve with nothing left to check it), within the
/// grazing band integration clamps anyway. With few, similar lights (the seed's dog) such
/// fits come from dropping one observation and amplifying noise through the remaining
/// ill-conditioned three, and made the height map's spikes.
fn implausible(g: [f32; 3], inliers: usize) -> bool {
    let rho = norm(g);
    if !rho.is_finite() || rho <= 0.0 {
        return false;
    }
    let nz = g[2] / rho;
    nz <= 0.0 || (inliers <= 3 && nz < super::integrate::MIN_NZ)
}

/// Set-level warnings for `result.json`: estimates that the capture makes implausible,
/// and a solve where most of the object fell back to least squares.
pub fn warnings(
    estimate: Option<&CaptureEstimate>,
    unreliable: usize,
    object: usize,
) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(e) = estimate {
        if e.noise_sigma > 0.25 * e.lit_median {
            out.push(format!(
                "estimated noise sigma {:.5} is over a quarter of the median lit observation {:.5} \
                 (fractions of full scale): the images are very dark or very noisy, so shadows \
                 and highlights are hard to tell from noise",
                e.noise_sigma, e.lit_median
            ));
        }
        if e.black_level > 0.5 * e.lit_median {
            out.push(format!(
                "estimated black level {:.5} is over half the median lit observation {:.5}: \
                 check the exposure, or subtract a dark frame before uploading",
                e.black_level, e.lit_median
            ));
        }
    }
    if object > 0 && 2 * unreliable > object {
        out.push(format!(
            "{unreliable} of {object} object pixels ({:.0} %) fell back to least squares over all \
             their observations (see unreliable.png): too few observations fit the Lambertian \
             model there (too few lights reach them, or shadows and highlights dominate)",
            100.0 * unreliable as f64 / object as f64
        ));
    }
    out
}

/// Confidence in [0, 1]: support grows from 3 kept observations (0.25) to 6 or more (1),
/// times a Gaussian fall-off of the kept observations' RMS against the tolerance.
pub fn confidence_of(kept: usize, rms: f32, tolerance: f32) -> f32 {
    let support = ((kept as f32 - 2.0) / 4.0).clamp(0.0, 1.0);
    support * (-(rms / tolerance.max(1e-9)).powi(2)).exp()
}

fn packed_outer(l: &[f32; 3]) -> [f64; 6] {
    let [x, y, z] = l.map(f64::from);
    [x * x, x * y, x * z, y * y, y * z, z * z]
}

fn unpack(m: &[f64; 6]) -> [[f64; 3]; 3] {
    [[m[0], m[1], m[2]], [m[1], m[3], m[4]], [m[2], m[4], m[5]]]
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}

/// Per-thread buffers of one pixel's solve, `n` lights long.
struct Buffers {
    y: Vec<f32>,
    out: Vec<bool>,
    next: Vec<bool>,
    r: Vec<f32>,
    spare: Vec<f32>,
}

impl Buffers {
    fn new(n: usize) -> Self {
        Self {
            y: vec![0.0; n],
            out: vec![false; n],
            next: vec![false; n],
            r: Vec::with_capacity(n),
            spare: Vec::with_capacity(n),
        }
    }
}

fn vec_false(v: &mut [bool]) -> &[bool] {
    v.fill(false);
    v
}

/// Median of |v| (reorders `v`).
fn median_abs(v: &mut [f32]) -> f32 {
    for x in v.iter_mut() {
        *x = x.abs();
    }
    median(v)
}

/// Row `r` of every image's rows in `planes` (each `cols` wide).
fn plane_rows<'a>(planes: &[&'a [u16]], cols: usize, r: usize) -> Vec<&'a [u16]> {
    planes
        .iter()
        .map(|p| &p[r * cols..(r + 1) * cols])
        .collect()
}

fn gather(rows: &[&[u16]], c: usize, obs: &mut [f32]) {
    for (o, row) in obs.iter_mut().zip(rows) {
        *o = row[c] as f32 * SCALE;
    }
}

/// Estimate black level and noise of a set in memory (see [`estimate_from`]).
pub fn estimate(set: &ImageSet) -> CaptureEstimate {
    let stack = InMemory::new(set);
    estimate_from(
        &scaled(&set.lights),
        quantum(set.bit_depth),
        stack.samples(),
        set.width,
    )
}

fn scaled(lights: &[Light]) -> Vec<[f32; 3]> {
    lights
        .iter()
        .map(|l| l.scaled().map(|v| v as f32))
        .collect()
}

/// Estimate black level and noise from the sampled pixels (about 12 000, on a grid of
/// rows and columns `samples.stride` apart).
fn estimate_from(
    lights: &[[f32; 3]],
    quantum: f32,
    samples: &Samples,
    width: usize,
) -> CaptureEstimate {
    let n = lights.len();
    let stride = samples.stride;
    let sampled = samples.planes.first().map_or(0, |p| p.len() / width.max(1));
    let mut black = 0.0f32;
    let mut sigma = quantum;
    let mut lit_median = 0.0f32;
    // Two rounds: the first fit is biased by the unknown black level, the second is not.
    for _ in 0..2 {
        let model = Model::new(lights.to_vec(), black, sigma, quantum);
        let (mut shadow, mut resid, mut lit) = (Vec::new(), Vec::new(), Vec::new());
        let (mut obs, mut b) = (vec![0f32; n], Buffers::new(n));
        let planes: Vec<&[u16]> = samples.planes.iter().map(|p| p.as_slice()).collect();
        for r in 0..sampled {
            let rows = plane_rows(&planes, width, r);
            for c in (stride / 2..width).step_by(stride) {
                gather(&rows, c, &mut obs);
                // The same robust fit as the solve: a plain fit here would let highlights
                // drag g, and with it every residual and every "shadowed" observation.
                let fit = model.judged(&obs, &mut b);
                if !fit.reliable {
                    continue;
                }
                let y = &b.y;
                let g = fit.g;
                let rho = norm(g) * model.light_scale;
                for (i, l) in lights.iter().enumerate() {
                    let pred = dot(g, *l);
                    if pred < -0.1 * rho {
                        shadow.push(obs[i]);
                    } else if pred > 0.1 * rho && obs[i] < SATURATED {
                        resid.push((y[i] - pred).abs());
                        lit.push(y[i]);
                    }
                }
            }
        }
        if shadow.len() >= 50 {
            black = median(&mut shadow);
        }
        if !lit.is_empty() {
            lit_median = median(&mut lit);
        }
        if resid.len() >= 50 {
            // MAD → σ, corrected for the 3 fitted parameters.
            let dof = ((n as f32) / (n as f32 - 3.0).max(1.0)).sqrt();
            sigma = (1.4826 * median(&mut resid) * dof).max(quantum);
        }
    }
    CaptureEstimate {
        black_level: black,
        noise_sigma: sigma,
        lit_median,
    }
}

/// The standard deviation of rounding to the set's integer levels (one level / √12): the
/// noise no capture can be below, and the only intensity-unit constant in this solver.
fn quantum(bit_depth: u8) -> f32 {
    let level = if bit_depth <= 8 {
        1.0 / 255.0
    } else {
        1.0 / 65535.0
    };
    level / 12f32.sqrt()
}

fn median(v: &mut [f32]) -> f32 {
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, f32::total_cmp).1
}

/// The robust solver for one set: its pre-pass estimate and the model it fits with.
pub struct Robust {
    model: Model,
    pub estimate: CaptureEstimate,
}

impl Robust {
    /// The pre-pass over `samples` (the set's sampled rows, `width` wide).
    pub fn new(lights: &[Light], bit_depth: u8, samples: &Samples, width: usize) -> Self {
        let lights = scaled(lights);
        let quantum = quantum(bit_depth);
        let estimate = estimate_from(&lights, quantum, samples, width);
        let model = Model::new(lights, estimate.black_level, estimate.noise_sigma, quantum);
        Self { model, estimate }
    }

    /// Solve the rows of a band (`planes[k]`: the band's rows of image `k`, `cols` wide)
    /// into `out`; once `halt` says stop, the rows not yet started stay zero.
    pub fn solve_rows(&self, planes: &[&[u16]], cols: usize, out: SurfaceRows<'_>, halt: Halt) {
        let model = &self.model;
        let n = model.lights.len();
        let SurfaceRows {
            mut albedo,
            mut normals,
            mut residual,
            mut confidence,
            mut inliers,
            mut unreliable,
        } = out;
        albedo
            .axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(normals.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(residual.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(confidence.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(inliers.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(unreliable.axis_iter_mut(Axis(0)).into_par_iter())
            .enumerate()
            .for_each(
                |(
                    r,
                    (
                        ((((mut a_row, mut n_row), mut res_row), mut conf_row), mut in_row),
                        mut bad_row,
                    ),
                )| {
                    if halt() {
                        return;
                    }
                    let (mut obs, mut b) = (vec![0f32; n], Buffers::new(n));
                    let rows = plane_rows(planes, cols, r);
                    // Most pixels are settled by the row-wide fast path; the rest, and every
                    // pixel of a set of 4 lights or fewer (nothing to test outliers with),
                    // by the per-pixel fit.
                    let mut settled = Vec::with_capacity(cols);
                    if n > 4 {
                        lanes::settle_row(model, &rows, &mut settled);
                    }
                    for c in 0..cols {
                        let fit = match settled.get(c) {
                            Some(&lanes::Settled::Fit(fit)) => fit,
                            _ => {
                                gather(&rows, c, &mut obs);
                                model.judged(&obs, &mut b)
                            }
                        };
                        let rho = norm(fit.g);
                        a_row[c] = rho;
                        if rho > 0.0 && rho.is_finite() {
                            for k in 0..3 {
                                n_row[[c, k]] = fit.g[k] / rho;
                            }
                        }
                        in_row[c] = fit.inliers as u16;
                        bad_row[c] = !fit.reliable;
                        // Reprojection over every observation, the shadow model included.
                        res_row[c] = (fit.sse_all / n as f32).sqrt();
                        if fit.reliable && fit.inliers >= 3 {
                            let rms = (fit.sse_inliers / fit.inliers as f32).sqrt();
                            conf_row[c] = confidence_of(fit.inliers, rms, model.tol(fit.g));
                        }
                    }
                },
            );
    }
}
