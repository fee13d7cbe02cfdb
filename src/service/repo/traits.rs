//! What a repo can do, one capability a trait: [`Jobs`] (the records), [`Queue`] (claims,
//! leases and the reaper), [`Calibrations`] and [`Idempotency`]; [`JobRepo`] is all of
//! them, which every backend is. The methods block: async callers go through
//! `tokio::task::spawn_blocking`, workers call them directly.

use std::sync::Arc;
use std::time::Duration;

use uuid::Uuid;

use super::error::RepoResult;
use super::model::{
    Admission, CalibrationRecord, Callback, Finish, JobRecord, JobStatus, Lease, Problem, Reaped,
    Remembered,
};

/// Durable job records. Every state change is conditional on the state it leaves, so a
/// worker, a `DELETE` and the reaper racing on one job cannot both win.
pub trait Jobs: Send + Sync + 'static {
    /// Record a new job unless its tenant already has `max_active` jobs queued or running
    /// or `max_queued` jobs are waiting; the counts and the insert are one step.
    fn insert(
        &self,
        job: &JobRecord,
        max_active: usize,
        max_queued: usize,
    ) -> RepoResult<Admission>;
    /// Jobs waiting for a worker, all tenants together.
    fn queued(&self) -> RepoResult<u64>;
    /// Jobs of `tenant` queued or running.
    fn active(&self, tenant: &str) -> RepoResult<u64>;
    /// Artifact bytes the jobs of `tenant` hold.
    fn stored_bytes(&self, tenant: &str) -> RepoResult<u64>;
    fn get(&self, id: Uuid) -> RepoResult<Option<JobRecord>>;
    /// Newest first, of one tenant or (None) all; `before` is the (created_at, id) of the
    /// last job of the previous page.
    fn list(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<JobRecord>>;
    /// Queued and running jobs, oldest first.
    fn unfinished(&self) -> RepoResult<Vec<JobRecord>>;
    /// queued | running → cancelled; returns the status it left, None if it was not
    /// cancellable (or does not exist).
    fn cancel(&self, id: Uuid, now: i64) -> RepoResult<Option<JobStatus>>;
    /// queued → failed (inputs lost, for example).
    fn fail_queued(&self, id: Uuid, problem: &Problem, now: i64) -> RepoResult<bool>;
    fn delete(&self, id: Uuid) -> RepoResult<bool>;
    /// Finished jobs whose `finished_at` is before `before`.
    fn expired(&self, before: i64, limit: usize) -> RepoResult<Vec<Uuid>>;
    fn counts(&self) -> RepoResult<Vec<(JobStatus, u64)>>;
    /// Jobs by tenant and status (only the pairs that have any).
    fn counts_by_tenant(&self) -> RepoResult<Vec<(String, JobStatus, u64)>>;
    fn ids(&self) -> RepoResult<Vec<Uuid>>;
    /// Record a job's callback state.
    fn set_callback(&self, id: Uuid, callback: &Callback) -> RepoResult<()>;
    /// Cheap round trip for readiness checks.
    fn ping(&self) -> RepoResult<()>;
}

/// The queue: workers claim queued jobs from it. A worker's every write about its job
/// carries its lease's token and is refused once the lease is no longer held.
pub trait Queue: Send + Sync + 'static {
    /// Every running job → queued: a single node's start, when no one else can hold one.
    fn release_running(&self) -> RepoResult<usize>;
    /// Take the next queued job for `owner` (queued → running, an attempt counted, a new
    /// token, a lease of `lease` from now). Tenants take turns: the next job is the oldest
    /// of the tenant served least recently. None when nothing waits.
    fn claim(&self, owner: &str, lease: Duration, now: i64) -> RepoResult<Option<Lease>>;
    /// Record the stage a running job has reached. False when the lease is no longer held.
    fn progress(&self, lease: Lease, stage: &str, progress: f64, now: i64) -> RepoResult<bool>;
    /// Extend the leases still held by `lease` from now; returns those no longer held
    /// (the job was cancelled, deleted, or reaped and perhaps claimed again).
    fn heartbeat(&self, leases: &[Lease], lease: Duration, now: i64) -> RepoResult<Vec<Lease>>;
    /// running → succeeded | failed. False when the lease is no longer held.
    fn finish(&self, lease: Lease, finish: &Finish, now: i64) -> RepoResult<bool>;
    /// running → queued (to run again, e.g. after a shutdown interrupted it). False when
    /// the lease is no longer held.
    fn requeue(&self, lease: Lease) -> RepoResult<bool>;
    /// Running jobs whose lease has expired (their worker died or lost the database):
    /// → queued, or → failed with `failure(id)` once `max_attempts` attempts have run.
    fn reap(
        &self,
        max_attempts: u32,
        failure: &dyn Fn(Uuid) -> Problem,
        now: i64,
    ) -> RepoResult<Reaped>;
    /// Have `wake` called whenever a job is queued or requeued by any instance. Without
    /// it (a single node) the instance rings its own workers.
    fn subscribe(&self, _wake: Arc<dyn Fn() + Send + Sync>) {}
}

/// Light calibrations' records.
pub trait Calibrations: Send + Sync + 'static {
    fn insert_calibration(&self, calibration: &CalibrationRecord) -> RepoResult<()>;
    fn get_calibration(&self, id: Uuid) -> RepoResult<Option<CalibrationRecord>>;
    /// Newest first, of one tenant or (None) all; `before` as for [`Jobs::list`].
    fn list_calibrations(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<CalibrationRecord>>;
    fn delete_calibration(&self, id: Uuid) -> RepoResult<bool>;
    fn calibration_ids(&self) -> RepoResult<Vec<Uuid>>;
}

/// Answers remembered for requests with an `Idempotency-Key`.
pub trait Idempotency: Send + Sync + 'static {
    /// The answer remembered for (`tenant`, `scope`, `key`) at or after `since`.
    fn idempotent(
        &self,
        tenant: &str,
        scope: &str,
        key: &str,
        since: i64,
    ) -> RepoResult<Option<Remembered>>;
    /// Remember an answer, unless one made at or after `since` is already remembered
    /// for the key: that one is returned and nothing is changed.
    fn remember(
        &self,
        tenant: &str,
        scope: &str,
        key: &str,
        answer: &Remembered,
        since: i64,
    ) -> RepoResult<Option<Remembered>>;
    /// Forget answers made before `before`.
    fn forget_idempotent(&self, before: i64) -> RepoResult<usize>;
}

/// Everything the service keeps in its database: what callers hold (`Arc<dyn JobRepo>`).
/// Every type with the four capabilities is one.
pub trait JobRepo: Jobs + Queue + Calibrations + Idempotency {}

impl<T: Jobs + Queue + Calibrations + Idempotency + ?Sized> JobRepo for T {}
