//! How far the surface is. Integration gives depth up to one scale; unlike distant
//! lights, near lights fix it: moving the surface along the rays changes every pixel's
//! light directions and falloff differently, and only the true distance lets one `ρ n`
//! explain all of a pixel's observations. The scale is the one whose fits leave the
//! smallest residual over a sample of the mask (golden-section search on its
//! logarithm). Pieces that depth steps separate ([`super::pieces`]) get their own scale:
//! the integration cannot say how far apart they are, the lights can.

use ndarray::{Array2, Zip};
use rayon::prelude::*;

use super::pieces::MIN_PIECE;
use super::point::{Scene, Scratch};

/// Pixels the scale search samples (about).
const SAMPLES: usize = 8_000;
/// The search brackets the current scale within this factor either way.
const BRACKET: f64 = 2.0;
/// Shrinkings of the bracket: to 10⁻⁴ of the scale.
const STEPS: usize = 20;

/// The grid stride that samples about [`SAMPLES`] of `count` pixels.
pub fn stride_for(count: usize) -> usize {
    ((count as f64 / SAMPLES as f64).sqrt().ceil() as usize).max(1)
}

/// Whether pixel `(r, c)` is on the sampling grid of `stride`.
pub fn sampled(r: usize, c: usize, stride: usize) -> bool {
    r % stride == stride / 2 && c % stride == stride / 2
}

/// The observations of some pixels, kept for the search.
pub struct Observed {
    lights: usize,
    at: Vec<(usize, usize)>,
    /// `lights` values in [0, 1] per pixel.
    obs: Vec<f32>,
}

impl Observed {
    pub fn new(lights: usize) -> Self {
        Self {
            lights,
            at: Vec::new(),
            obs: Vec::new(),
        }
    }

    /// The pixels kept, in order.
    pub fn pixels(&self) -> &[(usize, usize)] {
        &self.at
    }

    pub fn push(&mut self, at: (usize, usize), obs: impl IntoIterator<Item = f32>) {
        self.at.push(at);
        self.obs.extend(obs);
        debug_assert_eq!(self.obs.len(), self.at.len() * self.lights);
    }

    /// `relative` (depth up to scale, NaN where unknown) placed: the whole by the best
    /// scale around `current`, then each piece of `label` at least [`MIN_PIECE`] of the
    /// pieces' pixels (`sizes`) by its own around that. Returns the depth and the whole's
    /// scale.
    pub fn place(
        &self,
        scene: &Scene<'_>,
        relative: &Array2<f32>,
        (label, sizes): (&Array2<usize>, &[usize]),
        current: f64,
    ) -> (Array2<f32>, f64) {
        let whole = self.best_scale(scene, relative, current, |_| true);
        let mut depth = relative.mapv(|d| (f64::from(d) * whole) as f32);
        let smallest = (MIN_PIECE * sizes.iter().sum::<usize>() as f64) as usize;
        for (id, _) in sizes.iter().enumerate().filter(|(_, n)| **n >= smallest) {
            if sizes.len() == 1 {
                break;
            }
            let own = self.best_scale(scene, relative, whole, |at| label[at] == id);
            Zip::from(&mut depth)
                .and(relative)
                .and(label)
                .for_each(|d, &rel, &l| {
                    if l == id {
                        *d = (f64::from(rel) * own) as f32;
                    }
                });
        }
        (depth, whole)
    }

    /// The scale of `relative` whose fits leave the smallest squared residual over the
    /// pixels kept that `select` takes, searched around `current`; `current` when none.
    fn best_scale(
        &self,
        scene: &Scene<'_>,
        relative: &Array2<f32>,
        current: f64,
        select: impl Fn((usize, usize)) -> bool,
    ) -> f64 {
        let n = self.lights;
        let chosen: Vec<(usize, f64)> = (self.at.iter().enumerate())
            .filter(|(_, at)| select(**at) && relative[**at].is_finite())
            .map(|(i, at)| (i, f64::from(relative[*at])))
            .collect();
        if chosen.is_empty() {
            return current;
        }
        let cost = |t: f64| -> f64 {
            let s = t.exp();
            chosen
                .par_chunks(256)
                .map(|chunk| {
                    let mut scratch = Scratch::new(n);
                    chunk
                        .iter()
                        .map(|&(i, d)| {
                            scratch.obs.copy_from_slice(&self.obs[i * n..(i + 1) * n]);
                            let rms = scene.fit(self.at[i], d * s, &mut scratch).rms;
                            f64::from(rms) * f64::from(rms)
                        })
                        .sum::<f64>()
                })
                .sum()
        };
        let (low, high) = (current.ln() - BRACKET.ln(), current.ln() + BRACKET.ln());
        golden_min(cost, low, high, STEPS).exp()
    }
}

/// The minimum of `f` on `[a, b]` by golden-section search (`steps` shrinkings).
fn golden_min(f: impl Fn(f64) -> f64, mut a: f64, mut b: f64, steps: usize) -> f64 {
    let ratio = (5f64.sqrt() - 1.0) / 2.0;
    let mut x1 = b - ratio * (b - a);
    let mut x2 = a + ratio * (b - a);
    let (mut f1, mut f2) = (f(x1), f(x2));
    for _ in 0..steps {
        if f1 <= f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - ratio * (b - a);
            f1 = f(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + ratio * (b - a);
            f2 = f(x2);
        }
    }
    (a + b) / 2.0
}
