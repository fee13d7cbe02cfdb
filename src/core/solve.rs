//! Per-pixel solve of I = L·g with g = albedo·n.
//!
//! Images stay 16-bit; each pixel's observations are gathered into registers row by row
//! and the solve runs in f32/f64 scalars, in parallel over rows.

use std::ops::Range;

use ndarray::{Array2, Array3, ArrayViewMut3, Axis, s};
use rayon::prelude::*;

use super::bands::{Band, Samples, SetInfo, Stack, SurfaceRows, each_band};
use super::error::InputError;
use super::lambert::{invert3, pseudo_inverse, render_observation};
use super::lights::Light;
use super::options::Solver;
use super::progress::Halt;
use super::reconstruction::Gloss;
use super::reflectance::{self, GlossRows, Material};
use super::robust::{self, CaptureEstimate};

/// The raw per-pixel solution, before masking and clamping.
#[derive(Debug, Clone)]
pub struct Surface {
    /// |g|, unclamped.
    pub albedo: Array2<f32>,
    /// g/|g|, zero where |g| = 0.
    pub normals: Array3<f32>,
    /// RMS over the images of (observed − re-rendered), shadows rendered as black.
    pub residual: Array2<f32>,
    /// Per-pixel reliability in [0, 1] (see [`robust::confidence_of`]).
    pub confidence: Array2<f32>,
    /// Observations each pixel's fit used.
    pub inliers: Array2<u16>,
    /// Pixels with fewer than 3 usable observations.
    pub unreliable: Array2<bool>,
    /// Black level and noise, when the solver estimates them.
    pub estimate: Option<CaptureEstimate>,
    /// For colour sets: each channel's albedo fitted against the normals (see
    /// [`colour_albedo`]), everywhere; the mask is applied later.
    pub albedo_rgb: Option<Array3<f32>>,
    /// The `glossy` solver's lobe maps.
    pub gloss: Option<Gloss>,
}

impl Surface {
    fn zeros(rows: usize, cols: usize, colour: bool) -> Self {
        Self {
            albedo: Array2::zeros((rows, cols)),
            normals: Array3::zeros((rows, cols, 3)),
            residual: Array2::zeros((rows, cols)),
            confidence: Array2::zeros((rows, cols)),
            inliers: Array2::zeros((rows, cols)),
            unreliable: Array2::from_elem((rows, cols), false),
            estimate: None,
            albedo_rgb: colour.then(|| Array3::zeros((rows, cols, 3))),
            gloss: None,
        }
    }

    fn rows_mut(&mut self, r: Range<usize>) -> SurfaceRows<'_> {
        let (a, b) = (r.start, r.end);
        SurfaceRows {
            albedo: self.albedo.slice_mut(s![a..b, ..]),
            normals: self.normals.slice_mut(s![a..b, .., ..]),
            residual: self.residual.slice_mut(s![a..b, ..]),
            confidence: self.confidence.slice_mut(s![a..b, ..]),
            inliers: self.inliers.slice_mut(s![a..b, ..]),
            unreliable: self.unreliable.slice_mut(s![a..b, ..]),
        }
    }
}

const SCALE: f32 = 1.0 / 65535.0;

/// Solve every pixel of the set under `lights` (the set's table, or it with estimated
/// intensities) with the chosen solver, band by band as `stack` reads them: each band is
/// solved as it arrives, so only one band of the images is held. Once `halt` says stop,
/// the bands not yet read are left at zero.
pub fn solve(
    stack: &mut dyn Stack,
    lights: &[Light],
    solver: Solver,
    halt: Halt,
) -> Result<Surface, InputError> {
    let info = SetInfo {
        lights: lights.to_vec(),
        ..stack.info().clone_without_mask()
    };
    let (rows, cols) = (info.height, info.width);
    let mut surface = Surface::zeros(rows, cols, info.colour);
    let robust = matches!(solver, Solver::Robust | Solver::Glossy)
        .then(|| robust::Robust::new(&info.lights, info.bit_depth, stack.samples(), cols));
    let linear = Linear::new(&info, solver);
    surface.estimate = robust.as_ref().map(|r| r.estimate);
    let mut gloss = (solver == Solver::Glossy).then(|| Gloss::zeros(rows, cols));
    if let (Some(r), Some(e), Some(g)) = (&robust, &surface.estimate, &mut gloss) {
        g.material = shared_material(stack.samples(), cols, &info.lights, r, e, halt);
    }
    each_band(stack, halt, |band_rows, band| {
        let (r0, r1) = (band_rows.start, band_rows.end);
        let out = surface.rows_mut(r0..r1);
        match &robust {
            Some(r) => r.solve_rows(&band.planes, cols, out, halt),
            None => linear.solve_rows(&band.planes, cols, out, halt),
        }
        if let (Some(g), Some(e)) = (&mut gloss, &surface.estimate) {
            reflectance::refine_rows(
                &band.planes,
                cols,
                &info.lights,
                e.black_level as f64,
                e.noise_sigma as f64,
                g.material,
                surface.rows_mut(r0..r1),
                GlossRows::of(g, r0, r1),
                halt,
            );
        }
        if let (Some(rgb), Some(_)) = (&mut surface.albedo_rgb, band.moments) {
            let normals = surface.normals.slice(s![r0..r1, .., ..]);
            colour_albedo(
                &band,
                rgb.slice_mut(s![r0..r1, .., ..]),
                normals,
                &info.lights,
            );
        }
    })?;
    surface.gloss = gloss;
    Ok(surface)
}

/// The lobe the object's pixels share ([`reflectance::shared`]), from lobes fitted freely
/// at the pre-pass's sample lattice (`samples`' rows, every `stride`-th column of a set
/// `cols` wide): about 12,000 pixels, 0.3 % of a 2048² frame's.
fn shared_material(
    samples: &Samples,
    cols: usize,
    lights: &[Light],
    robust: &robust::Robust,
    estimate: &CaptureEstimate,
    halt: Halt,
) -> Option<Material> {
    let picked: Vec<usize> = (samples.stride / 2..cols).step_by(samples.stride).collect();
    let lattice: Vec<Vec<u16>> = (samples.planes.iter())
        .map(|plane| {
            (plane.chunks_exact(cols))
                .flat_map(|row| picked.iter().map(|&c| row[c]))
                .collect()
        })
        .collect();
    let n = picked.len();
    let rows = lattice.first().map_or(0, |p| p.len() / n.max(1));
    if rows == 0 || n == 0 {
        return None;
    }
    let planes: Vec<&[u16]> = lattice.iter().map(Vec::as_slice).collect();
    let mut surface = Surface::zeros(rows, n, false);
    let mut gloss = Gloss::zeros(rows, n);
    robust.solve_rows(&planes, n, surface.rows_mut(0..rows), halt);
    reflectance::refine_rows(
        &planes,
        n,
        lights,
        estimate.black_level as f64,
        estimate.noise_sigma as f64,
        None,
        surface.rows_mut(0..rows),
        GlossRows::of(&mut gloss, 0, rows),
        halt,
    );
    reflectance::shared(&gloss)
}

impl SetInfo {
    /// The set's description without its mask (which the solve does not need).
    fn clone_without_mask(&self) -> SetInfo {
        SetInfo {
            width: self.width,
            height: self.height,
            bit_depth: self.bit_depth,
            lights: self.lights.clone(),
            colour: self.colour,
            mask: None,
            mask_file: None,
            notes: Vec::new(),
        }
    }
}

/// Each channel's albedo fitted against the recovered normals: for shading sᵢ = n·lᵢ,
/// a_c = Σᵢ Iᵢ,c sᵢ / Σᵢ sᵢ² = n·(Σᵢ lᵢ Iᵢ,c) / nᵀ(LᵀL)n, from the band's moments.
fn colour_albedo(
    band: &Band<'_>,
    mut out: ArrayViewMut3<'_, f32>,
    normals: ndarray::ArrayView3<'_, f32>,
    lights: &[Light],
) {
    let Some(moments) = band.moments else {
        return;
    };
    let mut ltl = [[0f32; 3]; 3];
    for l in lights {
        let s = l.scaled();
        for r in 0..3 {
            for c in 0..3 {
                ltl[r][c] += (s[r] * s[c]) as f32;
            }
        }
    }
    let (rows, cols, _) = normals.dim();
    let moments = ndarray::ArrayView2::from_shape((rows * cols, 9), moments)
        .expect("a band's moments are 9 per pixel");
    let normals = normals
        .into_shape_with_order((rows * cols, 3))
        .expect("standard layout");
    let mut out = out
        .view_mut()
        .into_shape_with_order((rows * cols, 3))
        .expect("standard layout");
    ndarray::Zip::from(out.rows_mut())
        .and(moments.rows())
        .and(normals.rows())
        .par_for_each(|mut o, m, n| {
            let quad: f32 = (0..3)
                .map(|r| (0..3).map(|c| n[r] * ltl[r][c] * n[c]).sum::<f32>())
                .sum();
            if quad <= 0.0 {
                return;
            }
            for ch in 0..3 {
                let dot = n[0] * m[ch * 3] + n[1] * m[ch * 3 + 1] + n[2] * m[ch * 3 + 2];
                o[ch] = (dot / quad).clamp(0.0, 1.0);
            }
        });
}

/// Every observation counts: plain or intensity-weighted least squares.
///
/// Works row by row (rows in parallel): each image's row is a contiguous run of u16, so
/// the L2 solve is a streaming accumulation g += pinv_k · I_k over the images, and the
/// residual a second pass over the same rows while they are still in cache. The inner
/// loops run over columns and vectorise.
struct Linear {
    solver: Solver,
    lights: Vec<[f32; 3]>,
    pinv: Vec<[f32; 3]>,
    quantum: f32,
}

impl Linear {
    fn new(info: &SetInfo, solver: Solver) -> Self {
        let lights: Vec<[f32; 3]> = (info.lights.iter())
            .map(|l| l.scaled().map(|v| v as f32))
            .collect();
        Self {
            solver,
            pinv: pseudo_inverse(&lights),
            lights,
            quantum: if info.bit_depth <= 8 {
                1.0 / 255.0
            } else {
                SCALE
            },
        }
    }

    /// Rows of a band: `planes[k]` holds the band's rows of image `k`.
    fn solve_rows(&self, planes: &[&[u16]], cols: usize, out: SurfaceRows<'_>, halt: Halt) {
        let n = self.lights.len();
        let SurfaceRows {
            mut albedo,
            mut normals,
            mut residual,
            mut confidence,
            mut inliers,
            ..
        } = out;
        inliers.fill(n as u16);
        let fresh = "a row of a standard-layout array is contiguous";
        albedo
            .axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(normals.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(residual.axis_iter_mut(Axis(0)).into_par_iter())
            .zip(confidence.axis_iter_mut(Axis(0)).into_par_iter())
            .enumerate()
            .with_min_len(4)
            .for_each_init(
                || RowScratch::new(cols, n),
                |s, (r, (((mut a_row, mut n_row), mut res_row), mut conf_row))| {
                    if halt() {
                        return;
                    }
                    let rows: Vec<&[u16]> = (planes.iter())
                        .map(|p| &p[r * cols..(r + 1) * cols])
                        .collect();
                    let out = RowOut {
                        albedo: a_row.as_slice_mut().expect(fresh),
                        normals: n_row.as_slice_mut().expect(fresh),
                        residual: res_row.as_slice_mut().expect(fresh),
                        confidence: conf_row.as_slice_mut().expect(fresh),
                    };
                    let l = (&self.lights, &self.pinv);
                    linear_row(self.solver, l.0, l.1, self.quantum, &rows, s, out);
                },
            );
    }
}

/// One row's outputs in [`linear`].
struct RowOut<'a> {
    albedo: &'a mut [f32],
    normals: &'a mut [f32],
    residual: &'a mut [f32],
    confidence: &'a mut [f32],
}

multiversion! {
    fn linear_row(
        solver: Solver, lights: &[[f32; 3]], pinv: &[[f32; 3]], quantum: f32, rows: &[&[u16]],
        s: &mut RowScratch, out: RowOut<'_>,
    ) -> () => linear_row_body
}

/// One row of [`linear`]; `rows[k]` is the row in image `k`.
#[inline(always)]
fn linear_row_body(
    solver: Solver,
    lights: &[[f32; 3]],
    pinv: &[[f32; 3]],
    quantum: f32,
    rows: &[&[u16]],
    s: &mut RowScratch,
    out: RowOut<'_>,
) {
    let n = lights.len();
    let RowScratch {
        gx,
        gy,
        gz,
        sq,
        obs,
    } = s;
    match solver {
        Solver::L2 => {
            gx.fill(0.0);
            gy.fill(0.0);
            gz.fill(0.0);
            // Separate x, y, z lanes so the column loops vectorise.
            for (p, row) in pinv.iter().zip(rows) {
                let lanes = gx.iter_mut().zip(gy.iter_mut()).zip(gz.iter_mut());
                for (((x, y), z), &v) in lanes.zip(row.iter()) {
                    let o = v as f32 * SCALE;
                    *x += p[0] * o;
                    *y += p[1] * o;
                    *z += p[2] * o;
                }
            }
        }
        Solver::Weighted => {
            for c in 0..gx.len() {
                for (o, row) in obs.iter_mut().zip(rows) {
                    *o = row[c] as f32 * SCALE;
                }
                [gx[c], gy[c], gz[c]] = weighted(lights, obs);
            }
        }
        Solver::Robust | Solver::Glossy => unreachable!("handled by robust::solve"),
    }
    sq.fill(0.0);
    for (l, row) in lights.iter().zip(rows) {
        let lanes = gx.iter().zip(gy.iter()).zip(gz.iter());
        for ((((x, y), z), sq), &v) in lanes.zip(sq.iter_mut()).zip(row.iter()) {
            let d = v as f32 * SCALE - render_observation([*x, *y, *z], *l, 0.0);
            *sq += d * d;
        }
    }
    let RowOut {
        albedo,
        normals,
        residual,
        confidence,
    } = out;
    // |g| and the RMS residual in lane loops that vectorise; the normals and the
    // confidence (an `exp` per pixel) after them.
    let lanes = gx.iter().zip(gy.iter()).zip(gz.iter());
    for (a, ((x, y), z)) in albedo.iter_mut().zip(lanes) {
        *a = (x * x + y * y + z * z).sqrt();
    }
    for (res, sq) in residual.iter_mut().zip(sq.iter()) {
        *res = (sq / n as f32).sqrt();
    }
    for (c, &rho) in albedo.iter().enumerate() {
        if rho > 0.0 && rho.is_finite() {
            normals[c * 3] = gx[c] / rho;
            normals[c * 3 + 1] = gy[c] / rho;
            normals[c * 3 + 2] = gz[c] / rho;
        }
    }
    for ((conf, &res), &rho) in confidence
        .iter_mut()
        .zip(residual.iter())
        .zip(albedo.iter())
    {
        *conf = robust::confidence_of(n, res, 3.0 * quantum + 0.02 * rho);
    }
}

/// Per-thread buffers for one row: g per column (one lane per component), squared
/// residual sums, one pixel's observations (weighted solver).
struct RowScratch {
    gx: Vec<f32>,
    gy: Vec<f32>,
    gz: Vec<f32>,
    sq: Vec<f32>,
    obs: Vec<f32>,
}

impl RowScratch {
    fn new(cols: usize, n: usize) -> Self {
        Self {
            gx: vec![0.0; cols],
            gy: vec![0.0; cols],
            gz: vec![0.0; cols],
            sq: vec![0.0; cols],
            obs: vec![0.0; n],
        }
    }
}

/// RMS of observed minus re-rendered intensity (see [`render_observation`]).
pub fn reprojection_rms(lights: &[[f32; 3]], obs: &[f32], g: [f32; 3]) -> f32 {
    let sum: f32 = lights
        .iter()
        .zip(obs)
        .map(|(l, &o)| (o - render_observation(g, *l, 0.0)).powi(2))
        .sum();
    (sum / obs.len() as f32).sqrt()
}

/// The seed's "solution 1": least squares weighted by T = diag(i), i.e. weights i².
/// Observations in shadow get no say, but bright ones dominate, which biases normals
/// towards the brightest lights.
fn weighted(lights: &[[f32; 3]], obs: &[f32]) -> [f32; 3] {
    let mut m = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for (l, &o) in lights.iter().zip(obs) {
        let w = (o as f64) * (o as f64);
        for r in 0..3 {
            b[r] += w * o as f64 * l[r] as f64;
            for c in 0..3 {
                m[r][c] += w * l[r] as f64 * l[c] as f64;
            }
        }
    }
    match invert3(&m) {
        Some(inv) => [0, 1, 2].map(|r| (0..3).map(|k| inv[r][k] * b[k]).sum::<f64>() as f32),
        None => [0.0; 3],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::bands::InMemory;
    use crate::core::intake::ImageSet;
    use crate::core::lights::Light;
    use crate::core::progress::NEVER;

    fn set_from(lights: &[[f64; 3]], pixels: &[[f32; 3]], albedo: f32) -> ImageSet {
        let lights: Vec<Light> = lights
            .iter()
            .enumerate()
            .map(|(i, d)| {
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                Light {
                    name: format!("{i}"),
                    direction: d.map(|v| v / n),
                    intensity: 1.0,
                    rgb: None,
                    emitter: None,
                }
            })
            .collect();
        let planes = lights
            .iter()
            .map(|l| {
                Array2::from_shape_fn((1, pixels.len()), |(_, c)| {
                    let n = pixels[c];
                    let v = albedo
                        * (n[0] * l.direction[0] as f32
                            + n[1] * l.direction[1] as f32
                            + n[2] * l.direction[2] as f32);
                    (v.max(0.0) * 65535.0).round() as u16
                })
            })
            .collect();
        ImageSet {
            width: pixels.len(),
            height: 1,
            bit_depth: 16,
            lights,
            planes,
            colour_moments: None,
            mask: None,
            mask_file: None,
            notes: Vec::new(),
        }
    }

    #[test]
    fn l2_recovers_normals_and_albedo_of_unshadowed_pixels() {
        let s = 0.5f32.sqrt();
        let pixels = [[0.0, 0.0, 1.0], [s, 0.0, s], [0.0, -0.3, 0.9539392]];
        let set = set_from(
            &[
                [0.0, 0.0, 1.0],
                [0.3, 0.0, 1.0],
                [0.0, 0.3, 1.0],
                [-0.2, -0.2, 1.0],
            ],
            &pixels,
            0.7,
        );
        let surf = solve(&mut InMemory::new(&set), &set.lights, Solver::L2, NEVER).unwrap();
        for (c, n) in pixels.iter().enumerate() {
            assert!(
                (surf.albedo[[0, c]] - 0.7).abs() < 1e-3,
                "{}",
                surf.albedo[[0, c]]
            );
            for k in 0..3 {
                assert!((surf.normals[[0, c, k]] - n[k]).abs() < 1e-3);
            }
            assert!(surf.residual[[0, c]] < 1e-4);
        }
    }

    #[test]
    fn zero_pixels_get_zero_normal() {
        let set = set_from(
            &[[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [0.0, 0.3, 1.0]],
            &[[0.0, 0.0, 1.0]],
            0.0,
        );
        for solver in [Solver::L2, Solver::Weighted] {
            let surf = solve(&mut InMemory::new(&set), &set.lights, solver, NEVER).unwrap();
            assert_eq!(surf.albedo[[0, 0]], 0.0);
            assert_eq!(surf.normals.sum(), 0.0);
        }
    }
}
