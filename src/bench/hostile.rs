//! `bench --hostile`: what `photostereo serve`, with its default limits, gives its users
//! while an attacker or a careless client loads it. Per scenario: a fresh server as a
//! child process (so its VmHWM is that scenario's peak), tenant B's finished job to ask the
//! status of, then the load for `--hostile-seconds` while [`probe`](super::probe) times
//! health and status requests, then the server's memory, and the server is stopped and its
//! directory removed.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, anyhow, bail, ensure};
use futures_util::StreamExt;
use photostereo::core::intake::LIGHTS_FILE;
use photostereo::core::synth::ChromeSet;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::args::{BenchArgs, Scenario};
use super::child::{KEY_A, KEY_B, ServeChild};
use super::client::{self, Response};
use super::memory::MB;
use super::probe::{Prober, Probes};
use super::sets::{self, SizeResult};
use super::stats::{median, ms};
use super::temp_dir::TempDir;

/// The set of the job whose status is probed (the re-shading storm's is [`RESHADE_SIZE`]).
const PROBE_JOB_SIZE: usize = 128;
/// Tenant A's slow uploads, and how often each sends one more byte.
const SLOW_UPLOADS: usize = 64;
const SLOW_UPLOAD_EVERY: Duration = Duration::from_millis(500);
/// How long after A's uploads started tenant B submits.
const B_AFTER: Duration = Duration::from_secs(2);
/// How often a slowloris connection sends one more header byte.
const SLOWLORIS_EVERY: Duration = Duration::from_secs(1);
/// The calibration bomb: this many all-black PNGs of this side.
const BOMB_IMAGES: usize = 24;
const BOMB_SIDE: u32 = 5792;
/// Re-shades at once, of a job of this size.
const RESHADES: usize = 40;
const RESHADE_SIZE: usize = 2048;
/// Longest a request of a load (an upload, a re-shade) may wait for its answer.
pub(super) const ANSWER_TIMEOUT: Duration = Duration::from_secs(120);
/// Connections opened at once by the idle and slowloris loads.
const CONNECTING_AT_ONCE: usize = 256;
/// Pause after the load before the server's resident size is read.
const SETTLE: Duration = Duration::from_secs(2);
/// Longest the probed job may take.
const JOB_TIMEOUT: Duration = Duration::from_secs(600);
/// Descriptors the bench keeps for itself beyond the load's connections.
const SPARE_FILES: u64 = 1000;

/// One scenario's figures.
pub(super) struct HostileRow {
    pub(super) scenario: String,
    pub(super) probes: Probes,
    /// The server's VmRSS just before the load, its VmHWM over it (`peak_reset`: reset just
    /// before; otherwise since it started), its VmRSS [`SETTLE`] after it.
    pub(super) before_bytes: Option<f64>,
    pub(super) peak_bytes: Option<f64>,
    pub(super) peak_reset: bool,
    pub(super) after_bytes: Option<f64>,
    pub(super) outcome: String,
}

/// Every scenario's row, and the server's open-file limit.
pub(super) struct HostileRun {
    pub(super) rows: Vec<HostileRow>,
    pub(super) server_open_files: Option<u64>,
}

/// Run each of `args.scenarios` against a server of its own.
pub(super) fn run(args: &BenchArgs, tmp: &Path) -> anyhow::Result<HostileRun> {
    let files = raise_open_files();
    let needed = args.hostile_connections as u64 + SPARE_FILES;
    ensure!(
        files >= needed,
        "--hostile-connections {} needs {needed} open files; the limit is {files}",
        args.hostile_connections
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    let inputs = Inputs::prepare(args, tmp)?;
    let mut run = HostileRun {
        rows: Vec::new(),
        server_open_files: None,
    };
    for &scenario in &args.scenarios {
        eprintln!("bench: hostile scenario {scenario:?}");
        let row = measure(
            args,
            scenario,
            &inputs,
            &rt,
            tmp,
            &mut run.server_open_files,
        )?;
        eprintln!(
            "bench: {}: {} (probes: {} health, {} status; {:?})",
            row.scenario,
            row.outcome,
            row.probes.health.len(),
            row.probes.status.len(),
            row.probes.first_failure
        );
        run.rows.push(row);
    }
    Ok(run)
}

/// Raise this process's soft limit on open files to the hard limit (the server, its
/// child, inherits it); returns the limit now in force.
fn raise_open_files() -> u64 {
    // SAFETY: `rlimit` is two integers, for which zeros are a valid value.
    let mut limit: libc::rlimit = unsafe { std::mem::zeroed() };
    // SAFETY: a live local to write into; RLIMIT_NOFILE is a valid resource.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return 0;
    }
    if limit.rlim_cur < limit.rlim_max {
        let raised = libc::rlimit {
            rlim_cur: limit.rlim_max,
            rlim_max: limit.rlim_max,
        };
        // SAFETY: a live local to read from; raising the soft limit up to the hard one is
        // always allowed.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
            return raised.rlim_cur as u64;
        }
    }
    limit.rlim_cur as u64
}

/// The files the scenarios send, made once.
struct Inputs {
    /// The probed job's set, and the re-shading storm's.
    small: SizeResult,
    large: Option<SizeResult>,
    /// Tenant B's calibration: chrome-sphere images.
    chrome: Vec<PathBuf>,
    /// The bomb's one all-black PNG, sent [`BOMB_IMAGES`] times.
    black_png: Option<PathBuf>,
}

impl Inputs {
    fn prepare(args: &BenchArgs, tmp: &Path) -> anyhow::Result<Self> {
        let wants = |s: Scenario| args.scenarios.contains(&s);
        let small = sets::render(&[PROBE_JOB_SIZE], args.lights, tmp)?.remove(0);
        let large = if wants(Scenario::ReshadeStorm) {
            Some(sets::render(&[RESHADE_SIZE], args.lights, tmp)?.remove(0))
        } else {
            None
        };
        let chrome = if wants(Scenario::SlowUploads) {
            chrome_set(&tmp.join("chrome"))?
        } else {
            Vec::new()
        };
        let black_png = if wants(Scenario::CalibrationBomb) {
            let path = tmp.join("black.png");
            write_black_png(&path, BOMB_SIDE)?;
            Some(path)
        } else {
            None
        };
        Ok(Self {
            small,
            large,
            chrome,
            black_png,
        })
    }
}

/// The standard rendered chrome-sphere capture (24 lights); its images in light order.
fn chrome_set(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    ChromeSet::standard(16, 1)
        .write(dir, None)
        .context("rendering the chrome-sphere set")?;
    let mut images: Vec<PathBuf> = std::fs::read_dir(dir)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()?;
    images.retain(|p| p.extension().is_some_and(|e| e == "png"));
    images.sort();
    ensure!(!images.is_empty(), "the chrome-sphere set has no images");
    Ok(images)
}

/// An 8-bit gray PNG, `side` × `side`, every pixel 0: a few tens of kB.
fn write_black_png(path: &Path, side: u32) -> anyhow::Result<()> {
    let file = std::io::BufWriter::new(std::fs::File::create(path)?);
    let mut encoder = png::Encoder::new(file, side, side);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&vec![0u8; side as usize * side as usize])?;
    writer.finish()?;
    Ok(())
}

/// One scenario on a fresh server; the server is stopped and its directory removed
/// whatever happens.
fn measure(
    args: &BenchArgs,
    scenario: Scenario,
    inputs: &Inputs,
    rt: &tokio::runtime::Runtime,
    tmp: &Path,
    open_files: &mut Option<u64>,
) -> anyhow::Result<HostileRow> {
    let server = ServeChild::start(TempDir::new(tmp)?, &args.serve_args, rt)?;
    let addr = server.addr;
    *open_files = open_files.or(server.open_files_limit());
    let set = match (scenario, &inputs.large) {
        (Scenario::ReshadeStorm, Some(large)) => large,
        _ => &inputs.small,
    };
    let id = rt.block_on(async {
        let body = job_body(set)?;
        let (r, _) = post(addr, "/v1/jobs", KEY_B, &body).await?;
        ensure!(
            r.status == 202,
            "submitting the probed job: {}",
            r.describe()
        );
        let id = json_id(&r)?;
        wait_succeeded(addr, &id, KEY_B).await?;
        anyhow::Ok(id)
    })?;
    std::thread::sleep(SETTLE);

    let before_bytes = server.status_bytes("VmRSS");
    let peak_reset = server.reset_peak();
    let every = Duration::from_millis(args.probe_ms);
    let prober = Prober::start(addr, job_path(&id), KEY_B, every)?;
    let load = Load {
        addr,
        job: &id,
        inputs,
        start: Instant::now(),
        deadline: Instant::now() + Duration::from_secs(args.hostile_seconds),
        connections: args.hostile_connections,
    };
    let outcome = rt.block_on(load.run(scenario));
    let probes = prober.stop();
    std::thread::sleep(SETTLE);

    let mut server = server;
    let outcome = match (outcome, server.exited()) {
        (_, Some(exit)) => format!("the server exited ({exit})"),
        (Ok(o), None) => o,
        (Err(e), None) => format!("the load failed: {e:#}"),
    };
    Ok(HostileRow {
        scenario: label(scenario, args.hostile_connections),
        probes,
        before_bytes,
        peak_bytes: server.status_bytes("VmHWM"),
        peak_reset,
        after_bytes: server.status_bytes("VmRSS"),
        outcome,
    })
}

fn label(scenario: Scenario, connections: usize) -> String {
    match scenario {
        Scenario::Quiet => "none (the probes alone)".into(),
        Scenario::Idle => format!("{connections} idle connections"),
        Scenario::Slowloris => format!(
            "{connections} slowloris connections (a header byte every {} s)",
            SLOWLORIS_EVERY.as_secs()
        ),
        Scenario::SlowUploads => format!(
            "{SLOW_UPLOADS} slow job uploads from tenant A (a byte every {} ms); B submits a job and a calibration",
            SLOW_UPLOAD_EVERY.as_millis()
        ),
        Scenario::CalibrationBomb => {
            format!("calibration bomb: {BOMB_IMAGES} all-black {BOMB_SIDE} × {BOMB_SIDE} PNGs")
        }
        Scenario::ReshadeStorm => {
            format!("{RESHADES} re-shades at once (`shaded.png?light=`) of a {RESHADE_SIZE}² job")
        }
    }
}

/// What a load needs: the server, tenant B's finished job, the files, its time.
struct Load<'a> {
    addr: SocketAddr,
    job: &'a str,
    inputs: &'a Inputs,
    start: Instant,
    deadline: Instant,
    connections: usize,
}

impl Load<'_> {
    /// Run the load until its deadline (and its requests' answers); what came of it.
    async fn run(&self, scenario: Scenario) -> anyhow::Result<String> {
        let outcome = match scenario {
            Scenario::Quiet => Ok("–".to_string()),
            Scenario::Idle => self.hold_connections(false).await,
            Scenario::Slowloris => self.hold_connections(true).await,
            Scenario::SlowUploads => self.slow_uploads().await,
            Scenario::CalibrationBomb => self.calibration_bomb().await,
            Scenario::ReshadeStorm => self.reshade_storm().await,
        };
        tokio::time::sleep_until(self.deadline.into()).await;
        outcome
    }

    /// Open [`Load::connections`] connections (until the deadline) and hold each until the
    /// deadline from the moment it opens, silent or trickling a request head that never
    /// ends.
    async fn hold_connections(&self, trickle: bool) -> anyhow::Result<String> {
        let n = self.connections;
        let (addr, start, deadline) = (self.addr, self.start, self.deadline);
        let opened: Vec<_> = futures_util::stream::iter(0..n)
            .map(|i| async move {
                let left = deadline.saturating_duration_since(Instant::now());
                let wait = left.min(Duration::from_secs(5));
                let stream = match tokio::time::timeout(wait, TcpStream::connect(addr)).await {
                    Ok(Ok(stream)) => stream,
                    Ok(Err(e)) => return Err(e.to_string()),
                    Err(_) => return Err(format!("no connection within {wait:?}")),
                };
                let stagger = SLOWLORIS_EVERY.mul_f64(i as f64 / n as f64);
                let held = hold(stream, trickle.then_some(stagger), start, deadline);
                Ok(tokio::spawn(held))
            })
            .buffer_unordered(CONNECTING_AT_ONCE)
            .collect()
            .await;
        let mut ends = Vec::with_capacity(n);
        let mut failed = 0;
        let mut first_error = None;
        for c in opened {
            match c {
                Ok(task) => ends.push(task.await.unwrap_or(Ended::Closed(f64::NAN))),
                Err(e) => {
                    failed += 1;
                    first_error.get_or_insert(e);
                }
            }
        }
        if let Some(e) = first_error {
            eprintln!("bench: {failed} connections failed, the first: {e}");
        }
        Ok(held_summary(n, &ends, deadline - start))
    }

    /// Tenant A's slow uploads take the upload slots; then tenant B submits a job and a
    /// calibration, each answered or given up within [`ANSWER_TIMEOUT`].
    async fn slow_uploads(&self) -> anyhow::Result<String> {
        let body = job_body(&self.inputs.small)?;
        let a: Vec<_> = (0..SLOW_UPLOADS)
            .map(|_| {
                tokio::spawn(slow_upload(
                    self.addr,
                    body.clone(),
                    self.start,
                    self.deadline,
                ))
            })
            .collect();
        tokio::time::sleep(B_AFTER).await;
        let job = answer_of(post(self.addr, "/v1/jobs", KEY_B, &body).await);
        let calibration = calibration_body(&self.inputs.chrome)?;
        let calibration = answer_of(post(self.addr, "/v1/calibrations", KEY_B, &calibration).await);
        let mut ends = Vec::new();
        for t in a {
            ends.push(t.await.unwrap_or(Ended::Closed(f64::NAN)));
        }
        Ok(format!(
            "B: job {job}, calibration {calibration}; A's uploads: {}",
            held_summary(SLOW_UPLOADS, &ends, self.deadline - self.start)
        ))
    }

    async fn calibration_bomb(&self) -> anyhow::Result<String> {
        let black = self
            .inputs
            .black_png
            .as_ref()
            .ok_or_else(|| anyhow!("no bomb image"))?;
        let images = vec![black.clone(); BOMB_IMAGES];
        let body = calibration_body(&images)?;
        let answer = answer_of(post(self.addr, "/v1/calibrations", KEY_A, &body).await);
        Ok(format!(
            "{:.2} MB upload: {answer}",
            body.bytes.len() as f64 / MB
        ))
    }

    async fn reshade_storm(&self) -> anyhow::Result<String> {
        let requests = (0..RESHADES).map(|i| {
            let angle = std::f64::consts::TAU * i as f64 / RESHADES as f64;
            let path = format!(
                "{}/artifacts/shaded.png?light={:.4},{:.4},1",
                job_path(self.job),
                0.5 * angle.cos(),
                0.5 * angle.sin()
            );
            let addr = self.addr;
            async move {
                let start = Instant::now();
                let r = async {
                    let mut c = client::connect(addr).await?;
                    let auth = format!("Bearer {KEY_B}");
                    c.send(
                        "GET",
                        &path,
                        &[("Authorization", &auth)],
                        None,
                        ANSWER_TIMEOUT,
                    )
                    .await
                }
                .await;
                (r.map(|r| r.status), ms(start.elapsed()))
            }
        });
        let answers = futures_util::future::join_all(requests).await;
        let mut statuses = std::collections::BTreeMap::<String, usize>::new();
        let mut times = Vec::new();
        for (status, took) in &answers {
            let key = match status {
                Ok(s) => s.to_string(),
                Err(_) => "no answer".into(),
            };
            *statuses.entry(key).or_default() += 1;
            times.push(*took);
        }
        let counts: Vec<String> = statuses.iter().map(|(s, n)| format!("{n} × {s}")).collect();
        let slowest = times.iter().copied().fold(0.0, f64::max);
        Ok(format!(
            "{RESHADES} re-shades: {}; median {:.1} s, slowest {:.1} s",
            counts.join(", "),
            median(&times).unwrap_or(f64::NAN) / 1e3,
            slowest / 1e3
        ))
    }
}

/// How a held connection ended.
#[derive(Debug, Clone, Copy)]
enum Ended {
    /// Still open at the deadline.
    Open,
    /// Closed or reset by the server, ms after the load started.
    Closed(f64),
    /// The server answered (with this status), ms after the load started.
    Answered(u16, f64),
}

/// Hold `stream` until the deadline or until the server ends it; with `trickle` (the first
/// byte's delay), send a request head a byte at a time, never ending it.
async fn hold(
    mut stream: TcpStream,
    trickle: Option<Duration>,
    start: Instant,
    deadline: Instant,
) -> Ended {
    let mut head = b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "
        .iter()
        .copied();
    let mut next = trickle.map(|delay| Instant::now() + delay);
    let mut buf = [0u8; 512];
    loop {
        let wake = next.unwrap_or(deadline).min(deadline);
        tokio::select! {
            read = stream.read(&mut buf) => return ended_by(read, &buf, start),
            _ = tokio::time::sleep_until(wake.into()) => {
                if Instant::now() >= deadline {
                    return Ended::Open;
                }
                let byte = head.next().unwrap_or(b'a');
                if stream.write_all(&[byte]).await.is_err() {
                    return Ended::Closed(ms(start.elapsed()));
                }
                next = Some(wake + SLOWLORIS_EVERY);
            }
        }
    }
}

/// A read on a held connection: an answer's status, or its end.
fn ended_by(read: std::io::Result<usize>, buf: &[u8], start: Instant) -> Ended {
    let at = ms(start.elapsed());
    match read {
        Ok(n) if n > 0 => {
            let text = String::from_utf8_lossy(&buf[..n]);
            let status = text
                .split_whitespace()
                .nth(1)
                .and_then(|s| s.parse().ok())
                .unwrap_or(0);
            Ended::Answered(status, at)
        }
        _ => Ended::Closed(at),
    }
}

/// One of tenant A's uploads: the request head at once, then the body a byte every
/// [`SLOW_UPLOAD_EVERY`], until the deadline or the server's answer.
async fn slow_upload(
    addr: SocketAddr,
    body: Multipart,
    start: Instant,
    deadline: Instant,
) -> Ended {
    let Ok(Ok(mut stream)) =
        tokio::time::timeout(Duration::from_secs(5), TcpStream::connect(addr)).await
    else {
        return Ended::Closed(ms(start.elapsed()));
    };
    let head = format!(
        "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {KEY_A}\r\nContent-Type: {}\r\nContent-Length: {}\r\n\r\n",
        body.content_type(),
        body.bytes.len()
    );
    if stream.write_all(head.as_bytes()).await.is_err() {
        return Ended::Closed(ms(start.elapsed()));
    }
    let mut bytes = body.bytes.iter().copied();
    let mut tick = tokio::time::interval(SLOW_UPLOAD_EVERY);
    let mut buf = [0u8; 512];
    loop {
        tokio::select! {
            read = stream.read(&mut buf) => return ended_by(read, &buf, start),
            _ = tokio::time::sleep_until(deadline.into()) => return Ended::Open,
            _ = tick.tick() => {
                if let Some(b) = bytes.next()
                    && stream.write_all(&[b]).await.is_err()
                {
                    return Ended::Closed(ms(start.elapsed()));
                }
            }
        }
    }
}

/// "5000 connected: 4990 closed by the server (median after 10.2 s), 10 answered
/// (10 × 408), 0 still open after 15 s".
fn held_summary(tried: usize, ends: &[Ended], load: Duration) -> String {
    let closed: Vec<f64> = ends
        .iter()
        .filter_map(|e| match e {
            Ended::Closed(at) => Some(*at),
            _ => None,
        })
        .collect();
    let mut answered = std::collections::BTreeMap::<u16, (usize, Vec<f64>)>::new();
    for e in ends {
        if let Ended::Answered(status, at) = e {
            let entry = answered.entry(*status).or_default();
            entry.0 += 1;
            entry.1.push(*at);
        }
    }
    let open = ends.iter().filter(|e| matches!(e, Ended::Open)).count();
    let mut parts = vec![format!("{}/{tried} connected", ends.len())];
    if !closed.is_empty() {
        parts.push(format!(
            "{} closed by the server (median after {:.1} s)",
            closed.len(),
            median(&closed).unwrap_or(f64::NAN) / 1e3
        ));
    }
    for (status, (n, at)) in &answered {
        parts.push(format!(
            "{n} answered {status} (median after {:.1} s)",
            median(at).unwrap_or(f64::NAN) / 1e3
        ));
    }
    parts.push(format!("{open} still open after {} s", load.as_secs()));
    parts.join(", ")
}

/// A multipart/form-data body held in memory.
#[derive(Clone)]
struct Multipart {
    boundary: String,
    bytes: Vec<u8>,
}

impl Multipart {
    fn new() -> Self {
        let stamp = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        Self {
            boundary: format!("photostereo-bench-{stamp:032x}"),
            bytes: Vec::new(),
        }
    }

    fn file(self, part: &str, path: &Path, content_type: &str) -> anyhow::Result<Self> {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| anyhow!("no file name in {}", path.display()))?
            .to_string();
        self.file_named(part, &name, path, content_type)
    }

    /// A file part whose file name is `name` (not the file's own).
    fn file_named(
        mut self,
        part: &str,
        name: &str,
        path: &Path,
        content_type: &str,
    ) -> anyhow::Result<Self> {
        let head = format!(
            "--{}\r\nContent-Disposition: form-data; name=\"{part}\"; filename=\"{name}\"\r\nContent-Type: {content_type}\r\n\r\n",
            self.boundary
        );
        self.bytes.extend_from_slice(head.as_bytes());
        let data = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        self.bytes.extend_from_slice(&data);
        self.bytes.extend_from_slice(b"\r\n");
        Ok(self)
    }

    fn finish(mut self) -> Self {
        let closing = format!("--{}--\r\n", self.boundary);
        self.bytes.extend_from_slice(closing.as_bytes());
        self
    }

    fn content_type(&self) -> String {
        format!("multipart/form-data; boundary={}", self.boundary)
    }
}

/// A job's form: the set's light table and images.
fn job_body(set: &SizeResult) -> anyhow::Result<Multipart> {
    let mut body = Multipart::new().file("lights", &set.dir.join(LIGHTS_FILE), "text/csv")?;
    for name in set.image_names() {
        body = body.file("images", &set.dir.join(name), "image/png")?;
    }
    Ok(body.finish())
}

/// A calibration's form: the images, in order, each named `ball01.png`… by its place
/// (the bomb sends one file many times).
fn calibration_body(images: &[PathBuf]) -> anyhow::Result<Multipart> {
    let mut body = Multipart::new();
    for (i, path) in images.iter().enumerate() {
        let name = format!("ball{:02}.png", i + 1);
        body = body.file_named("images", &name, path, "image/png")?;
    }
    Ok(body.finish())
}

/// POST `body` as the tenant of `key` on a new connection: the answer and its time (ms).
async fn post(
    addr: SocketAddr,
    path: &str,
    key: &str,
    body: &Multipart,
) -> anyhow::Result<(Response, f64)> {
    let start = Instant::now();
    let mut c = client::connect(addr).await?;
    let auth = format!("Bearer {key}");
    let content_type = body.content_type();
    let headers = [
        ("Authorization", auth.as_str()),
        ("Content-Type", &content_type),
    ];
    let r = c
        .send("POST", path, &headers, Some(&body.bytes), ANSWER_TIMEOUT)
        .await?;
    Ok((r, ms(start.elapsed())))
}

/// "202 in 40 ms", or what failed.
fn answer_of(answer: anyhow::Result<(Response, f64)>) -> String {
    match answer {
        Ok((r, took)) if took < 10_000.0 => format!("{} in {took:.0} ms", r.status),
        Ok((r, took)) => format!("{} in {:.1} s", r.status, took / 1e3),
        Err(e) => format!("no answer ({e:#})"),
    }
}

fn json_id(r: &Response) -> anyhow::Result<String> {
    let v: Value = serde_json::from_slice(&r.body).context("a job's JSON")?;
    v["id"]
        .as_str()
        .map(String::from)
        .ok_or_else(|| anyhow!("no id in {v}"))
}

fn job_path(id: &str) -> String {
    format!("/v1/jobs/{id}")
}

/// Poll the job as tenant B until it has succeeded.
async fn wait_succeeded(addr: SocketAddr, id: &str, key: &str) -> anyhow::Result<()> {
    let start = Instant::now();
    let auth = format!("Bearer {key}");
    let mut conn = client::connect(addr).await?;
    loop {
        if conn.closed {
            conn = client::connect(addr).await?;
        }
        let r = conn
            .send(
                "GET",
                &job_path(id),
                &[("Authorization", &auth)],
                None,
                ANSWER_TIMEOUT,
            )
            .await?;
        ensure!(r.status == 200, "GET {}: {}", job_path(id), r.describe());
        let job: Value = serde_json::from_slice(&r.body).context("a job's JSON")?;
        match job["status"].as_str().unwrap_or_default() {
            "succeeded" => return Ok(()),
            s @ ("failed" | "cancelled") => bail!("job {id} ended {s}: {}", job["error"]),
            _ if start.elapsed() > JOB_TIMEOUT => bail!("job {id} did not finish in time"),
            _ => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}
