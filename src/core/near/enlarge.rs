//! A depth map of the shrunk grid ([`super::shrink`]) brought back to the images' pixels:
//! the first full-resolution surface, whose points give every pixel its light vectors.
//!
//! Depth off the shrunk mask is first filled from its neighbours, outward ring by ring,
//! so that every full-resolution pixel (the shrunk mask leaves out the blocks at the
//! object's outline) has a surface point near its own.

use ndarray::Array2;

/// Rings of neighbours the fill grows by before the rest takes the median depth: the
/// full-resolution mask lies within a block or two of the shrunk one.
const FILL_RINGS: usize = 8;

/// `depth` (NaN where unknown), on the grid of blocks of `factor × factor` pixels, to a
/// `height × width` image: bilinear between the blocks' centres, held at the edges.
pub fn enlarge(depth: &Array2<f32>, factor: usize, (height, width): (usize, usize)) -> Array2<f32> {
    let filled = fill(depth);
    let (ch, cw) = filled.dim();
    let f = factor as f32;
    let centre = (f - 1.0) / 2.0;
    let at = |p: usize, n: usize| {
        let x = ((p as f32 - centre) / f).clamp(0.0, (n - 1) as f32);
        let i = (x.floor() as usize).min(n.saturating_sub(2));
        (i, (i + 1).min(n - 1), x - i as f32)
    };
    let cols: Vec<(usize, usize, f32)> = (0..width).map(|c| at(c, cw)).collect();
    Array2::from_shape_fn((height, width), |(r, c)| {
        let (r0, r1, ty) = at(r, ch);
        let (c0, c1, tx) = cols[c];
        let top = filled[[r0, c0]] * (1.0 - tx) + filled[[r0, c1]] * tx;
        let bottom = filled[[r1, c0]] * (1.0 - tx) + filled[[r1, c1]] * tx;
        top * (1.0 - ty) + bottom * ty
    })
}

/// `depth` with every NaN replaced: by the mean of its known 8-neighbours, ring by ring
/// for up to [`FILL_RINGS`] rings, then by the median of what is known.
fn fill(depth: &Array2<f32>) -> Array2<f32> {
    let mut d = depth.clone();
    let (h, w) = d.dim();
    for _ in 0..FILL_RINGS {
        let next = Array2::from_shape_fn((h, w), |(r, c)| {
            if d[[r, c]].is_finite() {
                return d[[r, c]];
            }
            let (mut sum, mut n) = (0f32, 0);
            for y in r.saturating_sub(1)..(r + 2).min(h) {
                for x in c.saturating_sub(1)..(c + 2).min(w) {
                    if d[[y, x]].is_finite() {
                        sum += d[[y, x]];
                        n += 1;
                    }
                }
            }
            if n > 0 { sum / n as f32 } else { f32::NAN }
        });
        let done = next.iter().all(|v| v.is_finite());
        d = next;
        if done {
            return d;
        }
    }
    let mut known: Vec<f32> = d.iter().copied().filter(|v| v.is_finite()).collect();
    let median = if known.is_empty() {
        1.0
    } else {
        let k = known.len() / 2;
        *known.select_nth_unstable_by(k, f32::total_cmp).1
    };
    d.mapv_inplace(|v| if v.is_finite() { v } else { median });
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane tilted along the columns stays that plane, and the unknown corner is
    /// filled from its neighbours.
    #[test]
    fn a_plane_stays_a_plane() {
        let f = 4usize;
        let centre = (f as f32 - 1.0) / 2.0;
        let small = Array2::from_shape_fn((6, 8), |(r, c)| {
            if r == 0 && c == 0 {
                f32::NAN
            } else {
                100.0 + (c as f32 * f as f32 + centre) * 0.5
            }
        });
        let big = enlarge(&small, f, (24, 32));
        for c in 2..30 {
            let want = 100.0 + c as f32 * 0.5;
            assert!((big[[12, c]] - want).abs() < 1e-4, "{c}: {}", big[[12, c]]);
        }
        assert!(big.iter().all(|v| v.is_finite()));
    }
}
