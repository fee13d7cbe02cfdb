//! The first pass over one image file: decoded once (row by row when it is a PNG that
//! allows it, else whole) into its spill, with its size, depth, colour and the rows the
//! robust pre-pass samples.

use std::fs::File;
use std::io::{Read, Seek, Write};
use std::path::Path;

use image::{DynamicImage, ImageFormat};

use super::png_rows::{PngKind, PngRows, png_reader};
use super::spill::Spill;
use crate::core::bands;
use crate::core::error::InputError;
use crate::core::intake::{self, Limits, NamedFile};

/// What the first pass learned of one image.
pub(super) struct Scanned {
    pub(super) spill: Spill,
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) depth: u8,
    pub(super) colour: bool,
    /// The rows [`bands::sampled_rows`] names, as images of one or more rows.
    pub(super) sampled: Vec<DynamicImage>,
}

/// The first pass over one image file.
pub(super) fn scan(
    file: &NamedFile,
    limits: &Limits,
    scratch: &Path,
) -> Result<Scanned, InputError> {
    let f = File::open(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    scan_file(f, file, limits, scratch)
}

/// The first pass over an open image file (read from its start): PNGs that can be read row
/// by row are, others whole; either way into a spill in `scratch`.
pub(super) fn scan_file(
    mut f: File,
    file: &NamedFile,
    limits: &Limits,
    scratch: &Path,
) -> Result<Scanned, InputError> {
    let io = |e: std::io::Error| InputError::io(&file.path, e);
    let spill_error = |e: std::io::Error| {
        InputError::io(
            scratch,
            format!("writing the decoded {:?} to a scratch file: {e}", file.name),
        )
    };
    f.rewind().map_err(io)?;
    let mut head = [0u8; 64];
    let got = read_up_to(&mut f, &mut head).map_err(io)?;
    f.rewind().map_err(io)?;
    if image::guess_format(&head[..got]).ok() == Some(ImageFormat::Png)
        // Otherwise the whole decode names the problem, or reads what rows cannot.
        && let Ok((reader, Some(kind))) = png_reader(f.try_clone().map_err(io)?)
    {
        return match scan_rows(reader, kind, limits, scratch) {
            Ok(scanned) => Ok(scanned),
            Err(RowScan::TooLarge { width, height }) => Err(InputError::TooLarge {
                name: file.name.clone(),
                width: width as u64,
                height: height as u64,
                pixels: width as u64 * height as u64,
                limit: limits.max_pixels_per_image,
            }),
            Err(RowScan::Spill(e)) => Err(spill_error(e)),
            Err(RowScan::Broken(reason)) => whole_decode_error(f, file, limits, &reason),
        };
    }
    let bytes = read_whole(&mut f).map_err(io)?;
    let img = intake::decode(&file.name, &bytes, limits)?;
    drop(bytes);
    let (width, height) = (img.width() as usize, img.height() as usize);
    let sampled = (bands::sampled_rows(width, height))
        .map(|r| img.crop_imm(0, r as u32, width as u32, 1))
        .collect();
    let mut out = Spill::create(scratch).map_err(spill_error)?;
    out.write_all(img.as_bytes()).map_err(spill_error)?;
    let spill = Spill {
        file: out.into_inner().map_err(|e| spill_error(e.into_error()))?,
        color: img.color(),
        row_bytes: width * usize::from(img.color().bytes_per_pixel()),
    };
    Ok(Scanned {
        width,
        height,
        depth: intake::bit_depth(&img),
        colour: intake::has_colour(&img),
        sampled,
        spill,
    })
}

pub(super) fn read_up_to(f: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match f.read(&mut buf[got..])? {
            0 => break,
            n => got += n,
        }
    }
    Ok(got)
}

/// The whole file, from its start.
pub(super) fn read_whole(f: &mut File) -> std::io::Result<Vec<u8>> {
    f.rewind()?;
    let mut bytes = Vec::new();
    f.read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// Why a row scan stopped (the file's own error is named by the caller, who knows it).
enum RowScan {
    TooLarge {
        width: usize,
        height: usize,
    },
    Broken(String),
    /// Writing the spill failed (a full disk, most likely).
    Spill(std::io::Error),
}

/// Every row of a PNG once, into a spill in `scratch`: its size, depth, colour and
/// sampled rows.
fn scan_rows(
    mut reader: PngRows,
    kind: PngKind,
    limits: &Limits,
    scratch: &Path,
) -> Result<Scanned, RowScan> {
    let info = reader.info();
    let (width, height) = (info.width as usize, info.height as usize);
    if width as u64 * height as u64 > limits.max_pixels_per_image {
        return Err(RowScan::TooLarge { width, height });
    }
    let mut out = Spill::create(scratch).map_err(RowScan::Spill)?;
    let mut sampled_at = bands::sampled_rows(width, height).peekable();
    let mut sampled = Vec::new();
    let mut colour = false;
    let mut count = 0;
    let row_bytes = kind.row_bytes(width);
    let mut row = vec![0u8; row_bytes];
    for r in 0..height {
        match reader.read_row(&mut row) {
            Ok(Some(_)) => {}
            Ok(None) => return Err(RowScan::Broken("the image data ends early".into())),
            Err(e) => return Err(RowScan::Broken(e.to_string())),
        }
        if kind.channels >= 3 && !colour {
            colour = kind.row_has_colour(&row);
        }
        if sampled_at.peek() == Some(&r) {
            sampled_at.next();
            sampled.extend_from_slice(&row);
            count += 1;
        }
        kind.to_native(&mut row);
        out.write_all(&row).map_err(RowScan::Spill)?;
    }
    let spill = Spill {
        file: (out.into_inner()).map_err(|e| RowScan::Spill(e.into_error()))?,
        color: kind.color_type(),
        row_bytes,
    };
    Ok(Scanned {
        width,
        height,
        depth: kind.depth,
        colour,
        sampled: vec![kind.image(width, count, sampled)],
        spill,
    })
}

/// An error the row reader met: the whole decode's message for the same file (the one
/// [`intake::load`] gives), or the reader's own when the whole decode succeeds.
pub(super) fn whole_decode_error<T>(
    mut f: File,
    file: &NamedFile,
    limits: &Limits,
    reason: &str,
) -> Result<T, InputError> {
    let bytes = read_whole(&mut f).map_err(|e| InputError::io(&file.path, e))?;
    intake::decode(&file.name, &bytes, limits)?;
    Err(InputError::Decode {
        name: file.name.clone(),
        reason: reason.to_string(),
    })
}
