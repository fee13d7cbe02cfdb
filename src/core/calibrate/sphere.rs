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
//!    Tukey weights over those points; repeated with a narrowing window.
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

use ndarray::Array2;

use super::Circle;

/// Smallest radius searched, pixels.
const MIN_RADIUS: f64 = 8.0;
/// Rays of the refinement and sectors of the coverage count (per full turn).
const RAYS: usize = 720;
const SECTORS: usize = 360;
/// Most edge points kept (the strongest).
const MAX_EDGES: usize = 60_000;
/// Candidate centres tried per ball.
const CANDIDATES: usize = 12;
/// Distance octaves from this far are also voted in coarse cells (the module's notes,
/// step 2), pixels.
const OCTAVES_FROM: f64 = 64.0;
/// An octave's cells are its start divided by this.
const OCTAVE_CELLS: f64 = 16.0;
/// Candidates kept per octave.
const OCTAVE_CANDIDATES: usize = 4;
/// Most balls looked for in one frame (as many circles as the service takes).
pub const MAX_BALLS: usize = 16;
/// A further ball's outline is traced along at least this share of its circle: most of
/// it, as a ball's is (see [`is_another_ball`]).
const MORE_COVERAGE: f64 = 0.5;
/// Balls' radii differ by at most this factor: a rig's balls are alike.
const SIZE_RATIO: f64 = 1.5;
/// Two balls' outlines may cross by this much (pixels): touching, to the fits' accuracy.
const TOUCH: f64 = 2.0;

/// A fitted outline and how well the images support it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutlineFit {
    pub circle: Circle,
    /// Fraction of the refinement's rays that found the outline.
    pub coverage: f64,
    /// RMS distance of the kept outline points from the circle, pixels.
    pub rms: f64,
}

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
/// pixel) and little else.
pub fn refine_outline(image: &Array2<u16>, rough: Circle, off: f64) -> Result<OutlineFit, String> {
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
    Ok(fit)
}

/// How far outside its circle [`refine_outline`] may look, pixels: what the image around
/// a rough circle off by up to `off` pixels must hold.
pub fn refine_margin(r: f64, off: f64) -> f64 {
    (0.03 * r).max(4.0) + off + 8.0
}

/// [`gaussian`] of `image` scaled to [0, 1], a row at a time (the horizontal pass kept
/// for the rows the vertical pass needs), so only the result is held.
fn gaussian_u16(image: &Array2<u16>, sigma: f64) -> Array2<f32> {
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let sum: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / sum).collect();
    let (h, w) = image.dim();
    let across = |r: usize| -> Vec<f32> {
        (0..w)
            .map(|c| {
                let mut acc = 0.0;
                for (k, &g) in kernel.iter().enumerate() {
                    let o = k as isize - radius;
                    let x = (c as isize + o).clamp(0, w as isize - 1) as usize;
                    acc += g * (image[[r, x]] as f32 / 65535.0);
                }
                acc
            })
            .collect()
    };
    let span = 2 * radius as usize + 1;
    let mut ring: Vec<Option<(usize, Vec<f32>)>> = vec![None; span];
    let mut out = Array2::zeros((h, w));
    for r in 0..h {
        for (k, &g) in kernel.iter().enumerate() {
            let src = (r as isize + k as isize - radius).clamp(0, h as isize - 1) as usize;
            let slot = src % span;
            if ring[slot].as_ref().is_none_or(|(at, _)| *at != src) {
                ring[slot] = Some((src, across(src)));
            }
            let row = &ring[slot].as_ref().expect("filled above").1;
            for (o, &v) in out.row_mut(r).iter_mut().zip(row) {
                *o += g * v;
            }
        }
    }
    out
}

/// [`edge_points`]' threshold from the gradients of about a million pixels on a grid.
fn sampled_threshold(smooth: &Array2<f32>) -> f32 {
    let (h, w) = smooth.dim();
    let step = ((h * w) as f64 / 1e6).sqrt().ceil().max(1.0) as usize;
    let mut mags = Vec::new();
    for r in (1..h.saturating_sub(1)).step_by(step) {
        for c in (1..w.saturating_sub(1)).step_by(step) {
            let p = |dr: isize, dc: isize| {
                smooth[[(r as isize + dr) as usize, (c as isize + dc) as usize]]
            };
            let gx =
                (p(-1, 1) + 2.0 * p(0, 1) + p(1, 1) - p(-1, -1) - 2.0 * p(0, -1) - p(1, -1)) / 8.0;
            let gy =
                (p(1, -1) + 2.0 * p(1, 0) + p(1, 1) - p(-1, -1) - 2.0 * p(-1, 0) - p(-1, 1)) / 8.0;
            let m = (gx * gx + gy * gy).sqrt();
            if m > 0.0 {
                mags.push(m);
            }
        }
    }
    if mags.is_empty() {
        return f32::INFINITY;
    }
    mags.sort_unstable_by(f32::total_cmp);
    let q = |f: f64| mags[((mags.len() - 1) as f64 * f) as usize];
    (0.1 * q(0.99)).max(3.0 * q(0.5))
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

/// Separable Gaussian blur, clamped at the borders.
fn gaussian(a: &Array2<f32>, sigma: f64) -> Array2<f32> {
    let radius = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let sum: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / sum).collect();
    let (h, w) = a.dim();
    let pass = |src: &Array2<f32>, along_rows: bool| {
        Array2::from_shape_fn((h, w), |(r, c)| {
            let mut acc = 0.0;
            for (k, &g) in kernel.iter().enumerate() {
                let o = k as isize - radius;
                let v = if along_rows {
                    src[[r, (c as isize + o).clamp(0, w as isize - 1) as usize]]
                } else {
                    src[[(r as isize + o).clamp(0, h as isize - 1) as usize, c]]
                };
                acc += g * v;
            }
            acc
        })
    };
    pass(&pass(a, true), false)
}

/// Sobel gradients per pixel (units: full scale per pixel), zero on the border.
fn gradients(a: &Array2<f32>) -> (Array2<f32>, Array2<f32>) {
    let (h, w) = a.dim();
    let mut gx = Array2::zeros((h, w));
    let mut gy = Array2::zeros((h, w));
    for r in 1..h.saturating_sub(1) {
        for c in 1..w.saturating_sub(1) {
            let p =
                |dr: isize, dc: isize| a[[(r as isize + dr) as usize, (c as isize + dc) as usize]];
            gx[[r, c]] =
                (p(-1, 1) + 2.0 * p(0, 1) + p(1, 1) - p(-1, -1) - 2.0 * p(0, -1) - p(1, -1)) / 8.0;
            gy[[r, c]] =
                (p(1, -1) + 2.0 * p(1, 0) + p(1, 1) - p(-1, -1) - 2.0 * p(-1, 0) - p(-1, 1)) / 8.0;
        }
    }
    (gx, gy)
}

/// An edge point: sub-pixel position and unit gradient direction.
#[derive(Debug, Clone, Copy)]
struct Edge {
    x: f32,
    y: f32,
    ux: f32,
    uy: f32,
}

/// Gradient maxima along the gradient above the threshold, and the threshold: a tenth of
/// the 99th percentile of the gradient magnitude, and at least three times its median
/// (the noise), divided by `downscaled` (the image's downscaling factor, 1 at full
/// resolution; see [`fit_outline_downscaled`]).
fn edge_points(gx: &Array2<f32>, gy: &Array2<f32>, downscaled: f32) -> (Vec<Edge>, f32) {
    let (h, w) = gx.dim();
    let mag = Array2::from_shape_fn((h, w), |i| (gx[i] * gx[i] + gy[i] * gy[i]).sqrt());
    let mut sorted: Vec<f32> = mag.iter().cloned().filter(|&m| m > 0.0).collect();
    if sorted.is_empty() {
        return (Vec::new(), 0.0);
    }
    sorted.sort_unstable_by(f32::total_cmp);
    let q = |f: f64| sorted[((sorted.len() - 1) as f64 * f) as usize];
    let threshold = (0.1 * q(0.99)).max(3.0 * q(0.5)) / downscaled;
    let mut edges: Vec<(f32, Edge)> = Vec::new();
    for r in 2..h.saturating_sub(2) {
        for c in 2..w.saturating_sub(2) {
            let m = mag[[r, c]];
            if m < threshold {
                continue;
            }
            let (ux, uy) = (gx[[r, c]] / m, gy[[r, c]] / m);
            // The neighbour along the gradient, quantised to 45°.
            let (dc, dr) = (ux.round() as isize, uy.round() as isize);
            let before = mag[[(r as isize - dr) as usize, (c as isize - dc) as usize]];
            let after = mag[[(r as isize + dr) as usize, (c as isize + dc) as usize]];
            if m < before || m <= after {
                continue;
            }
            let curvature = before - 2.0 * m + after;
            let t = if curvature < 0.0 {
                (0.5 * (before - after) / curvature).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            edges.push((
                m,
                Edge {
                    x: c as f32 + t * dc as f32,
                    y: r as f32 + t * dr as f32,
                    ux,
                    uy,
                },
            ));
        }
    }
    if edges.len() > MAX_EDGES {
        edges.select_nth_unstable_by(MAX_EDGES, |a, b| b.0.total_cmp(&a.0));
        edges.truncate(MAX_EDGES);
    }
    (edges.into_iter().map(|e| e.1).collect(), threshold)
}

/// The pixels of the (3×3-smoothed) accumulator of the edge points' gradient lines, each
/// voting for the centres of the circles it could lie on: (votes, row, column), the most
/// first.
fn ranked_peaks(edges: &[Edge], w: usize, h: usize, max_radius: f64) -> Vec<(u32, usize, usize)> {
    let mut acc = Array2::<u32>::zeros((h, w));
    for e in edges {
        for sign in [-1.0f32, 1.0] {
            let mut t = MIN_RADIUS as f32;
            while t <= max_radius as f32 {
                let (x, y) = (e.x + sign * t * e.ux, e.y + sign * t * e.uy);
                if x < 0.0 || y < 0.0 || x > (w - 1) as f32 || y > (h - 1) as f32 {
                    break;
                }
                // Rounded (both are at least 0).
                acc[[(y + 0.5) as usize, (x + 0.5) as usize]] += 1;
                t += 1.0;
            }
        }
    }
    let mut smooth = Array2::<u32>::zeros((h, w));
    for r in 1..h - 1 {
        for c in 1..w - 1 {
            let mut s = 0;
            for dr in 0..3 {
                for dc in 0..3 {
                    s += acc[[r + dr - 1, c + dc - 1]];
                }
            }
            smooth[[r, c]] = s;
        }
    }
    drop(acc);
    let mut peaks: Vec<(u32, usize, usize)> = smooth
        .indexed_iter()
        .filter(|&(_, &v)| v > 0)
        .map(|((r, c), &v)| (v, r, c))
        .collect();
    peaks.sort_unstable_by_key(|p| std::cmp::Reverse(p.0));
    peaks
}

/// The octaves' candidate centres (the module's notes, step 2): per octave of distance
/// from [`OCTAVES_FROM`], the edge points' votes cast from that far (every quarter cell)
/// counted in cells 1/[`OCTAVE_CELLS`] of the octave's start wide, summed over 2 × 2
/// cells; the strongest [`OCTAVE_CANDIDATES`] local maxima, as (x, y, cell width).
fn octave_peaks(edges: &[Edge], w: usize, h: usize, max_radius: f64) -> Vec<(f64, f64, f64)> {
    let mut found = Vec::new();
    let mut start = OCTAVES_FROM;
    while start < max_radius {
        let end = (2.0 * start).min(max_radius);
        let cell = start / OCTAVE_CELLS;
        let (cw, ch) = (
            (w as f64 / cell) as usize + 1,
            (h as f64 / cell) as usize + 1,
        );
        let mut acc = Array2::<u32>::zeros((ch, cw));
        for e in edges {
            for sign in [-1.0f32, 1.0] {
                // A vote every quarter cell: about four in each cell the line crosses.
                let (mut t, step) = (start as f32, (cell as f32 / 4.0).max(1.0));
                let per_cell = 1.0 / cell as f32;
                while t < end as f32 {
                    let (x, y) = (e.x + sign * t * e.ux, e.y + sign * t * e.uy);
                    if x < 0.0 || y < 0.0 || x > (w - 1) as f32 || y > (h - 1) as f32 {
                        break;
                    }
                    acc[[(y * per_cell) as usize, (x * per_cell) as usize]] += 1;
                    t += step;
                }
            }
        }
        // sums[i, j] covers cells i..=i + 1, j..=j + 1: centred at (i + 1, j + 1) cells.
        let sums = Array2::from_shape_fn((ch - 1, cw - 1), |(i, j)| {
            acc[[i, j]] + acc[[i + 1, j]] + acc[[i, j + 1]] + acc[[i + 1, j + 1]]
        });
        let (sh, sw) = sums.dim();
        let mut maxima: Vec<(u32, usize, usize)> = sums
            .indexed_iter()
            .filter(|&((i, j), &v)| {
                v > 0
                    && (i.saturating_sub(1)..(i + 2).min(sh))
                        .all(|a| (j.saturating_sub(1)..(j + 2).min(sw)).all(|b| sums[[a, b]] <= v))
            })
            .map(|((i, j), &v)| (v, i, j))
            .collect();
        maxima.sort_unstable_by_key(|m| std::cmp::Reverse(m.0));
        found.extend(
            maxima
                .iter()
                .take(OCTAVE_CANDIDATES)
                .map(|&(_, i, j)| ((j + 1) as f64 * cell, (i + 1) as f64 * cell, cell)),
        );
        start *= 2.0;
    }
    found
}

/// An octave's candidate (x, y) centred from coarse to fine: on a grid of steps from half
/// its `cell` down to a pixel (5 × 5 at first, then 3 × 3 about the last best), each
/// time the point whose best radius covers the most sectors (counting a band as wide as
/// the step); the last (sectors, circle). Only the edge points that could lie on a
/// circle of the octave about the cell count: within its distances (and a margin of two
/// cells), their gradient within about 37° of radial (the centre moves by a cell at most,
/// 3.6° as seen from the octave's start).
fn centred(edges: &[Edge], x: f64, y: f64, cell: f64, max_radius: f64) -> Option<(usize, Circle)> {
    let start = cell * OCTAVE_CELLS;
    let (near, far) = (start - 2.0 * cell, 2.0 * start + 2.0 * cell);
    let edges: Vec<Edge> = edges
        .iter()
        .filter(|e| {
            let (dx, dy) = (e.x as f64 - x, e.y as f64 - y);
            let d = (dx * dx + dy * dy).sqrt();
            d >= near && d <= far && (e.ux as f64 * dx + e.uy as f64 * dy).abs() >= 0.8 * d
        })
        .copied()
        .collect();
    let edges = &edges[..];
    let mut step = (0.5 * cell).max(1.0);
    let (mut cx, mut cy) = (x, y);
    let mut reach = 2;
    loop {
        let band = step.round().max(1.0) as usize;
        let mut best: Option<(usize, Circle)> = None;
        for i in -reach..=reach {
            for j in -reach..=reach {
                let (px, py) = (cx + j as f64 * step, cy + i as f64 * step);
                if let Some((cover, r)) =
                    best_radius(edges, px, py, (near, far.min(max_radius)), band)
                    && best.is_none_or(|(b, _)| cover > b)
                {
                    best = Some((cover, Circle { cx: px, cy: py, r }));
                }
            }
        }
        let (_, c) = best?;
        (cx, cy) = (c.cx, c.cy);
        if step <= 1.0 {
            return best;
        }
        step = (0.5 * step).max(1.0);
        reach = 1;
    }
}

/// Candidate centres: the strongest [`CANDIDATES`] peaks at least `apart` px apart,
/// leaving out those `skip` says (x, y).
fn pick_centres(
    peaks: &[(u32, usize, usize)],
    apart: f64,
    skip: &impl Fn(f64, f64) -> bool,
) -> Vec<(f64, f64)> {
    let mut chosen: Vec<(f64, f64)> = Vec::new();
    for &(_, r, c) in peaks {
        let (x, y) = (c as f64, r as f64);
        if !skip(x, y)
            && chosen
                .iter()
                .all(|&(px, py)| (px - x).hypot(py - y) >= apart)
        {
            chosen.push((x, y));
            if chosen.len() == CANDIDATES {
                break;
            }
        }
    }
    chosen
}

/// The share of `circle`'s outline its edge points trace: of its sectors (1° or, on a
/// small circle, about a pixel of its circumference each), those holding an edge point
/// within 1.5 px of it whose gradient points radially (as [`best_radius`] counts them).
fn traced_share(edges: &[Edge], circle: &Circle) -> f64 {
    let n = ((std::f64::consts::TAU * circle.r) as usize).clamp(1, SECTORS);
    let mut hit = vec![false; n];
    for e in edges {
        let (dx, dy) = (e.x as f64 - circle.cx, e.y as f64 - circle.cy);
        let d = dx.hypot(dy);
        if (d - circle.r).abs() > 1.5 || d == 0.0 {
            continue;
        }
        if ((e.ux as f64 * dx + e.uy as f64 * dy) / d).abs() < 0.9 {
            continue;
        }
        let angle = dy.atan2(dx).rem_euclid(std::f64::consts::TAU);
        hit[((angle / std::f64::consts::TAU * n as f64) as usize).min(n - 1)] = true;
    }
    hit.iter().filter(|&&h| h).count() as f64 / n as f64
}

/// The radius about (cx, cy), between `radii` (and at least [`MIN_RADIUS`]), whose
/// radially oriented edge points cover the most 1° sectors (counting a ±`band` px band),
/// and that count.
fn best_radius(
    edges: &[Edge],
    cx: f64,
    cy: f64,
    radii: (f64, f64),
    band: usize,
) -> Option<(usize, f64)> {
    let (near, far) = (radii.0.max(MIN_RADIUS), radii.1);
    if far < near {
        return None;
    }
    // Bin i holds the distances that round to first + i.
    let first = (near.round() as usize).saturating_sub(band);
    let bins = far.round() as usize + band + 1 - first;
    let mut sectors = vec![[0u64; SECTORS.div_ceil(64)]; bins];
    let mut sums = vec![(0.0f64, 0usize); bins];
    for e in edges {
        let (dx, dy) = (e.x as f64 - cx, e.y as f64 - cy);
        let d = (dx * dx + dy * dy).sqrt();
        if d < near || d > far {
            continue;
        }
        if ((e.ux as f64 * dx + e.uy as f64 * dy) / d).abs() < 0.9 {
            continue;
        }
        let bin = d.round() as usize - first;
        // Single precision is ample for 1° sectors, and twice as fast.
        let angle = (dy as f32)
            .atan2(dx as f32)
            .rem_euclid(std::f32::consts::TAU);
        let s = ((angle / std::f32::consts::TAU * SECTORS as f32) as usize).min(SECTORS - 1);
        sectors[bin][s / 64] |= 1 << (s % 64);
        sums[bin].0 += d;
        sums[bin].1 += 1;
    }
    let mut best: Option<(usize, f64)> = None;
    for bin in band..bins - band {
        let mut words = [0u64; SECTORS.div_ceil(64)];
        for b in bin - band..=bin + band {
            for (w, s) in words.iter_mut().zip(&sectors[b]) {
                *w |= s;
            }
        }
        let cover = words.iter().map(|w| w.count_ones() as usize).sum();
        if best.is_none_or(|b| cover > b.0) {
            let (s, n) = (bin - band..=bin + band)
                .fold((0.0, 0), |acc, b| (acc.0 + sums[b].0, acc.1 + sums[b].1));
            best = Some((cover, s / n.max(1) as f64));
        }
    }
    best
}

/// One refinement round: the outline's sub-pixel position along each ray within
/// `window` px of `circle`, then a robust circle fit through them.
fn refine(image: &Array2<f32>, circle: Circle, window: f64, threshold: f32) -> Option<OutlineFit> {
    let (h, w) = image.dim();
    let step = 0.25;
    let n = (2.0 * window / step).round() as usize + 1;
    let mut points = Vec::new();
    for k in 0..RAYS {
        let a = k as f64 / RAYS as f64 * std::f64::consts::TAU;
        let (ux, uy) = (a.cos(), a.sin());
        let at = |i: usize| {
            let rho = circle.r - window + i as f64 * step;
            (circle.cx + rho * ux, circle.cy + rho * uy)
        };
        let (x0, y0) = at(0);
        let (x1, y1) = at(n - 1);
        let inside =
            |x: f64, y: f64| x >= 1.0 && y >= 1.0 && x <= (w - 2) as f64 && y <= (h - 2) as f64;
        if !inside(x0, y0) || !inside(x1, y1) {
            continue;
        }
        let samples: Vec<f64> = (0..n)
            .map(|i| {
                let (x, y) = at(i);
                bilinear(image, x, y)
            })
            .collect();
        let deriv: Vec<f64> = (1..n - 1)
            .map(|i| ((samples[i + 1] - samples[i - 1]) / (2.0 * step)).abs())
            .collect();
        let (i, &peak) = deriv.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
        if peak < threshold as f64 || i == 0 || i + 1 == deriv.len() {
            continue;
        }
        let (a0, a1, a2) = (deriv[i - 1], peak, deriv[i + 1]);
        let curvature = a0 - 2.0 * a1 + a2;
        let t = if curvature < 0.0 {
            (0.5 * (a0 - a2) / curvature).clamp(-0.5, 0.5)
        } else {
            0.0
        };
        let rho = circle.r - window + (i as f64 + 1.0 + t) * step;
        points.push((circle.cx + rho * ux, circle.cy + rho * uy));
    }
    if points.len() < 12 {
        return None;
    }
    // Tukey-weighted geometric fit, scale from the residuals' MAD.
    let mut c = circle;
    let mut weights = vec![1.0; points.len()];
    for _ in 0..8 {
        let mut res: Vec<f64> = points
            .iter()
            .map(|&(x, y)| ((x - c.cx).hypot(y - c.cy) - c.r).abs())
            .collect();
        let resid = res.clone();
        let mid = res.len() / 2;
        let mad = *res.select_nth_unstable_by(mid, f64::total_cmp).1;
        let cutoff = 4.685 * (1.4826 * mad).max(0.05);
        for (wt, r) in weights.iter_mut().zip(&resid) {
            let u = r / cutoff;
            *wt = if u < 1.0 { (1.0 - u * u).powi(2) } else { 0.0 };
        }
        c = geometric_fit(&points, c, &weights);
    }
    let (mut sq, mut kept) = (0.0, 0usize);
    for (&(x, y), &wt) in points.iter().zip(&weights) {
        if wt > 0.0 {
            sq += ((x - c.cx).hypot(y - c.cy) - c.r).powi(2);
            kept += 1;
        }
    }
    Some(OutlineFit {
        circle: c,
        coverage: kept as f64 / RAYS as f64,
        rms: (sq / kept.max(1) as f64).sqrt(),
    })
}

fn bilinear(a: &Array2<f32>, x: f64, y: f64) -> f64 {
    let (c0, r0) = (x.floor() as usize, y.floor() as usize);
    let (fx, fy) = (x - c0 as f64, y - r0 as f64);
    let p = |r: usize, c: usize| a[[r, c]] as f64;
    (p(r0, c0) * (1.0 - fx) + p(r0, c0 + 1) * fx) * (1.0 - fy)
        + (p(r0 + 1, c0) * (1.0 - fx) + p(r0 + 1, c0 + 1) * fx) * fy
}

/// Algebraic (Kåsa) circle through points: a start for the geometric fit.
fn kasa(points: &[(f64, f64)]) -> Option<Circle> {
    // Minimise Σ (x² + y² + D x + E y + F)².
    let mut m = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for &(x, y) in points {
        let row = [x, y, 1.0];
        let z = -(x * x + y * y);
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += row[i] * row[j];
            }
            b[i] += row[i] * z;
        }
    }
    let [d, e, f] = solve3(m, b)?;
    let (cx, cy) = (-d / 2.0, -e / 2.0);
    let r2 = cx * cx + cy * cy - f;
    (r2 > 0.0).then(|| Circle {
        cx,
        cy,
        r: r2.sqrt(),
    })
}

/// Weighted geometric circle fit (Gauss–Newton on distance − r) from `start`.
fn geometric_fit(points: &[(f64, f64)], start: Circle, weights: &[f64]) -> Circle {
    let mut c = start;
    for _ in 0..20 {
        let mut m = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for (&(x, y), &w) in points.iter().zip(weights) {
            if w == 0.0 {
                continue;
            }
            let (dx, dy) = (x - c.cx, y - c.cy);
            let d = dx.hypot(dy).max(1e-9);
            let j = [-dx / d, -dy / d, -1.0];
            let r = d - c.r;
            for i in 0..3 {
                for k in 0..3 {
                    m[i][k] += w * j[i] * j[k];
                }
                b[i] -= w * j[i] * r;
            }
        }
        let Some(delta) = solve3(m, b) else {
            break;
        };
        c = Circle {
            cx: c.cx + delta[0],
            cy: c.cy + delta[1],
            r: c.r + delta[2],
        };
        if delta.iter().all(|d| d.abs() < 1e-6) {
            break;
        }
    }
    c
}

/// Solve a 3×3 system by Cramer's rule; None when singular.
pub(super) fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |a: [[f64; 3]; 3]| {
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    };
    let d = det(m);
    let scale = m.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    if d.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let mut out = [0.0; 3];
    for (k, o) in out.iter_mut().enumerate() {
        let mut a = m;
        for i in 0..3 {
            a[i][k] = b[i];
        }
        *o = det(a) / d;
    }
    Some(out)
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
