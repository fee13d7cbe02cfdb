//! One pass over the images at full resolution, band by band as the stack reads them:
//! every pixel fitted with its light vectors from a given surface ([`super::point`]), and
//! the observations of a grid of pixels kept for placing the next surface
//! ([`super::scale`]).

use ndarray::{Array2, Array3, s};
use rayon::prelude::*;

use super::point::{Scene, Scratch};
use super::scale::{Observed, sampled};
use crate::core::bands::{Stack, each_band};
use crate::core::error::InputError;
use crate::core::progress::Halt;

/// Which pixels a pass fits.
#[derive(Debug, Clone, Copy)]
pub enum Pixels {
    /// Those of the mask it is given.
    Masked,
    /// Those [`lit`] above this level: the pass sets the mask.
    Lit { dark: u16 },
}

/// Whether a pixel with these observations is solved: three of them above `dark`.
pub fn lit(values: impl Iterator<Item = u16>, dark: u16) -> bool {
    values.filter(|&v| v > dark).count() >= 3
}

/// What the passes fitted: `g = ρ n` and the RMS of each pixel's kept observations,
/// zero off the mask.
pub struct Fits {
    pub g: Array3<f32>,
    pub residual: Array2<f32>,
}

impl Fits {
    pub fn zeros(h: usize, w: usize) -> Self {
        Self {
            g: Array3::zeros((h, w, 3)),
            residual: Array2::zeros((h, w)),
        }
    }
}

/// What one pass fits on.
pub struct Pass<'a> {
    pub scene: &'a Scene<'a>,
    /// Each pixel's surface depth.
    pub depth: &'a Array2<f32>,
    /// Only the pixels this marks, when given: the others keep their fits.
    pub only: Option<&'a Array2<bool>>,
}

/// Fit the pixels of `stack` that `pixels` (and the pass's `only`) take into `fits`, and
/// keep the observations of the mask pixels on the grid of a stride into `sampling`.
/// Once `halt` says stop, the bands not yet read are left as they were.
pub fn fit_bands(
    stack: &mut dyn Stack,
    pass: &Pass<'_>,
    (mask, pixels): (&mut Array2<bool>, Pixels),
    fits: &mut Fits,
    mut sampling: Option<(&mut Observed, usize)>,
    halt: Halt,
) -> Result<(), InputError> {
    let w = mask.dim().1;
    let (scene, depth) = (pass.scene, pass.depth);
    let n = scene.lights.len();
    each_band(stack, halt, |rows, band| {
        let (r0, r1) = (rows.start, rows.end);
        let planes = &band.planes;
        let value = |at: usize| planes.iter().map(move |p| f32::from(p[at]) / 65535.0);
        let mut g = fits.g.slice_mut(s![r0..r1, .., ..]);
        let mut residual = fits.residual.slice_mut(s![r0..r1, ..]);
        (g.outer_iter_mut().into_par_iter())
            .zip(residual.outer_iter_mut().into_par_iter())
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
                        on[c] = lit(planes.iter().map(|p| p[at]), dark);
                    }
                    let chosen = pass.only.is_none_or(|o| o[[r, c]]);
                    if !on[c] || !chosen || !depth[[r, c]].is_finite() {
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
        if let Some((observed, stride)) = sampling.as_mut() {
            for r in r0..r1 {
                for c in (0..w).filter(|&c| sampled(r, c, *stride) && mask[[r, c]]) {
                    observed.push((r, c), value((r - r0) * w + c));
                }
            }
        }
    })
}
