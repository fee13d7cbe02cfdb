//! The Lambertian image model and the 3×3 algebra its solves share: what a camera records
//! for albedo·normal `g` under a light ([`render_observation`]), least squares over the
//! lights ([`pseudo_inverse`], [`invert3`]), and the eigenvalues of LᵀL, which say how well
//! the lights pin a normal down ([`sym3_eigenvalues`]).

/// What the camera would record for albedo·normal `g` under light `l` with black level
/// `black`: attached shadows are black, and the sensor saturates at full scale.
pub fn render_observation(g: [f32; 3], l: [f32; 3], black: f32) -> f32 {
    ((g[0] * l[0] + g[1] * l[1] + g[2] * l[2]).max(0.0) + black).min(1.0)
}

/// (LᵀL)⁻¹Lᵀ as 3 rows of n coefficients.
pub fn pseudo_inverse(lights: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let mut m = [[0.0f64; 3]; 3];
    for l in lights {
        for r in 0..3 {
            for c in 0..3 {
                m[r][c] += l[r] as f64 * l[c] as f64;
            }
        }
    }
    let inv = invert3(&m).unwrap_or([[0.0; 3]; 3]);
    lights
        .iter()
        .map(|l| {
            let mut col = [0f32; 3];
            for (r, v) in col.iter_mut().enumerate() {
                *v = (0..3).map(|k| inv[r][k] * l[k] as f64).sum::<f64>() as f32;
            }
            col
        })
        .collect()
}

/// Inverse of a 3×3 matrix, or None when it is (numerically) singular.
pub fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c00 = m[1][1] * m[2][2] - m[1][2] * m[2][1];
    let c01 = m[1][2] * m[2][0] - m[1][0] * m[2][2];
    let c02 = m[1][0] * m[2][1] - m[1][1] * m[2][0];
    let det = m[0][0] * c00 + m[0][1] * c01 + m[0][2] * c02;
    let scale = m.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    if scale == 0.0 || det.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    let d = 1.0 / det;
    Some([
        [
            c00 * d,
            (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * d,
            (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * d,
        ],
        [
            c01 * d,
            (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * d,
            (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * d,
        ],
        [
            c02 * d,
            (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * d,
            (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * d,
        ],
    ])
}

/// Eigenvalues of a symmetric 3×3 matrix, ascending (closed form).
pub fn sym3_eigenvalues(m: &[[f64; 3]; 3]) -> [f64; 3] {
    let p1 = m[0][1].powi(2) + m[0][2].powi(2) + m[1][2].powi(2);
    let tr = m[0][0] + m[1][1] + m[2][2];
    if p1 == 0.0 {
        let mut e = [m[0][0], m[1][1], m[2][2]];
        e.sort_by(f64::total_cmp);
        return e;
    }
    let q = tr / 3.0;
    let p2 = (m[0][0] - q).powi(2) + (m[1][1] - q).powi(2) + (m[2][2] - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    let b = |r: usize, c: usize| (m[r][c] - if r == c { q } else { 0.0 }) / p;
    let det_b = b(0, 0) * (b(1, 1) * b(2, 2) - b(1, 2) * b(2, 1))
        - b(0, 1) * (b(1, 0) * b(2, 2) - b(1, 2) * b(2, 0))
        + b(0, 2) * (b(1, 0) * b(2, 1) - b(1, 1) * b(2, 0));
    let phi = (det_b / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    let e_max = q + 2.0 * p * phi.cos();
    let e_min = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
    let e_mid = tr - e_max - e_min;
    [e_min, e_mid, e_max]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eigenvalues_and_inverse_agree_with_definitions() {
        let m = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let e = sym3_eigenvalues(&m);
        assert!((e.iter().sum::<f64>() - 9.0).abs() < 1e-9);
        let inv = invert3(&m).unwrap();
        for r in 0..3 {
            for c in 0..3 {
                let v: f64 = (0..3).map(|k| m[r][k] * inv[k][c]).sum();
                assert!((v - if r == c { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        let det: f64 = e.iter().product();
        let direct = 4.0 * (3.0 * 2.0 - 0.04) - 1.0 * (2.0 - 0.1) + 0.5 * (0.2 - 1.5);
        assert!((det - direct).abs() < 1e-9);
        assert!(invert3(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]).is_none());
    }
}
