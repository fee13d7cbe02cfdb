//! The outline refined on the images themselves (the end of the sphere's notes, step 4):
//! along each of the refinement's rays, the strongest intensity step that any one image
//! shows.
//!
//! Why not the environment alone: how the rim of a mirror ball contrasts with what lies
//! beyond it changes from image to image (each light brightens the backdrop and the room
//! the ball mirrors near grazing differently), so the per-pixel median blends rims of
//! different strengths into a ramp many pixels wide, whose steepest point need not be
//! where any image's rim is. The image in which a ray's rim steps the most shows it best.
//! On one of the real chrome balls in `../shared/real/chrome` the median's rim is a ramp
//! 10–15 px wide; traced on the images instead, the outline's centre lies 1.75 px from the
//! authors' hand-fitted one rather than 2.2 px, and the lights 0.52° from theirs rather
//! than 0.63° (`tests/core/real_chrome.rs`).

use std::borrow::Cow;

use ndarray::Array2;
use rayon::prelude::*;

use super::filter::parabola_peak;
use super::fit::{OutlineFit, RAYS, ray_direction, robust_fit};
use crate::core::calibrate::circle::Circle;

/// How far either side of the start circle the profiles reach, pixels: the widest window
/// of [`WINDOWS`] plus how far the circle may move from the start.
const SPAN: f64 = 8.0;
/// Spacing of a profile's samples along its ray, pixels.
const STEP: f64 = 0.25;
/// The rounds' windows either side of the current circle, pixels: the environment's
/// refinement's last rounds.
const WINDOWS: [f64; 4] = [4.0, 3.0, 2.0, 2.0];
/// Standard deviation of the Gaussian each sample is taken with, pixels: the environment's
/// smoothing.
const SIGMA: f64 = 1.0;
/// Most pixels a sample's Gaussian spans along a row or column (those within 3σ).
const TAPS: usize = 2 * (3.0 * SIGMA) as usize + 1;

/// Per ray and position along it, the strongest step over the images: the derivative's
/// magnitude there and at the positions either side, in the same image.
struct Strongest {
    /// `(before, peak, after)` per ray × position, row-major by ray.
    steps: Vec<(f64, f64, f64)>,
    /// Rays whose profiles lie inside every image.
    inside: Vec<bool>,
    positions: usize,
}

/// `start` (the environment's outline, in the images' coordinates) refined on the `count`
/// images `image(k)`: per ray of [`RAYS`] from its centre, the strongest step over the
/// images within a window of the current circle, at least `threshold` (the environment's
/// edge threshold, in the images' 0..=65535 units), to sub-pixel by a parabola; then the
/// Tukey-weighted circle fit, over narrowing windows. None when too few rays find a step.
pub(in crate::core::calibrate) fn refine_on_images<'a, E>(
    count: usize,
    image: impl Fn(usize) -> Result<Cow<'a, Array2<u16>>, E>,
    start: &OutlineFit,
    threshold: f32,
) -> Result<Option<OutlineFit>, E> {
    let c0 = start.circle;
    let positions = (2.0 * SPAN / STEP).round() as usize + 1;
    let mut best = Strongest {
        steps: vec![(0.0, 0.0, 0.0); RAYS * positions],
        inside: vec![true; RAYS],
        positions,
    };
    for k in 0..count {
        best.add(&*image(k)?, &c0);
    }
    let mut fit = *start;
    for window in WINDOWS {
        let points = best.points(&c0, &fit.circle, window, f64::from(threshold));
        match robust_fit(&points, fit.circle) {
            Some(f) => fit = f,
            None => return Ok(None),
        }
    }
    Ok(Some(fit))
}

impl Strongest {
    /// Take image `img`'s steps along the rays from `c0`'s centre where they are the
    /// strongest yet (the rays in parallel).
    fn add(&mut self, img: &Array2<u16>, c0: &Circle) {
        let n = self.positions;
        (self.steps.par_chunks_mut(n).zip(self.inside.par_iter_mut()))
            .enumerate()
            .for_each(|(ray, (row, inside))| {
                if !*inside {
                    return;
                }
                let (ux, uy) = ray_direction(ray);
                let mut samples = vec![0.0; n];
                for (i, s) in samples.iter_mut().enumerate() {
                    let rho = c0.r - SPAN + i as f64 * STEP;
                    match gaussian_at(img, c0.cx + rho * ux, c0.cy + rho * uy) {
                        Some(v) => *s = v,
                        None => {
                            *inside = false;
                            return;
                        }
                    }
                }
                let d = |i: usize| ((samples[i + 1] - samples[i - 1]) / (2.0 * STEP)).abs();
                for i in 2..n - 2 {
                    let peak = d(i);
                    if peak > row[i].1 {
                        row[i] = (d(i - 1), peak, d(i + 1));
                    }
                }
            });
    }

    /// Per ray, the strongest step within `window` px of `circle` (at least `threshold`,
    /// not at the window's ends), to sub-pixel: the outline's points.
    fn points(&self, c0: &Circle, circle: &Circle, window: f64, threshold: f64) -> Vec<(f64, f64)> {
        let n = self.positions;
        let mut points = Vec::new();
        for ray in (0..RAYS).filter(|&r| self.inside[r]) {
            let (ux, uy) = ray_direction(ray);
            // Distance from c0's centre along the ray to `circle`.
            let (ox, oy) = (c0.cx - circle.cx, c0.cy - circle.cy);
            let b = ux * ox + uy * oy;
            let disc = b * b - (ox * ox + oy * oy - circle.r * circle.r);
            if disc < 0.0 {
                continue;
            }
            let t = -b + disc.sqrt();
            let lo = (((t - window) - (c0.r - SPAN)) / STEP).ceil().max(2.0) as usize;
            let hi = ((((t + window) - (c0.r - SPAN)) / STEP).floor() as usize).min(n - 3);
            if hi <= lo + 1 {
                continue;
            }
            let row = &self.steps[ray * n..(ray + 1) * n];
            let Some(i) = (lo..=hi).max_by(|&a, &b| row[a].1.total_cmp(&row[b].1)) else {
                continue;
            };
            let (a0, a1, a2) = row[i];
            if a1 < threshold || i == lo || i == hi {
                continue;
            }
            let shift = parabola_peak(a0, a1, a2);
            let rho = c0.r - SPAN + (i as f64 + shift) * STEP;
            points.push((c0.cx + rho * ux, c0.cy + rho * uy));
        }
        points
    }
}

/// `img` at `(x, y)` seen through a Gaussian of [`SIGMA`] (the weighted mean of the pixels
/// within 3σ); None where that reaches past the image.
fn gaussian_at(img: &Array2<u16>, x: f64, y: f64) -> Option<f64> {
    let (h, w) = img.dim();
    let reach = 3.0 * SIGMA;
    let (c0, c1) = ((x - reach).ceil(), (x + reach).floor());
    let (r0, r1) = ((y - reach).ceil(), (y + reach).floor());
    if c0 < 0.0 || r0 < 0.0 || c1 >= w as f64 || r1 >= h as f64 {
        return None;
    }
    // The Gaussian is separable: 7 + 7 exponentials rather than 49.
    let g = |d: f64| (-(d * d) / (2.0 * SIGMA * SIGMA)).exp();
    // At most TAPS columns: their weights on the stack, not a fresh vector per sample
    // (tens of thousands per image).
    let (c0, r0) = (c0 as usize, r0 as usize);
    let cols = c1 as usize - c0 + 1;
    let mut gx = [0.0; TAPS];
    for (k, wx) in gx[..cols].iter_mut().enumerate() {
        *wx = g((c0 + k) as f64 - x);
    }
    let (mut sum, mut weight) = (0.0, 0.0);
    for r in r0..=r1 as usize {
        let gy = g(r as f64 - y);
        let row = img.row(r);
        for (k, &wx) in gx[..cols].iter().enumerate() {
            sum += gy * wx * f64::from(row[c0 + k]);
            weight += gy * wx;
        }
    }
    Some(sum / weight)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A disc over a backdrop, 4 × 4 supersampled: inside `inside(angle)`, outside `back`.
    fn disc(
        c: &Circle,
        (w, h): (usize, usize),
        inside: impl Fn(f64) -> f64,
        back: f64,
    ) -> Array2<u16> {
        Array2::from_shape_fn((h, w), |(y, x)| {
            let mut v = 0.0;
            for j in 0..4 {
                for i in 0..4 {
                    let sx = x as f64 - 0.375 + 0.25 * i as f64;
                    let sy = y as f64 - 0.375 + 0.25 * j as f64;
                    let (dx, dy) = (sx - c.cx, sy - c.cy);
                    v += if dx.hypot(dy) <= c.r {
                        inside(dy.atan2(dx))
                    } else {
                        back
                    } / 16.0;
                }
            }
            v.round() as u16
        })
    }

    /// Each image's rim stands out along one third of the circle only (elsewhere the ball
    /// matches its backdrop, as a mirror ball's rim does where it reflects what lies
    /// beside it): the circle comes back from a start 1.5 px off.
    #[test]
    fn rims_that_stand_out_in_different_images_give_the_circle() {
        let truth = Circle {
            cx: 60.3,
            cy: 57.6,
            r: 40.4,
        };
        let images: Vec<Array2<u16>> = (0..3)
            .map(|k| {
                let lit = move |a: f64| {
                    let third = ((a + std::f64::consts::PI) / std::f64::consts::TAU * 3.0) as usize;
                    if third.min(2) == k {
                        50_000.0
                    } else {
                        20_000.0
                    }
                };
                disc(&truth, (120, 116), lit, 20_000.0)
            })
            .collect();
        let start = OutlineFit {
            circle: Circle {
                cx: truth.cx + 1.0,
                cy: truth.cy - 0.8,
                r: truth.r + 0.7,
            },
            coverage: 0.0,
            rms: 0.0,
        };
        let image = |k: usize| Ok::<_, ()>(Cow::Borrowed(&images[k]));
        let fit = refine_on_images(3, image, &start, 1000.0).unwrap().unwrap();
        let c = fit.circle;
        let off = (c.cx - truth.cx).hypot(c.cy - truth.cy);
        assert!(off < 0.1 && (c.r - truth.r).abs() < 0.1, "{fit:?}");
        assert!(fit.coverage > 0.9, "{fit:?}");
    }

    /// Images with no step anywhere leave nothing to refine.
    #[test]
    fn flat_images_refine_nothing() {
        let flat = Array2::from_elem((80, 80), 1000u16);
        let start = OutlineFit {
            circle: Circle {
                cx: 40.0,
                cy: 40.0,
                r: 20.0,
            },
            coverage: 1.0,
            rms: 0.0,
        };
        let image = |_: usize| Ok::<_, ()>(Cow::Borrowed(&flat));
        assert_eq!(refine_on_images(2, image, &start, 10.0), Ok(None));
    }
}
