//! Opening the [`Runner`]: the data directory locked, the repo and the store opened,
//! leftovers tidied and unfinished jobs queued again, undelivered webhooks resumed, the
//! workers started; and what starts work on its behalf later (the upkeep loop, a
//! webhook for a job that ended outside a worker).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use tokio::sync::watch;
use uuid::Uuid;

use crate::service::budget::Budget;
use crate::service::config::Config;
use crate::service::metrics::Metrics;
use crate::service::repo::{self, JobRepo, SqliteRepo};
use crate::service::store::{self, BlobStore, LocalStore};

use super::pool::Workers;
use super::prefetch::Prefetcher;
use super::runner::{Render, Runner};
use super::{run, upkeep, webhooks};

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

    /// A job has ended outside a worker (cancelled while queued): deliver its webhook.
    pub fn job_ended(self: &Arc<Self>, id: Uuid) {
        let runner = self.clone();
        tokio::task::spawn_blocking(move || webhooks::job_ended(&runner, id));
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
