//! PNGs read a row at a time: the reader, and the layout of its rows (which sample
//! layouts can be taken as they come, and the image they make).

use std::fs::File;
use std::io::BufReader;

use image::{ColorType, DynamicImage, ImageBuffer};

/// Sample layout of PNG rows as the reader gives them (16-bit big-endian).
#[derive(Clone, Copy)]
pub(super) struct PngKind {
    pub(super) channels: usize,
    pub(super) depth: u8,
}

impl PngKind {
    pub(super) fn row_bytes(self, width: usize) -> usize {
        width * self.channels * usize::from(self.depth / 8)
    }

    /// Whether R, G and B differ anywhere in the row (as `intake` decides colour: by more
    /// than 10⁻⁶ of full scale, which for integer samples is any difference).
    pub(super) fn row_has_colour(self, row: &[u8]) -> bool {
        let px = self.channels * usize::from(self.depth / 8);
        let s = usize::from(self.depth / 8);
        row.chunks_exact(px)
            .any(|p| p[0..s] != p[s..2 * s] || p[s..2 * s] != p[2 * s..3 * s])
    }

    /// The layout of the image `image` decodes the file to.
    pub(super) fn color_type(self) -> ColorType {
        match (self.channels, self.depth) {
            (1, 8) => ColorType::L8,
            (2, 8) => ColorType::La8,
            (3, 8) => ColorType::Rgb8,
            (4, 8) => ColorType::Rgba8,
            (1, _) => ColorType::L16,
            (2, _) => ColorType::La16,
            (3, _) => ColorType::Rgb16,
            _ => ColorType::Rgba16,
        }
    }

    /// A row's 16-bit samples from big-endian to native order (as the spill keeps them).
    pub(super) fn to_native(self, row: &mut [u8]) {
        if self.depth == 16 {
            for s in row.chunks_exact_mut(2) {
                let v = u16::from_be_bytes([s[0], s[1]]);
                s.copy_from_slice(&v.to_ne_bytes());
            }
        }
    }

    /// `rows` rows of raw bytes as an image of the kind `image` decodes the file to.
    pub(super) fn image(self, width: usize, rows: usize, raw: Vec<u8>) -> DynamicImage {
        let (w, h) = (width as u32, rows as u32);
        let wide = || -> Vec<u16> {
            raw.chunks_exact(2)
                .map(|b| u16::from_be_bytes([b[0], b[1]]))
                .collect()
        };
        let fits = "rows of the decoded size";
        match (self.channels, self.depth) {
            (1, 8) => DynamicImage::ImageLuma8(ImageBuffer::from_raw(w, h, raw).expect(fits)),
            (2, 8) => DynamicImage::ImageLumaA8(ImageBuffer::from_raw(w, h, raw).expect(fits)),
            (3, 8) => DynamicImage::ImageRgb8(ImageBuffer::from_raw(w, h, raw).expect(fits)),
            (4, 8) => DynamicImage::ImageRgba8(ImageBuffer::from_raw(w, h, raw).expect(fits)),
            (1, _) => DynamicImage::ImageLuma16(ImageBuffer::from_raw(w, h, wide()).expect(fits)),
            (2, _) => DynamicImage::ImageLumaA16(ImageBuffer::from_raw(w, h, wide()).expect(fits)),
            (3, _) => DynamicImage::ImageRgb16(ImageBuffer::from_raw(w, h, wide()).expect(fits)),
            _ => DynamicImage::ImageRgba16(ImageBuffer::from_raw(w, h, wide()).expect(fits)),
        }
    }
}

pub(super) type PngRows = png::Reader<BufReader<File>>;

/// A row reader over an open PNG, read from where it stands, and its layout when rows
/// can be taken as they come.
pub(super) fn png_reader(f: File) -> Result<(PngRows, Option<PngKind>), png::DecodingError> {
    let mut decoder = png::Decoder::new(BufReader::with_capacity(16 << 10, f));
    decoder.set_transformations(png::Transformations::EXPAND);
    let reader = decoder.read_info()?;
    let info = reader.info();
    let plain = !info.interlaced && info.trns.is_none();
    let kind = match (info.color_type, info.bit_depth) {
        (_, png::BitDepth::One | png::BitDepth::Two | png::BitDepth::Four) => None,
        (png::ColorType::Indexed, _) => None,
        (ct, bd) => Some(PngKind {
            channels: ct.samples(),
            depth: if bd == png::BitDepth::Sixteen { 16 } else { 8 },
        }),
    };
    Ok((reader, kind.filter(|_| plain)))
}
