//! The set-level warnings the robust solve adds to `result.json`.

use super::estimate::CaptureEstimate;

/// Set-level warnings for `result.json`: estimates that the capture makes implausible,
/// and a solve where most of the object fell back to least squares.
pub fn warnings(
    estimate: Option<&CaptureEstimate>,
    unreliable: usize,
    object: usize,
) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(e) = estimate {
        if e.noise_sigma > 0.25 * e.lit_median {
            out.push(format!(
                "estimated noise sigma {:.5} is over a quarter of the median lit observation {:.5} \
                 (fractions of full scale): the images are very dark or very noisy, so shadows \
                 and highlights are hard to tell from noise",
                e.noise_sigma, e.lit_median
            ));
        }
        if e.black_level > 0.5 * e.lit_median {
            out.push(format!(
                "estimated black level {:.5} is over half the median lit observation {:.5}: \
                 check the exposure, or subtract a dark frame before uploading",
                e.black_level, e.lit_median
            ));
        }
    }
    if object > 0 && 2 * unreliable > object {
        out.push(format!(
            "{unreliable} of {object} object pixels ({:.0} %) fell back to least squares over all \
             their observations (see unreliable.png): too few observations fit the Lambertian \
             model there (too few lights reach them, or shadows and highlights dominate)",
            100.0 * unreliable as f64 / object as f64
        ));
    }
    out
}
