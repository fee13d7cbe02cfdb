//! [`AppState`]: what the handlers share. It opens the [`Runner`] (the repo, the store,
//! the workers) and starts its upkeep loop, and holds the keys in force, the submission
//! rate, the upload, calibration and re-shade slots, and the staging directories.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Duration;

use anyhow::Context;
use uuid::Uuid;

use super::budget::{self, Reservation};
use super::config::{self, Config};
use super::error::ApiError;
use super::metrics::{Metrics, Snapshot};
use super::repo::{JobRepo, JobStatus, Problem, RepoResult};
use super::slots::{Busy, Slot, Slots};
use super::store::BlobStore;
use super::tenancy::Keyring;
use super::tenancy::quota;
use super::views;
use super::worker::{Failure, Prefetch, Render, Runner, Workers};

/// Everything the handlers and workers share. Cheap to clone.
#[derive(Clone)]
pub struct AppState {
    inner: Arc<Inner>,
}

pub(crate) struct Inner {
    /// The jobs' side: the config, the repo, the store, the workers.
    runner: Arc<Runner>,
    /// Each tenant's submissions of the last minute.
    submissions: quota::SubmissionRate,
    /// The API keys in force (replaced whole when the keys file is re-read).
    keys: RwLock<Arc<Keyring>>,
    shutting_down: AtomicBool,
    /// One slot per upload being received (`max_uploads`, a share per tenant).
    uploads: Arc<Slots>,
    /// One slot per calibration being computed (`workers`, a share per tenant), held
    /// until its work ends even when its client has gone.
    calibrating: Arc<Slots>,
    /// One slot per re-shade being computed (`max_reshades`).
    reshading: Arc<Slots>,
    /// Calibrations whose computation runs now, and the most at once.
    calibrations_computing: AtomicUsize,
    calibrations_computing_max: AtomicUsize,
}

/// How the jobs' side shows a job: as `GET /v1/jobs/{id}` does, a failure as its problem.
const RENDER: Render = Render {
    job: views::job_json,
    problem: problem_of,
};

fn problem_of(failure: Failure, instance: &str) -> Problem {
    ApiError::from(failure).with_instance(instance).problem()
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
        let uploads = Slots::new(config.max_uploads, config.tenant_upload_share());
        let calibrating = Slots::new(config.workers, config.tenant_calibration_share());
        let reshading = Slots::new(config.max_reshades, config.max_reshades);
        let submissions = quota::SubmissionRate::new(config.tenant_submissions_per_minute);
        let runner = Runner::open(config, RENDER)?;
        let inner = Arc::new(Inner {
            runner,
            keys: RwLock::new(Arc::new(keys)),
            submissions,
            shutting_down: AtomicBool::new(false),
            uploads,
            calibrating,
            reshading,
            calibrations_computing: Default::default(),
            calibrations_computing_max: Default::default(),
        });
        Ok(Self { inner })
    }

    fn spawn_background(&self) {
        self.inner.runner.spawn_upkeep();
    }

    pub fn config(&self) -> &Config {
        &self.inner.runner.config
    }

    pub fn workers(&self) -> &Workers {
        &self.inner.runner.pool
    }

    /// The store, to move into a blocking task.
    pub(crate) fn store_handle(&self) -> Arc<dyn BlobStore> {
        self.inner.runner.store.clone()
    }

    pub(crate) fn metrics(&self) -> &Metrics {
        &self.inner.runner.metrics
    }

    pub fn store(&self) -> &dyn BlobStore {
        &*self.inner.runner.store
    }

    /// The most jobs that were ever running at once (never more than the pool size).
    pub fn max_running(&self) -> usize {
        self.inner.runner.pool.running_max()
    }

    /// Run a repo call off the async runtime.
    pub async fn repo<T, F>(&self, f: F) -> Result<T, ApiError>
    where
        T: Send + 'static,
        F: FnOnce(&dyn JobRepo) -> RepoResult<T> + Send + 'static,
    {
        let repo = self.inner.runner.repo.clone();
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
        let config = &self.inner.runner.config;
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
        self.inner.runner.close();
    }

    /// [`begin_shutdown`](Self::begin_shutdown), then let running jobs finish for up to
    /// the shutdown grace; jobs still running then are interrupted within one step of work
    /// and run again at the next start.
    pub async fn shutdown(&self) {
        self.begin_shutdown();
        self.inner.runner.finish().await;
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
        let peak = budget::calibration_peak_bytes(&self.inner.runner.config);
        let memory = self
            .inner
            .runner
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
        let memory = (self.inner.runner.budget)
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
        self.inner
            .runner
            .metrics
            .submitted
            .fetch_add(1, Ordering::Relaxed);
    }

    /// The tenant's quotas before an upload is read: submissions per minute (counting
    /// this one), jobs queued or running, stored bytes. The insert checks the active
    /// jobs again ([`Self::over_active_jobs`]), as uploads run concurrently.
    pub(crate) async fn check_quotas(&self, tenant: &str) -> Result<(), ApiError> {
        let config = &self.inner.runner.config;
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
        let max = self.inner.runner.config.tenant_max_jobs;
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
            .runner
            .metrics
            .observe_quota_refusal(tenant, limit.as_str());
        ApiError::quota_exceeded(retry, detail)
    }

    /// Whether `tenant` has a webhook secret (callbacks need one).
    pub(crate) fn has_webhook_secret(&self, tenant: &str) -> bool {
        self.inner.runner.has_webhook_secret(tenant)
    }

    /// A job has ended outside a worker (cancelled while queued): deliver its webhook.
    pub(crate) fn job_ended(&self, id: Uuid) {
        self.inner.runner.job_ended(id);
    }

    pub(crate) fn count_queue_full(&self) {
        self.inner
            .runner
            .metrics
            .rejected_queue_full
            .fetch_add(1, Ordering::Relaxed);
    }

    /// 507 when the data directory's file system is short of space.
    pub(crate) async fn check_free_disk(&self) -> Result<(), ApiError> {
        let min = self.inner.runner.config.min_free_disk;
        if min == 0 {
            return Ok(());
        }
        let store = self.inner.runner.store.clone();
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
        let store = self.inner.runner.store.clone();
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
        self.inner.runner.prefetch.begin()
    }

    /// Keep an accepted job's decoded images for its worker.
    pub(crate) fn park_prefetch(&self, id: Uuid, set: Prefetch) {
        self.inner.runner.prefetch.park(id, set);
    }

    /// Drop the images decoded ahead for a job, if any.
    pub(crate) fn remove_prefetch(&self, id: Uuid) {
        self.inner.runner.prefetch.discard(id);
    }

    /// Remove a job's files and any images decoded ahead for it (errors are logged).
    pub(crate) async fn remove_files(&self, id: Uuid) {
        self.inner.runner.prefetch.discard(id);
        let store = self.inner.runner.store.clone();
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
        let budget = &self.inner.runner.budget;
        let job = budget::job_worst_bytes(&self.inner.runner.config).min(budget.limit());
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
        let store = self.inner.runner.store.clone();
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
        let store = self.inner.runner.store.clone();
        let free = tokio::task::spawn_blocking(move || store.free_bytes().ok()).await?;
        let jobs = &self.inner.runner.pool;
        let queued = counts
            .iter()
            .find(|(s, _)| *s == JobStatus::Queued)
            .map_or(0, |(_, n)| *n as usize);
        let mut text = self.inner.runner.metrics.render(&Snapshot {
            jobs_by_status: counts,
            jobs_by_tenant: by_tenant,
            queue_depth: queued,
            queue_capacity: self.inner.runner.config.queue_length,
            running: jobs.running(),
            running_max: jobs.running_max(),
            workers: self.inner.runner.config.workers,
            free_disk_bytes: free,
            prefetch_sets: self.inner.runner.prefetch.held(),
        });
        self.inner.runner.budget.render(&mut text);
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
        let delay = self.inner.runner.config.stage_delay;
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
        let store = self.state.inner.runner.store.clone();
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
        let store = self.state.inner.runner.store.clone();
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
