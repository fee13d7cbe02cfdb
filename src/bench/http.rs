//! The HTTP load: the service in this process, each set submitted over HTTP and polled
//! until it succeeds, and status requests timed while every worker is busy.

use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, anyhow, bail, ensure};
use photostereo::core::heap::release_free_heap;
use photostereo::core::intake::LIGHTS_FILE;
use photostereo::service::{AppState, Config, serve_with};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;

use super::args::BenchArgs;
use super::client::{self, Conn, REQUEST_TIMEOUT};
use super::memory::{own_cpu_ms, reset_peak, status_bytes, tree_cpu_ms};
use super::sets::SizeResult;
use super::stats::ms;

/// Polling interval while waiting for a job over HTTP.
pub(super) const POLL_EVERY: Duration = Duration::from_millis(10);
/// Longest one upload may take.
const UPLOAD_TIMEOUT: Duration = Duration::from_secs(600);
/// Longest one job may take over HTTP before the bench gives up.
const JOB_TIMEOUT: Duration = Duration::from_secs(1800);

/// Status-request latencies under load.
pub(super) struct LoadResult {
    pub(super) size: usize,
    pub(super) workers: usize,
    pub(super) requests: usize,
    pub(super) connections: usize,
    pub(super) latencies_ms: Vec<f64>,
    pub(super) failed: usize,
    /// Jobs still running when the last status request was answered.
    pub(super) running_after: usize,
    pub(super) first_failure: Option<String>,
}

/// The service running in this process on 127.0.0.1:0, on its own tokio runtime.
pub(super) struct Server {
    pub(super) rt: tokio::runtime::Runtime,
    pub(super) addr: SocketAddr,
    pub(super) workers: usize,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

/// Where a [`Server`] keeps its jobs.
pub(super) enum Backend {
    /// SQLite and the data directory (the single-node default).
    Local,
    /// PostgreSQL and an object store: `--database-url`, `--store`.
    Shared { database_url: String, store: String },
}

impl Server {
    pub(super) fn start(
        args: &BenchArgs,
        sets: &[SizeResult],
        tmp: &Path,
        backend: Backend,
    ) -> anyhow::Result<Self> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the tokio runtime")?;
        let mut config = match backend {
            Backend::Local => Config::new(tmp.join("service")),
            Backend::Shared {
                database_url,
                store,
            } => {
                let mut c = Config::new(tmp.join("service-shared"));
                c.database_url = Some(database_url);
                c.store = Some(store);
                c
            }
        };
        config.workers = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        config.min_free_disk = 0;
        config.shutdown_grace = Duration::from_secs(5);
        config.max_images = config.max_images.max(args.lights);
        let largest = sets.iter().map(|s| s.size).max().unwrap_or(0) as u64;
        config.max_pixels = config.max_pixels.max(largest * largest);
        // The bench's own sets (an 8192² × 24 upload passes 2 GiB): the body and input
        // limits are not what it measures.
        config.max_body_bytes = u64::MAX;
        config.max_input_bytes = u64::MAX;
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
    pub(super) fn stop(self) {
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

/// What one HTTP run measured.
pub(super) struct HttpRun {
    pub(super) total_ms: f64,
    pub(super) upload_ms: f64,
    /// Process VmHWM over the job, when it could be reset before it.
    pub(super) peak_bytes: Option<f64>,
    /// CPU time of this process (servers and client) over the job.
    pub(super) cpu_ms: f64,
    /// CPU time of the `servers` process trees over the job.
    pub(super) servers_cpu_ms: f64,
}

/// One HTTP run: upload, poll until succeeded, delete the job. `servers`: processes
/// outside this one that the job uses (the S3 server, PostgreSQL), whose CPU time is
/// counted too.
pub(super) async fn http_run(
    set: &SizeResult,
    label: &str,
    (run, runs): (usize, usize),
    addr: SocketAddr,
    servers: &[u32],
) -> anyhow::Result<HttpRun> {
    release_free_heap();
    let reset = reset_peak();
    let (cpu, servers_cpu) = (own_cpu_ms(), tree_cpu_ms(servers));
    let (id, upload, total) = submit_and_wait(addr, set).await?;
    let (cpu, servers_cpu) = (own_cpu_ms() - cpu, tree_cpu_ms(servers) - servers_cpu);
    let peak = status_bytes("VmHWM");
    let mut conn = client::connect(addr).await?;
    let r = conn.request("DELETE", &job_path(&id)).await?;
    ensure!(r.status == 204, "deleting job {id}: {}", r.describe());
    let servers_note = if servers.is_empty() {
        String::new()
    } else {
        format!(", servers' CPU {servers_cpu:.0} ms")
    };
    eprintln!(
        "bench: {label} {}² run {}/{runs}: upload {:.0} ms, succeeded after {:.0} ms, CPU \
         {cpu:.0} ms{servers_note}",
        set.size,
        run + 1,
        ms(upload),
        ms(total)
    );
    Ok(HttpRun {
        total_ms: ms(total),
        upload_ms: ms(upload),
        peak_bytes: peak.filter(|_| reset),
        cpu_ms: cpu,
        servers_cpu_ms: servers_cpu,
    })
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

    let mut conn = client::connect(addr).await?;
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
    let mut conn = client::connect(addr).await?;
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
            conn = client::connect(addr).await?;
        }
    }
}

/// Fill every worker with a job of the largest set, then time status requests.
pub(super) async fn load_test(
    args: &BenchArgs,
    set: &SizeResult,
    addr: SocketAddr,
    workers: usize,
) -> anyhow::Result<LoadResult> {
    let mut ids = Vec::new();
    let outcome = load_with_jobs(args, set, addr, workers, &mut ids).await;
    // Cancel whatever is still queued or running, and wait (bounded) for it to stop.
    for id in &ids {
        if let Ok(mut c) = client::connect(addr).await {
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
    let mut conn = client::connect(addr).await?;
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
                conn = Some(client::connect(addr).await?);
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
