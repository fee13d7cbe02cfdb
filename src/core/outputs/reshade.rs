//! `shaded.png` re-drawn under another light from a finished job's own `albedo.png`
//! and `normal.png` (the service's re-shading), a band of rows at a time.

use std::path::Path;

use super::encoding::{png16_rows_to, unit16};
use crate::core::error::InputError;
use crate::core::render;

/// `shaded.png` under another light, from a job's stored `albedo.png` and 16-bit
/// `normal.png` in `dir`: both read a row at a time in step, each row shaded and encoded
/// as it is read, so a re-shade holds a few rows and the encoded picture (given
/// [`shaded_png_capacity`] up front), whatever the job's size.
pub fn shaded_png_from_dir(dir: &Path, light: [f64; 3]) -> Result<Vec<u8>, InputError> {
    crate::core::lights::check_direction(light)?;
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
pub(super) struct PictureRows {
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
