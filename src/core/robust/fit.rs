//! One pixel's robust fit: the Lambertian [`Model`] of a set's lights, the backward
//! elimination and re-fits that choose the observations it explains ([`Fit`]), and the
//! judgement that replaces an untrustworthy fit by least squares; with the small vector,
//! median and row-reading helpers the rest of the solve shares.

use crate::core::integrate::MIN_NZ;
use crate::core::lambert::{invert3, pseudo_inverse, render_observation};

pub(super) const SCALE: f32 = 1.0 / 65535.0;
/// Re-fits per pixel at most; the inlier set almost always settles in two.
const MAX_ROUNDS: usize = 6;
/// Model-error allowance relative to the albedo (interreflection, mild gloss).
const RELATIVE_TOLERANCE: f32 = 0.02;
/// Observations at or above this fraction of full scale count as saturated.
pub(super) const SATURATED: f32 = 0.999;

pub(super) struct Model {
    pub(super) lights: Vec<[f32; 3]>,
    /// (LᵀL)⁻¹Lᵀ, per light: least squares over every observation as one sum.
    pub(super) pinv: Vec<[f32; 3]>,
    /// Each light's outer product lᵢlᵢᵀ, packed (xx, xy, xz, yy, yz, zz).
    outer: Vec<[f64; 6]>,
    /// Σ lᵢlᵢᵀ over every light, packed, and its inverse.
    full: [f64; 6],
    full_inverse: Option<[[f64; 3]; 3]>,
    pub(super) black: f32,
    pub(super) dark: f32,
    tolerance: f32,
    /// Mean |lᵢ|: turns |g| into the image units the observations are in.
    pub(super) light_scale: f32,
}

#[derive(Clone, Copy)]
pub(super) struct Fit {
    pub(super) g: [f32; 3],
    pub(super) inliers: usize,
    pub(super) reliable: bool,
    /// Σ (observed − re-rendered)² over every observation, and over the kept ones.
    pub(super) sse_all: f32,
    pub(super) sse_inliers: f32,
}

impl Model {
    pub(super) fn new(lights: Vec<[f32; 3]>, black: f32, sigma: f32, quantum: f32) -> Self {
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
    pub(super) fn tol(&self, g: [f32; 3]) -> f32 {
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
    pub(super) fn judged(&self, obs: &[f32], b: &mut Buffers) -> Fit {
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
pub(super) fn implausible(g: [f32; 3], inliers: usize) -> bool {
    let rho = norm(g);
    if !rho.is_finite() || rho <= 0.0 {
        return false;
    }
    let nz = g[2] / rho;
    nz <= 0.0 || (inliers <= 3 && nz < MIN_NZ)
}

fn packed_outer(l: &[f32; 3]) -> [f64; 6] {
    let [x, y, z] = l.map(f64::from);
    [x * x, x * y, x * z, y * y, y * z, z * z]
}

fn unpack(m: &[f64; 6]) -> [[f64; 3]; 3] {
    [[m[0], m[1], m[2]], [m[1], m[3], m[4]], [m[2], m[4], m[5]]]
}

pub(super) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(super) fn norm(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}

/// Per-thread buffers of one pixel's solve, `n` lights long.
pub(super) struct Buffers {
    pub(super) y: Vec<f32>,
    pub(super) out: Vec<bool>,
    next: Vec<bool>,
    r: Vec<f32>,
    spare: Vec<f32>,
}

impl Buffers {
    pub(super) fn new(n: usize) -> Self {
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
pub(super) fn plane_rows<'a>(planes: &[&'a [u16]], cols: usize, r: usize) -> Vec<&'a [u16]> {
    planes
        .iter()
        .map(|p| &p[r * cols..(r + 1) * cols])
        .collect()
}

pub(super) fn gather(rows: &[&[u16]], c: usize, obs: &mut [f32]) {
    for (o, row) in obs.iter_mut().zip(rows) {
        *o = row[c] as f32 * SCALE;
    }
}

pub(super) fn median(v: &mut [f32]) -> f32 {
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, f32::total_cmp).1
}
