//! Encoders: the PNG/EXR pictures of a reconstruction and `result.json`, written in
//! parallel, each under a temporary name and renamed once complete.

use std::io::{Cursor, Write};
use std::path::Path;

use exr::image::write::channels::WritableChannels;
use exr::prelude::{Encoding, Image, Layer, SpecificChannels, Vec2, WritableImage};
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ImageBuffer, ImageEncoder, ImageFormat, Luma};
use ndarray::{Array2, Array3, ArrayView2, ArrayViewMut2, Axis, Zip};
use rayon::prelude::*;

use super::InputError;
use super::camera::Pinhole;
use super::commit::{Committer, WriteSeek};
use super::error::RunError;
use super::mesh::{self, Document, MeshError};
use super::options::MeshOptions;
use super::progress::Halt;
use super::reconstruction::{Gloss, Reconstruction};
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
    ("depth.png", "image/png"),
    ("depth.exr", "image/x-exr"),
    ("needle.png", "image/png"),
    ("curl.png", "image/png"),
    ("confidence.png", "image/png"),
    ("unreliable.png", "image/png"),
    ("specular.png", "image/png"),
    ("roughness.png", "image/png"),
    ("shaded.png", "image/png"),
    ("preview.png", "image/png"),
    ("mesh.glb", "model/gltf-binary"),
    ("mesh.gltf", "model/gltf+json"),
    ("points.ply", "application/x-ply"),
    ("lights.json", "application/json"),
    ("result.json", "application/json"),
];

/// What a job writes when its options name no `outputs`: the maps most users fetch, in
/// their most precise lossless form that every viewer opens. The rest (EXRs, the three
/// normal components, needle/curl/unreliable pictures, the preview, `mesh.gltf`) are 95
/// of the 127 MB a 2048² job writes with every artifact, and are written on request.
/// `albedo_rgb.png` is written only for colour inputs, the [`GLOSSY_OUTPUTS`] only by the
/// `glossy` solver; under a camera `height.png` gives way to [`DEFAULT_DEPTH_OUTPUTS`].
pub const DEFAULT_OUTPUTS: &[&str] = &[
    "albedo.png",
    "albedo_rgb.png",
    "mask.png",
    "normal.png",
    "height.png",
    "confidence.png",
    "specular.png",
    "roughness.png",
    "shaded.png",
    "mesh.glb",
    "result.json",
];

/// Added to the default set under a camera: the depth in both forms and the point cloud,
/// what a perspective reconstruction is for.
pub const DEFAULT_DEPTH_OUTPUTS: &[&str] = &["depth.png", "depth.exr", "points.ply"];

/// The `glossy` solver's material maps: specular albedo and GGX roughness (0 where the
/// pixel is Lambertian), each 16-bit over [0, 1]; `albedo.png` is then the diffuse albedo.
pub const GLOSSY_OUTPUTS: [&str; 2] = ["specular.png", "roughness.png"];

/// In an `outputs` selection, stands for every artifact.
pub const ALL: &str = "all";

/// Artifacts a run writes when it has them, whatever the selection: `lights.json`, the
/// light table with the intensities a near-light run estimated.
pub const UNSELECTED: [&str; 1] = ["lights.json"];

/// Whether artifact `name` is to be written under the `outputs` selection `selection`
/// (the default set when there is none), for a surface of heights, or of depth when
/// `camera` ([`fits_surface`]); never one of [`UNSELECTED`].
pub fn wanted(selection: Option<&[String]>, name: &str, camera: bool) -> bool {
    let selected = match selection {
        None => DEFAULT_OUTPUTS.contains(&name) || camera && DEFAULT_DEPTH_OUTPUTS.contains(&name),
        Some(names) => names.iter().any(|n| n == name || n == ALL),
    };
    selected && fits_surface(name, camera) && !UNSELECTED.contains(&name)
}

/// Whether artifact `name` exists for a surface of heights (orthographic), or of depth
/// along the optical axis when `camera`: the height pictures for one, the depth pictures
/// for the other.
pub fn fits_surface(name: &str, camera: bool) -> bool {
    match name {
        "height.png" | "height.exr" => !camera,
        "depth.png" | "depth.exr" => camera,
        _ => true,
    }
}

/// Content-Type of an artifact, or None when the name is not one.
pub fn content_type(name: &str) -> Option<&'static str> {
    ARTIFACTS.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// `points.ply` and `mesh.glb` of `rec`'s surface (heights, or depth unprojected through
/// `camera`), each when `wanted` takes it; a mask too small to triangulate gives a note in
/// `notes` instead of the mesh. Returns the names written.
pub fn write_geometry(
    rec: &Reconstruction,
    mesh_options: &MeshOptions,
    camera: Option<&Pinhole>,
    wanted: &dyn Fn(&str) -> bool,
    (dir, commits): (&Path, &Committer),
    notes: &mut Vec<String>,
) -> Result<Vec<String>, RunError> {
    let mut written = Vec::new();
    if wanted("points.ply") {
        commits.write(dir, "points.ply", &mut |f| {
            mesh::write_points_ply(f, &rec.heights, &rec.normals, &rec.mask, camera)
        })?;
        written.push("points.ply".to_string());
    }
    if !wanted("mesh.glb") {
        return Ok(written);
    }
    match Document::with_camera(rec, mesh_options, camera) {
        Ok(doc) => {
            commits.write(dir, "mesh.glb", &mut |f| {
                doc.write_glb(f).map_err(|e| match e {
                    MeshError::Write(io) => io,
                    other => std::io::Error::other(other.to_string()),
                })
            })?;
            written.push("mesh.glb".to_string());
        }
        Err(e @ (MeshError::EmptyMask | MeshError::NoTriangles { .. })) => {
            notes.push(format!("no mesh.glb: {e}"))
        }
        Err(e) => {
            return Err(RunError::Output {
                path: dir.join("mesh.glb").display().to_string(),
                reason: e.to_string(),
            });
        }
    }
    Ok(written)
}

/// Check an `outputs` selection names only known artifacts.
pub fn check_selection(names: &[String]) -> Result<(), InputError> {
    match names
        .iter()
        .find(|n| *n != ALL && content_type(n).is_none())
    {
        Some(bad) => Err(InputError::Options(format!(
            "unknown output {bad:?}; known: {ALL:?} or {}",
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

/// A single-part scan-line float EXR of `channels`, uncompressed: float normals and
/// heights barely compress losslessly and the compressors cost more than they save.
fn exr_image<'c, C: 'c + WritableChannels<'c>>(
    (rows, cols): (usize, usize),
    channels: C,
) -> Image<Layer<C>> {
    Image::from_encoded_channels((cols, rows), Encoding::UNCOMPRESSED, channels)
}

/// Stream an EXR into `out`; pixels come from the image's closure a line at a time.
fn exr_to<'i, C: WritableChannels<'i>>(
    out: &mut dyn WriteSeek,
    image: &'i Image<Layer<C>>,
) -> std::io::Result<()> {
    image
        .write()
        .non_parallel()
        .to_buffered(out)
        .map_err(|e| match e {
            exr::error::Error::Io(e) => e,
            e => std::io::Error::other(e),
        })
}

/// A 16-bit PNG (gray or RGB) with one channel per plane: `unit(channel, value)` in
/// [0, 1] (clamped; NaN → 0), 0 off the mask. Streamed a row at a time with the `png`
/// crate, with the same settings as [`png_to`]: no whole-image buffer (through the image
/// crate's encoder there were three: the samples, their big-endian copy and the
/// compressed stream).
fn png16_to<const C: usize>(
    out: &mut dyn Write,
    mask: &Array2<bool>,
    planes: [ArrayView2<f32>; C],
    unit: impl Fn(usize, f32) -> f32,
) -> std::io::Result<()> {
    png16_rows_to::<C>(out, mask.dim(), |r, mut samples| {
        for (k, plane) in planes.iter().enumerate() {
            Zip::from(samples.column_mut(k))
                .and(plane.row(r))
                .and(mask.row(r))
                .for_each(|s, &v, &m| {
                    *s = if m { unit16(unit(k, v)) } else { 0 }.to_be_bytes();
                });
        }
    })
}

/// `shaded.png`: the albedo re-lit by `light`, shaded a row at a time as it is encoded
/// (a whole shaded frame would add a map to the job's peak, beside the integration).
fn shaded_to(
    out: &mut dyn Write,
    albedo: &Array2<f32>,
    normals: &Array3<f32>,
    mask: &Array2<bool>,
    light: [f64; 3],
) -> std::io::Result<()> {
    let shading = render::Shading::new(light);
    png16_rows_to::<1>(out, mask.dim(), |r, mut samples| {
        Zip::from(samples.column_mut(0))
            .and(albedo.row(r))
            .and(normals.index_axis(Axis(0), r).lanes(Axis(1)))
            .and(mask.row(r))
            .for_each(|s, &a, n, &m| {
                *s = if m { unit16(shading.at(a, n)) } else { 0 }.to_be_bytes();
            });
    })
}

/// A 16-bit PNG of `C` channels, a row at a time: `fill(r, samples)` writes row `r`'s
/// big-endian samples, one row of `C` per pixel.
fn png16_rows_to<const C: usize>(
    out: &mut dyn Write,
    (rows, cols): (usize, usize),
    mut fill: impl FnMut(usize, ArrayViewMut2<[u8; 2]>),
) -> std::io::Result<()> {
    let mut encoder = png::Encoder::new(out, cols as u32, rows as u32);
    encoder.set_color(match C {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        _ => unreachable!("16-bit pictures are gray or RGB"),
    });
    encoder.set_depth(png::BitDepth::Sixteen);
    encoder.set_compression(png::Compression::Fast);
    encoder.set_filter(png::Filter::Up);
    let mut writer = encoder.write_header()?;
    let mut stream = writer.stream_writer_with_size(1 << 18)?;
    let mut row = vec![[0u8; 2]; cols * C];
    for r in 0..rows {
        fill(
            r,
            ArrayViewMut2::from_shape((cols, C), &mut row).expect("C per pixel"),
        );
        stream.write_all(row.as_flattened())?;
    }
    stream.finish()?;
    Ok(writer.finish()?)
}

/// [0, 1] to 16 bits, rounding half away from zero like `f32::round` but without its
/// libm call, so the conversion loops vectorise: the fraction x − trunc(x) is exact.
fn unit16(v: f32) -> u16 {
    let x = v.clamp(0.0, 1.0) * 65535.0;
    let t = x as u16;
    t + u16::from(x - t as f32 >= 0.5)
}

fn binary_to(out: &mut dyn Write, m: &Array2<bool>) -> std::io::Result<()> {
    let (rows, cols) = m.dim();
    let mut data = Array2::<u8>::zeros((rows, cols));
    Zip::from(&mut data)
        .and(m)
        .par_for_each(|o, &b| *o = if b { 255 } else { 0 });
    let (data, _) = data.into_raw_vec_and_offset();
    let img = ImageBuffer::<Luma<u8>, _>::from_raw(cols as u32, rows as u32, data)
        .expect("one value per pixel");
    png_to(out, &img)
}

/// Normal in the OpenGL normal-map frame (x right, y up, z to viewer) from the seed frame.
fn gl_normal(n: &Array3<f32>, r: usize, c: usize) -> [f32; 3] {
    [n[[r, c, 0]], -n[[r, c, 1]], n[[r, c, 2]]]
}

/// The arrays the pictures are drawn from, borrowed from a [`Reconstruction`] or, while
/// the integration still runs, from the surface it starts from (then without heights).
pub struct Maps<'a> {
    pub albedo: &'a Array2<f32>,
    pub albedo_rgb: Option<&'a Array3<f32>>,
    pub normals: &'a Array3<f32>,
    pub mask: &'a Array2<bool>,
    /// None while the integration runs.
    pub curl: Option<&'a Array2<f32>>,
    pub confidence: &'a Array2<f32>,
    pub unreliable: &'a Array2<bool>,
    pub heights: Option<Heights<'a>>,
    /// The `glossy` solver's lobe maps.
    pub gloss: Option<&'a Gloss>,
}

/// Integrated heights (or depth, for the depth pictures) and their range over the mask.
pub struct Heights<'a> {
    pub z: &'a Array2<f32>,
    pub min: f32,
    pub max: f32,
}

impl<'a> Maps<'a> {
    pub fn of(rec: &'a Reconstruction) -> Self {
        Self {
            albedo: &rec.albedo,
            albedo_rgb: rec.albedo_rgb.as_ref(),
            normals: &rec.normals,
            mask: &rec.mask,
            curl: Some(&rec.curl),
            confidence: &rec.confidence,
            unreliable: &rec.unreliable,
            gloss: rec.gloss.as_ref(),
            heights: Some({
                let (min, max) = rec.report.surface_range();
                Heights {
                    z: &rec.heights,
                    min,
                    max,
                }
            }),
        }
    }

    fn heights(&self) -> &Heights<'a> {
        (self.heights.as_ref()).expect("height pictures are encoded after the integration")
    }

    fn curl(&self) -> &'a Array2<f32> {
        self.curl
            .expect("the curl picture is encoded after the integration")
    }
}

/// Whether picture `name` is drawn after the integration: from the heights (or depth), or
/// from the curl, which is formed once the integration's buffers are freed. The others are
/// written while the integration runs.
pub fn after_integration(name: &str) -> bool {
    matches!(
        name,
        "height.png" | "height.exr" | "depth.png" | "depth.exr" | "curl.png"
    )
}

/// Whether artifact `name` applies to these maps (`albedo_rgb.png` needs colour, the
/// [`GLOSSY_OUTPUTS`] the `glossy` solver).
pub fn applies(maps: &Maps, name: &str) -> bool {
    match name {
        "albedo_rgb.png" => maps.albedo_rgb.is_some(),
        _ if GLOSSY_OUTPUTS.contains(&name) => maps.gloss.is_some(),
        _ => true,
    }
}

/// Encode one named artifact (mesh files excepted), or None if it does not apply.
pub fn encode(rec: &Reconstruction, name: &str, shading_light: [f64; 3]) -> Option<Vec<u8>> {
    let mut out = Cursor::new(Vec::new());
    match encode_to(&mut out, &Maps::of(rec), name, shading_light) {
        Ok(true) => Some(out.into_inner()),
        Ok(false) => None,
        Err(e) => panic!("encoding {name} into memory cannot fail: {e}"),
    }
}

/// Stream one named artifact (mesh files excepted) into `out`; false when `name` is not
/// a picture this module knows or does not apply.
pub fn encode_to(
    out: &mut dyn WriteSeek,
    maps: &Maps,
    name: &str,
    shading_light: [f64; 3],
) -> std::io::Result<bool> {
    let (rows, cols) = maps.mask.dim();
    let mask = maps.mask;
    let value = |_, v| v;
    let signed = |_, v: f32| (v + 1.0) * 0.5;
    let normal = |k| maps.normals.index_axis(Axis(2), k);
    match name {
        "albedo.png" => png16_to(out, mask, [maps.albedo.view()], value)?,
        "albedo_rgb.png" => {
            let Some(rgb) = maps.albedo_rgb else {
                return Ok(false);
            };
            let planes = [0, 1, 2].map(|k| rgb.index_axis(Axis(2), k));
            png16_to(out, mask, planes, value)?
        }
        "mask.png" => binary_to(out, mask)?,
        "unreliable.png" => binary_to(out, maps.unreliable)?,
        "confidence.png" => png16_to(out, mask, [maps.confidence.view()], value)?,
        "specular.png" | "roughness.png" => {
            let Some(gloss) = maps.gloss else {
                return Ok(false);
            };
            let map = match name {
                "specular.png" => &gloss.specular,
                _ => &gloss.roughness,
            };
            png16_to(out, mask, [map.view()], value)?
        }
        // The OpenGL normal-map frame: y up, so the seed frame's y is flipped.
        "normal.png" => png16_to(out, mask, [0, 1, 2].map(normal), |k, v| {
            signed(k, if k == 1 { -v } else { v })
        })?,
        "normal_x.png" => png16_to(out, mask, [normal(0)], signed)?,
        "normal_y.png" => png16_to(out, mask, [normal(1)], signed)?,
        "normal_z.png" => png16_to(out, mask, [normal(2)], signed)?,
        "height.png" => {
            let Heights { z, min, max } = maps.heights();
            range_png16_to(out, mask, z, *min..=*max, false)?
        }
        "normal.exr" => {
            let n = SpecificChannels::rgb(|p: Vec2<usize>| {
                let [x, y, z] = gl_normal(maps.normals, p.y(), p.x());
                (x, y, z)
            });
            exr_to(out, &exr_image((rows, cols), n))?
        }
        "height.exr" | "depth.exr" => scalar_exr_to(out, maps.heights().z)?,
        "depth.png" => {
            let Heights { z, min, max } = maps.heights();
            range_png16_to(out, mask, z, *min..=*max, true)?
        }
        "needle.png" => png_to(out, &render::needle_map(maps.albedo, maps.normals, mask))?,
        "curl.png" => png_to(out, &render::diverging(maps.curl(), mask))?,
        "shaded.png" => shaded_to(out, maps.albedo, maps.normals, mask, shading_light)?,
        _ => return Ok(false),
    }
    Ok(true)
}

/// A 16-bit gray PNG of `z` over the mask, 0 off it: 0..65535 ↔ `range` (clamped), or
/// 65535..0 when `reversed` (`depth.png`: near is bright). An empty range maps to 0.
fn range_png16_to(
    out: &mut dyn Write,
    mask: &Array2<bool>,
    z: &Array2<f32>,
    range: std::ops::RangeInclusive<f32>,
    reversed: bool,
) -> std::io::Result<()> {
    let (min, max) = range.into_inner();
    let span = if max > min { max - min } else { 1.0 };
    png16_to(out, mask, [z.view()], |_, z| {
        if reversed {
            (max - z) / span
        } else {
            (z - min) / span
        }
    })
}

/// A one-channel (`Y`) 32-bit float EXR of `z` (`height.exr`, `depth.exr`); read it back
/// with [`decode_height_exr`].
fn scalar_exr_to(out: &mut dyn WriteSeek, z: &Array2<f32>) -> std::io::Result<()> {
    let channel = SpecificChannels::build()
        .with_channel("Y")
        .with_pixel_fn(|p: Vec2<usize>| (z[[p.y(), p.x()]],));
    exr_to(out, &exr_image(z.dim(), channel))
}

/// Write the picture artifacts `names` in parallel; returns the names written (an
/// artifact that does not apply, such as `albedo_rgb.png` for gray inputs, is skipped, and
/// so is every picture not yet started once `halt` says stop).
pub fn write_pictures(
    maps: &Maps,
    names: &[&str],
    shading_light: [f64; 3],
    dir: &Path,
    commits: &Committer,
    halt: Halt,
) -> Result<Vec<String>, RunError> {
    let written: Vec<Option<String>> = names
        .par_iter()
        .map(|name| {
            if !applies(maps, name) || halt() {
                return Ok(None);
            }
            commits.write(dir, name, &mut |f| {
                encode_to(f, maps, name, shading_light).map(|_| ())
            })?;

            Ok(Some(name.to_string()))
        })
        .collect::<Result<_, RunError>>()?;
    Ok(written.into_iter().flatten().collect())
}

/// `shaded.png` under another light, from a job's stored `albedo.png` and 16-bit
/// `normal.png` in `dir`: both read a row at a time in step, each row shaded and encoded
/// as it is read, so a re-shade holds a few rows and the encoded picture (given
/// [`shaded_png_capacity`] up front), whatever the job's size.
pub fn shaded_png_from_dir(dir: &Path, light: [f64; 3]) -> Result<Vec<u8>, InputError> {
    super::lights::check_direction(light)?;
    let mut albedo = PictureRows::open(dir, "albedo.png", 1)?;
    let mut normal = PictureRows::open(dir, "normal.png", 3)?;
    if albedo.size != normal.size {
        return Err(InputError::io(
            dir,
            "albedo.png and normal.png differ in size",
        ));
    }
    let (cols, rows) = albedo.size;
    let mut out = Vec::with_capacity(shaded_png_capacity(cols as u64, rows as u64));
    let shading = render::Shading::new(light);
    let mut failed = None;
    png16_rows_to::<1>(&mut out, (rows, cols), |_, mut samples| {
        let read = albedo.next().and_then(|a| Ok((a, normal.next()?)));
        let (a, n) = match read {
            Ok(rows) if failed.is_none() => rows,
            Ok(_) => return,
            Err(e) => {
                failed.get_or_insert(e);
                return;
            }
        };
        for (c, s) in samples.column_mut(0).iter_mut().enumerate() {
            // normal.png holds (n + 1) / 2 in the OpenGL frame (y up): back to a unit
            // normal in the seed frame. Off the mask it is 0, but so is the albedo, and
            // with it the shading.
            let v = [0, 1, 2].map(|k| 2.0 * n[3 * c + k] - 1.0);
            let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            let unit = if len > 0.0 {
                [v[0] / len, -v[1] / len, v[2] / len]
            } else {
                [0.0; 3]
            };
            *s = unit16(shading.at(a[c], ndarray::aview1(&unit))).to_be_bytes();
        }
    })
    .expect("encoding a PNG into memory cannot fail");
    match failed {
        Some(e) => Err(e),
        None => Ok(out),
    }
}

/// What a re-shaded `width × height` picture is given room for up front, so that its
/// buffer never grows by copying: the raw rows (a filter byte and 2 bytes a pixel) and
/// deflate's framing should they not compress.
pub fn shaded_png_capacity(width: u64, height: u64) -> usize {
    let raw = height.saturating_mul(1 + 2 * width);
    usize::try_from(raw + raw / 64 + 4096).unwrap_or(usize::MAX)
}

/// A job's stored picture read a row at a time, as values in [0, 1] (8- or 16-bit,
/// `channels` per pixel, not interlaced: what the job wrote).
struct PictureRows {
    path: std::path::PathBuf,
    reader: png::Reader<std::io::BufReader<std::fs::File>>,
    sixteen: bool,
    /// (width, height).
    size: (usize, usize),
    row: Vec<f32>,
}

impl PictureRows {
    fn open(dir: &Path, name: &str, channels: usize) -> Result<Self, InputError> {
        let path = dir.join(name);
        let bad = |why: String| InputError::io(&path, format!("cannot re-shade: {why}"));
        let file = std::fs::File::open(&path).map_err(|e| bad(e.to_string()))?;
        let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
        decoder.set_transformations(png::Transformations::EXPAND);
        let reader = decoder.read_info().map_err(|e| bad(e.to_string()))?;
        let (color, depth) = reader.output_color_type();
        let info = reader.info();
        if info.interlaced || color.samples() != channels {
            return Err(bad(format!(
                "{name} is not the picture a job writes ({color:?}, interlaced: {})",
                info.interlaced
            )));
        }
        let size = (info.width as usize, info.height as usize);
        Ok(Self {
            sixteen: depth == png::BitDepth::Sixteen,
            row: Vec::with_capacity(size.0 * channels),
            size,
            reader,
            path,
        })
    }

    /// The next row's values.
    fn next(&mut self) -> Result<&[f32], InputError> {
        let row = match self.reader.next_row() {
            Ok(Some(row)) => row.data(),
            Ok(None) => return Err(InputError::io(&self.path, "cannot re-shade: rows missing")),
            Err(e) => return Err(InputError::io(&self.path, format!("cannot re-shade: {e}"))),
        };
        self.row.clear();
        if self.sixteen {
            let values = row.chunks_exact(2);
            (self.row).extend(values.map(|b| u16::from_be_bytes([b[0], b[1]]) as f32 / 65535.0));
        } else {
            self.row.extend(row.iter().map(|&b| b as f32 / 255.0));
        }
        Ok(&self.row)
    }
}

/// Decode an encoded artifact's pixels, for tests and tools.
pub fn decode_png16(bytes: &[u8]) -> image::ImageResult<DynamicImage> {
    image::load_from_memory_with_format(bytes, ImageFormat::Png)
}

/// Decode `height.exr` or `depth.exr` (one float channel `Y`), for tests and tools: the
/// image crate reads only RGB(A) EXRs.
pub fn decode_height_exr(bytes: &[u8]) -> exr::error::Result<Array2<f32>> {
    use exr::prelude::{ReadChannels, ReadLayers, ReadSpecificChannel};
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .specific_channels()
        .required("Y")
        .collect_pixels(
            |size, _| Array2::<f32>::zeros((size.height(), size.width())),
            |z, p, (v,): (f32,)| z[[p.y(), p.x()]] = v,
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))?;
    Ok(image.layer_data.channel_data.pixels)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::progress::NEVER;

    #[test]
    fn unit16_rounds_like_f32_round() {
        let edges = (0..=65535u32).flat_map(|k| {
            let x = k as f32 / 65535.0;
            [x, x + 0.5 / 65535.0, (k as f32 + 0.5).next_down() / 65535.0]
        });
        for v in edges.chain([-1.0, 2.0, f32::NAN, f32::INFINITY]) {
            let expected = (v.clamp(0.0, 1.0) * 65535.0).round() as u16;
            assert_eq!(unit16(v), expected, "{v}");
        }
    }

    #[test]
    fn png16_rows_decode_to_their_samples() {
        let mask = Array2::from_shape_fn((3, 4), |(r, c)| r != c);
        let plane =
            |k: usize| Array2::from_shape_fn((3, 4), |(r, c)| (r * 4 + c + k) as f32 / 20.0);
        let (a, b, c) = (plane(0), plane(1), plane(2));
        let flip = |k: usize, v: f32| if k == 1 { 1.0 - v } else { v };
        let mut rgb = Vec::new();
        png16_to(&mut rgb, &mask, [a.view(), b.view(), c.view()], flip).unwrap();
        let rgb = decode_png16(&rgb).unwrap().into_rgb16();
        let mut gray = Vec::new();
        png16_to(&mut gray, &mask, [a.view()], |_, v| v).unwrap();
        let gray = decode_png16(&gray).unwrap().into_luma16();
        for ((r, col), &m) in mask.indexed_iter() {
            let want = |k: usize, v: f32| if m { unit16(flip(k, v)) } else { 0 };
            let px = rgb.get_pixel(col as u32, r as u32).0;
            assert_eq!(
                px,
                [0, 1, 2].map(|k| want(k, plane(k)[[r, col]])),
                "({r}, {col})"
            );
            assert_eq!(
                gray.get_pixel(col as u32, r as u32).0,
                [want(0, a[[r, col]])]
            );
        }
    }

    /// A hemisphere of varying albedo on a disc mask, in the seed frame.
    fn dome(n: usize) -> (Array2<f32>, Array3<f32>, Array2<bool>) {
        let c = (n as f32 - 1.0) / 2.0;
        let mask = Array2::from_shape_fn((n, n), |(r, col)| {
            (r as f32 - c).hypot(col as f32 - c) < 0.45 * n as f32
        });
        let mut normals = Array3::zeros((n, n, 3));
        let mut albedo = Array2::zeros((n, n));
        for ((r, col), &m) in mask.indexed_iter() {
            if m {
                let (x, y) = (
                    (col as f32 - c) / (0.5 * n as f32),
                    (r as f32 - c) / (0.5 * n as f32),
                );
                let z = (1.0 - x * x - y * y).sqrt();
                normals[[r, col, 0]] = x;
                normals[[r, col, 1]] = y;
                normals[[r, col, 2]] = z;
                albedo[[r, col]] = 0.3 + 0.6 * (col as f32 / n as f32);
            }
        }
        (albedo, normals, mask)
    }

    #[test]
    fn reshading_from_the_pictures_matches_shaded_png() {
        let (albedo, normals, mask) = dome(48);
        let zero = Array2::zeros(mask.dim());
        let no = Array2::from_elem(mask.dim(), false);
        let maps = Maps {
            albedo: &albedo,
            albedo_rgb: None,
            normals: &normals,
            mask: &mask,
            curl: None,
            confidence: &zero,
            unreliable: &no,
            gloss: None,
            heights: None,
        };
        let dir = tempfile::tempdir().unwrap();
        let light = [-1.0, 0.5, 2.0];
        let names = ["albedo.png", "normal.png", "shaded.png"];
        write_pictures(&maps, &names, light, dir.path(), &Committer::new(), NEVER).unwrap();
        let direct = image::open(dir.path().join("shaded.png"))
            .unwrap()
            .into_luma16();
        let again = decode_png16(&shaded_png_from_dir(dir.path(), light).unwrap())
            .unwrap()
            .into_luma16();
        let worst = direct
            .pixels()
            .zip(again.pixels())
            .map(|(a, b)| a.0[0].abs_diff(b.0[0]))
            .max()
            .unwrap();
        // 16-bit albedo and normals: a few units in the last bit, nothing more.
        assert!(worst <= 4, "re-shaded differs by {worst} / 65535");
        assert!(direct.pixels().any(|p| p.0[0] > 10_000), "the dome is lit");
    }

    #[test]
    fn the_default_selection_is_the_default_set_and_all_is_everything() {
        let all = [ALL.to_string()];
        for name in UNSELECTED {
            assert!(!wanted(Some(&all), name, false) && !wanted(Some(&all), name, true));
        }
        for (name, _) in ARTIFACTS.iter().filter(|(n, _)| !UNSELECTED.contains(n)) {
            assert_eq!(
                wanted(None, name, false),
                DEFAULT_OUTPUTS.contains(name) && !name.starts_with("depth."),
                "{name}"
            );
            assert!(wanted(Some(&all), name, false) || name.starts_with("depth."));
            // Under a camera: depth in place of heights, and the point cloud.
            let depth = DEFAULT_OUTPUTS.contains(name) || DEFAULT_DEPTH_OUTPUTS.contains(name);
            assert_eq!(
                wanted(None, name, true),
                depth && !name.starts_with("height."),
                "{name}"
            );
            assert!(wanted(Some(&all), name, true) || name.starts_with("height."));
        }
        let some = ["mesh.gltf".to_string()];
        assert!(
            wanted(Some(&some), "mesh.gltf", false) && !wanted(Some(&some), "albedo.png", false)
        );
        let mut defaults = DEFAULT_OUTPUTS.iter().chain(DEFAULT_DEPTH_OUTPUTS);
        assert!(defaults.all(|n| content_type(n).is_some()));
        assert!(check_selection(&[ALL.to_string(), "height.exr".into()]).is_ok());
        assert!(check_selection(&["everything".to_string()]).is_err());
    }

    #[test]
    fn exr_files_round_trip() {
        let (rows, cols) = (3, 5);
        let rgb = |r: usize, c: usize| [r as f32, c as f32 * 0.5, -1.25];
        let mut out = Cursor::new(Vec::new());
        let n = SpecificChannels::rgb(|p: Vec2<usize>| rgb(p.y(), p.x()).into());
        exr_to(&mut out, &exr_image((rows, cols), n)).unwrap();
        // An RGB file reads back through the image crate too.
        let img = image::load_from_memory_with_format(out.get_ref(), ImageFormat::OpenExr)
            .unwrap()
            .to_rgb32f();
        assert_eq!(img.dimensions(), (cols as u32, rows as u32));
        for (c, r, px) in img.enumerate_pixels() {
            assert_eq!(px.0, rgb(r as usize, c as usize), "({r}, {c})");
        }

        let z = Array2::from_shape_fn((rows, cols), |(r, c)| r as f32 - c as f32 * 0.25);
        let mut out = Cursor::new(Vec::new());
        let y = SpecificChannels::build()
            .with_channel("Y")
            .with_pixel_fn(|p: Vec2<usize>| (z[[p.y(), p.x()]],));
        exr_to(&mut out, &exr_image((rows, cols), y)).unwrap();
        assert_eq!(decode_height_exr(out.get_ref()).unwrap(), z);
    }
}
