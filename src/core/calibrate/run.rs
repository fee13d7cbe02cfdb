//! The calibration itself: the images read a few at a time (see [`reading`]), the balls
//! given or found, each image's highlight on each ball, each light's direction on the
//! first ball and its position where the balls' rays meet; and a matte sphere's relative
//! intensities fitted to a calibration.

use ndarray::Array2;

use super::balls::{self, Ball, Highlights, locate};
use super::checks::{check_circle, check_images, check_spread, light_name};
use super::circle::Circle;
use super::error::CalibrationError;
use super::highlight::{self, Highlight};
use super::matte;
use super::mirror::Camera;
use super::model::{CalibratedLight, Calibration, CircleSource, Settings, Skipped};
use super::positions::{self, LightPosition};
use super::reading::{self, Pass, Plan, Window, Windows};
use super::source::Source;
use super::sphere::circle_of_mask;

/// Calibrate from the sphere images (one per light, in light order). `names` are the
/// light table's names, one per image (default: the image names); `ambient` is the ball
/// with the rig's lights off (a source of one image), when there is one.
///
/// The images are read a few at a time, twice at most (see [`reading`]): with
/// [`CircleSource::Fit`] the outlines of every ball in the frame are fitted on the
/// per-pixel median of downscaled copies and refined at full resolution on the median of
/// each ball's window and on each image's (see [`balls`]), and each highlight is found in its own image's
/// window, so the memory held is [`peak_bytes`](super::peak_bytes) whatever the number of images.
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
