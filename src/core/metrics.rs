//! Accuracy against ground truth, shared by the tests and `photostereo evaluate`.
//!
//! Depth is scored the field's way ([`depth_error`]): an orthographic height map is known
//! up to an offset, a perspective depth map up to a scale, so the estimate is first
//! aligned to the truth by the median of their differences or of their ratios (robust to
//! the few pixels a step or a silhouette throws off), then the mean absolute error (under
//! a camera, the MADE of the normal-integration literature) and the RMS are taken.

use ndarray::Array2;
use serde::Serialize;

use super::reconstruction::Reconstruction;
use super::synth::Truth;

/// Errors of one reconstruction over a region.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Accuracy {
    /// Mean angle between recovered and true normals, degrees.
    pub mean_deg: f64,
    pub median_deg: f64,
    /// Depth RMS in pixels after removing the mean offset.
    pub depth_rms: f64,
}

/// Compare over `region` (true = counted).
pub fn accuracy(rec: &Reconstruction, truth: &Truth, region: &Array2<bool>) -> Accuracy {
    let mut angles = Vec::new();
    let mut diffs = Vec::new();
    for ((r, c), &inside) in region.indexed_iter() {
        if !inside {
            continue;
        }
        let dot: f64 = (0..3)
            .map(|k| rec.normals[[r, c, k]] as f64 * truth.normals[[r, c, k]] as f64)
            .sum();
        angles.push(dot.clamp(-1.0, 1.0).acos().to_degrees());
        diffs.push(rec.heights[[r, c]] as f64 - truth.depth[[r, c]] as f64);
    }
    if angles.is_empty() {
        return Accuracy {
            mean_deg: f64::NAN,
            median_deg: f64::NAN,
            depth_rms: f64::NAN,
        };
    }
    let n = angles.len() as f64;
    let mean_deg = angles.iter().sum::<f64>() / n;
    let k = angles.len() / 2;
    let median_deg = *angles.select_nth_unstable_by(k, f64::total_cmp).1;
    let offset = diffs.iter().sum::<f64>() / n;
    let depth_rms = (diffs.iter().map(|d| (d - offset).powi(2)).sum::<f64>() / n).sqrt();
    Accuracy {
        mean_deg,
        median_deg,
        depth_rms,
    }
}

/// How an estimate is aligned to the truth before its errors are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Align {
    /// Heights (orthographic): plus the offset `median(true − estimated)`.
    Offset,
    /// Depth (under a camera): times the scale `median(true / estimated)`.
    Scale,
}

/// Depth errors after alignment, in the truth's unit (pixels for heights).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct DepthError {
    /// Mean absolute error (MADE when aligned by scale).
    pub mean_abs: f64,
    pub rms: f64,
}

/// The errors of `estimate` against `truth` over `region`, after aligning it by `align`.
/// Pixels where either is not finite (or, by scale, the estimate is 0) are left out; NaN
/// when none is left.
pub fn depth_error(
    estimate: &Array2<f32>,
    truth: &Array2<f32>,
    region: &Array2<bool>,
    align: Align,
) -> DepthError {
    let pairs: Vec<(f64, f64)> = (estimate.iter().zip(truth).zip(region))
        .filter(|(_, inside)| **inside)
        .map(|((&e, &t), _)| (f64::from(e), f64::from(t)))
        .filter(|(e, t)| e.is_finite() && t.is_finite() && (align == Align::Offset || *e != 0.0))
        .collect();
    if pairs.is_empty() {
        return DepthError {
            mean_abs: f64::NAN,
            rms: f64::NAN,
        };
    }
    let mut fits: Vec<f64> = match align {
        Align::Offset => pairs.iter().map(|(e, t)| t - e).collect(),
        Align::Scale => pairs.iter().map(|(e, t)| t / e).collect(),
    };
    let k = fits.len() / 2;
    let fit = *fits.select_nth_unstable_by(k, f64::total_cmp).1;
    let aligned = |e: f64| match align {
        Align::Offset => e + fit,
        Align::Scale => e * fit,
    };
    let n = pairs.len() as f64;
    let (abs, sq) = pairs.iter().fold((0.0, 0.0), |(abs, sq), &(e, t)| {
        let d = aligned(e) - t;
        (abs + d.abs(), sq + d * d)
    });
    DepthError {
        mean_abs: abs / n,
        rms: (sq / n).sqrt(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_is_aligned_by_the_median_offset_or_scale() {
        let region = Array2::from_shape_fn((2, 3), |(r, c)| (r, c) != (1, 2));
        let truth =
            Array2::from_shape_vec((2, 3), vec![2.0, 4.0, 6.0, 8.0, 10.0, f32::NAN]).unwrap();
        // Half the truth everywhere: exact once scaled, off by a varying amount when shifted.
        let half = truth.mapv(|t| t / 2.0);
        let scaled = depth_error(&half, &truth, &region, Align::Scale);
        assert!(scaled.mean_abs < 1e-12 && scaled.rms < 1e-12, "{scaled:?}");
        let shifted = depth_error(&half, &truth, &region, Align::Offset);
        // Differences 1..5, median 3: errors 2, 1, 0, 1, 2.
        assert!((shifted.mean_abs - 1.2).abs() < 1e-12, "{shifted:?}");
        assert!((shifted.rms - 2.0f64.sqrt()).abs() < 1e-12, "{shifted:?}");
        // One wild pixel moves neither median.
        let mut wild = half.clone();
        wild[[0, 0]] = 100.0;
        let e = depth_error(&wild, &truth, &region, Align::Scale);
        assert!((e.mean_abs - 198.0 / 5.0).abs() < 1e-9, "{e:?}");
        let none = Array2::from_elem((2, 3), false);
        assert!(
            depth_error(&half, &truth, &none, Align::Offset)
                .rms
                .is_nan()
        );
    }
}
