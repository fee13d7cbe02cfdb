//! The PNG and EXR encoders the pictures are written with (16-bit rows streamed into
//! the writer, one filter for every PNG), and the decoders that read the project's own
//! 16-bit PNGs and height EXRs back.

use std::io::{Cursor, Write};

use exr::image::write::channels::WritableChannels;
use exr::prelude::{Encoding, Image, Layer, SpecificChannels, Vec2, WritableImage};
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ImageBuffer, ImageEncoder, ImageFormat, Luma};
use ndarray::{Array2, Array3, ArrayView2, ArrayViewMut2, Axis, Zip};

use crate::core::commit::WriteSeek;
use crate::core::render;

/// Row filter for every PNG written: `Up` is one subtraction per byte and on smooth
/// 16-bit maps compresses close to adaptive filtering, which tries all five per row.
pub(super) const PNG_FILTER: FilterType = FilterType::Up;

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

pub(super) fn png_with<P, C>(
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
pub(super) fn exr_image<'c, C: 'c + WritableChannels<'c>>(
    (rows, cols): (usize, usize),
    channels: C,
) -> Image<Layer<C>> {
    Image::from_encoded_channels((cols, rows), Encoding::UNCOMPRESSED, channels)
}

/// Stream an EXR into `out`; pixels come from the image's closure a line at a time.
pub(super) fn exr_to<'i, C: WritableChannels<'i>>(
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
pub(super) fn png16_to<const C: usize>(
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
pub(super) fn shaded_to(
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
pub(super) fn png16_rows_to<const C: usize>(
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
pub(super) fn unit16(v: f32) -> u16 {
    let x = v.clamp(0.0, 1.0) * 65535.0;
    let t = x as u16;
    t + u16::from(x - t as f32 >= 0.5)
}

pub(super) fn binary_to(out: &mut dyn Write, m: &Array2<bool>) -> std::io::Result<()> {
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
pub(super) fn gl_normal(n: &Array3<f32>, r: usize, c: usize) -> [f32; 3] {
    [n[[r, c, 0]], -n[[r, c, 1]], n[[r, c, 2]]]
}

/// A 16-bit gray PNG of `z` over the mask, 0 off it: 0..65535 ↔ `range` (clamped), or
/// 65535..0 when `reversed` (`depth.png`: near is bright). An empty range maps to 0.
pub(super) fn range_png16_to(
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
pub(super) fn scalar_exr_to(out: &mut dyn WriteSeek, z: &Array2<f32>) -> std::io::Result<()> {
    let channel = SpecificChannels::build()
        .with_channel("Y")
        .with_pixel_fn(|p: Vec2<usize>| (z[[p.y(), p.x()]],));
    exr_to(out, &exr_image(z.dim(), channel))
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
