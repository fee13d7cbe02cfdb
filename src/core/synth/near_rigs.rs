//! Near-light rigs with ground truth: LED rings and domes a few object sizes from the
//! object, as inspection lines and museum domes build them. Each LED sits at a position
//! in the camera frame, shines mostly along its axis (radiance ∝ cos^μ off the axis),
//! has its own brightness, and lights a point `X` with irradiance falling as `1/r²`:
//! `I = ρ · intensity · max(0, −l·axis)^μ · max(0, n·l) / r²`, rendered here on its own
//! (not with the solver's model) through a pinhole camera, with Gaussian read noise and
//! 16-bit quantisation.
//!
//! | rig | object | lights |
//! |---|---|---|
//! | [`ring_relief`] | a relief plate (six bumps and a ridge) 100 mm away | 12 LEDs on a 40 mm ring 10 mm before the lens, aimed at the plate's centre, μ = 1.5, ±20 % brightness |
//! | [`close_ring`] | the relief plate | 16 LEDs on a 35 mm ring 45 mm above the plate: strong falloff, μ = 3 |
//! | [`dome_sphere`] | a ball of 20 mm radius 20 mm before a plane, 100 mm away | 40 LEDs on a 90 mm dome around the ball's centre, isotropic, ±15 %; the ball's cast shadows |
//! | [`far_ring`] | the relief plate | the ring of [`ring_relief`] 10⁴× farther (and brighter): distant lights |
//!
//! Units are millimetres; the camera has `f = 1.2 × size` px with its principal point at
//! the centre, so the plate fills the frame (41.7 mm either side of the axis at 100 mm).

use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::sensor::Rng;
use crate::core::camera::Pinhole;
use crate::core::lights::{Emitter, Light, make_light};
use crate::core::vec3::{dot, normalise};

/// A rendered near-light capture and its truth.
#[derive(Debug, Clone)]
pub struct NearRig {
    pub name: &'static str,
    pub camera: Pinhole,
    /// Distance from the camera to the object along the optical axis (its nominal plane).
    pub distance: f64,
    pub unit: &'static str,
    /// The LEDs as a table gives them: positions, axes, anisotropy and true intensities.
    pub lights: Vec<Light>,
    /// One 16-bit image per light (full scale 65535).
    pub images: Vec<Array2<u16>>,
    /// True depth along the optical axis (mm); true unit normals; albedo as the images
    /// show it (ρ × the exposure's gain).
    pub depth: Array2<f32>,
    pub normals: Array3<f32>,
    pub albedo: Array2<f32>,
    pub mask: Array2<bool>,
}

impl NearRig {
    /// The best distant table a user could give: each LED's direction from the object's
    /// centre on the axis and its irradiance there as its intensity.
    pub fn distant_table(&self) -> Vec<Light> {
        let centre = [0.0, 0.0, -self.distance];
        self.lights
            .iter()
            .map(|l| {
                let e = l.emitter.expect("a rig's lights have positions");
                let v = [0, 1, 2].map(|k| e.position[k] - centre[k]);
                let r2: f64 = v.iter().map(|c| c * c).sum();
                let dir = v.map(|c| c / r2.sqrt());
                let intensity = l.intensity * cone(&e, dir) * self.distance.powi(2) / r2;
                make_light(
                    1,
                    &l.name,
                    dir,
                    Some(crate::core::lights::Intensity::One(intensity)),
                )
                .expect("a rig's light is valid")
            })
            .collect()
    }
}

/// The relief plate: heights above the plane `z = −distance` (mm) and their slopes.
fn relief(x: f64, y: f64) -> (f64, f64, f64) {
    const BUMPS: [(f64, f64, f64, f64); 6] = [
        (-20.0, -18.0, 4.0, 7.0),
        (15.0, -20.0, -3.0, 6.0),
        (-22.0, 16.0, 3.0, 9.0),
        (18.0, 18.0, 5.0, 8.0),
        (0.0, 0.0, 6.0, 10.0),
        (30.0, 0.0, 2.5, 4.0),
    ];
    let (mut h, mut hx, mut hy) = (0.0, 0.0, 0.0);
    for (x0, y0, a, s) in BUMPS {
        let e = a * (-((x - x0).powi(2) + (y - y0).powi(2)) / (2.0 * s * s)).exp();
        h += e;
        hx += -e * (x - x0) / (s * s);
        hy += -e * (y - y0) / (s * s);
    }
    // A ridge across the lower left: a scratch-like groove's opposite.
    let (u, s) = ((x + y + 40.0) / 2f64.sqrt(), 2.5);
    let e = 1.5 * (-(u * u) / (2.0 * s * s)).exp();
    h += e;
    let du = -e * u / (s * s) / 2f64.sqrt();
    (h, hx + du, hy + du)
}

/// What a pixel sees.
#[derive(Debug, Clone, Copy)]
struct Hit {
    point: [f64; 3],
    normal: [f64; 3],
}

#[derive(Debug, Clone, Copy)]
enum Object {
    /// The relief plate at this distance.
    Plate(f64),
    /// A ball (centre, radius) before the plane `z = −background`.
    Ball([f64; 3], f64, f64),
}

impl Object {
    fn hit(&self, d: [f64; 3]) -> Hit {
        match *self {
            Object::Plate(distance) => {
                // t = distance − h(t dx, t dy): a contraction for these slopes.
                let mut t = distance;
                for _ in 0..60 {
                    t = distance - relief(t * d[0], t * d[1]).0;
                }
                let (_, hx, hy) = relief(t * d[0], t * d[1]);
                Hit {
                    point: d.map(|c| c * t),
                    normal: normalise([-hx, -hy, 1.0]),
                }
            }
            Object::Ball(centre, radius, background) => match sphere_t(d, centre, radius) {
                Some(t) => {
                    let p = d.map(|c| c * t);
                    Hit {
                        point: p,
                        normal: normalise([0, 1, 2].map(|k| p[k] - centre[k])),
                    }
                }
                None => Hit {
                    point: d.map(|c| c * background),
                    normal: [0.0, 0.0, 1.0],
                },
            },
        }
    }

    /// Whether the segment from `p` to the light at `q` passes through the object (only
    /// the ball casts shadows; the relief's slopes stay below the lights' elevations).
    fn shadowed(&self, p: [f64; 3], q: [f64; 3]) -> bool {
        let Object::Ball(centre, radius, _) = *self else {
            return false;
        };
        let v = [0, 1, 2].map(|k| q[k] - p[k]);
        let len = v.iter().map(|c| c * c).sum::<f64>().sqrt();
        let dir = v.map(|c| c / len);
        let o = [0, 1, 2].map(|k| p[k] - centre[k]);
        let b = dot(o, dir);
        let c = dot(o, o) - radius * radius;
        let disc = b * b - c;
        if disc <= 0.0 {
            return false;
        }
        let t = -b - disc.sqrt();
        t > 1e-6 * radius && t < len
    }
}

/// Nearest ray parameter where the ray `t d` meets the sphere.
fn sphere_t(d: [f64; 3], centre: [f64; 3], radius: f64) -> Option<f64> {
    let a = dot(d, d);
    let b = dot(d, centre);
    let c = dot(centre, centre) - radius * radius;
    let disc = b * b - a * c;
    (disc > 0.0).then(|| (b - disc.sqrt()) / a)
}

/// The LED's radiance factor towards the unit direction `l` (from the point to the LED).
fn cone(e: &Emitter, l: [f64; 3]) -> f64 {
    match e.axis {
        Some(a) if e.anisotropy > 0.0 => (-dot(l, a)).max(0.0).powf(e.anisotropy),
        _ => 1.0,
    }
}

/// An albedo with texture: a smooth gradient and soft stripes (0.35..0.85).
fn albedo_at(x: f64, y: f64) -> f64 {
    0.6 + 0.15 * (x / 30.0).tanh() + 0.1 * (0.3 * y + 0.1 * x).sin()
}

/// An LED at `position` with `intensity`, aimed at `target` (None: isotropic).
fn led(i: usize, position: [f64; 3], target: Option<[f64; 3]>, mu: f64, intensity: f64) -> Light {
    let name = format!("led{:02}.png", i + 1);
    let mut light = make_light(
        i + 1,
        &name,
        [0.0, 0.0, 1.0],
        Some(crate::core::lights::Intensity::One(intensity)),
    )
    .expect("a valid light");
    light.emitter = Some(Emitter {
        position,
        axis: target.map(|t| normalise([0, 1, 2].map(|k| t[k] - position[k]))),
        anisotropy: if target.is_some() { mu } else { 0.0 },
        intensity_known: true,
    });
    light
}

/// Brightness ±`spread` around 1, fixed per LED.
fn uneven(i: usize, spread: f64) -> f64 {
    1.0 + spread * (2.0 * Rng::new(1000 + i as u64).uniform() - 1.0)
}

/// A ring of `n` LEDs of radius `radius` at `z`, aimed at the point on the axis at
/// `aim`, with brightness spread `spread`.
fn ring(n: usize, radius: f64, z: f64, aim: f64, mu: f64, spread: f64) -> Vec<Light> {
    (0..n)
        .map(|i| {
            let a = std::f64::consts::TAU * i as f64 / n as f64 + 0.1;
            let p = [radius * a.cos(), radius * a.sin(), z];
            led(i, p, Some([0.0, 0.0, -aim]), mu, uneven(i, spread))
        })
        .collect()
}

/// Render `object` under `lights` at `size²` with read noise `sigma`; the exposure puts
/// the brightest value at 90 % of full scale.
fn render(
    name: &'static str,
    size: usize,
    distance: f64,
    object: Object,
    lights: Vec<Light>,
    sigma: f64,
) -> NearRig {
    let f = 1.2 * size as f64;
    let camera = Pinhole::centred(f, size, size);
    let hits: Vec<Hit> = (0..size * size)
        .into_par_iter()
        .map(|i| object.hit(camera.ray((i % size) as f64, (i / size) as f64)))
        .collect();
    let shade = |k: usize, hit: &Hit| -> f64 {
        let l = &lights[k];
        let e = l.emitter.expect("rig lights have positions");
        let v = [0, 1, 2].map(|c| e.position[c] - hit.point[c]);
        let r2 = dot(v, v);
        let dir = v.map(|c| c / r2.sqrt());
        let cos = dot(hit.normal, dir);
        if cos <= 0.0 || object.shadowed(hit.point, e.position) {
            return 0.0;
        }
        let rho = albedo_at(hit.point[0], hit.point[1]);
        rho * l.intensity * cone(&e, dir) * cos * distance * distance / r2
    };
    let radiance: Vec<Vec<f64>> = (0..lights.len())
        .into_par_iter()
        .map(|k| hits.iter().map(|h| shade(k, h)).collect())
        .collect();
    let peak = radiance.iter().flatten().copied().fold(0.0, f64::max);
    let gain = 0.9 / peak;
    let images = radiance
        .iter()
        .enumerate()
        .map(|(k, plane)| {
            let mut rng = Rng::new(7 + k as u64);
            Array2::from_shape_fn((size, size), |(r, c)| {
                let v = gain * plane[r * size + c] + sigma * rng.gaussian();
                (v.clamp(0.0, 1.0) * 65535.0).round() as u16
            })
        })
        .collect();
    let depth = Array2::from_shape_fn((size, size), |(r, c)| -hits[r * size + c].point[2] as f32);
    let normals = Array3::from_shape_fn((size, size, 3), |(r, c, k)| {
        hits[r * size + c].normal[k] as f32
    });
    let albedo = Array2::from_shape_fn((size, size), |(r, c)| {
        let p = hits[r * size + c].point;
        (gain * albedo_at(p[0], p[1])) as f32
    });
    NearRig {
        name,
        camera,
        distance,
        unit: "mm",
        lights,
        images,
        depth,
        normals,
        albedo,
        mask: Array2::from_elem((size, size), true),
    }
}

/// Read noise of every rig: 0.002 of full scale.
pub const NOISE_SIGMA: f64 = 0.002;

/// A 40 mm ring of 12 LEDs 10 mm before the lens over the relief plate at 100 mm.
pub fn ring_relief(size: usize) -> NearRig {
    ring_relief_of(size, 12)
}

/// [`ring_relief`] with `leds` LEDs on the ring.
pub fn ring_relief_of(size: usize, leds: usize) -> NearRig {
    let lights = ring(leds, 40.0, -10.0, 100.0, 1.5, 0.2);
    render(
        "ring-relief",
        size,
        100.0,
        Object::Plate(100.0),
        lights,
        NOISE_SIGMA,
    )
}

/// A 35 mm ring of 16 LEDs only 45 mm above the relief plate: strong falloff.
pub fn close_ring(size: usize) -> NearRig {
    let lights = ring(16, 35.0, -55.0, 100.0, 3.0, 0.2);
    render(
        "close-ring",
        size,
        100.0,
        Object::Plate(100.0),
        lights,
        NOISE_SIGMA,
    )
}

/// A dome of 40 isotropic LEDs, 90 mm around a 20 mm ball that stands 20 mm before a
/// plane; the ball casts shadows on the plane.
pub fn dome_sphere(size: usize) -> NearRig {
    let centre = [0.0, 0.0, -100.0];
    // Rings of the dome at elevations 25°..75° above the plane, facing the camera side.
    let mut lights = Vec::new();
    for (ring_i, (elev, n)) in [(25.0f64, 12usize), (45.0, 12), (62.0, 10), (78.0, 6)]
        .iter()
        .enumerate()
    {
        for j in 0..*n {
            let a = std::f64::consts::TAU * j as f64 / *n as f64 + 0.3 * ring_i as f64;
            let (e, r) = (elev.to_radians(), 90.0);
            let p = [
                centre[0] + r * e.cos() * a.cos(),
                centre[1] + r * e.cos() * a.sin(),
                centre[2] + r * e.sin(),
            ];
            let i = lights.len();
            lights.push(led(i, p, None, 0.0, uneven(i, 0.15)));
        }
    }
    render(
        "dome-sphere",
        size,
        100.0,
        Object::Ball([0.0, 0.0, -100.0], 20.0, 120.0),
        lights,
        NOISE_SIGMA,
    )
}

/// The ring of [`ring_relief`] scaled 10⁴ times about the plate's centre (and 10⁸ times
/// brighter): distant lights in effect (directions across the plate within 0.003°),
/// though behind the camera's plane.
pub fn far_ring(size: usize) -> NearRig {
    let lights = ring(12, 40.0, -10.0, 100.0, 1.5, 0.2)
        .into_iter()
        .map(|mut l| {
            let e = l.emitter.as_mut().expect("positioned");
            let p = e.position;
            e.position = [1e4 * p[0], 1e4 * p[1], -100.0 + 1e4 * (p[2] + 100.0)];
            l.intensity *= 1e8;
            l
        })
        .collect();
    render(
        "far-ring",
        size,
        100.0,
        Object::Plate(100.0),
        lights,
        NOISE_SIGMA,
    )
}

impl NearRig {
    /// Write the capture as a folder `reconstruct` reads: one 16-bit PNG per LED and
    /// `light_directions.json` with the positions, axes, anisotropy, intensities, the
    /// camera, the working distance and the unit.
    pub fn write(&self, dir: &std::path::Path) -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        for (light, plane) in self.lights.iter().zip(&self.images) {
            let (h, w) = plane.dim();
            let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(
                w as u32,
                h as u32,
                |x, y| image::Luma([plane[[y as usize, x as usize]]]),
            );
            img.save(dir.join(&light.name))
                .map_err(std::io::Error::other)?;
        }
        let lights: Vec<serde_json::Value> = (self.lights.iter())
            .map(|l| {
                let e = l.emitter.expect("rig lights have positions");
                serde_json::json!({
                    "name": l.name,
                    "position": e.position,
                    "axis": e.axis,
                    "anisotropy": e.anisotropy,
                    "intensity": l.intensity,
                })
            })
            .collect();
        let table = serde_json::json!({
            "lights": lights,
            "camera": self.camera,
            "distance": self.distance,
            "unit": self.unit,
        });
        let text = serde_json::to_vec_pretty(&table).map_err(std::io::Error::other)?;
        std::fs::write(dir.join("light_directions.json"), text)
    }
}
