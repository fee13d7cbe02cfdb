//! Normal maps from elsewhere ("normals in"): 8/16-bit PNG (RGB or RGBA) and 32-bit float
//! OpenEXR, in the OpenGL or DirectX convention, read into the project's frame.
//!
//! **Decoding.** PNG samples `v` decode as `n = 2·v/max − 1` (`max` = 255 or 65535); EXR
//! values are the vector itself. The result is in the project's frame (x = column right,
//! y = row **down**, z towards the camera), renormalised to unit length, zero off the mask.
//!
//! **Conventions.** [`Convention::Opengl`] (the default): green = +y **up**, as the
//! project's own `normal.png`, Blender and three.js write them, and as the field's
//! benchmarks (DiLiGenT: x right, y up, z towards the camera) ship them; `project` and
//! `benchmark` are its aliases. [`Convention::Directx`]: green = +y **down**.
//!
//! **Treatment**, each counted in [`Counts`]:
//! - off the mask: pixels outside a given mask (`outside_mask`), with alpha 0
//!   (`transparent`), whose vector is NaN or infinite (`non_finite`), pure black
//!   (`black`: samples (0, 0, 0), the usual background), or shorter than
//!   [`MIN_LENGTH`] (`zero_length`: no direction, e.g. mid-grey (0.5, 0.5, 0.5));
//! - kept but counted: normals facing away from the camera (`back_facing`: z < 0
//!   orthographic, n·ray > 0 under a camera), which the integrators clamp to a grazing
//!   angle; vectors whose length is more than [`UNIT_TOLERANCE`] from 1 (`not_unit`),
//!   renormalised.
//!
//! **Refused** ([`NormalMapError`], naming the file): unreadable or unsupported files (a
//! gray picture has no normals), a map or mask over the caller's pixel limit (intake's own
//! [`InputError::TooLarge`]), a mask of another size than the map, an 8- or 16-bit map
//! where more than [`MAX_NOT_UNIT_SHARE`] of the non-background pixels are `not_unit`
//! (not a normal map, or another encoding), a map with no usable pixel, a camera whose
//! principal point lies outside the image.

use std::path::Path;

use image::ColorType;
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::camera::{CameraError, Pinhole};
use super::error::InputError;
use super::intake::{self, Limits};

/// Vectors shorter than this (after decoding) have no direction: off the mask.
pub const MIN_LENGTH: f32 = 0.05;
/// A decoded vector whose length is further than this from 1 is `not_unit`.
pub const UNIT_TOLERANCE: f32 = 0.15;
/// An 8- or 16-bit map with more than this share of `not_unit` pixels is refused.
pub const MAX_NOT_UNIT_SHARE: f64 = 0.10;

/// How a normal map's green channel (y) points.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, ToSchema, clap::ValueEnum,
)]
#[serde(rename_all = "kebab-case")]
pub enum Convention {
    /// x right, y **up**, z towards the viewer: OpenGL, the project's own `normal.png`
    /// (alias `project`) and the field's benchmarks such as DiLiGenT (alias `benchmark`).
    #[default]
    #[serde(alias = "project", alias = "benchmark")]
    #[value(alias = "project", alias = "benchmark")]
    Opengl,
    /// x right, y **down**, z towards the viewer (DirectX, Unreal).
    Directx,
}

/// Where a camera comes from: a full pinhole, or a focal length with the principal point
/// at the image's centre (which needs the image's size).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Lens {
    Pinhole(Pinhole),
    /// `--focal-length`: [`Pinhole::centred`].
    Centred {
        focal_px: f64,
    },
}

impl Lens {
    /// The camera of a `width × height` image.
    pub fn resolve(self, width: usize, height: usize) -> Pinhole {
        match self {
            Self::Pinhole(k) => k,
            Self::Centred { focal_px } => Pinhole::centred(focal_px, width, height),
        }
    }
}

/// What the normal-map reader did with each pixel: `used` ones are integrated; each other
/// one is off the mask, counted once, under the first of `outside_mask`, `transparent`,
/// `non_finite`, `black`, `zero_length` that applies.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct Counts {
    /// Every pixel of the map.
    pub pixels: usize,
    /// Pixels on the mask: the normals integrated.
    pub used: usize,
    /// Outside the given mask.
    pub outside_mask: usize,
    /// Alpha 0.
    pub transparent: usize,
    /// NaN or infinite components.
    pub non_finite: usize,
    /// Samples (0, 0, 0), the usual background.
    pub black: usize,
    /// Shorter than 0.05 ([`MIN_LENGTH`]) once decoded: no direction (e.g. mid-grey).
    pub zero_length: usize,
    /// Used, but facing away from the camera (the integrators clamp them).
    pub back_facing: usize,
    /// Used, but their length was more than 0.15 ([`UNIT_TOLERANCE`]) from 1: renormalised.
    pub not_unit: usize,
}

/// A normal map read into the project's frame.
#[derive(Debug, Clone)]
pub struct NormalMap {
    /// The file's name, as errors and reports give it.
    pub name: String,
    pub mask_name: Option<String>,
    pub width: usize,
    pub height: usize,
    /// 8 or 16 (PNG), 32 (float EXR).
    pub bits: u8,
    pub convention: Convention,
    /// The camera the map was checked against (resolved from the [`Lens`]).
    pub camera: Option<Pinhole>,
    /// Unit normals `(rows, cols, 3)` in the project's frame, zero off the mask.
    pub normals: Array3<f32>,
    pub mask: Array2<bool>,
    pub counts: Counts,
}

/// Why a normal map cannot be used; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum NormalMapError {
    #[error("normal map {name:?} cannot be read: {reason}")]
    Unreadable { name: String, reason: String },
    /// Over the pixel limit: intake's refusal as it is, so that a normal map is refused
    /// as an image of that size is (HTTP 413).
    #[error(transparent)]
    TooLarge(InputError),
    #[error(
        "normal map {name:?} is {what}; a normal map is RGB or RGBA: an 8/16-bit PNG or a 32-bit float OpenEXR"
    )]
    Unsupported { name: String, what: String },
    #[error("mask {mask:?} cannot be read: {reason}")]
    Mask { mask: String, reason: String },
    #[error(
        "mask {mask:?} is {mask_width}×{mask_height} but the normal map {name:?} is {width}×{height}"
    )]
    MaskSize {
        mask: String,
        mask_width: usize,
        mask_height: usize,
        name: String,
        width: usize,
        height: usize,
    },
    #[error(
        "normal map {name:?} does not decode to unit normals: {not_unit} of its {used} non-background pixels ({percent:.0} %) give vectors (n = 2·v/max − 1) whose length is more than {UNIT_TOLERANCE} from 1; it is probably not a normal map (a photo, a height or displacement map), or its normals are in another encoding"
    )]
    NotUnitLength {
        name: String,
        not_unit: usize,
        used: usize,
        percent: f64,
    },
    #[error(
        "normal map {name:?} has no usable pixel: of {pixels}, {black} black, {zero_length} zero-length, {non_finite} NaN/infinite, {transparent} transparent, {outside_mask} outside the mask"
    )]
    NoUsablePixel {
        name: String,
        pixels: usize,
        black: usize,
        zero_length: usize,
        non_finite: usize,
        transparent: usize,
        outside_mask: usize,
    },
    #[error("normal map {name:?}: {source}")]
    Camera {
        name: String,
        #[source]
        source: CameraError,
    },
}

impl NormalMapError {
    /// Why the file `name` could not be read as a picture (`e` from intake's decoder or
    /// header probe).
    pub fn unreadable(name: &str, e: InputError) -> Self {
        match e {
            InputError::UnsupportedFormat { reason, .. } => Self::Unsupported {
                name: name.into(),
                what: format!("not a format that can be read ({reason})"),
            },
            e if e.is_too_large() => Self::TooLarge(e),
            e => Self::Unreadable {
                name: name.into(),
                reason: e.to_string(),
            },
        }
    }
}

/// Bits per sample of a normal map `name` whose pixels are `colour`: 8 or 16 (PNG), 32
/// (float EXR); refused when the picture has no three channels (gray, gray + alpha).
pub fn bits_of(name: &str, colour: ColorType) -> Result<u8, NormalMapError> {
    match colour {
        ColorType::Rgb8 | ColorType::Rgba8 => Ok(8),
        ColorType::Rgb16 | ColorType::Rgba16 => Ok(16),
        ColorType::Rgb32F | ColorType::Rgba32F => Ok(32),
        other => Err(NormalMapError::Unsupported {
            name: name.into(),
            what: format!("{other:?}"),
        }),
    }
}

/// A mask given by name and bytes (PNG or any format intake reads; non-zero = object).
pub struct MaskInput<'a> {
    pub name: &'a str,
    pub bytes: &'a [u8],
}

/// Read a normal map file (and a mask file), see [`decode`].
pub fn read(
    path: &Path,
    mask: Option<&Path>,
    convention: Convention,
    lens: Option<Lens>,
    limits: &Limits,
) -> Result<NormalMap, NormalMapError> {
    let name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| NormalMapError::Unreadable {
        name: name.clone(),
        reason: e.to_string(),
    })?;
    let mask = match mask {
        Some(p) => {
            let mask_name = p.display().to_string();
            let bytes = std::fs::read(p).map_err(|e| NormalMapError::Mask {
                mask: mask_name.clone(),
                reason: e.to_string(),
            })?;
            Some((mask_name, bytes))
        }
        None => None,
    };
    let mask = mask.as_ref().map(|(name, bytes)| MaskInput { name, bytes });
    decode(&name, &bytes, mask, convention, lens, limits)
}

/// Decode a normal map (named `name` in errors) into the project's frame: the module
/// docs give the decoding, the treatment of each pixel and what is refused. The map and
/// the mask are refused over `limits.max_pixels_per_image` before they are decoded.
pub fn decode(
    name: &str,
    bytes: &[u8],
    mask: Option<MaskInput<'_>>,
    convention: Convention,
    lens: Option<Lens>,
    limits: &Limits,
) -> Result<NormalMap, NormalMapError> {
    let img =
        intake::decode(name, bytes, limits).map_err(|e| NormalMapError::unreadable(name, e))?;
    let bits = bits_of(name, img.color())?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    let mask_name = mask.as_ref().map(|m| m.name.to_string());
    let given = match mask {
        Some(m) => Some(read_mask(m, name, width, height, limits)?),
        None => None,
    };
    let camera = lens.map(|l| l.resolve(width, height));
    if let Some(k) = &camera {
        k.check(width, height)
            .map_err(|source| NormalMapError::Camera {
                name: name.into(),
                source,
            })?;
    }
    let rgba = img.into_rgba32f();
    let samples = rgba.as_raw();
    let mut normals = Array3::<f32>::zeros((height, width, 3));
    let mut on = Array2::from_elem((height, width), false);
    let flip_y = convention == Convention::Opengl;
    let counts = (normals.axis_iter_mut(Axis(0)).into_par_iter())
        .zip(on.axis_iter_mut(Axis(0)).into_par_iter())
        .enumerate()
        .map(|(r, (mut nrow, mut mrow))| {
            let mut k = Counts::default();
            for c in 0..width {
                let px = &samples[(r * width + c) * 4..(r * width + c) * 4 + 4];
                let verdict = classify(px, bits, given.as_ref().map(|g| g[[r, c]]));
                let v = match verdict {
                    Pixel::Off(count) => {
                        *count.of(&mut k) += 1;
                        continue;
                    }
                    Pixel::On(v) => v,
                };
                let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if (len - 1.0).abs() > UNIT_TOLERANCE {
                    k.not_unit += 1;
                }
                let n = [
                    v[0] / len,
                    if flip_y { -v[1] } else { v[1] } / len,
                    v[2] / len,
                ];
                let away = match &camera {
                    None => n[2] < 0.0,
                    Some(cam) => {
                        let d = cam.ray(c as f64, r as f64);
                        (0..3).map(|i| f64::from(n[i]) * d[i]).sum::<f64>() > 0.0
                    }
                };
                k.back_facing += usize::from(away);
                k.used += 1;
                nrow.row_mut(c).assign(&ndarray::aview1(&n));
                mrow[c] = true;
            }
            k
        })
        .reduce(Counts::default, Counts::add);
    let counts = Counts {
        pixels: width * height,
        ..counts
    };
    if counts.used == 0 {
        return Err(NormalMapError::NoUsablePixel {
            name: name.into(),
            pixels: counts.pixels,
            black: counts.black,
            zero_length: counts.zero_length,
            non_finite: counts.non_finite,
            transparent: counts.transparent,
            outside_mask: counts.outside_mask,
        });
    }
    let share = counts.not_unit as f64 / counts.used as f64;
    if bits < 32 && share > MAX_NOT_UNIT_SHARE {
        return Err(NormalMapError::NotUnitLength {
            name: name.into(),
            not_unit: counts.not_unit,
            used: counts.used,
            percent: 100.0 * share,
        });
    }
    Ok(NormalMap {
        name: name.into(),
        mask_name,
        width,
        height,
        bits,
        convention,
        camera,
        normals,
        mask: on,
        counts,
    })
}

/// Which count an off-mask pixel goes to.
#[derive(Clone, Copy)]
enum Off {
    OutsideMask,
    Transparent,
    NonFinite,
    Black,
    ZeroLength,
}

impl Off {
    fn of(self, k: &mut Counts) -> &mut usize {
        match self {
            Self::OutsideMask => &mut k.outside_mask,
            Self::Transparent => &mut k.transparent,
            Self::NonFinite => &mut k.non_finite,
            Self::Black => &mut k.black,
            Self::ZeroLength => &mut k.zero_length,
        }
    }
}

enum Pixel {
    Off(Off),
    /// The decoded vector, in the file's own y convention, not yet normalised.
    On([f32; 3]),
}

/// One pixel's verdict from its RGBA samples (in [0, 1] for PNG, raw for EXR).
fn classify(px: &[f32], bits: u8, in_mask: Option<bool>) -> Pixel {
    if in_mask == Some(false) {
        return Pixel::Off(Off::OutsideMask);
    }
    if px[3] == 0.0 {
        return Pixel::Off(Off::Transparent);
    }
    let s = [px[0], px[1], px[2]];
    if s.iter().any(|v| !v.is_finite()) {
        return Pixel::Off(Off::NonFinite);
    }
    if s == [0.0; 3] {
        return Pixel::Off(Off::Black);
    }
    let v = if bits == 32 {
        s
    } else {
        s.map(|v| 2.0 * v - 1.0)
    };
    if (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() < MIN_LENGTH {
        return Pixel::Off(Off::ZeroLength);
    }
    Pixel::On(v)
}

impl Counts {
    fn add(self, o: Self) -> Self {
        Self {
            pixels: self.pixels + o.pixels,
            used: self.used + o.used,
            outside_mask: self.outside_mask + o.outside_mask,
            transparent: self.transparent + o.transparent,
            non_finite: self.non_finite + o.non_finite,
            black: self.black + o.black,
            zero_length: self.zero_length + o.zero_length,
            back_facing: self.back_facing + o.back_facing,
            not_unit: self.not_unit + o.not_unit,
        }
    }
}

fn read_mask(
    m: MaskInput<'_>,
    name: &str,
    width: usize,
    height: usize,
    limits: &Limits,
) -> Result<Array2<bool>, NormalMapError> {
    let img = intake::decode(m.name, m.bytes, limits).map_err(|e| match e {
        e if e.is_too_large() => NormalMapError::TooLarge(e),
        e => NormalMapError::Mask {
            mask: m.name.into(),
            reason: e.to_string(),
        },
    })?;
    let (mw, mh) = (img.width() as usize, img.height() as usize);
    if (mw, mh) != (width, height) {
        return Err(NormalMapError::MaskSize {
            mask: m.name.into(),
            mask_width: mw,
            mask_height: mh,
            name: name.into(),
            width,
            height,
        });
    }
    Ok(intake::to_luma16(img).mapv(|v| v > 0))
}

#[cfg(test)]
mod tests;
