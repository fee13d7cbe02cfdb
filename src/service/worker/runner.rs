//! [`Runner`]: what the work away from requests holds — the config, the repo, the store,
//! the worker pool, the images decoded ahead, the memory budget, the metrics — and the end
//! of its life: closed, then finished. `start` opens it.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::watch;

use crate::service::budget::Budget;
use crate::service::config::Config;
use crate::service::metrics::Metrics;
use crate::service::repo::{JobRecord, JobRepo, Problem};
use crate::service::store::BlobStore;

use super::failure::Failure;
use super::pool::Workers;
use super::prefetch::Prefetcher;

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
    pub(super) data_lock: Mutex<Option<std::fs::File>>,
}

impl Runner {
    /// A failure as the problem a job's record keeps, `instance` its URL.
    pub(super) fn problem(&self, failure: Failure, instance: &str) -> Problem {
        (self.render.problem)(failure, instance)
    }

    /// Whether `tenant` has a webhook secret (callbacks need one).
    pub fn has_webhook_secret(&self, tenant: &str) -> bool {
        self.webhook_secrets.contains_key(tenant)
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
