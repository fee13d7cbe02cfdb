//! `photostereo serve` settings: flags, their environment variables and defaults.

use std::path::PathBuf;
use std::time::Duration;

use crate::core::intake::Limits;

use super::util::{parse_duration, parse_size};

/// Log line format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

/// Run the HTTP API: accept reconstruction jobs, run them on a bounded worker pool and
/// serve their artifacts.
///
/// Every flag can also be set through the environment variable named in its help.
/// Durations take `90` (seconds), `500ms`, `30s`, `15m`, `2h`, `7d`, `1w` or sums such as
/// `1h30m`; sizes take bytes or `KiB`/`MiB`/`GiB`/`TiB` (binary) and `KB`/`MB`/`GB`
/// (decimal).
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address and port to listen on.
    #[arg(long, env = "PHOTOSTEREO_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: String,

    /// Directory for the job database and the jobs' inputs and artifacts (with --store:
    /// the database and a scratch directory for uploads and running jobs).
    #[arg(long, env = "PHOTOSTEREO_DATA_DIR", default_value = "./data")]
    pub data_dir: PathBuf,

    /// Keep job inputs, artifacts and calibration files in an S3-compatible object store,
    /// `s3://bucket[/prefix]` [default: the data directory]; instances that share a
    /// prefix must share the job database.
    /// Connection settings come from AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID,
    /// AWS_SECRET_ACCESS_KEY, AWS_REGION and AWS_ALLOW_HTTP (true for a plain-HTTP
    /// endpoint); requests are path-style.
    #[arg(long, env = "PHOTOSTEREO_STORE")]
    pub store: Option<String>,

    /// Keep job records and the job queue in PostgreSQL,
    /// `postgres://user[:password]@host[:port]/database` [default: SQLite in the data
    /// directory]. Any number of instances may share the database (and the --store, which
    /// it requires), each with a data directory of its own: any instance answers for any
    /// job, and a job whose instance dies is taken over once its lease runs out.
    /// Migrations are applied at start.
    #[arg(long, env = "PHOTOSTEREO_DATABASE_URL", requires = "store")]
    pub database_url: Option<String>,

    /// How long a running job's claim lasts without a heartbeat (heartbeats come three
    /// times a lease). When an instance dies, its jobs run again elsewhere after this;
    /// a job whose lease runs out on its third attempt fails.
    #[arg(long, env = "PHOTOSTEREO_JOB_LEASE", default_value = "30s", value_parser = parse_lease)]
    pub job_lease: Duration,

    /// Reconstructions that run at once [default: the number of CPU cores].
    #[arg(long, env = "PHOTOSTEREO_WORKERS", value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub workers: Option<u32>,

    /// Accepted jobs that may wait for a worker; past this, submissions get 503 with
    /// Retry-After.
    #[arg(long, env = "PHOTOSTEREO_QUEUE_LENGTH", default_value_t = 64)]
    pub queue_length: usize,

    /// Largest request body accepted (413 past it).
    #[arg(long, env = "PHOTOSTEREO_MAX_BODY_BYTES", default_value = "2GiB", value_parser = parse_size)]
    pub max_body_bytes: u64,

    /// Most images in one job (413 past it).
    #[arg(long, env = "PHOTOSTEREO_MAX_IMAGES", default_value_t = 256)]
    pub max_images: usize,

    /// Most pixels in one image, width × height (413 past it): a job's output maps are
    /// sized by it, 80–104 bytes per pixel at the job's peak, whatever the image count.
    #[arg(long, env = "PHOTOSTEREO_MAX_PIXELS", default_value_t = 33_554_432)]
    pub max_pixels: u64,

    /// Most bytes of input files one job may store: its image and mask parts as
    /// uploaded, or the files its archive unpacks to (413 past it).
    #[arg(long, env = "PHOTOSTEREO_MAX_INPUT_BYTES", default_value = "4GiB", value_parser = parse_size)]
    pub max_input_bytes: u64,

    /// Deprecated, no effect (a warning at start): jobs read their images from the store
    /// in bands and never hold them all; --max-input-bytes and --max-pixels bound a job.
    #[arg(long, env = "PHOTOSTEREO_MAX_JOB_PIXELS")]
    pub max_job_pixels: Option<u64>,

    /// Most parts in one multipart upload, and most entries in one zip archive (413 past
    /// it); room for --max-images images and a benchmark folder's other files.
    #[arg(long, env = "PHOTOSTEREO_MAX_PARTS", default_value_t = 512)]
    pub max_parts: usize,

    /// Most bytes a zip archive may unpack to, all entries together (413 past it).
    #[arg(long, env = "PHOTOSTEREO_MAX_UNPACKED_BYTES", default_value = "2GiB", value_parser = parse_size)]
    pub max_unpacked_bytes: u64,

    /// How long finished jobs (and their artifacts) are kept before they are deleted.
    #[arg(long, env = "PHOTOSTEREO_RETENTION", default_value = "7d", value_parser = parse_duration)]
    pub retention: Duration,

    /// Longest a reconstruction may run; past it the job fails (checked as each stage
    /// starts and inside the long ones).
    #[arg(long, env = "PHOTOSTEREO_JOB_TIMEOUT", default_value = "30m", value_parser = parse_duration)]
    pub job_timeout: Duration,

    /// Uploads (POST /v1/jobs bodies) received at once; past this, submissions get 503
    /// with Retry-After.
    #[arg(long, env = "PHOTOSTEREO_MAX_UPLOADS", default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub max_uploads: u32,

    /// Longest an upload (one POST /v1/jobs body) may take (408 past it).
    #[arg(long, env = "PHOTOSTEREO_UPLOAD_TIMEOUT", default_value = "10m", value_parser = parse_duration)]
    pub upload_timeout: Duration,

    /// Most HTTP connections open at once [default: 4096, or fewer when the open-files
    /// limit, raised to its hard limit at start, leaves less room beside the files jobs
    /// and uploads hold]. At the cap a new connection takes the place of the one idle
    /// longest (between requests, or still sending its first request head); when every
    /// connection has a request in flight it gets 503 with Retry-After and is closed.
    #[arg(long, env = "PHOTOSTEREO_MAX_CONNECTIONS", value_parser = clap::value_parser!(u32).range(1..))]
    pub max_connections: Option<u32>,

    /// Longest a request head may take to arrive, from its first byte (for a
    /// connection's first request, from the connection's accept); the connection is closed
    /// past it.
    #[arg(long, env = "PHOTOSTEREO_HEADER_TIMEOUT", default_value = "20s", value_parser = parse_timeout)]
    pub header_timeout: Duration,

    /// How long a connection may stay open between requests (keep-alive) before it is
    /// closed.
    #[arg(long, env = "PHOTOSTEREO_KEEP_ALIVE_TIMEOUT", default_value = "75s", value_parser = parse_timeout)]
    pub keep_alive_timeout: Duration,

    /// How long a client may read nothing of a response the server is writing before its
    /// connection is closed.
    #[arg(long, env = "PHOTOSTEREO_SEND_TIMEOUT", default_value = "60s", value_parser = parse_timeout)]
    pub send_timeout: Duration,

    /// Refuse new jobs with 507 while the data directory's file system has less free
    /// space than this.
    #[arg(long, env = "PHOTOSTEREO_MIN_FREE_DISK", default_value = "1GiB", value_parser = parse_size)]
    pub min_free_disk: u64,

    /// API key required as `Authorization: Bearer <key>` on every /v1 route, as
    /// `tenant:secret` (a bare secret is a tenant of its own); repeat for several keys (the
    /// environment variable takes a comma-separated list). Each tenant sees only its own
    /// jobs. No key and no keys file: the API is open.
    #[arg(
        long = "api-key",
        env = "PHOTOSTEREO_API_KEYS",
        value_delimiter = ',',
        hide_env_values = true
    )]
    pub api_keys: Vec<String>,

    /// A file of API keys, one `tenant secret [role]` per line (role `admin` sees and
    /// manages every tenant's jobs; `member`, the default, its own); `#` starts a comment.
    /// Re-read on SIGHUP (a file that does not parse keeps the keys in force).
    #[arg(long, env = "PHOTOSTEREO_API_KEYS_FILE")]
    pub api_keys_file: Option<PathBuf>,

    /// Jobs one tenant may have queued or running at once; past it, submissions get 429
    /// with Retry-After.
    #[arg(long, env = "PHOTOSTEREO_TENANT_MAX_JOBS", default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..))]
    pub tenant_max_jobs: u32,

    /// Submissions one tenant may make per minute (0: no limit); past it, 429 with
    /// Retry-After.
    #[arg(
        long,
        env = "PHOTOSTEREO_TENANT_SUBMISSIONS_PER_MINUTE",
        default_value_t = 120
    )]
    pub tenant_submissions_per_minute: u32,

    /// Artifact bytes one tenant may keep stored (0: no limit); past it, submissions get
    /// 429 until jobs are deleted or expire.
    #[arg(long, env = "PHOTOSTEREO_TENANT_MAX_STORED_BYTES", default_value = "0", value_parser = parse_size)]
    pub tenant_max_stored_bytes: u64,

    /// A host that jobs' `callback_url` may name (repeat for several; exact names or IP
    /// addresses; none by default, and loopback or private addresses only when listed).
    #[arg(
        long = "webhook-allow-host",
        env = "PHOTOSTEREO_WEBHOOK_ALLOW_HOSTS",
        value_delimiter = ','
    )]
    pub webhook_allow_hosts: Vec<String>,

    /// A tenant's webhook signing secret, `tenant:secret` (repeat for several; the tenant
    /// of an open server, with no API keys, is `default`). Callbacks need one.
    #[arg(
        long = "webhook-secret",
        env = "PHOTOSTEREO_WEBHOOK_SECRETS",
        value_delimiter = ',',
        hide_env_values = true
    )]
    pub webhook_secrets: Vec<String>,

    /// How long a webhook delivery is retried (exponential backoff from 1 s) before it is
    /// given up as failed.
    #[arg(long, env = "PHOTOSTEREO_WEBHOOK_RETRY_FOR", default_value = "1h", value_parser = parse_duration)]
    pub webhook_retry_for: Duration,

    /// On SIGTERM or Ctrl-C, how long running jobs may go on finishing; jobs still running
    /// then are stopped within one step of work and run again at the next start.
    #[arg(long, env = "PHOTOSTEREO_SHUTDOWN_GRACE", default_value = "30s", value_parser = parse_duration)]
    pub shutdown_grace: Duration,

    /// Uploads whose images get their first pass (size, colour, the rows the robust
    /// solver samples) while they arrive, held for their job (0: off) [default: the
    /// number of workers].
    #[arg(long, env = "PHOTOSTEREO_DECODE_AHEAD", value_parser = clap::value_parser!(u32).range(0..=1024))]
    pub decode_ahead: Option<u32>,

    /// Memory that jobs, calibrations and re-shades may hold together, counted by their
    /// estimated peaks (a job: 80–104 bytes per pixel of one image plus a band): a job
    /// that does not fit waits in the queue, a calibration within its request, and a
    /// re-shade is answered 503 with Retry-After [default: three quarters of the
    /// machine's memory, or of the cgroup's memory limit when lower].
    #[arg(long, env = "PHOTOSTEREO_MEMORY_BUDGET", value_parser = parse_size)]
    pub memory_budget: Option<u64>,

    /// Uploads (job and calibration bodies) one tenant may be sending at once; past it,
    /// that tenant gets 503 with Retry-After while the other tenants keep the rest of the
    /// --max-uploads slots [default: half of --max-uploads, rounded up].
    #[arg(long, env = "PHOTOSTEREO_TENANT_MAX_UPLOADS", value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub tenant_max_uploads: Option<u32>,

    /// Calibrations one tenant may compute at once, of the --workers calibration slots;
    /// its next ones wait for one of its own to end [default: half of --workers, rounded
    /// up].
    #[arg(long, env = "PHOTOSTEREO_TENANT_MAX_CALIBRATIONS", value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub tenant_max_calibrations: Option<u32>,

    /// Re-shades (`shaded.png?light=`) computed at once; past it, 503 with Retry-After
    /// [default: the number of CPU cores].
    #[arg(long, env = "PHOTOSTEREO_MAX_RESHADES", value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub max_reshades: Option<u32>,

    /// Test hook: a pause at the start of every stage, and before a calibration is
    /// computed (holding its slot), so that tests of the real binary find work running.
    #[arg(long, env = "PHOTOSTEREO_TEST_STAGE_DELAY", hide = true, default_value = "0", value_parser = parse_duration)]
    pub stage_delay: Duration,

    /// Log format (the level is set with RUST_LOG, default `info`).
    #[arg(long, env = "PHOTOSTEREO_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,
}

/// The service's runtime settings (what [`ServeArgs`] resolves to; tests build it
/// directly).
#[derive(Debug, Clone)]
pub struct Config {
    pub data_dir: PathBuf,
    /// `s3://bucket[/prefix]`; none: the data directory.
    pub store: Option<String>,
    /// PostgreSQL for the job records (`postgres://…`); None: SQLite in `data_dir`.
    pub database_url: Option<String>,
    pub workers: usize,
    pub queue_length: usize,
    pub max_body_bytes: u64,
    pub max_images: usize,
    pub max_pixels: u64,
    pub max_input_bytes: u64,
    pub max_parts: usize,
    pub max_unpacked_bytes: u64,
    pub retention: Duration,
    pub job_timeout: Duration,
    /// A running job's lease (heartbeats come three times a lease).
    pub job_lease: Duration,
    pub max_uploads: usize,
    pub upload_timeout: Duration,
    pub min_free_disk: u64,
    /// HTTP connections open at once; None: from the open-files limit.
    pub max_connections: Option<usize>,
    pub header_timeout: Duration,
    pub keep_alive_timeout: Duration,
    pub send_timeout: Duration,
    /// `--api-key` values (`tenant:secret` or a bare secret).
    pub api_keys: Vec<String>,
    pub api_keys_file: Option<PathBuf>,
    /// Per tenant: jobs queued or running at once, submissions per minute (0: none),
    /// artifact bytes stored (0: none).
    pub tenant_max_jobs: usize,
    pub tenant_submissions_per_minute: usize,
    pub tenant_max_stored_bytes: u64,
    pub webhook_allow_hosts: Vec<String>,
    /// `tenant:secret` values.
    pub webhook_secrets: Vec<String>,
    pub webhook_retry_for: Duration,
    /// The first retry's delay (doubling after each failed attempt).
    pub webhook_first_retry: Duration,
    pub shutdown_grace: Duration,
    /// Uploads scanned ahead of their job at once.
    pub decode_ahead: usize,
    /// The memory budget (bytes) jobs, calibrations and re-shades reserve from.
    pub memory_budget: u64,
    /// Upload slots one tenant may hold; None: half of `max_uploads`, rounded up.
    pub tenant_max_uploads: Option<usize>,
    /// Calibration slots one tenant may hold; None: half of `workers`, rounded up.
    pub tenant_max_calibrations: Option<usize>,
    /// Re-shades at once.
    pub max_reshades: usize,
    /// How often expired jobs are looked for.
    pub sweep_interval: Duration,
    /// Test hook: a pause at the start of every stage (cancellable), to make jobs last,
    /// and before a calibration is computed.
    pub stage_delay: Duration,
    /// How often a job's event stream reads the job's record.
    pub event_interval: Duration,
}

/// Largest light table accepted (bytes).
pub const MAX_LIGHTS_BYTES: usize = 1 << 20;
/// Largest `options` part accepted (bytes).
pub const MAX_OPTIONS_BYTES: usize = 64 << 10;
/// Seconds a client is told to wait when the queue is full.
pub const RETRY_AFTER_SECS: u64 = 5;
/// How long an `Idempotency-Key`'s answer is kept and replayed.
pub const IDEMPOTENCY_WINDOW: Duration = Duration::from_secs(24 * 3600);

impl Config {
    /// The defaults of [`ServeArgs`], with the given data directory.
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        let workers = default_workers();
        Self {
            data_dir: data_dir.into(),
            store: None,
            database_url: None,
            workers,
            queue_length: 64,
            max_body_bytes: 2 << 30,
            max_images: 256,
            max_pixels: 33_554_432,
            max_input_bytes: 4 << 30,
            max_parts: 512,
            max_unpacked_bytes: 2 << 30,
            retention: Duration::from_secs(7 * 86_400),
            job_timeout: Duration::from_secs(30 * 60),
            job_lease: Duration::from_secs(30),
            max_uploads: 64,
            upload_timeout: Duration::from_secs(10 * 60),
            min_free_disk: 1 << 30,
            max_connections: None,
            header_timeout: Duration::from_secs(20),
            keep_alive_timeout: Duration::from_secs(75),
            send_timeout: Duration::from_secs(60),
            api_keys: Vec::new(),
            api_keys_file: None,
            tenant_max_jobs: 32,
            tenant_submissions_per_minute: 120,
            tenant_max_stored_bytes: 0,
            webhook_allow_hosts: Vec::new(),
            webhook_secrets: Vec::new(),
            webhook_retry_for: Duration::from_secs(3600),
            webhook_first_retry: Duration::from_secs(1),
            shutdown_grace: Duration::from_secs(30),
            decode_ahead: workers,
            memory_budget: default_budget(),
            tenant_max_uploads: None,
            tenant_max_calibrations: None,
            max_reshades: workers,
            sweep_interval: Duration::from_secs(60),
            stage_delay: Duration::ZERO,
            event_interval: Duration::from_millis(250),
        }
    }

    /// What the core's intake is allowed to decode.
    pub fn limits(&self) -> Limits {
        Limits {
            max_pixels_per_image: self.max_pixels,
            max_images: self.max_images,
        }
    }

    /// The upload slots one tenant may hold.
    pub fn tenant_upload_share(&self) -> usize {
        (self.tenant_max_uploads)
            .unwrap_or(self.max_uploads.div_ceil(2))
            .clamp(1, self.max_uploads.max(1))
    }

    /// The calibration slots one tenant may hold.
    pub fn tenant_calibration_share(&self) -> usize {
        (self.tenant_max_calibrations)
            .unwrap_or(self.workers.div_ceil(2))
            .clamp(1, self.workers.max(1))
    }
}

/// A lease of at least a second: heartbeats come three times a lease.
fn parse_lease(s: &str) -> Result<Duration, String> {
    let d = parse_duration(s)?;
    if d < Duration::from_secs(1) {
        return Err(format!("{s}: a lease is at least 1s"));
    }
    Ok(d)
}

/// A connection timeout: more than zero.
fn parse_timeout(s: &str) -> Result<Duration, String> {
    let d = parse_duration(s)?;
    if d.is_zero() {
        return Err(format!("{s}: a timeout is more than zero"));
    }
    Ok(d)
}

fn default_workers() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
}

impl From<&ServeArgs> for Config {
    fn from(a: &ServeArgs) -> Self {
        let mut c = Config::new(a.data_dir.clone());
        c.store = a.store.clone();
        c.database_url = a.database_url.clone();
        c.workers = a
            .workers
            .map(|w| w as usize)
            .unwrap_or_else(default_workers);
        c.queue_length = a.queue_length;
        c.max_body_bytes = a.max_body_bytes;
        c.max_images = a.max_images;
        c.max_pixels = a.max_pixels;
        c.max_input_bytes = a.max_input_bytes;
        c.max_parts = a.max_parts;
        c.max_unpacked_bytes = a.max_unpacked_bytes;
        c.retention = a.retention;
        c.job_timeout = a.job_timeout;
        c.job_lease = a.job_lease;
        c.max_uploads = a.max_uploads as usize;
        c.upload_timeout = a.upload_timeout;
        c.min_free_disk = a.min_free_disk;
        c.max_connections = a.max_connections.map(|n| n as usize);
        c.header_timeout = a.header_timeout;
        c.keep_alive_timeout = a.keep_alive_timeout;
        c.send_timeout = a.send_timeout;
        c.api_keys = a
            .api_keys
            .iter()
            .map(|k| k.trim().to_string())
            .filter(|k| !k.is_empty())
            .collect();
        c.api_keys_file = a.api_keys_file.clone();
        c.tenant_max_jobs = a.tenant_max_jobs as usize;
        c.tenant_submissions_per_minute = a.tenant_submissions_per_minute as usize;
        c.tenant_max_stored_bytes = a.tenant_max_stored_bytes;
        c.webhook_allow_hosts = a
            .webhook_allow_hosts
            .iter()
            .map(|h| h.trim().to_ascii_lowercase())
            .filter(|h| !h.is_empty())
            .collect();
        c.webhook_secrets = a.webhook_secrets.clone();
        c.webhook_retry_for = a.webhook_retry_for;
        c.shutdown_grace = a.shutdown_grace;
        c.decode_ahead = a.decode_ahead.map(|n| n as usize).unwrap_or(c.workers);
        c.stage_delay = a.stage_delay;
        c.memory_budget = a.memory_budget.unwrap_or(c.memory_budget);
        c.tenant_max_uploads = a.tenant_max_uploads.map(|n| n as usize);
        c.tenant_max_calibrations = a.tenant_max_calibrations.map(|n| n as usize);
        c.max_reshades = a.max_reshades.map_or(default_workers(), |n| n as usize);
        c.sweep_interval =
            (a.retention / 10).clamp(Duration::from_secs(1), Duration::from_secs(600));
        c
    }
}

/// The default memory budget: three quarters of the memory this process may use (the
/// machine's, or the cgroup's limit when lower), leaving the rest to the process's
/// fixed share, the uploads' buffers and the page cache the jobs read their bands from.
pub fn default_budget() -> u64 {
    let machine = meminfo_total().unwrap_or(4 << 30);
    let limit = cgroup_limit().map_or(machine, |c| c.min(machine));
    limit / 4 * 3
}

fn meminfo_total() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kb: u64 = text
        .lines()
        .find_map(|l| l.strip_prefix("MemTotal:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    Some(kb * 1024)
}

/// The memory limit of this process's cgroup (v2 `memory.max`, else v1
/// `memory.limit_in_bytes`), if one is set.
fn cgroup_limit() -> Option<u64> {
    let own = std::fs::read_to_string("/proc/self/cgroup").unwrap_or_default();
    let v2 = own
        .lines()
        .find_map(|l| l.strip_prefix("0::"))
        .map(|p| format!("/sys/fs/cgroup{}/memory.max", p.trim_end_matches('/')));
    let candidates = v2.into_iter().chain([
        "/sys/fs/cgroup/memory.max".to_string(),
        "/sys/fs/cgroup/memory/memory.limit_in_bytes".to_string(),
    ]);
    candidates
        .filter_map(|p| std::fs::read_to_string(p).ok())
        .filter_map(|t| t.trim().parse::<u64>().ok())
        // v1 reports "no limit" as a number near 2⁶³.
        .find(|&n| n < 1 << 60)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        serve: ServeArgs,
    }

    #[test]
    fn defaults_match_config_new() {
        let cli = Cli::try_parse_from(["x"]).unwrap();
        let c = Config::from(&cli.serve);
        let d = Config::new("./data");
        assert_eq!(cli.serve.listen, "127.0.0.1:8080");
        assert_eq!(c.data_dir, d.data_dir);
        assert_eq!(c.max_body_bytes, d.max_body_bytes);
        assert_eq!(c.max_pixels, d.max_pixels);
        assert_eq!(c.max_input_bytes, d.max_input_bytes);
        assert_eq!(c.retention, d.retention);
        assert_eq!(c.job_timeout, d.job_timeout);
        assert_eq!(c.job_lease, d.job_lease);
        assert_eq!(c.upload_timeout, d.upload_timeout);
        assert_eq!(c.max_uploads, d.max_uploads);
        assert_eq!(c.min_free_disk, d.min_free_disk);
        assert_eq!(c.max_unpacked_bytes, d.max_unpacked_bytes);
        assert_eq!(c.queue_length, d.queue_length);
        assert_eq!(c.max_parts, d.max_parts);
        assert_eq!(c.max_images, d.max_images);
        assert_eq!(c.max_connections, d.max_connections);
        assert_eq!(c.header_timeout, d.header_timeout);
        assert_eq!(c.keep_alive_timeout, d.keep_alive_timeout);
        assert_eq!(c.send_timeout, d.send_timeout);
        assert_eq!(c.tenant_max_jobs, d.tenant_max_jobs);
        assert_eq!(
            c.tenant_submissions_per_minute,
            d.tenant_submissions_per_minute
        );
        assert_eq!(c.tenant_max_stored_bytes, d.tenant_max_stored_bytes);
        assert!(c.workers >= 1);
        assert_eq!(c.decode_ahead, c.workers);
    }

    #[test]
    fn parses_units_and_repeated_keys() {
        let cli = Cli::try_parse_from([
            "x",
            "--retention",
            "2h",
            "--max-body-bytes",
            "10MiB",
            "--api-key",
            "a",
            "--api-key",
            "b,c",
            "--workers",
            "3",
        ])
        .unwrap();
        let c = Config::from(&cli.serve);
        assert_eq!(c.retention, Duration::from_secs(7200));
        assert_eq!(c.max_body_bytes, 10 << 20);
        assert_eq!(c.api_keys, ["a", "b", "c"]);
        assert_eq!(c.workers, 3);
        assert!(Cli::try_parse_from(["x", "--workers", "0"]).is_err());
        assert!(Cli::try_parse_from(["x", "--decode-ahead", "100000"]).is_err());
        let off = Cli::try_parse_from(["x", "--decode-ahead", "0"]).unwrap();
        assert_eq!(Config::from(&off.serve).decode_ahead, 0);
        let old = ["x", "--max-job-pixels", "700", "--max-input-bytes", "1MiB"];
        let old = Cli::try_parse_from(old).unwrap();
        assert_eq!(old.serve.max_job_pixels, Some(700), "still accepted");
        assert_eq!(Config::from(&old.serve).max_input_bytes, 1 << 20);
        assert!(Cli::try_parse_from(["x", "--retention", "soon"]).is_err());
        assert!(Cli::try_parse_from(["x", "--job-lease", "500ms"]).is_err());
        assert!(Cli::try_parse_from(["x", "--header-timeout", "0"]).is_err());
        assert!(Cli::try_parse_from(["x", "--max-connections", "0"]).is_err());
        let conns = ["x", "--max-connections", "10", "--keep-alive-timeout", "2s"];
        let conns = Config::from(&Cli::try_parse_from(conns).unwrap().serve);
        assert_eq!(conns.max_connections, Some(10));
        assert_eq!(conns.keep_alive_timeout, Duration::from_secs(2));
        let db = ["x", "--database-url", "postgres://u@127.0.0.1/p"];
        assert!(
            Cli::try_parse_from(db).is_err(),
            "a shared database needs a shared store"
        );
        let both = Cli::try_parse_from([&db[..], &["--store", "s3://b"]].concat()).unwrap();
        assert!(Config::from(&both.serve).database_url.is_some());
    }

    #[test]
    fn the_default_is_below_the_machine() {
        let d = default_budget();
        assert!(d > 0 && d < meminfo_total().unwrap());
    }
}
