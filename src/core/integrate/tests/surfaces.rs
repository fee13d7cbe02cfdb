//! The analytic surfaces the integrators' tests share (pixel units), their exact normals
//! and heights, and the error measure.

use ndarray::{Array2, Array3};

use crate::core::integrate::*;
use crate::core::options::Integration;

/// Analytic surface: height and its derivatives (dz/dx, dz/dy) at (x = col, y = row).
pub(super) type Surface = dyn Fn(f64, f64) -> (f64, f64, f64);

/// Exact unit normals of `s` on an `h × w` grid (zero off the mask).
pub(super) fn normals_of(s: &Surface, mask: &Array2<bool>) -> Array3<f32> {
    let (h, w) = mask.dim();
    let mut n = Array3::zeros((h, w, 3));
    for r in 0..h {
        for c in 0..w {
            if !mask[(r, c)] {
                continue;
            }
            let (_, zx, zy) = s(c as f64, r as f64);
            let len = (zx * zx + zy * zy + 1.0).sqrt();
            n[(r, c, 0)] = (-zx / len) as f32;
            n[(r, c, 1)] = (-zy / len) as f32;
            n[(r, c, 2)] = (1.0 / len) as f32;
        }
    }
    n
}

pub(super) fn heights_of(s: &Surface, h: usize, w: usize) -> Array2<f64> {
    Array2::from_shape_fn((h, w), |(r, c)| s(c as f64, r as f64).0)
}

/// Depth RMS over `region` after removing the mean offset over `region`.
pub(super) fn rms(z: &Array2<f32>, truth: &Array2<f64>, region: &Array2<bool>) -> f64 {
    let pts: Vec<f64> = z
        .iter()
        .zip(truth)
        .zip(region)
        .filter(|&(_, &m)| m)
        .map(|((&z, &t), _)| f64::from(z) - t)
        .collect();
    let mean = pts.iter().sum::<f64>() / pts.len() as f64;
    (pts.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / pts.len() as f64).sqrt()
}

pub(super) fn gaussians(x: f64, y: f64) -> (f64, f64, f64) {
    let mut out = (0.0, 0.0, 0.0);
    for (a, cx, cy, s) in [
        (14.0, 50.0, 60.0, 15.0),
        (-8.0, 88.0, 40.0, 11.0),
        (6.0, 75.0, 95.0, 20.0),
    ] {
        let (dx, dy) = (x - cx, y - cy);
        let g = a * (-(dx * dx + dy * dy) / (2.0 * s * s)).exp();
        out.0 += g;
        out.1 += -g * dx / (s * s);
        out.2 += -g * dy / (s * s);
    }
    out
}

pub(super) fn periodic(x: f64, y: f64) -> (f64, f64, f64) {
    use std::f64::consts::PI;
    let (kx, ky) = (2.0 * PI / 128.0, 4.0 * PI / 128.0);
    (
        12.0 * (kx * x).cos() * (ky * y).sin() + 5.0 * (kx * (x + y)).sin(),
        -12.0 * kx * (kx * x).sin() * (ky * y).sin() + 5.0 * kx * (kx * (x + y)).cos(),
        12.0 * ky * (kx * x).cos() * (ky * y).cos() + 5.0 * kx * (kx * (x + y)).cos(),
    )
}

pub(super) fn disc(h: usize, w: usize, cx: f64, cy: f64, rad: f64) -> Array2<bool> {
    Array2::from_shape_fn((h, w), |(r, c)| {
        (c as f64 - cx).powi(2) + (r as f64 - cy).powi(2) < rad * rad
    })
}

pub(super) fn hemisphere(cx: f64, cy: f64, rad: f64) -> impl Fn(f64, f64) -> (f64, f64, f64) {
    move |x, y| {
        let (dx, dy) = (x - cx, y - cy);
        let z = (rad * rad - dx * dx - dy * dy).max(1e-9).sqrt();
        (z, -dx / z, -dy / z)
    }
}

pub(super) fn run(s: &Surface, mask: &Array2<bool>, method: Integration) -> (Array2<f32>, f64) {
    let (h, w) = mask.dim();
    let (p, q) = gradients(&normals_of(s, mask), mask);
    let z = integrate(&p, &q, mask, method);
    assert!(z.iter().all(|v| v.is_finite()));
    let e = rms(&z, &heights_of(s, h, w), mask);
    (z, e)
}
