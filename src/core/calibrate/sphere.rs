//! Finding the sphere: its outline (centre and radius, sub-pixel) from the images
//! themselves, or from a mask.
//!
//! The per-pixel median over the set keeps what every image shares (the ball's outline,
//! the backdrop) and drops the highlights, each of which is in one image only. On it,
//! lightly smoothed:
//!
//! 1. Edge points: gradient maxima along the gradient (non-maximum suppression) above a
//!    threshold relative to the image's own gradients.
//! 2. Candidates: each edge point votes along its gradient line, both ways, for the centres
//!    of circles it could lie on (a Hough transform over centres); the strongest
//!    accumulator peaks are candidate centres. A large ball needs a second look: a
//!    textured backdrop bends the outline's gradients by several degrees, which at a
//!    radius of hundreds of pixels scatters its votes over many pixels while the
//!    backdrop's pile up everywhere. So the votes cast from 64 px away or more are also
//!    counted per octave of distance in cells a sixteenth of the octave's start wide (a
//!    constant angle), and the strongest cells of each octave are candidates too, their
//!    centre then found from coarse to fine as in step 3 with a radius band as wide as
//!    the step.
//! 3. Per candidate, the radius whose edge points (at that distance, gradient pointing
//!    radially) cover the most of the circumference, in 1° sectors. Counting sectors, not
//!    points, is what keeps a textured backdrop's many short or straight edges from
//!    outvoting one long round outline.
//! 4. Refinement: along 720 rays from the centre, the strongest intensity step within a
//!    few pixels of the circle, to sub-pixel by a parabola; a geometric circle fit with
//!    Tukey weights over those points; repeated with a narrowing window. Then again on
//!    the images themselves ([`refine_on_images`]): per ray, the strongest step of any
//!    one image, since the median blends rims that differ from image to image.
//! 5. More balls ([`fit_outlines_downscaled`]; a dome's rig holds two or more): the same
//!    search among the candidate centres outside the balls found, again and again. One
//!    more ball is a round outline as strong as a ball's: traced along at least half its
//!    circle both by the refinement's rays and by the edge points (within 1.5 px of it,
//!    their gradient across it: the rays find a step near any circle drawn over a
//!    textured backdrop, the edge points lie on a ball's outline only); of the first
//!    ball's size within 1.5× (a rig's balls are alike, and positions are in their
//!    radii); crossing no other ball's outline (side by side, one cannot overlap
//!    another). The first ball found is the best outline, as with one ball.
//!
//! Limits: the outline must differ in brightness from what surrounds it over a good part
//! of its length (a chrome ball that mirrors a backdrop identical to the one around it
//! has no outline to find), at least a fifth of it must lie in the frame, and a lens that
//! stretches the ball into a visible ellipse is fitted by a circle. A further ball's
//! outline must stand out along half its length: one that fades into its surroundings
//! (a dark ball on a dark backdrop) is not found, and must be given.
//!
//! This file is the search (its candidates tried, refined and judged); its stages are
//! below it: `filter` (blur, gradients), `edges` (step 1), `hough` (steps 2 and 3),
//! `fit` (step 4's refinement and circle fits) and `stack` (step 4 on the images).

mod edges;
mod filter;
mod fit;
mod hough;
mod stack;

use ndarray::Array2;

pub use fit::OutlineFit;
pub(super) use fit::solve3;

use super::circle::Circle;
use edges::{Edge, edge_points, sampled_threshold};
use filter::{gaussian, gaussian_u16, gradients};
use fit::{geometric_fit, kasa, refine};
use hough::{
    MIN_RADIUS, SECTORS, best_radius, centred, octave_peaks, pick_centres, ranked_peaks,
    traced_share,
};

/// Most balls looked for in one frame (as many circles as the service takes).
pub const MAX_BALLS: usize = 16;
/// A further ball's outline is traced along at least this share of its circle: most of
/// it, as a ball's is (see [`is_another_ball`]).
const MORE_COVERAGE: f64 = 0.5;
/// Balls' radii differ by at most this factor: a rig's balls are alike.
const SIZE_RATIO: f64 = 1.5;
/// Two balls' outlines may cross by this much (pixels): touching, to the fits' accuracy.
const TOUCH: f64 = 2.0;

/// Fit the sphere's outline in `image` (e.g. the environment, the per-pixel median of the set); the error says why none
/// was found.
pub fn fit_outline(image: &Array2<f32>) -> Result<OutlineFit, String> {
    fit_outline_downscaled(image, 1)
}

/// [`fit_outline`] on a copy of the images downscaled `factor` times (box averages; 1:
/// not downscaled), to be refined at full resolution ([`refine_outline`]).
///
/// The copy's gradients are not the image's: shading and texture rise `factor` times per
/// pixel, and edges take `factor` times the share of the pixels, while the ball's outline
/// (a step) keeps its strength. So the edge threshold taken from the copy's gradients is
/// divided by `factor`, which keeps a faint outline (a dark ball on a dark backdrop, a
/// ball mirroring a room as bright as its surroundings) above it as at full resolution;
/// and candidate centres are kept 6 pixels of the image apart, as at full resolution, but
/// at least 3 of the copy's.
pub fn fit_outline_downscaled(image: &Array2<f32>, factor: usize) -> Result<OutlineFit, String> {
    Search::new(image, factor)?.first()
}

/// Every ball's outline in `image`, downscaled `factor` times (see
/// [`fit_outline_downscaled`] and the module's notes, step 5): the best one first (the one
/// that gives), then each further ball's, the most traced first. Holds what one fit holds
/// and the accumulator's ranked pixels (24 bytes a pixel).
pub fn fit_outlines_downscaled(
    image: &Array2<f32>,
    factor: usize,
) -> Result<Vec<OutlineFit>, String> {
    let search = Search::new(image, factor)?;
    let mut balls = vec![search.first()?];
    while balls.len() < MAX_BALLS {
        match search.another(&balls) {
            Some(fit) => balls.push(fit),
            None => break,
        }
    }
    Ok(balls)
}

/// Whether a refined outline may be one more ball beside `balls` (the first one first):
/// traced by the refinement along at least [`MORE_COVERAGE`] of its rays, as a ball's
/// outline is wherever it lies in the frame (a partial arc is not), and [`beside`] them.
/// The search asks besides that its edge points trace as much of its circle; this part
/// is asked again of the outline refined at full resolution.
pub fn is_another_ball(fit: &OutlineFit, balls: &[OutlineFit]) -> bool {
    fit.coverage >= MORE_COVERAGE && beside(&fit.circle, balls)
}

/// Whether a circle could be one more ball beside `balls` (the first one first): of the
/// first ball's size within [`SIZE_RATIO`] (a dome's balls are alike, and the positions
/// are in their radii), and crossing no ball's outline (balls lie side by side; in the
/// image one cannot overlap another).
fn beside(c: &Circle, balls: &[OutlineFit]) -> bool {
    let Some(first) = balls.first() else {
        return false;
    };
    let r0 = first.circle.r;
    c.r <= SIZE_RATIO * r0
        && c.r * SIZE_RATIO >= r0
        && balls.iter().all(|b| {
            let d = (c.cx - b.circle.cx).hypot(c.cy - b.circle.cy);
            d >= c.r + b.circle.r - TOUCH
        })
}

/// The outline search over one image: its smoothed copy, its edge points and their
/// threshold, and the centres their gradient lines vote for.
struct Search {
    smooth: Array2<f32>,
    edges: Vec<Edge>,
    threshold: f32,
    /// The smoothed accumulator's pixels, strongest first.
    peaks: Vec<(u32, usize, usize)>,
    /// The octaves' strongest cells: (x, y, cell width).
    octave_peaks: Vec<(f64, f64, f64)>,
    /// Candidate centres are kept this far apart, pixels of the image searched.
    apart: f64,
    max_radius: f64,
}

impl Search {
    fn new(image: &Array2<f32>, factor: usize) -> Result<Self, String> {
        let factor = factor.max(1) as f64;
        let smooth = gaussian(image, 1.0);
        let (gx, gy) = gradients(&smooth);
        let (edges, threshold) = edge_points(&gx, &gy, factor as f32);
        if edges.len() < 20 {
            return Err("the images have almost no edges".into());
        }
        let (h, w) = image.dim();
        let max_radius = w.max(h) as f64;
        let peaks = ranked_peaks(&edges, w, h, max_radius);
        let octave_peaks = octave_peaks(&edges, w, h, max_radius);
        Ok(Self {
            smooth,
            edges,
            threshold,
            peaks,
            octave_peaks,
            apart: (6.0 / factor).max(3.0),
            max_radius,
        })
    }

    /// The best outline: of the strongest candidate centres, the one whose best radius
    /// covers the most sectors, refined; an error when it is not round enough.
    fn first(&self) -> Result<OutlineFit, String> {
        let Some((cover, rough)) = self.roundest(|_, _| false).into_iter().next() else {
            return Err("no round outline among the edges".into());
        };
        if cover < SECTORS / 5 {
            return Err(format!(
                "the roundest outline found covers only {:.0} % of a circle",
                100.0 * cover as f64 / SECTORS as f64
            ));
        }
        let fit = self.refined(rough)?;
        if fit.coverage < 0.2 {
            return Err(format!(
                "the outline was traced along only {:.0} % of the circle",
                100.0 * fit.coverage
            ));
        }
        Ok(fit)
    }

    /// One more ball beside `balls`: of the strongest candidate centres outside them, those
    /// round enough to be tried (as [`first`](Self::first) asks) and [`beside`] them,
    /// refined; of the outlines that [`is_another_ball`] and whose edge points trace at
    /// least [`MORE_COVERAGE`] of their circle ([`traced_share`]), the one they trace the
    /// most of (the earlier candidate among equals).
    ///
    /// Both measures are needed: the refinement's rays find a step near any circle drawn
    /// over a textured backdrop, only not on it (a share of its rays, not of its circle);
    /// the edge points must lie on the circle and point across it.
    fn another(&self, balls: &[OutlineFit]) -> Option<OutlineFit> {
        // A further ball's centre lies outside every ball found, by its own radius.
        let inside = |x: f64, y: f64| {
            balls
                .iter()
                .any(|b| (x - b.circle.cx).hypot(y - b.circle.cy) < b.circle.r + MIN_RADIUS)
        };
        let mut best: Option<(f64, OutlineFit)> = None;
        for (cover, rough) in self.roundest(inside) {
            if cover < SECTORS / 5 || !beside(&rough, balls) {
                continue;
            }
            let Ok(fit) = self.refined(rough) else {
                continue;
            };
            let traced = traced_share(&self.edges, &fit.circle);
            if is_another_ball(&fit, balls)
                && traced >= MORE_COVERAGE
                && best.is_none_or(|b| traced > b.0)
            {
                best = Some((traced, fit));
            }
        }
        best.map(|b| b.1)
    }

    /// Per candidate centre (those `skip` leaves, x and y), the radius whose edge points
    /// cover the most sectors: (sectors, circle), the most first (the earlier candidate
    /// first among equals); the octaves' candidates after the accumulator's, each centred
    /// first ([`centred`]).
    fn roundest(&self, skip: impl Fn(f64, f64) -> bool) -> Vec<(usize, Circle)> {
        let centres = pick_centres(&self.peaks, self.apart, &skip);
        let mut found: Vec<(usize, Circle)> = centres
            .iter()
            .filter_map(|&(cx, cy)| {
                best_radius(&self.edges, cx, cy, (MIN_RADIUS, self.max_radius), 1)
                    .map(|(cover, r)| (cover, Circle { cx, cy, r }))
            })
            .collect();
        found.extend(
            self.octave_peaks
                .iter()
                .filter(|&&(x, y, _)| !skip(x, y))
                .filter_map(|&(x, y, cell)| centred(&self.edges, x, y, cell, self.max_radius)),
        );
        found.sort_by_key(|f| std::cmp::Reverse(f.0));
        found
    }

    /// A rough circle refined to sub-pixel, from wide windows to narrow: a real ball's rim
    /// can be a ramp several pixels wide (defocus, JPEG), and a rough circle a few pixels
    /// off must still see all of it.
    fn refined(&self, rough: Circle) -> Result<OutlineFit, String> {
        let mut fit = OutlineFit {
            circle: rough,
            coverage: 0.0,
            rms: 0.0,
        };
        let wide = (0.03 * rough.r).max(4.0);
        for window in [wide, (0.5 * wide).max(4.0), 4.0, 3.0, 2.0, 2.0] {
            fit = refine(&self.smooth, fit.circle, window, self.threshold)
                .ok_or("the outline could not be traced to sub-pixel accuracy")?;
        }
        Ok(fit)
    }
}

/// Refine a rough outline (e.g. one fitted on a downscaled image) on the full-resolution
/// `image` (an environment, 0..=65535, around the ball): the same rounds of radial
/// sub-pixel refinement as [`fit_outline`]'s, the edge threshold from the image's own
/// gradients (a sample of them); the first round looks `off` pixels either side of the
/// rough circle at least, as far as it may be off. Holds the smoothed image (4 bytes a
/// pixel) and little else. Also gives the image's [`edge_threshold`].
pub fn refine_outline(
    image: &Array2<u16>,
    rough: Circle,
    off: f64,
) -> Result<(OutlineFit, f32), String> {
    let smooth = gaussian_u16(image, 1.0);
    let threshold = sampled_threshold(&smooth);
    let mut fit = OutlineFit {
        circle: rough,
        coverage: 0.0,
        rms: 0.0,
    };
    let wide = (0.03 * rough.r).max(4.0).max(off);
    for window in [wide, (0.5 * wide).max(4.0), 4.0, 3.0, 2.0, 2.0] {
        fit = refine(&smooth, fit.circle, window, threshold)
            .ok_or("the outline could not be traced to sub-pixel accuracy")?;
    }
    if fit.coverage < 0.2 {
        return Err(format!(
            "the outline was traced along only {:.0} % of the circle",
            100.0 * fit.coverage
        ));
    }
    Ok((fit, threshold))
}

/// The outline `start` (fitted on an environment whose [`edge_threshold`] is `threshold`)
/// refined on the `count` images `image(k)` themselves, all over the environment's pixels
/// ([`stack`]: per ray, the strongest step any one image shows, at least `threshold`).
/// `start` itself when too few rays find one.
pub fn refine_on_images<'a, E>(
    threshold: f32,
    count: usize,
    image: impl Fn(usize) -> Result<std::borrow::Cow<'a, Array2<u16>>, E>,
    start: &OutlineFit,
) -> Result<OutlineFit, E> {
    Ok(stack::refine_on_images(count, image, start, threshold)?.unwrap_or(*start))
}

/// The edge threshold of a full-resolution `image` (0..=65535): what the refinement holds
/// a ray's step to.
pub fn edge_threshold(image: &Array2<u16>) -> f32 {
    sampled_threshold(&gaussian_u16(image, 1.0))
}

/// How far outside its circle [`refine_outline`] may look, pixels: what the image around
/// a rough circle off by up to `off` pixels must hold.
pub fn refine_margin(r: f64, off: f64) -> f64 {
    (0.03 * r).max(4.0) + off + 8.0
}

/// The circle of a sphere mask (true = sphere): a least-squares circle through the
/// midpoints of the mask's boundary edges, leaving out the image border.
pub fn circle_of_mask(mask: &Array2<bool>) -> Result<Circle, String> {
    let (h, w) = mask.dim();
    let mut points = Vec::new();
    for r in 0..h {
        for c in 0..w {
            if c + 1 < w && mask[[r, c]] != mask[[r, c + 1]] {
                points.push((c as f64 + 0.5, r as f64));
            }
            if r + 1 < h && mask[[r, c]] != mask[[r + 1, c]] {
                points.push((c as f64, r as f64 + 0.5));
            }
        }
    }
    if points.len() < 12 {
        return Err("it has no outline to fit a circle to".into());
    }
    let c = kasa(&points).ok_or("its outline is not round")?;
    Ok(geometric_fit(&points, c, &vec![1.0; points.len()]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mask_circle_is_recovered_to_a_tenth_of_a_pixel() {
        let (cx, cy, r) = (61.3, 47.8, 30.6);
        let mask = Array2::from_shape_fn((100, 120), |(y, x)| {
            (x as f64 - cx).hypot(y as f64 - cy) <= r
        });
        let c = circle_of_mask(&mask).unwrap();
        assert!((c.cx - cx).abs() < 0.1 && (c.cy - cy).abs() < 0.1, "{c:?}");
        assert!((c.r - r).abs() < 0.1, "{c:?}");
        assert!(circle_of_mask(&Array2::from_elem((20, 20), false)).is_err());
    }

    #[test]
    fn outline_of_a_bright_disc_on_stripes() {
        let (cx, cy, r) = (70.4, 52.7, 33.3);
        let img = Array2::from_shape_fn((110, 140), |(y, x)| {
            // 4×4 supersampled coverage of the disc over a striped backdrop.
            let mut cover = 0.0;
            for j in 0..4 {
                for i in 0..4 {
                    let (sx, sy) = (
                        x as f64 - 0.375 + 0.25 * i as f64,
                        y as f64 - 0.375 + 0.25 * j as f64,
                    );
                    if (sx - cx).hypot(sy - cy) <= r {
                        cover += 1.0 / 16.0;
                    }
                }
            }
            let back = 0.3 + 0.2 * ((x as f64) / 5.0).sin();
            (cover * 0.8 + (1.0 - cover) * back) as f32
        });
        let fit = fit_outline(&img).unwrap();
        let c = fit.circle;
        assert!(
            (c.cx - cx).abs() < 0.1 && (c.cy - cy).abs() < 0.1,
            "{fit:?}"
        );
        assert!((c.r - r).abs() < 0.1, "{fit:?}");
    }
}
