//! Finding the balls in the images, when no circle is given.
//!
//! The outlines are fitted on the per-pixel median of downscaled copies of the images
//! (see [`sphere`]): the best one (the ball when the frame holds one), then every further
//! round outline as strong as a ball's, of its size and beside the others
//! ([`sphere::is_another_ball`]). A second pass reads each ball's window at full
//! resolution, where each outline is refined and judged again. Each ball's outline is then
//! refined on the images themselves: along each ray, the strongest step any one image
//! shows. Last, the images confirm them: a ball shows a
//! light's highlight in most images, so an outline whose window has none in most images
//! (a plate, a round patch of the backdrop) is no ball and is left out, unless none is
//! left: then the best one is the ball, whatever it shows, and its errors are the
//! calibration's, as when one ball is found.
//!
//! The balls are then ordered left to right (by their centre's column, then row): the
//! first ball, which the light table's directions and the positions' origin are on, is
//! the leftmost.

use std::borrow::Cow;
use std::path::Path;

use ndarray::Array2;

use super::checks::check_circle;
use super::circle::Circle;
use super::environment;
use super::error::CalibrationError;
use super::highlight::Highlight;
use super::model::Budget;
use super::reading::{self, Pass, Plan, Window, Windows};
use super::source::Source;
use super::sphere::{self, OutlineFit};

/// Where the balls are, fitted to the images: per ball (the best-fitting first) its
/// outline, the pass's window of every image around it, and the environment over that
/// window.
pub(super) struct Located {
    pub fits: Vec<OutlineFit>,
    pub pass: Pass,
    pub envs: Vec<Array2<u16>>,
}

/// Why [`locate`] found no ball (a reason for the caller's error), or another error.
pub(super) enum LocateError {
    NoOutline(String),
    Other(CalibrationError),
}

impl LocateError {
    pub fn into_error(
        self,
        no_outline: impl FnOnce(String) -> CalibrationError,
    ) -> CalibrationError {
        match self {
            Self::NoOutline(reason) => no_outline(reason),
            Self::Other(e) => e,
        }
    }
}

impl From<CalibrationError> for LocateError {
    fn from(e: CalibrationError) -> Self {
        Self::Other(e)
    }
}

/// Fit the ball's outline (`several`: every ball's): on the per-pixel median of the images
/// (raised to `ambient`) downscaled to fit the budget, then, when they were downscaled,
/// refined at full resolution on the median of a second pass over each ball's window;
/// last, each ball's outline refined on the images themselves
/// ([`sphere::refine_on_images`]), once it has been judged a ball on the median.
pub(super) fn locate(
    images: &dyn Source,
    ambient: Option<&dyn Source>,
    dim: (usize, usize),
    budget: &Budget,
    scratch: &Path,
    several: bool,
) -> Result<Located, LocateError> {
    let f = reading::coarse_factor(images.count(), dim, budget.coarse_bytes);
    let plan = |factor, windows, overlay| plan(factor, windows, overlay, scratch, budget);
    let first = reading::read_all(images, dim, &plan(Some(f), &[], true))?;
    let ambient_coarse = match ambient {
        Some(a) => Some(
            reading::read_all(a, dim, &plan(Some(f), &[], false))?
                .coarse
                .remove(0),
        ),
        None => None,
    };
    let env = {
        let refs: Vec<&Array2<u16>> = first.coarse.iter().collect();
        environment::estimate(&refs, ambient_coarse.as_ref())
    };
    let copy = env.mapv(|v| v as f32 / 65535.0);
    let rough = match several {
        true => sphere::fit_outlines_downscaled(&copy, f),
        false => sphere::fit_outline_downscaled(&copy, f).map(|fit| vec![fit]),
    }
    .map_err(LocateError::NoOutline)?;
    drop(copy);
    let (w, h) = dim;
    check_circle(&rough[0].circle, w, h)?;
    let rough: Vec<OutlineFit> = rough
        .into_iter()
        .filter(|fit| check_circle(&fit.circle, w, h).is_ok())
        .collect();
    if f == 1 {
        // The copies are the images: each outline is refined on them, and the balls'
        // windows are cut from them, one at a time.
        let images = &first.coarse;
        let image = |k: usize| Ok::<_, CalibrationError>(Cow::Borrowed(&images[k]));
        let threshold = sphere::edge_threshold(&env);
        let rough = rough
            .iter()
            .map(|fit| sphere::refine_on_images(threshold, images.len(), image, fit))
            .collect::<Result<Vec<OutlineFit>, _>>()?;
        let windows: Vec<Window> = rough
            .iter()
            .map(|fit| Window::around(&fit.circle, 0.0, dim))
            .collect();
        let cut = |p: &Array2<u16>, win: &Window| {
            p.slice(ndarray::s![win.r0..win.r0 + win.h, win.c0..win.c0 + win.w])
                .to_owned()
        };
        let envs = windows.iter().map(|win| cut(&env, win)).collect();
        let cuts = windows
            .iter()
            .map(|win| Windows::Memory(*win, first.coarse.iter().map(|p| cut(p, win)).collect()))
            .collect();
        return Ok(Located {
            fits: rough,
            pass: Pass {
                coarse: Vec::new(),
                windows: cuts,
                maxima: first.maxima,
                overlay: first.overlay,
            },
            envs,
        });
    }
    drop(env);
    let Pass {
        maxima, overlay, ..
    } = first;
    // A coarse pixel's centre is the mean of the pixels it averages.
    let k = f as f64;
    let up = |c: &Circle| Circle {
        cx: c.cx * k + (k - 1.0) / 2.0,
        cy: c.cy * k + (k - 1.0) / 2.0,
        r: c.r * k,
    };
    let ups: Vec<Circle> = rough.iter().map(|fit| up(&fit.circle)).collect();
    check_circle(&ups[0], w, h)?;
    // The rough circles may be off by a coarse pixel or two.
    let off = 2.0 * k;
    let wins: Vec<Window> = ups
        .iter()
        .map(|c| Window::around(c, sphere::refine_margin(c.r, off), dim))
        .collect();
    let second = reading::read_all(images, dim, &plan(None, &wins, false))?;
    let ambient_windows = match ambient {
        Some(a) => {
            let read = reading::read_all(a, dim, &plan(None, &wins, false))?;
            read.windows
                .iter()
                .map(|ws| ws.image(0).map(|p| Some(p.into_owned())))
                .collect::<Result<Vec<_>, _>>()?
        }
        None => vec![None; wins.len()],
    };
    let mut fits: Vec<OutlineFit> = Vec::new();
    let mut windows = Vec::new();
    let mut envs = Vec::new();
    for (((up, win), ws), amb) in ups
        .iter()
        .zip(&wins)
        .zip(second.windows)
        .zip(ambient_windows)
    {
        let env = ws.median(amb.as_ref())?;
        drop(amb);
        let fine = refined(&env, up, win, off, dim, f);
        let (fit, threshold) = match (fits.is_empty(), fine) {
            (true, fine) => fine?,
            (false, Ok((fit, t))) if sphere::is_another_ball(&fit, &fits) => (fit, t),
            // At full resolution it is no ball's outline after all.
            (false, _) => continue,
        };
        let fit = on_images(threshold, &ws, win, &fit)?;
        fits.push(fit);
        windows.push(ws);
        envs.push(env);
    }
    // The highlights are searched within each ball's own box.
    Ok(Located {
        fits,
        pass: Pass {
            coarse: Vec::new(),
            windows,
            maxima,
            overlay,
        },
        envs,
    })
}

/// What a pass of [`locate`] keeps.
fn plan<'a>(
    factor: Option<usize>,
    windows: &'a [Window],
    overlay: bool,
    scratch: &'a Path,
    budget: &Budget,
) -> Plan<'a> {
    Plan {
        factor,
        windows,
        overlay,
        scratch,
        crop_bytes: budget.crop_bytes,
    }
}

/// The outline `up` (fitted on the `f`× downscaled copies) refined at full resolution on
/// `env`, the environment over its window `win`: in the image's coordinates, with `env`'s
/// edge threshold.
fn refined(
    env: &Array2<u16>,
    up: &Circle,
    win: &Window,
    off: f64,
    dim: (usize, usize),
    f: usize,
) -> Result<(OutlineFit, f32), LocateError> {
    let (fine, threshold) =
        sphere::refine_outline(env, win.local(up), off).map_err(LocateError::NoOutline)?;
    let circle = Circle {
        cx: fine.circle.cx + win.c0 as f64,
        cy: fine.circle.cy + win.r0 as f64,
        r: fine.circle.r,
    };
    check_circle(&circle, dim.0, dim.1)?;
    if !win.holds(&circle, dim) {
        return Err(LocateError::NoOutline(format!(
            "the outline traced at full resolution ({:.1}, {:.1}, radius {:.1}) lies far from the one found on the {f}× downscaled images",
            circle.cx, circle.cy, circle.r
        )));
    }
    Ok((OutlineFit { circle, ..fine }, threshold))
}

/// `fit` (in the image's coordinates, fitted on the environment over `win`, whose edge
/// threshold is `threshold`) refined on the images' windows `ws` themselves
/// ([`sphere::refine_on_images`]).
fn on_images(
    threshold: f32,
    ws: &Windows,
    win: &Window,
    fit: &OutlineFit,
) -> Result<OutlineFit, CalibrationError> {
    let local = OutlineFit {
        circle: win.local(&fit.circle),
        ..*fit
    };
    let fine = sphere::refine_on_images(threshold, ws.count(), |k| ws.image(k), &local)?;
    Ok(OutlineFit {
        circle: Circle {
            cx: fine.circle.cx + win.c0 as f64,
            cy: fine.circle.cy + win.r0 as f64,
            r: fine.circle.r,
        },
        ..fine
    })
}

/// Per image, its highlight on one ball or why it has none.
pub(super) type Highlights = Vec<Result<Highlight, String>>;

/// One ball as calibrated: its circle, its outline when fitted, and its highlights.
pub(super) struct Ball {
    pub circle: Circle,
    pub outline: Option<OutlineFit>,
    pub highlights: Highlights,
}

/// The balls found (the best-fitting first, each with its highlights or the error that
/// found none), confirmed by the images and ordered left to right; and the outlines left
/// out. An outline whose images are all alike, or that shows a highlight in half of them
/// or fewer, is no ball; when none is left, the best-fitting one is the ball, as when it
/// is found alone, and its error is the calibration's.
pub(super) fn confirm(
    found: Vec<(OutlineFit, Result<Highlights, CalibrationError>)>,
) -> Result<(Vec<Ball>, Vec<Circle>), CalibrationError> {
    let ball = |fit: OutlineFit, highlights| Ball {
        circle: fit.circle,
        outline: Some(fit),
        highlights,
    };
    let mut balls = Vec::new();
    let mut left_out = Vec::new();
    for (fit, highlights) in found {
        match highlights {
            Ok(h) if shows_highlights(&h) => balls.push(ball(fit, h)),
            Err(e) if !matches!(e, CalibrationError::AllAlike { .. }) => return Err(e),
            other => left_out.push((fit, other)),
        }
    }
    if balls.is_empty() {
        let (fit, highlights) = left_out.remove(0);
        balls.push(ball(fit, highlights?));
    }
    balls.sort_by(|a, b| {
        (a.circle.cx, a.circle.cy)
            .partial_cmp(&(b.circle.cx, b.circle.cy))
            .expect("circles are finite")
    });
    let not_balls = left_out.into_iter().map(|(fit, _)| fit.circle).collect();
    Ok((balls, not_balls))
}

/// Whether a ball shows a highlight in most images (more than half).
fn shows_highlights(highlights: &Highlights) -> bool {
    2 * highlights.iter().filter(|h| h.is_ok()).count() > highlights.len()
}
