//! `photostereo bench`: render synthetic sets, time the core and (optionally) the HTTP
//! service on them in this one process, and print the figures as Markdown tables next to
//! the project's performance targets.
//!
//! Everything lives in a temporary directory that is removed at the end (also on errors).
//! The HTTP side is a small HTTP/1.1 client written here on `tokio::net::TcpStream`
//! (multipart uploads streamed from disk, keep-alive status requests); it only ever talks
//! to the in-process server on 127.0.0.1, and every network wait has a timeout.

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, anyhow, bail, ensure};
use clap::Args;
use photostereo::core::intake::{self, LIGHTS_FILE, Limits};
use photostereo::core::options::Integration;
use photostereo::core::{Options, integrate, outputs, pipeline, synth};
use photostereo::service::{AppState, Config, release_free_heap, serve_with};
use serde_json::Value;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};

/// Time, memory and HTTP figures on synthetic data sets (see the README's Performance).
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Square image sizes in pixels, comma-separated (up to 8192; 5120² is a 26-megapixel camera).
    #[arg(long, value_delimiter = ',', default_value = "512,1024,2048")]
    pub sizes: Vec<usize>,
    /// Lights (= 16-bit PNG images) per data set.
    #[arg(long, default_value_t = 24)]
    pub lights: usize,
    /// Runs of each measurement; the tables show medians (peak memory: the largest).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// Also submit every set to an in-process server over HTTP and time it.
    #[arg(long)]
    pub http: bool,
    /// Also time status requests while every server worker is busy with a big job.
    #[arg(long)]
    pub load: bool,
    /// Status requests sent by --load.
    #[arg(long, default_value_t = 1000)]
    pub requests: usize,
    /// Keep-alive connections the --load status requests are spread over.
    #[arg(long, default_value_t = 4)]
    pub connections: usize,
    /// Where to create the temporary directory [default: the system's temp dir].
    #[arg(long)]
    pub tmp_dir: Option<PathBuf>,
}

/// Polling interval while waiting for a job over HTTP.
const POLL_EVERY: Duration = Duration::from_millis(10);
/// Longest one request (or one upload) may take.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);
const UPLOAD_TIMEOUT: Duration = Duration::from_secs(600);
/// Longest one job may take over HTTP before the bench gives up.
const JOB_TIMEOUT: Duration = Duration::from_secs(1800);
/// Largest response body read (status JSON is a few kB).
const MAX_BODY: usize = 16 << 20;
const MB: f64 = 1e6;

// The targets of issue 7.
const TARGET_FULL_OVER_DECODE: f64 = 1.5;
const TARGET_PEAK_MB: f64 = 480.0;
const TARGET_HTTP_OVER_CORE: f64 = 1.15;
const TARGET_LINEARITY: f64 = 0.25;
const TARGET_STATUS_P99_MS: f64 = 50.0;
const TARGET_POISSON_OVER_FC: f64 = 3.0;
const TARGET_SIZE: usize = 2048;

/// Stages the pipeline reports, in order (decode is timed here).
const STAGES: [&str; 5] = ["solve", "mask", "integrate", "outputs", "mesh"];

pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    check_args(&args)?;
    let parent = match &args.tmp_dir {
        Some(p) => p.clone(),
        None => std::env::temp_dir(),
    };
    let tmp = TempDir::new(&parent)?;
    eprintln!("bench: working in {}", tmp.0.display());

    let machine = machine();
    let load_at_start = load_average();

    let lights = synth::light_rings(args.lights, 10.0, 60.0);
    let mut sets = Vec::new();
    for &size in &args.sizes {
        let dir = tmp.0.join(format!("set-{size}"));
        let start = Instant::now();
        synth::write_set(
            &dir,
            &synth::Scene::sphere(size),
            &lights,
            &synth::Capture::default(),
        )
        .with_context(|| format!("rendering the {size}² set"))?;
        eprintln!(
            "bench: rendered {size}² × {} in {:.1} s",
            args.lights,
            start.elapsed().as_secs_f64()
        );
        sets.push(SizeResult::new(size, args.lights, dir));
    }

    let server = if args.http || args.load {
        Some(Server::start(&args, &sets, &tmp.0)?)
    } else {
        None
    };
    let outcome = measure(&args, &mut sets, server.as_ref(), &tmp.0);
    if let Some(server) = server {
        server.stop();
    }
    let load = outcome?;

    let load_at_end = load_average();
    print!(
        "{}",
        tables(
            &args,
            &machine,
            (&load_at_start, &load_at_end),
            &sets,
            load.as_ref()
        )
    );
    Ok(())
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// Core and HTTP runs alternate (core, HTTP, core, HTTP, …) so that a change in the
/// machine's background load hits both alike; then the load test.
fn measure(
    args: &BenchArgs,
    sets: &mut [SizeResult],
    server: Option<&Server>,
    tmp: &Path,
) -> anyhow::Result<Option<LoadResult>> {
    for set in sets.iter_mut() {
        // Before the jobs, and dropped before them, so it stays out of their peak memory.
        let gradients = Gradients::of_sphere(set.size);
        for _ in 0..args.runs {
            integration_run(set, &gradients);
        }
        drop(gradients);
        for run in 0..args.runs {
            core_run(set, run, args.runs, tmp)?;
            if let (true, Some(server)) = (args.http, server) {
                server
                    .rt
                    .block_on(http_run(set, run, args.runs, server.addr))?;
            }
        }
    }
    match (args.load, server, sets.iter().max_by_key(|s| s.size)) {
        (true, Some(server), Some(big)) => server
            .rt
            .block_on(load_test(args, big, server.addr, server.workers))
            .map(Some),
        _ => Ok(None),
    }
}

fn check_args(args: &BenchArgs) -> anyhow::Result<()> {
    ensure!(!args.sizes.is_empty(), "--sizes needs at least one size");
    for &s in &args.sizes {
        ensure!(
            (32..=8192).contains(&s),
            "--sizes: {s} is outside 32..=8192"
        );
    }
    let mut seen = args.sizes.clone();
    seen.sort_unstable();
    seen.dedup();
    ensure!(
        seen.len() == args.sizes.len(),
        "--sizes: a size is repeated"
    );
    ensure!(
        (3..=64).contains(&args.lights),
        "--lights must be 3..=64 (the service takes at most 64 images)"
    );
    ensure!((1..=100).contains(&args.runs), "--runs must be 1..=100");
    ensure!(
        (1..=100_000).contains(&args.requests),
        "--requests must be 1..=100000"
    );
    ensure!(
        (1..=64).contains(&args.connections),
        "--connections must be 1..=64"
    );
    Ok(())
}

/// A directory removed with everything in it when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(parent: &Path) -> anyhow::Result<Self> {
        let stamp = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        let path = parent.join(format!(
            "photostereo-bench-{}-{stamp:x}",
            std::process::id()
        ));
        std::fs::create_dir(&path)
            .with_context(|| format!("creating the temporary directory {}", path.display()))?;
        Ok(Self(path))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_dir_all(&self.0) {
            eprintln!("bench: could not remove {}: {e}", self.0.display());
        }
    }
}

/// Everything measured for one size.
struct SizeResult {
    size: usize,
    lights: usize,
    dir: PathBuf,
    /// `intake::load_dir` alone.
    decode_only_ms: Vec<f64>,
    /// `load_dir` inside the full job.
    job_decode_ms: Vec<f64>,
    /// `load_dir` + `pipeline::run`.
    full_ms: Vec<f64>,
    /// The same with every artifact written (`"outputs": ["all"]`).
    all_ms: Vec<f64>,
    /// Per stage of [`STAGES`], one entry per run.
    stage_ms: Vec<Vec<f64>>,
    /// Full minus decode minus the wall time of the reported stages, per run.
    other_ms: Vec<f64>,
    /// VmHWM after each full job (bytes), when it could be reset before it.
    peak_bytes: Vec<f64>,
    /// VmRSS just before each full job (bytes).
    base_bytes: Vec<f64>,
    /// VmHWM minus VmRSS before, per full job (bytes).
    growth_bytes: Vec<f64>,
    /// Peak RSS of the default job in a process of its own, per run (bytes).
    alone_peak_bytes: Vec<f64>,
    /// First byte of the upload until the job reads `succeeded`.
    http_ms: Vec<f64>,
    /// First byte of the upload until the 202.
    upload_ms: Vec<f64>,
    /// Process VmHWM over each HTTP job (server and client together).
    http_peak_bytes: Vec<f64>,
    /// `integrate` alone with `poisson`, `frankot-chellappa` and `robust-poisson`, per run.
    poisson_ms: Vec<f64>,
    fc_ms: Vec<f64>,
    robust_ms: Vec<f64>,
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
            poisson_ms: Vec::new(),
            fc_ms: Vec::new(),
            robust_ms: Vec::new(),
        }
    }

    fn pixel_images(&self) -> f64 {
        (self.size * self.size * self.lights) as f64
    }

    fn stack_bytes(&self) -> f64 {
        self.pixel_images() * 2.0
    }

    fn image_names(&self) -> Vec<String> {
        (1..=self.lights).map(|i| format!("im{i}.png")).collect()
    }

    /// Full-job time per pixel-image, ns.
    fn ns_per_pixel_image(&self) -> Option<f64> {
        median(&self.full_ms).map(|ms| ms * 1e6 / self.pixel_images())
    }
}

/// Wall time the stages of [`STAGES`] cover: integrate and outputs start together and
/// overlap, so the longer of the two counts.
fn wall_of_stages([solve, mask, integrate, outputs, mesh]: [f64; 5]) -> f64 {
    solve + mask + integrate.max(outputs) + mesh
}

/// One core run: `load_dir` alone, then the full job with its peak memory.
/// The sphere's exact gradients and mask, the input of the integration-only timings.
struct Gradients {
    p: ndarray::Array2<f32>,
    q: ndarray::Array2<f32>,
    mask: ndarray::Array2<bool>,
}

impl Gradients {
    fn of_sphere(size: usize) -> Self {
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
fn integration_run(set: &mut SizeResult, g: &Gradients) {
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

fn core_run(set: &mut SizeResult, run: usize, runs: usize, tmp: &Path) -> anyhow::Result<()> {
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
    let decoded = intake::load_dir(&set.dir, intake::DirMask::Folder, &limits)
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

/// Wait for `child` and read its peak resident size (bytes) from `wait4`'s resource usage.
#[cfg(target_os = "linux")]
fn wait_with_peak(
    child: std::process::Child,
) -> std::io::Result<(std::process::ExitStatus, Option<f64>)> {
    use std::os::unix::process::ExitStatusExt;
    let pid = child.id() as libc::pid_t;
    let mut raw = 0;
    // SAFETY: `rusage` is plain integers, for which all zeros is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: both pointers are to live locals; `pid` is our own child, not yet waited
        // for (`Child` waits only when asked to, and it is not asked).
        let got = unsafe { libc::wait4(pid, &mut raw, 0, &mut usage) };
        if got == pid {
            // Linux reports ru_maxrss in KiB.
            let peak = usage.ru_maxrss as f64 * 1024.0;
            return Ok((std::process::ExitStatus::from_raw(raw), Some(peak)));
        }
        let e = std::io::Error::last_os_error();
        if e.kind() != std::io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn wait_with_peak(
    mut child: std::process::Child,
) -> std::io::Result<(std::process::ExitStatus, Option<f64>)> {
    Ok((child.wait()?, None))
}

/// Reset the process's peak resident size (VmHWM) to its current size (Linux only).
fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// A `kB` field of /proc/self/status, in bytes.
fn status_bytes(key: &str) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status.lines().find_map(|line| {
        let rest = line.strip_prefix(key)?.strip_prefix(':')?;
        let kb: f64 = rest.split_whitespace().next()?.parse().ok()?;
        Some(kb * 1024.0)
    })
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn median(v: &[f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    Some(if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    })
}

/// Nearest-rank percentile of sorted values.
fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = (p / 100.0 * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

fn max_of(v: &[f64]) -> Option<f64> {
    v.iter().copied().reduce(f64::max)
}

/// "N × model, M GiB RAM".
fn machine() -> String {
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let mem = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("MemTotal:"))
                .and_then(|v| v.split_whitespace().next()?.parse::<f64>().ok())
        })
        .map(|kb| format!("{:.1} GiB RAM", kb / (1024.0 * 1024.0)))
        .unwrap_or_else(|| "unknown RAM".into());
    format!(
        "{cores} cores (nproc), {model}, {mem}, {} {}",
        std::env::consts::OS,
        std::env::consts::ARCH
    )
}

// ---------------------------------------------------------------------------------------
// HTTP

/// Status-request latencies under load.
struct LoadResult {
    size: usize,
    workers: usize,
    requests: usize,
    connections: usize,
    latencies_ms: Vec<f64>,
    failed: usize,
    /// Jobs still running when the last status request was answered.
    running_after: usize,
    first_failure: Option<String>,
}

/// The service running in this process on 127.0.0.1:0, on its own tokio runtime.
struct Server {
    rt: tokio::runtime::Runtime,
    addr: SocketAddr,
    workers: usize,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl Server {
    fn start(args: &BenchArgs, sets: &[SizeResult], tmp: &Path) -> anyhow::Result<Self> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the tokio runtime")?;
        let mut config = Config::new(tmp.join("service"));
        config.workers = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        config.min_free_disk = 0;
        config.shutdown_grace = Duration::from_secs(5);
        config.max_images = config.max_images.max(args.lights);
        let largest = sets.iter().map(|s| s.size).max().unwrap_or(0) as u64;
        config.max_pixels = config.max_pixels.max(largest * largest);
        config.max_job_pixels = config
            .max_job_pixels
            .max(largest * largest * args.lights as u64);
        // The bench's own sets (an 8192² × 24 upload passes 2 GiB): the body limit is not
        // what it measures.
        config.max_body_bytes = u64::MAX;
        let workers = config.workers;
        let (addr, stop, task) = rt.block_on(async {
            let state = AppState::open(config)
                .await
                .context("opening the service")?;
            let listener = TcpListener::bind("127.0.0.1:0")
                .await
                .context("binding 127.0.0.1:0")?;
            let addr = listener.local_addr()?;
            let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
            let task = tokio::spawn(serve_with(listener, state, async move {
                let _ = stopped.await;
            }));
            anyhow::Ok((addr, stop, task))
        })?;
        eprintln!("bench: service on http://{addr} with {workers} workers");
        Ok(Self {
            rt,
            addr,
            workers,
            stop,
            task,
        })
    }

    /// Graceful stop (bounded), then the runtime.
    fn stop(self) {
        let Self { rt, stop, task, .. } = self;
        let _ = stop.send(());
        // The timer must be made inside the runtime.
        let stopped =
            rt.block_on(async { tokio::time::timeout(Duration::from_secs(60), task).await });
        match stopped {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => eprintln!("bench: the service stopped with an error: {e:#}"),
            Ok(Err(e)) => eprintln!("bench: the service task failed: {e}"),
            Err(_) => eprintln!("bench: the service did not stop within 60 s"),
        }
        rt.shutdown_timeout(Duration::from_secs(10));
    }
}

/// One HTTP run: upload, poll until succeeded, delete the job.
async fn http_run(
    set: &mut SizeResult,
    run: usize,
    runs: usize,
    addr: SocketAddr,
) -> anyhow::Result<()> {
    release_free_heap();
    let reset = reset_peak();
    let (id, upload, total) = submit_and_wait(addr, set).await?;
    let peak = status_bytes("VmHWM");
    let mut conn = Conn::connect(addr).await?;
    let r = conn.request("DELETE", &job_path(&id)).await?;
    ensure!(r.status == 204, "deleting job {id}: {}", r.describe());
    set.http_ms.push(ms(total));
    set.upload_ms.push(ms(upload));
    if let (true, Some(p)) = (reset, peak) {
        set.http_peak_bytes.push(p);
    }
    eprintln!(
        "bench: HTTP {}² run {}/{runs}: upload {:.0} ms, succeeded after {:.0} ms",
        set.size,
        run + 1,
        ms(upload),
        ms(total)
    );
    Ok(())
}

/// Submit `set` and poll until it succeeded: (job id, upload time, total time), both
/// from the first byte sent.
async fn submit_and_wait(
    addr: SocketAddr,
    set: &SizeResult,
) -> anyhow::Result<(String, Duration, Duration)> {
    let (id, start, upload) = submit(addr, set).await?;
    let job = wait_for(addr, &id, Instant::now() + JOB_TIMEOUT, |s| {
        s == "succeeded"
    })
    .await?;
    let total = start.elapsed();
    let width = job["result"]["width"].as_u64().unwrap_or(0) as usize;
    ensure!(
        width == set.size,
        "job {id} reports width {width}, sent {}²",
        set.size
    );
    Ok((id, upload, total))
}

/// POST /v1/jobs with the set's light table and images, streamed from disk. Returns the
/// job id, when the first byte went out, and how long until the 202.
async fn submit(addr: SocketAddr, set: &SizeResult) -> anyhow::Result<(String, Instant, Duration)> {
    let boundary = format!(
        "photostereo-bench-{:032x}",
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default()
    );
    let mut parts = vec![(
        format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"lights\"; filename=\"{LIGHTS_FILE}\"\r\nContent-Type: text/csv\r\n\r\n"
        ),
        set.dir.join(LIGHTS_FILE),
    )];
    for name in set.image_names() {
        parts.push((
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"images\"; filename=\"{name}\"\r\nContent-Type: image/png\r\n\r\n"
            ),
            set.dir.join(&name),
        ));
    }
    let closing = format!("--{boundary}--\r\n");
    let mut length = closing.len() as u64;
    let mut sizes = Vec::new();
    for (head, path) in &parts {
        let size = tokio::fs::metadata(path)
            .await
            .with_context(|| format!("reading {}", path.display()))?
            .len();
        sizes.push(size);
        length += head.len() as u64 + size + 2;
    }

    let mut conn = Conn::connect(addr).await?;
    let start = Instant::now();
    let sent = tokio::time::timeout(UPLOAD_TIMEOUT, async {
        let head = format!(
            "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nContent-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: {length}\r\n\r\n"
        );
        let w = conn.stream.get_mut();
        w.write_all(head.as_bytes()).await?;
        for ((head, path), size) in parts.iter().zip(&sizes) {
            w.write_all(head.as_bytes()).await?;
            // 1 MiB reads: tokio::io::copy's 8 KiB ones cost a blocking-pool trip each.
            let file = tokio::fs::File::open(path).await?;
            let file = tokio::io::BufReader::with_capacity(1 << 20, file);
            let copied = tokio::io::copy_buf(&mut file.take(*size), w).await?;
            if copied != *size {
                return Err(std::io::Error::other(format!(
                    "{} shrank while being sent",
                    path.display()
                )));
            }
            w.write_all(b"\r\n").await?;
        }
        w.write_all(closing.as_bytes()).await?;
        w.flush().await
    })
    .await;
    let sent = match sent {
        Ok(r) => r,
        Err(_) => bail!(
            "the upload of the {}² set took over {UPLOAD_TIMEOUT:?}",
            set.size
        ),
    };
    if let Err(e) = sent {
        // The server may have answered (and closed) early, e.g. 413: show its answer.
        let answer = match tokio::time::timeout(Duration::from_secs(2), conn.read_response()).await
        {
            Ok(Ok(r)) => format!(" (server said {})", r.describe()),
            _ => String::new(),
        };
        bail!("uploading the {}² set: {e}{answer}", set.size);
    }
    let r = tokio::time::timeout(REQUEST_TIMEOUT, conn.read_response())
        .await
        .map_err(|_| anyhow!("no answer to the upload within {REQUEST_TIMEOUT:?}"))??;
    let upload = start.elapsed();
    ensure!(
        r.status == 202,
        "submitting the {}² set: {}",
        set.size,
        r.describe()
    );
    let job: Value = serde_json::from_slice(&r.body).context("the 202's body")?;
    let id = job["id"]
        .as_str()
        .ok_or_else(|| anyhow!("no id in {job}"))?
        .to_string();
    Ok((id, start, upload))
}

fn job_path(id: &str) -> String {
    format!("/v1/jobs/{id}")
}

/// Poll a job (over one keep-alive connection) until its status satisfies `done`; a job
/// that ends otherwise, or the deadline, is an error.
async fn wait_for(
    addr: SocketAddr,
    id: &str,
    deadline: Instant,
    done: impl Fn(&str) -> bool,
) -> anyhow::Result<Value> {
    let mut conn = Conn::connect(addr).await?;
    let path = job_path(id);
    loop {
        let r = conn.request("GET", &path).await?;
        ensure!(r.status == 200, "GET {path}: {}", r.describe());
        let job: Value = serde_json::from_slice(&r.body).context("a job's JSON")?;
        let status = job["status"].as_str().unwrap_or_default().to_string();
        if done(&status) {
            return Ok(job);
        }
        if matches!(status.as_str(), "succeeded" | "failed" | "cancelled") {
            bail!("job {id} ended {status}: {}", job["error"]);
        }
        if Instant::now() > deadline {
            bail!("job {id} is still {status} at the deadline");
        }
        tokio::time::sleep(POLL_EVERY).await;
        if conn.closed {
            conn = Conn::connect(addr).await?;
        }
    }
}

/// Fill every worker with a job of the largest set, then time status requests.
async fn load_test(
    args: &BenchArgs,
    set: &SizeResult,
    addr: SocketAddr,
    workers: usize,
) -> anyhow::Result<LoadResult> {
    let mut ids = Vec::new();
    let outcome = load_with_jobs(args, set, addr, workers, &mut ids).await;
    // Cancel whatever is still queued or running, and wait (bounded) for it to stop.
    for id in &ids {
        if let Ok(mut c) = Conn::connect(addr).await {
            let _ = c.request("DELETE", &job_path(id)).await;
        }
    }
    let deadline = Instant::now() + Duration::from_secs(120);
    for id in &ids {
        let _ = wait_for(addr, id, deadline, |s| {
            matches!(s, "succeeded" | "failed" | "cancelled")
        })
        .await;
    }
    outcome
}

async fn load_with_jobs(
    args: &BenchArgs,
    set: &SizeResult,
    addr: SocketAddr,
    workers: usize,
    ids: &mut Vec<String>,
) -> anyhow::Result<LoadResult> {
    for _ in 0..workers {
        let (id, _, _) = submit(addr, set).await?;
        ids.push(id);
    }
    let deadline = Instant::now() + Duration::from_secs(300);
    for id in ids.iter() {
        wait_for(addr, id, deadline, |s| s == "running").await?;
    }
    eprintln!(
        "bench: {workers} jobs of {}² running; sending {} status requests over {} connections",
        set.size, args.requests, args.connections
    );

    let per_conn: Vec<usize> = (0..args.connections)
        .map(|c| {
            args.requests / args.connections + usize::from(c < args.requests % args.connections)
        })
        .collect();
    let ids_now: &[String] = ids;
    let clients = per_conn
        .iter()
        .enumerate()
        .map(|(c, &n)| status_client(addr, ids_now, c, n));
    let results = futures_util::future::join_all(clients).await;
    let mut latencies_ms = Vec::new();
    let mut failed = 0;
    let mut first_failure = None;
    for (lat, fails, first) in results {
        latencies_ms.extend(lat);
        failed += fails;
        if first_failure.is_none() {
            first_failure = first;
        }
    }
    let mut running_after = 0;
    let mut conn = Conn::connect(addr).await?;
    for id in ids.iter() {
        let r = conn.request("GET", &job_path(id)).await?;
        let job: Value = serde_json::from_slice(&r.body).unwrap_or_default();
        if job["status"] == "running" {
            running_after += 1;
        }
    }
    latencies_ms.sort_by(f64::total_cmp);
    Ok(LoadResult {
        size: set.size,
        workers,
        requests: args.requests,
        connections: args.connections,
        latencies_ms,
        failed,
        running_after,
        first_failure,
    })
}

/// `n` sequential status requests over one keep-alive connection (reconnecting after a
/// failure): latencies of the successful ones, the failure count, the first failure.
async fn status_client(
    addr: SocketAddr,
    ids: &[String],
    client: usize,
    n: usize,
) -> (Vec<f64>, usize, Option<String>) {
    let mut latencies = Vec::with_capacity(n);
    let mut failed = 0;
    let mut first = None;
    let mut conn: Option<Conn> = None;
    for i in 0..n {
        let path = job_path(&ids[(client + i) % ids.len().max(1)]);
        let start = Instant::now();
        let outcome: anyhow::Result<()> = async {
            if conn.as_ref().is_none_or(|c| c.closed) {
                conn = Some(Conn::connect(addr).await?);
            }
            let c = conn.as_mut().ok_or_else(|| anyhow!("no connection"))?;
            let r = c.request("GET", &path).await?;
            ensure!(r.status == 200, "GET {path}: {}", r.describe());
            Ok(())
        }
        .await;
        match outcome {
            Ok(()) => latencies.push(ms(start.elapsed())),
            Err(e) => {
                failed += 1;
                conn = None;
                first.get_or_insert_with(|| format!("{e:#}"));
            }
        }
    }
    (latencies, failed, first)
}

/// One HTTP/1.1 connection to the bench's server.
struct Conn {
    stream: BufReader<TcpStream>,
    host: String,
    /// The server said `Connection: close` (or the stream failed).
    closed: bool,
}

struct Response {
    status: u16,
    body: Vec<u8>,
}

impl Response {
    fn describe(&self) -> String {
        let body = String::from_utf8_lossy(&self.body);
        let body: String = body.chars().take(300).collect();
        format!("HTTP {} {body}", self.status)
    }
}

impl Conn {
    async fn connect(addr: SocketAddr) -> anyhow::Result<Self> {
        ensure!(addr.ip().is_loopback(), "the bench only talks to loopback");
        let stream = tokio::time::timeout(REQUEST_TIMEOUT, TcpStream::connect(addr))
            .await
            .map_err(|_| anyhow!("connecting to {addr} timed out"))?
            .with_context(|| format!("connecting to {addr}"))?;
        stream.set_nodelay(true)?;
        Ok(Self {
            stream: BufReader::new(stream),
            host: addr.to_string(),
            closed: false,
        })
    }

    /// A request without a body, and its response.
    async fn request(&mut self, method: &str, path: &str) -> anyhow::Result<Response> {
        let exchange = async {
            let head = format!("{method} {path} HTTP/1.1\r\nHost: {}\r\n\r\n", self.host);
            let w = self.stream.get_mut();
            w.write_all(head.as_bytes()).await?;
            w.flush().await?;
            self.read_response().await
        };
        let r = tokio::time::timeout(REQUEST_TIMEOUT, exchange).await;
        match r {
            Ok(Ok(r)) => Ok(r),
            Ok(Err(e)) => {
                self.closed = true;
                Err(e.context(format!("{method} {path}")))
            }
            Err(_) => {
                self.closed = true;
                bail!("{method} {path}: no answer within {REQUEST_TIMEOUT:?}")
            }
        }
    }

    /// Read one response: status line, headers, then a Content-Length or chunked body.
    async fn read_response(&mut self) -> anyhow::Result<Response> {
        let head = self.read_until_blank_line().await?;
        let head = String::from_utf8(head).context("response head is not UTF-8")?;
        let mut lines = head.split("\r\n");
        let status_line = lines.next().unwrap_or_default();
        let status: u16 = status_line
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| anyhow!("bad status line {status_line:?}"))?;
        let mut length = None;
        let mut chunked = false;
        for line in lines.filter(|l| !l.is_empty()) {
            let Some((name, value)) = line.split_once(':') else {
                bail!("bad header line {line:?}");
            };
            let value = value.trim();
            if name.eq_ignore_ascii_case("content-length") {
                length = Some(value.parse::<usize>().context("Content-Length")?);
            } else if name.eq_ignore_ascii_case("transfer-encoding") {
                chunked = value.to_ascii_lowercase().contains("chunked");
            } else if name.eq_ignore_ascii_case("connection") && value.eq_ignore_ascii_case("close")
            {
                self.closed = true;
            }
        }
        let mut body = Vec::new();
        if status == 204 || status == 304 || (100..200).contains(&status) {
            // No body.
        } else if chunked {
            loop {
                let line = self.read_line().await?;
                let size_text = line.split(';').next().unwrap_or_default().trim();
                let size = usize::from_str_radix(size_text, 16)
                    .with_context(|| format!("bad chunk size {size_text:?}"))?;
                if size == 0 {
                    // Trailers, then the blank line.
                    self.skip_trailers().await?;
                    break;
                }
                ensure!(body.len() + size <= MAX_BODY, "response body too large");
                let at = body.len();
                body.resize(at + size, 0);
                self.stream.read_exact(&mut body[at..]).await?;
                let mut crlf = [0u8; 2];
                self.stream.read_exact(&mut crlf).await?;
                ensure!(&crlf == b"\r\n", "chunk not followed by CRLF");
            }
        } else if let Some(n) = length {
            ensure!(n <= MAX_BODY, "response body too large ({n} bytes)");
            body.resize(n, 0);
            self.stream.read_exact(&mut body).await?;
        } else {
            // Delimited by the end of the connection.
            self.closed = true;
            (&mut self.stream)
                .take(MAX_BODY as u64)
                .read_to_end(&mut body)
                .await?;
        }
        Ok(Response { status, body })
    }

    /// Bytes up to and including the first empty line (`\r\n\r\n`), at most 64 KiB.
    async fn read_until_blank_line(&mut self) -> anyhow::Result<Vec<u8>> {
        let mut head: Vec<u8> = Vec::new();
        loop {
            let (used, found) = {
                let buf = self.stream.fill_buf().await?;
                if buf.is_empty() {
                    self.closed = true;
                    bail!("the server closed the connection");
                }
                let from = head.len().saturating_sub(3);
                let before = head.len();
                head.extend_from_slice(buf);
                match head[from..].windows(4).position(|w| w == b"\r\n\r\n") {
                    Some(pos) => {
                        let end = from + pos + 4;
                        head.truncate(end);
                        (end - before, true)
                    }
                    None => (buf.len(), false),
                }
            };
            self.stream.consume(used);
            if found {
                return Ok(head);
            }
            ensure!(head.len() <= 64 << 10, "response head over 64 KiB");
        }
    }

    /// One CRLF-terminated line (without the CRLF), at most 4 KiB.
    async fn read_line(&mut self) -> anyhow::Result<String> {
        let mut line = Vec::new();
        let n = (&mut self.stream)
            .take(4096)
            .read_until(b'\n', &mut line)
            .await?;
        ensure!(
            n > 0 && line.ends_with(b"\n"),
            "truncated line in the response"
        );
        line.pop();
        if line.ends_with(b"\r") {
            line.pop();
        }
        String::from_utf8(line).context("line is not UTF-8")
    }

    /// After the last chunk: trailer lines up to the empty line.
    async fn skip_trailers(&mut self) -> anyhow::Result<()> {
        for _ in 0..100 {
            if self.read_line().await?.is_empty() {
                return Ok(());
            }
        }
        bail!("too many trailer lines")
    }
}

// ---------------------------------------------------------------------------------------
// Output

fn tables(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    sets: &[SizeResult],
    load: Option<&LoadResult>,
) -> String {
    let mut o = String::new();
    let sizes: Vec<String> = args.sizes.iter().map(|s| s.to_string()).collect();
    let _ = writeln!(o, "## photostereo bench\n");
    let _ = writeln!(
        o,
        "- machine: {machine}; load average {load_at_start} at the start, {load_at_end} at \
         the end"
    );
    let _ = writeln!(
        o,
        "- command: `photostereo bench --sizes {} --lights {} --runs {}{}{}`",
        sizes.join(","),
        args.lights,
        args.runs,
        if args.http { " --http" } else { "" },
        if args.load {
            format!(
                " --load --requests {} --connections {}",
                args.requests, args.connections
            )
        } else {
            String::new()
        }
    );
    let _ = writeln!(
        o,
        "- data: `synth::Scene::sphere(size)`, {} lights (`light_rings({}, 10, 60)`), 16-bit \
         gray PNG; default options (the default artifact set); \"every artifact\" = the same \
         job with `\"outputs\": [\"all\"]`; times are medians of {} run(s), peak RSS the \
         largest over both jobs; MB = 10⁶ bytes",
        args.lights, args.lights, args.runs
    );
    let _ = writeln!(
        o,
        "- full job = `intake::load_dir` + `pipeline::run`; decode = `load_dir` alone; peak \
         RSS = the process's VmHWM over the full job (reset through /proc/self/clear_refs), \
         baseline = VmRSS before it; own process = the peak RSS of the same default job run \
         as `photostereo reconstruct` in a child process (wait4's ru_maxrss; – where it is \
         below the bench process's own size, which Linux counts into a child's peak)"
    );
    if args.http {
        let _ = writeln!(
            o,
            "- HTTP = in-process server on 127.0.0.1 (workers = cores), multipart upload \
             streamed from disk, polled every {} ms: first byte sent → `succeeded`; core and \
             HTTP runs alternate",
            POLL_EVERY.as_millis()
        );
    }

    let reference = sets
        .iter()
        .find(|s| s.size == 512)
        .or_else(|| sets.iter().min_by_key(|s| s.size));
    let ref_ns = reference.and_then(|r| r.ns_per_pixel_image());
    let ref_label = reference.map_or("?".into(), |r| format!("{}²", r.size));
    // Linearity is judged only against a smaller set (with 2048² alone the reference is
    // the target itself).
    let smaller = reference.is_some_and(|r| r.size < TARGET_SIZE);

    // Time.
    let _ = writeln!(o, "\n### Time (medians)\n");
    let mut header = format!(
        "| size × lights | decode ms | full job ms | full / decode (≤ {TARGET_FULL_OVER_DECODE} at 2048²) | ns per pixel-image | vs {ref_label} (± {:.0} % at 2048²) | every artifact ms | every artifact / decode |",
        TARGET_LINEARITY * 100.0
    );
    let mut rule = "|---|---:|---:|---:|---:|---:|---:|---:|".to_string();
    if args.http {
        let _ = write!(
            header,
            " HTTP upload ms | HTTP job ms | HTTP / core (≤ {TARGET_HTTP_OVER_CORE}) |"
        );
        rule.push_str("---:|---:|---:|");
    }
    let _ = writeln!(o, "{header}\n{rule}");
    for s in sets {
        let decode = median(&s.decode_only_ms);
        let full = median(&s.full_ms);
        let ratio = zip2(full, decode, |f, d| f / d);
        let ns = s.ns_per_pixel_image();
        let lin = zip2(ns, ref_ns, |a, b| a / b);
        let judged = s.size == TARGET_SIZE;
        let all = median(&s.all_ms);
        let mut row = format!(
            "| {}² × {} | {} | {} | {} | {} | {} | {} | {} |",
            s.size,
            s.lights,
            num(decode, 0),
            num(full, 0),
            with_mark(ratio, 2, judged, |r| r <= TARGET_FULL_OVER_DECODE),
            num(ns, 1),
            with_mark(lin, 2, judged && smaller, linear_enough),
            num(all, 0),
            num(zip2(all, decode, |a, d| a / d), 2),
        );
        if args.http {
            let http = median(&s.http_ms);
            let _ = write!(
                row,
                " {} | {} | {} |",
                num(median(&s.upload_ms), 0),
                num(http, 0),
                with_mark(zip2(http, full, |h, c| h / c), 2, true, |r| r
                    <= TARGET_HTTP_OVER_CORE),
            );
        }
        let _ = writeln!(o, "{row}");
    }

    // Memory.
    let _ = writeln!(o, "\n### Memory (largest over the runs)\n");
    let mut header = format!(
        "| size × lights | 16-bit stack MB | peak RSS MB (≤ {TARGET_PEAK_MB:.0} at 2048² × 24) | baseline RSS MB | peak − baseline MB | own process: peak RSS MB |"
    );
    let mut rule = "|---|---:|---:|---:|---:|---:|".to_string();
    if args.http {
        header.push_str(" peak RSS over the HTTP job MB |");
        rule.push_str("---:|");
    }
    let _ = writeln!(o, "{header}\n{rule}");
    for s in sets {
        let at_target = s.size == TARGET_SIZE && s.lights == 24;
        let mut row = format!(
            "| {}² × {} | {:.1} | {} | {} | {} | {} |",
            s.size,
            s.lights,
            s.stack_bytes() / MB,
            with_mark(max_of(&s.peak_bytes).map(|b| b / MB), 0, at_target, |p| p
                <= TARGET_PEAK_MB),
            num(max_of(&s.base_bytes).map(|b| b / MB), 0),
            num(max_of(&s.growth_bytes).map(|b| b / MB), 0),
            with_mark(
                max_of(&s.alone_peak_bytes).map(|b| b / MB),
                0,
                at_target,
                |p| p <= TARGET_PEAK_MB
            ),
        );
        if args.http {
            let _ = write!(
                row,
                " {} |",
                num(max_of(&s.http_peak_bytes).map(|b| b / MB), 0)
            );
        }
        let _ = writeln!(o, "{row}");
    }

    // Stages.
    let _ = writeln!(o, "\n### Where the full job's time goes (ms, medians)\n");
    let _ = writeln!(
        o,
        "| size | decode | solve | mask | integrate | outputs | mesh | other | full job |"
    );
    let _ = writeln!(o, "|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for s in sets {
        let full = median(&s.full_ms);
        let cell = |v: Option<f64>| match (v, full) {
            (Some(v), Some(f)) if f > 0.0 => format!("{v:.0} ({:.0} %)", 100.0 * v / f),
            _ => num(v, 0),
        };
        let mut row = format!("| {}² | {} |", s.size, cell(median(&s.job_decode_ms)));
        for stage in &s.stage_ms {
            let _ = write!(row, " {} |", cell(median(stage)));
        }
        let _ = write!(row, " {} | {} |", cell(median(&s.other_ms)), num(full, 0));
        let _ = writeln!(o, "{row}");
    }
    let _ = writeln!(
        o,
        "\n(decode = `load_dir` inside the full job; outputs = the pictures that need no \
         heights, written while integrate runs, so the stages can sum to more than the \
         job; mesh = meshes, preview and the height pictures together; other = the rest \
         of the job, outside the longer of integrate and outputs: light check, masking the \
         arrays, the report, result.json)"
    );

    let _ = writeln!(
        o,
        "\n### Integration alone (ms, medians; the sphere's exact gradients)\n"
    );
    let _ = writeln!(
        o,
        "| size | poisson (mask-aware) | frankot-chellappa (full frame) | poisson / FC (≤ {TARGET_POISSON_OVER_FC} at 2048²) | robust-poisson | robust / poisson |"
    );
    let _ = writeln!(o, "|---|---:|---:|---:|---:|---:|");
    for s in sets {
        let (p, f, r) = (
            median(&s.poisson_ms),
            median(&s.fc_ms),
            median(&s.robust_ms),
        );
        let _ = writeln!(
            o,
            "| {}² | {} | {} | {} | {} | {} |",
            s.size,
            num(p, 0),
            num(f, 0),
            with_mark(zip2(p, f, |p, f| p / f), 2, s.size == TARGET_SIZE, |r| {
                r <= TARGET_POISSON_OVER_FC
            }),
            num(r, 0),
            num(zip2(r, p, |r, p| r / p), 2),
        );
    }

    // Load.
    if let Some(l) = load {
        let _ = writeln!(
            o,
            "\n### Status requests while all {} workers run {}² jobs\n",
            l.workers, l.size
        );
        let _ = writeln!(
            o,
            "| requests | connections | p50 ms | p99 ms (< {TARGET_STATUS_P99_MS:.0}) | max ms | failed | jobs still running after |"
        );
        let _ = writeln!(o, "|---:|---:|---:|---:|---:|---:|---:|");
        let p99 = percentile(&l.latencies_ms, 99.0);
        let _ = writeln!(
            o,
            "| {} | {} | {:.1} | {} | {:.1} | {} {} | {} / {} |",
            l.requests,
            l.connections,
            percentile(&l.latencies_ms, 50.0),
            with_mark(Some(p99), 1, true, |p| p < TARGET_STATUS_P99_MS),
            max_of(&l.latencies_ms).unwrap_or(f64::NAN),
            l.failed,
            mark(l.failed == 0),
            l.running_after,
            l.workers
        );
        if let Some(f) = &l.first_failure {
            let _ = writeln!(o, "\nfirst failed request: {f}");
        }
    }

    // Targets.
    let _ = writeln!(o, "\n### Targets\n");
    let _ = writeln!(o, "| target | measured | met |");
    let _ = writeln!(o, "|---|---:|:---:|");
    let target = sets.iter().find(|s| s.size == TARGET_SIZE);
    let mut line = |name: &str, value: Option<f64>, digits: usize, unit: &str, ok: bool| {
        let (measured, met) = match value {
            Some(v) if v.is_finite() => (format!("{v:.digits$}{unit}"), mark(ok)),
            _ => ("not measured".to_string(), "–"),
        };
        let _ = writeln!(o, "| {name} | {measured} | {met} |");
    };
    let t_ratio =
        target.and_then(|s| zip2(median(&s.full_ms), median(&s.decode_only_ms), |f, d| f / d));
    line(
        &format!("full job ≤ {TARGET_FULL_OVER_DECODE} × decode at 2048²"),
        t_ratio,
        2,
        " ×",
        t_ratio.is_some_and(|r| r <= TARGET_FULL_OVER_DECODE),
    );
    let at_target = target.filter(|s| s.lights == 24);
    for (peaks, whose) in [
        (at_target.map(|s| &s.peak_bytes), ""),
        (
            at_target.map(|s| &s.alone_peak_bytes),
            ", the job in its own process",
        ),
    ] {
        let peak = peaks.and_then(|p| max_of(p)).map(|b| b / MB);
        line(
            &format!("peak RSS ≤ {TARGET_PEAK_MB:.0} MB at 2048² × 24{whose}"),
            peak,
            0,
            " MB",
            peak.is_some_and(|p| p <= TARGET_PEAK_MB),
        );
    }
    for s in sets.iter().filter(|_| args.http) {
        let r = zip2(median(&s.http_ms), median(&s.full_ms), |h, c| h / c);
        line(
            &format!("HTTP ≤ {TARGET_HTTP_OVER_CORE} × core at {}²", s.size),
            r,
            2,
            " ×",
            r.is_some_and(|r| r <= TARGET_HTTP_OVER_CORE),
        );
    }
    let t_fc = target.and_then(|s| zip2(median(&s.poisson_ms), median(&s.fc_ms), |p, f| p / f));
    line(
        &format!("poisson ≤ {TARGET_POISSON_OVER_FC} × frankot-chellappa at 2048²"),
        t_fc,
        2,
        " ×",
        t_fc.is_some_and(|r| r <= TARGET_POISSON_OVER_FC),
    );
    let t_lin = (target.filter(|_| smaller))
        .and_then(|s| zip2(s.ns_per_pixel_image(), ref_ns, |a, b| a / b));
    line(
        &format!(
            "time per pixel-image at 2048² within {:.0} % of {ref_label}",
            TARGET_LINEARITY * 100.0
        ),
        t_lin,
        2,
        " ×",
        t_lin.is_some_and(linear_enough),
    );
    if let Some(l) = load {
        let p99 = percentile(&l.latencies_ms, 99.0);
        line(
            &format!("status p99 < {TARGET_STATUS_P99_MS:.0} ms under load"),
            Some(p99),
            1,
            " ms",
            p99 < TARGET_STATUS_P99_MS,
        );
        line(
            "failed status requests = 0",
            Some(l.failed as f64),
            0,
            "",
            l.failed == 0,
        );
    } else {
        line("status p99 < 50 ms under load", None, 0, "", false);
    }
    o
}

/// Per-pixel-image time within ±25 % of the reference (faster by more also passes: the
/// target is about staying linear, not getting slower per pixel).
fn linear_enough(ratio: f64) -> bool {
    ratio <= 1.0 + TARGET_LINEARITY
}

fn zip2(a: Option<f64>, b: Option<f64>, f: impl Fn(f64, f64) -> f64) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b != 0.0 => Some(f(a, b)),
        _ => None,
    }
}

fn num(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(v) if v.is_finite() => format!("{v:.digits$}"),
        _ => "–".into(),
    }
}

fn mark(ok: bool) -> &'static str {
    if ok { "✓" } else { "✗" }
}

/// The number, followed by ✓/✗ when `judged`.
fn with_mark(v: Option<f64>, digits: usize, judged: bool, ok: impl Fn(f64) -> bool) -> String {
    match v {
        Some(x) if x.is_finite() && judged => format!("{x:.digits$} {}", mark(ok(x))),
        _ => num(v, digits),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_and_percentiles() {
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        let v: Vec<f64> = (1..=1000).map(f64::from).collect();
        assert_eq!(percentile(&v, 50.0), 500.0);
        assert_eq!(percentile(&v, 99.0), 990.0);
        assert_eq!(percentile(&v, 100.0), 1000.0);
        assert_eq!(percentile(&[7.0], 99.0), 7.0);
    }

    #[test]
    fn reads_own_status() {
        if cfg!(target_os = "linux") {
            assert!(status_bytes("VmRSS").is_some_and(|b| b > 0.0));
            assert!(status_bytes("VmNothing").is_none());
        }
    }
}
