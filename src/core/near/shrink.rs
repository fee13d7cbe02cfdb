//! The set shrunk for the alternation: every image box-averaged over `factor × factor`
//! blocks in one pass over its bands, so that the images are never held whole.
//!
//! A block's average is what a camera with `factor` times larger pixels would see, and
//! its camera is this one with the focal lengths divided by `factor` and the principal
//! point moved to the blocks' frame: block `C` covers pixels `fC .. fC + f − 1`, whose
//! centre `fC + (f − 1)/2` is where the block's ray passes.

use ndarray::Array2;
use rayon::prelude::*;

use crate::core::bands::{Stack, each_band};
use crate::core::camera::Pinhole;
use crate::core::error::InputError;
use crate::core::progress::Halt;

/// The shrunk set.
pub struct Shrunk {
    /// Per image, the block averages (0..=65535).
    pub planes: Vec<Array2<u16>>,
    pub camera: Pinhole,
    /// The brightest sample of the whole set (not of the averages).
    pub peak: u16,
}

/// The smallest factor that brings a `width × height` image to at most `pixels`.
pub fn factor_for(width: usize, height: usize, pixels: usize) -> usize {
    let area = (width * height) as f64 / pixels.max(1) as f64;
    (area.sqrt().ceil() as usize).max(1)
}

/// `camera` for blocks of `factor × factor` pixels.
pub fn shrink_camera(camera: &Pinhole, factor: usize) -> Pinhole {
    let f = factor as f64;
    let centre = (f - 1.0) / 2.0;
    Pinhole {
        fx: camera.fx / f,
        fy: camera.fy / f,
        cx: (camera.cx - centre) / f,
        cy: (camera.cy - centre) / f,
    }
}

/// Read `stack` from its first row and average its images over blocks of `factor ×
/// factor` (the last row and column of blocks over what the image has). Once `halt`
/// says stop, the rows not yet read are left dark.
pub fn shrink(
    stack: &mut dyn Stack,
    factor: usize,
    camera: &Pinhole,
    halt: Halt,
) -> Result<Shrunk, InputError> {
    let (w, h) = (stack.info().width, stack.info().height);
    let (cw, ch) = (w.div_ceil(factor), h.div_ceil(factor));
    let images = stack.info().lights.len();
    let mut sums = vec![vec![0u32; cw * ch]; images];
    let mut peak = 0u16;
    each_band(stack, halt, |rows, band| {
        let top = (sums.par_iter_mut().zip(&band.planes))
            .map(|(sum, plane)| {
                let mut top = 0u16;
                for (i, row) in plane.chunks_exact(w).enumerate() {
                    let out = &mut sum[(rows.start + i) / factor * cw..][..cw];
                    for (c, &v) in row.iter().enumerate() {
                        out[c / factor] += u32::from(v);
                        top = top.max(v);
                    }
                }
                top
            })
            .max()
            .unwrap_or(0);
        peak = peak.max(top);
    })?;
    let size = |i: usize, n: usize| (factor.min(n - i * factor)) as u32;
    let planes = (sums.into_par_iter())
        .map(|sum| {
            Array2::from_shape_fn((ch, cw), |(r, c)| {
                let n = size(r, h) * size(c, w);
                ((sum[r * cw + c] + n / 2) / n) as u16
            })
        })
        .collect();
    Ok(Shrunk {
        planes,
        camera: shrink_camera(camera, factor),
        peak,
    })
}

/// `mask` over blocks: a block is on when all its pixels are (a block that mixes the
/// object with what lies around it averages two surfaces).
pub fn shrink_mask(mask: &Array2<bool>, factor: usize) -> Array2<bool> {
    let (h, w) = mask.dim();
    Array2::from_shape_fn((h.div_ceil(factor), w.div_ceil(factor)), |(r, c)| {
        let rows = r * factor..((r + 1) * factor).min(h);
        let cols = c * factor..((c + 1) * factor).min(w);
        rows.into_iter().all(|y| cols.clone().all(|x| mask[[y, x]]))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A block's ray is its pixels' mean ray.
    #[test]
    fn a_block_sees_along_its_pixels_mean_ray() {
        let camera = Pinhole {
            fx: 800.0,
            fy: 810.0,
            cx: 319.5,
            cy: 241.0,
        };
        let small = shrink_camera(&camera, 4);
        let (r, c) = (7usize, 11usize);
        let mean = |k: usize| {
            let rays: Vec<[f64; 3]> = (0..4)
                .flat_map(|y| (0..4).map(move |x| (4 * c + x, 4 * r + y)))
                .map(|(u, v)| camera.ray(u as f64, v as f64))
                .collect();
            rays.iter().map(|ray| ray[k]).sum::<f64>() / 16.0
        };
        let ray = small.ray(c as f64, r as f64);
        for k in 0..3 {
            assert!((ray[k] - mean(k)).abs() < 1e-12, "{ray:?}");
        }
    }

    #[test]
    fn factors_bring_images_under_the_budget() {
        assert_eq!(factor_for(160, 160, 512 * 512), 1);
        assert_eq!(factor_for(2048, 2048, 512 * 512), 4);
        assert_eq!(factor_for(2049, 2048, 512 * 512), 5);
        let m = Array2::from_shape_fn((5, 5), |(r, c)| r < 4 && c < 3);
        let s = shrink_mask(&m, 2);
        assert_eq!(s.dim(), (3, 3));
        assert!(s[[0, 0]] && s[[1, 0]] && !s[[0, 1]] && !s[[2, 0]]);
    }
}
