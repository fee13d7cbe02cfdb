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

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, Write};
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::Path;

use image::{ColorType, DynamicImage, ImageBuffer, ImageFormat};
use rayon::prelude::*;

use super::InputError;
use super::bands::{self, Band, Samples, SetInfo, Stack};
use super::intake::{self, DirMask, Limits, NamedFile};
use super::lights::Light;

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
                add_moments(&mut self.moments, &rgb, image.scaled);
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

/// Σ s_k·I_c per pixel of a band, added in table order (so the sums are the same run to
/// run).
fn add_moments(moments: &mut [f32], rgb: &image::Rgb32FImage, s: [f32; 3]) {
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

/// An image's decoded samples in an unlinked scratch file: its rows one after another, in
/// the layout of the `DynamicImage` it decodes to (native byte order).
struct Spill {
    file: File,
    color: ColorType,
    row_bytes: usize,
}

impl Spill {
    /// A new, empty spill in `dir`, written through a buffer.
    fn create(dir: &Path) -> std::io::Result<BufWriter<File>> {
        Ok(BufWriter::with_capacity(
            1 << 20,
            tempfile::tempfile_in(dir)?,
        ))
    }

    /// Rows `rows` as a `width`-wide image, read back.
    fn rows(&self, rows: Range<usize>, width: usize) -> std::io::Result<DynamicImage> {
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

/// What the first pass learned of one image.
struct Scanned {
    spill: Spill,
    width: usize,
    height: usize,
    depth: u8,
    colour: bool,
    /// The rows [`bands::sampled_rows`] names, as images of one or more rows.
    sampled: Vec<DynamicImage>,
}

/// The first pass over one image file.
fn scan(file: &NamedFile, limits: &Limits, scratch: &Path) -> Result<Scanned, InputError> {
    let f = File::open(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    scan_file(f, file, limits, scratch)
}

/// The first pass over an open image file (read from its start): PNGs that can be read row
/// by row are, others whole; either way into a spill in `scratch`.
fn scan_file(
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

fn read_up_to(f: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
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
fn read_whole(f: &mut File) -> std::io::Result<Vec<u8>> {
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
fn whole_decode_error<T>(
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

/// Sample layout of PNG rows as the reader gives them (16-bit big-endian).
#[derive(Clone, Copy)]
struct PngKind {
    channels: usize,
    depth: u8,
}

impl PngKind {
    fn row_bytes(self, width: usize) -> usize {
        width * self.channels * usize::from(self.depth / 8)
    }

    /// Whether R, G and B differ anywhere in the row (as `intake` decides colour: by more
    /// than 10⁻⁶ of full scale, which for integer samples is any difference).
    fn row_has_colour(self, row: &[u8]) -> bool {
        let px = self.channels * usize::from(self.depth / 8);
        let s = usize::from(self.depth / 8);
        row.chunks_exact(px)
            .any(|p| p[0..s] != p[s..2 * s] || p[s..2 * s] != p[2 * s..3 * s])
    }

    /// The layout of the image `image` decodes the file to.
    fn color_type(self) -> ColorType {
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
    fn to_native(self, row: &mut [u8]) {
        if self.depth == 16 {
            for s in row.chunks_exact_mut(2) {
                let v = u16::from_be_bytes([s[0], s[1]]);
                s.copy_from_slice(&v.to_ne_bytes());
            }
        }
    }

    /// `rows` rows of raw bytes as an image of the kind `image` decodes the file to.
    fn image(self, width: usize, rows: usize, raw: Vec<u8>) -> DynamicImage {
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

type PngRows = png::Reader<BufReader<File>>;

/// A row reader over an open PNG, read from where it stands, and its layout when rows
/// can be taken as they come.
fn png_reader(f: File) -> Result<(PngRows, Option<PngKind>), png::DecodingError> {
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

/// An image file's rows in order, about `band_bytes` of decoded samples at a time, each
/// band an image of those rows in the layout [`intake::decode`] gives the file (for a
/// reader that needs every row once and never the whole image, e.g. the light
/// calibration). PNGs that can be read row by row are; any other file is decoded whole
/// first. Errors are [`intake::decode`]'s for the same file.
pub fn each_band(
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
fn rows_of(img: &DynamicImage, first: u32, n: u32) -> DynamicImage {
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

#[cfg(test)]
mod tests {
    use super::*;

    use crate::core::lights::{Intensity, make_light};

    /// A band cut from a decoded image is the cropped view's pixels, for every layout.
    #[test]
    fn rows_of_matches_a_cropped_copy() {
        let base = DynamicImage::ImageRgb16(ImageBuffer::from_fn(5, 7, |x, y| {
            image::Rgb([(x * 1000 + y) as u16, (y * 300) as u16, (x + y) as u16 * 77])
        }));
        for img in [
            DynamicImage::ImageLuma8(base.to_luma8()),
            DynamicImage::ImageLumaA8(base.to_luma_alpha8()),
            DynamicImage::ImageRgb8(base.to_rgb8()),
            DynamicImage::ImageRgba8(base.to_rgba8()),
            DynamicImage::ImageLuma16(base.to_luma16()),
            DynamicImage::ImageLumaA16(base.to_luma_alpha16()),
            base.clone(),
            DynamicImage::ImageRgba16(base.to_rgba16()),
            DynamicImage::ImageRgb32F(base.to_rgb32f()),
            DynamicImage::ImageRgba32F(base.to_rgba32f()),
        ] {
            for (first, n) in [(0, 7), (2, 3), (6, 1)] {
                let band = rows_of(&img, first, n);
                assert_eq!(band, img.crop_imm(0, first, 5, n), "{:?}", img.color());
            }
        }
    }

    /// Images of every kind the reader handles: 8- and 16-bit gray PNG, 8- and 16-bit RGB
    /// PNG (colour), 16-bit RGBA PNG (read by rows); palette PNG, TIFF and BMP (decoded
    /// whole).
    fn write_set(
        dir: &Path,
        kind: &str,
        count: usize,
        rgb_light: bool,
    ) -> (Vec<Light>, Vec<NamedFile>) {
        let (w, h) = (37u32, 29u32);
        let mut lights = Vec::new();
        let mut files = Vec::new();
        for i in 0..count {
            let v = |x: u32, y: u32, c: u32| ((x * 7 + y * 13 + c * 5 + i as u32 * 11) % 256) as u8;
            let ext = match kind {
                "bmp" => "bmp",
                "tiff" => "tiff",
                _ => "png",
            };
            let name = format!("{i}.{ext}");
            let path = dir.join(&name);
            match kind {
                "gray8" => image::GrayImage::from_fn(w, h, |x, y| image::Luma([v(x, y, 0)]))
                    .save(&path)
                    .unwrap(),
                "rgb16" | "tiff" => image::ImageBuffer::from_fn(w, h, |x, y| {
                    let c = |k| v(x, y, k) as u16 * 250 + y as u16;
                    image::Rgb([c(0), c(1), c(2)])
                })
                .save(&path)
                .unwrap(),
                "palette" => write_palette_png(&path, w, h, |x, y| v(x, y, 0) % 16),
                "gray16" => image::ImageBuffer::from_fn(w, h, |x, y| {
                    image::Luma([v(x, y, 0) as u16 * 250 + x as u16])
                })
                .save(&path)
                .unwrap(),
                "rgb8" | "bmp" => image::RgbImage::from_fn(w, h, |x, y| {
                    image::Rgb([v(x, y, 0), v(x, y, 1), v(x, y, 2)])
                })
                .save(&path)
                .unwrap(),
                "rgba16" => image::ImageBuffer::from_fn(w, h, |x, y| {
                    let c = |k| v(x, y, k) as u16 * 257;
                    image::Rgba([c(0), c(0), c(0), 65535])
                })
                .save(&path)
                .unwrap(),
                _ => unreachable!(),
            }
            let a = i as f64 * 2.1;
            let d = [0.3 * a.cos(), 0.3 * a.sin(), 1.0];
            let intensity = rgb_light.then_some(Intensity::Rgb([0.9, 0.6 + 0.01 * i as f64, 0.4]));
            lights.push(make_light(i + 1, &name, d, intensity).unwrap());
            files.push(NamedFile { name, path });
        }
        (lights, files)
    }

    /// An 8-bit palette PNG of 16 colours (indices from `index`).
    fn write_palette_png(path: &Path, w: u32, h: u32, index: impl Fn(u32, u32) -> u8) {
        let mut e = png::Encoder::new(std::io::BufWriter::new(File::create(path).unwrap()), w, h);
        e.set_color(png::ColorType::Indexed);
        e.set_depth(png::BitDepth::Eight);
        let palette: Vec<u8> = (0..16u8)
            .flat_map(|k| [k * 16, 255 - k * 9, k * 5])
            .collect();
        e.set_palette(palette);
        let mut writer = e.write_header().unwrap();
        let data: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| index(x, y))
            .collect();
        writer.write_image_data(&data).unwrap();
    }

    /// Open descriptors of this process that point into `dir` (the spills, which are
    /// unlinked, show as `dir/#inode (deleted)` or a deleted named file).
    fn spills_open(dir: &Path) -> usize {
        (std::fs::read_dir("/proc/self/fd").unwrap())
            .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
            .filter(|target| target.starts_with(dir))
            .count()
    }

    /// Waits up to 5 s for every spill in `dir` to be closed (a run drops its set on a
    /// thread of its own), and that nothing is left in it.
    fn assert_no_spills(dir: &Path, when: &str) {
        let start = std::time::Instant::now();
        while spills_open(dir) > 0 && start.elapsed().as_secs() < 5 {
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        assert_eq!(spills_open(dir), 0, "spills still open after {when}");
        let left: Vec<_> = std::fs::read_dir(dir).unwrap().collect();
        assert!(
            left.is_empty(),
            "left in the scratch directory after {when}: {left:?}"
        );
    }

    /// Every band read in order, concatenated per image; and the moments.
    fn read_all(s: &mut Streamed) -> (Vec<Vec<u16>>, Vec<f32>) {
        let (h, step) = (s.info.height, s.band_rows());
        let mut planes = vec![Vec::new(); s.images.len()];
        let mut moments = Vec::new();
        for r0 in (0..h).step_by(step) {
            let band = s.band(r0..(r0 + step).min(h)).unwrap();
            for (p, b) in planes.iter_mut().zip(&band.planes) {
                p.extend_from_slice(b);
            }
            moments.extend_from_slice(band.moments.unwrap_or_default());
        }
        (planes, moments)
    }

    #[test]
    fn bands_are_the_planes_intake_decodes_whole() {
        for (kind, rgb_light) in [
            ("gray8", false),
            ("gray16", false),
            ("rgb8", true),
            ("rgb8", false),
            ("rgb16", true),
            ("rgba16", false),
            ("palette", true),
            ("tiff", true),
            ("bmp", true),
        ] {
            let dir = tempfile::tempdir().unwrap();
            let scratch = tempfile::tempdir().unwrap();
            let (lights, files) = write_set(dir.path(), kind, 5, rgb_light);
            let whole = intake::load(lights.clone(), &files, None, &Limits::default()).unwrap();
            let mut s = open(lights, &files, None, &Limits::default(), scratch.path()).unwrap();
            assert_eq!(spills_open(scratch.path()), 5, "{kind}: one spill an image");
            // Small bands, so that the reader is asked for many.
            s.band_rows = 4;
            assert_eq!(s.info.bit_depth, whole.bit_depth, "{kind}");
            assert_eq!(s.info.colour, whole.colour_moments.is_some(), "{kind}");
            for (a, b) in s.info.lights.iter().zip(&whole.lights) {
                assert_eq!(a.intensity, b.intensity, "{kind}");
            }
            let sampled = crate::core::bands::InMemory::new(&whole);
            assert_eq!(s.samples.planes, sampled.samples().planes, "{kind}");
            let (planes, moments) = read_all(&mut s);
            for (p, w) in planes.iter().zip(&whole.planes) {
                assert_eq!(p.as_slice(), w.as_slice().unwrap(), "{kind}");
            }
            if let Some(m) = &whole.colour_moments {
                let most = (m.iter().zip(&moments))
                    .map(|(a, b)| (a - b).abs())
                    .fold(0f32, f32::max);
                assert_eq!(moments.len(), m.len());
                assert!(most < 1e-5, "{kind}: moments differ by {most}");
            }
            drop(s);
            assert_no_spills(scratch.path(), kind);
        }
    }

    /// A spilled set's job writes exactly the artifacts of the set loaded whole.
    #[test]
    fn spilled_sets_reconstruct_bit_identically() {
        use crate::core::{Options, RunToEnd, bands::InMemory, pipeline};
        for (kind, rgb_light) in [("gray16", false), ("rgb8", true), ("tiff", true)] {
            let dir = tempfile::tempdir().unwrap();
            let scratch = tempfile::tempdir().unwrap();
            let out = tempfile::tempdir().unwrap();
            let (lights, files) = write_set(dir.path(), kind, 6, rgb_light);
            let limits = Limits::default();
            let opts = Options::default();
            let whole = intake::load(lights.clone(), &files, None, &limits).unwrap();
            let (a, b) = (out.path().join("whole"), out.path().join("spilled"));
            pipeline::run(InMemory::new(whole), &opts, &a, &mut RunToEnd).unwrap();
            let s = open(lights, &files, None, &limits, scratch.path()).unwrap();
            pipeline::run(s, &opts, &b, &mut RunToEnd).unwrap();
            let mut compared = 0;
            for entry in std::fs::read_dir(&a).unwrap() {
                let name = entry.unwrap().file_name();
                if name == "result.json" {
                    continue; // its timings differ
                }
                let (x, y) = (std::fs::read(a.join(&name)), std::fs::read(b.join(&name)));
                let (x, y) = (x.unwrap(), y.unwrap());
                if name == "albedo_rgb.png" {
                    // `intake::load` adds each image's colour moments as its decode
                    // finishes (in parallel, so the f32 sums' order varies run to run);
                    // the spilled set adds them in table order. Within one level.
                    let decode = |v: &[u8]| image::load_from_memory(v).unwrap().to_rgb8();
                    let (x, y) = (decode(&x), decode(&y));
                    let most = (x.as_raw().iter().zip(y.as_raw()))
                        .map(|(p, q)| p.abs_diff(*q))
                        .max();
                    assert!(
                        most <= Some(1),
                        "{kind}: albedo_rgb.png differs by {most:?}"
                    );
                } else {
                    assert!(x == y, "{kind}: {name:?} differs");
                }
                compared += 1;
            }
            assert!(compared >= 3, "{kind}: {compared} artifacts");
            assert_no_spills(scratch.path(), kind);
        }
    }

    /// Spills are closed, and nothing is left in the scratch directory, after a run that
    /// succeeds, a set that fails to open and a run that is stopped.
    #[test]
    fn spills_go_after_success_error_and_cancel() {
        use crate::core::progress::Stage;
        use crate::core::{Options, RunError, RunToEnd, pipeline};
        let dir = tempfile::tempdir().unwrap();
        let scratch = tempfile::tempdir().unwrap();
        let out = tempfile::tempdir().unwrap();
        let limits = Limits::default();
        let (lights, files) = write_set(dir.path(), "gray16", 6, false);

        let s = open(lights.clone(), &files, None, &limits, scratch.path()).unwrap();
        assert_eq!(spills_open(scratch.path()), 6);
        let opts = Options::default();
        pipeline::run(s, &opts, &out.path().join("a"), &mut RunToEnd).unwrap();
        assert_no_spills(scratch.path(), "success");

        let s = open(lights.clone(), &files, None, &limits, scratch.path()).unwrap();
        let mut stop = |stage: Stage| stage != Stage::Integrate;
        let stopped = pipeline::run(s, &opts, &out.path().join("b"), &mut stop);
        assert!(matches!(stopped, Err(RunError::Cancelled)), "{stopped:?}");
        assert_no_spills(scratch.path(), "cancel");

        // The last image broken: the others were spilled before its error.
        let bytes = std::fs::read(&files[5].path).unwrap();
        std::fs::write(&files[5].path, &bytes[..bytes.len() / 2]).unwrap();
        let e = open(lights, &files, None, &limits, scratch.path()).err();
        assert!(e.expect("a broken image").to_string().contains("5.png"));
        assert_no_spills(scratch.path(), "error");
    }

    /// A scratch directory that cannot take the spills is an error naming it.
    #[test]
    fn a_scratch_directory_that_fails_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let (lights, files) = write_set(dir.path(), "gray16", 3, false);
        let missing = dir.path().join("no-such-dir");
        let e = open(lights, &files, None, &Limits::default(), &missing)
            .err()
            .expect("no scratch directory")
            .to_string();
        assert!(e.contains("no-such-dir") && e.contains("scratch"), "{e}");
    }

    #[test]
    fn prescanned_images_give_the_same_set() {
        let dir = tempfile::tempdir().unwrap();
        let scratch = tempfile::tempdir().unwrap();
        let limits = Limits::default();
        for kind in ["rgb8", "bmp"] {
            let (lights, files) = write_set(dir.path(), kind, 4, true);
            let mut plain = open(lights.clone(), &files, None, &limits, scratch.path()).unwrap();
            let ahead = |i: usize| {
                let mut f = File::open(&files[i].path).unwrap();
                // Read from its start, wherever the handle stands.
                f.seek(std::io::SeekFrom::End(0)).unwrap();
                i.is_multiple_of(2)
                    .then(|| Ok(prescan(f, &limits, scratch.path()).expect("scanned ahead")))
            };
            let mut prescanned =
                open_with(lights, &files, None, &limits, scratch.path(), ahead).unwrap();
            assert_eq!(plain.samples.planes, prescanned.samples.planes);
            assert_eq!(read_all(&mut plain), read_all(&mut prescanned));
        }
        // Errors are left to the set.
        std::fs::write(dir.path().join("junk"), b"not an image").unwrap();
        let junk = File::open(dir.path().join("junk")).unwrap();
        assert!(prescan(junk, &limits, scratch.path()).is_none());
        assert_no_spills(scratch.path(), "prescans dropped");
    }

    #[test]
    fn bands_out_of_order_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (lights, files) = write_set(dir.path(), "gray16", 3, false);
        let mut s = open(lights, &files, None, &Limits::default(), dir.path()).unwrap();
        assert!(s.band(0..5).is_ok());
        let e = s.band(10..12).err().expect("a skipped band").to_string();
        assert!(e.contains("out of order"), "{e}");
    }

    #[test]
    fn a_broken_png_gets_the_error_intake_gives() {
        let dir = tempfile::tempdir().unwrap();
        let (lights, files) = write_set(dir.path(), "gray16", 4, false);
        let bytes = std::fs::read(&files[2].path).unwrap();
        std::fs::write(&files[2].path, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let whole = intake::load(lights.clone(), &files, None, &Limits::default());
        let streamed = open(lights, &files, None, &Limits::default(), dir.path());
        let (a, b) = (
            whole.err().unwrap().to_string(),
            streamed.err().unwrap().to_string(),
        );
        assert_eq!(a, b);
        assert!(a.contains("2.png"), "{a}");
    }
}
