//! Accuracy against ground truth, shared by the tests and `photostereo evaluate`.

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
