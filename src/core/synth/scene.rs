//! The surfaces: analytic height fields with exact normals, depth and albedo.

use ndarray::{Array2, Array3};

use crate::core::camera::Pinhole;

/// A surface with ground truth, sampled at pixel centres (x = column, y = row down).
#[derive(Debug, Clone)]
pub struct Scene {
    pub width: usize,
    pub height: usize,
    /// Heights in pixel units (0 off the mask); with a `camera`, depth along the optical
    /// axis instead.
    pub depth: Array2<f64>,
    /// Unit normals in the seed frame, zero off the mask.
    pub normals: Array3<f64>,
    /// Diffuse albedo per channel, `(rows, cols, 1 or 3)`: gray or RGB.
    pub albedo: Array3<f64>,
    pub mask: Array2<bool>,
    /// The pinhole camera of a perspective scene ([`super::DepthScene::to_scene`]): its
    /// normals are in the camera frame and its `depth` is depth. None: orthographic.
    pub camera: Option<Pinhole>,
}

impl Scene {
    /// Build from an analytic height function returning (z, dz/dx, dz/dy), or None off
    /// the object, with a gray albedo.
    pub fn from_fn(
        width: usize,
        height: usize,
        surface: impl Fn(f64, f64) -> Option<(f64, f64, f64)> + Sync,
        albedo: impl Fn(f64, f64) -> f64 + Sync,
    ) -> Self {
        let mut depth = Array2::zeros((height, width));
        let mut normals = Array3::zeros((height, width, 3));
        let mut alb = Array3::zeros((height, width, 1));
        let mut mask = Array2::from_elem((height, width), false);
        for r in 0..height {
            for c in 0..width {
                let (x, y) = (c as f64, r as f64);
                if let Some((z, p, q)) = surface(x, y) {
                    let len = (p * p + q * q + 1.0).sqrt();
                    depth[[r, c]] = z;
                    normals[[r, c, 0]] = -p / len;
                    normals[[r, c, 1]] = -q / len;
                    normals[[r, c, 2]] = 1.0 / len;
                    alb[[r, c, 0]] = albedo(x, y);
                    mask[[r, c]] = true;
                }
            }
        }
        Self {
            width,
            height,
            depth,
            normals,
            albedo: alb,
            mask,
            camera: None,
        }
    }

    /// The same surface with an RGB albedo on the object (0 off it).
    pub fn with_colour(mut self, albedo: impl Fn(f64, f64) -> [f64; 3]) -> Self {
        self.albedo = Array3::from_shape_fn((self.height, self.width, 3), |(r, c, k)| {
            if self.mask[[r, c]] {
                albedo(c as f64, r as f64)[k]
            } else {
                0.0
            }
        });
        self
    }

    pub fn channels(&self) -> usize {
        self.albedo.dim().2
    }

    /// The seed's kind of synthetic scene: a smooth bump filling the frame, albedo varying
    /// between 0.2 and 0.8.
    pub fn bump(size: usize) -> Self {
        let s = size as f64;
        let (cx, cy, sigma, amp) = (0.5 * (s - 1.0), 0.45 * (s - 1.0), 0.18 * s, 0.1 * s);
        Self::from_fn(
            size,
            size,
            |x, y| {
                let (dx, dy) = (x - cx, y - cy);
                let z = amp * (-(dx * dx + dy * dy) / (2.0 * sigma * sigma)).exp();
                Some((z, -z * dx / (sigma * sigma), -z * dy / (sigma * sigma)))
            },
            |x, y| 0.5 + 0.3 * (x / s * 5.0).sin() * (y / s * 3.0).cos(),
        )
    }

    /// A sphere of radius 0.4·size on a black background (albedo 0), textured albedo.
    pub fn sphere(size: usize) -> Self {
        let s = size as f64;
        Self::from_fn(size, size, sphere_surface(size), |x, y| {
            0.6 + 0.25 * ((x / s * 9.0).sin() * (y / s * 7.0).sin())
        })
    }

    /// The sphere in a dark glaze: diffuse albedo 0.05–0.09, for a glossy coat whose
    /// highlights outshine the diffuse shading a hundredfold.
    pub fn dark_sphere(size: usize) -> Self {
        let s = size as f64;
        Self::from_fn(size, size, sphere_surface(size), |x, y| {
            0.07 + 0.02 * ((x / s * 9.0).sin() * (y / s * 7.0).sin())
        })
    }

    /// The sphere painted in three colours: each channel its own texture, 0.15–0.7.
    pub fn painted_sphere(size: usize) -> Self {
        let s = size as f64;
        Self::from_fn(size, size, sphere_surface(size), |_, _| 0.0).with_colour(|x, y| {
            let (u, v) = (x / s, y / s);
            [
                0.45 + 0.25 * (u * 11.0).sin() * (v * 5.0).cos(),
                0.4 + 0.2 * ((u + v) * 8.0).cos(),
                0.35 + 0.2 * (v * 13.0).sin(),
            ]
        })
    }

    /// A plane with steep bumps that cast shadows across it under low lights.
    pub fn shadows(size: usize) -> Self {
        let s = size as f64;
        let bumps = [
            (0.3, 0.3, 0.07, 0.12),
            (0.7, 0.35, 0.05, 0.10),
            (0.45, 0.7, 0.08, 0.14),
            (0.78, 0.75, 0.04, 0.08),
        ];
        Self::from_fn(
            size,
            size,
            |x, y| {
                let (mut z, mut p, mut q) = (0.0, 0.0, 0.0);
                add_gaussians(s, &bumps, x, y, (&mut z, &mut p, &mut q));
                Some((z, p, q))
            },
            |x, y| 0.55 + 0.25 * ((x / s * 11.0).cos() * (y / s * 4.0).sin()),
        )
    }

    /// Concavities for interreflection and cast shadows: a plane holding a bowl, a cluster
    /// of steep bumps with valleys between them and a trench across the lower part.
    pub fn basin(size: usize) -> Self {
        let s = size as f64;
        let (bx, by, radius, deep) = (0.3 * s, 0.33 * s, 0.22 * s, 0.14 * s);
        let bumps = [
            (0.66, 0.28, 0.06, 0.16),
            (0.82, 0.42, 0.055, 0.15),
            (0.6, 0.52, 0.05, 0.12),
        ];
        let (trench_y, trench_w, trench_d) = (0.8 * s, 0.05 * s, 0.08 * s);
        Self::from_fn(
            size,
            size,
            |x, y| {
                let (mut z, mut p, mut q) = (0.0, 0.0, 0.0);
                // Bowl: -deep·(1 - r²/R²)², smooth (zero slope) at its rim.
                let (dx, dy) = (x - bx, y - by);
                let u = (dx * dx + dy * dy) / (radius * radius);
                if u < 1.0 {
                    z -= deep * (1.0 - u).powi(2);
                    p += 4.0 * deep * (1.0 - u) * dx / (radius * radius);
                    q += 4.0 * deep * (1.0 - u) * dy / (radius * radius);
                }
                add_gaussians(s, &bumps, x, y, (&mut z, &mut p, &mut q));
                let t = y - trench_y;
                let g = trench_d * (-t * t / (2.0 * trench_w * trench_w)).exp();
                z -= g;
                q += g * t / (trench_w * trench_w);
                Some((z, p, q))
            },
            |x, y| 0.6 + 0.15 * ((x / s * 7.0).sin() * (y / s * 5.0).cos()),
        )
    }

    /// Bilinear height at a point inside the frame.
    pub(super) fn sample_depth(&self, x: f64, y: f64) -> f64 {
        bilinear(&self.depth, x, y)
    }
}

/// A value of `a` between pixel centres (x = column, y = row), clamped at the last
/// row and column.
pub(super) fn bilinear(a: &Array2<f64>, x: f64, y: f64) -> f64 {
    let (rows, cols) = a.dim();
    let (c0, r0) = (x.floor() as usize, y.floor() as usize);
    let (c1, r1) = ((c0 + 1).min(cols - 1), (r0 + 1).min(rows - 1));
    let (fx, fy) = (x - c0 as f64, y - r0 as f64);
    (a[[r0, c0]] * (1.0 - fx) + a[[r0, c1]] * fx) * (1.0 - fy)
        + (a[[r1, c0]] * (1.0 - fx) + a[[r1, c1]] * fx) * fy
}

/// The sphere of radius 0.4·size centred in the frame, as a height function.
fn sphere_surface(size: usize) -> impl Fn(f64, f64) -> Option<(f64, f64, f64)> + Sync {
    let s = size as f64;
    let (c, radius) = (0.5 * (s - 1.0), 0.4 * s);
    move |x, y| {
        let (dx, dy) = (x - c, y - c);
        let h2 = radius * radius - dx * dx - dy * dy;
        // Stop just inside the rim, where normals are still defined.
        (h2 > (0.05 * radius).powi(2)).then(|| {
            let z = h2.sqrt();
            (z, -dx / z, -dy / z)
        })
    }
}

/// Add Gaussian bumps `(x, y, sigma, amplitude)` (fractions of the frame size `s`) to a
/// height and its slopes at (x, y).
fn add_gaussians(
    s: f64,
    bumps: &[(f64, f64, f64, f64)],
    x: f64,
    y: f64,
    (z, p, q): (&mut f64, &mut f64, &mut f64),
) {
    for &(bx, by, sig, amp) in bumps {
        let (dx, dy, sg) = (x - bx * s, y - by * s, sig * s);
        let g = amp * s * (-(dx * dx + dy * dy) / (2.0 * sg * sg)).exp();
        *z += g;
        *p -= g * dx / (sg * sg);
        *q -= g * dy / (sg * sg);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normals_are_unit_and_match_depth_slopes() {
        for s in [Scene::bump(64), Scene::basin(64)] {
            for (r, c) in [(10, 10), (30, 40), (50, 20), (21, 19), (51, 30)] {
                let n: f64 = (0..3).map(|k| s.normals[[r, c, k]].powi(2)).sum();
                assert!((n - 1.0).abs() < 1e-12);
                let p_fd = (s.depth[[r, c + 1]] - s.depth[[r, c - 1]]) / 2.0;
                let q_fd = (s.depth[[r + 1, c]] - s.depth[[r - 1, c]]) / 2.0;
                let p = -s.normals[[r, c, 0]] / s.normals[[r, c, 2]];
                let q = -s.normals[[r, c, 1]] / s.normals[[r, c, 2]];
                // Central differences lag the slope on the steep bumps by a few per cent, and by
                // 0.014 at the bowl's rim, where the curvature jumps.
                assert!((p - p_fd).abs() < 0.02 + 0.05 * p.abs(), "{p} vs {p_fd}");
                assert!((q - q_fd).abs() < 0.02 + 0.05 * q.abs(), "{q} vs {q_fd}");
            }
        }
    }

    #[test]
    fn basin_has_a_bowl_below_the_plane() {
        let s = Scene::basin(128);
        let bottom = s.depth[[(0.33f64 * 128.0) as usize, (0.3f64 * 128.0) as usize]];
        assert!(bottom < -0.1 * 128.0, "{bottom}");
    }
}
