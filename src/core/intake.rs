//! Intake: light table + image files → [`ImageSet`], with errors that name the culprit.
//!
//! Images are decoded in parallel and kept as 16-bit luminance planes (2 bytes per pixel
//! per image): 8-bit data is widened exactly (v·257), colour is reduced to luminance with
//! the Rec. 709 weights (0.2126 R + 0.7152 G + 0.0722 B) applied to the stored values.
//! Under a light with RGB intensities, a colour image's channel c is first divided by
//! rgb_c and the whole rescaled by s = min_c rgb_c (so no factor exceeds 1 and the plane
//! cannot clip); the light's scalar intensity becomes s.

use std::io::Cursor;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageFormat, ImageReader};
use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::error::InputError;
use super::error::panic_message;
use super::layout;
pub use super::lights::LUMA_WEIGHTS;
use super::lights::Light;

/// The light table's file name inside a data-set folder.
pub const LIGHTS_FILE: &str = layout::SEED_CSV;
/// The JSON alternative to [`LIGHTS_FILE`].
pub const LIGHTS_JSON_FILE: &str = layout::SEED_JSON;

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
    /// The name of the mask file used, if any.
    pub mask_file: Option<String>,
    /// What intake ignored or chose on the caller's behalf (for `result.json`).
    pub notes: Vec<String>,
}

/// An input file under the name the light table uses for it.
#[derive(Debug, Clone)]
pub struct NamedFile {
    pub name: String,
    pub path: PathBuf,
}

/// Which mask [`load_dir`] gives the set.
#[derive(Debug, Clone, Copy, Default)]
pub enum DirMask<'a> {
    /// The folder's own `mask.png`, when it has one.
    #[default]
    Folder,
    /// This file.
    File(&'a Path),
    /// None (a folder `mask.png` is left unused, with a note).
    Without,
}

/// Load a folder in one of the layouts [`layout`] reads (the seed's
/// `light_directions.csv` / `.json`, an `.lp` file, or the benchmark's
/// `light_directions.txt` + `filenames.txt`): the images its table names. Image files it
/// does not name are ignored and listed in the set's notes.
pub fn load_dir(dir: &Path, mask: DirMask<'_>, limits: &Limits) -> Result<ImageSet, InputError> {
    let found = dir_files(dir, mask)?;
    let mut set = load(found.lights, &found.files, found.mask.as_ref(), limits)?;
    set.notes = found.notes;
    Ok(set)
}

/// What a folder holds for a set: its light table, the files it names, the mask chosen.
pub(super) struct DirFiles {
    pub lights: Vec<Light>,
    pub files: Vec<NamedFile>,
    pub mask: Option<NamedFile>,
    pub notes: Vec<String>,
}

/// A folder's light table (lights, mask file, rig, notes), its images not read.
pub fn dir_table(dir: &Path) -> Result<layout::Table, InputError> {
    dir_table_of(dir, &dir_names(dir)?)
}

/// The files at the top of a folder, sorted.
fn dir_names(dir: &Path) -> Result<Vec<String>, InputError> {
    let mut names = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| InputError::io(dir, e))? {
        let entry = entry.map_err(|e| InputError::io(dir, e))?;
        if entry.path().is_file() {
            names.push(entry.file_name().to_string_lossy().into_owned());
        }
    }
    names.sort();
    Ok(names)
}

fn dir_table_of(dir: &Path, names: &[String]) -> Result<layout::Table, InputError> {
    let mut read = |name: &str| {
        let path = dir.join(name);
        std::fs::read(&path).map_err(|e| InputError::io(&path, e))
    };
    layout::read_table(&dir.display().to_string(), names, &mut read)
}

/// The light table, image files and mask of a folder (see [`load_dir`]).
pub(super) fn dir_files(dir: &Path, mask: DirMask<'_>) -> Result<DirFiles, InputError> {
    let names = dir_names(dir)?;
    let table = dir_table_of(dir, &names)?;
    let named = |name: &str| NamedFile {
        name: name.to_string(),
        path: dir.join(name),
    };
    // Only files that exist, so that a missing one is reported by name.
    let files: Vec<NamedFile> = (table.lights.iter())
        .filter(|l| names.contains(&l.name))
        .map(|l| named(&l.name))
        .collect();
    let mut notes = table.notes;
    let unused = |why: &str| format!("{} in the folder not used: {why}", layout::MASK);
    let mask = match (mask, &table.mask) {
        (DirMask::Folder, Some(m)) => Some(named(m)),
        (DirMask::Folder, None) | (DirMask::Without, None) => None,
        (DirMask::File(p), folder) => {
            if folder.is_some() {
                notes.push(unused("another mask file was given"));
            }
            Some(NamedFile {
                name: (p.file_name().unwrap_or_default())
                    .to_string_lossy()
                    .into_owned(),
                path: p.to_path_buf(),
            })
        }
        (DirMask::Without, Some(_)) => {
            notes.push(unused("the mask mode asked for takes no mask"));
            None
        }
    };
    Ok(DirFiles {
        lights: table.lights,
        files,
        mask,
        notes,
    })
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
/// which must be left to the load: their plane and colour moments need the image's light.
pub fn predecode(name: &str, bytes: &[u8], limits: &Limits) -> Option<Result<Decoded, InputError>> {
    match decode_bytes(name, bytes, limits, None) {
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
    let ordered = check_files(&lights, files, limits)?;
    let mut lights = lights;

    // Images are decoded in parallel a few at a time, and each colour image's moments are
    // added in table order before the next few are decoded: the f32 sums are then the same
    // on every run (and the same as a streamed set's), with no more RGB images held at once
    // than there are threads.
    let mut moments: Option<Array3<f32>> = None;
    let mut colour_count = 0;
    let mut decoded = Vec::with_capacity(ordered.len());
    let at_once = rayon::current_num_threads().max(1);
    for (order, lights) in ordered.chunks(at_once).zip(lights.chunks_mut(at_once)) {
        let part: Vec<Result<_, InputError>> = (order.par_iter())
            .zip(lights.par_iter())
            .map(|(&i, light)| {
                if let Some(ready) = predecoded(i) {
                    // Gray by construction: no colour moments to add, the scalar stands.
                    return ready.map(|d| (d, None));
                }
                decode_file(&files[i], limits, light.rgb)
            })
            .collect();
        // The first failure in table order, not the first in time: the error a set gets
        // must not depend on thread scheduling.
        for (result, light) in part.into_iter().zip(lights.iter_mut()) {
            let (d, colour) = result?;
            if let Some(colour) = colour {
                if let Some(s) = colour.balanced {
                    light.intensity = s;
                }
                let scaled = light.direction.map(|c| (c * light.intensity) as f32);
                let (w, h) = (colour.rgb.width() as usize, colour.rgb.height() as usize);
                let m = moments.get_or_insert_with(|| Array3::zeros((h, w, 9)));
                // A size mismatch is reported below.
                if m.dim() == (h, w, 9)
                    && let Some(m) = m.as_slice_mut()
                {
                    add_moments(m, &colour.rgb, scaled);
                }
                colour_count += 1;
            }
            decoded.push(d);
        }
    }

    let sizes: Vec<_> = decoded.iter().map(|d| (d.plane.dim(), d.depth)).collect();
    check_sizes(&lights, &sizes)?;
    let (rows, cols) = sizes[0].0;
    let bit_depth = sizes[0].1;
    let mask_file = mask;
    let mask = mask.map(|m| load_mask(m, rows, cols, limits)).transpose()?;
    // A set where only some images carry colour is treated as gray: moments from a
    // subset of lights would bias every channel.
    let colour_images = colour_count == lights.len();
    Ok(ImageSet {
        width: cols,
        height: rows,
        bit_depth,
        lights,
        planes: decoded.into_iter().map(|d| d.plane).collect(),
        colour_moments: if colour_images { moments } else { None },
        mask,
        mask_file: mask_file.map(|m| m.name.clone()),
        notes: Vec::new(),
    })
}

/// The checks before any decoding: image count, and each table row paired with its file
/// (indices into `files`, in table order).
pub(super) fn check_files(
    lights: &[Light],
    files: &[NamedFile],
    limits: &Limits,
) -> Result<Vec<usize>, InputError> {
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
    match_files(lights, files)
}

/// Every image the size and depth of the first: `sizes[i]` is image i's (rows, cols)
/// and bits per sample.
pub(super) fn check_sizes(
    lights: &[Light],
    sizes: &[((usize, usize), u8)],
) -> Result<(), InputError> {
    let ((rows, cols), first_depth) = sizes[0];
    for (i, &((r, c), depth)) in sizes.iter().enumerate() {
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
        if depth != first_depth {
            return Err(InputError::BitDepthMismatch {
                name: lights[i].name.clone(),
                depth,
                first: lights[0].name.clone(),
                expected: first_depth,
            });
        }
    }
    Ok(())
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

/// A colour image's values as the set uses them.
struct Colour {
    /// RGB in [0, 1]; balanced: each channel divided by its light's intensity, times s.
    rgb: image::Rgb32FImage,
    /// s = min_c rgb_c, the light's scalar intensity, when the light gave RGB intensities.
    balanced: Option<f64>,
}

/// Read and decode one image file.
fn decode_file(
    file: &NamedFile,
    limits: &Limits,
    light_rgb: Option<[f64; 3]>,
) -> Result<(Decoded, Option<Colour>), InputError> {
    let bytes = std::fs::read(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    decode_bytes(&file.name, &bytes, limits, light_rgb)
}

/// Decode one image: its plane, and its RGB values when it really carries colour. The one
/// decode path of [`load_with`] and [`predecode`]. With a per-channel light intensity, a
/// colour image is balanced by it before its luminance is taken (see the module docs).
fn decode_bytes(
    name: &str,
    bytes: &[u8],
    limits: &Limits,
    light_rgb: Option<[f64; 3]>,
) -> Result<(Decoded, Option<Colour>), InputError> {
    let img = decode(name, bytes, limits)?;
    let depth = bit_depth(&img);
    if !has_colour(&img) {
        let plane = to_luma16(img);
        return Ok((Decoded { plane, depth }, None));
    }
    let (plane, rgb) = band_plane(img, true, light_rgb, true);
    let colour = Colour {
        rgb: rgb.expect("asked for"),
        balanced: light_rgb.map(|g| g.iter().copied().fold(f64::INFINITY, f64::min)),
    };
    Ok((Decoded { plane, depth }, Some(colour)))
}

/// An image's (or a band of its rows') plane, given whether the whole image carries
/// colour: with a per-channel light intensity `gains`, a colour image is balanced by it
/// before its luminance is taken (see the module docs). With `with_rgb`, also the RGB
/// values (balanced) its colour moments are summed from.
pub(super) fn band_plane(
    img: DynamicImage,
    colour: bool,
    gains: Option<[f64; 3]>,
    with_rgb: bool,
) -> (Array2<u16>, Option<image::Rgb32FImage>) {
    if !colour {
        return (to_luma16(img), None);
    }
    let Some(gains) = gains else {
        let rgb = with_rgb.then(|| img.to_rgb32f());
        return (to_luma16(img), rgb);
    };
    let mut rgb = img.to_rgb32f();
    let s = gains.iter().copied().fold(f64::INFINITY, f64::min);
    let factor = gains.map(|g| (s / g) as f32);
    for p in rgb.pixels_mut() {
        for c in 0..3 {
            p.0[c] *= factor[c];
        }
    }
    (luma_plane(&rgb), with_rgb.then_some(rgb))
}

/// Whether the image has colour channels whose values actually differ somewhere (a gray
/// picture stored as RGB is gray).
pub(super) fn has_colour(img: &DynamicImage) -> bool {
    if !img.color().has_color() {
        return false;
    }
    let rgb = img.to_rgb32f();
    rgb.pixels()
        .any(|p| (p.0[0] - p.0[1]).abs() > 1e-6 || (p.0[1] - p.0[2]).abs() > 1e-6)
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

pub(super) fn bit_depth(img: &DynamicImage) -> u8 {
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

fn luma_plane(rgb: &image::Rgb32FImage) -> Array2<u16> {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let data = luma_of(rgb.pixels().map(|p| p.0));
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

/// Add one image's (or band's) Σ s_k·I_c to each pixel's moments, `s` its light as the
/// solve sees it (direction × intensity). The one place moments are summed: images added
/// in table order give the same sums run to run, whole or streamed.
pub(super) fn add_moments(moments: &mut [f32], rgb: &image::Rgb32FImage, s: [f32; 3]) {
    (moments.par_chunks_mut(9 * 1024))
        .zip(rgb.as_raw().par_chunks(3 * 1024))
        .for_each(|(m, px)| {
            for (out, p) in m.chunks_exact_mut(9).zip(px.chunks_exact(3)) {
                for c in 0..3 {
                    for k in 0..3 {
                        out[c * 3 + k] += s[k] * p[c];
                    }
                }
            }
        });
}

pub(super) fn load_mask(
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::lights::{Intensity, make_light};
    use crate::core::synth::{self, Capture, Scene};
    use crate::core::{Options, RunToEnd, reconstruct};

    const TINT: [f64; 3] = [0.95, 0.7, 0.45];
    const SIZE: usize = 40;

    /// Per-light RGB intensities that differ from light to light and channel to channel.
    fn intensities(count: usize) -> Vec<[f64; 3]> {
        (0..count)
            .map(|i| {
                let t = i as f64 / count as f64;
                [
                    0.6 + 0.5 * t,
                    1.1 - 0.4 * t,
                    0.8 + 0.3 * (t * 9.0).sin().abs(),
                ]
            })
            .collect()
    }

    /// A colour sphere under 8 lights of the given RGB intensities, written and loaded;
    /// the table's intensities are the true ones times `table_scale`.
    fn colour_set(dir: &Path, table_scale: f64) -> (Scene, ImageSet) {
        let scene = Scene::sphere(SIZE);
        let dirs = synth::light_rings(8, 20.0, 45.0);
        let rgb = intensities(dirs.len());
        let images = synth::render_rgb(&scene, TINT, &dirs, &rgb, &Capture::default());
        let mut files = Vec::new();
        let mut lights = Vec::new();
        for (i, img) in images.iter().enumerate() {
            let name = format!("{i}.png");
            img.save(dir.join(&name)).unwrap();
            files.push(NamedFile {
                path: dir.join(&name),
                name: name.clone(),
            });
            let given = rgb[i].map(|v| v * table_scale);
            lights.push(make_light(i + 1, &name, dirs[i], Some(Intensity::Rgb(given))).unwrap());
        }
        let set = load(lights, &files, None, &Limits::default()).unwrap();
        (scene, set)
    }

    fn opts() -> Options {
        Options {
            mask: crate::core::options::MaskMode::None,
            ..Options::default()
        }
    }

    #[test]
    fn rgb_light_intensities_give_true_normals_and_channel_albedo() {
        let dir = tempfile::tempdir().unwrap();
        let (scene, set) = colour_set(dir.path(), 1.0);
        let rgb = intensities(set.lights.len());
        for (l, i) in set.lights.iter().zip(&rgb) {
            assert_eq!(l.intensity, i.iter().copied().fold(f64::INFINITY, f64::min));
        }
        let rec = reconstruct(&set, &opts(), &mut RunToEnd).unwrap();
        let albedo_rgb = rec.albedo_rgb.as_ref().expect("colour inputs");
        let (mut worst_deg, mut worst_albedo, mut count) = (0f64, [0f64; 3], 0);
        for ((r, c), &inside) in scene.mask.indexed_iter() {
            // Away from the rim, where every light reaches.
            let n = [0, 1, 2].map(|k| scene.normals[[r, c, k]]);
            if !inside || n[2] < 0.8 {
                continue;
            }
            count += 1;
            let dot: f64 = (0..3).map(|k| n[k] * rec.normals[[r, c, k]] as f64).sum();
            worst_deg = worst_deg.max(dot.clamp(-1.0, 1.0).acos().to_degrees());
            for ch in 0..3 {
                let truth = scene.albedo[[r, c, 0]] * TINT[ch];
                let err = (albedo_rgb[[r, c, ch]] as f64 - truth).abs();
                worst_albedo[ch] = worst_albedo[ch].max(err);
            }
        }
        assert!(count > 200, "{count}");
        assert!(worst_deg < 0.1, "normals off by up to {worst_deg}°");
        assert!(
            worst_albedo.iter().all(|&e| e < 2e-3),
            "albedo errors {worst_albedo:?}"
        );
    }

    #[test]
    fn scaling_every_intensity_leaves_normals_unchanged() {
        let dir = tempfile::tempdir().unwrap();
        let (_, one) = colour_set(dir.path(), 1.0);
        let (_, tripled) = colour_set(dir.path(), 3.0);
        let a = reconstruct(&one, &opts(), &mut RunToEnd).unwrap();
        let b = reconstruct(&tripled, &opts(), &mut RunToEnd).unwrap();
        let most = (a.normals.iter().zip(&b.normals))
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(most < 1e-5, "normals moved by {most}");
        let ratio = (a.albedo.iter().zip(&b.albedo))
            .filter(|(x, _)| **x > 0.05)
            .map(|(x, y)| x / y)
            .fold(0f32, f32::max);
        assert!((ratio - 3.0).abs() < 1e-3, "albedo ratio {ratio}");
    }

    #[test]
    fn gray_images_take_the_luminance_of_an_rgb_intensity() {
        let dir = tempfile::tempdir().unwrap();
        let mut files = Vec::new();
        let mut lights = Vec::new();
        for (i, d) in [[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [0.0, 0.5, 1.0]]
            .iter()
            .enumerate()
        {
            let name = format!("{i}.png");
            image::GrayImage::from_pixel(4, 4, image::Luma([100]))
                .save(dir.path().join(&name))
                .unwrap();
            files.push(NamedFile {
                path: dir.path().join(&name),
                name: name.clone(),
            });
            let rgb = Intensity::Rgb([1.0, 2.0, 4.0]);
            lights.push(make_light(i + 1, &name, *d, Some(rgb)).unwrap());
        }
        let set = load(lights, &files, None, &Limits::default()).unwrap();
        let luma = 0.2126 + 0.7152 * 2.0 + 0.0722 * 4.0;
        assert!(set.lights.iter().all(|l| (l.intensity - luma).abs() < 1e-6));
    }
}
