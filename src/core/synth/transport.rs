//! Light transport over a height field: rays marched for cast shadows, area lights as
//! caps of directions, and one bounce of interreflection.

use ndarray::Array2;
use rayon::prelude::*;

use super::scene::{Scene, bilinear};
use super::sensor::Rng;
use crate::core::vec3::{cross, normalise};

/// Horizontal step of the ray march, pixels: well below the scale of the surfaces' bumps.
const STEP: f64 = 0.5;

/// The golden angle, radians: successive samples turned by it cover a disc evenly.
const GOLDEN: f64 = 2.399963229728653;

/// A height field with its highest point, above which a rising ray has escaped.
pub(super) struct Field<'a> {
    pub scene: &'a Scene,
    max_z: f64,
}

impl<'a> Field<'a> {
    pub fn new(scene: &'a Scene) -> Self {
        let max_z = scene.depth.iter().cloned().fold(f64::MIN, f64::max);
        Self { scene, max_z }
    }

    /// The horizontal distance along unit `d` from `from` at which the ray first passes
    /// below the surface, or None when it leaves the frame or rises above every point.
    fn march(&self, from: [f64; 3], d: [f64; 3]) -> Option<f64> {
        let s = self.scene;
        let horiz = (d[0] * d[0] + d[1] * d[1]).sqrt();
        if horiz < 1e-9 {
            return None;
        }
        let (dx, dy, rise) = (d[0] / horiz, d[1] / horiz, d[2] / horiz);
        let mut t = STEP;
        loop {
            let (x, y) = (from[0] + dx * t, from[1] + dy * t);
            let ray_z = from[2] + rise * t;
            if ray_z > self.max_z
                || x < 0.0
                || y < 0.0
                || x > (s.width - 1) as f64
                || y > (s.height - 1) as f64
            {
                return None;
            }
            if s.sample_depth(x, y) > ray_z + 1e-6 {
                return Some(t);
            }
            t += STEP;
        }
    }

    /// The horizon's tan(elevation) from (r, c) towards azimuth `phi`: the steepest rise
    /// to any surface point along the way, marched until the frame's edge or until even
    /// the highest point could not rise above it.
    fn horizon(&self, r: usize, c: usize, phi: f64) -> f32 {
        let s = self.scene;
        let (dx, dy) = (phi.cos(), phi.sin());
        let z0 = s.depth[[r, c]];
        let mut best = f64::MIN;
        let mut t = STEP;
        loop {
            let (x, y) = (c as f64 + dx * t, r as f64 + dy * t);
            if (self.max_z - z0) / t <= best
                || x < 0.0
                || y < 0.0
                || x > (s.width - 1) as f64
                || y > (s.height - 1) as f64
            {
                return best as f32;
            }
            best = best.max((s.sample_depth(x, y) - z0) / t);
            // Far away a height step moves the horizon less: stride with the distance.
            t += STEP.max(t / 32.0);
        }
    }

    fn surface_point(&self, r: usize, c: usize) -> [f64; 3] {
        [c as f64, r as f64, self.scene.depth[[r, c]]]
    }

    /// Whether the surface point at (r, c) sees a distant light along unit `l`.
    pub fn lit(&self, r: usize, c: usize, l: [f64; 3]) -> bool {
        self.march(self.surface_point(r, c), l).is_none()
    }

    /// Where the ray from (r, c) along unit `d` meets the surface (x, y), refined between
    /// the march's last two steps by bisection.
    fn hit(&self, r: usize, c: usize, d: [f64; 3]) -> Option<[f64; 2]> {
        let from = self.surface_point(r, c);
        let t = self.march(from, d)?;
        let horiz = (d[0] * d[0] + d[1] * d[1]).sqrt();
        let at = |t: f64| {
            [
                from[0] + d[0] / horiz * t,
                from[1] + d[1] / horiz * t,
                from[2] + d[2] / horiz * t,
            ]
        };
        let (mut lo, mut hi) = (t - STEP, t);
        for _ in 0..8 {
            let mid = 0.5 * (lo + hi);
            let p = at(mid);
            if self.scene.sample_depth(p[0], p[1]) > p[2] {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        let p = at(hi);
        Some([p[0], p[1]])
    }
}

/// The horizon of every object pixel: how high (tan of the elevation) the surface rises
/// above it, seen from it, at `AZIMUTHS` evenly spaced azimuths. An area light's many
/// sample directions are then each tested by a lookup instead of a march.
pub(super) struct Horizons {
    width: usize,
    tan: Vec<f32>,
}

/// Azimuths of the horizon map: 2° apart, inside an area light's cap.
const AZIMUTHS: usize = 180;

impl Horizons {
    pub fn trace(field: &Field) -> Self {
        let s = field.scene;
        let tan = (0..s.height * s.width)
            .into_par_iter()
            .flat_map_iter(|i| {
                let (r, c) = (i / s.width, i % s.width);
                let inside = s.mask[[r, c]];
                (0..AZIMUTHS).map(move |a| {
                    if inside {
                        field.horizon(r, c, a as f64 * std::f64::consts::TAU / AZIMUTHS as f64)
                    } else {
                        f32::MIN
                    }
                })
            })
            .collect();
        Self {
            width: s.width,
            tan,
        }
    }

    /// Whether the direction unit `d` from pixel (r, c) clears the horizon, interpolated
    /// between the two nearest azimuths.
    pub fn clears(&self, r: usize, c: usize, d: [f64; 3]) -> bool {
        let horiz = (d[0] * d[0] + d[1] * d[1]).sqrt();
        if horiz < 1e-9 {
            return true;
        }
        let turns = d[1].atan2(d[0]).rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU;
        let at = turns * AZIMUTHS as f64;
        let (a0, f) = (at.floor() as usize % AZIMUTHS, at.fract());
        let row = &self.tan[(r * self.width + c) * AZIMUTHS..][..AZIMUTHS];
        let h = row[a0] as f64 * (1.0 - f) + row[(a0 + 1) % AZIMUTHS] as f64 * f;
        d[2] / horiz > h
    }
}

/// A distant light of finite size: a cap of directions of angular radius `radius_deg`
/// around its direction, integrated with `samples` directions of equal solid angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AreaLight {
    pub radius_deg: f64,
    pub samples: usize,
}

impl AreaLight {
    /// The sample directions around unit `l`, the pattern turned by `turn` radians (a
    /// different turn per pixel trades the banding of a fixed pattern for fine noise).
    pub(super) fn directions(&self, l: [f64; 3], turn: f64) -> impl Iterator<Item = [f64; 3]> {
        let cos_r = self.radius_deg.to_radians().cos();
        let n = self.samples;
        let (u, w) = basis(l);
        (0..n).map(move |i| {
            // Equal steps in cos θ are equal steps in solid angle.
            let cos_t = 1.0 - (i as f64 + 0.5) / n as f64 * (1.0 - cos_r);
            let sin_t = (1.0 - cos_t * cos_t).sqrt();
            let phi = i as f64 * GOLDEN + turn;
            let (a, b) = (sin_t * phi.cos(), sin_t * phi.sin());
            [0, 1, 2].map(|k| cos_t * l[k] + a * u[k] + b * w[k])
        })
    }
}

/// A pseudo-random angle for pixel `index` under light `light`, fixed by `seed`.
pub(super) fn turn(seed: u64, light: usize, index: usize) -> f64 {
    let key = seed ^ (light as u64).wrapping_mul(0x9E37_79B9) ^ (index as u64) << 20;
    std::f64::consts::TAU * Rng::new(key).uniform()
}

/// Two unit vectors completing unit `n` to an orthonormal basis.
fn basis(n: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let a = if n[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = normalise(cross(n, a));
    (u, cross(n, u))
}

/// One bounce of light off the rest of the surface. For each object pixel, where its
/// cosine-weighted hemisphere rays first meet the height field: this depends on the
/// geometry only, so it is traced once and gathered per light.
pub(super) struct Bounces {
    rays: usize,
    /// Per pixel (row-major), the (x, y) hit points of the rays that met the surface;
    /// the rest escaped to the dark surroundings.
    hits: Vec<Vec<[f64; 2]>>,
}

impl Bounces {
    pub fn trace(field: &Field, rays: usize, seed: u64) -> Self {
        let s = field.scene;
        let hits = (0..s.height * s.width)
            .into_par_iter()
            .map(|i| {
                let (r, c) = (i / s.width, i % s.width);
                if !s.mask[[r, c]] {
                    return Vec::new();
                }
                let n = [0, 1, 2].map(|k| s.normals[[r, c, k]]);
                let (u, w) = basis(n);
                let spin = turn(seed, usize::MAX, i);
                (0..rays)
                    .filter_map(|k| {
                        // Malley: uniform points on the disc, lifted to the hemisphere,
                        // are cosine-distributed.
                        let rho = ((k as f64 + 0.5) / rays as f64).sqrt();
                        let phi = k as f64 * GOLDEN + spin;
                        let (a, b) = (rho * phi.cos(), rho * phi.sin());
                        let up = (1.0 - rho * rho).sqrt();
                        let d = [0, 1, 2].map(|j| a * u[j] + b * w[j] + up * n[j]);
                        field.hit(r, c, d)
                    })
                    .collect()
            })
            .collect();
        Self { rays, hits }
    }

    /// The irradiance each pixel receives after one bounce, given the light leaving the
    /// surface `radiosity` (pixel units: albedo × direct irradiance). With cosine-weighted
    /// rays the irradiance integral ∫ L cos θ dω = π · mean L is the mean radiosity at
    /// the hit points, a Lambertian surface's radiosity being π times its radiance.
    pub fn gather(&self, radiosity: &Array2<f64>) -> Array2<f64> {
        let (rows, cols) = radiosity.dim();
        let values: Vec<f64> = self
            .hits
            .par_iter()
            .map(|hits| {
                let sum: f64 = hits.iter().map(|h| bilinear(radiosity, h[0], h[1])).sum();
                sum / self.rays as f64
            })
            .collect();
        Array2::from_shape_vec((rows, cols), values).expect("one value per pixel")
    }
}
