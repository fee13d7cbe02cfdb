//! A decoded image's samples in an unlinked scratch file, rows one after another, and
//! any run of its rows read back as an image.

use std::fs::File;
use std::io::BufWriter;
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::Path;

use image::{ColorType, DynamicImage, ImageBuffer};

/// An image's decoded samples in an unlinked scratch file: its rows one after another, in
/// the layout of the `DynamicImage` it decodes to (native byte order).
pub(super) struct Spill {
    pub(super) file: File,
    pub(super) color: ColorType,
    pub(super) row_bytes: usize,
}

impl Spill {
    /// A new, empty spill in `dir`, written through a buffer.
    pub(super) fn create(dir: &Path) -> std::io::Result<BufWriter<File>> {
        Ok(BufWriter::with_capacity(
            1 << 20,
            tempfile::tempfile_in(dir)?,
        ))
    }

    /// Rows `rows` as a `width`-wide image, read back.
    pub(super) fn rows(&self, rows: Range<usize>, width: usize) -> std::io::Result<DynamicImage> {
        let at = (rows.start * self.row_bytes) as u64;
        let len = rows.len() * self.row_bytes;
        let (w, h) = (width as u32, rows.len() as u32);
        let bytes = |len: usize| -> std::io::Result<Vec<u8>> {
            let mut v = vec![0u8; len];
            self.file.read_exact_at(&mut v, at)?;
            Ok(v)
        };
        let wide = || -> std::io::Result<Vec<u16>> {
            let mut v = vec![0u16; len / 2];
            self.file
                .read_exact_at(bytemuck::cast_slice_mut(&mut v), at)?;
            Ok(v)
        };
        let float = || -> std::io::Result<Vec<f32>> {
            let mut v = vec![0f32; len / 4];
            self.file
                .read_exact_at(bytemuck::cast_slice_mut(&mut v), at)?;
            Ok(v)
        };
        let fits = "rows of the spilled size";
        Ok(match self.color {
            ColorType::L8 => {
                DynamicImage::ImageLuma8(ImageBuffer::from_raw(w, h, bytes(len)?).expect(fits))
            }
            ColorType::La8 => {
                DynamicImage::ImageLumaA8(ImageBuffer::from_raw(w, h, bytes(len)?).expect(fits))
            }
            ColorType::Rgb8 => {
                DynamicImage::ImageRgb8(ImageBuffer::from_raw(w, h, bytes(len)?).expect(fits))
            }
            ColorType::Rgba8 => {
                DynamicImage::ImageRgba8(ImageBuffer::from_raw(w, h, bytes(len)?).expect(fits))
            }
            ColorType::L16 => {
                DynamicImage::ImageLuma16(ImageBuffer::from_raw(w, h, wide()?).expect(fits))
            }
            ColorType::La16 => {
                DynamicImage::ImageLumaA16(ImageBuffer::from_raw(w, h, wide()?).expect(fits))
            }
            ColorType::Rgb16 => {
                DynamicImage::ImageRgb16(ImageBuffer::from_raw(w, h, wide()?).expect(fits))
            }
            ColorType::Rgba16 => {
                DynamicImage::ImageRgba16(ImageBuffer::from_raw(w, h, wide()?).expect(fits))
            }
            ColorType::Rgb32F => {
                DynamicImage::ImageRgb32F(ImageBuffer::from_raw(w, h, float()?).expect(fits))
            }
            ColorType::Rgba32F => {
                DynamicImage::ImageRgba32F(ImageBuffer::from_raw(w, h, float()?).expect(fits))
            }
            other => {
                return Err(std::io::Error::other(format!(
                    "no spill layout for {other:?}"
                )));
            }
        })
    }
}
