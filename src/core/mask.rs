//! Which pixels are the object: a given mask, every pixel, or a threshold on albedo with
//! holes filled and specks dropped.

use std::collections::VecDeque;

use ndarray::Array2;

use super::InputError;
use super::options::MaskMode;

/// Lowest auto-mask threshold: below one 8-bit step, albedo is indistinguishable from 0.
const MIN_THRESHOLD: f32 = 1.0 / 255.0;
/// The auto threshold, as a fraction of the object's robust (99th percentile) albedo.
const RELATIVE_THRESHOLD: f32 = 0.1;
/// Auto-mask components smaller than this fraction of the largest are noise.
const SPECK_FRACTION: f64 = 0.005;

/// Build the mask. A supplied mask is used unless the mode is `none`; `given` without
/// one is an error. Pixels of zero albedo are background, except holes the auto mask fills.
pub fn build(
    mode: MaskMode,
    albedo: &Array2<f32>,
    given: Option<&Array2<bool>>,
) -> Result<Array2<bool>, InputError> {
    let lit = albedo.mapv(|a| a > 0.0);
    match (mode, given) {
        (MaskMode::None, _) => Ok(lit),
        (MaskMode::Given | MaskMode::Auto, Some(m)) => Ok(&lit & m),
        (MaskMode::Given, None) => Err(InputError::Mask(
            "mask mode `given` needs a mask image, and none was supplied".into(),
        )),
        (MaskMode::Auto, None) => Ok(auto(albedo)),
    }
}

/// Threshold at a tenth of the 99th-percentile albedo, drop specks, fill holes.
pub fn auto(albedo: &Array2<f32>) -> Array2<bool> {
    let t = auto_threshold(albedo);
    let raw = albedo.mapv(|a| a > t);
    fill_holes(&drop_specks(&raw))
}

/// The albedo threshold `auto` uses: Otsu's split of the albedo histogram when it
/// separates a dark background from a bright object (class means at least 2.5× apart),
/// else a tenth of the 99th-percentile albedo (an object filling the frame, or one on
/// a black background with nothing to split).
pub fn auto_threshold(albedo: &Array2<f32>) -> f32 {
    let mut v: Vec<f32> = albedo
        .iter()
        .copied()
        .filter(|a| a.is_finite() && *a > 0.0)
        .collect();
    if v.is_empty() {
        return MIN_THRESHOLD;
    }
    let k = ((v.len() - 1) as f64 * 0.99) as usize;
    let p99 = *v.select_nth_unstable_by(k, f32::total_cmp).1;
    let relative = (RELATIVE_THRESHOLD * p99).max(MIN_THRESHOLD);
    match otsu(albedo.iter().copied(), p99) {
        Some((t, low, high)) if low * 2.5 <= high => t.max(relative),
        _ => relative,
    }
}

/// Otsu's threshold over [0, top] in 256 bins: (threshold, low-class mean, high-class mean).
fn otsu(values: impl Iterator<Item = f32>, top: f32) -> Option<(f32, f64, f64)> {
    const BINS: usize = 256;
    if top <= 0.0 {
        return None;
    }
    let mut hist = [0u64; BINS];
    for v in values.filter(|v| v.is_finite()) {
        hist[((v / top).clamp(0.0, 1.0) * (BINS - 1) as f32) as usize] += 1;
    }
    let total: u64 = hist.iter().sum();
    let sum: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &h)| i as f64 * h as f64)
        .sum();
    let (mut w0, mut s0, mut best) = (0u64, 0f64, None::<(f64, usize, f64, f64)>);
    for (i, &h) in hist.iter().enumerate().take(BINS - 1) {
        w0 += h;
        s0 += i as f64 * h as f64;
        let w1 = total - w0;
        if w0 == 0 || w1 == 0 {
            continue;
        }
        let (m0, m1) = (s0 / w0 as f64, (sum - s0) / w1 as f64);
        let between = w0 as f64 * w1 as f64 * (m0 - m1).powi(2);
        if best.is_none_or(|b| between > b.0) {
            best = Some((between, i, m0, m1));
        }
    }
    let (_, i, m0, m1) = best?;
    let scale = top as f64 / (BINS - 1) as f64;
    Some((
        (i as f64 + 1.0) as f32 * scale as f32,
        m0 * scale,
        m1 * scale,
    ))
}

/// Label 4-connected components of `true` pixels; returns labels (0 = none) and sizes.
pub fn components(mask: &Array2<bool>) -> (Array2<u32>, Vec<usize>) {
    let (rows, cols) = mask.dim();
    let mut labels = Array2::<u32>::zeros((rows, cols));
    let mut sizes = vec![0usize];
    let mut queue = VecDeque::new();
    for r in 0..rows {
        for c in 0..cols {
            if !mask[[r, c]] || labels[[r, c]] != 0 {
                continue;
            }
            let label = sizes.len() as u32;
            let mut size = 0;
            labels[[r, c]] = label;
            queue.push_back((r, c));
            while let Some((y, x)) = queue.pop_front() {
                size += 1;
                for (ny, nx) in neighbours(y, x, rows, cols) {
                    if mask[[ny, nx]] && labels[[ny, nx]] == 0 {
                        labels[[ny, nx]] = label;
                        queue.push_back((ny, nx));
                    }
                }
            }
            sizes.push(size);
        }
    }
    (labels, sizes)
}

fn neighbours(
    r: usize,
    c: usize,
    rows: usize,
    cols: usize,
) -> impl Iterator<Item = (usize, usize)> {
    let up = (r > 0).then(|| (r - 1, c));
    let down = (r + 1 < rows).then(|| (r + 1, c));
    let left = (c > 0).then(|| (r, c - 1));
    let right = (c + 1 < cols).then(|| (r, c + 1));
    [up, down, left, right].into_iter().flatten()
}

fn drop_specks(mask: &Array2<bool>) -> Array2<bool> {
    let (labels, sizes) = components(mask);
    let largest = sizes.iter().copied().max().unwrap_or(0);
    let min = ((largest as f64 * SPECK_FRACTION) as usize).max(1);
    labels.mapv(|l| l != 0 && sizes[l as usize] >= min)
}

/// Background pixels not connected to the image border become object.
pub fn fill_holes(mask: &Array2<bool>) -> Array2<bool> {
    let (rows, cols) = mask.dim();
    let mut outside = Array2::from_elem((rows, cols), false);
    let mut queue = VecDeque::new();
    for r in 0..rows {
        for c in 0..cols {
            let border = r == 0 || c == 0 || r + 1 == rows || c + 1 == cols;
            if border && !mask[[r, c]] {
                outside[[r, c]] = true;
                queue.push_back((r, c));
            }
        }
    }
    while let Some((y, x)) = queue.pop_front() {
        for (ny, nx) in neighbours(y, x, rows, cols) {
            if !mask[[ny, nx]] && !outside[[ny, nx]] {
                outside[[ny, nx]] = true;
                queue.push_back((ny, nx));
            }
        }
    }
    outside.mapv(|o| !o)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disc(n: usize, r: f32, hole: f32) -> Array2<f32> {
        Array2::from_shape_fn((n, n), |(y, x)| {
            let d =
                ((x as f32 - n as f32 / 2.0).powi(2) + (y as f32 - n as f32 / 2.0).powi(2)).sqrt();
            if d < hole {
                0.0
            } else if d < r {
                0.8
            } else {
                0.002
            }
        })
    }

    #[test]
    fn auto_mask_is_one_disc_with_holes_filled() {
        let mut a = disc(64, 20.0, 4.0);
        a[[2, 2]] = 0.9; // a bright speck in the background
        let m = auto(&a);
        let (_, sizes) = components(&m);
        assert_eq!(sizes.len(), 2, "one component: {sizes:?}");
        assert!(m[[32, 32]], "hole filled");
        assert!(!m[[2, 2]] && !m[[0, 0]]);
    }

    #[test]
    fn modes() {
        let a = disc(16, 5.0, 0.0);
        let given = Array2::from_elem((16, 16), true);
        assert_eq!(
            build(MaskMode::None, &a, None)
                .unwrap()
                .iter()
                .filter(|&&b| b)
                .count(),
            256
        );
        assert!(
            build(MaskMode::Given, &a, None)
                .unwrap_err()
                .to_string()
                .contains("given")
        );
        assert_eq!(build(MaskMode::Auto, &a, Some(&given)).unwrap(), given);
    }
}
