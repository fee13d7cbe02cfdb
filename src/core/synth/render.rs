//! One image per light: direct light (point or area, with cast shadows), a specular lobe,
//! one bounce of interreflection, then the camera.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::brdf::Diffuse;
use super::capture::Capture;
use super::scene::Scene;
use super::sensor::{self, Rng};
use super::transport::{Bounces, Field, Horizons, turn};
use crate::core::vec3::normalise;

/// The rendered images `(rows, cols, channels)`, 0..=max of the capture's bit depth,
/// and the exposure gain that produced them.
pub struct Rendered {
    pub images: Vec<Array3<u16>>,
    pub gain: f64,
}

/// Render one image per light (directions need not be unit length).
///
/// Cast shadows and interreflection march the scene as an orthographic height field: a
/// perspective scene (one with a camera) takes neither.
pub fn render(scene: &Scene, lights: &[[f64; 3]], capture: &Capture) -> Rendered {
    assert!(
        scene.camera.is_none() || !(capture.cast_shadows || capture.bounce_rays.is_some()),
        "cast shadows and interreflection need an orthographic scene"
    );
    let max = if capture.bit_depth == 8 {
        255.0
    } else {
        65535.0
    };
    let field = Field::new(scene);
    let horizons =
        (capture.cast_shadows && capture.area_light.is_some()).then(|| Horizons::trace(&field));
    let bounces = capture
        .bounce_rays
        .map(|rays| Bounces::trace(&field, rays, capture.seed));
    let light: Vec<Array3<f64>> = lights
        .par_iter()
        .enumerate()
        .map(|(i, l)| {
            let occluders = Occluders {
                field: &field,
                horizons: horizons.as_ref(),
            };
            scene_light(&occluders, bounces.as_ref(), i, normalise(*l), capture)
        })
        .collect();
    let peak = light
        .iter()
        .flat_map(|img| img.iter())
        .cloned()
        .fold(0.0, f64::max);
    let gain = capture.exposure.gain(peak);
    let noise = sensor::Noise {
        black_level: capture.black_level,
        read_sigma: capture.noise_sigma,
        full_well: capture.full_well,
    };
    let images = light
        .par_iter()
        .enumerate()
        .map(|(i, img)| {
            let mut rng = Rng::new(capture.seed.wrapping_mul(1_000_003).wrapping_add(i as u64));
            sensor::capture(img, gain, noise, max, &mut rng)
        })
        .collect();
    Rendered { images, gain }
}

/// The light reaching the camera from each pixel under light `index` (unit `l`), per
/// channel, before exposure: intensity_c · (albedo_c · E + tint_c · specular) +
/// albedo_c · E_bounce_c, E the diffuse model's shading.
fn scene_light(
    occluders: &Occluders,
    bounces: Option<&Bounces>,
    index: usize,
    l: [f64; 3],
    capture: &Capture,
) -> Array3<f64> {
    let s = occluders.field.scene;
    let channels = s.channels();
    let colour = capture
        .light_colours
        .as_ref()
        .map_or([1.0; 3], |c| c[index]);
    // A gray scene has one channel: its lobe takes the tint's first.
    let tint = capture.specular_tint;
    let mut irradiance = Array2::zeros((s.height, s.width));
    let mut specular = Array2::zeros((s.height, s.width));
    for ((r, c), &inside) in s.mask.indexed_iter() {
        if inside {
            let (e, sp) = direct(
                occluders,
                r,
                c,
                l,
                capture,
                turn(capture.seed, index, r * s.width + c),
            );
            irradiance[[r, c]] = e;
            specular[[r, c]] = sp;
        }
    }
    let mut out = Array3::from_shape_fn((s.height, s.width, channels), |(r, c, k)| {
        colour[k] * (s.albedo[[r, c, k]] * irradiance[[r, c]] + tint[k] * specular[[r, c]])
    });
    if let Some(b) = bounces {
        for k in 0..channels {
            let radiosity = Array2::from_shape_fn((s.height, s.width), |(r, c)| {
                colour[k] * s.albedo[[r, c, k]] * irradiance[[r, c]]
            });
            let bounced = b.gather(&radiosity);
            for ((r, c), e) in bounced.indexed_iter() {
                out[[r, c, k]] += s.albedo[[r, c, k]] * e;
            }
        }
    }
    out
}

/// Direct diffuse shading at (r, c) from a unit light along `l` (mean of max(0, n·l),
/// times the diffuse model's factor, over the light's directions that the surface does not
/// hide), and the specular value.
fn direct(
    occluders: &Occluders,
    r: usize,
    c: usize,
    l: [f64; 3],
    capture: &Capture,
    turn: f64,
) -> (f64, f64) {
    let s = occluders.field.scene;
    let n = [
        s.normals[[r, c, 0]],
        s.normals[[r, c, 1]],
        s.normals[[r, c, 2]],
    ];
    let sample = |d: [f64; 3], sums: &mut (f64, f64)| {
        let ndl = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
        if ndl > 0.0 && (!capture.cast_shadows || occluders.lit(r, c, d)) {
            sums.0 += match capture.diffuse {
                // Kept apart so Lambertian scenes render exactly as before.
                Diffuse::Lambert => ndl,
                rough => ndl * rough.factor(n, d),
            };
            if let Some(spec) = capture.specular {
                sums.1 += spec.value(n, d);
            }
        }
    };
    let mut sums = (0.0, 0.0);
    match capture.area_light {
        None => sample(l, &mut sums),
        Some(area) => {
            for d in area.directions(l, turn) {
                sample(d, &mut sums);
            }
            let k = area.samples as f64;
            sums = (sums.0 / k, sums.1 / k);
        }
    }
    sums
}

/// What hides a light from a pixel: the height field itself, marched along a point
/// light's one direction, or its horizon map for an area light's many.
struct Occluders<'a> {
    field: &'a Field<'a>,
    horizons: Option<&'a Horizons>,
}

impl Occluders<'_> {
    fn lit(&self, r: usize, c: usize, d: [f64; 3]) -> bool {
        match self.horizons {
            Some(h) => h.clears(r, c, d),
            None => self.field.lit(r, c, d),
        }
    }
}

/// Render one colour image per light, as a white-balanced camera sees the scene's gray
/// albedo tinted by `tint` under light i of per-channel intensity `intensities[i]`: RGB
/// at the capture's bit depth, for tests that write their own folder layouts.
pub fn render_rgb(
    scene: &Scene,
    tint: [f64; 3],
    lights: &[[f64; 3]],
    intensities: &[[f64; 3]],
    capture: &Capture,
) -> Vec<image::DynamicImage> {
    let gray = scene.albedo.clone();
    let tinted = scene
        .clone()
        .with_colour(|x, y| tint.map(|t| t * gray[[y as usize, x as usize, 0]]));
    let capture = Capture {
        light_colours: Some(intensities.to_vec()),
        ..capture.clone()
    };
    let rendered = render(&tinted, lights, &capture);
    rendered
        .images
        .iter()
        .map(|img| {
            let (h, w, _) = img.dim();
            let at = |x: u32, y: u32| [0, 1, 2].map(|k| img[[y as usize, x as usize, k]]);
            if capture.bit_depth == 8 {
                image::DynamicImage::ImageRgb8(image::ImageBuffer::from_fn(
                    w as u32,
                    h as u32,
                    |x, y| image::Rgb(at(x, y).map(|v| v as u8)),
                ))
            } else {
                image::DynamicImage::ImageRgb16(image::ImageBuffer::from_fn(
                    w as u32,
                    h as u32,
                    |x, y| image::Rgb(at(x, y)),
                ))
            }
        })
        .collect()
}
