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
mod environment;
mod highlight;
mod matte;
mod mirror;
mod positions;
mod sphere;

use std::path::Path;

use ndarray::Array2;
use serde::Serialize;
use thiserror::Error;

pub use highlight::{Highlight, MAX_BEHIND_DEG};
pub use mirror::{Camera, FOCAL_PX};
pub use positions::LightPosition;
pub use sphere::{OutlineFit, circle_of_mask, fit_outline};

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
    /// Several balls in the frame, each its circle: each ball is calibrated, and each
    /// light is placed where the balls' rays meet.
    Balls(Vec<Circle>),
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

/// Lights that all come out within this angle of their mean direction are one light, or a
/// reflection that stays put: not a calibration.
pub const MIN_SPREAD_DEG: f64 = 2.0;

/// One calibrated light.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibratedLight {
    /// Position of its sphere image in the set (0-based).
    pub index: usize,
    /// The sphere image's file name and the name the light table gives the light.
    pub image: String,
    pub name: String,
    /// Its highlight on the (first) ball.
    pub highlight: Highlight,
    /// Its highlights on the other balls, in the order of [`Calibration::more_circles`].
    pub more: Vec<Highlight>,
    /// Where the balls' rays meet, with several balls (None when they are parallel).
    pub position: Option<LightPosition>,
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
    /// The other balls' circles, with several balls.
    pub more_circles: Vec<Circle>,
    /// Whether positions are relative to a pinhole camera (else to the first ball).
    pub camera_is_pinhole: bool,
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
    #[error(
        "the {count} images are alike: only {differing} have a highlight the others lack (one light photographed again and again, or the rig's lights did not change between the shots)"
    )]
    AllAlike { differing: usize, count: usize },
    #[error(
        "all {count} lights come out within {spread:.1}° of each other although the images differ: the highlight found is not the rig's light but something the ball shows in every image; add an ambient image of the ball with the rig's lights off (ambient.png) or give --circle"
    )]
    OneDirection { count: usize, spread: f64 },
    #[error("names: {0}")]
    Names(String),
    #[error("matte sphere image {name:?}: {reason}")]
    Matte { name: String, reason: String },
}

/// Calibrate from the sphere images (one per light, in light order). `names` are the
/// light table's names, one per image (default: the image names); `ambient` is the ball
/// with the rig's lights off, when there is one.
pub fn calibrate(
    images: &[SphereImage],
    names: Option<&[String]>,
    ambient: Option<&SphereImage>,
    settings: &Settings,
) -> Result<Calibration, CalibrationError> {
    let (w, h) = check_images(images)?;
    if let Some(a) = ambient
        && a.plane.dim() != images[0].plane.dim()
    {
        return Err(CalibrationError::Image {
            name: a.name.clone(),
            reason: format!(
                "the ambient image is {}×{} but the sphere images are {w}×{h}",
                a.plane.dim().1,
                a.plane.dim().0
            ),
        });
    }
    if let Some(n) = names
        && n.len() != images.len()
    {
        return Err(CalibrationError::Names(format!(
            "{} names for {} sphere images",
            n.len(),
            images.len()
        )));
    }
    let planes: Vec<&Array2<u16>> = images.iter().map(|i| &i.plane).collect();
    let env = environment::estimate(&planes, ambient.map(|a| &a.plane));
    let (circle, outline) = match &settings.circle {
        CircleSource::Fit => {
            let fit = fit_outline(&env.mapv(|v| v as f32 / 65535.0))
                .map_err(CalibrationError::NoSphere)?;
            (fit.circle, Some(fit))
        }
        CircleSource::Given(c) => (*c, None),
        CircleSource::Balls(cs) if cs.is_empty() => {
            return Err(CalibrationError::NoSphere("no circle given".into()));
        }
        CircleSource::Balls(cs) => (cs[0], None),
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
    let more_circles = match &settings.circle {
        CircleSource::Balls(cs) => cs[1..].to_vec(),
        _ => Vec::new(),
    };
    let circles: Vec<Circle> = std::iter::once(circle)
        .chain(more_circles.iter().copied())
        .collect();
    for c in &circles {
        check_circle(c, w, h)?;
    }
    let clip = clip_level(&planes);
    let per_ball: Vec<Vec<Result<Highlight, String>>> = circles
        .iter()
        .map(|c| {
            let ctx = highlight::Context {
                circle: c,
                camera: &settings.camera,
                env: &env,
                count: planes.len(),
                clip,
                typical_rise: 0.0,
            };
            find_highlights(&planes, &ctx)
        })
        .collect::<Result<_, _>>()?;
    let mut lights = Vec::new();
    let mut skipped = Vec::new();
    for (i, img) in images.iter().enumerate() {
        let found: Result<Vec<Highlight>, String> = per_ball
            .iter()
            .enumerate()
            .map(|(b, ball)| {
                ball[i].clone().map_err(|reason| {
                    if circles.len() > 1 {
                        format!("ball {}: {reason}", b + 1)
                    } else {
                        reason
                    }
                })
            })
            .collect();
        match found {
            Ok(mut hls) => {
                let highlight = hls.remove(0);
                let position = place(&settings.camera, &circles, &highlight, &hls);
                lights.push(CalibratedLight {
                    index: i,
                    image: img.name.clone(),
                    name: names.map_or_else(|| img.name.clone(), |n| n[i].clone()),
                    highlight,
                    more: hls,
                    position,
                    intensity: None,
                });
            }
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
    check_spread(&lights)?;
    let mut max_image = planes[0].clone();
    for p in planes[1..].iter().copied() {
        max_image.zip_mut_with(p, |m, &v| *m = (*m).max(v));
    }
    Ok(Calibration {
        circle,
        more_circles,
        camera_is_pinhole: matches!(settings.camera, Camera::Perspective { .. }),
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
        let planes: Vec<&Array2<u16>> = matte.iter().map(|i| &i.plane).collect();
        let fit = fit_outline(&environment::estimate(&planes, None).mapv(|v| v as f32 / 65535.0))
            .map_err(|reason| CalibrationError::Matte {
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

    /// The light table as a `.lp` file (RTIBuilder, RelightLab: y up; no intensities).
    pub fn lp_table(&self) -> String {
        let rows: Vec<(String, [f64; 3])> = self
            .lights
            .iter()
            .map(|l| (l.name.clone(), l.highlight.direction))
            .collect();
        super::lights::lp::format(&rows)
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

    /// The light positions (several balls) as a table `name, x, y, z`, in ball radii or,
    /// given the balls' diameter, in its unit; a comment line says which. Lights whose rays
    /// do not meet are left out. None with one ball.
    pub fn positions_table(&self, ball_diameter: Option<f64>) -> Option<String> {
        if self.more_circles.is_empty() {
            return None;
        }
        let (k, unit) = match ball_diameter {
            Some(d) => (d / 2.0, "the unit of --ball-diameter"),
            None => (1.0, "ball radii"),
        };
        let mut out = format!(
            "# light positions in {unit}; x = column right, y = row down, z towards the camera; origin: {}\n",
            match self.camera_is_pinhole {
                true => "the camera",
                false => "the first ball's centre",
            }
        );
        for l in &self.lights {
            if let Some(p) = &l.position {
                let x = p.position.map(|v| v * k);
                out.push_str(&format!(
                    "{}, {:.6}, {:.6}, {:.6}\n",
                    l.name, x[0], x[1], x[2]
                ));
            }
        }
        Some(out)
    }

    /// The per-light quality table, as aligned text.
    pub fn quality_table(&self) -> String {
        let mut out = String::from(
            "  #  image                 name                  highlight x, y    px   peak  clip  rim px  elev °  azim °  conf\n",
        );
        for l in &self.lights {
            let hl = &l.highlight;
            let d = hl.direction;
            let elevation = d[2].clamp(-1.0, 1.0).asin().to_degrees();
            let azimuth = d[1].atan2(d[0]).to_degrees();
            out.push_str(&format!(
                "{:>3}  {:<20}  {:<20}  {:>8.2}, {:>7.2}  {:>4}  {:.3}  {:<4}  {:>6.1}  {:>6.1}  {:>6.1}  {:.2}\n",
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
                azimuth,
                hl.confidence
            ));
        }
        out
    }

    /// The overlay picture as PNG: the circle and the numbered highlights over the
    /// maximum image.
    pub fn overlay_png(&self) -> Vec<u8> {
        let marks: Vec<draw::Mark> = self
            .lights
            .iter()
            .map(|l| draw::Mark {
                number: l.index + 1,
                x: l.highlight.x,
                y: l.highlight.y,
                confidence: l.highlight.confidence,
            })
            .collect();
        let circles: Vec<Circle> = std::iter::once(self.circle)
            .chain(self.more_circles.iter().copied())
            .collect();
        png_bytes(&draw::overlay(&self.max_image, &circles, &marks))
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

/// Each image's highlight: its significant residual first, for the recurrence map, then
/// the highlight judged against it. Images that are all alike are one error.
fn find_highlights(
    planes: &[&Array2<u16>],
    ctx: &highlight::Context,
) -> Result<Vec<Result<Highlight, String>>, CalibrationError> {
    use rayon::prelude::*;
    let significant: Vec<Result<highlight::Significant, String>> = planes
        .par_iter()
        .map(|p| highlight::significant(p, ctx))
        .collect();
    let differing = significant.iter().filter(|s| s.is_ok()).count();
    if differing < 3 || 2 * differing < planes.len() {
        return Err(CalibrationError::AllAlike {
            differing,
            count: planes.len(),
        });
    }
    let (lists, mut rises): (Vec<Vec<(usize, usize)>>, Vec<f64>) = significant
        .into_iter()
        .flatten()
        .map(|s| (s.pixels, s.peak))
        .unzip();
    let recurrence = environment::recurrence(planes[0].dim(), &lists);
    let mid = rises.len() / 2;
    let typical_rise = *rises.select_nth_unstable_by(mid, f64::total_cmp).1;
    let ctx = highlight::Context {
        typical_rise,
        ..*ctx
    };
    Ok(planes
        .par_iter()
        .map(|p| highlight::find(p, &ctx, &recurrence))
        .collect())
}

/// A light's position from its highlights on several balls (`first` on `circles[0]`).
fn place(
    camera: &Camera,
    circles: &[Circle],
    first: &Highlight,
    more: &[Highlight],
) -> Option<LightPosition> {
    if circles.len() < 2 {
        return None;
    }
    let scale = circles.iter().map(|c| c.r).sum::<f64>() / circles.len() as f64;
    let rays: Vec<([f64; 3], [f64; 3])> = std::iter::once(first)
        .chain(more)
        .zip(circles)
        .filter_map(|(h, c)| positions::ray(camera, c, (h.x, h.y), h.direction, &circles[0], scale))
        .collect();
    positions::intersect(&rays)
}

/// Refuse lights that all point the same way: the images show one light, or the finder
/// followed something that stays put.
fn check_spread(lights: &[CalibratedLight]) -> Result<(), CalibrationError> {
    if lights.len() < 3 {
        return Ok(());
    }
    let mut mean = [0.0; 3];
    for l in lights {
        for k in 0..3 {
            mean[k] += l.highlight.direction[k];
        }
    }
    let mean = mirror::normalise(mean);
    let spread = lights
        .iter()
        .map(|l| {
            mirror::dot(l.highlight.direction, mean)
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        })
        .fold(0.0, f64::max);
    if spread < MIN_SPREAD_DEG {
        return Err(CalibrationError::OneDirection {
            count: lights.len(),
            spread,
        });
    }
    Ok(())
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

/// The value at and above which a pixel counts as clipped: within 1 % of full scale of
/// the brightest value in the set (JPEG's ringing leaves a clipped core a little below
/// full scale).
fn clip_level(planes: &[&Array2<u16>]) -> u16 {
    let top = planes
        .iter()
        .map(|p| p.iter().copied().max().unwrap_or(0))
        .max()
        .unwrap_or(0);
    top.saturating_sub(655)
}

/// Files that name the lights of a sphere folder: the seed's table (only its names are
/// read) or a plain list.
pub const NAMES_FILE: &str = "names.txt";

/// A sphere folder as read: the sphere images (one per light, in name order), the light
/// names, and the ambient image (the ball with the rig's lights off), if any.
#[derive(Debug, Clone)]
pub struct SphereFolder {
    pub images: Vec<SphereImage>,
    pub names: Option<Vec<String>>,
    pub ambient: Option<SphereImage>,
}

/// Whether an image file is the ambient image: its stem is `ambient` or `ref`
/// (any case), as light-dome software names it.
pub fn is_ambient(name: &str) -> bool {
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    stem.eq_ignore_ascii_case("ambient") || stem.eq_ignore_ascii_case("ref")
}

/// Read a sphere folder: every image file in it, in name order, but the ambient image
/// (`ambient.*` or `ref.*`), and the light names from its `light_directions.csv` /
/// `.json` or `names.txt` (one per image, same order), if any.
pub fn load_dir(dir: &Path) -> Result<SphereFolder, CalibrationError> {
    let mut files = Vec::new();
    let mut ambient_file = None;
    for entry in std::fs::read_dir(dir).map_err(|e| InputError::io(dir, e))? {
        let entry = entry.map_err(|e| InputError::io(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if entry.path().is_file() && layout::is_image(&name) {
            if is_ambient(&name) {
                if let Some(first) = ambient_file.replace(name.clone()) {
                    return Err(CalibrationError::Names(format!(
                        "{} holds two ambient images, {first} and {name}: keep one",
                        dir.display()
                    )));
                }
            } else {
                files.push(name);
            }
        }
    }
    files.sort();
    files.extend(ambient_file.iter().cloned());
    let mut images = read_images(dir, &files)?;
    let ambient = ambient_file.and_then(|_| images.pop());
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
    Ok(SphereFolder {
        images,
        names,
        ambient,
    })
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
    load_dir(dir).map(|f| f.images)
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
