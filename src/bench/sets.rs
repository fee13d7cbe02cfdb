//! The bench's image sets: one rendered sphere per size, and the record of everything
//! measured on it.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use photostereo::core::synth;

use super::stats::median;

/// Render the sphere at each size under `lights` lights into `tmp/set-<size>`.
pub(super) fn render(
    sizes: &[usize],
    lights: usize,
    tmp: &Path,
) -> anyhow::Result<Vec<SizeResult>> {
    let directions = synth::light_rings(lights, 10.0, 60.0);
    let mut sets = Vec::new();
    for &size in sizes {
        let dir = tmp.join(format!("set-{size}"));
        let start = Instant::now();
        synth::write_set(
            &dir,
            &synth::Scene::sphere(size),
            &directions,
            &synth::Capture::default(),
        )
        .with_context(|| format!("rendering the {size}² set"))?;
        eprintln!(
            "bench: rendered {size}² × {lights} in {:.1} s",
            start.elapsed().as_secs_f64()
        );
        sets.push(SizeResult::new(size, lights, dir));
    }
    Ok(sets)
}

/// Stages the pipeline reports, in order (decode is timed here).
pub(super) const STAGES: [&str; 5] = ["solve", "mask", "integrate", "outputs", "mesh"];

/// Everything measured for one size.
pub(super) struct SizeResult {
    pub(super) size: usize,
    pub(super) lights: usize,
    pub(super) dir: PathBuf,
    /// `intake::load_dir` alone.
    pub(super) decode_only_ms: Vec<f64>,
    /// `load_dir` inside the full job.
    pub(super) job_decode_ms: Vec<f64>,
    /// `load_dir` + `pipeline::run`.
    pub(super) full_ms: Vec<f64>,
    /// The same with every artifact written (`"outputs": ["all"]`).
    pub(super) all_ms: Vec<f64>,
    /// Per stage of [`STAGES`], one entry per run.
    pub(super) stage_ms: Vec<Vec<f64>>,
    /// Full minus decode minus the wall time of the reported stages, per run.
    pub(super) other_ms: Vec<f64>,
    /// VmHWM after each full job (bytes), when it could be reset before it.
    pub(super) peak_bytes: Vec<f64>,
    /// VmRSS just before each full job (bytes).
    pub(super) base_bytes: Vec<f64>,
    /// VmHWM minus VmRSS before, per full job (bytes).
    pub(super) growth_bytes: Vec<f64>,
    /// Peak RSS of the default job in a process of its own, per run (bytes).
    pub(super) alone_peak_bytes: Vec<f64>,
    /// First byte of the upload until the job reads `succeeded`.
    pub(super) http_ms: Vec<f64>,
    /// First byte of the upload until the 202.
    pub(super) upload_ms: Vec<f64>,
    /// Process VmHWM over each HTTP job (server and client together).
    pub(super) http_peak_bytes: Vec<f64>,
    /// This process's CPU time over each HTTP job (server and client).
    pub(super) http_cpu_ms: Vec<f64>,
    /// The same HTTP job on the PostgreSQL + S3 server (`--database-url`, `--store`):
    /// until `succeeded`, until the 202, this process's CPU time, and that of
    /// `--server-pids`.
    pub(super) shared_http_ms: Vec<f64>,
    pub(super) shared_upload_ms: Vec<f64>,
    pub(super) shared_cpu_ms: Vec<f64>,
    pub(super) shared_servers_cpu_ms: Vec<f64>,
    /// `integrate` alone with `poisson`, `frankot-chellappa` and `robust-poisson`, per run.
    pub(super) poisson_ms: Vec<f64>,
    pub(super) fc_ms: Vec<f64>,
    pub(super) robust_ms: Vec<f64>,
    /// The l2 job and the default job (decode + `pipeline::run`), run alternately.
    pub(super) l2_job_ms: Vec<f64>,
    pub(super) default_job_ms: Vec<f64>,
}

impl SizeResult {
    fn new(size: usize, lights: usize, dir: PathBuf) -> Self {
        Self {
            size,
            lights,
            dir,
            decode_only_ms: Vec::new(),
            job_decode_ms: Vec::new(),
            full_ms: Vec::new(),
            all_ms: Vec::new(),
            stage_ms: vec![Vec::new(); STAGES.len()],
            other_ms: Vec::new(),
            peak_bytes: Vec::new(),
            base_bytes: Vec::new(),
            growth_bytes: Vec::new(),
            alone_peak_bytes: Vec::new(),
            http_ms: Vec::new(),
            upload_ms: Vec::new(),
            http_peak_bytes: Vec::new(),
            http_cpu_ms: Vec::new(),
            shared_http_ms: Vec::new(),
            shared_upload_ms: Vec::new(),
            shared_cpu_ms: Vec::new(),
            shared_servers_cpu_ms: Vec::new(),
            poisson_ms: Vec::new(),
            fc_ms: Vec::new(),
            robust_ms: Vec::new(),
            l2_job_ms: Vec::new(),
            default_job_ms: Vec::new(),
        }
    }

    pub(super) fn pixel_images(&self) -> f64 {
        (self.size * self.size * self.lights) as f64
    }

    pub(super) fn stack_bytes(&self) -> f64 {
        self.pixel_images() * 2.0
    }

    pub(super) fn image_names(&self) -> Vec<String> {
        (1..=self.lights).map(|i| format!("im{i}.png")).collect()
    }

    /// Full-job time per pixel-image, ns.
    pub(super) fn ns_per_pixel_image(&self) -> Option<f64> {
        median(&self.full_ms).map(|ms| ms * 1e6 / self.pixel_images())
    }
}
