//! One pass over the images at full resolution, band by band as the stack reads them:
//! every pixel fitted with its light vectors from a given surface ([`super::point`]), and
//! the observations of a grid of pixels kept for placing the next surface
//! ([`super::scale`]).

use ndarray::{Array2, Array3, s};
use rayon::prelude::*;

use super::point::{Scene, Scratch};
use super::scale::{Observed, sampled};
use crate::core::InputError;
use crate::core::bands::Stack;
use crate::core::progress::Halt;

/// Which pixels a pass fits.
#[derive(Debug, Clone, Copy)]
pub enum Pixels {
    /// Those of the mask it is given.
    Masked,
    /// Those with three observations above this level: the pass sets the mask.
    Lit { dark: u16 },
}

/// What a pass fitted: `g = ρ n` and the RMS of each pixel's kept observations, zero
/// off the mask; and the observations of the mask pixels on the sampling grid.
pub struct Fits {
    pub g: Array3<f32>,
    pub residual: Array2<f32>,
    pub observed: Observed,
}

/// Fit every pixel of `stack` that `pixels` takes, its surface point at `depth`, keeping
/// the observations of those on the grid of `stride`. Once `halt` says stop, the bands
/// not yet read are left at zero.
pub fn fit_bands(
    stack: &mut dyn Stack,
    scene: &Scene<'_>,
    depth: &Array2<f32>,
    (mask, pixels): (&mut Array2<bool>, Pixels),
    stride: usize,
    halt: Halt,
) -> Result<Fits, InputError> {
    let (h, w) = mask.dim();
    let mut g = Array3::<f32>::zeros((h, w, 3));
    let mut residual = Array2::<f32>::zeros((h, w));
    let n = scene.lights.len();
    let mut observed = Observed::new(n);
    let step = stack.band_rows().max(1);
    stack.rewind();
    for r0 in (0..h).step_by(step) {
        if halt() {
            break;
        }
        let r1 = (r0 + step).min(h);
        let band = stack.band(r0..r1)?;
        let planes = &band.planes;
        let value = |at: usize| planes.iter().map(move |p| f32::from(p[at]) / 65535.0);
        (g.slice_mut(s![r0..r1, .., ..])
            .outer_iter_mut()
            .into_par_iter())
        .zip(
            residual
                .slice_mut(s![r0..r1, ..])
                .outer_iter_mut()
                .into_par_iter(),
        )
        .zip(
            mask.slice_mut(s![r0..r1, ..])
                .outer_iter_mut()
                .into_par_iter(),
        )
        .enumerate()
        .for_each(|(i, ((mut g, mut rms), mut on))| {
            let mut scratch = Scratch::new(n);
            let r = r0 + i;
            for c in 0..w {
                let at = i * w + c;
                if let Pixels::Lit { dark } = pixels {
                    on[c] = planes.iter().filter(|p| p[at] > dark).count() >= 3;
                }
                if !on[c] || !depth[[r, c]].is_finite() {
                    continue;
                }
                for (o, v) in scratch.obs.iter_mut().zip(value(at)) {
                    *o = v;
                }
                let f = scene.fit((r, c), f64::from(depth[[r, c]]), &mut scratch);
                for k in 0..3 {
                    g[[c, k]] = f.g[k];
                }
                rms[c] = f.rms;
            }
        });
        for r in r0..r1 {
            for c in (0..w).filter(|&c| sampled(r, c, stride) && mask[[r, c]]) {
                observed.push((r, c), value((r - r0) * w + c));
            }
        }
    }
    Ok(Fits {
        g,
        residual,
        observed,
    })
}
