//! Timed core runs on a rendered set: integration alone, the full job (decode +
//! `pipeline::run`) with its peak memory, and the same job in a child process.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail, ensure};
use photostereo::core::heap::release_free_heap;
use photostereo::core::intake::{self, Limits};
use photostereo::core::options::{Integration, Solver};
use photostereo::core::{Options, integrate, outputs, pipeline, stream, synth};

use super::memory::{MB, reset_peak, status_bytes, wait_with_peak};
use super::sets::{STAGES, SizeResult};
use super::stats::ms;

/// The sphere's exact gradients and mask, the input of the integration-only timings.
pub(super) struct Gradients {
    p: ndarray::Array2<f32>,
    q: ndarray::Array2<f32>,
    mask: ndarray::Array2<bool>,
}

impl Gradients {
    pub(super) fn of_sphere(size: usize) -> Self {
        let scene = synth::Scene::sphere(size);
        let normals = scene.normals.mapv(|v| v as f32);
        let (p, q) = integrate::gradients(&normals, &scene.mask);
        Self {
            p,
            q,
            mask: scene.mask,
        }
    }
}

/// Time mask-aware Poisson against Frankot–Chellappa (issue 7: at most 3 × at 2048²), and
/// the re-weighted `robust-poisson` (five Poisson solves, each after the first warm-started).
pub(super) fn integration_run(set: &mut SizeResult, g: &Gradients) {
    for (method, times) in [
        (Integration::Poisson, &mut set.poisson_ms),
        (Integration::FrankotChellappa, &mut set.fc_ms),
        (Integration::RobustPoisson, &mut set.robust_ms),
    ] {
        let start = Instant::now();
        let z = integrate::integrate(&g.p, &g.q, &g.mask, method);
        times.push(ms(start.elapsed()));
        std::hint::black_box(z);
    }
}

/// One core run: `load_dir` alone, then the full job with its peak memory.
pub(super) fn core_run(
    set: &mut SizeResult,
    run: usize,
    runs: usize,
    tmp: &Path,
) -> anyhow::Result<()> {
    let limits = Limits::default();
    release_free_heap();
    let start = Instant::now();
    let decoded = intake::load_dir(&set.dir, intake::DirMask::Folder, &limits)
        .with_context(|| format!("decoding the {}² set", set.size))?;
    let decode_only = ms(start.elapsed());
    ensure!(
        decoded.width == set.size && decoded.height == set.size,
        "decoded {}×{}, rendered {}²",
        decoded.width,
        decoded.height,
        set.size
    );
    drop(decoded);

    let job = timed_job(
        set,
        &Options::default(),
        &tmp.join(format!("out-{}-{run}", set.size)),
    )?;
    let every = Options {
        outputs: Some(vec![outputs::ALL.to_string()]),
        ..Options::default()
    };
    let all = timed_job(set, &every, &tmp.join(format!("all-{}-{run}", set.size)))?;
    let alone = alone_peak(set, &tmp.join(format!("alone-{}-{run}", set.size)))?;

    let stages = STAGES.map(|stage| {
        (job.report.timings_ms.iter())
            .filter(|t| t.stage == stage)
            .map(|t| t.ms)
            .sum::<f64>()
    });
    for (i, t) in stages.iter().enumerate() {
        set.stage_ms[i].push(*t);
    }
    set.decode_only_ms.push(decode_only);
    set.job_decode_ms.push(job.decode_ms);
    set.full_ms.push(job.full_ms);
    set.all_ms.push(all.full_ms);
    set.other_ms
        .push((job.full_ms - job.decode_ms - wall_of_stages(stages)).max(0.0));
    for j in [&job, &all] {
        if let (Some(p), Some(b)) = (j.peak, j.base) {
            set.peak_bytes.push(p);
            set.base_bytes.push(b);
            set.growth_bytes.push(p - b);
        }
    }
    set.alone_peak_bytes.extend(alone);
    let peak = |j: &Job| {
        j.peak
            .map_or(String::new(), |p| format!(", peak RSS {:.0} MB", p / MB))
    };
    eprintln!(
        "bench: core {}² run {}/{runs}: decode {decode_only:.0} ms, full job {:.0} ms{}, \
         every artifact {:.0} ms{}",
        set.size,
        run + 1,
        job.full_ms,
        peak(&job),
        all.full_ms,
        peak(&all),
    );
    Ok(())
}

/// Issue 18's speed check: the l2 job and the default job on the same set, one after the
/// other so that a change in the machine's load hits both alike. Which goes first swaps
/// every round, so that neither always runs on the heap the other left.
pub(super) fn default_against_l2_run(
    set: &mut SizeResult,
    run: usize,
    runs: usize,
    tmp: &Path,
) -> anyhow::Result<()> {
    let job = |set: &SizeResult, opts: &Options, name: &str| {
        timed_job(set, opts, &tmp.join(format!("{name}-{}-{run}", set.size)))
    };
    let (l2, default) = if run.is_multiple_of(2) {
        let l2 = job(set, &l2_job(), "l2")?;
        (l2, job(set, &Options::default(), "default")?)
    } else {
        let default = job(set, &Options::default(), "default")?;
        (job(set, &l2_job(), "l2")?, default)
    };
    set.l2_job_ms.push(l2.full_ms);
    set.default_job_ms.push(default.full_ms);
    eprintln!(
        "bench: {}² run {}/{runs}: the l2 job {:.0} ms, the default job {:.0} ms",
        set.size,
        run + 1,
        l2.full_ms,
        default.full_ms
    );
    Ok(())
}

/// The l2 job: plain least squares and Poisson integration, the default job before issue
/// 18, spelled out so that it stays the yardstick when `Options::default()` changes.
fn l2_job() -> Options {
    Options {
        solver: Solver::L2,
        integration: Integration::Poisson,
        ..Options::default()
    }
}

/// One timed core job: decode and `pipeline::run` into `out` (removed afterwards).
struct Job {
    decode_ms: f64,
    full_ms: f64,
    report: photostereo::core::reconstruction::Report,
    /// VmHWM over the job and VmRSS before it (bytes), when the peak could be reset.
    peak: Option<f64>,
    base: Option<f64>,
}

fn timed_job(set: &SizeResult, opts: &Options, out: &Path) -> anyhow::Result<Job> {
    let limits = Limits::default();
    release_free_heap();
    let base = status_bytes("VmRSS");
    let reset = reset_peak();
    let start = Instant::now();
    // The decoded images go beside the output, as the CLI's do.
    let scratch = out.parent().unwrap_or(out);
    let decoded = stream::open_dir(&set.dir, intake::DirMask::Folder, &limits, scratch)
        .with_context(|| format!("decoding the {}² set", set.size))?;
    let decode_ms = ms(start.elapsed());
    let report = pipeline::run(decoded, opts, out, &mut photostereo::core::RunToEnd)
        .with_context(|| format!("reconstructing the {}² set", set.size))?;
    let full_ms = ms(start.elapsed());
    let peak = status_bytes("VmHWM").filter(|_| reset);
    std::fs::remove_dir_all(out).with_context(|| format!("removing {}", out.display()))?;
    Ok(Job {
        decode_ms,
        full_ms,
        report,
        peak,
        base: base.filter(|_| reset),
    })
}

/// Peak resident size (bytes) of the default job run as `photostereo reconstruct` (this
/// binary) in a process of its own, into `out` (removed afterwards). The bench process's
/// own VmHWM over a job also counts what its in-process server and earlier runs left
/// resident even after `malloc_trim` (108–160 MB seen before a 2048² job, in glibc's
/// thread arenas, which later jobs partly reuse).
///
/// Linux starts a child's `ru_maxrss` at the peak of the memory it was started from (the
/// parent's, with `vfork`), so the parent's peak is reset to its current size first, and
/// a child peak no higher than the parent's is reported as `None` (not measurable here;
/// only small sets, whose job needs less than the bench holds).
fn alone_peak(set: &SizeResult, out: &Path) -> anyhow::Result<Option<f64>> {
    let exe = std::env::current_exe().context("finding this binary")?;
    let log = out.with_extension("log");
    release_free_heap();
    let reset = reset_peak();
    let child = std::process::Command::new(exe)
        .arg("reconstruct")
        .arg(&set.dir)
        .arg("--out")
        .arg(out)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).with_context(|| format!("creating {}", log.display()))?)
        .spawn()
        .context("starting `photostereo reconstruct`")?;
    let (status, peak) = wait_with_peak(child).context("waiting for `photostereo reconstruct`")?;
    if !status.success() {
        let said = std::fs::read_to_string(&log).unwrap_or_default();
        bail!(
            "`photostereo reconstruct` on the {}² set failed ({status}): {}",
            set.size,
            said.trim()
        );
    }
    std::fs::remove_dir_all(out).with_context(|| format!("removing {}", out.display()))?;
    std::fs::remove_file(&log).with_context(|| format!("removing {}", log.display()))?;
    // Only a child peak above the parent's can be the child's own.
    let parent = status_bytes("VmHWM").filter(|_| reset);
    Ok(match (peak, parent) {
        (Some(child), Some(parent)) if child > parent => Some(child),
        _ => None,
    })
}

/// Wall time the stages of [`STAGES`] cover: integrate and outputs start together and
/// overlap, so the longer of the two counts.
fn wall_of_stages([solve, mask, integrate, outputs, mesh]: [f64; 5]) -> f64 {
    solve + mask + integrate.max(outputs) + mesh
}
