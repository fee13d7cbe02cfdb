//! What the ball shows in every image: the environment each light's highlight is judged
//! against.
//!
//! A light is what its own image has and the others lack. Room lights, windows, the
//! camera, fixtures and the mirrored object stay put from image to image, so the
//! per-pixel median of the set keeps them and drops each highlight (every highlight is in
//! one image only). An ambient image (the ball with the rig's lights off) adds what the
//! median may miss; the environment is the brighter of the two at each pixel.
//!
//! Residuals (image less environment) then hold the lights, and also whatever the lights
//! themselves make brighter (an object beside the ball, a reflection that wanders a
//! little). The recurrence map counts, per pixel, in how many images the residual is
//! significant: a light's blob is where few other images have one.

use ndarray::{Array2, Zip};
use rayon::prelude::*;

use super::circle::Circle;

/// The sphere's pixels: its bounding box in the image, and which pixels of it are on the
/// ball (half a pixel inside the outline, so the backdrop's edge never counts).
#[derive(Debug, Clone, Copy)]
pub struct Disc {
    pub r0: usize,
    pub r1: usize,
    pub c0: usize,
    pub c1: usize,
    circle: Circle,
}

impl Disc {
    pub fn new(circle: &Circle, (h, w): (usize, usize)) -> Self {
        Self {
            r0: (circle.cy - circle.r).floor().max(0.0) as usize,
            r1: ((circle.cy + circle.r).ceil().max(0.0) as usize).min(h - 1),
            c0: (circle.cx - circle.r).floor().max(0.0) as usize,
            c1: ((circle.cx + circle.r).ceil().max(0.0) as usize).min(w - 1),
            circle: *circle,
        }
    }

    pub fn contains(&self, r: usize, c: usize) -> bool {
        let (dx, dy) = (c as f64 - self.circle.cx, r as f64 - self.circle.cy);
        let inner = self.circle.r - 0.5;
        inner >= 0.0 && dx * dx + dy * dy <= inner * inner
    }

    /// Every pixel on the ball, row by row.
    pub fn pixels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.rows().flat_map(|(r, cols)| cols.map(move |c| (r, c)))
    }

    /// Each row's span of pixels on the ball (rows without any are left out): solved for,
    /// then its ends checked against [`Self::contains`]. Every stage walks the disc several
    /// times per image, and a 24-megapixel ball's box is most of 10 million pixels.
    pub fn rows(&self) -> impl Iterator<Item = (usize, std::ops::RangeInclusive<usize>)> + '_ {
        let inner = (self.circle.r - 0.5).max(0.0);
        (self.r0..=self.r1).filter_map(move |r| {
            let dy = r as f64 - self.circle.cy;
            let half = (inner * inner - dy * dy).max(0.0).sqrt();
            let mut a = ((self.circle.cx - half).floor() - 1.0).max(self.c0 as f64) as usize;
            let mut b = ((self.circle.cx + half).ceil() + 1.0).min(self.c1 as f64) as usize;
            while a <= b && !self.contains(r, a) {
                a += 1;
            }
            while b > a && !self.contains(r, b) {
                b -= 1;
            }
            (a <= b && self.contains(r, b)).then_some((r, a..=b))
        })
    }
}

/// The environment: per pixel, the median of the set, raised to the ambient image where
/// that is brighter.
pub fn estimate(planes: &[&Array2<u16>], ambient: Option<&Array2<u16>>) -> Array2<u16> {
    let (h, w) = planes[0].dim();
    let mut env = Array2::zeros((h, w));
    env.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(r, mut row)| {
            let mut v = Vec::with_capacity(planes.len());
            let rows: Vec<ndarray::ArrayView1<u16>> = planes.iter().map(|p| p.row(r)).collect();
            for (c, o) in row.iter_mut().enumerate() {
                v.clear();
                v.extend(rows.iter().map(|p| p[c]));
                let k = v.len() / 2;
                *o = *v.select_nth_unstable(k).1;
            }
        });
    if let Some(a) = ambient {
        Zip::from(&mut env)
            .and(a)
            .for_each(|e, &a| *e = (*e).max(a));
    }
    env
}

#[cfg(test)]
mod tests {
    use super::{Circle, Disc};

    #[test]
    fn the_row_spans_hold_exactly_the_pixels_the_disc_contains() {
        for (cx, cy, r, w, h) in [
            (20.3, 17.8, 11.6, 40, 36),
            (3.0, 4.5, 9.0, 20, 20),
            (30.7, 2.2, 5.1, 32, 16),
            (5.0, 5.0, 0.4, 10, 10),
        ] {
            let disc = Disc::new(&Circle { cx, cy, r }, (h, w));
            let spans: Vec<(usize, usize)> = disc.pixels().collect();
            let mut brute = Vec::new();
            for row in disc.r0..=disc.r1 {
                for c in disc.c0..=disc.c1 {
                    if disc.contains(row, c) {
                        brute.push((row, c));
                    }
                }
            }
            assert_eq!(spans, brute, "circle ({cx}, {cy}, {r}) in {w}×{h}");
        }
    }
}
