//! The HTTP service: an axum shell around [`crate::core`].
//!
//! - [`app`]: the browser app at `/`, compiled in.
//! - [`routes`]: the handlers (typed extractors in, `Result<impl IntoResponse, ApiError>`
//!   out), documented with `#[utoipa::path]`.
//! - [`events`]: a job's server-sent event stream.
//! - [`jobs`]: the worker pool that claims and runs reconstructions.
//! - [`repo`]: job records behind [`repo::JobRepo`] (SQLite, or PostgreSQL).
//! - [`store`]: job inputs and artifacts behind [`store::BlobStore`] (a local directory,
//!   or an S3-compatible object store).
//! - [`error`]: [`ApiError`], every failure as RFC 9457 problem+json.
//! - [`config`]: [`ServeArgs`] (flags + environment) and [`Config`].
//! - [`connections`]: the accept loop, the connection cap and timeouts.
//!
//! [`router`] is what tests call; [`serve`] is `photostereo serve`.

mod app;
mod budget;
mod calibrations;
pub mod config;
mod connections;
mod download;
pub mod error;
mod events;
mod health;
mod idempotency;
pub mod jobs;
mod metrics;
mod openapi;
mod prefetch;
pub mod problem;
mod quota;
pub mod repo;
pub mod routes;
mod slots;
pub mod store;
pub mod tenants;
mod upload;
mod util;
mod webhooks;

use std::collections::HashSet;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use anyhow::Context;
use axum::Router;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;
use utoipa_swagger_ui::SwaggerUi;
use uuid::Uuid;

pub use config::{Config, LogFormat, ServeArgs};
pub use error::ApiError;
pub use health::{HealthcheckArgs, healthcheck};
pub use problem::Problem;
pub use upload::{parse_options, unpack_archive};

use budget::{Budget, Reservation};
use jobs::Workers;
use metrics::{Metrics, Snapshot};
use prefetch::{Prefetch, Prefetcher};
use repo::{JobRepo, JobStatus, RepoResult, SqliteRepo};
use slots::{Busy, Slot, Slots};
use store::{BlobStore, LocalStore};
use tenants::{Caller, Keyring};
use util::now_ms;

/// A job whose lease runs out on this attempt fails instead of running again: it may be
/// what kills its workers.
const MAX_ATTEMPTS: u32 = 3;

/// Everything the handlers and workers share. Cheap to clone.
#[derive(Clone)]
pub struct AppState {
    inner: Arc<Inner>,
}

pub(crate) struct Inner {
    config: Config,
    repo: Arc<dyn JobRepo>,
    store: Arc<dyn BlobStore>,
    workers: Workers,
    /// This instance's name on the leases it holds.
    owner: String,
    /// Uploads' images decoded ahead of their jobs.
    prefetch: Prefetcher,
    metrics: Metrics,
    /// Webhook signing secrets by tenant.
    webhook_secrets: std::collections::HashMap<String, Vec<u8>>,
    /// The job resource as JSON (what webhooks deliver).
    render_job: fn(repo::JobRecord) -> String,
    /// Where webhook deliveries run (workers are plain threads).
    runtime: tokio::runtime::Handle,
    /// Each tenant's submissions of the last minute.
    submissions: quota::SubmissionRate,
    /// The API keys in force (replaced whole when the keys file is re-read).
    keys: std::sync::RwLock<Arc<Keyring>>,
    shutting_down: AtomicBool,
    stop: watch::Sender<bool>,
    /// One slot per upload being received (`max_uploads`, a share per tenant).
    uploads: Arc<Slots>,
    /// One slot per calibration being computed (`workers`, a share per tenant), held
    /// until its work ends even when its client has gone.
    calibrating: Arc<Slots>,
    /// One slot per re-shade being computed (`max_reshades`).
    reshading: Arc<Slots>,
    /// What jobs, calibrations and re-shades reserve (`memory_budget`).
    budget: Arc<Budget>,
    /// Calibrations whose computation runs now, and the most at once.
    calibrations_computing: std::sync::atomic::AtomicUsize,
    calibrations_computing_max: std::sync::atomic::AtomicUsize,
    /// The data directory's lock file, held (flock) while this server uses it, so that a
    /// second server cannot run the same jobs or tidy away the first one's uploads.
    data_lock: std::sync::Mutex<Option<std::fs::File>>,
}

impl AppState {
    /// Open the data directory (database, job files), put every unfinished job back in the
    /// queue, start the workers and the background sweeper.
    pub async fn open(config: Config) -> anyhow::Result<Self> {
        let state = tokio::task::spawn_blocking(move || Self::open_blocking(config))
            .await
            .context("opening the service state")??;
        state.spawn_background();
        Ok(state)
    }

    fn open_blocking(config: Config) -> anyhow::Result<Self> {
        std::fs::create_dir_all(&config.data_dir).with_context(|| {
            format!(
                "cannot create the data directory {}",
                config.data_dir.display()
            )
        })?;
        if config.database_url.is_some() && config.store.is_none() {
            anyhow::bail!(
                "--database-url needs --store: instances that share the job database must share its files"
            );
        }
        anyhow::ensure!(
            config.job_lease >= Duration::from_secs(1),
            "--job-lease must be at least 1s"
        );
        let keys = Keyring::load(&config.api_keys, config.api_keys_file.as_deref())?;
        let webhook_secrets = webhooks::parse_secrets(&config.webhook_secrets)?;
        let data_lock = lock_data_dir(&config.data_dir)?;
        let repo: Arc<dyn JobRepo> = match &config.database_url {
            None => {
                let db = config.data_dir.join("jobs.sqlite");
                Arc::new(
                    SqliteRepo::open(&db).with_context(|| format!("opening {}", db.display()))?,
                )
            }
            Some(url) => {
                Arc::new(repo::PostgresRepo::connect(url).context("opening the job database")?)
            }
        };
        let store: Arc<dyn BlobStore> = match &config.store {
            None => Arc::new(
                LocalStore::open(&config.data_dir)
                    .with_context(|| format!("opening {}", config.data_dir.display()))?,
            ),
            // Another instance may be committing an upload the repo does not know yet.
            Some(url) => Arc::new(store::S3Store::open(
                url,
                &config.data_dir.join("scratch"),
                tokio::runtime::Handle::current(),
                config.upload_timeout + Duration::from_secs(3600),
            )?),
        };
        let (stop, _) = watch::channel(false);
        anyhow::ensure!(
            config.memory_budget >= 64 << 20,
            "--memory-budget must be at least 64MiB"
        );
        let uploads = Slots::new(config.max_uploads, config.tenant_upload_share());
        let calibrating = Slots::new(config.workers, config.tenant_calibration_share());
        let reshading = Slots::new(config.max_reshades, config.max_reshades);
        let budget = Budget::new(config.memory_budget);
        let submissions = quota::SubmissionRate::new(config.tenant_submissions_per_minute);
        let inner = Arc::new(Inner {
            workers: Workers::default(),
            owner: format!("{}-{}", std::process::id(), Uuid::new_v4().simple()),
            prefetch: Prefetcher::new(config.decode_ahead, config.limits()),
            config,
            repo,
            store,
            metrics: Metrics::default(),
            keys: std::sync::RwLock::new(Arc::new(keys)),
            submissions,
            webhook_secrets,
            render_job: routes::job_json,
            runtime: tokio::runtime::Handle::current(),
            shutting_down: AtomicBool::new(false),
            stop,
            uploads,
            calibrating,
            reshading,
            budget,
            calibrations_computing: Default::default(),
            calibrations_computing_max: Default::default(),
            data_lock: std::sync::Mutex::new(Some(data_lock)),
        });
        let requeued = recover(&inner)?;
        if requeued > 0 {
            tracing::info!(jobs = requeued, "unfinished jobs queued again");
        }
        match webhooks::resume(&inner) {
            Ok(0) => {}
            Ok(n) => tracing::info!(jobs = n, "undelivered webhooks resumed"),
            Err(e) => tracing::warn!(error = %e, "cannot resume undelivered webhooks"),
        }
        for i in 0..inner.config.workers.max(1) {
            let worker = inner.clone();
            let handle = std::thread::Builder::new()
                .name(format!("photostereo-worker-{i}"))
                .spawn(move || jobs::worker_loop(worker))
                .context("starting a worker thread")?;
            inner.workers.add_thread(handle);
        }
        let bell = inner.clone();
        inner.repo.subscribe(Arc::new(move || bell.workers.ring()));
        Ok(Self { inner })
    }

    fn spawn_background(&self) {
        let inner = self.inner.clone();
        let mut stop = self.inner.stop.subscribe();
        tokio::spawn(async move {
            let mut sweep = tokio::time::interval(inner.config.sweep_interval);
            // Three beats to a lease: one late beat does not lose it.
            let mut beat = tokio::time::interval(inner.config.job_lease / 3);
            loop {
                tokio::select! {
                    _ = sweep.tick() => {
                        let i = inner.clone();
                        let _ = tokio::task::spawn_blocking(move || sweep_expired(&i)).await;
                    }
                    _ = beat.tick() => {
                        let i = inner.clone();
                        let _ = tokio::task::spawn_blocking(move || {
                            heartbeat(&i);
                            reap(&i);
                            forget_prefetched(&i);
                        })
                        .await;
                    }
                    _ = stop.changed() => break,
                }
            }
        });
    }

    pub fn config(&self) -> &Config {
        &self.inner.config
    }

    pub fn workers(&self) -> &Workers {
        &self.inner.workers
    }

    pub fn store(&self) -> &dyn BlobStore {
        &*self.inner.store
    }

    /// The most jobs that were ever running at once (never more than the pool size).
    pub fn max_running(&self) -> usize {
        self.inner.workers.running_max()
    }

    /// Run a repo call off the async runtime.
    pub async fn repo<T, F>(&self, f: F) -> Result<T, ApiError>
    where
        T: Send + 'static,
        F: FnOnce(&dyn JobRepo) -> RepoResult<T> + Send + 'static,
    {
        let repo = self.inner.repo.clone();
        Ok(tokio::task::spawn_blocking(move || f(&*repo)).await??)
    }

    /// The keys in force.
    pub(crate) fn keys(&self) -> Arc<Keyring> {
        self.inner
            .keys
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Read `--api-key` and the keys file again (what SIGHUP does). On an error the keys
    /// in force stay; the error names the line at fault.
    pub fn reload_keys(&self) -> anyhow::Result<usize> {
        let config = &self.inner.config;
        let keys = Keyring::load(&config.api_keys, config.api_keys_file.as_deref())?;
        let n = keys.count();
        *self.inner.keys.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(keys);
        Ok(n)
    }

    pub fn is_shutting_down(&self) -> bool {
        self.inner.shutting_down.load(Ordering::SeqCst)
    }

    /// Stop taking work: readiness fails, new submissions get 503, workers take no new
    /// jobs (queued ones stay queued for the next start), background tasks stop.
    pub fn begin_shutdown(&self) {
        if self.inner.shutting_down.swap(true, Ordering::SeqCst) {
            return;
        }
        self.inner.workers.close();
        let _ = self.inner.stop.send(true);
    }

    /// [`begin_shutdown`](Self::begin_shutdown), then let running jobs finish for up to
    /// the shutdown grace; jobs still running then are interrupted within one step of work
    /// and run again at the next start.
    pub async fn shutdown(&self) {
        self.begin_shutdown();
        let jobs = &self.inner.workers;
        let deadline = Instant::now() + self.inner.config.shutdown_grace;
        while jobs.busy() > 0 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        if jobs.busy() > 0 {
            tracing::warn!(
                jobs = jobs.busy(),
                "interrupting running jobs; they run again"
            );
            jobs.interrupt_all();
            let until = Instant::now() + Duration::from_secs(10);
            while jobs.busy() > 0 && Instant::now() < until {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        jobs.join_finished_threads();
        // Let a next server (a restart in the same process) have the data directory.
        if let Ok(mut lock) = self.inner.data_lock.lock() {
            lock.take();
        }
        tracing::info!("stopped");
    }

    /// A slot to receive one upload for `tenant`, or 503 when `max_uploads` are under
    /// way or the tenant holds its share of them.
    pub(crate) fn upload_slot(&self, tenant: &str) -> Result<Slot, ApiError> {
        let uploads = &self.inner.uploads;
        uploads.try_take(tenant).map_err(|busy| {
            let detail = match busy {
                Busy::Full => format!(
                    "{} uploads are being received already (the limit); retry later",
                    uploads.total()
                ),
                Busy::TenantShare => format!(
                    "tenant {tenant} is sending {} uploads already (its share of the {} upload slots); retry later",
                    uploads.per_tenant(),
                    uploads.total()
                ),
            };
            ApiError::unavailable(config::RETRY_AFTER_SECS, detail)
        })
    }

    /// A slot and the memory to compute one calibration for `tenant`, waited for (a
    /// tenant holding its share waits for one of its own to end).
    pub(crate) async fn calibration_slot(&self, tenant: &str) -> Computing {
        let slot = self.inner.calibrating.take(tenant).await;
        let peak = budget::calibration_peak_bytes(&self.inner.config);
        let memory = self
            .inner
            .budget
            .reserve(budget::Use::Calibration, peak)
            .await;
        Computing {
            inner: self.inner.clone(),
            _slot: slot,
            _memory: memory,
        }
    }

    /// A slot and the memory to re-shade a `width × height` job now, or 503.
    pub(crate) fn reshade_slot(
        &self,
        tenant: &str,
        width: u64,
        height: u64,
    ) -> Result<(Slot, Reservation), ApiError> {
        let slot = self.inner.reshading.try_take(tenant).map_err(|_| {
            ApiError::unavailable(
                1,
                format!(
                    "{} re-shades are being computed already (the limit); retry later",
                    self.inner.reshading.total()
                ),
            )
        })?;
        let bytes = budget::reshade_peak_bytes(width, height);
        let memory = (self.inner.budget)
            .try_reserve(budget::Use::Reshade, bytes)
            .ok_or_else(|| {
                ApiError::unavailable(
                    1,
                    format!(
                        "the memory budget has no room for a re-shade of {width}×{height} now ({bytes} bytes); retry later"
                    ),
                )
            })?;
        Ok((slot, memory))
    }

    pub(crate) fn count_submitted(&self) {
        self.inner.metrics.submitted.fetch_add(1, Ordering::Relaxed);
    }

    /// The tenant's quotas before an upload is read: submissions per minute (counting
    /// this one), jobs queued or running, stored bytes. The insert checks the active
    /// jobs again ([`Self::over_active_jobs`]), as uploads run concurrently.
    pub(crate) async fn check_quotas(&self, tenant: &str) -> Result<(), ApiError> {
        let config = &self.inner.config;
        self.admit_submission(tenant)?;
        let t = tenant.to_string();
        let active = self.repo(move |r| r.active(&t)).await?;
        if active >= config.tenant_max_jobs as u64 {
            return Err(self.over_active_jobs(tenant));
        }
        let max_bytes = config.tenant_max_stored_bytes;
        if max_bytes > 0 {
            let t = tenant.to_string();
            let stored = self.repo(move |r| r.stored_bytes(&t)).await?;
            if stored >= max_bytes {
                return Err(self.refuse(
                    tenant,
                    quota::Limit::StoredBytes,
                    config::RETRY_AFTER_SECS,
                    format!(
                        "tenant {tenant} stores {stored} bytes of artifacts, the limit is {max_bytes}: delete finished jobs to make room"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The submission rate (jobs and calibrations together), counting this one.
    pub(crate) fn admit_submission(&self, tenant: &str) -> Result<(), ApiError> {
        self.inner.submissions.admit(tenant).map_err(|wait| {
            self.refuse(
                tenant,
                quota::Limit::SubmissionsPerMinute,
                quota::retry_secs(wait),
                format!(
                    "tenant {tenant} has made {} submissions in the last minute (the limit)",
                    self.inner.submissions.per_minute()
                ),
            )
        })
    }

    /// 429 for a tenant at its limit of jobs queued or running.
    pub(crate) fn over_active_jobs(&self, tenant: &str) -> ApiError {
        let max = self.inner.config.tenant_max_jobs;
        self.refuse(
            tenant,
            quota::Limit::ActiveJobs,
            config::RETRY_AFTER_SECS,
            format!(
                "tenant {tenant} has {max} jobs queued or running, the limit; retry when one has finished"
            ),
        )
    }

    fn refuse(&self, tenant: &str, limit: quota::Limit, retry: u64, detail: String) -> ApiError {
        self.inner
            .metrics
            .observe_quota_refusal(tenant, limit.as_str());
        ApiError::quota_exceeded(retry, detail)
    }

    /// Whether `tenant` has a webhook secret (callbacks need one).
    pub(crate) fn has_webhook_secret(&self, tenant: &str) -> bool {
        self.inner.webhook_secrets.contains_key(tenant)
    }

    /// A job has ended outside a worker (cancelled while queued): deliver its webhook.
    pub(crate) fn job_ended(&self, id: Uuid) {
        let inner = self.inner.clone();
        tokio::task::spawn_blocking(move || webhooks::job_ended(&inner, id));
    }

    pub(crate) fn count_queue_full(&self) {
        self.inner
            .metrics
            .rejected_queue_full
            .fetch_add(1, Ordering::Relaxed);
    }

    /// 507 when the data directory's file system is short of space.
    pub(crate) async fn check_free_disk(&self) -> Result<(), ApiError> {
        let min = self.inner.config.min_free_disk;
        if min == 0 {
            return Ok(());
        }
        let store = self.inner.store.clone();
        match tokio::task::spawn_blocking(move || store.free_bytes()).await? {
            Ok(free) if free < min => Err(ApiError::insufficient_storage(format!(
                "only {free} bytes are free for job data; new jobs need at least {min}"
            ))),
            Ok(_) => Ok(()),
            Err(e) => {
                tracing::warn!(error = %e, "cannot read free disk space");
                Ok(())
            }
        }
    }

    /// A staging directory for an upload, removed again unless kept.
    pub(crate) async fn stage_upload(&self, id: Uuid) -> Result<Staging, ApiError> {
        self.stage(Staged::Job, id).await
    }

    /// A fresh staging directory for a calibration's upload.
    pub(crate) async fn stage_calibration(&self, id: Uuid) -> Result<Staging, ApiError> {
        self.stage(Staged::Calibration, id).await
    }

    async fn stage(&self, kind: Staged, id: Uuid) -> Result<Staging, ApiError> {
        let store = self.inner.store.clone();
        let path = tokio::task::spawn_blocking(move || match kind {
            Staged::Job => store.stage_inputs(id),
            Staged::Calibration => store.stage_calibration(id),
        })
        .await??;
        Ok(Staging {
            state: self.clone(),
            kind,
            id,
            path,
            keep: false,
        })
    }

    /// A set to decode a new upload's images into ahead of its job, if a slot is free.
    pub(crate) fn begin_prefetch(&self) -> Option<Prefetch> {
        self.inner.prefetch.begin()
    }

    /// Keep an accepted job's decoded images for its worker.
    pub(crate) fn park_prefetch(&self, id: Uuid, set: Prefetch) {
        self.inner.prefetch.park(id, set);
    }

    /// Drop the images decoded ahead for a job, if any.
    pub(crate) fn remove_prefetch(&self, id: Uuid) {
        self.inner.prefetch.discard(id);
    }

    /// Remove a job's files and any images decoded ahead for it (errors are logged).
    pub(crate) async fn remove_files(&self, id: Uuid) {
        self.inner.prefetch.discard(id);
        let store = self.inner.store.clone();
        match tokio::task::spawn_blocking(move || store.remove_job(id)).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::warn!(job = %id, error = %e, "cannot remove job files"),
            Err(e) => tracing::warn!(job = %id, error = %e, "cannot remove job files"),
        }
    }

    pub(crate) async fn readiness_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.is_shutting_down() {
            problems.push("the service is shutting down".to_string());
        }
        let uploads = &self.inner.uploads;
        if uploads.taken() >= uploads.total() {
            problems.push(format!(
                "every upload slot is taken ({} uploads being received)",
                uploads.total()
            ));
        }
        let budget = &self.inner.budget;
        let job = budget::job_worst_bytes(&self.inner.config).min(budget.limit());
        if budget.free() < job {
            problems.push(format!(
                "the memory budget has no room for another job ({} of {} bytes free, a job may need {job})",
                budget.free(),
                budget.limit()
            ));
        }
        if let Err(e) = self.repo(|r| r.ping()).await {
            problems.push(format!("the job database does not answer ({})", e.detail()));
        }
        let store = self.inner.store.clone();
        match tokio::task::spawn_blocking(move || store.probe_writable()).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => problems.push(format!("the data directory is not writable: {e}")),
            Err(e) => problems.push(format!("the data directory check failed: {e}")),
        }
        problems
    }

    pub(crate) async fn render_metrics(&self) -> Result<String, ApiError> {
        let counts = self.repo(|r| r.counts()).await?;
        let by_tenant = self.repo(|r| r.counts_by_tenant()).await?;
        let store = self.inner.store.clone();
        let free = tokio::task::spawn_blocking(move || store.free_bytes().ok()).await?;
        let jobs = &self.inner.workers;
        let queued = counts
            .iter()
            .find(|(s, _)| *s == JobStatus::Queued)
            .map_or(0, |(_, n)| *n as usize);
        let mut text = self.inner.metrics.render(&Snapshot {
            jobs_by_status: counts,
            jobs_by_tenant: by_tenant,
            queue_depth: queued,
            queue_capacity: self.inner.config.queue_length,
            running: jobs.running(),
            running_max: jobs.running_max(),
            workers: self.inner.config.workers,
            free_disk_bytes: free,
            prefetch_sets: self.inner.prefetch.held(),
        });
        self.inner.budget.render(&mut text);
        self.render_slots(&mut text);
        Ok(text)
    }

    /// The slot gauges and refusals (uploads, calibrations, re-shades).
    fn render_slots(&self, out: &mut String) {
        use std::fmt::Write as _;
        let inner = &self.inner;
        let computing = inner.calibrations_computing.load(Ordering::SeqCst);
        let most = inner.calibrations_computing_max.load(Ordering::SeqCst);
        let gauges = [
            (
                "photostereo_upload_slots",
                "Uploads that may be received at once.",
                inner.uploads.total(),
            ),
            (
                "photostereo_upload_slots_per_tenant",
                "Upload slots one tenant may hold.",
                inner.uploads.per_tenant(),
            ),
            (
                "photostereo_uploads_receiving",
                "Uploads being received now.",
                inner.uploads.taken(),
            ),
            (
                "photostereo_calibration_slots_taken",
                "Calibration slots held now (until each calibration's work ends).",
                inner.calibrating.taken(),
            ),
            (
                "photostereo_calibrations_waiting",
                "Calibrations waiting for a slot or for memory.",
                inner.calibrating.waiting(),
            ),
            (
                "photostereo_calibrations_computing",
                "Calibrations computing now.",
                computing,
            ),
            (
                "photostereo_calibrations_computing_max",
                "Most calibrations ever computing at once since start.",
                most,
            ),
            (
                "photostereo_reshade_slots",
                "Re-shades that may be computed at once.",
                inner.reshading.total(),
            ),
            (
                "photostereo_reshades_running",
                "Re-shades being computed now.",
                inner.reshading.taken(),
            ),
        ];
        for (name, help, v) in gauges {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        }
        let name = "photostereo_slot_refusals_total";
        let _ = writeln!(
            out,
            "# HELP {name} Requests refused (503) for want of a slot: every slot taken, or the tenant's share.\n# TYPE {name} counter"
        );
        for (what, slots) in [("upload", &inner.uploads), ("reshade", &inner.reshading)] {
            let (full, share) = slots.refusals();
            let _ = writeln!(out, "{name}{{slots=\"{what}\",reason=\"full\"}} {full}");
            let _ = writeln!(
                out,
                "{name}{{slots=\"{what}\",reason=\"tenant_share\"}} {share}"
            );
        }
    }
}

/// A calibration's slot and memory, held by its computation (moved into the blocking
/// task, so a client that goes away does not free them while the work goes on).
pub(crate) struct Computing {
    inner: Arc<Inner>,
    _slot: Slot,
    _memory: Reservation,
}

impl Computing {
    /// Run the calibration's computation `f` on this thread (a blocking one); the slot and
    /// the memory are given back when it ends.
    pub(crate) fn run<T>(self, f: impl FnOnce() -> T) -> T {
        let counted = CountedWork::start(
            &self.inner.calibrations_computing,
            &self.inner.calibrations_computing_max,
        );
        let delay = self.inner.config.stage_delay;
        if !delay.is_zero() {
            std::thread::sleep(delay);
        }
        let out = f();
        drop(counted);
        out
    }
}

impl Drop for Computing {
    /// The work has ended (or panicked): its freed memory goes back to the kernel before
    /// the slot and the reservation do.
    fn drop(&mut self) {
        crate::core::heap::release_free_heap();
    }
}

/// One unit of work counted in a gauge (and its most at once) while it runs.
struct CountedWork<'a>(&'a std::sync::atomic::AtomicUsize);

impl<'a> CountedWork<'a> {
    fn start(
        now: &'a std::sync::atomic::AtomicUsize,
        most: &std::sync::atomic::AtomicUsize,
    ) -> Self {
        let n = now.fetch_add(1, Ordering::SeqCst) + 1;
        most.fetch_max(n, Ordering::SeqCst);
        Self(now)
    }
}

impl Drop for CountedWork<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

/// What a [`Staging`] directory receives.
#[derive(Debug, Clone, Copy)]
enum Staged {
    Job,
    Calibration,
}

/// An upload's staging directory; removed (with the job's or calibration's directory)
/// when dropped unless [`keep`](Staging::keep) was called.
pub(crate) struct Staging {
    state: AppState,
    kind: Staged,
    id: Uuid,
    path: PathBuf,
    keep: bool,
}

impl Staging {
    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// Make the upload the job's inputs (or the calibration's files), durably.
    pub(crate) async fn commit(&mut self) -> Result<(), ApiError> {
        let store = self.state.inner.store.clone();
        let (kind, id) = (self.kind, self.id);
        tokio::task::spawn_blocking(move || match kind {
            Staged::Job => store.commit_inputs(id),
            Staged::Calibration => store.commit_calibration(id),
        })
        .await??;
        Ok(())
    }

    pub(crate) fn keep(&mut self) {
        self.keep = true;
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if self.keep {
            return;
        }
        let store = self.state.inner.store.clone();
        let (kind, id) = (self.kind, self.id);
        let remove = move || {
            let removed = match kind {
                Staged::Job => store.remove_job(id),
                Staged::Calibration => store.remove_calibration(id),
            };
            if let Err(e) = removed {
                tracing::warn!(?kind, %id, error = %e, "cannot remove a refused upload");
            }
        };
        match tokio::runtime::Handle::try_current() {
            Ok(rt) => {
                rt.spawn_blocking(remove);
            }
            Err(_) => remove(),
        }
    }
}

/// Startup: drop leftovers, put unfinished jobs back in the queue (oldest first).
fn recover(inner: &Inner) -> anyhow::Result<usize> {
    let known: HashSet<Uuid> = inner.repo.ids()?.into_iter().collect();
    for id in listed(inner.store.job_ids(), "jobs") {
        let tidy = if known.contains(&id) {
            inner.store.remove_partials(id).and_then(|()| {
                // A stop between recording a job's end and removing its inputs.
                match inner.repo.get(id) {
                    Ok(Some(rec)) if rec.status.is_terminal() => inner.store.remove_inputs(id),
                    _ => Ok(()),
                }
            })
        } else {
            inner.store.remove_job(id) // an upload that never became a job
        };
        if let Err(e) = tidy {
            tracing::warn!(job = %id, error = %e, "cannot tidy job files");
        }
    }
    // Calibration files are committed before their record: files without one are a
    // calibration that was never answered.
    let calibrations: HashSet<Uuid> = inner.repo.calibration_ids()?.into_iter().collect();
    for id in listed(inner.store.calibration_ids(), "calibrations") {
        if !calibrations.contains(&id)
            && let Err(e) = inner.store.remove_calibration(id)
        {
            tracing::warn!(calibration = %id, error = %e, "cannot tidy calibration files");
        }
    }
    let queued = if inner.config.database_url.is_some() {
        // Other instances may hold running jobs: expired leases are the reaper's.
        0
    } else {
        // A single node: no one else holds a job, so every running one was cut off.
        inner.repo.release_running()?;
        let mut queued = 0;
        for rec in inner.repo.unfinished()? {
            // A store that does not answer now may later: the job stays queued and waits.
            if let Ok(false) = inner.store.has_inputs(rec.id) {
                let problem = ApiError::job_failed(
                    "the job's input files are gone (the data directory changed while the service was stopped)",
                )
                .with_instance(format!("/v1/jobs/{}", rec.id))
                .problem();
                inner.repo.fail_queued(rec.id, &problem, now_ms())?;
                continue;
            }
            queued += 1;
        }
        queued
    };
    sweep_expired(inner);
    Ok(queued)
}

/// Extend the leases of the jobs running here; stop those no longer held (cancelled on
/// another instance, or reaped).
fn heartbeat(inner: &Inner) {
    let leases = inner.workers.leases();
    if leases.is_empty() {
        return;
    }
    let lost = match inner
        .repo
        .heartbeat(&leases, inner.config.job_lease, now_ms())
    {
        Ok(lost) => lost,
        Err(e) => {
            tracing::warn!(error = %e, "cannot extend the running jobs' leases");
            return;
        }
    };
    for lease in lost {
        let cancelled = matches!(
            inner.repo.get(lease.id),
            Ok(Some(rec)) if rec.status == JobStatus::Cancelled
        );
        if cancelled {
            inner.workers.cancel_running(lease.id);
        } else {
            inner.workers.lose(lease.id);
        }
    }
}

/// Drop the images decoded ahead for jobs another instance claimed (or that ended): only
/// the instance that received an upload has them, and any instance may claim its job.
fn forget_prefetched(inner: &Inner) {
    for id in inner.prefetch.parked() {
        if inner.workers.is_held(id) {
            continue;
        }
        match inner.repo.get(id) {
            Ok(Some(rec)) if rec.status == JobStatus::Queued => {}
            Ok(_) => inner.prefetch.discard(id),
            Err(e) => tracing::debug!(job = %id, error = %e, "cannot read the job"),
        }
    }
}

/// Put jobs whose lease ran out (their worker died, here or on another instance) back in
/// the queue, or fail them after their last attempt.
fn reap(inner: &Inner) {
    let failure = |id: Uuid| {
        ApiError::job_failed(format!(
            "the job's worker stopped answering on each of its {MAX_ATTEMPTS} attempts; it is not run again"
        ))
        .with_instance(format!("/v1/jobs/{id}"))
        .problem()
    };
    match inner.repo.reap(MAX_ATTEMPTS, &failure, now_ms()) {
        Ok(reaped) => {
            if !reaped.requeued.is_empty() {
                tracing::warn!(jobs = ?reaped.requeued, "leases ran out; the jobs run again");
                inner.workers.ring();
            }
            for id in reaped.failed {
                tracing::warn!(job = %id, "lease ran out on the last attempt; the job failed");
                if let Err(e) = inner.store.remove_inputs(id) {
                    tracing::warn!(job = %id, error = %e, "cannot remove the job's inputs");
                }
                webhooks::job_ended(inner, id);
            }
        }
        Err(e) => tracing::warn!(error = %e, "cannot reap expired leases"),
    }
}

/// What a store listing found; nothing (and a warning) when the store does not answer,
/// so that a start never waits for it.
fn listed(ids: store::Result<Vec<Uuid>>, what: &str) -> Vec<Uuid> {
    ids.unwrap_or_else(|e| {
        tracing::warn!(error = %e, "cannot list the stored {what}; leftovers stay");
        Vec::new()
    })
}

/// Delete finished jobs past the retention period: the record first (the job is gone from
/// the API at once), then the files.
fn sweep_expired(inner: &Inner) {
    let retention = i64::try_from(inner.config.retention.as_millis()).unwrap_or(i64::MAX);
    let cutoff = now_ms().saturating_sub(retention);
    let ids = match inner.repo.expired(cutoff, 1000) {
        Ok(ids) => ids,
        Err(e) => {
            tracing::warn!(error = %e, "cannot list expired jobs");
            return;
        }
    };
    let stale = now_ms() - idempotency::WINDOW.as_millis() as i64;
    if let Err(e) = inner.repo.forget_idempotent(stale) {
        tracing::warn!(error = %e, "cannot forget old idempotency keys");
    }
    for id in ids {
        match inner.repo.delete(id) {
            Ok(_) => {
                if let Err(e) = inner.store.remove_job(id) {
                    tracing::warn!(job = %id, error = %e, "cannot remove expired job files");
                } else {
                    tracing::info!(job = %id, "expired job removed");
                }
            }
            Err(e) => tracing::warn!(job = %id, error = %e, "cannot delete expired job"),
        }
    }
}

/// The `/v1` routes (behind the API key when one is configured).
fn api_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        .routes(routes!(routes::create_job, routes::list_jobs))
        .routes(routes!(routes::get_job, routes::delete_job))
        .routes(routes!(routes::get_artifact))
        .routes(routes!(events::job_events))
        .routes(routes!(
            calibrations::create_calibration,
            calibrations::list_calibrations
        ))
        .routes(routes!(
            calibrations::get_calibration,
            calibrations::delete_calibration
        ))
        .routes(routes!(calibrations::get_lights_csv))
        .routes(routes!(calibrations::get_overlay))
        .routes(routes!(calibrations::get_lights_png))
        .routes(routes!(calibrations::get_positions_csv))
}

/// Health, readiness, metrics, the OpenAPI document (always open).
fn operations_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::default()
        .routes(routes!(routes::healthz))
        .routes(routes!(routes::readyz))
        .routes(routes!(routes::metrics))
        .routes(routes!(routes::openapi_doc))
}

/// The OpenAPI document served at `/openapi.json` (pretty JSON, trailing newline), also
/// what `photostereo openapi` prints and `openapi/openapi.json` holds.
pub fn openapi_json() -> String {
    static DOC: OnceLock<String> = OnceLock::new();
    DOC.get_or_init(|| {
        let mut doc = api_routes().merge(operations_routes()).into_openapi();
        openapi::name_artifacts(&mut doc);
        let mut text = doc
            .to_pretty_json()
            .expect("the OpenAPI document serialises");
        text.push('\n');
        text
    })
    .clone()
}

/// The whole HTTP app over `state`.
pub fn router(state: AppState) -> Router {
    let max_body = usize::try_from(state.inner.config.max_body_bytes).unwrap_or(usize::MAX);
    let api = api_routes().route_layer(middleware::from_fn_with_state(state.clone(), authenticate));
    let (app, _) = api.merge(operations_routes()).split_for_parts();
    app.merge(SwaggerUi::new("/docs").config(utoipa_swagger_ui::Config::new(["/openapi.json"])))
        .route("/", axum::routing::get(app::page))
        .route("/app/auth.json", axum::routing::get(app::auth))
        .route("/app/{name}", axum::routing::get(app::asset))
        .fallback(routes::not_found)
        .method_not_allowed_fallback(routes::method_not_allowed)
        .layer(middleware::from_fn_with_state(state.clone(), track_http))
        .layer(DefaultBodyLimit::max(max_body))
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(|req: &Request| {
                    let id = req
                        .headers()
                        .get("x-request-id")
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or("-");
                    tracing::info_span!(
                        "request",
                        method = %req.method(),
                        path = %req.uri().path(),
                        request_id = %id
                    )
                })
                .on_response(DefaultOnResponse::new().level(tracing::Level::INFO)),
        )
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        .layer(CatchPanicLayer::custom(routes::panic_response))
        .with_state(state)
}

/// Take the data directory's lock file, or say which directory is in use.
fn lock_data_dir(dir: &std::path::Path) -> anyhow::Result<std::fs::File> {
    let path = dir.join("lock");
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| format!("opening {}", path.display()))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => anyhow::bail!(
            "the data directory {} is in use by another photostereo server (it holds {})",
            dir.display(),
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => {
            Err(e).with_context(|| format!("locking {}", path.display()))
        }
    }
}

/// `Authorization: Bearer <key>` on the /v1 routes when keys are configured: the key's
/// [`Caller`] goes into the request's extensions. With no keys, every caller is
/// [`Caller::open`].
async fn authenticate(State(state): State<AppState>, mut req: Request, next: Next) -> Response {
    // Which of two keys would count is ambiguous between proxies and servers: refuse both.
    if req
        .headers()
        .get_all(header::AUTHORIZATION)
        .iter()
        .nth(1)
        .is_some()
    {
        let tap = upload::BodyTap::new(req.into_body(), state.inner.config.max_body_bytes);
        tokio::spawn(async move { tap.drain(upload::LINGER).await });
        return ApiError::bad_request("send one Authorization header, not several").into_response();
    }
    let keys = state.keys();
    if keys.is_open() {
        req.extensions_mut().insert(Caller::open());
        return next.run(req).await;
    }
    let presented = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            let (scheme, key) = v.trim().split_once(' ')?;
            scheme
                .eq_ignore_ascii_case("bearer")
                .then(|| key.trim().to_string())
        });
    let Some(presented) = presented else {
        return refuse_unauthorized(
            &state,
            req,
            "this server needs an API key: send Authorization: Bearer <key>",
        );
    };
    match keys.find(&presented) {
        Some(caller) => {
            req.extensions_mut().insert(caller);
            next.run(req).await
        }
        None => refuse_unauthorized(&state, req, "the API key is not valid"),
    }
}

/// 401, reading what the client is still uploading in the background (bounded by the body
/// limit and [`upload::LINGER`]) so that it sees the answer rather than a broken pipe.
fn refuse_unauthorized(state: &AppState, req: Request, detail: &str) -> Response {
    let tap = upload::BodyTap::new(req.into_body(), state.inner.config.max_body_bytes);
    tokio::spawn(async move { tap.drain(upload::LINGER).await });
    ApiError::unauthorized(detail).into_response()
}

/// Count requests by method, route template and status.
async fn track_http(State(state): State<AppState>, req: Request, next: Next) -> Response {
    const METHODS: [&str; 7] = ["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"];
    let method = req.method().as_str();
    let method = METHODS
        .iter()
        .find(|m| **m == method)
        .copied()
        .unwrap_or("other");
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_string())
        .unwrap_or_else(|| "unmatched".to_string());
    let started = Instant::now();
    let response = next.run(req).await;
    state.inner.metrics.observe_http(
        method,
        &route,
        response.status().as_u16(),
        started.elapsed(),
    );
    response
}

/// Serve `state` on `listener` until `shutdown` completes, then stop gracefully: no new
/// connections, idle ones closed, in-flight requests finish, running jobs get the
/// shutdown grace.
///
/// Connections get the shutdown grace too: one still open then (a request that never
/// finishes, say) is abandoned rather than waited for.
pub async fn serve_with(
    listener: TcpListener,
    state: AppState,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let config = &state.inner.config;
    let limits = connections::Limits::resolve(config);
    let stopping = state.clone();
    connections::serve(
        listener,
        router(state.clone()),
        limits,
        state.inner.metrics.connections.clone(),
        shutdown,
        move || {
            tracing::info!("shutting down: finishing requests and running jobs");
            stopping.begin_shutdown();
        },
        config.shutdown_grace,
    )
    .await;
    state.shutdown().await;
    Ok(())
}

/// `photostereo serve`: run the API until SIGTERM or Ctrl-C.
pub async fn serve(args: ServeArgs) -> anyhow::Result<()> {
    init_tracing(args.log_format);
    if args.max_job_pixels.is_some() {
        tracing::warn!(
            "--max-job-pixels (PHOTOSTEREO_MAX_JOB_PIXELS) is deprecated and has no effect: jobs read their images in bands; --max-input-bytes and --max-pixels bound a job"
        );
    }
    let open_files = connections::raise_open_files_limit();
    let config = Config::from(&args);
    let listener = TcpListener::bind(&args.listen)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let state = AppState::open(config).await?;
    let addr = listener.local_addr()?;
    reload_keys_on_hangup(state.clone());
    tracing::info!(
        %addr,
        data_dir = %state.config().data_dir.display(),
        workers = state.config().workers,
        queue_length = state.config().queue_length,
        api_keys = state.keys().count(),
        open_files_limit = open_files,
        "photostereo serving; API docs at /docs"
    );
    serve_with(listener, state, shutdown_signal()).await
}

/// SIGHUP re-reads the keys file without a restart. The handler is installed before
/// this returns, so from then on a SIGHUP never takes its default action (exit).
fn reload_keys_on_hangup(state: AppState) {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let Ok(mut hangup) = signal(SignalKind::hangup()) else {
            tracing::warn!("cannot handle SIGHUP; the keys file is read at start only");
            return;
        };
        tokio::spawn(async move {
            while hangup.recv().await.is_some() {
                match state.reload_keys() {
                    Ok(n) => tracing::info!(api_keys = n, "API keys re-read"),
                    Err(e) => {
                        tracing::error!(error = %e, "API keys not re-read; the previous keys stay")
                    }
                }
            }
        });
    }
    #[cfg(not(unix))]
    let _ = state;
}

fn init_tracing(format: LogFormat) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(ansi);
    let _ = match format {
        LogFormat::Json => builder.json().try_init(),
        LogFormat::Text => builder.try_init(),
    };
}

async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
