//! Encoders: the PNG/EXR pictures of a reconstruction and `result.json`, written in
//! parallel, each under a temporary name and renamed once complete.

use std::fs::File;
use std::io::Write;
use std::path::Path;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ImageBuffer, ImageEncoder, ImageFormat, Luma, Rgb};
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

/// Row filter for every PNG written: `Up` is one subtraction per byte and on smooth
/// 16-bit maps compresses close to adaptive filtering, which tries all five per row.
const PNG_FILTER: FilterType = FilterType::Up;

/// Encode a picture as PNG with fast compression (outputs are written on every job; the
/// few percent that maximum compression saves is not worth several times the time).
pub fn png_bytes<P, C>(img: &ImageBuffer<P, C>) -> Vec<u8>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    png_bytes_filtered(img, PNG_FILTER)
}

/// [`png_bytes`] with a chosen row filter (the rendered test sets keep the adaptive
/// filtering their committed bytes were made with).
pub fn png_bytes_filtered<P, C>(img: &ImageBuffer<P, C>, filter: FilterType) -> Vec<u8>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    let mut out = Vec::new();
    png_with(&mut out, img, filter).expect("encoding a PNG into memory cannot fail");
    out
}

/// [`png_bytes`] streamed into `out`.
pub fn png_to<P, C>(out: &mut dyn Write, img: &ImageBuffer<P, C>) -> std::io::Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    png_with(out, img, PNG_FILTER)
}

fn png_with<P, C>(
    out: &mut dyn Write,
    img: &ImageBuffer<P, C>,
    filter: FilterType,
) -> std::io::Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    PngEncoder::new_with_quality(out, CompressionType::Fast, filter)
        .write_image(
            image::EncodableLayout::as_bytes(&**img),
            img.width(),
            img.height(),
            P::COLOR_TYPE,
        )
        .map_err(std::io::Error::other)
}

/// Write a 32-bit float RGBA OpenEXR file (single part, scan lines, no compression),
/// one row at a time from `pixel`: no whole-image buffer, no copy. Uncompressed because
/// float normals and heights barely compress losslessly and the compressors cost more
/// than the bytes they save.
fn write_exr(
    out: &mut dyn Write,
    width: usize,
    height: usize,
    pixel: impl Fn(usize, usize) -> [f32; 4],
) -> std::io::Result<()> {
    fn attribute(h: &mut Vec<u8>, name: &str, kind: &str, value: &[u8]) {
        h.extend_from_slice(name.as_bytes());
        h.push(0);
        h.extend_from_slice(kind.as_bytes());
        h.push(0);
        h.extend_from_slice(&(value.len() as i32).to_le_bytes());
        h.extend_from_slice(value);
    }
    let i32s = |v: &[i32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let mut h = Vec::with_capacity(512);
    h.extend_from_slice(&[0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0]);
    let mut channels = Vec::new();
    // Channels in the file are sorted by name: A, B, G, R.
    for name in ["A", "B", "G", "R"] {
        channels.extend_from_slice(name.as_bytes());
        channels.push(0);
        channels.extend_from_slice(&2i32.to_le_bytes()); // FLOAT
        channels.extend_from_slice(&[0, 0, 0, 0]); // pLinear, reserved
        channels.extend_from_slice(&i32s(&[1, 1])); // x, y sampling
    }
    channels.push(0);
    attribute(&mut h, "channels", "chlist", &channels);
    attribute(&mut h, "compression", "compression", &[0]);
    let window = i32s(&[0, 0, width as i32 - 1, height as i32 - 1]);
    attribute(&mut h, "dataWindow", "box2i", &window);
    attribute(&mut h, "displayWindow", "box2i", &window);
    attribute(&mut h, "lineOrder", "lineOrder", &[0]);
    attribute(&mut h, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    attribute(&mut h, "screenWindowCenter", "v2f", &[0; 8]);
    attribute(&mut h, "screenWindowWidth", "float", &1f32.to_le_bytes());
    h.push(0);
    let line = width * 4 * 4;
    let first = (h.len() + height * 8) as u64;
    for y in 0..height as u64 {
        h.extend_from_slice(&(first + y * (8 + line as u64)).to_le_bytes());
    }
    out.write_all(&h)?;
    let mut row = vec![0u8; 8 + line];
    let plane = width * 4;
    for y in 0..height {
        row[..4].copy_from_slice(&(y as i32).to_le_bytes());
        row[4..8].copy_from_slice(&(line as i32).to_le_bytes());
        let (a, rest) = row[8..].split_at_mut(plane);
        let (b, rest) = rest.split_at_mut(plane);
        let (g, r) = rest.split_at_mut(plane);
        for x in 0..width {
            let p = pixel(y, x);
            let at = x * 4..x * 4 + 4;
            r[at.clone()].copy_from_slice(&p[0].to_le_bytes());
            g[at.clone()].copy_from_slice(&p[1].to_le_bytes());
            b[at.clone()].copy_from_slice(&p[2].to_le_bytes());
            a[at].copy_from_slice(&p[3].to_le_bytes());
        }
        out.write_all(&row)?;
    }
    Ok(())
}

/// 16-bit gray PNG of values in [0, 1] (clamped; NaN → 0), in row-major order.
fn gray16_to(
    out: &mut dyn Write,
    (rows, cols): (usize, usize),
    values: impl Iterator<Item = f32>,
) -> std::io::Result<()> {
    let data: Vec<u16> = values.map(unit16).collect();
    let img = ImageBuffer::<Luma<u16>, _>::from_raw(cols as u32, rows as u32, data)
        .expect("one value per pixel");
    png_to(out, &img)
}

fn unit16(v: f32) -> u16 {
    (v.clamp(0.0, 1.0) * 65535.0).round() as u16
}

fn gray16(values: &Array2<f32>, map: impl Fn(f32) -> f32) -> Vec<u8> {
    let mut out = Vec::new();
    gray16_to(&mut out, values.dim(), values.iter().map(|&v| map(v)))
        .expect("encoding a PNG into memory cannot fail");
    out
}

fn binary_to(out: &mut dyn Write, m: &Array2<bool>) -> std::io::Result<()> {
    let (rows, cols) = m.dim();
    let data: Vec<u8> = m.iter().map(|&b| if b { 255 } else { 0 }).collect();
    let img = ImageBuffer::<Luma<u8>, _>::from_raw(cols as u32, rows as u32, data)
        .expect("one value per pixel");
    png_to(out, &img)
}

/// Normal in the OpenGL normal-map frame (x right, y up, z to viewer) from the seed frame.
fn gl_normal(n: &Array3<f32>, r: usize, c: usize) -> [f32; 3] {
    [n[[r, c, 0]], -n[[r, c, 1]], n[[r, c, 2]]]
}

/// Whether artifact `name` applies to this reconstruction (`albedo_rgb.png` needs colour).
pub fn applies(rec: &Reconstruction, name: &str) -> bool {
    name != "albedo_rgb.png" || rec.albedo_rgb.is_some()
}

/// Encode one named artifact (mesh files excepted), or None if it does not apply.
pub fn encode(rec: &Reconstruction, name: &str, shading_light: [f64; 3]) -> Option<Vec<u8>> {
    if !applies(rec, name) {
        return None;
    }
    let mut out = Vec::new();
    match encode_to(&mut out, rec, name, shading_light) {
        Ok(true) => Some(out),
        Ok(false) => None,
        Err(e) => panic!("encoding {name} into memory cannot fail: {e}"),
    }
}

/// Stream one named artifact (mesh files excepted) into `out`; false when `name` is not
/// a picture this module knows or does not apply.
pub fn encode_to(
    out: &mut dyn Write,
    rec: &Reconstruction,
    name: &str,
    shading_light: [f64; 3],
) -> std::io::Result<bool> {
    let (rows, cols) = (rec.height, rec.width);
    let (w, h) = (cols as u32, rows as u32);
    let mask = &rec.mask;
    let normals = || rec.normals.rows().into_iter().zip(mask.iter());
    match name {
        "albedo.png" => gray16_to(out, (rows, cols), rec.albedo.iter().copied())?,
        "albedo_rgb.png" => {
            let Some(rgb) = rec.albedo_rgb.as_ref() else {
                return Ok(false);
            };
            let data: Vec<u16> = rgb.iter().map(|&v| unit16(v)).collect();
            let img = ImageBuffer::<Rgb<u16>, _>::from_raw(w, h, data).expect("3 per pixel");
            png_to(out, &img)?
        }
        "mask.png" => binary_to(out, mask)?,
        "unreliable.png" => binary_to(out, &rec.unreliable)?,
        "confidence.png" => gray16_to(out, (rows, cols), rec.confidence.iter().copied())?,
        "normal.png" => {
            let mut data = Vec::with_capacity(rows * cols * 3);
            for (n, &m) in normals() {
                let gl = [n[0], -n[1], n[2]];
                data.extend(gl.map(|v| if m { unit16((v + 1.0) * 0.5) } else { 0 }));
            }
            let img = ImageBuffer::<Rgb<u16>, _>::from_raw(w, h, data).expect("3 per pixel");
            png_to(out, &img)?
        }
        "normal_x.png" | "normal_y.png" | "normal_z.png" => {
            let k = match name {
                "normal_x.png" => 0,
                "normal_y.png" => 1,
                _ => 2,
            };
            let comp = normals().map(|(n, &m)| if m { (n[k] + 1.0) * 0.5 } else { 0.0 });
            gray16_to(out, (rows, cols), comp)?
        }
        "height.png" => {
            let (lo, hi) = (rec.report.height_min, rec.report.height_max);
            let span = if hi > lo { hi - lo } else { 1.0 };
            let z = (rec.heights.iter().zip(mask.iter()))
                .map(|(&z, &m)| if m { (z - lo) / span } else { 0.0 });
            gray16_to(out, (rows, cols), z)?
        }
        "normal.exr" => write_exr(out, cols, rows, |r, c| {
            let [nx, ny, nz] = gl_normal(&rec.normals, r, c);
            [nx, ny, nz, if mask[[r, c]] { 1.0 } else { 0.0 }]
        })?,
        "height.exr" => write_exr(out, cols, rows, |r, c| {
            let z = rec.heights[[r, c]];
            [z, z, z, if mask[[r, c]] { 1.0 } else { 0.0 }]
        })?,
        "needle.png" => png_to(out, &render::needle_map(&rec.albedo, &rec.normals, mask))?,
        "curl.png" => png_to(out, &render::diverging(&rec.curl, mask))?,
        "shaded.png" => {
            let shaded = render::shade(&rec.albedo, &rec.normals, shading_light);
            gray16_to(out, (rows, cols), shaded.iter().copied())?
        }
        _ => return Ok(false),
    }
    Ok(true)
}

/// Write `bytes` to `dir/name` through a temporary file, so a reader never sees a
/// partial artifact.
pub fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), RunError> {
    write_atomic_with(dir, name, &mut |f| f.write_all(bytes))
}

/// Stream an artifact into `dir/name` through a temporary file (buffered, synced, then
/// renamed), so large outputs never exist as a whole in memory.
pub fn write_atomic_with(
    dir: &Path,
    name: &str,
    write: &mut dyn FnMut(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), RunError> {
    let tmp = dir.join(format!(".{name}.tmp"));
    let path = dir.join(name);
    let fail = |e: std::io::Error| RunError::Output {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    {
        let mut f = std::io::BufWriter::with_capacity(1 << 20, File::create(&tmp).map_err(fail)?);
        write(&mut f).map_err(fail)?;
        let f = f.into_inner().map_err(|e| fail(e.into_error()))?;
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
        .map(|name| {
            if !applies(rec, name) {
                return Ok(None);
            }
            write_atomic_with(dir, name, &mut |f| {
                encode_to(f, rec, name, shading_light).map(|_| ())
            })?;

            Ok(Some(name.to_string()))
        })
        .collect::<Result<_, RunError>>()?;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_writer_round_trips_through_the_image_crate() {
        let (w, h) = (5, 3);
        let px = |r: usize, c: usize| [r as f32, c as f32 * 0.5, -1.25, (r + c) as f32 % 2.0];
        let mut bytes = Vec::new();
        write_exr(&mut bytes, w, h, px).unwrap();
        let img = image::load_from_memory_with_format(&bytes, ImageFormat::OpenExr)
            .unwrap()
            .to_rgba32f();
        assert_eq!(img.dimensions(), (w as u32, h as u32));
        for r in 0..h {
            for c in 0..w {
                assert_eq!(img.get_pixel(c as u32, r as u32).0, px(r, c), "({r}, {c})");
            }
        }
    }
}
