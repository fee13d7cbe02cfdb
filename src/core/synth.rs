//! The scenes the project renders for `res/` and its tests: analytic surfaces with exact
//! normals, depth and albedo, lit by distant lights, with optional camera effects (black
//! level, Gaussian noise, quantisation), specular highlights and cast shadows.

use std::path::Path;

use image::{ImageBuffer, Luma, Rgba, Rgba32FImage};
use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::commit::write_atomic;
use super::error::RunError;
use super::intake::LIGHTS_FILE;
use super::outputs::png_bytes_filtered;
use image::codecs::png::FilterType;

/// A surface with ground truth, sampled at pixel centres (x = column, y = row down).
#[derive(Debug, Clone)]
pub struct Scene {
    pub width: usize,
    pub height: usize,
    /// Heights in pixel units (0 off the mask).
    pub depth: Array2<f64>,
    /// Unit normals in the seed frame, zero off the mask.
    pub normals: Array3<f64>,
    pub albedo: Array2<f64>,
    pub mask: Array2<bool>,
}

impl Scene {
    /// Build from an analytic height function returning (z, dz/dx, dz/dy), or None off
    /// the object.
    pub fn from_fn(
        width: usize,
        height: usize,
        surface: impl Fn(f64, f64) -> Option<(f64, f64, f64)> + Sync,
        albedo: impl Fn(f64, f64) -> f64 + Sync,
    ) -> Self {
        let mut depth = Array2::zeros((height, width));
        let mut normals = Array3::zeros((height, width, 3));
        let mut alb = Array2::zeros((height, width));
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
                    alb[[r, c]] = albedo(x, y);
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
        }
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
        let (c, radius) = (0.5 * (s - 1.0), 0.4 * s);
        Self::from_fn(
            size,
            size,
            |x, y| {
                let (dx, dy) = (x - c, y - c);
                let h2 = radius * radius - dx * dx - dy * dy;
                // Stop just inside the rim, where normals are still defined.
                (h2 > (0.05 * radius).powi(2)).then(|| {
                    let z = h2.sqrt();
                    (z, -dx / z, -dy / z)
                })
            },
            |x, y| 0.6 + 0.25 * ((x / s * 9.0).sin() * (y / s * 7.0).sin()),
        )
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
                for &(bx, by, sig, amp) in &bumps {
                    let (dx, dy, sg) = (x - bx * s, y - by * s, sig * s);
                    let g = amp * s * (-(dx * dx + dy * dy) / (2.0 * sg * sg)).exp();
                    z += g;
                    p -= g * dx / (sg * sg);
                    q -= g * dy / (sg * sg);
                }
                Some((z, p, q))
            },
            |x, y| 0.55 + 0.25 * ((x / s * 11.0).cos() * (y / s * 4.0).sin()),
        )
    }

    /// Whether the surface point at (r, c) sees the light `l` (unit, seed frame), by
    /// marching the height field towards it.
    fn lit(&self, r: usize, c: usize, l: [f64; 3], max_z: f64) -> bool {
        let horiz = (l[0] * l[0] + l[1] * l[1]).sqrt();
        if horiz < 1e-9 {
            return true;
        }
        let (dx, dy, rise) = (l[0] / horiz, l[1] / horiz, l[2] / horiz);
        let z0 = self.depth[[r, c]];
        let mut t = 0.5;
        loop {
            let (x, y) = (c as f64 + dx * t, r as f64 + dy * t);
            let ray_z = z0 + rise * t;
            if ray_z > max_z
                || x < 0.0
                || y < 0.0
                || x > (self.width - 1) as f64
                || y > (self.height - 1) as f64
            {
                return true;
            }
            if self.sample_depth(x, y) > ray_z + 1e-6 {
                return false;
            }
            t += 0.5;
        }
    }

    fn sample_depth(&self, x: f64, y: f64) -> f64 {
        let (c0, r0) = (x.floor() as usize, y.floor() as usize);
        let (c1, r1) = ((c0 + 1).min(self.width - 1), (r0 + 1).min(self.height - 1));
        let (fx, fy) = (x - c0 as f64, y - r0 as f64);
        let d = &self.depth;
        (d[[r0, c0]] * (1.0 - fx) + d[[r0, c1]] * fx) * (1.0 - fy)
            + (d[[r1, c0]] * (1.0 - fx) + d[[r1, c1]] * fx) * fy
    }
}

/// How the camera and the material depart from the ideal Lambertian capture.
#[derive(Debug, Clone)]
pub struct Capture {
    pub bit_depth: u8,
    /// Added to every pixel (ambient light + sensor offset), as a fraction of full scale.
    pub black_level: f64,
    /// Standard deviation of additive Gaussian noise, fraction of full scale.
    pub noise_sigma: f64,
    /// Blinn–Phong specular lobe: (strength, shininess).
    pub specular: Option<(f64, f64)>,
    pub cast_shadows: bool,
    pub seed: u64,
}

impl Default for Capture {
    fn default() -> Self {
        Self {
            bit_depth: 16,
            black_level: 0.0,
            noise_sigma: 0.0,
            specular: None,
            cast_shadows: false,
            seed: 1,
        }
    }
}

/// Lights in rings around the view axis: `count` directions with polar angles spread
/// evenly up to `max_polar_deg` and azimuths on a golden-angle spiral.
pub fn light_rings(count: usize, min_polar_deg: f64, max_polar_deg: f64) -> Vec<[f64; 3]> {
    (0..count)
        .map(|i| {
            let t = if count > 1 {
                i as f64 / (count - 1) as f64
            } else {
                0.0
            };
            let polar = (min_polar_deg + t * (max_polar_deg - min_polar_deg)).to_radians();
            let azimuth = i as f64 * 2.399963229728653;
            [
                polar.sin() * azimuth.cos(),
                polar.sin() * azimuth.sin(),
                polar.cos(),
            ]
        })
        .collect()
}

/// Render one image per light, quantised to the capture's bit depth (values 0..=max).
pub fn render(scene: &Scene, lights: &[[f64; 3]], capture: &Capture) -> Vec<Array2<u16>> {
    let max = if capture.bit_depth == 8 {
        255.0
    } else {
        65535.0
    };
    let max_z = scene.depth.iter().cloned().fold(f64::MIN, f64::max);
    lights
        .par_iter()
        .enumerate()
        .map(|(i, l)| {
            let len = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
            let l = l.map(|v| v / len);
            let mut rng = Rng::new(capture.seed.wrapping_mul(1_000_003).wrapping_add(i as u64));
            Array2::from_shape_fn((scene.height, scene.width), |(r, c)| {
                let mut v = capture.black_level;
                if scene.mask[[r, c]] {
                    let n = [
                        scene.normals[[r, c, 0]],
                        scene.normals[[r, c, 1]],
                        scene.normals[[r, c, 2]],
                    ];
                    let ndl = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
                    let visible = ndl > 0.0 && (!capture.cast_shadows || scene.lit(r, c, l, max_z));
                    if visible {
                        v += scene.albedo[[r, c]] * ndl;
                        if let Some((ks, shininess)) = capture.specular {
                            let h = [l[0], l[1], l[2] + 1.0];
                            let hl = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
                            let ndh = (n[0] * h[0] + n[1] * h[1] + n[2] * h[2]) / hl;
                            v += ks * ndh.max(0.0).powf(shininess);
                        }
                    }
                }
                v += capture.noise_sigma * rng.gaussian();
                (v.clamp(0.0, 1.0) * max).round() as u16
            })
        })
        .collect()
}

/// Render one colour image per light, as a white-balanced camera sees a surface of albedo
/// `albedo · tint[c]` in channel c under light i of per-channel intensity
/// `intensities[i][c]`. RGB at the capture's bit depth.
pub fn render_rgb(
    scene: &Scene,
    tint: [f64; 3],
    lights: &[[f64; 3]],
    intensities: &[[f64; 3]],
    capture: &Capture,
) -> Vec<image::DynamicImage> {
    let (w, h) = (scene.width as u32, scene.height as u32);
    lights
        .iter()
        .zip(intensities)
        .enumerate()
        .map(|(i, (l, rgb))| {
            let channels: Vec<Array2<u16>> = (0..3)
                .map(|c| {
                    let mut lit = scene.clone();
                    lit.albedo.mapv_inplace(|a| a * tint[c] * rgb[c]);
                    let seed = capture.seed.wrapping_add((3 * i + c) as u64);
                    let one = Capture { seed, ..*capture };
                    render(&lit, &[*l], &one).remove(0)
                })
                .collect();
            let at = |x: u32, y: u32| channels.iter().map(move |ch| ch[[y as usize, x as usize]]);
            if capture.bit_depth == 8 {
                image::DynamicImage::ImageRgb8(ImageBuffer::from_fn(w, h, |x, y| {
                    let mut v = at(x, y).map(|v| v as u8);
                    image::Rgb([0; 3].map(|_| v.next().unwrap_or(0)))
                }))
            } else {
                image::DynamicImage::ImageRgb16(ImageBuffer::from_fn(w, h, |x, y| {
                    let mut v = at(x, y);
                    image::Rgb([0; 3].map(|_| v.next().unwrap_or(0)))
                }))
            }
        })
        .collect()
}

/// Write a data set in the seed's layout: images `im1.png`…, `light_directions.csv`, and
/// ground truth under `truth/` (`normal.exr`: seed-frame normals with the mask in alpha;
/// `depth.exr`: heights in pixels; `albedo.exr`).
pub fn write_set(
    dir: &Path,
    scene: &Scene,
    lights: &[[f64; 3]],
    capture: &Capture,
) -> Result<(), RunError> {
    let truth = dir.join("truth");
    std::fs::create_dir_all(&truth).map_err(|e| RunError::Output {
        path: truth.display().to_string(),
        reason: e.to_string(),
    })?;
    let images = render(scene, lights, capture);
    let mut csv = String::new();
    for (i, (img, l)) in images.iter().zip(lights).enumerate() {
        let name = format!("im{}.png", i + 1);
        let (w, h) = (scene.width as u32, scene.height as u32);
        let bytes = if capture.bit_depth == 8 {
            png_bytes_filtered(
                &ImageBuffer::<Luma<u8>, Vec<u8>>::from_fn(w, h, |x, y| {
                    Luma([img[[y as usize, x as usize]] as u8])
                }),
                FilterType::Adaptive,
            )
        } else {
            png_bytes_filtered(
                &ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
                    Luma([img[[y as usize, x as usize]]])
                }),
                FilterType::Adaptive,
            )
        };
        write_atomic(dir, &name, &bytes)?;
        csv.push_str(&format!("{name}, {}, {}, {}\n", l[0], l[1], l[2]));
    }
    write_atomic(dir, LIGHTS_FILE, csv.as_bytes())?;
    let exr = |f: &dyn Fn(usize, usize) -> [f32; 4]| {
        let img = Rgba32FImage::from_fn(scene.width as u32, scene.height as u32, |x, y| {
            Rgba(f(y as usize, x as usize))
        });
        let mut out = std::io::Cursor::new(Vec::new());
        image::DynamicImage::ImageRgba32F(img)
            .write_to(&mut out, image::ImageFormat::OpenExr)
            .expect("EXR encodes in memory");
        out.into_inner()
    };
    let m = |r: usize, c: usize| if scene.mask[[r, c]] { 1.0 } else { 0.0 };
    let n = &scene.normals;
    write_atomic(
        &truth,
        "normal.exr",
        &exr(&|r, c| {
            [
                n[[r, c, 0]] as f32,
                n[[r, c, 1]] as f32,
                n[[r, c, 2]] as f32,
                m(r, c),
            ]
        }),
    )?;
    let d = |r: usize, c: usize| scene.depth[[r, c]] as f32;
    write_atomic(
        &truth,
        "depth.exr",
        &exr(&|r, c| [d(r, c), d(r, c), d(r, c), m(r, c)]),
    )?;
    let a = |r: usize, c: usize| scene.albedo[[r, c]] as f32;
    write_atomic(
        &truth,
        "albedo.exr",
        &exr(&|r, c| [a(r, c), a(r, c), a(r, c), m(r, c)]),
    )?;
    Ok(())
}

/// Ground truth read back from a set's `truth/` folder.
pub struct Truth {
    pub normals: Array3<f32>,
    pub depth: Array2<f32>,
    pub albedo: Array2<f32>,
    pub mask: Array2<bool>,
}

/// Read `truth/normal.exr`, `truth/depth.exr` and `truth/albedo.exr` of a data set.
pub fn read_truth(dir: &Path) -> image::ImageResult<Truth> {
    let open = |n: &str| image::open(dir.join("truth").join(n)).map(|i| i.to_rgba32f());
    let (normal, depth, albedo) = (open("normal.exr")?, open("depth.exr")?, open("albedo.exr")?);
    let (w, h) = normal.dimensions();
    let px =
        |img: &Rgba32FImage, r: usize, c: usize, k: usize| img.get_pixel(c as u32, r as u32).0[k];
    Ok(Truth {
        normals: Array3::from_shape_fn((h as usize, w as usize, 3), |(r, c, k)| {
            px(&normal, r, c, k)
        }),
        depth: Array2::from_shape_fn((h as usize, w as usize), |(r, c)| px(&depth, r, c, 0)),
        albedo: Array2::from_shape_fn((h as usize, w as usize), |(r, c)| px(&albedo, r, c, 0)),
        mask: Array2::from_shape_fn((h as usize, w as usize), |(r, c)| {
            px(&normal, r, c, 3) > 0.5
        }),
    })
}

/// The data sets `photostereo render` writes into `res/`: name, scene, lights, capture.
pub fn catalogue() -> Vec<(&'static str, Scene, Vec<[f64; 3]>, Capture)> {
    let seed_lights = vec![
        [0.0, 0.0, 1.0],
        [-0.2, 0.0, 1.0],
        [0.2, 0.0, 1.0],
        [0.0, -0.2, 1.0],
    ];
    let sphere_lights = light_rings(24, 10.0, 60.0);
    let low_lights: Vec<[f64; 3]> = (0..24)
        .map(|i| {
            let elevation = (15.0 + 25.0 * (i % 6) as f64 / 5.0).to_radians();
            let azimuth = i as f64 * std::f64::consts::TAU / 24.0 + 0.3;
            [
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            ]
        })
        .collect();
    let noisy = Capture {
        black_level: 0.02,
        noise_sigma: 0.004,
        seed: 7,
        ..Capture::default()
    };
    vec![
        (
            "bump",
            Scene::bump(128),
            seed_lights.clone(),
            Capture::default(),
        ),
        (
            "bump-noisy",
            Scene::bump(128),
            seed_lights,
            Capture {
                bit_depth: 8,
                noise_sigma: 0.01,
                seed: 3,
                ..Capture::default()
            },
        ),
        (
            "sphere",
            Scene::sphere(256),
            sphere_lights.clone(),
            Capture::default(),
        ),
        (
            "sphere-noisy",
            Scene::sphere(256),
            sphere_lights.clone(),
            noisy.clone(),
        ),
        (
            "sphere-specular",
            Scene::sphere(256),
            sphere_lights,
            Capture {
                specular: Some((0.6, 40.0)),
                ..Capture::default()
            },
        ),
        (
            "shadows",
            Scene::shadows(192),
            low_lights.clone(),
            Capture {
                cast_shadows: true,
                ..Capture::default()
            },
        ),
        (
            "shadows-noisy",
            Scene::shadows(192),
            low_lights,
            Capture {
                bit_depth: 8,
                black_level: 0.01,
                noise_sigma: 0.01,
                cast_shadows: true,
                seed: 11,
                ..Capture::default()
            },
        ),
    ]
}

/// A small, fast, seedable generator (SplitMix64) for reproducible noise.
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Self(seed)
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// Standard normal by Box–Muller.
    fn gaussian(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normals_are_unit_and_match_depth_slopes() {
        let s = Scene::bump(64);
        for (r, c) in [(10, 10), (30, 40), (50, 20)] {
            let n: f64 = (0..3).map(|k| s.normals[[r, c, k]].powi(2)).sum();
            assert!((n - 1.0).abs() < 1e-12);
            let p_fd = (s.depth[[r, c + 1]] - s.depth[[r, c - 1]]) / 2.0;
            let p = -s.normals[[r, c, 0]] / s.normals[[r, c, 2]];
            assert!((p - p_fd).abs() < 0.01, "{p} vs {p_fd}");
        }
    }

    #[test]
    fn cast_shadows_darken_the_far_side_of_a_bump() {
        let s = Scene::shadows(96);
        let low = [(10f64).to_radians().cos(), 0.0, (10f64).to_radians().sin()];
        let lit = render(&s, &[low], &Capture::default());
        let shadowed = render(
            &s,
            &[low],
            &Capture {
                cast_shadows: true,
                ..Capture::default()
            },
        );
        let dark: usize = lit[0]
            .iter()
            .zip(shadowed[0].iter())
            .filter(|(a, b)| a > b)
            .count();
        assert!(dark > 50, "{dark} pixels in cast shadow");
        assert!(lit[0].iter().zip(shadowed[0].iter()).all(|(a, b)| a >= b));
    }

    #[test]
    fn noise_has_the_requested_spread() {
        let mut rng = Rng::new(3);
        let v: Vec<f64> = (0..20000).map(|_| rng.gaussian()).collect();
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64;
        assert!(mean.abs() < 0.03 && (var.sqrt() - 1.0).abs() < 0.03);
    }
}
