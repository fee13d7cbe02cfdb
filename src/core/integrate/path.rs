//! The seed's naive path integration, kept for parity with the original tool.
//!
//! One path per pixel: down the first column with `q`, then along the row with `p`.
//! Every gradient error is accumulated along the path and rows are never reconciled with
//! each other, so noise turns into streaks; it is here as a baseline, not a recommendation.

/// Heights (row-major `h × w`) by path integration; pixels off the mask get 0 during the
/// pass, so the path restarts from 0 after every gap.
pub(super) fn integrate(p: &[f32], q: &[f32], mask: &[bool], h: usize, w: usize) -> Vec<f32> {
    let mut z = vec![0.0f32; h * w];
    for i in 0..h {
        let s = i * w;
        if w == 0 {
            break;
        }
        z[s] = if i == 0 || !mask[s] {
            0.0
        } else {
            z[s - w] + q[s]
        };
        for j in 1..w {
            z[s + j] = if mask[s + j] {
                z[s + j - 1] + p[s + j]
            } else {
                0.0
            };
        }
    }
    z
}
