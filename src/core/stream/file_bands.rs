//! One image file's rows in bands, in order, for a reader that needs every row once and
//! never the whole image (the light calibration).

use std::fs::File;
use std::io::Seek;

use image::{DynamicImage, ImageBuffer, ImageFormat};

use super::png_rows::png_reader;
use super::scan::{read_up_to, read_whole, whole_decode_error};
use crate::core::error::InputError;
use crate::core::intake::{self, Limits, NamedFile};

/// An image file's rows in order, about `band_bytes` of decoded samples at a time, each
/// band an image of those rows in the layout [`intake::decode`] gives the file (for a
/// reader that needs every row once and never the whole image, e.g. the light
/// calibration). PNGs that can be read row by row are; any other file is decoded whole
/// first. Errors are [`intake::decode`]'s for the same file.
pub fn each_file_band(
    file: &NamedFile,
    limits: &Limits,
    band_bytes: usize,
    mut each: impl FnMut(usize, DynamicImage),
) -> Result<(), InputError> {
    let io = |e: std::io::Error| InputError::io(&file.path, e);
    let mut f = File::open(&file.path).map_err(io)?;
    let mut head = [0u8; 64];
    let got = read_up_to(&mut f, &mut head).map_err(io)?;
    f.rewind().map_err(io)?;
    if image::guess_format(&head[..got]).ok() == Some(ImageFormat::Png)
        && let Ok((mut reader, Some(kind))) = png_reader(f.try_clone().map_err(io)?)
    {
        let info = reader.info();
        let (width, height) = (info.width as usize, info.height as usize);
        if width as u64 * height as u64 > limits.max_pixels_per_image {
            return Err(InputError::TooLarge {
                name: file.name.clone(),
                width: width as u64,
                height: height as u64,
                pixels: width as u64 * height as u64,
                limit: limits.max_pixels_per_image,
            });
        }
        let row_bytes = kind.row_bytes(width);
        let rows = (band_bytes / row_bytes.max(1)).clamp(1, height.max(1));
        let mut raw = Vec::with_capacity(rows * row_bytes);
        let mut row = vec![0u8; row_bytes];
        let mut first = 0;
        for r in 0..height {
            let broken = match reader.read_row(&mut row) {
                Ok(Some(_)) => None,
                Ok(None) => Some("the image data ends early".to_string()),
                Err(e) => Some(e.to_string()),
            };
            if let Some(reason) = broken {
                return whole_decode_error(f, file, limits, &reason);
            }
            raw.extend_from_slice(&row);
            if r + 1 - first == rows || r + 1 == height {
                let n = r + 1 - first;
                each(first, kind.image(width, n, std::mem::take(&mut raw)));
                first = r + 1;
            }
        }
        return Ok(());
    }
    let bytes = read_whole(&mut f).map_err(io)?;
    let img = intake::decode(&file.name, &bytes, limits)?;
    drop(bytes);
    let (width, height) = (img.width(), img.height());
    let row_bytes = width as usize * usize::from(img.color().bytes_per_pixel());
    let rows = (band_bytes / row_bytes.max(1)).clamp(1, height.max(1) as usize) as u32;
    let mut first = 0;
    while first < height {
        let n = rows.min(height - first);
        each(first as usize, rows_of(&img, first, n));
        first += n;
    }
    Ok(())
}

/// Rows `first..first + n` of `img`, copied as one slice of its buffer (a cropped view's
/// `to_image` copies pixel by pixel, several times slower on a camera-sized image).
pub(super) fn rows_of(img: &DynamicImage, first: u32, n: u32) -> DynamicImage {
    fn rows<P: image::Pixel>(
        b: &ImageBuffer<P, Vec<P::Subpixel>>,
        first: u32,
        n: u32,
    ) -> ImageBuffer<P, Vec<P::Subpixel>> {
        let per_row = b.width() as usize * usize::from(P::CHANNEL_COUNT);
        let (start, end) = (first as usize * per_row, (first + n) as usize * per_row);
        ImageBuffer::from_raw(b.width(), n, b.as_raw()[start..end].to_vec())
            .expect("whole rows of the buffer")
    }
    match img {
        DynamicImage::ImageLuma8(b) => DynamicImage::ImageLuma8(rows(b, first, n)),
        DynamicImage::ImageLumaA8(b) => DynamicImage::ImageLumaA8(rows(b, first, n)),
        DynamicImage::ImageRgb8(b) => DynamicImage::ImageRgb8(rows(b, first, n)),
        DynamicImage::ImageRgba8(b) => DynamicImage::ImageRgba8(rows(b, first, n)),
        DynamicImage::ImageLuma16(b) => DynamicImage::ImageLuma16(rows(b, first, n)),
        DynamicImage::ImageLumaA16(b) => DynamicImage::ImageLumaA16(rows(b, first, n)),
        DynamicImage::ImageRgb16(b) => DynamicImage::ImageRgb16(rows(b, first, n)),
        DynamicImage::ImageRgba16(b) => DynamicImage::ImageRgba16(rows(b, first, n)),
        DynamicImage::ImageRgb32F(b) => DynamicImage::ImageRgb32F(rows(b, first, n)),
        DynamicImage::ImageRgba32F(b) => DynamicImage::ImageRgba32F(rows(b, first, n)),
        other => other.crop_imm(0, first, other.width(), n),
    }
}
