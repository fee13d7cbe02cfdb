//! Image files read in bands of rows, in lockstep over the set, so that a job holds a band
//! per image rather than the whole 16-bit stack ([`Streamed`], a [`Stack`]).
//!
//! Two passes over the files. The first reads every image once (in parallel over the
//! images) and keeps only what must be known of the whole set before any band is solved:
//! each image's size, depth and whether it carries colour, and the rows the robust
//! pre-pass samples (see [`bands::sampled_rows`]). The second reads the bands in order;
//! each band's images are decoded in parallel. Non-interlaced 8/16-bit PNGs without a
//! palette are decoded row by row through the `png` crate in both passes; every other
//! file is decoded whole once (by [`intake::decode`]) and kept decoded until the solve
//! has read it, so it costs one decoded image. A row-read PNG's first pass can also be
//! done ahead ([`prescan`], e.g. while the rest of an upload arrives): it keeps only the
//! sampled rows, and [`open_with`] then starts with the bands.
//!
//! A band is converted exactly as [`intake::load`] converts a whole image (the same
//! per-pixel functions over the band as a small image), so the planes, and with them
//! every result, are the same as the set loaded whole.

use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::ops::Range;
use std::path::Path;

use image::{DynamicImage, ImageBuffer, ImageFormat};
use rayon::prelude::*;

use super::InputError;
use super::bands::{self, Band, Samples, SetInfo, Stack};
use super::intake::{self, DirMask, Limits, NamedFile};
use super::lights::Light;

/// What one band may hold over all images together (raw rows, planes, colour): the
/// bound on the images' memory, whatever their number.
const BAND_BYTES: usize = 32 << 20;

/// [`intake::load_dir`], streamed: the folder's set as a [`Stack`].
pub fn open_dir(dir: &Path, mask: DirMask<'_>, limits: &Limits) -> Result<Streamed, InputError> {
    let found = intake::dir_files(dir, mask)?;
    let set = open(found.lights, &found.files, found.mask.as_ref(), limits)?;
    Ok(set.noted(found.notes))
}

/// [`intake::load`], streamed: the first pass over the files (errors as `load` reports
/// them, the first in table order), leaving the bands to be read by the solve.
pub fn open(
    lights: Vec<Light>,
    files: &[NamedFile],
    mask: Option<&NamedFile>,
    limits: &Limits,
) -> Result<Streamed, InputError> {
    open_with(lights, files, mask, limits, |_| None)
}

/// One image's first pass done ahead by [`prescan`]: its sampled rows, not its planes.
pub struct Prescanned(Scanned);

/// The first pass over a PNG read row by row, from an open handle to it (read from its
/// start), with the limits [`open_with`] will be given. `None` when it is left to
/// `open_with`: files decoded whole (their decoded image would be held until the job),
/// and every error, which `open_with` reports as it would without a prescan.
pub fn prescan(mut file: File, limits: &Limits) -> Option<Prescanned> {
    file.rewind().ok()?;
    let (reader, kind) = png_reader(file).ok()?;
    scan_rows(reader, kind?, limits).ok().map(Prescanned)
}

/// [`open`], taking image `i` of `files` from `prescanned(i)` when that has it (the
/// [`prescan`] of the same file with the same limits, or an error that stands for its
/// scan's), so the set and its first error are the same as without.
pub fn open_with(
    lights: Vec<Light>,
    files: &[NamedFile],
    mask: Option<&NamedFile>,
    limits: &Limits,
    prescanned: impl Fn(usize) -> Option<Result<Prescanned, InputError>> + Sync,
) -> Result<Streamed, InputError> {
    let ordered = intake::check_files(&lights, files, limits)?;
    let scanned: Vec<Scanned> = (ordered.par_iter())
        .map(|&i| match prescanned(i) {
            Some(ready) => ready.map(|Prescanned(mut s)| {
                // Its second pass reads the file where the set has it.
                s.source = Source::Png {
                    file: files[i].clone(),
                    reader: None,
                };
                s
            }),
            None => scan(&files[i], limits),
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
            source: s.source,
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

/// A set whose files are read band by band (see the module docs).
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
        let read: Vec<(Vec<u16>, Option<image::Rgb32FImage>)> = (self.images.par_iter_mut())
            .map(|i| {
                let raw = i.source.rows(rows.clone(), width)?;
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
}

/// One image of a [`Streamed`] set.
struct Image {
    source: Source,
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

/// Where an image's rows come from.
enum Source {
    /// Read row by row; the reader is opened again for the second pass.
    Png {
        file: NamedFile,
        reader: Option<Box<PngRows>>,
    },
    /// Decoded whole in the first pass.
    Whole(DynamicImage),
}

type PngRows = png::Reader<BufReader<File>>;

impl Source {
    /// Rows `rows` (the next ones) as a `width`-wide image.
    fn rows(&mut self, rows: Range<usize>, width: usize) -> Result<DynamicImage, InputError> {
        match self {
            Source::Whole(img) => {
                Ok(img.crop_imm(0, rows.start as u32, width as u32, rows.len() as u32))
            }
            Source::Png { file, reader } => {
                if reader.is_none() {
                    *reader = Some(Box::new(open_png(file)?.0));
                }
                let r = reader.as_mut().expect("opened above");
                read_png_rows(r, rows.len()).map_err(|e| png_error(file, e))
            }
        }
    }
}

/// What the first pass learned of one image.
struct Scanned {
    source: Source,
    width: usize,
    height: usize,
    depth: u8,
    colour: bool,
    /// The rows [`bands::sampled_rows`] names, as images of one or more rows.
    sampled: Vec<DynamicImage>,
}

/// The first pass over one image: PNGs that can be read row by row are, others whole.
fn scan(file: &NamedFile, limits: &Limits) -> Result<Scanned, InputError> {
    let mut head = [0u8; 64];
    let got = File::open(&file.path)
        .and_then(|mut f| read_up_to(&mut f, &mut head))
        .map_err(|e| InputError::io(&file.path, e))?;
    if image::guess_format(&head[..got]).ok() == Some(ImageFormat::Png)
        && let Some(scanned) = scan_png(file, limits)?
    {
        return Ok(scanned);
    }
    let bytes = std::fs::read(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    let img = intake::decode(&file.name, &bytes, limits)?;
    drop(bytes);
    let (width, height) = (img.width() as usize, img.height() as usize);
    let sampled = (bands::sampled_rows(width, height))
        .map(|r| img.crop_imm(0, r as u32, width as u32, 1))
        .collect();
    Ok(Scanned {
        width,
        height,
        depth: intake::bit_depth(&img),
        colour: intake::has_colour(&img),
        sampled,
        source: Source::Whole(img),
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

/// The first pass over a PNG read row by row, or `None` when it must be decoded whole
/// (palette, interlacing, transparency chunk, under 8 bits: the conversions the `image`
/// crate applies are left to it).
fn scan_png(file: &NamedFile, limits: &Limits) -> Result<Option<Scanned>, InputError> {
    let Ok((reader, kind)) = open_png(file) else {
        return Ok(None); // the whole decode names the problem
    };
    let Some(kind) = kind else {
        return Ok(None);
    };
    match scan_rows(reader, kind, limits) {
        Ok(mut scanned) => {
            scanned.source = Source::Png {
                file: file.clone(),
                reader: None,
            };
            Ok(Some(scanned))
        }
        Err(RowScan::TooLarge { width, height }) => Err(InputError::TooLarge {
            name: file.name.clone(),
            width: width as u64,
            height: height as u64,
            pixels: width as u64 * height as u64,
            limit: limits.max_pixels_per_image,
        }),
        Err(RowScan::Broken(reason)) => whole_decode_error(file, limits, &reason),
    }
}

/// Why a row scan stopped (the file's own error is named by the caller, who knows it).
enum RowScan {
    TooLarge { width: usize, height: usize },
    Broken(String),
}

/// Every row of a PNG once: its size, depth, colour and sampled rows. The source it
/// returns is a placeholder for the caller to name the file in.
fn scan_rows(mut reader: PngRows, kind: PngKind, limits: &Limits) -> Result<Scanned, RowScan> {
    let info = reader.info();
    let (width, height) = (info.width as usize, info.height as usize);
    if width as u64 * height as u64 > limits.max_pixels_per_image {
        return Err(RowScan::TooLarge { width, height });
    }
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
    }
    Ok(Scanned {
        width,
        height,
        depth: kind.depth,
        colour,
        sampled: vec![kind.image(width, count, sampled)],
        source: Source::Png {
            file: NamedFile {
                name: String::new(),
                path: Default::default(),
            },
            reader: None,
        },
    })
}

/// An error the row reader met: the whole decode's message for the same file (the one
/// [`intake::load`] gives), or the reader's own when the whole decode succeeds.
fn whole_decode_error<T>(file: &NamedFile, limits: &Limits, reason: &str) -> Result<T, InputError> {
    let bytes = std::fs::read(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    intake::decode(&file.name, &bytes, limits)?;
    Err(InputError::Decode {
        name: file.name.clone(),
        reason: reason.to_string(),
    })
}

/// A second-pass read error (the file changed between the passes, or the disk failed).
fn png_error(file: &NamedFile, e: png::DecodingError) -> InputError {
    InputError::Decode {
        name: file.name.clone(),
        reason: e.to_string(),
    }
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

/// A row reader for the file, and its layout when rows can be taken as they come.
fn open_png(file: &NamedFile) -> Result<(PngRows, Option<PngKind>), InputError> {
    let f = File::open(&file.path).map_err(|e| InputError::io(&file.path, e))?;
    png_reader(f).map_err(|e| png_error(file, e))
}

/// [`open_png`] over an open file, read from where it stands.
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

/// The next `rows` rows of a PNG.
fn read_png_rows(r: &mut PngRows, rows: usize) -> Result<DynamicImage, png::DecodingError> {
    let info = r.info();
    let width = info.width as usize;
    let kind = PngKind {
        channels: info.color_type.samples(),
        depth: if info.bit_depth == png::BitDepth::Sixteen {
            16
        } else {
            8
        },
    };
    let row_bytes = kind.row_bytes(width);
    let mut raw = vec![0u8; row_bytes * rows];
    for row in raw.chunks_exact_mut(row_bytes) {
        if r.read_row(row)?.is_none() {
            return Err(png::DecodingError::IoError(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                "the image data ends early",
            )));
        }
    }
    Ok(kind.image(width, rows, raw))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::lights::{Intensity, make_light};

    /// Images of every kind the reader handles: 16-bit gray PNG, 8-bit RGB PNG (colour),
    /// 16-bit RGBA PNG, interlaced or palette PNG (decoded whole) and BMP (whole).
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
            let name = format!("{i}.{}", if kind == "bmp" { "bmp" } else { "png" });
            let path = dir.join(&name);
            match kind {
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
            let d = [0.1 * i as f64 - 0.2, 0.05 * i as f64, 1.0];
            let intensity = rgb_light.then_some(Intensity::Rgb([0.9, 0.6 + 0.01 * i as f64, 0.4]));
            lights.push(make_light(i + 1, &name, d, intensity).unwrap());
            files.push(NamedFile { name, path });
        }
        (lights, files)
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
            ("gray16", false),
            ("rgb8", true),
            ("rgb8", false),
            ("rgba16", false),
            ("bmp", true),
        ] {
            let dir = tempfile::tempdir().unwrap();
            let (lights, files) = write_set(dir.path(), kind, 5, rgb_light);
            let whole = intake::load(lights.clone(), &files, None, &Limits::default()).unwrap();
            let mut s = open(lights, &files, None, &Limits::default()).unwrap();
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
        }
    }

    #[test]
    fn prescanned_images_give_the_same_set() {
        let dir = tempfile::tempdir().unwrap();
        let limits = Limits::default();
        let (lights, files) = write_set(dir.path(), "rgb8", 4, true);
        let mut plain = open(lights.clone(), &files, None, &limits).unwrap();
        let ahead = |i: usize| {
            let f = File::open(&files[i].path).unwrap();
            i.is_multiple_of(2)
                .then(|| Ok(prescan(f, &limits).expect("a PNG read by rows")))
        };
        let mut prescanned = open_with(lights, &files, None, &limits, ahead).unwrap();
        assert_eq!(plain.samples.planes, prescanned.samples.planes);
        assert_eq!(read_all(&mut plain), read_all(&mut prescanned));
        // Files decoded whole are left to the set.
        let (_, bmps) = write_set(dir.path(), "bmp", 1, false);
        assert!(prescan(File::open(&bmps[0].path).unwrap(), &limits).is_none());
    }

    #[test]
    fn bands_out_of_order_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (lights, files) = write_set(dir.path(), "gray16", 3, false);
        let mut s = open(lights, &files, None, &Limits::default()).unwrap();
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
        let streamed = open(lights, &files, None, &Limits::default());
        let (a, b) = (
            whole.err().unwrap().to_string(),
            streamed.err().unwrap().to_string(),
        );
        assert_eq!(a, b);
        assert!(a.contains("2.png"), "{a}");
    }
}
