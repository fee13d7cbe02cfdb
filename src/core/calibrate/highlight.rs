//! One image's highlight: the light's own mirror image on the sphere, told apart from the
//! environment the ball reflects in every image, and its direction.
//!
//! 1. The residual (image less the environment, see [`super::environment`]) is what this
//!    image has and the others lack. Its significant pixels (above the noise and a quarter
//!    of its peak) form blobs (pixels within 2 of each other join, so a clipped core split
//!    by JPEG ringing stays one).
//! 2. The light is the brightest blob: of the blobs whose peak is clipped or whose rise
//!    over the environment is within 20 % of the largest, the one with the most residual
//!    light, counted where few other images have a residual too (a reflection of the room that the lights brighten
//!    recurs from image to image; a light does not). A runner-up nearly as strong makes
//!    the image ambiguous.
//! 3. Its core is the light's disc: the clipped pixels when the peak clips (the glare
//!    and the scratches' streaks around a real highlight are not the light and are seldom
//!    symmetric), else the pixels down to a tenth of the blob's peak. No shape is refused: a
//!    highlight may be small or large, round or elongated.
//! 4. A clipped light also clips where it shines on something near the ball: the image's
//!    other clipped blobs of its own move with the light and are its echoes.
//! 5. The light's centre is the radiance-weighted median of the core's and its echoes'
//!    pixel positions (column and row), and its direction the mirror direction there: the
//!    rule the field's data sets measure their lights by. An orthographic mirror sphere
//!    maps equal image areas to equal solid angles, so the median halves the light's
//!    directions each way; an echo moves it only by its share of the light, where a mean
//!    would follow it by its distance (several degrees). The price: a large light near
//!    the rim, squeezed unevenly, comes out about 0.1° off its disc's centre at 20° across.
//!
//! Every highlight gets a confidence in [0, 1]: how clearly it beats the runner-up, how
//! much of its brightness the environment leaves unexplained, and whether its core has a
//! few pixels at least.

use std::collections::HashSet;

use ndarray::Array2;

use super::circle::Circle;
use super::environment::Disc;
use super::mirror::Camera;

/// A clipped blob besides the light's counts as the light's own reflection when at least
/// this share of its light (weighted as the blob score is) is where other images have no
/// residual.
const ECHO_OWN: f64 = 0.5;
/// Pixels at most this far apart (in rows and in columns) belong to one blob.
const JOIN: isize = 2;
/// A clipped core of fewer pixels takes its partly covered edge too.
const SMALL_CORE: usize = 64;
/// A runner-up with at least this share of the winner's score makes the image ambiguous.
const AMBIGUOUS: f64 = 0.8;
/// Below this share of its brightness unexplained by the environment, a highlight is the
/// environment's, not a light's.
const MIN_OWN: f64 = 0.3;
/// A light's direction at most this far behind the ball's equator plane (z below
/// −sin of it) is refused: no highlight of a light there reaches the camera but a rim
/// glint.
pub const MAX_BEHIND_DEG: f64 = 10.0;

/// A highlight found in one image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Highlight {
    /// Unit light direction.
    pub direction: [f64; 3],
    /// The light's centre (see the module's notes), pixels (0-based, centres at integers).
    pub x: f64,
    pub y: f64,
    /// Pixels in the core.
    pub pixels: usize,
    /// Brightest value, fraction of full scale, and whether it is clipped.
    pub peak: f64,
    pub clipped: bool,
    /// Distance of the centroid from the outline, pixels.
    pub rim_distance: f64,
    /// Ratio of the core's principal axes in direction space (1 = round).
    pub elongation: f64,
    /// Equivalent angular radius of the core, degrees.
    pub radius_deg: f64,
    /// How sure the finder is, 0..1 (see the module's notes).
    pub confidence: f64,
}

/// What every image of a set is judged against.
#[derive(Clone, Copy)]
pub struct Context<'a> {
    pub circle: &'a Circle,
    pub camera: &'a Camera,
    pub env: &'a Array2<u16>,
    /// Images in the set (for the recurrence share).
    pub count: usize,
    /// At and above: a clipped pixel (the `clipped` flag, and a clipped blob's core).
    pub clip: u16,
    /// The set's typical rise of a highlight over the environment (the median of the
    /// images' largest residuals): a blob far below it is something a light brightens.
    pub typical_rise: f64,
}

/// An unclipped blob rising less than this share of the set's typical highlight is not a
/// light (a light outshines what it lights).
const MIN_RISE: f64 = 0.3;

fn residual(plane: &Array2<u16>, env: &Array2<u16>, p: (usize, usize)) -> f64 {
    plane[p].saturating_sub(env[p]) as f64
}

/// The residual's significance threshold in one image (above its noise and a quarter of
/// its peak on the ball) and its peak, which is above it; an error when nothing on the
/// ball stands out.
fn floor(plane: &Array2<u16>, ctx: &Context, disc: &Disc) -> Result<Significant, String> {
    // The median neighbour difference by counting (no copy of the disc's pixels).
    let mut diffs = vec![0u32; 1 << 16];
    let mut count = 0usize;
    let mut peak = 0.0f64;
    let mut n = 0usize;
    for (r, cols) in disc.rows() {
        let (row, env) = (plane.row(r), ctx.env.row(r));
        let first = *cols.start();
        for c in cols {
            n += 1;
            peak = peak.max(row[c].saturating_sub(env[c]) as f64);
            // A row's span is contiguous: its left neighbour is on the ball too.
            if c > first {
                diffs[row[c].abs_diff(row[c - 1]) as usize] += 1;
                count += 1;
            }
        }
    }
    if n < 20 {
        return Err("the sphere covers almost no pixels of the image".into());
    }
    let noise = 1.4826 * median_of_counts(&diffs, count) as f64 / std::f64::consts::SQRT_2;
    let least = (10.0 * noise).max(0.02 * 65535.0);
    if peak < least {
        return Err(format!(
            "no highlight: nothing on the sphere is brighter than in the other images (at most {:.3} of full scale above them); the light's highlight is missing, or this image is like the others",
            peak / 65535.0
        ));
    }
    Ok(Significant {
        floor: (6.0 * noise).max(0.01 * 65535.0).max(0.25 * peak),
        peak,
    })
}

/// An image's significant residual: the level it starts at and its largest value.
pub struct Significant {
    floor: f64,
    pub peak: f64,
}

/// The level above which `plane`'s residual is significant, and its largest residual;
/// or why nothing is.
pub fn significant(plane: &Array2<u16>, ctx: &Context) -> Result<Significant, String> {
    let disc = Disc::new(ctx.circle, plane.dim());
    floor(plane, ctx, &disc)
}

/// Count `plane`'s significant pixels in `recurrence` (see [`super::environment`]).
pub fn add_recurrence(
    plane: &Array2<u16>,
    ctx: &Context,
    sig: &Significant,
    recurrence: &mut Array2<u16>,
) {
    let disc = Disc::new(ctx.circle, plane.dim());
    for (r, cols) in disc.rows() {
        let (row, env, mut counts) = (plane.row(r), ctx.env.row(r), recurrence.row_mut(r));
        for c in cols {
            if row[c].saturating_sub(env[c]) as f64 >= sig.floor {
                counts[c] = counts[c].saturating_add(1);
            }
        }
    }
}

/// A pixel (row, column) of a core, kept compact: a core may be most of the ball.
type Pixel = (u32, u32);

fn pixel((r, c): (usize, usize)) -> Pixel {
    (r as u32, c as u32)
}

/// A blob of significant residual.
struct Blob {
    /// Its label in the disc's label map.
    label: u32,
    /// Brightest image value in it.
    peak: u16,
    /// Its largest residual, and the last pixel (row-major) that has it.
    peak_residual: f64,
    top: (usize, usize),
    /// Residual light, each pixel weighted by how seldom other images have one there.
    score: f64,
    /// Residual light.
    light: f64,
    centre: (f64, f64),
}

/// The highlight of `plane`, or why there is none. `recurrence` counts per pixel the
/// images with a significant residual there.
pub fn find(
    plane: &Array2<u16>,
    ctx: &Context,
    recurrence: &Array2<u16>,
) -> Result<Highlight, String> {
    let disc = Disc::new(ctx.circle, plane.dim());
    let floor = floor(plane, ctx, &disc)?.floor;
    let keep = |p: (usize, usize)| disc.contains(p.0, p.1) && residual(plane, ctx.env, p) >= floor;
    let others = (ctx.count.max(2) - 1) as f64;
    let labels = Labels::of(&disc, &keep);
    let mut blobs: Vec<Blob> = (1..=labels.count as u32)
        .map(|label| Blob {
            label,
            peak: 0,
            peak_residual: 0.0,
            top: (0, 0),
            score: 0.0,
            light: 0.0,
            centre: (0.0, 0.0),
        })
        .collect();
    let mut sizes = vec![0usize; labels.count];
    for p in disc.pixels() {
        let l = labels.at(p);
        if l == 0 {
            continue;
        }
        let b = &mut blobs[l as usize - 1];
        let e = residual(plane, ctx.env, p);
        b.peak = b.peak.max(plane[p]);
        if e >= b.peak_residual {
            b.peak_residual = e;
            b.top = p;
        }
        let unique = 1.0 - (recurrence[p].max(1) - 1) as f64 / others;
        b.score += e * unique * unique;
        b.light += e;
        b.centre.0 += p.1 as f64;
        b.centre.1 += p.0 as f64;
        sizes[l as usize - 1] += 1;
    }
    for (b, &n) in blobs.iter_mut().zip(&sizes) {
        b.centre = (b.centre.0 / n as f64, b.centre.1 / n as f64);
    }
    // A light outshines whatever it lights: its blob's rise over the environment is (near)
    // the image's largest, or it clips.
    let top = blobs.iter().map(|b| b.peak_residual).fold(0.0, f64::max);
    let mut contenders: Vec<&Blob> = blobs
        .iter()
        .filter(|b| b.peak >= ctx.clip || b.peak_residual >= 0.8 * top)
        .collect();
    contenders.retain(|b| b.peak >= ctx.clip || b.peak_residual >= MIN_RISE * ctx.typical_rise);
    if contenders.is_empty() {
        return Err(format!(
            "no highlight: what this image adds to the others rises {:.3} of full scale over them, far less than the other images' highlights ({:.3}): a lit object, not a light; is the light behind the ball or hidden?",
            top / 65535.0,
            ctx.typical_rise / 65535.0
        ));
    }
    contenders.sort_by(|a, b| b.score.total_cmp(&a.score));
    let Some(&best) = contenders.first() else {
        return Err("no highlight: no bright blob on the sphere".into());
    };
    let second = contenders.get(1).map_or(0.0, |b| b.score);
    if best.score <= 0.0 {
        return Err(format!(
            "no highlight of its own: the brightest blob, at ({:.0}, {:.0}), is there in the other images too (a room light or a reflection that stays put); add an ambient image of the ball with the rig's lights off (ambient.png), or leave the image out with --skip-bad",
            best.centre.0, best.centre.1
        ));
    }
    if second >= AMBIGUOUS * best.score {
        let b = contenders[1];
        return Err(format!(
            "two highlights about equally strong, at ({:.0}, {:.0}) and ({:.0}, {:.0}), neither in the other images; add an ambient image of the ball with the rig's lights off (ambient.png), or leave the image out with --skip-bad",
            best.centre.0, best.centre.1, b.centre.0, b.centre.1
        ));
    }
    let core = core_of(plane, ctx, &labels, best);
    let echoes = echoes_of(plane, ctx, &labels, &blobs, best);
    drop(labels);
    let hl = measure(plane, ctx, &core, &echoes, best.peak)?;
    let dominance = best.score / (best.score + second);
    let own = hl.own;
    if own < MIN_OWN {
        return Err(format!(
            "the highlight at ({:.0}, {:.0}) is mostly the environment's (only {:.0} % of its brightness is not in the other images); add an ambient image of the ball with the rig's lights off (ambient.png), or leave the image out with --skip-bad",
            hl.highlight.x,
            hl.highlight.y,
            100.0 * own
        ));
    }
    let behind = -MAX_BEHIND_DEG.to_radians().sin();
    if hl.highlight.direction[2] < behind {
        return Err(format!(
            "the highlight at ({:.0}, {:.0}) stands for a light {:.0}° behind the ball, which cannot light the object: a glint at the rim, or the circle is wrong (give --circle cx,cy,r)",
            hl.highlight.x,
            hl.highlight.y,
            -hl.highlight.direction[2].asin().to_degrees()
        ));
    }
    let support = (hl.highlight.pixels as f64 / 4.0).min(1.0);
    let clear = ((dominance - 0.5) / 0.4).clamp(0.0, 1.0);
    Ok(Highlight {
        confidence: clear * own.min(1.0) * support,
        ..hl.highlight
    })
}

/// The light's disc within its blob. Clipped: the clipped pixels (the group holding the
/// most light); a small core also takes the partly covered pixels on its edge, which carry
/// most of its sub-pixel position (on a large core their share is small, and the glare
/// beside a real highlight would bias them). Not clipped: the pixels down to a tenth of
/// the peak, joined to it.
fn core_of(plane: &Array2<u16>, ctx: &Context, labels: &Labels, blob: &Blob) -> Vec<Pixel> {
    let disc = Disc::new(ctx.circle, plane.dim());
    if blob.peak < ctx.clip {
        let tenth = 0.1 * blob.peak_residual;
        let keep = |p: (usize, usize)| residual(plane, ctx.env, p) >= tenth;
        return Labels::group_of(&disc, &keep, blob.top);
    }
    let keep = |p: (usize, usize)| labels.at(p) == blob.label && plane[p] >= ctx.clip;
    let clipped = Labels::of(&disc, &keep);
    let mut light = vec![0.0f64; clipped.count];
    for p in disc.pixels() {
        let l = clipped.at(p);
        if l > 0 {
            light[l as usize - 1] += residual(plane, ctx.env, p);
        }
    }
    // The last of equally bright groups, as `max_by` picks.
    let best = light
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map_or(0, |(i, _)| i as u32 + 1);
    let mut core: Vec<Pixel> = (disc.pixels())
        .filter(|&p| clipped.at(p) == best)
        .map(pixel)
        .collect();
    drop(clipped);
    if core.len() < SMALL_CORE {
        let inner: HashSet<Pixel> = core.iter().copied().collect();
        let mut edge = HashSet::new();
        for &(r, c) in &core {
            let (r, c) = (r as usize, c as usize);
            for (dr, dc) in [
                (-1, 0),
                (1, 0),
                (0, -1),
                (0, 1),
                (-1, -1),
                (-1, 1),
                (1, -1),
                (1, 1),
            ] {
                let (y, x) = (r as isize + dr, c as isize + dc);
                if y < 0 || x < 0 {
                    continue;
                }
                let p = (y as usize, x as usize);
                if p.0 < plane.dim().0
                    && p.1 < plane.dim().1
                    && disc.contains(p.0, p.1)
                    && !inner.contains(&pixel(p))
                {
                    edge.insert(pixel(p));
                }
            }
        }
        core.extend(edge);
    }
    core
}

/// The light's other reflections in a clipped image: the clipped pixels of the image's
/// other blobs of its own (mostly where no other image has a residual). A light also
/// shines on what stands near the ball, whose reflection clips beside the light's and
/// moves with it; the environment cannot explain it away, and the direction's median
/// gives it only its share.
fn echoes_of(
    plane: &Array2<u16>,
    ctx: &Context,
    labels: &Labels,
    blobs: &[Blob],
    best: &Blob,
) -> Vec<Pixel> {
    if best.peak < ctx.clip {
        return Vec::new();
    }
    let own: HashSet<u32> = blobs
        .iter()
        .filter(|b| b.label != best.label && b.peak >= ctx.clip && b.score > ECHO_OWN * b.light)
        .map(|b| b.label)
        .collect();
    if own.is_empty() {
        return Vec::new();
    }
    Disc::new(ctx.circle, plane.dim())
        .pixels()
        .filter(|&p| plane[p] >= ctx.clip && own.contains(&labels.at(p)))
        .map(pixel)
        .collect()
}

struct Measured {
    highlight: Highlight,
    /// Share of the core's brightness the environment does not explain.
    own: f64,
}

/// Direction, position and shape of a core, its echoes taking their share of the centre.
fn measure(
    plane: &Array2<u16>,
    ctx: &Context,
    core: &[Pixel],
    echoes: &[Pixel],
    peak: u16,
) -> Result<Measured, String> {
    let circle = ctx.circle;
    let (mut xs, mut ys, mut sw, mut total) = (Vec::new(), Vec::new(), 0.0, 0.0);
    for &(r, c) in core.iter().chain(echoes) {
        let (r, c) = (r as usize, c as usize);
        let wt = residual(plane, ctx.env, (r, c));
        xs.push((c as i64, wt));
        ys.push((r as i64, wt));
        sw += wt;
        total += plane[[r, c]] as f64;
    }
    if sw <= 0.0 {
        return Err("the highlight has no light above the environment".into());
    }
    let (x, y) = (weighted_median(&mut xs), weighted_median(&mut ys));
    let Some(direction) = ctx.camera.light_at(circle, x, y) else {
        return Err(format!(
            "the highlight's centre ({x:.0}, {y:.0}) is off the sphere; give --circle cx,cy,r"
        ));
    };
    let (elongation, radius_deg) = shape(core, circle, (x, y));
    Ok(Measured {
        highlight: Highlight {
            direction,
            x,
            y,
            pixels: core.len(),
            peak: peak as f64 / 65535.0,
            clipped: peak >= ctx.clip,
            rim_distance: circle.r - (x - circle.cx).hypot(y - circle.cy),
            elongation,
            radius_deg,
            confidence: 0.0,
        },
        own: sw / total.max(1.0),
    })
}

/// The weighted median of pixel coordinates, each pixel's weight spread evenly over its
/// width: sub-pixel, the centre of any symmetric blob, and moved by a stray part only by
/// its share of the light (a mean would follow it by its distance).
fn weighted_median(values: &mut [(i64, f64)]) -> f64 {
    values.sort_unstable_by_key(|v| v.0);
    let half = 0.5 * values.iter().map(|v| v.1).sum::<f64>();
    let mut seen = 0.0;
    let mut i = 0;
    while i < values.len() {
        let at = values[i].0;
        let mut mass = 0.0;
        while i < values.len() && values[i].0 == at {
            mass += values[i].1;
            i += 1;
        }
        if mass > 0.0 && seen + mass >= half {
            return at as f64 - 0.5 + (half - seen) / mass;
        }
        seen += mass;
    }
    values.last().map_or(0.0, |v| v.0 as f64)
}

/// Elongation and equivalent angular radius of a set of pixels in direction space: the
/// mirror map stretches an image blob along the outline and squeezes it towards the rim
/// by 1/n_z each way.
fn shape(pixels: &[Pixel], circle: &Circle, (mx, my): (f64, f64)) -> (f64, f64) {
    let n = pixels.len().max(1) as f64;
    // Image covariance, each pixel a unit square (variance 1/12 per axis).
    let (mut cxx, mut cyy, mut cxy) = (1.0 / 12.0, 1.0 / 12.0, 0.0);
    for &(r, c) in pixels {
        let (dx, dy) = (c as f64 - mx, r as f64 - my);
        cxx += dx * dx / n;
        cyy += dy * dy / n;
        cxy += dx * dy / n;
    }
    let (ox, oy) = (mx - circle.cx, my - circle.cy);
    let rho = ox.hypot(oy);
    let (ux, uy) = if rho > 1e-6 {
        (ox / rho, oy / rho)
    } else {
        (1.0, 0.0)
    };
    let (tx, ty) = (-uy, ux);
    let crr = ux * ux * cxx + 2.0 * ux * uy * cxy + uy * uy * cyy;
    let ctt = tx * tx * cxx + 2.0 * tx * ty * cxy + ty * ty * cyy;
    let crt = ux * tx * cxx + (ux * ty + uy * tx) * cxy + uy * ty * cyy;
    let (sr, st) = Camera::scales(circle, mx, my);
    let (a, b, d) = (crr * sr * sr, crt * sr * st, ctt * st * st);
    let mean = 0.5 * (a + d);
    let spread = (0.25 * (a - d).powi(2) + b * b).sqrt();
    let elongation = ((mean + spread) / (mean - spread).max(1e-12)).sqrt();
    let radius_deg = (n * sr * st / std::f64::consts::PI).sqrt().to_degrees();
    (elongation, radius_deg)
}

/// Groups of the disc's pixels that `keep` accepts, pixels within [`JOIN`] of each other
/// joined: a label per pixel of the disc's box (0: in no group; g: the g-th group found
/// in row-major order), 4 bytes a pixel whatever the groups.
struct Labels {
    map: Array2<u32>,
    r0: usize,
    c0: usize,
    count: usize,
}

impl Labels {
    fn of(disc: &Disc, keep: &dyn Fn((usize, usize)) -> bool) -> Self {
        let mut labels = Self {
            map: Array2::zeros((disc.r1 - disc.r0 + 1, disc.c1 - disc.c0 + 1)),
            r0: disc.r0,
            c0: disc.c0,
            count: 0,
        };
        let mut stack = Vec::new();
        for p in disc.pixels() {
            if labels.at(p) != 0 || !keep(p) {
                continue;
            }
            labels.count += 1;
            let label = labels.count as u32;
            labels.flood(disc, keep, p, label, &mut stack, &mut |_| {});
        }
        labels
    }

    /// The group of `keep`'s pixels holding `start`.
    fn group_of(
        disc: &Disc,
        keep: &dyn Fn((usize, usize)) -> bool,
        start: (usize, usize),
    ) -> Vec<Pixel> {
        let mut labels = Self {
            map: Array2::zeros((disc.r1 - disc.r0 + 1, disc.c1 - disc.c0 + 1)),
            r0: disc.r0,
            c0: disc.c0,
            count: 1,
        };
        let mut group = Vec::new();
        if keep(start) {
            labels.flood(disc, keep, start, 1, &mut Vec::new(), &mut |p| {
                group.push(pixel(p))
            });
        }
        group
    }

    fn at(&self, (r, c): (usize, usize)) -> u32 {
        self.map[[r - self.r0, c - self.c0]]
    }

    /// Label everything joined to `start` that `keep` accepts and is unlabelled (within
    /// the disc's box: `keep` says whether the disc itself bounds it).
    fn flood(
        &mut self,
        disc: &Disc,
        keep: &dyn Fn((usize, usize)) -> bool,
        start: (usize, usize),
        label: u32,
        stack: &mut Vec<(u32, u32)>,
        each: &mut dyn FnMut((usize, usize)),
    ) {
        self.map[[start.0 - self.r0, start.1 - self.c0]] = label;
        stack.push((start.0 as u32, start.1 as u32));
        while let Some((y, x)) = stack.pop() {
            each((y as usize, x as usize));
            for dy in -JOIN..=JOIN {
                for dx in -JOIN..=JOIN {
                    let (ny, nx) = (y as isize + dy, x as isize + dx);
                    if ny < disc.r0 as isize
                        || nx < disc.c0 as isize
                        || ny > disc.r1 as isize
                        || nx > disc.c1 as isize
                    {
                        continue;
                    }
                    let p = (ny as usize, nx as usize);
                    let s = &mut self.map[[p.0 - self.r0, p.1 - self.c0]];
                    if *s == 0 && keep(p) {
                        *s = label;
                        stack.push((p.0 as u32, p.1 as u32));
                    }
                }
            }
        }
    }
}

/// The median of values counted in `counts` (`total` of them), as `select_nth_unstable`
/// at `total / 2` gives it.
fn median_of_counts(counts: &[u32], total: usize) -> u16 {
    let k = total / 2;
    let mut seen = 0usize;
    for (v, &n) in counts.iter().enumerate() {
        seen += n as usize;
        if seen > k {
            return v as u16;
        }
    }
    0
}

#[cfg(test)]
mod tests {
    use super::weighted_median;

    #[test]
    fn weighted_median_is_sub_pixel_and_moved_by_a_stray_part_only_by_its_share() {
        // A symmetric run of pixels: its middle, between pixels.
        assert!((weighted_median(&mut [(3, 1.0), (4, 1.0)]) - 3.5).abs() < 1e-12);
        // A partly covered edge pixel moves it by less than half a pixel.
        let m = weighted_median(&mut [(3, 1.0), (4, 1.0), (5, 1.0), (6, 0.5)]);
        assert!((m - 4.25).abs() < 1e-12, "{m}");
        // A tenth of the light 100 px away moves the middle of 20 px (9.5) by 1 px, where a
        // mean would move 10 px.
        let mut v: Vec<(i64, f64)> = (0..20).map(|c| (c, 1.0)).collect();
        v.extend((120..122).map(|c| (c, 1.0)));
        assert!((weighted_median(&mut v) - 10.5).abs() < 1e-12);
    }
}
