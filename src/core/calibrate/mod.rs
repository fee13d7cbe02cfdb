//! Light calibration from a chrome sphere: one image of a mirror ball per light → the light
//! table (`name, x, y, z[, intensity]`) that `reconstruct` reads.
//!
//! `sphere` finds the ball's outline (or takes a given circle or mask), `highlight` finds
//! each image's highlight and its direction through `mirror` (orthographic or pinhole
//! camera), `matte` fits relative intensities from a matte sphere, `draw` makes the
//! pictures a person checks it by. Pure functions over decoded planes; [`load_dir`] and
//! [`read_mask`] are the only file I/O.
//!
//! Pixel coordinates are 0-based with pixel centres at integers: the first pixel's centre
//! is (0, 0). Directions are in the project's frame (x = column right, y = row down,
//! z towards the camera).

mod draw;
mod highlight;
mod matte;
mod mirror;
mod sphere;

use std::path::Path;

use ndarray::Array2;
use serde::Serialize;
use thiserror::Error;

pub use highlight::Highlight;
pub use mirror::Camera;
pub use sphere::{OutlineFit, circle_of_mask, fit_outline, median_image};

use super::InputError;
use super::intake::{self, Limits};
use super::layout;
use super::outputs::png_bytes;

/// The sphere's outline in the image, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Circle {
    pub cx: f64,
    pub cy: f64,
    pub r: f64,
}

/// Where the sphere's circle comes from.
#[derive(Debug, Clone)]
pub enum CircleSource {
    /// Fitted to the images' outline.
    Fit,
    Given(Circle),
    /// A mask (true = sphere), its circle fitted to the mask's outline.
    Mask {
        name: String,
        mask: Array2<bool>,
    },
}

/// One decoded sphere image.
#[derive(Debug, Clone)]
pub struct SphereImage {
    pub name: String,
    /// Luminance, 0..=65535 standing for [0, 1].
    pub plane: Array2<u16>,
}

#[derive(Debug, Clone)]
pub struct Settings {
    pub circle: CircleSource,
    pub camera: Camera,
    /// Leave out images without a usable highlight (reported) instead of failing.
    pub skip_bad: bool,
}

/// One calibrated light.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibratedLight {
    /// Position of its sphere image in the set (0-based).
    pub index: usize,
    /// The sphere image's file name and the name the light table gives the light.
    pub image: String,
    pub name: String,
    pub highlight: Highlight,
    /// Relative intensity from a matte sphere, when fitted.
    pub intensity: Option<f64>,
}

/// An image left out by `skip_bad`, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Skipped {
    pub image: String,
    pub reason: String,
}

/// A calibration: the circle used, the lights, what was left out, and the maximum image
/// (for the overlay).
#[derive(Debug, Clone)]
pub struct Calibration {
    pub circle: Circle,
    /// How the outline fit went, when the circle was fitted to the images.
    pub outline: Option<OutlineFit>,
    pub lights: Vec<CalibratedLight>,
    pub skipped: Vec<Skipped>,
    pub max_image: Array2<u16>,
}

#[derive(Debug, Error)]
pub enum CalibrationError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error(
        "no sphere found in the images: {0}; give its circle (cx,cy,r in pixels) or a sphere mask"
    )]
    NoSphere(String),
    #[error("circle (centre {cx}, {cy}, radius {r}): {reason}")]
    BadCircle {
        cx: f64,
        cy: f64,
        r: f64,
        reason: String,
    },
    #[error("sphere mask {name:?}: {reason}")]
    Mask { name: String, reason: String },
    #[error("image {name:?}: {reason}")]
    Image { name: String, reason: String },
    #[error(
        "only {usable} of {count} images have a usable highlight, at least 3 are needed; left out: {left_out}"
    )]
    TooFewUsable {
        usable: usize,
        count: usize,
        left_out: String,
    },
    #[error("names: {0}")]
    Names(String),
    #[error("matte sphere image {name:?}: {reason}")]
    Matte { name: String, reason: String },
}

/// Calibrate from the sphere images (one per light, in light order). `names` are the
/// light table's names, one per image (default: the image names).
pub fn calibrate(
    images: &[SphereImage],
    names: Option<&[String]>,
    settings: &Settings,
) -> Result<Calibration, CalibrationError> {
    let (w, h) = check_images(images)?;
    if let Some(n) = names
        && n.len() != images.len()
    {
        return Err(CalibrationError::Names(format!(
            "{} names for {} sphere images",
            n.len(),
            images.len()
        )));
    }
    let planes: Vec<Array2<u16>> = images.iter().map(|i| i.plane.clone()).collect();
    let (circle, outline) = match &settings.circle {
        CircleSource::Fit => {
            let fit = fit_outline(&median_image(&planes)).map_err(CalibrationError::NoSphere)?;
            (fit.circle, Some(fit))
        }
        CircleSource::Given(c) => (*c, None),
        CircleSource::Mask { name, mask } => {
            if mask.dim() != (h, w) {
                return Err(CalibrationError::Mask {
                    name: name.clone(),
                    reason: format!(
                        "it is {}×{} but the sphere images are {w}×{h}",
                        mask.dim().1,
                        mask.dim().0
                    ),
                });
            }
            let c = circle_of_mask(mask).map_err(|reason| CalibrationError::Mask {
                name: name.clone(),
                reason,
            })?;
            (c, None)
        }
    };
    check_circle(&circle, w, h)?;
    let clip = clip_level(&planes);
    let found: Vec<Result<Highlight, String>> = {
        use rayon::prelude::*;
        planes
            .par_iter()
            .map(|p| highlight::find(p, &circle, &settings.camera, clip))
            .collect()
    };
    let mut lights = Vec::new();
    let mut skipped = Vec::new();
    for (i, (img, result)) in images.iter().zip(found).enumerate() {
        match result {
            Ok(hl) => lights.push(CalibratedLight {
                index: i,
                image: img.name.clone(),
                name: names.map_or_else(|| img.name.clone(), |n| n[i].clone()),
                highlight: hl,
                intensity: None,
            }),
            Err(reason) if settings.skip_bad => skipped.push(Skipped {
                image: img.name.clone(),
                reason,
            }),
            Err(reason) => {
                return Err(CalibrationError::Image {
                    name: img.name.clone(),
                    reason,
                });
            }
        }
    }
    if lights.len() < 3 {
        let left_out: Vec<String> = skipped
            .iter()
            .map(|s| format!("{} ({})", s.image, s.reason))
            .collect();
        return Err(CalibrationError::TooFewUsable {
            usable: lights.len(),
            count: images.len(),
            left_out: left_out.join("; "),
        });
    }
    let mut max_image = planes[0].clone();
    for p in &planes[1..] {
        max_image.zip_mut_with(p, |m, &v| *m = (*m).max(v));
    }
    Ok(Calibration {
        circle,
        outline,
        lights,
        skipped,
        max_image,
    })
}

impl Calibration {
    /// Fit each light's relative intensity from a matte sphere's images, one per sphere
    /// image in the same order (the matte sphere's outline is fitted to its own images).
    pub fn fit_intensities(&mut self, matte: &[SphereImage]) -> Result<(), CalibrationError> {
        let count = self.lights.len() + self.skipped.len();
        if matte.len() != count {
            return Err(CalibrationError::Names(format!(
                "{} matte sphere images for {count} chrome sphere images",
                matte.len()
            )));
        }
        let (w, h) = check_images(matte)?;
        let planes: Vec<Array2<u16>> = matte.iter().map(|i| i.plane.clone()).collect();
        let fit =
            fit_outline(&median_image(&planes)).map_err(|reason| CalibrationError::Matte {
                name: matte[0].name.clone(),
                reason: format!("no sphere outline found: {reason}"),
            })?;
        check_circle(&fit.circle, w, h)?;
        let used: Vec<Array2<u16>> = self
            .lights
            .iter()
            .map(|l| planes[l.index].clone())
            .collect();
        let directions: Vec<[f64; 3]> = self.lights.iter().map(|l| l.highlight.direction).collect();
        let k = matte::intensities(&used, &directions, &fit.circle, clip_level(&planes)).map_err(
            |(i, reason)| CalibrationError::Matte {
                name: matte[self.lights[i].index].name.clone(),
                reason,
            },
        )?;
        for (l, k) in self.lights.iter_mut().zip(k) {
            l.intensity = Some(k);
        }
        Ok(())
    }

    /// The light table in the seed's format: `name, x, y, z` or `name, x, y, z, intensity`.
    pub fn table(&self) -> String {
        let mut out = String::new();
        for l in &self.lights {
            let d = l.highlight.direction;
            out.push_str(&format!(
                "{}, {:.6}, {:.6}, {:.6}",
                l.name, d[0], d[1], d[2]
            ));
            if let Some(k) = l.intensity {
                out.push_str(&format!(", {k:.4}"));
            }
            out.push('\n');
        }
        out
    }

    /// The per-light quality table, as aligned text.
    pub fn quality_table(&self) -> String {
        let mut out = String::from(
            "  #  image                 name                  highlight x, y    px   peak  clip  rim px  elev °  azim °\n",
        );
        for l in &self.lights {
            let hl = &l.highlight;
            let d = hl.direction;
            let elevation = d[2].clamp(-1.0, 1.0).asin().to_degrees();
            let azimuth = d[1].atan2(d[0]).to_degrees();
            out.push_str(&format!(
                "{:>3}  {:<20}  {:<20}  {:>8.2}, {:>7.2}  {:>4}  {:.3}  {:<4}  {:>6.1}  {:>6.1}  {:>6.1}\n",
                l.index + 1,
                l.image,
                l.name,
                hl.x,
                hl.y,
                hl.pixels,
                hl.peak,
                if hl.clipped { "yes" } else { "no" },
                hl.rim_distance,
                elevation,
                azimuth
            ));
        }
        out
    }

    /// The overlay picture as PNG: the circle and the numbered highlights over the
    /// maximum image.
    pub fn overlay_png(&self) -> Vec<u8> {
        let marks: Vec<(usize, f64, f64)> = self
            .lights
            .iter()
            .map(|l| (l.index + 1, l.highlight.x, l.highlight.y))
            .collect();
        png_bytes(&draw::overlay(&self.max_image, &self.circle, &marks))
    }

    /// The light diagram as PNG (`lights.png`).
    pub fn lights_png(&self) -> Vec<u8> {
        let dirs: Vec<(usize, [f64; 3])> = self
            .lights
            .iter()
            .map(|l| (l.index + 1, l.highlight.direction))
            .collect();
        png_bytes(&draw::lights_diagram(&dirs))
    }
}

/// At least 3 images, all one size; their (width, height).
fn check_images(images: &[SphereImage]) -> Result<(usize, usize), CalibrationError> {
    if images.len() < 3 {
        return Err(InputError::TooFewImages {
            count: images.len(),
        }
        .into());
    }
    let (h, w) = images[0].plane.dim();
    for img in &images[1..] {
        let (ih, iw) = img.plane.dim();
        if (ih, iw) != (h, w) {
            return Err(InputError::SizeMismatch {
                name: img.name.clone(),
                width: iw as u32,
                height: ih as u32,
                first: images[0].name.clone(),
                expected_width: w as u32,
                expected_height: h as u32,
            }
            .into());
        }
    }
    Ok((w, h))
}

/// A circle is usable when its centre lies in the image and its radius is a few pixels
/// at least and not far beyond the frame.
fn check_circle(c: &Circle, w: usize, h: usize) -> Result<(), CalibrationError> {
    let bad = |reason: String| CalibrationError::BadCircle {
        cx: c.cx,
        cy: c.cy,
        r: c.r,
        reason,
    };
    if ![c.cx, c.cy, c.r].iter().all(|v| v.is_finite()) {
        return Err(bad("not finite".into()));
    }
    if c.cx < 0.0 || c.cy < 0.0 || c.cx > (w - 1) as f64 || c.cy > (h - 1) as f64 {
        return Err(bad(format!(
            "the centre lies outside the {w}×{h} image (pixel centres 0..{} × 0..{})",
            w - 1,
            h - 1
        )));
    }
    if c.r < 4.0 {
        return Err(bad("the radius is under 4 pixels".into()));
    }
    if c.r > 2.0 * w.max(h) as f64 {
        return Err(bad(format!(
            "the radius is over twice the {w}×{h} image's size"
        )));
    }
    Ok(())
}

/// The value at and above which a pixel counts as clipped: within 0.5 % of full scale
/// of the brightest value in the set.
fn clip_level(planes: &[Array2<u16>]) -> u16 {
    let top = planes
        .iter()
        .map(|p| p.iter().copied().max().unwrap_or(0))
        .max()
        .unwrap_or(0);
    top.saturating_sub(327)
}

/// Files that name the lights of a sphere folder: the seed's table (only its names are
/// read) or a plain list.
pub const NAMES_FILE: &str = "names.txt";

/// Read a sphere folder: every image file in it, in name order, and the light names from
/// its `light_directions.csv` / `.json` or `names.txt` (one per image, same order), if any.
pub fn load_dir(dir: &Path) -> Result<(Vec<SphereImage>, Option<Vec<String>>), CalibrationError> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| InputError::io(dir, e))? {
        let entry = entry.map_err(|e| InputError::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if entry.path().is_file() && layout::is_image(&name) {
            files.push(name);
        }
    }
    files.sort();
    let images = read_images(dir, &files)?;
    let read = |name: &str| {
        let p = dir.join(name);
        std::fs::read(&p).map_err(|e| InputError::io(&p, e))
    };
    let names = if let Some(table) = [layout::SEED_CSV, layout::SEED_JSON]
        .into_iter()
        .find(|n| dir.join(n).is_file())
    {
        let lights = super::lights::parse_bytes(&read(table)?)?;
        Some(lights.into_iter().map(|l| l.name).collect::<Vec<String>>())
    } else if dir.join(NAMES_FILE).is_file() {
        let text = String::from_utf8(read(NAMES_FILE)?)
            .map_err(|_| CalibrationError::Names(format!("{NAMES_FILE} is not UTF-8 text")))?;
        Some(
            text.lines()
                .map(str::trim)
                .filter(|l| !l.is_empty())
                .map(String::from)
                .collect(),
        )
    } else {
        None
    };
    if let Some(n) = &names
        && n.len() != images.len()
    {
        return Err(CalibrationError::Names(format!(
            "{} in {} lists {} names but the folder has {} sphere images",
            if dir.join(NAMES_FILE).is_file() && !dir.join(layout::SEED_CSV).is_file() {
                NAMES_FILE
            } else {
                "the light table"
            },
            dir.display(),
            n.len(),
            images.len()
        )));
    }
    Ok((images, names))
}

fn read_images(dir: &Path, files: &[String]) -> Result<Vec<SphereImage>, CalibrationError> {
    use rayon::prelude::*;
    let limits = Limits::default();
    if files.len() > limits.max_images {
        return Err(InputError::TooManyImages {
            count: files.len(),
            limit: limits.max_images,
        }
        .into());
    }
    let images: Result<Vec<SphereImage>, InputError> = files
        .par_iter()
        .map(|name| {
            let path = dir.join(name);
            let bytes = std::fs::read(&path).map_err(|e| InputError::io(&path, e))?;
            let plane = intake::to_luma16(intake::decode(name, &bytes, &limits)?);
            Ok(SphereImage {
                name: name.clone(),
                plane,
            })
        })
        .collect();
    Ok(images?)
}

/// Read the images of a folder (every image file, in name order), e.g. a matte sphere's.
pub fn load_images(dir: &Path) -> Result<Vec<SphereImage>, CalibrationError> {
    load_dir(dir).map(|(images, _)| images)
}

/// Read a sphere mask (non-zero = sphere).
pub fn read_mask(path: &Path) -> Result<CircleSource, CalibrationError> {
    let name = path
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    let bytes = std::fs::read(path).map_err(|e| InputError::io(path, e))?;
    let plane = intake::to_luma16(intake::decode(&name, &bytes, &Limits::default())?);
    Ok(CircleSource::Mask {
        name,
        mask: plane.mapv(|v| v > 0),
    })
}
