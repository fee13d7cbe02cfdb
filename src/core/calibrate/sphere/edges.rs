//! Edge points (the sphere's notes, step 1): gradient maxima along the gradient above a
//! threshold relative to the image's own gradients, each with its sub-pixel position and
//! unit gradient direction.

use ndarray::Array2;

use super::filter::parabola_peak;

/// Most edge points kept (the strongest).
const MAX_EDGES: usize = 60_000;

/// An edge point: sub-pixel position and unit gradient direction.
#[derive(Debug, Clone, Copy)]
pub(super) struct Edge {
    pub(super) x: f32,
    pub(super) y: f32,
    pub(super) ux: f32,
    pub(super) uy: f32,
}

/// [`edge_points`]' threshold from the gradients of about a million pixels on a grid.
pub(super) fn sampled_threshold(smooth: &Array2<f32>) -> f32 {
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

/// Gradient maxima along the gradient above the threshold, and the threshold: a tenth of
/// the 99th percentile of the gradient magnitude, and at least three times its median
/// (the noise), divided by `downscaled` (the image's downscaling factor, 1 at full
/// resolution; see [`fit_outline_downscaled`](super::fit_outline_downscaled)).
pub(super) fn edge_points(gx: &Array2<f32>, gy: &Array2<f32>, downscaled: f32) -> (Vec<Edge>, f32) {
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
            let t = parabola_peak(before.into(), m.into(), after.into()) as f32;
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
