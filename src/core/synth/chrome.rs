//! Light-calibration captures: a mirror (chrome) sphere photographed once per light by an
//! orthographic camera, and a matte white sphere under the same lights.
//!
//! Each pixel integrates the environment the ball reflects over its footprint
//! (`SUPERSAMPLE`² samples), so a light of finite angular size leaves a highlight with a
//! real, finite shape: round near the ball's centre, squeezed towards the rim. The
//! environment is a dim room, the light (a disc of `light_radius_deg`), a bright diffuse
//! object beside the ball and a thin streak from another fixture; outside the ball a
//! textured backdrop (stripes and a checkerboard) lit by the same light.

use std::path::Path;

use image::{ImageBuffer, Luma};
use ndarray::Array2;
use rayon::prelude::*;

use super::brdf::normalise;
use super::sensor::{self, Rng};
use crate::core::commit::write_atomic;
use crate::core::error::RunError;
use crate::core::outputs::png_bytes;

/// The folder of a set's true lights and circle.
pub const TRUTH: &str = "truth-lights";

/// Samples per pixel side.
const SUPERSAMPLE: usize = 6;

/// Mirror reflectance of the chrome (roughly constant with angle for a metal).
const CHROME: f64 = 0.65;

/// A calibration capture: the frame, the ball, the lights and the camera.
#[derive(Debug, Clone)]
pub struct ChromeSet {
    pub width: usize,
    pub height: usize,
    /// Ball centre (column, row; pixel centres at integers) and radius, pixels.
    pub centre: [f64; 2],
    pub radius: f64,
    /// Unit light directions (x right, y down, z towards the camera).
    pub lights: Vec<[f64; 3]>,
    /// Each light's highlight level as a fraction of full scale (above 1 it clips).
    pub highlight: Vec<f64>,
    /// Angular radius of each light (a uniform disc), degrees.
    pub light_radius_deg: f64,
    /// Brightness of the room the ball reflects and of the backdrop around it, as
    /// fractions of full scale.
    pub room: f64,
    pub backdrop: f64,
    /// A bright diffuse object beside the ball and a streak from another fixture.
    pub distractors: bool,
    pub bit_depth: u8,
    pub noise_sigma: f64,
    pub black_level: f64,
    pub seed: u64,
}

impl ChromeSet {
    /// The usual capture: 24 lights from 10° to 80° off the view axis (the last ones at
    /// grazing elevation, highlights near 0.64 of the radius), every third clipping, on an
    /// off-centre ball with distractors.
    pub fn standard(bit_depth: u8, seed: u64) -> Self {
        let lights = super::light_rings(24, 10.0, 80.0);
        let highlight = (0..lights.len())
            .map(|i| [0.75, 0.9, 2.5][i % 3] + 0.02 * (i % 5) as f64)
            .collect();
        Self {
            width: 320,
            height: 240,
            centre: [187.3, 109.6],
            radius: 93.4,
            lights,
            highlight,
            light_radius_deg: 1.8,
            room: 0.22,
            backdrop: 0.45,
            distractors: true,
            bit_depth,
            noise_sigma: 0.004,
            black_level: 0.01,
            seed,
        }
    }

    /// A ball filling most of the frame (its outline 2–20 px from the border), dark on a
    /// dark backdrop, with 3° lights.
    pub fn filling(bit_depth: u8, seed: u64) -> Self {
        Self {
            width: 256,
            height: 224,
            centre: [129.6, 112.3],
            radius: 109.2,
            light_radius_deg: 3.0,
            room: 0.05,
            backdrop: 0.03,
            ..Self::standard(bit_depth, seed)
        }
    }

    fn max(&self) -> f64 {
        if self.bit_depth == 8 { 255.0 } else { 65535.0 }
    }

    /// One image per light of the chrome ball.
    pub fn render(&self) -> Vec<Array2<u16>> {
        self.lights
            .par_iter()
            .enumerate()
            .map(|(i, &l)| {
                let light = Light {
                    direction: normalise(l),
                    level: self.highlight[i],
                    cos_radius: self.light_radius_deg.to_radians().cos(),
                };
                let img = self.supersampled(|x, y| match self.ball_normal(x, y) {
                    Some(n) => CHROME * self.environment(reflect(n), &light),
                    None => self.backdrop_at(x, y, l),
                });
                self.expose(img, i)
            })
            .collect()
    }

    /// One image per light of a matte white sphere (albedo 0.8, Lambertian) of the same
    /// size and place, each light with its intensity, on the same backdrop.
    pub fn render_matte(&self, intensities: &[f64]) -> Vec<Array2<u16>> {
        self.lights
            .par_iter()
            .zip(intensities)
            .enumerate()
            .map(|(i, (&l, &k))| {
                let img = self.supersampled(|x, y| match self.ball_normal(x, y) {
                    Some(n) => 0.02 + 0.6 * k * dot(n, l).max(0.0),
                    None => self.backdrop_at(x, y, l),
                });
                self.expose(img, i + 1000)
            })
            .collect()
    }

    /// The mean of `f` over each pixel's footprint.
    fn supersampled(&self, f: impl Fn(f64, f64) -> f64 + Sync) -> Array2<f64> {
        let s = SUPERSAMPLE as f64;
        Array2::from_shape_fn((self.height, self.width), |(r, c)| {
            let mut sum = 0.0;
            for j in 0..SUPERSAMPLE {
                for i in 0..SUPERSAMPLE {
                    let x = c as f64 - 0.5 + (i as f64 + 0.5) / s;
                    let y = r as f64 - 0.5 + (j as f64 + 0.5) / s;
                    sum += f(x, y);
                }
            }
            sum / (s * s)
        })
    }

    fn expose(&self, img: Array2<f64>, index: usize) -> Array2<u16> {
        let noise = sensor::Noise {
            black_level: self.black_level,
            read_sigma: self.noise_sigma,
            full_well: Some(20_000.0),
        };
        let mut rng = Rng::new(self.seed.wrapping_mul(1_000_003).wrapping_add(index as u64));
        let shaped = img.insert_axis(ndarray::Axis(2));
        sensor::capture(&shaped, 1.0, noise, self.max(), &mut rng).remove_axis(ndarray::Axis(2))
    }

    /// The ball's unit normal at image point (x, y), if the ball covers it.
    fn ball_normal(&self, x: f64, y: f64) -> Option<[f64; 3]> {
        let (u, v) = (
            (x - self.centre[0]) / self.radius,
            (y - self.centre[1]) / self.radius,
        );
        let h = 1.0 - u * u - v * v;
        (h > 0.0).then(|| [u, v, h.sqrt()])
    }

    /// What the ball reflects along unit direction `d`.
    fn environment(&self, d: [f64; 3], light: &Light) -> f64 {
        if dot(d, light.direction) > light.cos_radius {
            return light.level / CHROME;
        }
        // A room: walls with soft structure, a darker floor and the dark camera side.
        let mut v = self.room
            * (0.7 + 0.2 * (3.0 * d[0]).sin() * (2.0 * d[1]).cos() - 0.15 * d[1] + 0.1 * d[2]);
        if self.distractors {
            // A white box beside the ball, lit by the light (a ~16° patch).
            let side = normalise([0.93, 0.12, 0.35]);
            if dot(d, side) > 16f64.to_radians().cos() {
                v = 0.55 * (0.5 + 0.5 * dot(light.direction, normalise([-1.0, -0.2, 0.6])));
            }
            // A fluorescent tube: 0.5° thick along 30° of a great circle.
            let (mid, axis) = (normalise([-0.45, -0.55, 0.7]), normalise([0.8, -0.3, 0.3]));
            let plane = normalise(cross(mid, axis));
            if dot(d, plane).abs() < 0.25f64.to_radians().sin()
                && dot(d, mid) > 15f64.to_radians().cos()
            {
                v = 0.9;
            }
        }
        v
    }

    /// The backdrop: stripes and a checkerboard, lit by `l`.
    fn backdrop_at(&self, x: f64, y: f64, l: [f64; 3]) -> f64 {
        let checker = if ((x / 23.0).floor() + (y / 17.0).floor()) as i64 % 2 == 0 {
            1.0
        } else {
            0.6
        };
        let stripes = 0.8 + 0.2 * (x / 4.1 + 0.6 * y / 9.0).sin();
        self.backdrop * checker * stripes * (0.75 + 0.25 * l[2])
    }

    /// Write the set: `ball01.png`…, `names.txt` naming the object images `im1.png`… in
    /// the same order, and the true light table as `truth-lights/light_directions.csv`
    /// (with the intensities when given) and the ball as `truth-lights/circle.txt`
    /// (`cx, cy, r`). Not `truth/`: that holds the maps of the reconstruction sets.
    /// With `matte`, the matte sphere's images go to `<dir>/matte/`.
    pub fn write(&self, dir: &Path, matte: Option<&[f64]>) -> Result<(), RunError> {
        let truth = dir.join(TRUTH);
        std::fs::create_dir_all(&truth).map_err(|e| RunError::Output {
            path: truth.display().to_string(),
            reason: e.to_string(),
        })?;
        self.write_images(dir, "ball", &self.render())?;
        if let Some(k) = matte {
            let matte_dir = dir.join("matte");
            std::fs::create_dir_all(&matte_dir).map_err(|e| RunError::Output {
                path: matte_dir.display().to_string(),
                reason: e.to_string(),
            })?;
            self.write_images(&matte_dir, "matte", &self.render_matte(k))?;
        }
        let names: Vec<String> = (1..=self.lights.len())
            .map(|i| format!("im{i}.png"))
            .collect();
        write_atomic(dir, "names.txt", (names.join("\n") + "\n").as_bytes())?;
        let mut csv = String::new();
        for (i, (name, l)) in names.iter().zip(&self.lights).enumerate() {
            csv.push_str(&format!("{name}, {}, {}, {}", l[0], l[1], l[2]));
            if let Some(k) = matte {
                csv.push_str(&format!(", {}", k[i]));
            }
            csv.push('\n');
        }
        write_atomic(&truth, "light_directions.csv", csv.as_bytes())?;
        let circle = format!("{}, {}, {}\n", self.centre[0], self.centre[1], self.radius);
        write_atomic(&truth, "circle.txt", circle.as_bytes())
    }

    fn write_images(&self, dir: &Path, stem: &str, images: &[Array2<u16>]) -> Result<(), RunError> {
        for (i, img) in images.iter().enumerate() {
            let (h, w) = img.dim();
            let at = |x: u32, y: u32| img[[y as usize, x as usize]];
            let bytes = if self.bit_depth == 8 {
                png_bytes(&ImageBuffer::<Luma<u8>, Vec<u8>>::from_fn(
                    w as u32,
                    h as u32,
                    |x, y| Luma([at(x, y) as u8]),
                ))
            } else {
                png_bytes(&ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(
                    w as u32,
                    h as u32,
                    |x, y| Luma([at(x, y)]),
                ))
            };
            write_atomic(dir, &format!("{stem}{:02}.png", i + 1), &bytes)?;
        }
        Ok(())
    }
}

/// Relative light intensities for a matte set, 0.6–1.4, reproducible from `seed`.
pub fn matte_intensities(count: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng::new(seed);
    (0..count).map(|_| 0.6 + 0.8 * rng.uniform()).collect()
}

struct Light {
    direction: [f64; 3],
    level: f64,
    cos_radius: f64,
}

/// The direction the camera sees reflected at a point of normal `n` (view along +z).
fn reflect(n: [f64; 3]) -> [f64; 3] {
    let k = 2.0 * n[2];
    [k * n[0], k * n[1], k * n[2] - 1.0]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
