//! Image files read in bands of rows, in lockstep over the set, so that a job holds a band
//! per image rather than the whole 16-bit stack ([`Streamed`], a [`Stack`]).
//!
//! Each image is decoded once, in a first pass over the set (in parallel over the images),
//! into a scratch file of its own (its spill: the decoded samples, row after row). The pass
//! keeps in memory only what must be known of the whole set before any band is solved:
//! each image's size, depth and whether it carries colour, and the rows the robust
//! pre-pass samples (see [`bands::sampled_rows`]). The solve then reads the bands back from
//! the spills (positioned reads, each band's images in parallel), with no second decode.
//! Non-interlaced 8/16-bit PNGs without a palette are decoded row by row through the `png`
//! crate straight into their spill; every other file is decoded whole (by
//! [`intake::decode`]), spilled and dropped, so the first pass holds at most one decoded
//! image per thread. The first pass over one file can be done ahead ([`prescan`], e.g.
//! while the rest of an upload arrives) and handed to [`open_with`].
//!
//! Spills are made in the caller's scratch directory and unlinked from the start
//! (`tempfile::tempfile_in`): their space is freed when the set (or the prescan) is
//! dropped, whether the run succeeds, fails or is stopped, and a crash leaves nothing
//! behind. They take the decoded samples' size (2 bytes per pixel for 16-bit gray), so the
//! directory should be on a disk, not a tmpfs, which would hold them in memory.
//!
//! A band is converted exactly as [`intake::load`] converts a whole image (the same
//! per-pixel functions over the band as a small image), so the planes, and with them
//! every result, are the same as the set loaded whole.
//!
//! This file is the set and its bands; below it: `scan` (the first pass over one file),
//! `png_rows` (PNGs a row at a time), `spill` (the scratch files) and `file_bands` (one
//! file's rows in bands, for the calibration).

mod file_bands;
mod png_rows;
mod scan;
mod spill;

use std::fs::File;
use std::ops::Range;
use std::path::Path;

use image::DynamicImage;
use rayon::prelude::*;

pub use file_bands::each_file_band;

use super::bands::{self, Band, Samples, SetInfo, Stack};
use super::error::InputError;
use super::intake::{self, DirMask, Limits, NamedFile};
use super::lights::Light;
use scan::{Scanned, scan, scan_file};
use spill::Spill;

/// What one band may hold over all images together (raw rows, planes, colour): the
/// bound on the images' memory, whatever their number.
pub const BAND_BYTES: usize = 32 << 20;

/// [`intake::load_dir`], streamed: the folder's set as a [`Stack`], spilled to `scratch`.
pub fn open_dir(
    dir: &Path,
    mask: DirMask<'_>,
    limits: &Limits,
    scratch: &Path,
) -> Result<Streamed, InputError> {
    let found = intake::dir_files(dir, mask)?;
    let set = open(
        found.lights,
        &found.files,
        found.mask.as_ref(),
        limits,
        scratch,
    )?;
    Ok(set.noted(found.notes))
}

/// [`intake::load`], streamed: the first pass over the files (errors as `load` reports
/// them, the first in table order), spilling each image to `scratch`, leaving the bands to
/// be read by the solve.
pub fn open(
    lights: Vec<Light>,
    files: &[NamedFile],
    mask: Option<&NamedFile>,
    limits: &Limits,
    scratch: &Path,
) -> Result<Streamed, InputError> {
    open_with(lights, files, mask, limits, scratch, |_| None)
}

/// One image's first pass done ahead by [`prescan`]: its spill and sampled rows.
pub struct Prescanned(Scanned);

/// The first pass over an image file, from an open handle to it (read from its start),
/// with the limits [`open_with`] will be given, spilling to `scratch`. `None` on every
/// error, which `open_with` then reports as it would without a prescan.
pub fn prescan(file: File, limits: &Limits, scratch: &Path) -> Option<Prescanned> {
    let unnamed = NamedFile {
        name: String::new(),
        path: Default::default(),
    };
    scan_file(file, &unnamed, limits, scratch)
        .ok()
        .map(Prescanned)
}

/// [`open`], taking image `i` of `files` from `prescanned(i)` when that has it (the
/// [`prescan`] of the same file with the same limits, or an error that stands for its
/// scan's), so the set and its first error are the same as without.
pub fn open_with(
    lights: Vec<Light>,
    files: &[NamedFile],
    mask: Option<&NamedFile>,
    limits: &Limits,
    scratch: &Path,
    prescanned: impl Fn(usize) -> Option<Result<Prescanned, InputError>> + Sync,
) -> Result<Streamed, InputError> {
    let ordered = intake::check_files(&lights, files, limits)?;
    let scanned: Vec<Scanned> = (ordered.par_iter())
        .map(|&i| match prescanned(i) {
            Some(ready) => ready.map(|Prescanned(s)| s),
            None => scan(&files[i], limits, scratch),
        })
        .collect::<Vec<_>>()
        .into_iter()
        .collect::<Result<_, InputError>>()?;
    let (width, height) = (scanned[0].width, scanned[0].height);
    let sizes: Vec<((usize, usize), u8)> = (scanned.iter())
        .map(|s| ((s.height, s.width), s.depth))
        .collect();
    intake::check_sizes(&lights, &sizes)?;
    let mut lights = lights;
    let mut images = Vec::with_capacity(scanned.len());
    for (s, light) in scanned.into_iter().zip(&mut lights) {
        // As intake: a colour image under an RGB light is balanced, and its light's
        // intensity becomes s = min(r, g, b).
        let gains = light.rgb.filter(|_| s.colour);
        if let Some(g) = gains {
            light.intensity = g.iter().copied().fold(f64::INFINITY, f64::min);
        }
        let scaled = light.direction.map(|c| (c * light.intensity) as f32);
        images.push(Image {
            name: light.name.clone(),
            spill: s.spill,
            colour: s.colour,
            gains,
            scaled,
            sampled: s.sampled,
        });
    }
    let colour = images.iter().all(|i| i.colour);
    let samples = Samples {
        stride: bands::sample_stride(width, height),
        planes: (images.iter_mut())
            .map(|i| {
                let rows = std::mem::take(&mut i.sampled);
                rows.into_iter()
                    .flat_map(|r| i.convert(r, false).0)
                    .collect()
            })
            .collect(),
    };
    let mask_file = mask.map(|m| m.name.clone());
    let mask = (mask.map(|m| intake::load_mask(m, height, width, limits))).transpose()?;
    let per_pixel = 4 + 8 + if colour { 16 } else { 0 };
    let band_rows =
        (BAND_BYTES / (images.len() * width * per_pixel).max(1)).clamp(1, height.max(1));
    Ok(Streamed {
        info: SetInfo {
            width,
            height,
            bit_depth: sizes[0].1,
            lights,
            colour,
            mask,
            mask_file,
            notes: Vec::new(),
        },
        samples,
        images,
        band_rows,
        planes: Vec::new(),
        moments: Vec::new(),
        next_row: 0,
    })
}

/// A set whose images are read back from their spills band by band (see the module docs).
pub struct Streamed {
    info: SetInfo,
    samples: Samples,
    images: Vec<Image>,
    band_rows: usize,
    /// The current band: per image, its luminance rows; for colour sets, the moments.
    planes: Vec<Vec<u16>>,
    moments: Vec<f32>,
    next_row: usize,
}

impl Streamed {
    /// The set with what intake noted on the caller's behalf (for `result.json`).
    pub fn noted(mut self, notes: Vec<String>) -> Self {
        self.info.notes = notes;
        self
    }
}

impl Stack for Streamed {
    fn info(&self) -> &SetInfo {
        &self.info
    }

    fn samples(&self) -> &Samples {
        &self.samples
    }

    fn band_rows(&self) -> usize {
        self.band_rows
    }

    fn band(&mut self, rows: Range<usize>) -> Result<Band<'_>, InputError> {
        if rows.start != self.next_row || rows.end > self.info.height {
            return Err(InputError::Decode {
                name: "the image set".into(),
                reason: format!(
                    "rows {rows:?} asked for out of order (next is row {})",
                    self.next_row
                ),
            });
        }
        self.next_row = rows.end;
        let (width, count) = (self.info.width, rows.len());
        let colour = self.info.colour;
        let read: Vec<(Vec<u16>, Option<image::Rgb32FImage>)> = (self.images.par_iter())
            .map(|i| {
                let raw = (i.spill.rows(rows.clone(), width)).map_err(|e| InputError::Decode {
                    name: i.name.clone(),
                    reason: format!("reading its decoded rows back from the scratch file: {e}"),
                })?;
                Ok(i.convert(raw, colour))
            })
            .collect::<Vec<_>>()
            .into_iter()
            .collect::<Result<_, InputError>>()?;
        self.planes.clear();
        self.moments.clear();
        if colour {
            self.moments.resize(count * width * 9, 0.0);
        }
        for ((plane, rgb), image) in read.into_iter().zip(&self.images) {
            if let Some(rgb) = rgb {
                intake::add_moments(&mut self.moments, &rgb, image.scaled);
            }
            self.planes.push(plane);
        }
        Ok(Band {
            planes: self.planes.iter().map(|p| p.as_slice()).collect(),
            moments: colour.then_some(self.moments.as_slice()),
        })
    }

    fn rewind(&mut self) {
        self.next_row = 0;
    }
}

/// One image of a [`Streamed`] set.
struct Image {
    /// The light table's name for it.
    name: String,
    spill: Spill,
    /// The image's own colour (its plane is balanced under an RGB light only then).
    colour: bool,
    gains: Option<[f64; 3]>,
    /// Its light as the solve sees it (direction × intensity).
    scaled: [f32; 3],
    /// The first pass's sampled rows, until they are converted.
    sampled: Vec<DynamicImage>,
}

impl Image {
    /// A band's rows (as an image) → its plane, as [`intake::load`] makes an image's
    /// plane, and (for `with_rgb`) the RGB values its colour moments are summed from.
    fn convert(
        &self,
        rows: DynamicImage,
        with_rgb: bool,
    ) -> (Vec<u16>, Option<image::Rgb32FImage>) {
        let (plane, rgb) = intake::band_plane(rows, self.colour, self.gains, with_rgb);
        (plane.into_raw_vec_and_offset().0, rgb)
    }
}

#[cfg(test)]
mod tests;
