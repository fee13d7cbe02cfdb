//! Light calibration from a chrome sphere: one image of a mirror ball per light → the light
//! table (`name, x, y, z[, intensity]`) that `reconstruct` reads.
//!
//! `sphere` finds the balls' outlines (or a given circle or mask is taken), `balls` finds
//! every ball in the frame with it and keeps those the images confirm, `highlight` finds
//! each image's highlight on each ball and its direction through `mirror` (orthographic
//! or pinhole camera), `positions` places near lights where several balls' rays meet,
//! `matte` fits relative intensities from a matte sphere, `draw` makes the pictures a
//! person checks it by. Pure functions over decoded planes; [`load_dir`] and
//! [`read_mask`] are the only file I/O.
//!
//! With several balls, given or found, the first ball is the one the light table's
//! directions are on and the positions' origin (orthographic): the first circle given or,
//! found, the leftmost ball.
//!
//! Pixel coordinates are 0-based with pixel centres at integers: the first pixel's centre
//! is (0, 0). Directions are in the project's frame (x = column right, y = row down,
//! z towards the camera).

mod balls;
mod draw;
mod environment;
mod highlight;
mod matte;
mod mirror;
mod positions;
mod reading;
mod source;
mod sphere;

use std::path::{Path, PathBuf};

use ndarray::Array2;
use serde::Serialize;
use thiserror::Error;

pub use highlight::{Highlight, MAX_BEHIND_DEG};
pub use mirror::{Camera, FOCAL_PX};
pub use positions::LightPosition;
pub use reading::{COARSE_BYTES, CROP_BYTES, FIT_PIXELS, READERS, peak_bytes};
pub use source::{ImageFiles, Source};
pub use sphere::{OutlineFit, circle_of_mask, fit_outline};

use balls::{Ball, Highlights, locate};
use reading::{Pass, Plan, Window, Windows};

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
    /// Fitted to the images' outlines: every ball in the frame (see [`balls`]).
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
    /// What the images may hold in memory (see [`reading`]): the defaults, unless a test
    /// wants the downscaled and spilled paths on small images.
    pub budget: Budget,
    /// Where images' windows are spilled when they do not fit [`Budget::crop_bytes`]
    /// (unlinked files; default: the system's temporary directory).
    pub scratch: Option<PathBuf>,
}

/// The memory budgets of a calibration (defaults [`COARSE_BYTES`], [`CROP_BYTES`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Budget {
    /// The downscaled copies of the whole set.
    pub coarse_bytes: usize,
    /// The balls' windows of the whole set in memory; past it, spilled.
    pub crop_bytes: usize,
}

impl Default for Budget {
    fn default() -> Self {
        Self {
            coarse_bytes: COARSE_BYTES,
            crop_bytes: CROP_BYTES,
        }
    }
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
    /// The other balls' outline fits, in the order of `more_circles`, when they were
    /// found in the images; empty when given.
    pub more_outlines: Vec<OutlineFit>,
    /// Round outlines found beside the ball that show no highlight in most images: not
    /// balls, left out.
    pub not_balls: Vec<Circle>,
    pub lights: Vec<CalibratedLight>,
    pub skipped: Vec<Skipped>,
    /// Per pixel, the brightest of the images as the overlay shows it (gamma ½, 8 bits).
    pub max_image: Array2<u8>,
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
/// with the rig's lights off (a source of one image), when there is one.
///
/// The images are read a few at a time, twice at most (see [`reading`]): with
/// [`CircleSource::Fit`] the outlines of every ball in the frame are fitted on the
/// per-pixel median of downscaled copies and refined at full resolution on the median of
/// each ball's window (see [`balls`]), and each highlight is found in its own image's
/// window, so the memory held is [`peak_bytes`] whatever the number of images.
pub fn calibrate(
    images: &dyn Source,
    names: Option<&[String]>,
    ambient: Option<&dyn Source>,
    settings: &Settings,
) -> Result<Calibration, CalibrationError> {
    let (w, h) = check_images(images)?;
    let dim = (w, h);
    if let Some(a) = ambient {
        let (aw, ah) = a.size(0)?;
        if a.count() != 1 || (aw, ah) != dim {
            return Err(CalibrationError::Image {
                name: a.name(0).to_string(),
                reason: format!("the ambient image is {aw}×{ah} but the sphere images are {w}×{h}"),
            });
        }
    }
    if let Some(n) = names
        && n.len() != images.count()
    {
        return Err(CalibrationError::Names(format!(
            "{} names for {} sphere images",
            n.len(),
            images.count()
        )));
    }
    if let Some(bad) = names
        .into_iter()
        .flatten()
        .find_map(|n| crate::core::lights::check_name(n).err())
    {
        return Err(CalibrationError::Names(bad));
    }
    let given = match &settings.circle {
        CircleSource::Fit => None,
        CircleSource::Given(c) => Some(vec![*c]),
        CircleSource::Balls(cs) if cs.is_empty() => {
            return Err(CalibrationError::NoSphere("no circle given".into()));
        }
        CircleSource::Balls(cs) => Some(cs.clone()),
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
            Some(vec![c])
        }
    };
    let scratch = settings.scratch.clone().unwrap_or_else(std::env::temp_dir);
    let (circles, outlines, pass, envs) = match given {
        Some(circles) => {
            for c in &circles {
                check_circle(c, w, h)?;
            }
            let windows: Vec<Window> = circles
                .iter()
                .map(|c| Window::around(c, 0.0, dim))
                .collect();
            let plan = Plan {
                factor: None,
                windows: &windows,
                overlay: true,
                scratch: &scratch,
                crop_bytes: settings.budget.crop_bytes,
            };
            let envs = vec![None; circles.len()];
            (
                circles,
                Vec::new(),
                reading::read_all(images, dim, &plan)?,
                envs,
            )
        }
        None => {
            let found = locate(images, ambient, dim, &settings.budget, &scratch, true)
                .map_err(|e| e.into_error(CalibrationError::NoSphere))?;
            let circles = found.fits.iter().map(|f| f.circle).collect();
            let envs = found.envs.into_iter().map(Some).collect();
            (circles, found.fits, found.pass, envs)
        }
    };
    let clip = pass
        .maxima
        .iter()
        .copied()
        .max()
        .unwrap_or(0)
        .saturating_sub(655);
    let ambient_windows = match ambient {
        Some(a) => {
            let windows: Vec<Window> = pass.windows.iter().map(|ws| ws.window()).collect();
            let plan = Plan {
                factor: None,
                windows: &windows,
                overlay: false,
                scratch: &scratch,
                crop_bytes: usize::MAX,
            };
            let read = reading::read_all(a, dim, &plan)?;
            read.windows
                .iter()
                .map(|ws| ws.image(0).map(|p| Some(p.into_owned())))
                .collect::<Result<Vec<_>, _>>()?
        }
        None => vec![None; circles.len()],
    };
    let Pass {
        overlay, windows, ..
    } = pass;
    let per_ball = circles
        .iter()
        .zip(windows)
        .zip(ambient_windows)
        .zip(envs)
        .map(|(((c, windows), amb), env)| {
            let view = BallView {
                circle: c,
                windows: &windows,
                env,
                ambient: amb.as_ref(),
            };
            ball_highlights(view, &settings.camera, clip)
        });
    let (balls, not_balls) = match outlines.is_empty() {
        true => {
            let balls = circles
                .iter()
                .zip(per_ball)
                .map(|(c, highlights)| {
                    Ok(Ball {
                        circle: *c,
                        outline: None,
                        highlights: highlights?,
                    })
                })
                .collect::<Result<Vec<Ball>, CalibrationError>>()?;
            (balls, Vec::new())
        }
        false => balls::confirm(outlines.into_iter().zip(per_ball).collect())?,
    };
    let circles: Vec<Circle> = balls.iter().map(|b| b.circle).collect();
    let max_image = overlay.unwrap_or_default();
    let mut lights = Vec::new();
    let mut skipped = Vec::new();
    for i in 0..images.count() {
        let image = images.name(i);
        let found: Result<Vec<Highlight>, String> = balls
            .iter()
            .enumerate()
            .map(|(b, ball)| {
                ball.highlights[i].clone().map_err(|reason| {
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
                    image: image.to_string(),
                    name: names.map_or_else(|| light_name(image), |n| n[i].clone()),
                    highlight,
                    more: hls,
                    position,
                    intensity: None,
                });
            }
            Err(reason) if settings.skip_bad => skipped.push(Skipped {
                image: image.to_string(),
                reason,
            }),
            Err(reason) => {
                return Err(CalibrationError::Image {
                    name: image.to_string(),
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
            count: images.count(),
            left_out: left_out.join("; "),
        });
    }
    check_spread(&lights)?;
    Ok(Calibration {
        circle: circles[0],
        more_circles: circles[1..].to_vec(),
        camera_is_pinhole: matches!(settings.camera, Camera::Perspective { .. }),
        outline: balls[0].outline,
        more_outlines: balls[1..].iter().filter_map(|b| b.outline).collect(),
        not_balls,
        lights,
        skipped,
        max_image,
    })
}

impl Calibration {
    /// Fit each light's relative intensity from a matte sphere's images, one per sphere
    /// image in the same order (the matte sphere's outline is fitted to its own images,
    /// read as the chrome sphere's are).
    pub fn fit_intensities(
        &mut self,
        matte: &dyn Source,
        settings: &Settings,
    ) -> Result<(), CalibrationError> {
        let count = self.lights.len() + self.skipped.len();
        if matte.count() != count {
            return Err(CalibrationError::Names(format!(
                "{} matte sphere images for {count} chrome sphere images",
                matte.count()
            )));
        }
        let (w, h) = check_images(matte)?;
        let scratch = settings.scratch.clone().unwrap_or_else(std::env::temp_dir);
        // One matte ball: the best-fitting outline.
        let found =
            locate(matte, None, (w, h), &settings.budget, &scratch, false).map_err(|e| {
                e.into_error(|reason| CalibrationError::Matte {
                    name: matte.name(0).to_string(),
                    reason: format!("no sphere outline found: {reason}"),
                })
            })?;
        let circle = found.fits[0].circle;
        check_circle(&circle, w, h)?;
        let clip = found
            .pass
            .maxima
            .iter()
            .copied()
            .max()
            .unwrap_or(0)
            .saturating_sub(655);
        let windows = &found.pass.windows[0];
        let local = windows.window().local(&circle);
        let raw = reading::bounded(self.lights.len(), |i| {
            let l = &self.lights[i];
            let plane = windows.image(l.index)?;
            matte::intensity(&plane, l.highlight.direction, &local, clip).map_err(|reason| {
                CalibrationError::Matte {
                    name: matte.name(l.index).to_string(),
                    reason,
                }
            })
        })?;
        let mean = raw.iter().sum::<f64>() / raw.len() as f64;
        for (l, k) in self.lights.iter_mut().zip(raw) {
            l.intensity = Some(k / mean);
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
            Some(d) => (d / 2.0, "the unit of the balls' diameter"),
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

/// One ball's pixels as a pass read them: its circle (in the image), every image's window
/// around it, the environment there when already known, and the ambient image's window.
struct BallView<'a> {
    circle: &'a Circle,
    windows: &'a Windows,
    env: Option<Array2<u16>>,
    ambient: Option<&'a Array2<u16>>,
}

/// Each image's highlight on one ball, in the image's coordinates (see
/// [`find_highlights`]).
fn ball_highlights(
    ball: BallView,
    camera: &Camera,
    clip: u16,
) -> Result<Highlights, CalibrationError> {
    let win = ball.windows.window();
    let env = match ball.env {
        Some(e) => e,
        None => ball.windows.median(ball.ambient)?,
    };
    let local = win.local(ball.circle);
    let camera = match *camera {
        Camera::Perspective {
            focal_px,
            principal,
        } => Camera::Perspective {
            focal_px,
            principal: [principal[0] - win.c0 as f64, principal[1] - win.r0 as f64],
        },
        Camera::Orthographic => Camera::Orthographic,
    };
    let ctx = highlight::Context {
        circle: &local,
        camera: &camera,
        env: &env,
        count: ball.windows.count(),
        clip,
        typical_rise: 0.0,
    };
    let found = find_highlights(ball.windows, &ctx)?;
    Ok(found
        .into_iter()
        .map(|r| {
            r.map(|hl| Highlight {
                x: hl.x + win.c0 as f64,
                y: hl.y + win.r0 as f64,
                ..hl
            })
        })
        .collect())
}

/// Each image's highlight within the ball's window (`ctx` in the window's coordinates):
/// its significant residual first, counted in the recurrence map, then the highlight
/// judged against it. Images that are all alike are one error.
fn find_highlights(
    windows: &Windows,
    ctx: &highlight::Context,
) -> Result<Vec<Result<Highlight, String>>, CalibrationError> {
    let n = windows.count();
    let recurrence = std::sync::Mutex::new(Array2::<u16>::zeros(ctx.env.dim()));
    let rises: Vec<Result<f64, String>> = reading::bounded(n, |k| {
        let plane = windows.image(k)?;
        Ok(highlight::significant(&plane, ctx).map(|sig| {
            let mut counts = recurrence.lock().expect("no reader panics holding it");
            highlight::add_recurrence(&plane, ctx, &sig, &mut counts);
            sig.peak
        }))
    })?;
    let differing = rises.iter().filter(|s| s.is_ok()).count();
    if differing < 3 || 2 * differing < n {
        return Err(CalibrationError::AllAlike {
            differing,
            count: n,
        });
    }
    let mut rises: Vec<f64> = rises.into_iter().flatten().collect();
    let recurrence = recurrence.into_inner().expect("no reader panicked");
    let mid = rises.len() / 2;
    let typical_rise = *rises.select_nth_unstable_by(mid, f64::total_cmp).1;
    let ctx = highlight::Context {
        typical_rise,
        ..*ctx
    };
    reading::bounded(n, |k| {
        Ok(highlight::find(&*windows.image(k)?, &ctx, &recurrence))
    })
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
fn check_images(images: &dyn Source) -> Result<(usize, usize), CalibrationError> {
    if images.count() < 3 {
        return Err(InputError::TooFewImages {
            count: images.count(),
        }
        .into());
    }
    let (w, h) = images.size(0)?;
    for k in 1..images.count() {
        let (iw, ih) = images.size(k)?;
        if (iw, ih) != (w, h) {
            return Err(InputError::SizeMismatch {
                name: images.name(k).to_string(),
                width: iw as u32,
                height: ih as u32,
                first: images.name(0).to_string(),
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

/// An image's name as a light's: the characters a light table cannot hold become `_`.
fn light_name(image: &str) -> String {
    let mut name = String::new();
    for c in image.chars() {
        let c = if matches!(c, ',' | '#' | '"') || c.is_control() {
            '_'
        } else {
            c
        };
        if name.len() + c.len_utf8() > crate::core::lights::MAX_NAME_BYTES {
            break;
        }
        name.push(c);
    }
    match name.trim() {
        "" => "light".to_string(),
        t => t.to_string(),
    }
}

/// Files that name the lights of a sphere folder: the seed's table (only its names are
/// read) or a plain list.
pub const NAMES_FILE: &str = "names.txt";

/// A sphere folder as found: the sphere images (one per light, in name order, read when
/// the calibration reads them), the light names, and the ambient image (the ball with the
/// rig's lights off), if any.
#[derive(Debug, Clone)]
pub struct SphereFolder {
    pub images: ImageFiles,
    pub names: Option<Vec<String>>,
    pub ambient: Option<ImageFiles>,
}

impl SphereFolder {
    /// The ambient image as [`calibrate`] takes it.
    pub fn ambient_source(&self) -> Option<&dyn Source> {
        self.ambient.as_ref().map(|a| a as &dyn Source)
    }
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
    let images = image_files(dir, &files)?;
    let ambient = ambient_file.map(|a| ImageFiles::in_dir(dir, &[a], Limits::default()));
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
        && n.len() != images.count()
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
            images.count()
        )));
    }
    Ok(SphereFolder {
        images,
        names,
        ambient,
    })
}

fn image_files(dir: &Path, files: &[String]) -> Result<ImageFiles, CalibrationError> {
    let limits = Limits::default();
    if files.len() > limits.max_images {
        return Err(InputError::TooManyImages {
            count: files.len(),
            limit: limits.max_images,
        }
        .into());
    }
    Ok(ImageFiles::in_dir(dir, files, limits))
}

/// The images of a folder (every image file, in name order), e.g. a matte sphere's.
pub fn load_images(dir: &Path) -> Result<ImageFiles, CalibrationError> {
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
