//! `--light-sweep`: the default job at a fixed size over a range of light counts, each run
//! as `photostereo reconstruct` in a process of its own, so that each peak resident size
//! is that job's alone (read from `wait4`), and the time per pixel-image.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail};
use photostereo::core::synth;

use super::memory::{reset_peak, status_bytes, wait_with_peak};
use super::stats::ms;

/// One point of the sweep: a size and a light count, and what each run measured.
pub(super) struct Point {
    pub(super) size: usize,
    pub(super) lights: usize,
    pub(super) ms: Vec<f64>,
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
}

/// Render each set in turn, run it `runs` times, and remove it before the next. With
/// `against`, each run of this binary is paired with one of that binary, which goes
/// first every other round, so that a change in the machine's load hits both alike.
pub(super) fn run(
    sizes: &[usize],
    counts: &[usize],
    runs: usize,
    against: Option<&Path>,
    options: &[String],
    tmp: &Path,
) -> anyhow::Result<Vec<Point>> {
    let this = std::env::current_exe().context("finding this binary")?;
    let mut points = Vec::new();
    for &size in sizes {
        for &lights in counts {
            let dir = tmp.join(format!("sweep-{size}-{lights}"));
            let directions = synth::light_rings(lights, 10.0, 60.0);
            let scene = synth::Scene::sphere(size);
            synth::write_set(&dir, &scene, &directions, &synth::Capture::default())
                .with_context(|| format!("rendering the {size}² × {lights} set"))?;
            drop(scene);
            let mut point = Point {
                size,
                lights,
                ms: Vec::new(),
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
                    let (took, peak) = alone(exe, &dir, &out, options)?;
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

/// Wall time (ms) and peak resident size (bytes) of `exe reconstruct dir options…`.
/// The child's `ru_maxrss` starts at the parent's peak, so that is reset first and a
/// child peak no higher than the parent's is not reported.
fn alone(
    exe: &Path,
    dir: &Path,
    out: &Path,
    options: &[String],
) -> anyhow::Result<(f64, Option<f64>)> {
    photostereo::service::release_free_heap();
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
    std::fs::remove_dir_all(out).with_context(|| format!("removing {}", out.display()))?;
    let parent = status_bytes("VmHWM").filter(|_| reset);
    Ok((
        took,
        match (peak, parent) {
            (Some(child), Some(parent)) if child > parent => Some(child),
            _ => None,
        },
    ))
}
