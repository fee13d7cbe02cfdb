//! The outline search's image filters: a separable Gaussian blur (of a float image, or of
//! a 16-bit one a row at a time), Sobel gradients, and bilinear sampling.

use ndarray::Array2;

/// [`gaussian`] of `image` scaled to [0, 1], a row at a time (the horizontal pass kept
/// for the rows the vertical pass needs), so only the result is held.
pub(super) fn gaussian_u16(image: &Array2<u16>, sigma: f64) -> Array2<f32> {
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

/// Separable Gaussian blur, clamped at the borders.
pub(super) fn gaussian(a: &Array2<f32>, sigma: f64) -> Array2<f32> {
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
pub(super) fn gradients(a: &Array2<f32>) -> (Array2<f32>, Array2<f32>) {
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

pub(super) fn bilinear(a: &Array2<f32>, x: f64, y: f64) -> f64 {
    let (c0, r0) = (x.floor() as usize, y.floor() as usize);
    let (fx, fy) = (x - c0 as f64, y - r0 as f64);
    let p = |r: usize, c: usize| a[[r, c]] as f64;
    (p(r0, c0) * (1.0 - fx) + p(r0, c0 + 1) * fx) * (1.0 - fy)
        + (p(r0 + 1, c0) * (1.0 - fx) + p(r0 + 1, c0 + 1) * fx) * fy
}

/// Where a sampled peak lies between its neighbours, in samples from the middle one
/// (−½..½): the vertex of the parabola through the three values; 0 where they do not bend
/// down.
pub(super) fn parabola_peak(before: f64, peak: f64, after: f64) -> f64 {
    let curvature = before - 2.0 * peak + after;
    if curvature < 0.0 {
        (0.5 * (before - after) / curvature).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}
