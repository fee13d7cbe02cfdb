//! Intake: light table + image files → [`ImageSet`], with errors that name the culprit.
//!
//! Images are decoded in parallel and kept as 16-bit luminance planes (2 bytes per pixel
//! per image): 8-bit data is widened exactly (v·257), colour is reduced to luminance with
//! the Rec. 709 weights (0.2126 R + 0.7152 G + 0.0722 B) applied to the stored values.

use std::io::Cursor;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use image::{DynamicImage, ImageFormat, ImageReader};
use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::InputError;
use super::error::panic_message;
use super::lights::{self, Light};

/// Rec. 709 luminance weights for R, G, B.
pub const LUMA_WEIGHTS: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// The light table's file name inside a data-set folder.
pub const LIGHTS_FILE: &str = "light_directions.csv";
/// The JSON alternative to [`LIGHTS_FILE`].
pub const LIGHTS_JSON_FILE: &str = "light_directions.json";

const IMAGE_EXTENSIONS: [&str; 7] = ["png", "bmp", "jpg", "jpeg", "tif", "tiff", "exr"];

/// Bounds on what intake will decode.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_pixels_per_image: u64,
    pub max_images: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_pixels_per_image: 64 * 1024 * 1024,
            max_images: 256,
        }
    }
}

/// A decoded image set, ready for the solve.
#[derive(Debug, Clone)]
pub struct ImageSet {
    pub width: usize,
    pub height: usize,
    /// Bits per sample of the source images (8 or 16).
    pub bit_depth: u8,
    /// One light per plane, same order.
    pub lights: Vec<Light>,
    /// Luminance, 0..=65535 standing for [0, 1].
    pub planes: Vec<Array2<u16>>,
    /// For colour inputs: Σᵢ lᵢ·Iᵢ,c per pixel, laid out `(rows, cols, 3 channels × 3)`,
    /// enough to fit each channel's albedo against the recovered normals later without
    /// keeping the colour images.
    pub colour_moments: Option<Array3<f32>>,
    /// The caller's mask (true = object), if any.
    pub mask: Option<Array2<bool>>,
}

/// An input file under the name the light table uses for it.
#[derive(Debug, Clone)]
pub struct NamedFile {
    pub name: String,
    pub path: PathBuf,
}

/// Load a folder in the seed's layout: `light_directions.csv` (or `.json`) and the images
/// it names. Image files in the folder that the table does not name are an error.
pub fn load_dir(dir: &Path, mask: Option<&Path>, limits: &Limits) -> Result<ImageSet, InputError> {
    let table_path = [LIGHTS_FILE, LIGHTS_JSON_FILE]
        .iter()
        .map(|f| dir.join(f))
        .find(|p| p.is_file())
        .ok_or_else(|| {
            InputError::Lights(format!(
                "no {LIGHTS_FILE} or {LIGHTS_JSON_FILE} in {}",
                dir.display()
            ))
        })?;
    let bytes = std::fs::read(&table_path).map_err(|e| InputError::io(&table_path, e))?;
    let lights = lights::parse_bytes(&bytes)?;
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| InputError::io(dir, e))? {
        let path = entry.map_err(|e| InputError::io(dir, e))?.path();
        let is_image = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()));
        let is_mask = mask.is_some_and(|m| same_file(m, &path));
        if path.is_file() && is_image && !is_mask {
            let name = path
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            files.push(NamedFile { name, path });
        }
    }
    files.sort_by(|a, b| a.name.cmp(&b.name));
    let mask = mask.map(|p| NamedFile {
        name: p
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned(),
        path: p.to_path_buf(),
    });
    load(lights, &files, mask.as_ref(), limits)
}

fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// Decode the images a light table names, in the table's order.
pub fn load(
    lights: Vec<Light>,
    files: &[NamedFile],
    mask: Option<&NamedFile>,
    limits: &Limits,
) -> Result<ImageSet, InputError> {
    load_with(lights, files, mask, limits, |_| None)
}

/// One image as a set keeps it.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// Luminance, 0..=65535 standing for [0, 1].
    pub plane: Array2<u16>,
    /// Bits per sample of the source image.
    pub depth: u8,
}

/// Decode one image's bytes ahead of [`load_with`] (e.g. while the rest of a set is still
/// being received); `name` is the light table's name for it. `None` for colour images,
/// which must be left to the load: their colour moments need the image's light.
pub fn predecode(name: &str, bytes: &[u8], limits: &Limits) -> Option<Result<Decoded, InputError>> {
    match decode_bytes(name, bytes, limits) {
        Ok((decoded, None)) => Some(Ok(decoded)),
        Ok((_, Some(_colour))) => None,
        Err(e) => Some(Err(e)),
    }
}

/// [`load`], taking image `i` of `files` from `predecoded(i)` when that has it: the results
/// of [`predecode`] on the same file's bytes and name with the same limits, so the set
/// (and the first error, in table order) is the same as without them.
pub fn load_with(
    lights: Vec<Light>,
    files: &[NamedFile],
    mask: Option<&NamedFile>,
    limits: &Limits,
    predecoded: impl Fn(usize) -> Option<Result<Decoded, InputError>> + Sync,
) -> Result<ImageSet, InputError> {
    if lights.len() > limits.max_images || files.len() > limits.max_images {
        return Err(InputError::TooManyImages {
            count: lights.len().max(files.len()),
            limit: limits.max_images,
        });
    }
    if lights.len() < 3 {
        return Err(InputError::TooFewImages {
            count: lights.len(),
        });
    }
    let ordered = match_files(&lights, files)?;

    let moments: Mutex<Option<Array3<f32>>> = Mutex::new(None);
    let colour_count = AtomicUsize::new(0);
    let decoded: Vec<Decoded> = ordered
        .par_iter()
        .zip(lights.par_iter())
        .map(|(&i, light)| {
            if let Some(ready) = predecoded(i) {
                return ready; // gray by construction: no colour moments to add
            }
            let (decoded, colour) = decode_file(&files[i], limits)?;
            if let Some(rgb) = colour {
                accumulate_moments(&moments, &rgb, light);
                colour_count.fetch_add(1, Ordering::Relaxed);
            }
            Ok(decoded)
        })
        .collect::<Vec<Result<_, InputError>>>()
        // The first failure in table order, not the first in time: the error a set gets
        // must not depend on thread scheduling.
        .into_iter()
        .collect::<Result<_, InputError>>()?;

    let (rows, cols) = decoded[0].plane.dim();
    let first_depth = decoded[0].depth;
    for (i, Decoded { plane, depth }) in decoded.iter().enumerate() {
        let (r, c) = plane.dim();
        if (r, c) != (rows, cols) {
            return Err(InputError::SizeMismatch {
                name: lights[i].name.clone(),
                width: c as u32,
                height: r as u32,
                first: lights[0].name.clone(),
                expected_width: cols as u32,
                expected_height: rows as u32,
            });
        }
        if *depth != first_depth {
            return Err(InputError::BitDepthMismatch {
                name: lights[i].name.clone(),
                depth: *depth,
                first: lights[0].name.clone(),
                expected: first_depth,
            });
        }
    }
    let bit_depth = first_depth;
    let mask = mask.map(|m| load_mask(m, rows, cols, limits)).transpose()?;
    let colour_moments = moments.into_inner().unwrap_or_else(|p| p.into_inner());
    // A set where only some images carry colour is treated as gray: moments from a
    // subset of lights would bias every channel.
    let colour_images = colour_count.into_inner() == lights.len();
    Ok(ImageSet {
        width: cols,
        height: rows,
        bit_depth,
        lights,
        planes: decoded.into_iter().map(|d| d.plane).collect(),
        colour_moments: if colour_images { colour_moments } else { None },
        mask,
    })
}

/// Pair each table row with its file (an index into `files`); every row needs a file and
/// every file a row.
fn match_files(lights: &[Light], files: &[NamedFile]) -> Result<Vec<usize>, InputError> {
    let mut by_name = std::collections::HashMap::new();
    for (i, f) in files.iter().enumerate() {
        if by_name.insert(f.name.as_str(), i).is_some() {
            return Err(InputError::DuplicateName {
                name: f.name.clone(),
                first: 0,
                second: 0,
            });
        }
    }
    let mut ordered = Vec::with_capacity(lights.len());
    for l in lights {
        match by_name.remove(l.name.as_str()) {
            Some(i) => ordered.push(i),
            None => {
                return Err(InputError::MissingImage {
                    name: l.name.clone(),
                });
            }
        }
    }
    if let Some(f) = files.iter().find(|f| by_name.contains_key(f.name.as_str())) {
        return Err(InputError::UnlistedImage {
            name: f.name.clone(),
        });
    }
    Ok(ordered)
}

/// Read and decode one image file.
fn decode_file(
    file: &NamedFile,
    limits: &Limits,
) -> Result<(Decoded, Option<image::Rgb32FImage>), InputError> {
    let bytes = std::fs::read(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    decode_bytes(&file.name, &bytes, limits)
}

/// Decode one image: its plane, and its RGB values when it really carries colour. The one
/// decode path of [`load_with`] and [`predecode`].
fn decode_bytes(
    name: &str,
    bytes: &[u8],
    limits: &Limits,
) -> Result<(Decoded, Option<image::Rgb32FImage>), InputError> {
    let img = decode(name, bytes, limits)?;
    let depth = bit_depth(&img);
    let colour = colour_content(&img);
    Ok((
        Decoded {
            plane: to_luma16(img),
            depth,
        },
        colour,
    ))
}

/// Decode one image, refusing unknown formats and oversized headers before allocating.
pub fn decode(name: &str, bytes: &[u8], limits: &Limits) -> Result<DynamicImage, InputError> {
    let reader = ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| InputError::Decode {
            name: name.into(),
            reason: e.to_string(),
        })?;
    let Some(format) = reader.format() else {
        return Err(InputError::UnsupportedFormat {
            name: name.into(),
            reason: "unrecognised file signature".into(),
        });
    };
    let undecodable = |e: image::ImageError| match e {
        image::ImageError::Unsupported(u) => InputError::UnsupportedFormat {
            name: name.into(),
            reason: u.to_string(),
        },
        other => InputError::Decode {
            name: name.into(),
            reason: other.to_string(),
        },
    };
    if format == ImageFormat::Png
        && let Some(reason) = png_palette_problem(bytes)
    {
        return Err(InputError::Decode {
            name: name.into(),
            reason,
        });
    }
    let (w, h) = ImageReader::with_format(Cursor::new(bytes), format)
        .into_dimensions()
        .map_err(undecodable)?;
    let pixels = w as u64 * h as u64;
    if pixels > limits.max_pixels_per_image {
        return Err(InputError::TooLarge {
            name: name.into(),
            width: w as u64,
            height: h as u64,
            pixels,
            limit: limits.max_pixels_per_image,
        });
    }
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    let mut l = image::Limits::default();
    // Room for a 4-channel 16-bit image of the allowed size, plus decoder scratch.
    l.max_alloc = Some(limits.max_pixels_per_image.saturating_mul(8) + (64 << 20));
    reader.limits(l);
    // A decoder bug must cost one refused file, not the process: these run on rayon's
    // pool, which aborts on a panic, while a set is still being uploaded.
    std::panic::catch_unwind(AssertUnwindSafe(|| reader.decode()))
        .map_err(|panic| InputError::Decode {
            name: name.into(),
            reason: format!(
                "the {format:?} decoder failed on it ({})",
                panic_message(&*panic)
            ),
        })?
        .map_err(undecodable)
}

/// A PLTE chunk whose length is not a multiple of 3, which the `png` crate (0.18.1) accepts
/// and then panics on while expanding the palette. Only the chunks before the first IDAT
/// are looked at (PLTE must precede it); everything else is left to the decoder.
fn png_palette_problem(bytes: &[u8]) -> Option<String> {
    let mut at = 8; // the signature
    while let Some(head) = bytes.get(at..at + 8) {
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]);
        match &head[4..8] {
            b"PLTE" if len % 3 != 0 => {
                return Some(format!(
                    "its PLTE (palette) chunk is {len} bytes long, not a multiple of 3"
                ));
            }
            b"IDAT" | b"IEND" => return None,
            _ => at = at.checked_add(12 + len as usize)?,
        }
    }
    None
}

fn bit_depth(img: &DynamicImage) -> u8 {
    match img {
        DynamicImage::ImageLuma8(_)
        | DynamicImage::ImageLumaA8(_)
        | DynamicImage::ImageRgb8(_)
        | DynamicImage::ImageRgba8(_) => 8,
        DynamicImage::ImageRgb32F(_) | DynamicImage::ImageRgba32F(_) => 32,
        _ => 16,
    }
}

/// Luminance as u16 (0..=65535 ↔ [0, 1]).
pub fn to_luma16(img: DynamicImage) -> Array2<u16> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data: Vec<u16> = match img {
        DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(|v| v as u16 * 257).collect(),
        DynamicImage::ImageLuma16(b) => b.into_raw(),
        DynamicImage::ImageLumaA8(b) => b.pixels().map(|p| p.0[0] as u16 * 257).collect(),
        DynamicImage::ImageLumaA16(b) => b.pixels().map(|p| p.0[0]).collect(),
        DynamicImage::ImageRgb8(b) => luma_of(b.pixels().map(|p| p.0.map(|v| v as f32 / 255.0))),
        DynamicImage::ImageRgba8(b) => luma_of(
            b.pixels()
                .map(|p| [p.0[0], p.0[1], p.0[2]].map(|v| v as f32 / 255.0)),
        ),
        DynamicImage::ImageRgb16(b) => luma_of(b.pixels().map(|p| p.0.map(|v| v as f32 / 65535.0))),
        DynamicImage::ImageRgba16(b) => luma_of(
            b.pixels()
                .map(|p| [p.0[0], p.0[1], p.0[2]].map(|v| v as f32 / 65535.0)),
        ),
        other => luma_of(other.to_rgb32f().pixels().map(|p| p.0)),
    };
    Array2::from_shape_vec((h, w), data).expect("buffer matches its dimensions")
}

fn luma_of(pixels: impl Iterator<Item = [f32; 3]>) -> Vec<u16> {
    pixels
        .map(|[r, g, b]| {
            let y = LUMA_WEIGHTS[0] * r + LUMA_WEIGHTS[1] * g + LUMA_WEIGHTS[2] * b;
            (y.clamp(0.0, 1.0) * 65535.0).round() as u16
        })
        .collect()
}

/// The image as RGB in [0, 1] if it has colour channels whose values actually differ
/// somewhere (a gray picture stored as RGB is gray).
fn colour_content(img: &DynamicImage) -> Option<image::Rgb32FImage> {
    if !img.color().has_color() {
        return None;
    }
    let rgb = img.to_rgb32f();
    let coloured = rgb
        .pixels()
        .any(|p| (p.0[0] - p.0[1]).abs() > 1e-6 || (p.0[1] - p.0[2]).abs() > 1e-6);
    coloured.then_some(rgb)
}

fn accumulate_moments(
    moments: &Mutex<Option<Array3<f32>>>,
    rgb: &image::Rgb32FImage,
    light: &Light,
) {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let s = light.scaled().map(|v| v as f32);
    let mut guard = moments.lock().unwrap_or_else(|p| p.into_inner());
    let m = guard.get_or_insert_with(|| Array3::zeros((h, w, 9)));
    if m.dim() != (h, w, 9) {
        return; // size mismatch is reported by the caller
    }
    for (px, mut out) in rgb.pixels().zip(m.rows_mut()) {
        for c in 0..3 {
            for k in 0..3 {
                out[c * 3 + k] += s[k] * px.0[c];
            }
        }
    }
}

fn load_mask(
    file: &NamedFile,
    rows: usize,
    cols: usize,
    limits: &Limits,
) -> Result<Array2<bool>, InputError> {
    let bytes = std::fs::read(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    let img = decode(&file.name, &bytes, limits).map_err(|e| InputError::Mask(e.to_string()))?;
    if (img.height() as usize, img.width() as usize) != (rows, cols) {
        return Err(InputError::Mask(format!(
            "{:?} is {}×{} but the images are {cols}×{rows}",
            file.name,
            img.width(),
            img.height()
        )));
    }
    Ok(to_luma16(img).mapv(|v| v > 0))
}
