//! Whether a set of lights can be solved: the conditioning of the stacked light matrix.

use super::light::Light;
use crate::core::error::InputError;

/// Refuse light sets whose normals cannot be solved reliably.
pub fn check_solvable(lights: &[Light], max_condition: f64) -> Result<f64, InputError> {
    let (condition, rank) = conditioning(lights);
    if rank < 3 {
        return Err(InputError::RankDeficient { rank });
    }
    if condition > max_condition {
        return Err(InputError::IllConditioned {
            condition,
            limit: max_condition,
        });
    }
    Ok(condition)
}

/// Condition number and numerical rank of the stacked (scaled) light matrix, from the
/// eigenvalues of LᵀL.
pub fn conditioning(lights: &[Light]) -> (f64, usize) {
    let mut m = [[0.0f64; 3]; 3];
    for l in lights {
        let s = l.scaled();
        for (r, row) in m.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v += s[r] * s[c];
            }
        }
    }
    let eig = crate::core::lambert::sym3_eigenvalues(&m);
    let max = eig[2].max(0.0);
    let rank = eig.iter().filter(|&&e| e > max * 1e-12 && e > 0.0).count();
    let min = eig[0].max(0.0);
    let cond = if min > 0.0 {
        (max / min).sqrt()
    } else {
        f64::INFINITY
    };
    (cond, rank)
}
