//! `photostereo calibrate`: the lights from chrome-ball images, as a light table and
//! pictures to check it by.

use std::path::PathBuf;

use super::flags::circle_arg;
use anyhow::Context;
use clap::Args;

#[derive(Args)]
pub(crate) struct CalibrateArgs {
    /// Folder of chrome sphere images, one per light. A light_directions.csv (or .json) or
    /// names.txt in it gives the light table's names, one per image in the same order
    /// (only the names are read); without one, rows are named by the image files.
    pub(crate) dir: PathBuf,
    /// Where to write the light table (`name, x, y, z[, intensity]`; x = column right,
    /// y = row down, z towards the camera); a name ending in `.lp` writes the `.lp` file
    /// of RTIBuilder and RelightLab instead (count, then `name x y z`, y up).
    #[arg(long, short)]
    pub(crate) out: PathBuf,
    /// The sphere's circle in pixels, as cx,cy,r (0-based, pixel centres at integers: the
    /// first pixel's centre is 0,0) instead of fitting its outline. Give it once per ball
    /// when the frame holds several: each is calibrated and the lights are placed where
    /// the balls' rays meet (--positions). Without it every ball in the frame is found
    /// (round outlines of one size side by side, each showing the lights' highlights),
    /// the first ball being the leftmost.
    #[arg(long, value_parser = circle_arg, allow_hyphen_values = true)]
    pub(crate) circle: Vec<[f64; 3]>,
    /// With two balls or more (each given by --circle, or found when none is given):
    /// write the lights' positions (`name, x, y, z`) here; an error when one ball is
    /// given or found.
    #[arg(long)]
    pub(crate) positions: Option<PathBuf>,
    /// The balls' diameter, in the unit the positions should be in (default: ball radii).
    #[arg(long)]
    pub(crate) ball_diameter: Option<f64>,
    /// A mask image of the sphere (non-zero = sphere) instead of fitting its outline.
    #[arg(long)]
    pub(crate) sphere_mask: Option<PathBuf>,
    /// Write the overlay picture (circle and numbered highlights over the maximum image).
    #[arg(long)]
    pub(crate) overlay: Option<PathBuf>,
    /// Write the diagram of the light directions on the unit hemisphere.
    #[arg(long)]
    pub(crate) lights_png: Option<PathBuf>,
    /// A perspective camera with this focal length in pixels (principal point at the image
    /// centre); orthographic without it.
    #[arg(long)]
    pub(crate) focal_length: Option<f64>,
    /// Folder of matte white sphere images under the same lights (same order): fits each
    /// light's relative intensity, written as the table's fifth column.
    #[arg(long)]
    pub(crate) matte: Option<PathBuf>,
    /// Leave out images without a usable highlight (reported) instead of failing.
    #[arg(long)]
    pub(crate) skip_bad: bool,
}

pub(crate) fn calibrate(args: CalibrateArgs) -> anyhow::Result<()> {
    use photostereo::core::calibrate::{self, Camera, Circle, CircleSource, Settings, Source};
    let folder = calibrate::load_dir(&args.dir)?;
    let (images, names) = (&folder.images, &folder.names);
    let circles: Vec<Circle> = args
        .circle
        .iter()
        .map(|&[cx, cy, r]| Circle { cx, cy, r })
        .collect();
    let circle = match (circles.len(), &args.sphere_mask) {
        (1.., Some(_)) => anyhow::bail!("give --circle or --sphere-mask, not both"),
        (1, None) => CircleSource::Given(circles[0]),
        (2.., None) => CircleSource::Balls(circles),
        (0, Some(mask)) => calibrate::read_mask(mask)?,
        (0, None) => CircleSource::Fit,
    };
    if let Some(d) = args.ball_diameter
        && !(d.is_finite() && d > 0.0)
    {
        anyhow::bail!("--ball-diameter must be a positive number, got {d}");
    }
    if args.positions.is_some() && (args.circle.len() == 1 || args.sphere_mask.is_some()) {
        anyhow::bail!(
            "--positions needs two balls or more in the frame: give each by --circle cx,cy,r, or none to have them found"
        );
    }
    let camera = match args.focal_length {
        Some(f) if calibrate::FOCAL_PX.contains(&f) => {
            let (w, h) = if images.count() > 0 {
                images.size(0)?
            } else {
                (1, 1)
            };
            Camera::Perspective {
                focal_px: f,
                principal: [(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0],
            }
        }
        Some(f) => anyhow::bail!(
            "--focal-length must be a number of pixels from {} to {:e} (leave it out for a long lens far away), got {f}",
            calibrate::FOCAL_PX.start(),
            calibrate::FOCAL_PX.end()
        ),
        None => Camera::Orthographic,
    };
    let settings = Settings {
        circle,
        camera,
        skip_bad: args.skip_bad,
        budget: Default::default(),
        scratch: None,
    };
    if let Some(a) = folder.ambient_source() {
        eprintln!("ambient image: {}", a.name(0));
    }
    let mut cal =
        calibrate::calibrate(images, names.as_deref(), folder.ambient_source(), &settings)?;
    if let Some(matte) = &args.matte {
        cal.fit_intensities(&calibrate::load_images(matte)?, &settings)?;
    }
    if args.positions.is_some() && cal.more_circles.is_empty() {
        let c = cal.circle;
        anyhow::bail!(
            "--positions needs two balls or more in the frame, but one ball was found (centre ({:.1}, {:.1}), radius {:.1} px): give each ball by --circle cx,cy,r",
            c.cx,
            c.cy,
            c.r
        );
    }
    print_balls(&cal);
    eprint!("{}", cal.quality_table());
    for s in &cal.skipped {
        eprintln!("skipped {}: {}", s.image, s.reason);
    }
    let write = |path: &PathBuf, bytes: &[u8]| {
        std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
    };
    for l in &cal.lights {
        if let Some(p) = &l.position {
            let k = args.ball_diameter.map_or(1.0, |d| d / 2.0);
            eprintln!(
                "position {:>3}  {:<20}  {:>9.3}, {:>9.3}, {:>9.3}  residual {:.3}  rays {:.2}° apart",
                l.index + 1,
                l.name,
                k * p.position[0],
                k * p.position[1],
                k * p.position[2],
                k * p.residual,
                p.spread_deg
            );
        }
    }
    let is_lp = args
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("lp"));
    if is_lp && cal.lights.iter().any(|l| l.intensity.is_some()) {
        eprintln!(
            "note: a .lp table has no intensity column; the matte sphere's intensities are left out"
        );
    }
    let table = if is_lp { cal.lp_table() } else { cal.table() };
    write(&args.out, table.as_bytes())?;
    if let (Some(path), Some(table)) = (&args.positions, cal.positions_table(args.ball_diameter)) {
        write(path, table.as_bytes())?;
    }
    if let Some(p) = &args.overlay {
        write(p, &cal.overlay_png())?;
    }
    if let Some(p) = &args.lights_png {
        write(p, &cal.lights_png())?;
    }
    println!("{}", args.out.display());
    Ok(())
}

/// The balls' circles as the calibration used them (`sphere` with one ball, `sphere 1`,
/// `sphere 2`… with several, the first being the positions' origin), and the round
/// outlines found that were no balls.
pub(crate) fn print_balls(cal: &photostereo::core::calibrate::Calibration) {
    let several = !cal.more_circles.is_empty();
    let circles = std::iter::once(&cal.circle).chain(&cal.more_circles);
    for (k, c) in circles.enumerate() {
        let fit = match k {
            0 => cal.outline.as_ref(),
            k => cal.more_outlines.get(k - 1),
        };
        let label = match several {
            true => format!("sphere {}", k + 1),
            false => "sphere".to_string(),
        };
        let how = match fit {
            Some(fit) => format!(
                "outline fitted along {:.0} % of the circle, RMS {:.2} px",
                100.0 * fit.coverage,
                fit.rms
            ),
            None => "given".to_string(),
        };
        eprintln!(
            "{label}: centre ({:.2}, {:.2}), radius {:.2} px ({how})",
            c.cx, c.cy, c.r
        );
    }
    for c in &cal.not_balls {
        eprintln!(
            "left out the round outline at ({:.1}, {:.1}), radius {:.1} px: it shows no highlight in most images, so it is no ball",
            c.cx, c.cy, c.r
        );
    }
}
