//! Data sets on disk in the seed's layout, with ground truth, and the truth read back.

use std::path::Path;

use image::codecs::png::FilterType;
use image::{ImageBuffer, Luma, Rgb, Rgba, Rgba32FImage};
use ndarray::{Array2, Array3};

use super::capture::Capture;
use super::render::render;
use super::scene::Scene;
use crate::core::commit::write_atomic;
use crate::core::error::RunError;
use crate::core::intake::{LIGHTS_FILE, LUMA_WEIGHTS};
use crate::core::outputs::png_bytes_filtered;

/// Write a data set in the seed's layout: images `im1.png`… (gray, or RGB for an RGB
/// scene), `light_directions.csv` (`name, x, y, z`, or `name, x, y, z, r, g, b` with the
/// capture's light colours), and ground truth under `truth/` (`normal.exr`: seed-frame
/// normals with the mask in alpha; `depth.exr`: heights in pixels; `albedo.exr`: the
/// diffuse albedo per channel, gray in RGB for a gray scene, times the exposure gain so
/// that it is the albedo the images show under a unit light). A perspective scene (one
/// with a camera) writes camera-frame normals, depth along the optical axis in
/// `depth.exr`, and its camera beside the images as `K.txt` (3 × 3) and `camera.json`.
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
    let rendered = render(scene, lights, capture);
    let mut csv = String::new();
    for (i, (img, l)) in rendered.images.iter().zip(lights).enumerate() {
        let name = format!("im{}.png", i + 1);
        write_atomic(dir, &name, &png(img, capture.bit_depth))?;
        csv.push_str(&format!("{name}, {}, {}, {}", l[0], l[1], l[2]));
        if let Some(colours) = &capture.light_colours {
            let [r, g, b] = colours[i];
            csv.push_str(&format!(", {r}, {g}, {b}"));
        }
        csv.push('\n');
    }
    write_atomic(dir, LIGHTS_FILE, csv.as_bytes())?;
    if let Some(k) = scene.camera {
        let text = format!("{} 0 {}\n0 {} {}\n0 0 1\n", k.fx, k.cx, k.fy, k.cy);
        write_atomic(dir, "K.txt", text.as_bytes())?;
        let json = serde_json::to_vec_pretty(&k).expect("a camera serialises");
        write_atomic(dir, "camera.json", &json)?;
    }
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
    let last = scene.channels() - 1;
    let a =
        |r: usize, c: usize, k: usize| (rendered.gain * scene.albedo[[r, c, k.min(last)]]) as f32;
    write_atomic(
        &truth,
        "albedo.exr",
        &exr(&|r, c| [a(r, c, 0), a(r, c, 1), a(r, c, 2), m(r, c)]),
    )?;
    Ok(())
}

/// A PNG of one image: 8- or 16-bit, gray or RGB by its channel count.
fn png(img: &Array3<u16>, bit_depth: u8) -> Vec<u8> {
    let (h, w, channels) = img.dim();
    let (w, h) = (w as u32, h as u32);
    let at = |x: u32, y: u32, k: usize| img[[y as usize, x as usize, k]];
    match (channels, bit_depth) {
        (1, 8) => png_bytes_filtered(
            &ImageBuffer::<Luma<u8>, Vec<u8>>::from_fn(w, h, |x, y| Luma([at(x, y, 0) as u8])),
            FilterType::Adaptive,
        ),
        (1, _) => png_bytes_filtered(
            &ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| Luma([at(x, y, 0)])),
            FilterType::Adaptive,
        ),
        (_, 8) => png_bytes_filtered(
            &ImageBuffer::<Rgb<u8>, Vec<u8>>::from_fn(w, h, |x, y| {
                Rgb([0, 1, 2].map(|k| at(x, y, k) as u8))
            }),
            FilterType::Adaptive,
        ),
        _ => png_bytes_filtered(
            &ImageBuffer::<Rgb<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
                Rgb([0, 1, 2].map(|k| at(x, y, k)))
            }),
            FilterType::Adaptive,
        ),
    }
}

/// Ground truth read back from a set's `truth/` folder.
pub struct Truth {
    pub normals: Array3<f32>,
    pub depth: Array2<f32>,
    /// The Rec. 709 luminance 0.2126 R + 0.7152 G + 0.0722 B of `albedo.exr` (for a gray
    /// scene, its gray value).
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
    let luminance = |r: usize, c: usize| {
        (0..3)
            .map(|k| LUMA_WEIGHTS[k] * px(&albedo, r, c, k))
            .sum::<f32>()
    };
    Ok(Truth {
        normals: Array3::from_shape_fn((h as usize, w as usize, 3), |(r, c, k)| {
            px(&normal, r, c, k)
        }),
        depth: Array2::from_shape_fn((h as usize, w as usize), |(r, c)| px(&depth, r, c, 0)),
        albedo: Array2::from_shape_fn((h as usize, w as usize), |(r, c)| luminance(r, c)),
        mask: Array2::from_shape_fn((h as usize, w as usize), |(r, c)| {
            px(&normal, r, c, 3) > 0.5
        }),
    })
}
