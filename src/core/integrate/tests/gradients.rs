//! Gradients from normals and their curl: zero for surfaces, the same edge slopes as the
//! Poisson right-hand side, grazing normals clamped.

use ndarray::{Array2, Array3};

use super::surfaces::*;
use crate::core::integrate::multigrid::MaskStencil;
use crate::core::integrate::*;

#[test]
fn curl_is_zero_for_surfaces_and_two_for_rotation() {
    let full = Array2::from_elem((64, 64), true);
    let (p, q) = gradients(&normals_of(&gaussians, &full), &full);
    let c = curl(&p, &q, &full);
    let max = c.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(max < 1e-3, "curl of a surface {max}");

    // p = −y, q = x: dp/dy − dq/dx = −2 everywhere inside.
    let p = Array2::from_shape_fn((20, 30), |(r, _)| -(r as f32));
    let q = Array2::from_shape_fn((20, 30), |(_, c)| c as f32);
    let mask = Array2::from_elem((20, 30), true);
    let c = curl(&p, &q, &mask);
    for r in 0..19 {
        for col in 0..29 {
            assert!((c[(r, col)] + 2.0).abs() < 1e-5);
        }
    }
    assert_eq!(c[(19, 3)], 0.0);
    assert_eq!(c[(3, 29)], 0.0);
    // A neighbour off the mask → 0.
    let mut holey = mask.clone();
    holey[(5, 5)] = false;
    let c = curl(&p, &q, &holey);
    assert_eq!(c[(4, 4)], 0.0);
    assert_eq!(c[(5, 5)], 0.0);
    assert!((c[(6, 6)] + 2.0).abs() < 1e-5);
}

/// `curl` and `rhs` form each pixel's weight once; they must give exactly what
/// `edge_slope` per edge gives.
#[test]
fn curl_and_rhs_match_edge_slopes_bitwise() {
    use poisson::edge_slope;
    let (h, w) = (37, 53);
    let mut seed = 99u64;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % 10_000) as f32 / 500.0 - 10.0
    };
    let p = Array2::from_shape_fn((h, w), |_| rnd());
    let q = Array2::from_shape_fn((h, w), |_| rnd());
    let mask = Array2::from_shape_fn((h, w), |(r, c)| (r * 7 + c * 3) % 11 != 0);
    let g = |r: usize, c: usize| [p[(r, c)], q[(r, c)]];
    let on = |r: usize, c: usize| r < h && c < w && mask[(r, c)];
    let got = curl(&p, &q, &mask);
    let m: Vec<bool> = mask.iter().copied().collect();
    let b = poisson::rhs(
        &MaskStencil::new(&m, h, w),
        p.as_slice().unwrap(),
        q.as_slice().unwrap(),
    );
    for r in 0..h {
        for c in 0..w {
            let inside = on(r, c) && on(r, c + 1) && on(r + 1, c) && on(r + 1, c + 1);
            let want = if inside {
                let dpy = edge_slope(g(r + 1, c), g(r + 1, c + 1), 0)
                    - edge_slope(g(r, c), g(r, c + 1), 0);
                let dqx = edge_slope(g(r, c + 1), g(r + 1, c + 1), 1)
                    - edge_slope(g(r, c), g(r + 1, c), 1);
                dpy - dqx
            } else {
                0.0
            };
            assert_eq!(got[(r, c)].to_bits(), want.to_bits(), "curl at ({r}, {c})");
            // Edges into (r, c) minus edges out of it, each weighted 1 between mask pixels.
            let mut sum = 0.0f64;
            if on(r, c) {
                if c > 0 && on(r, c - 1) {
                    sum += f64::from(edge_slope(g(r, c - 1), g(r, c), 0));
                }
                if on(r, c + 1) {
                    sum -= f64::from(edge_slope(g(r, c), g(r, c + 1), 0));
                }
                if r > 0 && on(r - 1, c) {
                    sum += f64::from(edge_slope(g(r - 1, c), g(r, c), 1));
                }
                if on(r + 1, c) {
                    sum -= f64::from(edge_slope(g(r, c), g(r + 1, c), 1));
                }
            }
            assert!(
                (f64::from(b[r * w + c]) - sum).abs() < 1e-5,
                "rhs at ({r}, {c})"
            );
        }
    }
}

#[test]
fn gradients_clamp_grazing_normals() {
    let mut n = Array3::zeros((1, 3, 3));
    n[(0, 0, 0)] = 1.0; // grazing: nz = 0
    n[(0, 1, 0)] = -0.6;
    n[(0, 1, 2)] = 0.8;
    n[(0, 2, 0)] = f32::NAN;
    let mask = Array2::from_elem((1, 3), true);
    let (p, q) = gradients(&n, &mask);
    assert!((p[(0, 0)] + 1.0 / MIN_NZ).abs() < 1e-3);
    assert!((p[(0, 1)] - 0.75).abs() < 1e-6);
    assert_eq!(p[(0, 2)], 0.0);
    assert!(q.iter().all(|&v| v == 0.0));
    let off = Array2::from_elem((1, 3), false);
    let (p, _) = gradients(&n, &off);
    assert!(p.iter().all(|&v| v == 0.0));
}
