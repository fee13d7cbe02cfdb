//! Job records behind [`JobRepo`]; [`SqliteRepo`] keeps them in one SQLite file (WAL,
//! versioned migrations). The methods block: async callers go through
//! `tokio::task::spawn_blocking` (see `AppState::repo`), workers call them directly.

use std::path::Path;
use std::sync::Mutex;
use std::time::Duration;

use rusqlite::{Connection, OptionalExtension, Row, TransactionBehavior, params};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use uuid::Uuid;

use super::problem::Problem;

/// Where a job is in its life.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, ToSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum JobStatus {
    /// Accepted and waiting for a worker.
    Queued,
    /// A worker is reconstructing it.
    Running,
    /// Finished; its artifacts can be downloaded.
    Succeeded,
    /// Finished with an error (see `error`).
    Failed,
    /// Stopped by a `DELETE` before it finished.
    Cancelled,
}

impl JobStatus {
    pub const ALL: [JobStatus; 5] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Failed,
        JobStatus::Cancelled,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|j| j.as_str() == s)
    }

    /// Succeeded, failed or cancelled: nothing will change it any more.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobStatus::Succeeded | JobStatus::Failed | JobStatus::Cancelled
        )
    }
}

/// One stored artifact of a finished job.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ArtifactInfo {
    pub name: String,
    pub bytes: u64,
    /// Strong entity tag, quotes included.
    pub etag: String,
    /// Where the store keeps it, when under a name of its own (an object store's
    /// attempt-specific key); none in the data directory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub key: Option<String>,
}

/// A job as the repo stores it. Times are milliseconds since the Unix epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRecord {
    pub id: Uuid,
    /// The tenant that created it (the name, never a key).
    pub tenant: String,
    pub status: JobStatus,
    pub stage: Option<String>,
    pub progress: f64,
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
    pub heartbeat_at: Option<i64>,
    /// How many times a worker has started it (more than 1 after a restart).
    pub attempts: u32,
    pub image_count: u32,
    /// The job's `Options`, as JSON.
    pub options: serde_json::Value,
    pub error: Option<Problem>,
    /// The result summary (from the pipeline's report) once succeeded.
    pub result: Option<serde_json::Value>,
    pub artifacts: Vec<ArtifactInfo>,
    pub callback: Option<Callback>,
}

impl JobRecord {
    /// A freshly accepted job.
    pub fn new_queued(
        id: Uuid,
        tenant: &str,
        now: i64,
        image_count: u32,
        options: serde_json::Value,
    ) -> Self {
        Self {
            id,
            tenant: tenant.to_string(),
            status: JobStatus::Queued,
            stage: None,
            progress: 0.0,
            created_at: now,
            started_at: None,
            finished_at: None,
            heartbeat_at: None,
            attempts: 0,
            image_count,
            options,
            error: None,
            result: None,
            artifacts: Vec::new(),
            callback: None,
        }
    }
}

/// Where a job's end is POSTed, and how that went.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Callback {
    /// The job's `callback_url`.
    pub url: String,
    pub state: CallbackState,
    /// Every delivery attempt, oldest first.
    pub attempts: Vec<CallbackAttempt>,
}

/// `pending` until the job ends and a delivery is answered with 2xx (`delivered`), or the
/// retries run out (`failed`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum CallbackState {
    Pending,
    Delivered,
    Failed,
}

/// One delivery attempt.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CallbackAttempt {
    /// RFC 3339.
    pub at: String,
    /// The receiver's HTTP status, when it answered.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub status: Option<u16>,
    /// Why there was no answer (connection refused, time-out, host not allowed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The answer to a request with an `Idempotency-Key` (see `idempotency`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Remembered {
    /// Hash of the request's parts.
    pub body_hash: String,
    pub status: u16,
    pub body: String,
    pub location: Option<String>,
    /// Milliseconds since the Unix epoch.
    pub created_at: i64,
}

/// A calibration as the repo stores it (see `calibrations`). Times are milliseconds since
/// the Unix epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationRecord {
    pub id: Uuid,
    /// The tenant that created it.
    pub tenant: String,
    pub created_at: i64,
    /// What was measured (circle, lights, quality, skipped images), as JSON.
    pub detail: serde_json::Value,
    /// The light table (`name, x, y, z[, intensity]`), as jobs take it.
    pub table: String,
    /// Its stored files (`lights.csv`, `overlay.png`, `lights.png`, `positions.csv` with
    /// several balls).
    pub artifacts: Vec<ArtifactInfo>,
}

/// How a running job ended.
#[derive(Debug, Clone)]
pub enum Finish {
    Succeeded {
        result: serde_json::Value,
        artifacts: Vec<ArtifactInfo>,
    },
    Failed(Problem),
}

/// A storage failure: the server's fault, or a database that does not answer for now
/// ([`is_unavailable`](Self::is_unavailable)), which callers wait out.
#[derive(Debug, thiserror::Error)]
#[error("job repository: {message}")]
pub struct RepoError {
    message: String,
    unavailable: bool,
}

impl RepoError {
    pub(super) fn new(message: String) -> Self {
        Self {
            message,
            unavailable: false,
        }
    }

    /// The database cannot be reached (down, restarting, out of connections).
    pub(super) fn unavailable(message: String) -> Self {
        Self {
            message,
            unavailable: true,
        }
    }

    pub fn is_unavailable(&self) -> bool {
        self.unavailable
    }
}

impl From<rusqlite::Error> for RepoError {
    fn from(e: rusqlite::Error) -> Self {
        Self::new(e.to_string())
    }
}

impl From<serde_json::Error> for RepoError {
    fn from(e: serde_json::Error) -> Self {
        Self::new(format!("stored JSON: {e}"))
    }
}

pub type RepoResult<T> = Result<T, RepoError>;

/// A claimed job as its worker holds it. Every write the worker makes about the job
/// carries the token and is refused once the job has ended or another claim has taken it
/// (a fencing token: a worker that lost its lease can never overwrite the one that took
/// over).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Lease {
    pub id: Uuid,
    pub token: i64,
}

/// Whether a new job was recorded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admission {
    Accepted,
    /// Its tenant already has `max_active` jobs queued or running.
    TenantFull,
    /// `max_queued` jobs are waiting, all tenants together.
    QueueFull,
}

/// What the reaper did with running jobs whose lease had expired.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Reaped {
    /// Back in the queue, to run again.
    pub requeued: Vec<Uuid>,
    /// Failed: their lease expired on their last attempt.
    pub failed: Vec<Uuid>,
}

/// Durable job records, and the queue: workers claim queued jobs from it. Every state
/// change is conditional on the state it leaves (and a worker's on its lease's token), so
/// a worker, a `DELETE` and the reaper racing on one job cannot both win.
pub trait JobRepo: Send + Sync + 'static {
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
    fn subscribe(&self, _wake: std::sync::Arc<dyn Fn() + Send + Sync>) {}
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
    /// Record a job's callback state.
    fn set_callback(&self, id: Uuid, callback: &Callback) -> RepoResult<()>;
    /// Cheap round trip for readiness checks.
    fn ping(&self) -> RepoResult<()>;
    fn insert_calibration(&self, calibration: &CalibrationRecord) -> RepoResult<()>;
    fn get_calibration(&self, id: Uuid) -> RepoResult<Option<CalibrationRecord>>;
    /// Newest first, of one tenant or (None) all; `before` as for [`JobRepo::list`].
    fn list_calibrations(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<CalibrationRecord>>;
    fn delete_calibration(&self, id: Uuid) -> RepoResult<bool>;
    fn calibration_ids(&self) -> RepoResult<Vec<Uuid>>;
}

/// Schema versions; `PRAGMA user_version` is the number applied.
const MIGRATIONS: &[&str] = &[
    // 1: the jobs table.
    "CREATE TABLE jobs (
        id           TEXT PRIMARY KEY NOT NULL,
        status       TEXT NOT NULL,
        stage        TEXT,
        progress     REAL NOT NULL DEFAULT 0,
        created_at   INTEGER NOT NULL,
        started_at   INTEGER,
        finished_at  INTEGER,
        heartbeat_at INTEGER,
        attempts     INTEGER NOT NULL DEFAULT 0,
        image_count  INTEGER NOT NULL DEFAULT 0,
        options      TEXT NOT NULL,
        error        TEXT,
        result       TEXT,
        artifacts    TEXT
    );
    CREATE INDEX jobs_by_created ON jobs (created_at DESC, id DESC);
    CREATE INDEX jobs_by_status ON jobs (status, finished_at);",
    // 2: jobs belong to tenants; those recorded before belong to the open API's tenant.
    "ALTER TABLE jobs ADD COLUMN tenant TEXT NOT NULL DEFAULT 'default';
    CREATE INDEX jobs_by_tenant ON jobs (tenant, created_at DESC, id DESC);",
    // 3: answers to requests with an Idempotency-Key.
    "CREATE TABLE idempotency (
        tenant     TEXT NOT NULL,
        scope      TEXT NOT NULL,
        key        TEXT NOT NULL,
        body_hash  TEXT NOT NULL,
        status     INTEGER NOT NULL,
        body       TEXT NOT NULL,
        location   TEXT,
        created_at INTEGER NOT NULL,
        PRIMARY KEY (tenant, scope, key)
    );
    CREATE INDEX idempotency_by_age ON idempotency (created_at);",
    // 4: jobs' webhooks.
    "ALTER TABLE jobs ADD COLUMN callback TEXT;",
    // 5: light calibrations.
    "CREATE TABLE calibrations (
        id         TEXT PRIMARY KEY NOT NULL,
        tenant     TEXT NOT NULL,
        created_at INTEGER NOT NULL,
        detail     TEXT NOT NULL,
        light_table TEXT NOT NULL,
        artifacts  TEXT NOT NULL
    );
    CREATE INDEX calibrations_by_created ON calibrations (created_at DESC, id DESC);
    CREATE INDEX calibrations_by_tenant ON calibrations (tenant, created_at DESC, id DESC);",
    // 6: leases (the claiming worker, its fencing token, when the lease runs out) and the
    // tenants' turns.
    "ALTER TABLE jobs ADD COLUMN owner TEXT;
    ALTER TABLE jobs ADD COLUMN token INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE jobs ADD COLUMN lease_until INTEGER;
    CREATE TABLE turns (tenant TEXT PRIMARY KEY NOT NULL, served INTEGER NOT NULL);",
];

/// [`JobRepo`] in a SQLite database file.
pub struct SqliteRepo {
    conn: Mutex<Connection>,
}

const COLUMNS: &str = "id, status, stage, progress, created_at, started_at, finished_at, \
     heartbeat_at, attempts, image_count, options, error, result, artifacts, tenant, callback";

impl SqliteRepo {
    /// Open (creating if needed) and migrate the database at `path`.
    pub fn open(path: &Path) -> RepoResult<Self> {
        let mut conn = Connection::open(path)?;
        conn.busy_timeout(Duration::from_secs(5))?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        // Every commit reaches the disk before a 202 is sent.
        conn.pragma_update(None, "synchronous", "FULL")?;
        conn.pragma_update(None, "foreign_keys", "ON")?;
        migrate(&mut conn)?;
        Ok(Self {
            conn: Mutex::new(conn),
        })
    }

    fn with<T>(&self, f: impl FnOnce(&mut Connection) -> RepoResult<T>) -> RepoResult<T> {
        let mut conn = self.conn.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut conn)
    }
}

fn migrate(conn: &mut Connection) -> RepoResult<()> {
    let version: i64 = conn.pragma_query_value(None, "user_version", |r| r.get(0))?;
    if version as usize > MIGRATIONS.len() {
        return Err(RepoError::new(format!(
            "database schema version {version} is newer than this program ({}); upgrade photostereo",
            MIGRATIONS.len()
        )));
    }
    for (i, sql) in MIGRATIONS.iter().enumerate().skip(version as usize) {
        let tx = conn.transaction()?;
        tx.execute_batch(sql)?;
        tx.pragma_update(None, "user_version", (i + 1) as i64)?;
        tx.commit()?;
    }
    Ok(())
}

fn read_record(row: &Row<'_>) -> rusqlite::Result<RawRecord> {
    Ok(RawRecord {
        id: row.get(0)?,
        status: row.get(1)?,
        stage: row.get(2)?,
        progress: row.get(3)?,
        created_at: row.get(4)?,
        started_at: row.get(5)?,
        finished_at: row.get(6)?,
        heartbeat_at: row.get(7)?,
        attempts: row.get(8)?,
        image_count: row.get(9)?,
        options: row.get(10)?,
        error: row.get(11)?,
        result: row.get(12)?,
        artifacts: row.get(13)?,
        tenant: row.get(14)?,
        callback: row.get(15)?,
    })
}

/// A job row as stored (JSON as text), in either database.
pub(super) struct RawRecord {
    pub(super) id: String,
    pub(super) status: String,
    pub(super) stage: Option<String>,
    pub(super) progress: f64,
    pub(super) created_at: i64,
    pub(super) started_at: Option<i64>,
    pub(super) finished_at: Option<i64>,
    pub(super) heartbeat_at: Option<i64>,
    pub(super) attempts: i64,
    pub(super) image_count: i64,
    pub(super) options: String,
    pub(super) error: Option<String>,
    pub(super) result: Option<String>,
    pub(super) artifacts: Option<String>,
    pub(super) tenant: String,
    pub(super) callback: Option<String>,
}

impl RawRecord {
    pub(super) fn decode(self) -> RepoResult<JobRecord> {
        let id = Uuid::parse_str(&self.id)
            .map_err(|e| RepoError::new(format!("stored job id {:?}: {e}", self.id)))?;
        let status = JobStatus::parse(&self.status)
            .ok_or_else(|| RepoError::new(format!("stored status {:?} of {id}", self.status)))?;
        Ok(JobRecord {
            id,
            tenant: self.tenant,
            status,
            stage: self.stage,
            progress: self.progress,
            created_at: self.created_at,
            started_at: self.started_at,
            finished_at: self.finished_at,
            heartbeat_at: self.heartbeat_at,
            attempts: self.attempts.max(0) as u32,
            image_count: self.image_count.max(0) as u32,
            options: serde_json::from_str(&self.options)?,
            error: self.error.map(|e| serde_json::from_str(&e)).transpose()?,
            result: self.result.map(|r| serde_json::from_str(&r)).transpose()?,
            artifacts: self
                .artifacts
                .map(|a| serde_json::from_str(&a))
                .transpose()?
                .unwrap_or_default(),
            callback: self
                .callback
                .map(|c| serde_json::from_str(&c))
                .transpose()?,
        })
    }
}

fn read_remembered(
    conn: &Connection,
    tenant: &str,
    scope: &str,
    key: &str,
    since: i64,
) -> RepoResult<Option<Remembered>> {
    Ok(conn
        .query_row(
            "SELECT body_hash, status, body, location, created_at FROM idempotency \
             WHERE tenant = ?1 AND scope = ?2 AND key = ?3 AND created_at >= ?4",
            params![tenant, scope, key, since],
            |r| {
                Ok(Remembered {
                    body_hash: r.get(0)?,
                    status: r.get(1)?,
                    body: r.get(2)?,
                    location: r.get(3)?,
                    created_at: r.get(4)?,
                })
            },
        )
        .optional()?)
}

const CALIBRATION_COLUMNS: &str = "id, tenant, created_at, detail, light_table, artifacts";

/// A calibration row: id, tenant, created_at, detail, light_table, artifacts.
pub(super) type RawCalibration = (String, String, i64, String, String, String);

fn read_calibration(row: &Row<'_>) -> rusqlite::Result<RawCalibration> {
    Ok((
        row.get(0)?,
        row.get(1)?,
        row.get(2)?,
        row.get(3)?,
        row.get(4)?,
        row.get(5)?,
    ))
}

pub(super) fn decode_calibration(
    (id, tenant, created_at, detail, table, artifacts): RawCalibration,
) -> RepoResult<CalibrationRecord> {
    Ok(CalibrationRecord {
        id: Uuid::parse_str(&id)
            .map_err(|e| RepoError::new(format!("stored calibration id {id:?}: {e}")))?,
        tenant,
        created_at,
        detail: serde_json::from_str(&detail)?,
        table,
        artifacts: serde_json::from_str(&artifacts)?,
    })
}

/// Rows of a listing that could not be decoded since the process started (see
/// [`readable`]).
static UNREADABLE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// How many stored records a listing has left out because they could not be read.
pub fn unreadable_records() -> u64 {
    UNREADABLE.load(std::sync::atomic::Ordering::Relaxed)
}

/// The decoded rows of a listing. A row that does not decode is logged, counted
/// ([`unreadable_records`]) and left out: one bad record never breaks a list.
pub(super) fn readable<T>(decoded: impl IntoIterator<Item = RepoResult<T>>, what: &str) -> Vec<T> {
    decoded
        .into_iter()
        .filter_map(|r| {
            r.map_err(|e| {
                UNREADABLE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                tracing::error!(error = %e, "a stored {what} cannot be read; left out of the list");
            })
            .ok()
        })
        .collect()
}

fn query_records(
    conn: &Connection,
    sql: &str,
    params: impl rusqlite::Params,
) -> RepoResult<Vec<JobRecord>> {
    let mut stmt = conn.prepare_cached(sql)?;
    let rows = stmt
        .query_map(params, read_record)?
        .collect::<rusqlite::Result<Vec<_>>>()?;
    Ok(readable(rows.into_iter().map(RawRecord::decode), "job"))
}

impl JobRepo for SqliteRepo {
    fn insert(
        &self,
        job: &JobRecord,
        max_active: usize,
        max_queued: usize,
    ) -> RepoResult<Admission> {
        let options = serde_json::to_string(&job.options)?;
        let error = job.error.as_ref().map(serde_json::to_string).transpose()?;
        let result = job.result.as_ref().map(serde_json::to_string).transpose()?;
        let artifacts = serde_json::to_string(&job.artifacts)?;
        let callback = job
            .callback
            .as_ref()
            .map(serde_json::to_string)
            .transpose()?;
        self.with(|c| {
            let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
            let (active, queued): (i64, i64) = tx.query_row(
                "SELECT COUNT(*) FILTER (WHERE tenant = ?1 AND status IN ('queued', 'running')), \
                 COUNT(*) FILTER (WHERE status = 'queued') FROM jobs",
                params![job.tenant],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )?;
            if active >= max_active as i64 {
                return Ok(Admission::TenantFull);
            }
            if queued >= max_queued as i64 {
                return Ok(Admission::QueueFull);
            }
            tx.execute(
                &format!(
                    "INSERT INTO jobs ({COLUMNS}) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, \
                     ?10, ?11, ?12, ?13, ?14, ?15, ?16)"
                ),
                params![
                    job.id.to_string(),
                    job.status.as_str(),
                    job.stage,
                    job.progress,
                    job.created_at,
                    job.started_at,
                    job.finished_at,
                    job.heartbeat_at,
                    job.attempts,
                    job.image_count,
                    options,
                    error,
                    result,
                    artifacts,
                    job.tenant,
                    callback,
                ],
            )?;
            tx.commit()?;
            Ok(Admission::Accepted)
        })
    }

    fn queued(&self) -> RepoResult<u64> {
        self.with(|c| {
            Ok(c.query_row(
                "SELECT COUNT(*) FROM jobs WHERE status = 'queued'",
                [],
                |r| r.get::<_, i64>(0),
            )? as u64)
        })
    }

    fn active(&self, tenant: &str) -> RepoResult<u64> {
        self.with(|c| {
            Ok(c.query_row(
                "SELECT COUNT(*) FROM jobs WHERE tenant = ?1 AND status IN ('queued', 'running')",
                params![tenant],
                |r| r.get::<_, i64>(0),
            )? as u64)
        })
    }

    fn stored_bytes(&self, tenant: &str) -> RepoResult<u64> {
        self.with(|c| {
            Ok(c.query_row(
                "SELECT COALESCE(SUM(json_extract(a.value, '$.bytes')), 0) \
                 FROM jobs, json_each(jobs.artifacts) AS a \
                 WHERE jobs.tenant = ?1 AND jobs.artifacts IS NOT NULL",
                params![tenant],
                |r| r.get::<_, i64>(0),
            )? as u64)
        })
    }

    fn get(&self, id: Uuid) -> RepoResult<Option<JobRecord>> {
        self.with(|c| {
            let raw = c
                .query_row(
                    &format!("SELECT {COLUMNS} FROM jobs WHERE id = ?1"),
                    params![id.to_string()],
                    read_record,
                )
                .optional()?;
            raw.map(RawRecord::decode).transpose()
        })
    }

    fn list(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<JobRecord>> {
        let limit = limit as i64;
        // No cursor and a NULL tenant are conditions too, so one statement serves every case.
        let first = before.is_none();
        let (at, id) = before.map_or((0, String::new()), |(at, id)| (at, id.to_string()));
        self.with(|c| {
            query_records(
                c,
                &format!(
                    "SELECT {COLUMNS} FROM jobs WHERE (?1 IS NULL OR tenant = ?1) \
                     AND (?2 OR (created_at, id) < (?3, ?4)) \
                     ORDER BY created_at DESC, id DESC LIMIT ?5"
                ),
                params![tenant, first, at, id, limit],
            )
        })
    }

    fn unfinished(&self) -> RepoResult<Vec<JobRecord>> {
        self.with(|c| {
            query_records(
                c,
                &format!(
                    "SELECT {COLUMNS} FROM jobs WHERE status IN ('queued', 'running') \
                     ORDER BY created_at ASC, id ASC"
                ),
                [],
            )
        })
    }

    fn release_running(&self) -> RepoResult<usize> {
        self.with(|c| {
            Ok(c.execute(
                "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, owner = NULL, \
                 lease_until = NULL WHERE status = 'running'",
                [],
            )?)
        })
    }

    fn claim(&self, owner: &str, lease: Duration, now: i64) -> RepoResult<Option<Lease>> {
        let until = now.saturating_add(lease.as_millis() as i64);
        self.with(|c| {
            let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
            let next: Option<(String, String)> = tx
                .query_row(
                    "SELECT j.id, j.tenant FROM jobs j LEFT JOIN turns t ON t.tenant = j.tenant \
                     WHERE j.status = 'queued' \
                     ORDER BY COALESCE(t.served, 0), j.created_at, j.id LIMIT 1",
                    [],
                    |r| Ok((r.get(0)?, r.get(1)?)),
                )
                .optional()?;
            let Some((id, tenant)) = next else {
                return Ok(None);
            };
            let token: i64 = tx.query_row(
                "UPDATE jobs SET status = 'running', stage = NULL, progress = 0, \
                 started_at = ?2, heartbeat_at = ?2, attempts = attempts + 1, \
                 token = token + 1, owner = ?3, lease_until = ?4 WHERE id = ?1 RETURNING token",
                params![id, now, owner, until],
                |r| r.get(0),
            )?;
            tx.execute(
                "INSERT INTO turns (tenant, served) \
                 VALUES (?1, (SELECT COALESCE(MAX(served), 0) + 1 FROM turns)) \
                 ON CONFLICT (tenant) DO UPDATE SET served = excluded.served",
                params![tenant],
            )?;
            tx.commit()?;
            let id = Uuid::parse_str(&id)
                .map_err(|e| RepoError::new(format!("stored job id {id:?}: {e}")))?;
            Ok(Some(Lease { id, token }))
        })
    }

    fn progress(&self, lease: Lease, stage: &str, progress: f64, now: i64) -> RepoResult<bool> {
        self.with(|c| {
            let n = c.execute(
                "UPDATE jobs SET stage = ?3, progress = ?4, heartbeat_at = ?5 \
                 WHERE id = ?1 AND token = ?2 AND status = 'running'",
                params![lease.id.to_string(), lease.token, stage, progress, now],
            )?;
            Ok(n == 1)
        })
    }

    fn heartbeat(&self, leases: &[Lease], lease: Duration, now: i64) -> RepoResult<Vec<Lease>> {
        let until = now.saturating_add(lease.as_millis() as i64);
        self.with(|c| {
            let tx = c.transaction()?;
            let mut lost = Vec::new();
            for l in leases {
                let n = tx.execute(
                    "UPDATE jobs SET heartbeat_at = ?3, lease_until = ?4 \
                     WHERE id = ?1 AND token = ?2 AND status = 'running'",
                    params![l.id.to_string(), l.token, now, until],
                )?;
                if n == 0 {
                    lost.push(*l);
                }
            }
            tx.commit()?;
            Ok(lost)
        })
    }

    fn finish(&self, lease: Lease, finish: &Finish, now: i64) -> RepoResult<bool> {
        let (id, token) = (lease.id.to_string(), lease.token);
        let n = match finish {
            Finish::Succeeded { result, artifacts } => {
                let result = serde_json::to_string(result)?;
                let artifacts = serde_json::to_string(artifacts)?;
                self.with(|c| {
                    Ok(c.execute(
                        "UPDATE jobs SET status = 'succeeded', progress = 1, finished_at = ?3, \
                         heartbeat_at = ?3, result = ?4, artifacts = ?5, error = NULL, \
                         lease_until = NULL WHERE id = ?1 AND token = ?2 AND status = 'running'",
                        params![id, token, now, result, artifacts],
                    )?)
                })?
            }
            Finish::Failed(problem) => {
                let error = serde_json::to_string(problem)?;
                self.with(|c| {
                    Ok(c.execute(
                        "UPDATE jobs SET status = 'failed', finished_at = ?3, heartbeat_at = ?3, \
                         error = ?4, lease_until = NULL \
                         WHERE id = ?1 AND token = ?2 AND status = 'running'",
                        params![id, token, now, error],
                    )?)
                })?
            }
        };
        Ok(n == 1)
    }

    fn requeue(&self, lease: Lease) -> RepoResult<bool> {
        self.with(|c| {
            let n = c.execute(
                "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, owner = NULL, \
                 lease_until = NULL WHERE id = ?1 AND token = ?2 AND status = 'running'",
                params![lease.id.to_string(), lease.token],
            )?;
            Ok(n == 1)
        })
    }

    fn reap(
        &self,
        max_attempts: u32,
        failure: &dyn Fn(Uuid) -> Problem,
        now: i64,
    ) -> RepoResult<Reaped> {
        self.with(|c| {
            let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
            let expired: Vec<(String, i64)> = {
                let mut stmt = tx.prepare_cached(
                    "SELECT id, attempts FROM jobs WHERE status = 'running' AND lease_until < ?1",
                )?;
                stmt.query_map(params![now], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect::<Result<_, _>>()?
            };
            let mut reaped = Reaped::default();
            for (id, attempts) in expired {
                let Ok(uuid) = Uuid::parse_str(&id) else {
                    continue;
                };
                if attempts >= i64::from(max_attempts) {
                    let error = serde_json::to_string(&failure(uuid))?;
                    tx.execute(
                        "UPDATE jobs SET status = 'failed', finished_at = ?2, error = ?3, \
                         lease_until = NULL WHERE id = ?1",
                        params![id, now, error],
                    )?;
                    reaped.failed.push(uuid);
                } else {
                    tx.execute(
                        "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                         owner = NULL, lease_until = NULL WHERE id = ?1",
                        params![id],
                    )?;
                    reaped.requeued.push(uuid);
                }
            }
            tx.commit()?;
            Ok(reaped)
        })
    }

    fn cancel(&self, id: Uuid, now: i64) -> RepoResult<Option<JobStatus>> {
        self.with(|c| {
            let tx = c.transaction()?;
            let status: Option<String> = tx
                .query_row(
                    "SELECT status FROM jobs WHERE id = ?1",
                    params![id.to_string()],
                    |r| r.get(0),
                )
                .optional()?;
            let Some(prev) = status.as_deref().and_then(JobStatus::parse) else {
                return Ok(None);
            };
            if prev.is_terminal() {
                return Ok(None);
            }
            tx.execute(
                "UPDATE jobs SET status = 'cancelled', finished_at = ?2, lease_until = NULL \
                 WHERE id = ?1",
                params![id.to_string(), now],
            )?;
            tx.commit()?;
            Ok(Some(prev))
        })
    }

    fn fail_queued(&self, id: Uuid, problem: &Problem, now: i64) -> RepoResult<bool> {
        let error = serde_json::to_string(problem)?;
        self.with(|c| {
            let n = c.execute(
                "UPDATE jobs SET status = 'failed', finished_at = ?2, error = ?3 \
                 WHERE id = ?1 AND status = 'queued'",
                params![id.to_string(), now, error],
            )?;
            Ok(n == 1)
        })
    }

    fn delete(&self, id: Uuid) -> RepoResult<bool> {
        self.with(|c| {
            let n = c.execute("DELETE FROM jobs WHERE id = ?1", params![id.to_string()])?;
            Ok(n == 1)
        })
    }

    fn expired(&self, before: i64, limit: usize) -> RepoResult<Vec<Uuid>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached(
                "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') \
                 AND finished_at < ?1 ORDER BY finished_at ASC LIMIT ?2",
            )?;
            let ids = stmt
                .query_map(params![before, limit as i64], |r| r.get::<_, String>(0))?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ids.iter().filter_map(|s| Uuid::parse_str(s).ok()).collect())
        })
    }

    fn counts(&self) -> RepoResult<Vec<(JobStatus, u64)>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached("SELECT status, COUNT(*) FROM jobs GROUP BY status")?;
            let rows = stmt
                .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(JobStatus::ALL
                .iter()
                .map(|s| {
                    let n = rows
                        .iter()
                        .find(|(name, _)| name == s.as_str())
                        .map(|(_, n)| *n as u64)
                        .unwrap_or(0);
                    (*s, n)
                })
                .collect())
        })
    }

    fn counts_by_tenant(&self) -> RepoResult<Vec<(String, JobStatus, u64)>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached(
                "SELECT tenant, status, COUNT(*) FROM jobs GROUP BY tenant, status \
                 ORDER BY tenant, status",
            )?;
            let rows = stmt
                .query_map([], |r| {
                    Ok((
                        r.get::<_, String>(0)?,
                        r.get::<_, String>(1)?,
                        r.get::<_, i64>(2)?,
                    ))
                })?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(rows
                .into_iter()
                .filter_map(|(t, s, n)| Some((t, JobStatus::parse(&s)?, n as u64)))
                .collect())
        })
    }

    fn ids(&self) -> RepoResult<Vec<Uuid>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached("SELECT id FROM jobs")?;
            let ids = stmt
                .query_map([], |r| r.get::<_, String>(0))?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ids.iter().filter_map(|s| Uuid::parse_str(s).ok()).collect())
        })
    }

    fn idempotent(
        &self,
        tenant: &str,
        scope: &str,
        key: &str,
        since: i64,
    ) -> RepoResult<Option<Remembered>> {
        self.with(|c| read_remembered(c, tenant, scope, key, since))
    }

    fn remember(
        &self,
        tenant: &str,
        scope: &str,
        key: &str,
        answer: &Remembered,
        since: i64,
    ) -> RepoResult<Option<Remembered>> {
        self.with(|c| {
            let tx = c.transaction()?;
            if let Some(earlier) = read_remembered(&tx, tenant, scope, key, since)? {
                return Ok(Some(earlier));
            }
            tx.execute(
                "INSERT OR REPLACE INTO idempotency \
                 (tenant, scope, key, body_hash, status, body, location, created_at) \
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
                params![
                    tenant,
                    scope,
                    key,
                    answer.body_hash,
                    answer.status,
                    answer.body,
                    answer.location,
                    answer.created_at
                ],
            )?;
            tx.commit()?;
            Ok(None)
        })
    }

    fn forget_idempotent(&self, before: i64) -> RepoResult<usize> {
        self.with(|c| {
            Ok(c.execute(
                "DELETE FROM idempotency WHERE created_at < ?1",
                params![before],
            )?)
        })
    }

    fn set_callback(&self, id: Uuid, callback: &Callback) -> RepoResult<()> {
        let text = serde_json::to_string(callback)?;
        self.with(|c| {
            c.execute(
                "UPDATE jobs SET callback = ?2 WHERE id = ?1",
                params![id.to_string(), text],
            )?;
            Ok(())
        })
    }

    fn ping(&self) -> RepoResult<()> {
        self.with(|c| {
            c.query_row("SELECT COUNT(*) FROM jobs WHERE 0", [], |r| {
                r.get::<_, i64>(0)
            })?;
            Ok(())
        })
    }

    fn insert_calibration(&self, cal: &CalibrationRecord) -> RepoResult<()> {
        let detail = serde_json::to_string(&cal.detail)?;
        let artifacts = serde_json::to_string(&cal.artifacts)?;
        self.with(|c| {
            c.execute(
                &format!(
                    "INSERT INTO calibrations ({CALIBRATION_COLUMNS}) VALUES (?1, ?2, ?3, ?4, ?5, ?6)"
                ),
                params![
                    cal.id.to_string(),
                    cal.tenant,
                    cal.created_at,
                    detail,
                    cal.table,
                    artifacts
                ],
            )?;
            Ok(())
        })
    }

    fn get_calibration(&self, id: Uuid) -> RepoResult<Option<CalibrationRecord>> {
        self.with(|c| {
            c.query_row(
                &format!("SELECT {CALIBRATION_COLUMNS} FROM calibrations WHERE id = ?1"),
                params![id.to_string()],
                read_calibration,
            )
            .optional()?
            .map(decode_calibration)
            .transpose()
        })
    }

    fn list_calibrations(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<CalibrationRecord>> {
        let first = before.is_none();
        let (at, id) = before.map_or((0, String::new()), |(at, id)| (at, id.to_string()));
        self.with(|c| {
            let mut stmt = c.prepare_cached(&format!(
                "SELECT {CALIBRATION_COLUMNS} FROM calibrations WHERE (?1 IS NULL OR tenant = ?1) \
                 AND (?2 OR (created_at, id) < (?3, ?4)) \
                 ORDER BY created_at DESC, id DESC LIMIT ?5"
            ))?;
            let rows = stmt.query_map(
                params![tenant, first, at, id, limit as i64],
                read_calibration,
            )?;
            let rows = rows.collect::<rusqlite::Result<Vec<_>>>()?;
            Ok(readable(
                rows.into_iter().map(decode_calibration),
                "calibration",
            ))
        })
    }

    fn delete_calibration(&self, id: Uuid) -> RepoResult<bool> {
        self.with(|c| {
            let n = c.execute(
                "DELETE FROM calibrations WHERE id = ?1",
                params![id.to_string()],
            )?;
            Ok(n == 1)
        })
    }

    fn calibration_ids(&self) -> RepoResult<Vec<Uuid>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached("SELECT id FROM calibrations")?;
            let ids = stmt
                .query_map([], |r| r.get::<_, String>(0))?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ids.iter().filter_map(|s| Uuid::parse_str(s).ok()).collect())
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn repo() -> (tempfile::TempDir, SqliteRepo) {
        let dir = tempfile::tempdir().unwrap();
        let repo = SqliteRepo::open(&dir.path().join("jobs.sqlite")).unwrap();
        (dir, repo)
    }

    fn claim(repo: &SqliteRepo, now: i64) -> Option<Lease> {
        repo.claim("w", Duration::from_secs(5), now).unwrap()
    }

    fn queue(repo: &SqliteRepo, tenant: &str, at: i64) -> Uuid {
        let id = Uuid::new_v4();
        let job = JobRecord::new_queued(id, tenant, at, 3, serde_json::json!({}));
        assert_eq!(repo.insert(&job, 100, 100).unwrap(), Admission::Accepted);
        id
    }

    #[test]
    fn tenants_take_turns_and_each_keeps_its_order() {
        let (_dir, repo) = repo();
        let a: Vec<Uuid> = (0..4).map(|i| queue(&repo, "a", i)).collect();
        let b: Vec<Uuid> = (0..2).map(|i| queue(&repo, "b", 10 + i)).collect();
        let order: Vec<Uuid> = (0..6).map(|i| claim(&repo, 100 + i).unwrap().id).collect();
        assert_eq!(order, [a[0], b[0], a[1], b[1], a[2], a[3]]);
    }

    #[test]
    fn an_expired_lease_is_reaped_and_its_late_writes_refused() {
        let (_dir, repo) = repo();
        let id = queue(&repo, "t", 1);
        let failure = |id: Uuid| Problem {
            kind: "urn:test".into(),
            title: "lost".into(),
            status: 500,
            detail: format!("{id} lost"),
            instance: None,
        };
        let first = claim(&repo, 1000).unwrap(); // lease until 6000
        assert_eq!(repo.reap(2, &failure, 5999).unwrap(), Reaped::default());
        assert!(
            repo.heartbeat(&[first], Duration::from_secs(5), 2000)
                .unwrap()
                .is_empty()
        );
        assert_eq!(
            repo.reap(2, &failure, 6999).unwrap(),
            Reaped::default(),
            "extended"
        );
        let reaped = repo.reap(2, &failure, 7001).unwrap();
        assert_eq!(reaped.requeued, [id]);
        let second = claim(&repo, 7100).unwrap();
        assert_eq!(second.id, id);
        assert!(second.token > first.token);
        // The first worker wakes up: every write it makes is refused.
        assert!(!repo.progress(first, "solve", 0.5, 7200).unwrap());
        assert_eq!(
            repo.heartbeat(&[first, second], Duration::from_secs(5), 7200)
                .unwrap(),
            [first]
        );
        let done = Finish::Succeeded {
            result: serde_json::json!({}),
            artifacts: vec![],
        };
        assert!(!repo.finish(first, &done, 7300).unwrap());
        assert!(!repo.requeue(first).unwrap());
        assert_eq!(repo.get(id).unwrap().unwrap().status, JobStatus::Running);
        // The second attempt's lease expires too: that was the last attempt.
        let reaped = repo.reap(2, &failure, 20_000).unwrap();
        assert_eq!(reaped.failed, [id]);
        let rec = repo.get(id).unwrap().unwrap();
        assert_eq!((rec.status, rec.attempts), (JobStatus::Failed, 2));
        assert_eq!(rec.error.unwrap().detail, format!("{id} lost"));
        assert!(!repo.finish(second, &done, 20_001).unwrap());
    }

    #[test]
    fn lifecycle_and_races() {
        let (_dir, repo) = repo();
        let id = Uuid::new_v4();
        assert_eq!(
            repo.insert(
                &JobRecord::new_queued(id, "t", 1000, 4, serde_json::json!({})),
                9,
                9
            )
            .unwrap(),
            Admission::Accepted
        );
        let lease = claim(&repo, 2000).unwrap();
        assert_eq!(lease.id, id);
        assert!(claim(&repo, 2001).is_none(), "only a queued job is claimed");
        assert!(repo.progress(lease, "solve", 0.25, 2100).unwrap());
        let rec = repo.get(id).unwrap().unwrap();
        assert_eq!(rec.status, JobStatus::Running);
        assert_eq!(rec.stage.as_deref(), Some("solve"));
        assert_eq!(rec.attempts, 1);
        assert_eq!(repo.cancel(id, 2200).unwrap(), Some(JobStatus::Running));
        assert_eq!(
            repo.heartbeat(&[lease], Duration::from_secs(5), 2250)
                .unwrap(),
            [lease],
            "a cancelled job's lease is no longer held"
        );
        let done = Finish::Succeeded {
            result: serde_json::json!({"width": 3}),
            artifacts: vec![],
        };
        assert!(!repo.finish(lease, &done, 2300).unwrap(), "cancel wins");
        assert_eq!(repo.cancel(id, 2400).unwrap(), None);
        assert_eq!(repo.get(id).unwrap().unwrap().status, JobStatus::Cancelled);
        assert_eq!(repo.expired(2201, 10).unwrap(), vec![id]);
        assert!(repo.delete(id).unwrap());
        assert!(repo.get(id).unwrap().is_none());
    }

    #[test]
    fn paging_is_newest_first_and_stable() {
        let (_dir, repo) = repo();
        let mut ids = Vec::new();
        for i in 0..7 {
            let id = Uuid::new_v4();
            // Two jobs per millisecond: the id breaks ties.
            repo.insert(
                &JobRecord::new_queued(
                    id,
                    if i % 3 == 0 { "a" } else { "b" },
                    100 + i / 2,
                    3,
                    serde_json::json!({}),
                ),
                100,
                100,
            )
            .unwrap();
            ids.push(id);
        }
        let mut seen = Vec::new();
        let mut cursor = None;
        loop {
            let page = repo.list(None, 3, cursor).unwrap();
            if page.is_empty() {
                break;
            }
            cursor = page.last().map(|r| (r.created_at, r.id));
            seen.extend(page);
        }
        assert_eq!(seen.len(), 7);
        assert!(
            seen.windows(2)
                .all(|w| (w[0].created_at, w[0].id) > (w[1].created_at, w[1].id))
        );
        let counts = repo.counts().unwrap();
        assert_eq!(counts[0], (JobStatus::Queued, 7));
        // One tenant's pages hold only its jobs, in the same order.
        let a = repo.list(Some("a"), 2, None).unwrap();
        let rest = repo
            .list(Some("a"), 2, a.last().map(|r| (r.created_at, r.id)))
            .unwrap();
        let theirs: Vec<Uuid> = seen
            .iter()
            .filter(|r| r.tenant == "a")
            .map(|r| r.id)
            .collect();
        let paged: Vec<Uuid> = a.iter().chain(&rest).map(|r| r.id).collect();
        assert_eq!(paged, theirs);
        assert_eq!(theirs.len(), 3);
    }

    #[test]
    fn reopening_keeps_records_and_schema() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("jobs.sqlite");
        let id = Uuid::new_v4();
        {
            let repo = SqliteRepo::open(&path).unwrap();
            repo.insert(
                &JobRecord::new_queued(id, "t", 5, 3, serde_json::json!({"solver": "l2"})),
                100,
                100,
            )
            .unwrap();
        }
        let repo = SqliteRepo::open(&path).unwrap();
        let rec = repo.get(id).unwrap().unwrap();
        assert_eq!(rec.options, serde_json::json!({"solver": "l2"}));
        assert_eq!(repo.unfinished().unwrap().len(), 1);
    }

    #[test]
    fn a_tenant_past_its_active_jobs_is_not_recorded() {
        let (_dir, repo) = repo();
        // Created in the order made, so that the first one is claimed first.
        let clock = std::cell::Cell::new(0);
        let job = |t: &str| {
            clock.set(clock.get() + 1);
            JobRecord::new_queued(Uuid::new_v4(), t, clock.get(), 1, serde_json::json!({}))
        };
        let (first, second) = (job("a"), job("a"));
        let accepted = |j: &JobRecord| repo.insert(j, 2, 4).unwrap() == Admission::Accepted;
        assert!(accepted(&first));
        assert!(accepted(&second));
        assert_eq!(
            repo.insert(&job("a"), 2, 4).unwrap(),
            Admission::TenantFull,
            "a has 2 active"
        );
        assert!(accepted(&job("b")), "b is not counted with a");
        assert_eq!(repo.active("a").unwrap(), 2);
        assert_eq!(repo.queued().unwrap(), 3);
        assert_eq!(
            repo.insert(&job("c"), 2, 3).unwrap(),
            Admission::QueueFull,
            "3 wait"
        );
        // A finished job no longer counts, but its artifacts are stored bytes.
        let first = claim(&repo, 2).unwrap();
        assert_eq!(repo.queued().unwrap(), 2);
        assert_eq!(repo.get(first.id).unwrap().unwrap().tenant, "a");
        let artifact = |name: &str, bytes| ArtifactInfo {
            name: name.into(),
            bytes,
            etag: "\"x\"".into(),
            key: None,
        };
        let done = Finish::Succeeded {
            result: serde_json::json!({}),
            artifacts: vec![artifact("albedo.png", 1000), artifact("mesh.glb", 234)],
        };
        assert!(repo.finish(first, &done, 3).unwrap());
        assert_eq!(repo.active("a").unwrap(), 1);
        assert!(accepted(&job("a")));
        assert_eq!(repo.stored_bytes("a").unwrap(), 1234);
        assert_eq!(repo.stored_bytes("b").unwrap(), 0);
        let by_tenant = repo.counts_by_tenant().unwrap();
        assert!(by_tenant.contains(&("a".into(), JobStatus::Queued, 2)));
        assert!(by_tenant.contains(&("a".into(), JobStatus::Succeeded, 1)));
        assert!(by_tenant.contains(&("b".into(), JobStatus::Queued, 1)));
    }

    #[test]
    fn jobs_recorded_before_tenants_belong_to_the_default_tenant() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("jobs.sqlite");
        {
            let conn = Connection::open(&path).unwrap();
            conn.execute_batch(MIGRATIONS[0]).unwrap();
            conn.pragma_update(None, "user_version", 1).unwrap();
            conn.execute(
                "INSERT INTO jobs (id, status, created_at, options) VALUES (?1, 'queued', 1, '{}')",
                params![Uuid::nil().to_string()],
            )
            .unwrap();
        }
        let repo = SqliteRepo::open(&path).unwrap();
        let rec = repo.get(Uuid::nil()).unwrap().unwrap();
        assert_eq!(rec.tenant, super::super::tenants::OPEN_TENANT);
        assert_eq!(repo.list(Some("default"), 5, None).unwrap().len(), 1);
    }

    #[test]
    fn calibrations_are_kept_listed_per_tenant_and_deleted() {
        let (_dir, repo) = repo();
        let cal = |tenant: &str, at| CalibrationRecord {
            id: Uuid::new_v4(),
            tenant: tenant.into(),
            created_at: at,
            detail: serde_json::json!({"image_count": 3}),
            table: "im1.png, 0, 0, 1\n".into(),
            artifacts: vec![ArtifactInfo {
                name: "lights.csv".into(),
                bytes: 17,
                etag: "\"x\"".into(),
                key: None,
            }],
        };
        let (a1, b1, a2) = (cal("a", 10), cal("b", 11), cal("a", 12));
        for c in [&a1, &b1, &a2] {
            repo.insert_calibration(c).unwrap();
        }
        assert_eq!(repo.get_calibration(a1.id).unwrap().as_ref(), Some(&a1));
        let ids = |page: Vec<CalibrationRecord>| page.into_iter().map(|c| c.id).collect::<Vec<_>>();
        assert_eq!(
            ids(repo.list_calibrations(Some("a"), 10, None).unwrap()),
            [a2.id, a1.id]
        );
        assert_eq!(
            ids(repo.list_calibrations(None, 2, Some((12, a2.id))).unwrap()),
            [b1.id, a1.id]
        );
        assert_eq!(repo.calibration_ids().unwrap().len(), 3);
        assert!(repo.delete_calibration(a1.id).unwrap());
        assert!(!repo.delete_calibration(a1.id).unwrap());
        assert!(repo.get_calibration(a1.id).unwrap().is_none());
        // Jobs and calibrations do not meet.
        assert!(repo.get(b1.id).unwrap().is_none());
    }

    #[test]
    fn idempotent_answers_are_kept_per_tenant_and_key_for_the_window() {
        let (_dir, repo) = repo();
        let answer = |hash: &str, at| Remembered {
            body_hash: hash.into(),
            status: 202,
            body: format!("{{\"h\":\"{hash}\"}}"),
            location: Some("/v1/jobs/x".into()),
            created_at: at,
        };
        let first = answer("h1", 100);
        assert_eq!(repo.remember("a", "jobs", "k", &first, 0).unwrap(), None);
        // A second answer for the same key does not replace the first.
        assert_eq!(
            repo.remember("a", "jobs", "k", &answer("h2", 150), 0)
                .unwrap(),
            Some(first.clone())
        );
        assert_eq!(
            repo.idempotent("a", "jobs", "k", 0).unwrap(),
            Some(first.clone())
        );
        assert_eq!(repo.idempotent("b", "jobs", "k", 0).unwrap(), None);
        assert_eq!(repo.idempotent("a", "calibrations", "k", 0).unwrap(), None);
        // Past the window the key is free again.
        assert_eq!(repo.idempotent("a", "jobs", "k", 101).unwrap(), None);
        let later = answer("h3", 300);
        assert_eq!(repo.remember("a", "jobs", "k", &later, 101).unwrap(), None);
        assert_eq!(repo.idempotent("a", "jobs", "k", 101).unwrap(), Some(later));
        assert_eq!(repo.forget_idempotent(301).unwrap(), 1);
        assert_eq!(repo.idempotent("a", "jobs", "k", 0).unwrap(), None);
    }
}
