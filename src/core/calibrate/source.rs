//! Where the sphere images come from: a [`Source`] says how many there are, their names
//! and sizes, and reads one image's luminance rows in order, a band at a time, so the
//! calibration never needs a whole set (or, for PNGs, a whole image) decoded at once.
//! Files ([`ImageFiles`]) are read from disk on each pass; decoded images
//! ([`SphereImage`], slices of them) are a source too.

use std::path::PathBuf;

use image::ImageReader;
use ndarray::{Array2, ArrayView2, s};

use super::error::CalibrationError;
use crate::core::error::InputError;
use crate::core::intake::{self, Limits, NamedFile};
use crate::core::stream;

/// One decoded sphere image.
#[derive(Debug, Clone)]
pub struct SphereImage {
    pub name: String,
    /// Luminance, 0..=65535 standing for [0, 1].
    pub plane: Array2<u16>,
}

/// Decoded samples a file source hands over at a time (one band of one image).
const BAND_BYTES: usize = 4 << 20;

/// The sphere images of a calibration, read image by image.
pub trait Source: Sync {
    fn count(&self) -> usize;
    fn name(&self, k: usize) -> &str;
    /// Image `k`'s (width, height), from its header where it is a file.
    fn size(&self, k: usize) -> Result<(usize, usize), CalibrationError>;
    /// Image `k`'s luminance (0..=65535), its rows in order: `rows(first_row, band)`.
    fn read(
        &self,
        k: usize,
        rows: &mut dyn FnMut(usize, ArrayView2<u16>),
    ) -> Result<(), CalibrationError>;
}

impl Source for [SphereImage] {
    fn count(&self) -> usize {
        self.len()
    }

    fn name(&self, k: usize) -> &str {
        &self[k].name
    }

    fn size(&self, k: usize) -> Result<(usize, usize), CalibrationError> {
        let (h, w) = self[k].plane.dim();
        Ok((w, h))
    }

    fn read(
        &self,
        k: usize,
        rows: &mut dyn FnMut(usize, ArrayView2<u16>),
    ) -> Result<(), CalibrationError> {
        let plane = &self[k].plane;
        let band = (BAND_BYTES / (2 * plane.ncols()).max(1)).max(1);
        let mut r = 0;
        while r < plane.nrows() {
            let end = (r + band).min(plane.nrows());
            rows(r, plane.slice(s![r..end, ..]));
            r = end;
        }
        Ok(())
    }
}

impl Source for Vec<SphereImage> {
    fn count(&self) -> usize {
        self.len()
    }

    fn name(&self, k: usize) -> &str {
        self.as_slice().name(k)
    }

    fn size(&self, k: usize) -> Result<(usize, usize), CalibrationError> {
        self.as_slice().size(k)
    }

    fn read(
        &self,
        k: usize,
        rows: &mut dyn FnMut(usize, ArrayView2<u16>),
    ) -> Result<(), CalibrationError> {
        self.as_slice().read(k, rows)
    }
}

impl Source for SphereImage {
    fn count(&self) -> usize {
        1
    }

    fn name(&self, _: usize) -> &str {
        &self.name
    }

    fn size(&self, _: usize) -> Result<(usize, usize), CalibrationError> {
        std::slice::from_ref(self).size(0)
    }

    fn read(
        &self,
        _: usize,
        rows: &mut dyn FnMut(usize, ArrayView2<u16>),
    ) -> Result<(), CalibrationError> {
        std::slice::from_ref(self).read(0, rows)
    }
}

/// Image files, decoded each time they are read (PNGs row by row, other formats whole,
/// one at a time per reading thread), within `limits`.
#[derive(Debug, Clone)]
pub struct ImageFiles {
    pub files: Vec<NamedFile>,
    pub limits: Limits,
}

impl ImageFiles {
    pub fn new(files: Vec<NamedFile>, limits: Limits) -> Self {
        Self { files, limits }
    }

    /// The files in `dir` named `names`, in that order.
    pub fn in_dir(dir: &std::path::Path, names: &[String], limits: Limits) -> Self {
        let files = names
            .iter()
            .map(|n| NamedFile {
                name: n.clone(),
                path: dir.join(n),
            })
            .collect();
        Self { files, limits }
    }

    /// Every image decoded whole (for callers that edit them, e.g. tests).
    pub fn decode_all(&self) -> Result<Vec<SphereImage>, CalibrationError> {
        use rayon::prelude::*;
        (0..self.files.len())
            .into_par_iter()
            .map(|k| {
                let (w, h) = self.size(k)?;
                let mut plane = Array2::zeros((h, w));
                self.read(k, &mut |r, band| {
                    plane.slice_mut(s![r..r + band.nrows(), ..]).assign(&band);
                })?;
                Ok(SphereImage {
                    name: self.files[k].name.clone(),
                    plane,
                })
            })
            .collect()
    }

    fn path(&self, k: usize) -> &PathBuf {
        &self.files[k].path
    }
}

impl Source for ImageFiles {
    fn count(&self) -> usize {
        self.files.len()
    }

    fn name(&self, k: usize) -> &str {
        &self.files[k].name
    }

    fn size(&self, k: usize) -> Result<(usize, usize), CalibrationError> {
        let name = &self.files[k].name;
        let undecodable = |reason: String| InputError::Decode {
            name: name.clone(),
            reason,
        };
        let reader = ImageReader::open(self.path(k))
            .map_err(|e| InputError::io(self.path(k), e))?
            .with_guessed_format()
            .map_err(|e| InputError::io(self.path(k), e))?;
        if reader.format().is_none() {
            return Err(InputError::UnsupportedFormat {
                name: name.clone(),
                reason: "unrecognised file signature".into(),
            }
            .into());
        }
        let (w, h) = reader
            .into_dimensions()
            .map_err(|e| undecodable(e.to_string()))?;
        let pixels = w as u64 * h as u64;
        if pixels > self.limits.max_pixels_per_image {
            return Err(InputError::TooLarge {
                name: name.clone(),
                width: w as u64,
                height: h as u64,
                pixels,
                limit: self.limits.max_pixels_per_image,
            }
            .into());
        }
        Ok((w as usize, h as usize))
    }

    fn read(
        &self,
        k: usize,
        rows: &mut dyn FnMut(usize, ArrayView2<u16>),
    ) -> Result<(), CalibrationError> {
        stream::each_file_band(&self.files[k], &self.limits, BAND_BYTES, |r, band| {
            rows(r, intake::to_luma16(band).view())
        })?;
        Ok(())
    }
}
