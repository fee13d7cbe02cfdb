//! Which pixels are the object: a given mask, every pixel, or a threshold on albedo with
//! holes filled and specks dropped.

use ndarray::Array2;

use super::error::InputError;
use super::histogram::{histogram, nth_nonnegative};
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
    let lit = || albedo.mapv(|a| a > 0.0);
    match (mode, given) {
        (MaskMode::None, _) => Ok(lit()),
        (MaskMode::Given | MaskMode::Auto, Some(m)) => Ok(&lit() & m),
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
    let values = super::arrays::contiguous(albedo.view());
    let Some(p99) = positive_quantile(&values, 0.99) else {
        return MIN_THRESHOLD;
    };
    let relative = (RELATIVE_THRESHOLD * p99).max(MIN_THRESHOLD);
    match otsu(&values, p99) {
        Some((t, low, high)) if low * 2.5 <= high => t.max(relative),
        _ => relative,
    }
}

/// The `q`-quantile of the positive finite values: the element of rank
/// `⌊(n − 1)·q⌋` in sorted order, exactly, `None` when there are none.
fn positive_quantile(values: &[f32], q: f64) -> Option<f32> {
    let positive = |i: usize| Some(values[i]).filter(|v| v.is_finite() && *v > 0.0);
    nth_nonnegative(values.len(), positive, |n| ((n - 1) as f64 * q) as u64)
}

/// Otsu's threshold over [0, top] in 256 bins: (threshold, low-class mean, high-class mean).
fn otsu(values: &[f32], top: f32) -> Option<(f32, f64, f64)> {
    const BINS: usize = 256;
    if top <= 0.0 {
        return None;
    }
    let hist = histogram(values.len(), BINS, |i| {
        let v = values[i];
        v.is_finite()
            .then(|| ((v / top).clamp(0.0, 1.0) * (BINS - 1) as f32) as usize)
    });
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

/// Label 4-connected components of `true` pixels; returns labels (0 = none, numbered in
/// raster order of each component's first pixel) and sizes (index 0 unused).
pub fn components(mask: &Array2<bool>) -> (Array2<u32>, Vec<usize>) {
    let (rows, cols) = mask.dim();
    let runs = Runs::of(mask, true);
    let mut labels = Array2::<u32>::zeros((rows, cols));
    for (run, &label) in runs.runs.iter().zip(&runs.label) {
        labels
            .row_mut(run.row)
            .slice_mut(ndarray::s![run.start..run.end])
            .fill(label);
    }
    (labels, runs.sizes)
}

/// One horizontal run of equal pixels.
struct Run {
    row: usize,
    start: usize,
    end: usize,
}

/// Connected components over row runs (union–find of runs overlapping the previous
/// row's): linear in the frame, but with one entry per run rather than a per-pixel queue.
struct Runs {
    runs: Vec<Run>,
    /// Component of each run, from 1, in raster order of first appearance.
    label: Vec<u32>,
    /// Pixels per component (index 0 unused).
    sizes: Vec<usize>,
}

impl Runs {
    /// Components of the pixels equal to `value`.
    fn of(mask: &Array2<bool>, value: bool) -> Self {
        let cols = mask.ncols();
        let mut runs: Vec<Run> = Vec::new();
        let mut parent: Vec<u32> = Vec::new();
        let mut prev = 0..0; // the previous row's runs
        for (r, line) in mask.rows().into_iter().enumerate() {
            let first = runs.len();
            let mut c = 0;
            while c < cols {
                if line[c] != value {
                    c += 1;
                    continue;
                }
                let start = c;
                while c < cols && line[c] == value {
                    c += 1;
                }
                let me = runs.len() as u32;
                runs.push(Run {
                    row: r,
                    start,
                    end: c,
                });
                parent.push(me);
                // Previous-row runs overlapping [start, c) share the component.
                for k in prev.clone() {
                    let above: &Run = &runs[k];
                    if above.end <= start {
                        continue;
                    }
                    if above.start >= c {
                        break;
                    }
                    union(&mut parent, k as u32, me);
                }
            }
            prev = first..runs.len();
        }
        let mut label = vec![0u32; runs.len()];
        let mut root_label = vec![0u32; runs.len()];
        let mut sizes = vec![0usize];
        for (i, run) in runs.iter().enumerate() {
            let root = find(&mut parent, i as u32) as usize;
            if root_label[root] == 0 {
                root_label[root] = sizes.len() as u32;
                sizes.push(0);
            }
            label[i] = root_label[root];
            sizes[label[i] as usize] += run.end - run.start;
        }
        Self { runs, label, sizes }
    }

    /// A mask of the runs whose component passes `keep`, over `base` (pixels set there
    /// stay set).
    fn paint(&self, base: Array2<bool>, keep: impl Fn(u32) -> bool) -> Array2<bool> {
        let mut out = base;
        for (run, &label) in self.runs.iter().zip(&self.label) {
            if keep(label) {
                out.row_mut(run.row)
                    .slice_mut(ndarray::s![run.start..run.end])
                    .fill(true);
            }
        }
        out
    }
}

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let up = parent[parent[i as usize] as usize];
        parent[i as usize] = up;
        i = up;
    }
    i
}

fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    // The older run's root wins, so roots stay the earliest run of their component.
    if ra < rb {
        parent[rb as usize] = ra;
    } else if rb < ra {
        parent[ra as usize] = rb;
    }
}

fn drop_specks(mask: &Array2<bool>) -> Array2<bool> {
    let runs = Runs::of(mask, true);
    let largest = runs.sizes.iter().copied().max().unwrap_or(0);
    let min = ((largest as f64 * SPECK_FRACTION) as usize).max(1);
    runs.paint(Array2::from_elem(mask.dim(), false), |l| {
        runs.sizes[l as usize] >= min
    })
}

/// Background pixels not connected to the image border become object.
pub fn fill_holes(mask: &Array2<bool>) -> Array2<bool> {
    let (rows, cols) = mask.dim();
    let background = Runs::of(mask, false);
    let mut touches = vec![false; background.sizes.len()];
    for (run, &label) in background.runs.iter().zip(&background.label) {
        if run.row == 0 || run.row + 1 == rows || run.start == 0 || run.end == cols {
            touches[label as usize] = true;
        }
    }
    background.paint(mask.clone(), |l| !touches[l as usize])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rank-⌊(n − 1)q⌋ positive finite value, by sorting.
    fn sorted_quantile(values: &[f32], q: f64) -> Option<f32> {
        let mut v: Vec<f32> = (values.iter().copied())
            .filter(|a| a.is_finite() && *a > 0.0)
            .collect();
        v.sort_by(f32::total_cmp);
        (!v.is_empty()).then(|| v[((v.len() - 1) as f64 * q) as usize])
    }

    #[test]
    fn quantile_by_histograms_is_the_sorted_one() {
        // Deterministic pseudo-random values with ties, zeros, negatives and non-finite ones.
        let mut x = 0x2545_f491_u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        let special = [0.0, -0.5, f32::NAN, f32::INFINITY, 1e-30, 0.25, 0.25];
        for len in [0, 1, 2, 7, 1000, 200_000] {
            let values: Vec<f32> = (0..len)
                .map(|i| match next() % 10 {
                    0 => special[i % special.len()],
                    _ => (next() % 100_000) as f32 / 37_000.0,
                })
                .collect();
            for q in [0.0, 0.5, 0.99, 1.0] {
                assert_eq!(
                    positive_quantile(&values, q).map(f32::to_bits),
                    sorted_quantile(&values, q).map(f32::to_bits),
                    "{len} values, q = {q}"
                );
            }
        }
        assert_eq!(positive_quantile(&[3.0; 5000], 0.99), Some(3.0));
        assert_eq!(positive_quantile(&[0.0, -1.0, f32::NAN], 0.99), None);
    }

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

    /// Flood-fill references for the run-based labelling.
    fn reference(mask: &Array2<bool>) -> (Array2<u32>, Vec<usize>, Array2<bool>) {
        let (rows, cols) = mask.dim();
        let near = |r: usize, c: usize| {
            [
                (r > 0).then(|| (r - 1, c)),
                (r + 1 < rows).then(|| (r + 1, c)),
                (c > 0).then(|| (r, c - 1)),
                (c + 1 < cols).then(|| (r, c + 1)),
            ]
            .into_iter()
            .flatten()
        };
        let mut labels = Array2::<u32>::zeros((rows, cols));
        let mut sizes = vec![0];
        for start in (0..rows).flat_map(|r| (0..cols).map(move |c| (r, c))) {
            if !mask[start] || labels[start] != 0 {
                continue;
            }
            let label = sizes.len() as u32;
            labels[start] = label;
            let (mut stack, mut size) = (vec![start], 0);
            while let Some((r, c)) = stack.pop() {
                size += 1;
                for n in near(r, c) {
                    if mask[n] && labels[n] == 0 {
                        labels[n] = label;
                        stack.push(n);
                    }
                }
            }
            sizes.push(size);
        }
        let mut outside = Array2::from_elem((rows, cols), false);
        let mut stack: Vec<_> = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (r, c)))
            .filter(|&(r, c)| (r == 0 || c == 0 || r + 1 == rows || c + 1 == cols) && !mask[[r, c]])
            .collect();
        stack.iter().for_each(|&p| outside[p] = true);
        while let Some((r, c)) = stack.pop() {
            for n in near(r, c) {
                if !mask[n] && !outside[n] {
                    outside[n] = true;
                    stack.push(n);
                }
            }
        }
        (labels, sizes, outside.mapv(|o| !o))
    }

    #[test]
    fn run_components_match_a_flood_fill() {
        let mut seed = 0x2545_f491_u64;
        for density in [0.2, 0.45, 0.6, 0.8] {
            for _ in 0..20 {
                let mask = Array2::from_shape_fn((19, 23), |_| {
                    seed = seed
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    ((seed >> 33) as f64 / (1u64 << 31) as f64) < density
                });
                let (labels, sizes, filled) = reference(&mask);
                assert_eq!(components(&mask), (labels, sizes));
                assert_eq!(fill_holes(&mask), filled);
            }
        }
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
