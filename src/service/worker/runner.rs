//! [`Runner`]: what the work away from requests holds — the config, the repo, the store,
//! the worker pool, the images decoded ahead, the memory budget, the metrics — and its
//! life: opened (the data directory locked, leftovers tidied, unfinished jobs queued
//! again, undelivered webhooks resumed, the workers started), closed, finished.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use tokio::sync::watch;
use uuid::Uuid;

use crate::service::budget::Budget;
use crate::service::config::Config;
use crate::service::metrics::Metrics;
use crate::service::repo::{self, JobRecord, JobRepo, Problem, SqliteRepo};
use crate::service::store::{self, BlobStore, LocalStore};

use super::failure::Failure;
use super::pool::Workers;
use super::prefetch::Prefetcher;
use super::{run, upkeep, webhooks};

/// How the runner shows a job to the outside, given by the HTTP side: the job resource as
/// JSON (what a webhook delivers), and a failure as the problem the job's record keeps
/// (its URL the problem's instance).
#[derive(Clone, Copy)]
pub struct Render {
    pub job: fn(JobRecord) -> String,
    pub problem: fn(Failure, &str) -> Problem,
}

/// The jobs' side of the service. Worker threads and the upkeep loop share it.
pub struct Runner {
    pub(crate) config: Config,
    pub(crate) repo: Arc<dyn JobRepo>,
    pub(crate) store: Arc<dyn BlobStore>,
    pub(crate) pool: Workers,
    /// This instance's name on the leases it holds.
    pub(super) owner: String,
    /// Uploads' images decoded ahead of their jobs.
    pub(crate) prefetch: Prefetcher,
    pub(crate) metrics: Metrics,
    /// What jobs, calibrations and re-shades reserve (`memory_budget`).
    pub(crate) budget: Arc<Budget>,
    /// Webhook signing secrets by tenant.
    pub(super) webhook_secrets: HashMap<String, Vec<u8>>,
    pub(super) render: Render,
    /// Where webhook deliveries run (workers are plain threads).
    pub(super) runtime: tokio::runtime::Handle,
    pub(super) stop: watch::Sender<bool>,
    /// The data directory's lock file, held (flock) while this server uses it, so that a
    /// second server cannot run the same jobs or tidy away the first one's uploads.
    data_lock: Mutex<Option<std::fs::File>>,
}

impl Runner {
    /// Lock the data directory, open the repo and the store, put every unfinished job back
    /// in the queue, resume undelivered webhooks and start the workers. Blocking: call it
    /// off the async threads, within a runtime.
    pub fn open(config: Config, render: Render) -> anyhow::Result<Arc<Self>> {
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
        let runner = Arc::new(Self {
            pool: Workers::default(),
            owner: format!("{}-{}", std::process::id(), Uuid::new_v4().simple()),
            prefetch: Prefetcher::new(config.decode_ahead, config.limits()),
            budget: Budget::new(config.memory_budget),
            config,
            repo,
            store,
            metrics: Metrics::default(),
            webhook_secrets,
            render,
            runtime: tokio::runtime::Handle::current(),
            stop,
            data_lock: Mutex::new(Some(data_lock)),
        });
        let requeued = upkeep::recover(&runner)?;
        if requeued > 0 {
            tracing::info!(jobs = requeued, "unfinished jobs queued again");
        }
        match webhooks::resume(&runner) {
            Ok(0) => {}
            Ok(n) => tracing::info!(jobs = n, "undelivered webhooks resumed"),
            Err(e) => tracing::warn!(error = %e, "cannot resume undelivered webhooks"),
        }
        for i in 0..runner.config.workers.max(1) {
            let worker = runner.clone();
            let handle = std::thread::Builder::new()
                .name(format!("photostereo-worker-{i}"))
                .spawn(move || run::worker_loop(worker))
                .context("starting a worker thread")?;
            runner.pool.add_thread(handle);
        }
        let bell = runner.clone();
        runner.repo.subscribe(Arc::new(move || bell.pool.ring()));
        Ok(runner)
    }

    /// Start the upkeep loop (on the current runtime) until [`close`](Self::close).
    pub fn spawn_upkeep(self: &Arc<Self>) {
        upkeep::spawn(self.clone(), self.stop.subscribe());
    }

    /// A failure as the problem a job's record keeps, `instance` its URL.
    pub(super) fn problem(&self, failure: Failure, instance: &str) -> Problem {
        (self.render.problem)(failure, instance)
    }

    /// Whether `tenant` has a webhook secret (callbacks need one).
    pub fn has_webhook_secret(&self, tenant: &str) -> bool {
        self.webhook_secrets.contains_key(tenant)
    }

    /// A job has ended outside a worker (cancelled while queued): deliver its webhook.
    pub fn job_ended(self: &Arc<Self>, id: Uuid) {
        let runner = self.clone();
        tokio::task::spawn_blocking(move || webhooks::job_ended(&runner, id));
    }

    /// Take no new jobs (queued ones stay queued for the next start) and stop the upkeep
    /// loop and webhook retries.
    pub fn close(&self) {
        self.pool.close();
        let _ = self.stop.send(true);
    }

    /// After [`close`](Self::close): let running jobs finish for up to the shutdown grace;
    /// jobs still running then are interrupted within one step of work and run again at
    /// the next start. Then the data directory is let go.
    pub async fn finish(&self) {
        let jobs = &self.pool;
        let deadline = Instant::now() + self.config.shutdown_grace;
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
        if let Ok(mut lock) = self.data_lock.lock() {
            lock.take();
        }
    }
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
