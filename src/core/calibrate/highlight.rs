//! One image's highlight: the light's mirror image on the sphere, told apart from the
//! other bright things a chrome ball reflects, and its direction to sub-pixel accuracy.
//!
//! Candidates are the connected regions inside the sphere brighter than halfway between
//! the sphere's median and its brightest pixel. Each is judged by its shape in the space
//! of reflected directions (the mirror map stretches an image blob along the outline and
//! squeezes it towards the rim by 1/n_z each way, so a round light is round there): a
//! light is compact (elongation at most [`MAX_ELONGATION`]) and small (equivalent radius
//! at most [`MAX_RADIUS_DEG`]). Streaks and the mirrored room and objects are not. Of the
//! compact candidates the light is the brightest (clipped, or within 20 % of the
//! brightest peak) with the most light above the threshold; a second one as bright and
//! at least half as large makes the image ambiguous.
//!
//! The direction is the centroid in direction space: every pixel of the blob (and its
//! rim down to a tenth of the peak) contributes its reflected direction weighted by its
//! brightness above the local background. An orthographic mirror sphere maps equal image
//! areas to equal solid angles, so this is the centroid of the light's disc of directions,
//! unbiased by the squeeze near the rim.

use ndarray::Array2;

use super::Circle;
use super::mirror::{Camera, normalise};

/// Most elongation (ratio of the principal axes, in direction space) of a light's blob.
pub const MAX_ELONGATION: f64 = 3.0;
/// Largest equivalent angular radius of a light's blob, degrees.
pub const MAX_RADIUS_DEG: f64 = 8.0;

/// A highlight found in one image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Highlight {
    /// Unit light direction.
    pub direction: [f64; 3],
    /// Brightness-weighted centroid, pixels (0-based, pixel centres at integers).
    pub x: f64,
    pub y: f64,
    /// Pixels above the blob threshold.
    pub pixels: usize,
    /// Brightest value, fraction of full scale, and whether it is clipped.
    pub peak: f64,
    pub clipped: bool,
    /// Distance of the centroid from the outline, pixels.
    pub rim_distance: f64,
    pub elongation: f64,
    /// Equivalent angular radius of the blob, degrees.
    pub radius_deg: f64,
}

/// A bright region inside the sphere.
struct Blob {
    pixels: Vec<(usize, usize)>,
    peak: u16,
    energy: f64,
    elongation: f64,
    radius_deg: f64,
    centre: (f64, f64),
}

/// The highlight in `plane` on the sphere `circle`; `clip` is the value at and above
/// which a pixel counts as clipped. The error says what was found instead.
pub fn find(
    plane: &Array2<u16>,
    circle: &Circle,
    camera: &Camera,
    clip: u16,
) -> Result<Highlight, String> {
    let (h, w) = plane.dim();
    let inside =
        |r: usize, c: usize| (c as f64 - circle.cx).hypot(r as f64 - circle.cy) <= circle.r - 0.5;
    let r0 = (circle.cy - circle.r).floor().max(0.0) as usize;
    let r1 = ((circle.cy + circle.r).ceil() as usize).min(h - 1);
    let c0 = (circle.cx - circle.r).floor().max(0.0) as usize;
    let c1 = ((circle.cx + circle.r).ceil() as usize).min(w - 1);
    let mut values = Vec::new();
    let mut diffs = Vec::new();
    for r in r0..=r1 {
        for c in c0..=c1 {
            if inside(r, c) {
                values.push(plane[[r, c]]);
                if c > c0 && inside(r, c - 1) {
                    diffs.push(plane[[r, c]].abs_diff(plane[[r, c - 1]]));
                }
            }
        }
    }
    if values.len() < 20 {
        return Err("the sphere covers almost no pixels of the image".into());
    }
    let median = median_u16(&mut values.clone()) as f64;
    let peak = *values.iter().max().expect("not empty") as f64;
    let noise = 1.4826 * median_u16(&mut diffs) as f64 / std::f64::consts::SQRT_2;
    if peak - median < (10.0 * noise).max(0.02 * 65535.0) {
        return Err(format!(
            "no highlight: the brightest point on the sphere is only {:.3} of full scale above its median",
            (peak - median) / 65535.0
        ));
    }
    let threshold = median + 0.5 * (peak - median);
    let blobs = components(plane, (r0, r1, c0, c1), &inside, threshold, circle);
    let (lights, others): (Vec<&Blob>, Vec<&Blob>) = blobs
        .iter()
        .partition(|b| b.elongation <= MAX_ELONGATION && b.radius_deg <= MAX_RADIUS_DEG);
    if lights.is_empty() {
        let seen: Vec<String> = others
            .iter()
            .take(3)
            .map(|b| {
                format!(
                    "at ({:.0}, {:.0}) {:.1}° across, elongation {:.1}",
                    b.centre.0,
                    b.centre.1,
                    2.0 * b.radius_deg,
                    b.elongation
                )
            })
            .collect();
        return Err(format!(
            "no highlight: the bright regions on the sphere are too large or elongated to be a light ({})",
            seen.join("; ")
        ));
    }
    let top = lights.iter().map(|b| b.peak).max().expect("not empty");
    let bright = |b: &&&Blob| b.peak >= clip || b.peak as f64 >= 0.8 * top as f64;
    let mut contenders: Vec<&Blob> = lights.iter().filter(bright).copied().collect();
    contenders.sort_by(|a, b| b.energy.total_cmp(&a.energy));
    let best = contenders[0];
    if let Some(second) = contenders.get(1) {
        let as_bright = (second.peak >= clip && best.peak >= clip)
            || second.peak as f64 >= 0.9 * best.peak as f64;
        if as_bright && second.energy >= 0.5 * best.energy {
            return Err(format!(
                "two equally plausible highlights, at ({:.1}, {:.1}) and ({:.1}, {:.1})",
                best.centre.0, best.centre.1, second.centre.0, second.centre.1
            ));
        }
    }
    refine(plane, circle, camera, best, threshold, clip, &inside)
}

/// Connected (8-neighbour) regions of pixels at or above `threshold` inside the sphere,
/// with their shape measured in direction space.
fn components(
    plane: &Array2<u16>,
    (r0, r1, c0, c1): (usize, usize, usize, usize),
    inside: &dyn Fn(usize, usize) -> bool,
    threshold: f64,
    circle: &Circle,
) -> Vec<Blob> {
    let mut seen = Array2::from_elem(plane.dim(), false);
    let mut blobs = Vec::new();
    for r in r0..=r1 {
        for c in c0..=c1 {
            if seen[[r, c]] || !inside(r, c) || (plane[[r, c]] as f64) < threshold {
                continue;
            }
            let mut pixels = Vec::new();
            let mut stack = vec![(r, c)];
            seen[[r, c]] = true;
            while let Some((y, x)) = stack.pop() {
                pixels.push((y, x));
                for dy in -1isize..=1 {
                    for dx in -1isize..=1 {
                        let (ny, nx) = (y as isize + dy, x as isize + dx);
                        if ny < r0 as isize
                            || nx < c0 as isize
                            || ny > r1 as isize
                            || nx > c1 as isize
                        {
                            continue;
                        }
                        let (ny, nx) = (ny as usize, nx as usize);
                        if !seen[[ny, nx]] && inside(ny, nx) && plane[[ny, nx]] as f64 >= threshold
                        {
                            seen[[ny, nx]] = true;
                            stack.push((ny, nx));
                        }
                    }
                }
            }
            blobs.push(measure(plane, pixels, threshold, circle));
        }
    }
    blobs
}

fn measure(
    plane: &Array2<u16>,
    pixels: Vec<(usize, usize)>,
    threshold: f64,
    circle: &Circle,
) -> Blob {
    let n = pixels.len() as f64;
    let (mut sx, mut sy) = (0.0, 0.0);
    let (mut peak, mut energy) = (0u16, 0.0);
    for &(r, c) in &pixels {
        sx += c as f64;
        sy += r as f64;
        let v = plane[[r, c]];
        peak = peak.max(v);
        energy += v as f64 - threshold;
    }
    let (mx, my) = (sx / n, sy / n);
    // Image covariance, each pixel a unit square (variance 1/12 per axis).
    let (mut cxx, mut cyy, mut cxy) = (1.0 / 12.0, 1.0 / 12.0, 0.0);
    for &(r, c) in &pixels {
        let (dx, dy) = (c as f64 - mx, r as f64 - my);
        cxx += dx * dx / n;
        cyy += dy * dy / n;
        cxy += dx * dy / n;
    }
    // Into radial / tangential axes, scaled by the mirror map there.
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
    Blob {
        pixels,
        peak,
        energy,
        elongation,
        radius_deg,
        centre: (mx, my),
    }
}

/// The direction-space centroid of `blob` and its surroundings down to a tenth of its
/// peak above the local background (the median of a ring around it).
fn refine(
    plane: &Array2<u16>,
    circle: &Circle,
    camera: &Camera,
    blob: &Blob,
    threshold: f64,
    clip: u16,
    inside: &dyn Fn(usize, usize) -> bool,
) -> Result<Highlight, String> {
    let (h, w) = plane.dim();
    let (mut r0, mut r1, mut c0, mut c1) = (usize::MAX, 0, usize::MAX, 0);
    for &(r, c) in &blob.pixels {
        (r0, r1, c0, c1) = (r0.min(r), r1.max(r), c0.min(c), c1.max(c));
    }
    let grow = |lo: usize, hi: usize, by: usize, len: usize| {
        (lo.saturating_sub(by), (hi + by).min(len - 1))
    };
    let (ir0, ir1) = grow(r0, r1, 3, h);
    let (ic0, ic1) = grow(c0, c1, 3, w);
    let (or0, or1) = grow(r0, r1, 6, h);
    let (oc0, oc1) = grow(c0, c1, 6, w);
    let mut ring = Vec::new();
    for r in or0..=or1 {
        for c in oc0..=oc1 {
            let in_window = (ir0..=ir1).contains(&r) && (ic0..=ic1).contains(&c);
            if !in_window && inside(r, c) && (plane[[r, c]] as f64) < threshold {
                ring.push(plane[[r, c]]);
            }
        }
    }
    let base = if ring.is_empty() {
        threshold
    } else {
        median_u16(&mut ring) as f64
    };
    let floor = base + 0.1 * (blob.peak as f64 - base);
    let (mut sum, mut sx, mut sy, mut sw) = ([0.0; 3], 0.0, 0.0, 0.0);
    for r in ir0..=ir1 {
        for c in ic0..=ic1 {
            let v = plane[[r, c]] as f64;
            if !inside(r, c) || v < floor {
                continue;
            }
            let Some(d) = camera.light_at(circle, c as f64, r as f64) else {
                continue;
            };
            let wt = v - base;
            for k in 0..3 {
                sum[k] += wt * d[k];
            }
            sx += wt * c as f64;
            sy += wt * r as f64;
            sw += wt;
        }
    }
    if sw <= 0.0 {
        return Err("the highlight has no light above its surroundings".into());
    }
    let (x, y) = (sx / sw, sy / sw);
    Ok(Highlight {
        direction: normalise(sum),
        x,
        y,
        pixels: blob.pixels.len(),
        peak: blob.peak as f64 / 65535.0,
        clipped: blob.peak >= clip,
        rim_distance: circle.r - (x - circle.cx).hypot(y - circle.cy),
        elongation: blob.elongation,
        radius_deg: blob.radius_deg,
    })
}

fn median_u16(v: &mut [u16]) -> u16 {
    if v.is_empty() {
        return 0;
    }
    let k = v.len() / 2;
    *v.select_nth_unstable(k).1
}
