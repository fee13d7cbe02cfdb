//! Frankot–Chellappa integration: least-squares projection onto integrable surfaces in the
//! Fourier domain, on the full (periodic) rectangle.
//!
//! Frequency convention: the same discretisation as the Poisson integrator, i.e. the height
//! difference across each pixel edge equals the average of the two gradient samples
//! (`z[c+1] − z[c] = (p[c] + p[c+1]) / 2`). Minimising the squared mismatch of these
//! equations on a periodic grid gives, with `ωx = 2πl/W`, `ωy = 2πk/H`,
//!
//! ```text
//! Ẑ = −i (sin ωx · P̂ + sin ωy · Q̂) / (4 sin²(ωx/2) + 4 sin²(ωy/2)),   Ẑ(0,0) = 0
//! ```
//!
//! ("sin" numerator = central differences, denominator = the 5-point Laplacian). Unlike
//! the continuous `iω / ω²` form it is exact for the discrete equations (a discretely
//! integrable field is reproduced to round-off), and unlike a pure central-difference
//! `sin / sin²` form its denominator vanishes only at DC (no checkerboard null space at
//! Nyquist).
//!
//! Boundary: deliberately periodic, no mirror extension. With an even/odd mirror
//! extension this exact least-squares problem becomes the Neumann problem that the
//! `poisson` integrator already solves on a full mask with a DCT, on a quarter of the
//! samples, so the extension would only duplicate it. Frankot–Chellappa therefore stays the classical,
//! mask-unaware global method (gradients are 0 off the mask); it is accurate on
//! periodic-ish surfaces and on objects that do not touch the frame edge.

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};
use std::f64::consts::PI;
use std::sync::Arc;

/// Rows per rayon task for the batched 1-D transforms.
const ROWS_PER_TASK: usize = 8;

/// Out-of-place transpose of a row-major `h × w` array into `w × h`, in cache tiles, in
/// parallel over output rows.
pub(super) fn transpose<T: Copy + Send + Sync>(src: &[T], h: usize, w: usize, dst: &mut [T]) {
    const TILE: usize = 32;
    assert_eq!(src.len(), h * w);
    assert_eq!(dst.len(), h * w);
    if h == 0 || w == 0 {
        return;
    }
    dst.par_chunks_mut(h * TILE)
        .enumerate()
        .for_each(|(t, out)| {
            let c0 = t * TILE;
            let nc = out.len() / h;
            for r0 in (0..h).step_by(TILE) {
                let r1 = (r0 + TILE).min(h);
                for r in r0..r1 {
                    let src_row = &src[r * w + c0..r * w + c0 + nc];
                    for (c, &v) in src_row.iter().enumerate() {
                        out[c * h + r] = v;
                    }
                }
            }
        });
}

/// Apply a 1-D FFT to every length-`len` row of `data`, rows in parallel, one scratch
/// buffer per rayon task.
fn rows_fft(fft: &Arc<dyn Fft<f32>>, data: &mut [Complex32], len: usize) {
    let scratch_len = fft.get_inplace_scratch_len();
    data.par_chunks_mut(len * ROWS_PER_TASK).for_each_init(
        || vec![Complex32::default(); scratch_len],
        |scratch, chunk| fft.process_with_scratch(chunk, scratch),
    );
}

/// Heights (row-major `h × w`, zero mean over the frame) from gradients `p = dz/dx`,
/// `q = dz/dy` that are zero off the mask.
pub(super) fn frankot_chellappa(p: &[f32], q: &[f32], h: usize, w: usize) -> Vec<f32> {
    let n = h * w;
    if n == 0 {
        return Vec::new();
    }
    let mut planner = FftPlanner::<f32>::new();
    let (fw, fh) = (planner.plan_fft_forward(w), planner.plan_fft_forward(h));
    let (iw, ih) = (planner.plan_fft_inverse(w), planner.plan_fft_inverse(h));

    // Both real fields in one complex transform: F = FFT(p + i q).
    let mut a: Vec<Complex32> = p
        .par_iter()
        .zip(q.par_iter())
        .map(|(&p, &q)| Complex32::new(finite(p), finite(q)))
        .collect();
    rows_fft(&fw, &mut a, w);
    let mut t = vec![Complex32::default(); n];
    transpose(&a, h, w, &mut t); // t[l][k] = F(k, l) after the next pass
    rows_fft(&fh, &mut t, h);

    let trig = |len: usize| -> (Vec<f32>, Vec<f32>) {
        (0..len)
            .map(|k| {
                let om = 2.0 * PI * k as f64 / len as f64;
                (om.sin() as f32, (4.0 * (om / 2.0).sin().powi(2)) as f32)
            })
            .unzip()
    };
    let (sx, lx) = trig(w);
    let (sy, ly) = trig(h);

    // Split F into P̂, Q̂ via Hermitian symmetry and apply the filter; a[l][k] = Ẑ(k, l).
    a.par_chunks_mut(h).enumerate().for_each(|(l, out)| {
        let lm = (w - l) % w;
        let row = &t[l * h..(l + 1) * h];
        let row_m = &t[lm * h..(lm + 1) * h];
        for (k, o) in out.iter_mut().enumerate() {
            let km = (h - k) % h;
            let f = row[k];
            let fm = row_m[km].conj();
            let den = lx[l] + ly[k];
            if den <= 0.0 {
                *o = Complex32::default();
                continue;
            }
            let ph = (f + fm) * 0.5;
            let d = f - fm; // Q̂ = d / 2i = (d.im − i d.re) / 2
            let qh = Complex32::new(d.im * 0.5, -d.re * 0.5);
            let num = ph * sx[l] + qh * sy[k];
            // Ẑ = −i · num / den
            *o = Complex32::new(num.im / den, -num.re / den);
        }
    });

    rows_fft(&ih, &mut a, h);
    transpose(&a, w, h, &mut t);
    rows_fft(&iw, &mut t, w);
    let scale = 1.0 / n as f32;
    t.par_iter().map(|c| c.re * scale).collect()
}

fn finite(v: f32) -> f32 {
    if v.is_finite() { v } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose_roundtrip_odd_sizes() {
        for (h, w) in [(1, 1), (1, 7), (7, 1), (33, 65), (70, 3)] {
            let src: Vec<u32> = (0..(h * w) as u32).collect();
            let mut t = vec![0; h * w];
            transpose(&src, h, w, &mut t);
            for r in 0..h {
                for c in 0..w {
                    assert_eq!(t[c * h + r], src[r * w + c]);
                }
            }
            let mut back = vec![0; h * w];
            transpose(&t, w, h, &mut back);
            assert_eq!(back, src);
        }
    }

    /// A discretely integrable periodic field is reproduced exactly (up to f32 rounding):
    /// build p, q so that the trapezoid edge equations hold exactly for a given z.
    #[test]
    fn exact_on_discrete_periodic_field() {
        let (h, w) = (24, 40);
        let z: Vec<f64> = (0..h * w)
            .map(|i| {
                let (r, c) = ((i / w) as f64, (i % w) as f64);
                3.0 * (2.0 * PI * c / w as f64).sin() + 2.0 * (4.0 * PI * r / h as f64).cos()
            })
            .collect();
        // z = A sin(ωc) satisfies z[c+1] − z[c] = (p[c] + p[c+1])/2 exactly for
        // p = 2A tan(ω/2) cos(ωc) (and likewise for the cosine in r).
        let ox = 2.0 * PI / w as f64;
        let oy = 4.0 * PI / h as f64;
        let mut p = vec![0f32; h * w];
        let mut q = vec![0f32; h * w];
        for i in 0..h * w {
            let (r, c) = ((i / w) as f64, (i % w) as f64);
            p[i] = (3.0 * 2.0 * (ox / 2.0).tan() * (ox * c).cos()) as f32;
            q[i] = (-2.0 * 2.0 * (oy / 2.0).tan() * (oy * r).sin()) as f32;
        }
        let got = frankot_chellappa(&p, &q, h, w);
        let mean = z.iter().sum::<f64>() / z.len() as f64;
        for i in 0..h * w {
            assert!(
                (f64::from(got[i]) - (z[i] - mean)).abs() < 1e-4,
                "{i}: {} vs {}",
                got[i],
                z[i] - mean
            );
        }
    }
}
