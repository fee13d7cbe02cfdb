//! `--light-sweep`: the default job at a fixed size over a range of light counts, each run
//! as `photostereo reconstruct` in a process of its own, so that each peak resident size
//! is that job's alone (read from `wait4`), and the time per pixel-image: of the whole
//! job, and of each added image (the step in the job's time from one light count to the
//! next, over the pixel-images added). The job's stages per pixel cost the same whatever
//! the image count, so its whole time per pixel-image falls as images are added; the
//! added images' cost is the one that must stay flat.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail};
use photostereo::core::progress::Stage;
use photostereo::core::synth;

use super::args::SweepScene;
use super::memory::{reset_peak, status_bytes, wait_with_peak};
use super::stats::{median, ms};

/// One point of the sweep: a size and a light count, and what each run measured.
pub(super) struct Point {
    pub(super) size: usize,
    pub(super) lights: usize,
    pub(super) ms: Vec<f64>,
    /// Of each run: the stages whose work is per pixel (mask, integration with the
    /// pictures beside it, mesh), from its result.json.
    pub(super) per_pixel_ms: Vec<f64>,
    pub(super) peak_bytes: Vec<f64>,
    /// The same job by the `--against` binary, run alternately with this one's.
    pub(super) against_ms: Vec<f64>,
    pub(super) against_peak_bytes: Vec<f64>,
}

impl Point {
    /// Nanoseconds per pixel and image of a run of `ms`.
    pub(super) fn ns_per_pixel_image(&self, ms: f64) -> f64 {
        ms * 1e6 / (self.size * self.size * self.lights) as f64
    }

    /// Nanoseconds per pixel-image of the images this point has beyond `before`: the
    /// step between the two points' median times over the pixel-images it adds.
    pub(super) fn ns_per_added_pixel_image(&self, before: &Point) -> Option<f64> {
        let added = self.lights.checked_sub(before.lights).filter(|&n| n > 0)?;
        let step = median(&self.ms)? - median(&before.ms)?;
        Some(step * 1e6 / (self.size * self.size * added) as f64)
    }
}

/// Render each set in turn, run it `runs` times, and remove it before the next. With
/// `against`, each run of this binary is paired with one of that binary, which goes
/// first every other round, so that a change in the machine's load hits both alike.
pub(super) fn run(
    sizes: &[usize],
    counts: &[usize],
    runs: usize,
    against: Option<&Path>,
    (options, scene): (&[String], SweepScene),
    tmp: &Path,
) -> anyhow::Result<Vec<Point>> {
    let this = std::env::current_exe().context("finding this binary")?;
    let mut points = Vec::new();
    for &size in sizes {
        for &lights in counts {
            let dir = tmp.join(format!("sweep-{size}-{lights}"));
            let directions = synth::light_rings(lights, 10.0, 60.0);
            let (surface, capture) = match scene {
                SweepScene::Sphere => (synth::Scene::sphere(size), synth::Capture::default()),
                SweepScene::Glossy => (synth::Scene::dark_sphere(size), synth::glossy_coat()),
            };
            synth::write_set(&dir, &surface, &directions, &capture)
                .with_context(|| format!("rendering the {size}² × {lights} set"))?;
            drop(surface);
            let mut point = Point {
                size,
                lights,
                ms: Vec::new(),
                per_pixel_ms: Vec::new(),
                peak_bytes: Vec::new(),
                against_ms: Vec::new(),
                against_peak_bytes: Vec::new(),
            };
            let out = tmp.join("sweep-out");
            let shown = |p: Option<f64>| p.map_or("–".into(), |p| format!("{:.0} MB", p / 1e6));
            for run in 0..runs {
                let mut order = vec![(this.as_path(), false)];
                if let Some(other) = against {
                    order.push((other, true));
                    if run % 2 == 1 {
                        order.reverse();
                    }
                }
                for (exe, is_against) in order {
                    let Run {
                        took,
                        per_pixel,
                        peak,
                    } = alone(exe, &dir, &out, options)?;
                    eprintln!(
                        "bench: sweep {size}² × {lights} run {}/{runs}{}: {took:.0} ms, peak RSS {}",
                        run + 1,
                        if is_against { " (--against)" } else { "" },
                        shown(peak),
                    );
                    if is_against {
                        point.against_ms.push(took);
                        point.against_peak_bytes.extend(peak);
                    } else {
                        point.ms.push(took);
                        point.per_pixel_ms.push(per_pixel);
                        point.peak_bytes.extend(peak);
                    }
                }
            }
            std::fs::remove_dir_all(&dir).with_context(|| format!("removing {}", dir.display()))?;
            points.push(point);
        }
    }
    Ok(points)
}

/// What one `reconstruct` process took.
struct Run {
    /// Wall time, ms.
    took: f64,
    /// Its stages per pixel, ms ([`per_pixel_ms`]).
    per_pixel: f64,
    /// Peak resident size, bytes.
    peak: Option<f64>,
}

/// One run of `exe reconstruct dir options…`. The child's `ru_maxrss` starts at the
/// parent's peak, so that is reset first and a child peak no higher than the parent's is
/// not reported.
fn alone(exe: &Path, dir: &Path, out: &Path, options: &[String]) -> anyhow::Result<Run> {
    photostereo::core::heap::release_free_heap();
    let reset = reset_peak();
    let start = Instant::now();
    let child = std::process::Command::new(exe)
        .arg("reconstruct")
        .arg(dir)
        .arg("--out")
        .arg(out)
        .args(options)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .with_context(|| format!("starting `{} reconstruct`", exe.display()))?;
    let (status, peak) = wait_with_peak(child).context("waiting for `photostereo reconstruct`")?;
    let took = ms(start.elapsed());
    if !status.success() {
        bail!(
            "`photostereo reconstruct` on {} failed ({status})",
            dir.display()
        );
    }
    let report = std::fs::read(out.join("result.json")).context("reading result.json")?;
    let per_pixel = per_pixel_ms(&report)?;
    std::fs::remove_dir_all(out).with_context(|| format!("removing {}", out.display()))?;
    let parent = status_bytes("VmHWM").filter(|_| reset);
    Ok(Run {
        took,
        per_pixel,
        peak: match (peak, parent) {
            (Some(child), Some(parent)) if child > parent => Some(child),
            _ => None,
        },
    })
}

/// The wall time of a job's stages per pixel, from its result.json's `timings_ms`: mask,
/// then integration and the pictures written beside it (both timed from one start, so the
/// longer of the two), then mesh.
fn per_pixel_ms(report: &[u8]) -> anyhow::Result<f64> {
    #[derive(serde::Deserialize)]
    struct Report {
        timings_ms: Vec<Timing>,
    }
    #[derive(serde::Deserialize)]
    struct Timing {
        stage: String,
        ms: f64,
    }
    let report: Report = serde_json::from_slice(report).context("parsing result.json")?;
    let of = |stage: Stage| {
        (report.timings_ms.iter())
            .filter(|t| t.stage == stage.as_str())
            .map(|t| t.ms)
            .sum::<f64>()
    };
    Ok(of(Stage::Mask) + of(Stage::Integrate).max(of(Stage::Outputs)) + of(Stage::Mesh))
}
