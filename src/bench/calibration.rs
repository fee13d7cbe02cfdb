//! `bench --calibration`: a chrome-ball calibration of camera-sized images, as
//! `photostereo calibrate` runs it in a child process, timed (wall clock) with its peak
//! resident memory (`wait4`), against the targets of 15 s and 1.5 GB for 24 images of
//! 24 megapixels.
//!
//! The images are the renderer's usual capture (`ChromeSet::standard`: an off-centre ball
//! with distractors, every third highlight clipping), rendered at [`NATIVE`] times its own
//! size (supersampled, as every chrome set) and enlarged to [`WIDTH`] × [`HEIGHT`]
//! (bilinear), written as 8-bit JPEG as cameras write them: the ball's outline is a ramp a
//! few pixels wide, as a lens and demosaicing leave it. Rendering all 27 megapixels with
//! the renderer's supersampling would take minutes per image.
//! One run finds the ball's outline itself; the timed runs are given its true circle, so
//! that they measure the calibration even where the outline fit fails. Each run's lights
//! are checked against the truth, so a fast wrong answer does not pass.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{Context, ensure};
use image::{GrayImage, ImageBuffer, Luma, imageops};

use photostereo::core::synth::ChromeSet;

use super::memory;
use super::stats::median;

/// The enlarged frame: 6000 × 4500 = 27 megapixels (4:3, as the rendered set).
pub(super) const WIDTH: u32 = 6000;
pub(super) const HEIGHT: u32 = 4500;
/// The scale the set is rendered at before it is enlarged.
const NATIVE: usize = 4;
/// The set's images.
pub(super) const IMAGES: usize = 24;

/// What the bench measured.
pub(super) struct Measured {
    pub megapixels: f64,
    pub images: usize,
    /// The one run with the outline found automatically, or why it failed.
    pub automatic: Result<Run, String>,
    /// The runs with the ball's circle given.
    pub given: Vec<Run>,
}

impl Measured {
    /// Median seconds and peak bytes of the runs with the circle given.
    pub fn given_medians(&self) -> (f64, f64) {
        let seconds: Vec<f64> = self.given.iter().map(|r| r.seconds).collect();
        let peaks: Vec<f64> = self.given.iter().filter_map(|r| r.peak_bytes).collect();
        (
            median(&seconds).unwrap_or(f64::NAN),
            median(&peaks).unwrap_or(f64::NAN),
        )
    }
}

/// Render the set into `tmp`, calibrate it once with the outline found automatically, then
/// `runs` times with the ball's true circle given.
pub(super) fn run(runs: usize, tmp: &Path) -> anyhow::Result<Measured> {
    let mut set = ChromeSet::standard(8, 11);
    ensure!(
        set.lights.len() == IMAGES,
        "the standard set has {IMAGES} lights"
    );
    // Pixel centres at integers: a pixel's centre x maps to k (x + ½) − ½.
    let k = NATIVE as f64;
    set.width *= NATIVE;
    set.height *= NATIVE;
    set.centre = set.centre.map(|v| k * (v + 0.5) - 0.5);
    set.radius *= k;
    let dir = tmp.join("calibration");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    eprintln!(
        "bench: rendering {IMAGES} chrome-ball images and enlarging them to {WIDTH} × {HEIGHT}"
    );
    let up = WIDTH as f64 / set.width as f64;
    for (i, plane) in set.render().iter().enumerate() {
        let (h, w) = plane.dim();
        let small: GrayImage = ImageBuffer::from_fn(w as u32, h as u32, |x, y| {
            Luma([plane[[y as usize, x as usize]] as u8])
        });
        let large = imageops::resize(&small, WIDTH, HEIGHT, imageops::FilterType::Triangle);
        let path = dir.join(format!("ball{:02}.jpg", i + 1));
        large
            .save(&path)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let circle = [
        up * (set.centre[0] + 0.5) - 0.5,
        up * (set.centre[1] + 0.5) - 0.5,
        up * set.radius,
    ];
    let child = Child {
        exe: std::env::current_exe().context("finding this binary")?,
        dir: &dir,
        out: tmp.join("calibration-lights.csv"),
        log: tmp.join("calibrate.log"),
        set: &set,
    };
    let automatic = child.calibrate(None);
    match &automatic {
        Ok(r) => eprintln!(
            "bench: calibration, outline found automatically: {}",
            r.shown()
        ),
        Err(e) => eprintln!("bench: calibration, outline found automatically: {e:#}"),
    }
    let mut given = Vec::new();
    for run in 0..runs {
        let r = child.calibrate(Some(circle))?;
        eprintln!(
            "bench: calibration run {}/{runs}, circle given: {}",
            run + 1,
            r.shown()
        );
        given.push(r);
    }
    std::fs::remove_dir_all(&dir).with_context(|| format!("removing {}", dir.display()))?;
    Ok(Measured {
        megapixels: (WIDTH * HEIGHT) as f64 / 1e6,
        images: IMAGES,
        automatic: automatic.map_err(|e| format!("{e:#}")),
        given,
    })
}

/// One calibration's figures.
pub(super) struct Run {
    pub seconds: f64,
    pub peak_bytes: Option<f64>,
    /// Mean and max angle between the calibrated and the true lights, degrees.
    pub mean_deg: f64,
    pub max_deg: f64,
}

impl Run {
    fn shown(&self) -> String {
        format!(
            "{:.2} s, peak RSS {}, lights {:.3}° mean, {:.3}° max",
            self.seconds,
            self.peak_bytes
                .map_or("–".into(), |p| format!("{:.0} MB", p / memory::MB)),
            self.mean_deg,
            self.max_deg
        )
    }
}

/// `photostereo calibrate` on the set, as a child process.
struct Child<'a> {
    exe: PathBuf,
    dir: &'a Path,
    out: PathBuf,
    log: PathBuf,
    set: &'a ChromeSet,
}

impl Child<'_> {
    /// Calibrate, with `circle` (cx, cy, r) given or the outline found; an error says what
    /// the child said.
    fn calibrate(&self, circle: Option<[f64; 3]>) -> anyhow::Result<Run> {
        let stderr = std::fs::File::create(&self.log).context("creating the child's log")?;
        let mut cmd = Command::new(&self.exe);
        cmd.arg("calibrate")
            .arg(self.dir)
            .arg("--out")
            .arg(&self.out);
        if let Some([x, y, r]) = circle {
            cmd.arg("--circle").arg(format!("{x},{y},{r}"));
        }
        let start = Instant::now();
        let child = cmd
            .stdout(Stdio::null())
            .stderr(stderr)
            .spawn()
            .context("starting `photostereo calibrate`")?;
        let (status, peak_bytes) = memory::wait_with_peak(child).context("waiting for it")?;
        let seconds = start.elapsed().as_secs_f64();
        if !status.success() {
            let said = std::fs::read_to_string(&self.log).unwrap_or_default();
            anyhow::bail!("`photostereo calibrate` failed ({status}): {}", said.trim());
        }
        let (mean_deg, max_deg) = errors(&self.out, self.set)?;
        Ok(Run {
            seconds,
            peak_bytes,
            mean_deg,
            max_deg,
        })
    }
}

/// Mean and max angle between the light table at `path` (in image order) and the set's
/// true lights, degrees.
fn errors(path: &Path, set: &ChromeSet) -> anyhow::Result<(f64, f64)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let lights = photostereo::core::lights::parse(&text)?;
    ensure!(
        lights.len() == set.lights.len(),
        "{} lights calibrated for {} images",
        lights.len(),
        set.lights.len()
    );
    let angles: Vec<f64> = (lights.iter().zip(&set.lights))
        .map(|(l, b)| {
            let a = l.direction;
            let cos = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0);
            cos.acos().to_degrees()
        })
        .collect();
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    Ok((mean, angles.iter().copied().fold(0.0, f64::max)))
}
