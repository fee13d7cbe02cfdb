//! Encoders: the PNG/EXR pictures of a reconstruction and `result.json`, written in
//! parallel, each under a temporary name and renamed once complete.

use std::io::Cursor;
use std::path::Path;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ImageBuffer, ImageEncoder, ImageFormat, Luma, Rgb, Rgba, Rgba32FImage};
use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::InputError;
use super::pipeline::{Reconstruction, RunError};
use super::render;

/// Every artifact a job can produce: file name and Content-Type.
pub const ARTIFACTS: &[(&str, &str)] = &[
    ("albedo.png", "image/png"),
    ("albedo_rgb.png", "image/png"),
    ("mask.png", "image/png"),
    ("normal.png", "image/png"),
    ("normal_x.png", "image/png"),
    ("normal_y.png", "image/png"),
    ("normal_z.png", "image/png"),
    ("height.png", "image/png"),
    ("normal.exr", "image/x-exr"),
    ("height.exr", "image/x-exr"),
    ("needle.png", "image/png"),
    ("curl.png", "image/png"),
    ("confidence.png", "image/png"),
    ("unreliable.png", "image/png"),
    ("shaded.png", "image/png"),
    ("preview.png", "image/png"),
    ("mesh.glb", "model/gltf-binary"),
    ("mesh.gltf", "model/gltf+json"),
    ("result.json", "application/json"),
];

/// Content-Type of an artifact, or None when the name is not one.
pub fn content_type(name: &str) -> Option<&'static str> {
    ARTIFACTS.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// Check an `outputs` selection names only known artifacts.
pub fn check_selection(names: &[String]) -> Result<(), InputError> {
    match names.iter().find(|n| content_type(n).is_none()) {
        Some(bad) => Err(InputError::Options(format!(
            "unknown output {bad:?}; known: {}",
            ARTIFACTS
                .iter()
                .map(|(n, _)| *n)
                .collect::<Vec<_>>()
                .join(", ")
        ))),
        None => Ok(()),
    }
}

/// Encode a picture as PNG with fast compression (outputs are written on every job; the
/// few percent that maximum compression saves is not worth several times the time).
pub fn png_bytes<P, C>(img: &ImageBuffer<P, C>) -> Vec<u8>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(
            image::EncodableLayout::as_bytes(&**img),
            img.width(),
            img.height(),
            P::COLOR_TYPE,
        )
        .expect("encoding a PNG into memory cannot fail");
    out
}

fn exr_bytes(img: &Rgba32FImage) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    DynamicImage::ImageRgba32F(img.clone())
        .write_to(&mut out, ImageFormat::OpenExr)
        .expect("encoding EXR into memory cannot fail");
    out.into_inner()
}

fn gray16(values: &Array2<f32>, map: impl Fn(f32) -> f32 + Sync) -> Vec<u8> {
    let (rows, cols) = values.dim();
    let img = ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(cols as u32, rows as u32, |x, y| {
        let v = map(values[[y as usize, x as usize]]).clamp(0.0, 1.0);
        Luma([(v * 65535.0).round() as u16])
    });
    png_bytes(&img)
}

fn binary(m: &Array2<bool>) -> Vec<u8> {
    let (rows, cols) = m.dim();
    let img = ImageBuffer::<Luma<u8>, Vec<u8>>::from_fn(cols as u32, rows as u32, |x, y| {
        Luma([if m[[y as usize, x as usize]] { 255 } else { 0 }])
    });
    png_bytes(&img)
}

/// Normal in the OpenGL normal-map frame (x right, y up, z to viewer) from the seed frame.
fn gl_normal(n: &Array3<f32>, r: usize, c: usize) -> [f32; 3] {
    [n[[r, c, 0]], -n[[r, c, 1]], n[[r, c, 2]]]
}

/// Encode one named artifact (mesh files excepted), or None if it does not apply.
pub fn encode(rec: &Reconstruction, name: &str, shading_light: [f64; 3]) -> Option<Vec<u8>> {
    let (rows, cols) = (rec.height, rec.width);
    let (w, h) = (cols as u32, rows as u32);
    let mask = &rec.mask;
    let bytes = match name {
        "albedo.png" => gray16(&rec.albedo, |a| a),
        "albedo_rgb.png" => {
            let rgb = rec.albedo_rgb.as_ref()?;
            let img = ImageBuffer::<Rgb<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
                Rgb([0, 1, 2].map(|k| {
                    (rgb[[y as usize, x as usize, k]].clamp(0.0, 1.0) * 65535.0).round() as u16
                }))
            });
            png_bytes(&img)
        }
        "mask.png" => binary(mask),
        "unreliable.png" => binary(&rec.unreliable),
        "confidence.png" => gray16(&rec.confidence, |v| v),
        "normal.png" => {
            let img = ImageBuffer::<Rgb<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
                let (r, c) = (y as usize, x as usize);
                if !mask[[r, c]] {
                    return Rgb([0, 0, 0]);
                }
                Rgb(gl_normal(&rec.normals, r, c)
                    .map(|v| ((v + 1.0) * 0.5 * 65535.0).round().clamp(0.0, 65535.0) as u16))
            });
            png_bytes(&img)
        }
        "normal_x.png" | "normal_y.png" | "normal_z.png" => {
            let k = match name {
                "normal_x.png" => 0,
                "normal_y.png" => 1,
                _ => 2,
            };
            let comp = Array2::from_shape_fn((rows, cols), |(r, c)| {
                if mask[[r, c]] {
                    (rec.normals[[r, c, k]] + 1.0) * 0.5
                } else {
                    0.0
                }
            });
            gray16(&comp, |v| v)
        }
        "height.png" => {
            let (lo, hi) = (rec.report.height_min, rec.report.height_max);
            let span = if hi > lo { hi - lo } else { 1.0 };
            let z = Array2::from_shape_fn((rows, cols), |(r, c)| {
                if mask[[r, c]] {
                    (rec.heights[[r, c]] - lo) / span
                } else {
                    0.0
                }
            });
            gray16(&z, |v| v)
        }
        "normal.exr" => {
            let img = Rgba32FImage::from_fn(w, h, |x, y| {
                let (r, c) = (y as usize, x as usize);
                let [nx, ny, nz] = gl_normal(&rec.normals, r, c);
                Rgba([nx, ny, nz, if mask[[r, c]] { 1.0 } else { 0.0 }])
            });
            exr_bytes(&img)
        }
        "height.exr" => {
            let img = Rgba32FImage::from_fn(w, h, |x, y| {
                let (r, c) = (y as usize, x as usize);
                let z = rec.heights[[r, c]];
                Rgba([z, z, z, if mask[[r, c]] { 1.0 } else { 0.0 }])
            });
            exr_bytes(&img)
        }
        "needle.png" => png_bytes(&render::needle_map(&rec.albedo, &rec.normals, mask)),
        "curl.png" => png_bytes(&render::diverging(&rec.curl, mask)),
        "shaded.png" => gray16(
            &render::shade(&rec.albedo, &rec.normals, shading_light),
            |v| v,
        ),
        _ => return None,
    };
    Some(bytes)
}

/// Write `bytes` to `dir/name` through a temporary file, so a reader never sees a
/// partial artifact.
pub fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), RunError> {
    let tmp = dir.join(format!(".{name}.tmp"));
    let path = dir.join(name);
    let fail = |e: std::io::Error| RunError::Output {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    {
        use std::io::Write;
        let mut f = std::fs::File::create(&tmp).map_err(fail)?;
        f.write_all(bytes).map_err(fail)?;
        f.sync_all().map_err(fail)?;
    }
    std::fs::rename(&tmp, &path).map_err(fail)
}

/// Write the picture artifacts `names` in parallel; returns the names written (an
/// artifact that does not apply, such as `albedo_rgb.png` for gray inputs, is skipped).
pub fn write_pictures(
    rec: &Reconstruction,
    names: &[&str],
    shading_light: [f64; 3],
    dir: &Path,
) -> Result<Vec<String>, RunError> {
    let written: Vec<Option<String>> = names
        .par_iter()
        .map(|name| match encode(rec, name, shading_light) {
            Some(bytes) => write_atomic(dir, name, &bytes).map(|_| Some(name.to_string())),
            None => Ok(None),
        })
        .collect::<Result<_, _>>()?;
    Ok(written.into_iter().flatten().collect())
}

/// Re-shade a finished job's outputs (`albedo.png`, `normal.exr` in `dir`) under `light`
/// and encode the picture as a 16-bit PNG.
pub fn shaded_png_from_dir(dir: &Path, light: [f64; 3]) -> Result<Vec<u8>, InputError> {
    super::lights::check_direction(light)?;
    let read = |name: &str| {
        image::open(dir.join(name))
            .map_err(|e| InputError::io(dir.join(name), format!("cannot re-shade: {e}")))
    };
    let albedo = read("albedo.png")?.to_luma32f();
    let normal = read("normal.exr")?.to_rgba32f();
    if albedo.dimensions() != normal.dimensions() {
        return Err(InputError::io(
            dir,
            "albedo.png and normal.exr differ in size",
        ));
    }
    let (w, h) = albedo.dimensions();
    let a = Array2::from_shape_fn((h as usize, w as usize), |(r, c)| {
        albedo.get_pixel(c as u32, r as u32).0[0]
    });
    // normal.exr is in the OpenGL frame (y up): back to the seed frame for shading.
    let n = Array3::from_shape_fn((h as usize, w as usize, 3), |(r, c, k)| {
        let v = normal.get_pixel(c as u32, r as u32).0[k];
        if k == 1 { -v } else { v }
    });
    Ok(gray16(&render::shade(&a, &n, light), |v| v))
}

/// Decode an encoded artifact's pixels, for tests and tools.
pub fn decode_png16(bytes: &[u8]) -> image::ImageResult<DynamicImage> {
    image::load_from_memory_with_format(bytes, ImageFormat::Png)
}
