//! Job records behind [`JobRepo`]; [`SqliteRepo`] keeps them in one SQLite file (WAL,
//! versioned migrations). The methods block: async callers go through
//! `tokio::task::spawn_blocking` (see `AppState::repo`), workers call them directly.

use std::path::Path;
use std::sync::Mutex;
use std::time::Duration;

use rusqlite::{Connection, OptionalExtension, Row, params};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use uuid::Uuid;

use super::error::Problem;

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
}

/// A job as the repo stores it. Times are milliseconds since the Unix epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRecord {
    pub id: Uuid,
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
}

impl JobRecord {
    /// A freshly accepted job.
    pub fn new_queued(id: Uuid, now: i64, image_count: u32, options: serde_json::Value) -> Self {
        Self {
            id,
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
        }
    }
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

/// A storage failure (the server's fault).
#[derive(Debug, thiserror::Error)]
#[error("job repository: {0}")]
pub struct RepoError(String);

impl From<rusqlite::Error> for RepoError {
    fn from(e: rusqlite::Error) -> Self {
        Self(e.to_string())
    }
}

impl From<serde_json::Error> for RepoError {
    fn from(e: serde_json::Error) -> Self {
        Self(format!("stored JSON: {e}"))
    }
}

pub type RepoResult<T> = Result<T, RepoError>;

/// Durable job records. Every state change is conditional on the state it leaves, so a
/// worker and a `DELETE` racing on one job cannot both win.
pub trait JobRepo: Send + Sync + 'static {
    fn insert(&self, job: &JobRecord) -> RepoResult<()>;
    fn get(&self, id: Uuid) -> RepoResult<Option<JobRecord>>;
    /// Newest first; `before` is the (created_at, id) of the last job of the previous page.
    fn list(&self, limit: usize, before: Option<(i64, Uuid)>) -> RepoResult<Vec<JobRecord>>;
    /// Queued and running jobs, oldest first (for the queue at startup).
    fn unfinished(&self) -> RepoResult<Vec<JobRecord>>;
    /// queued → running; counts an attempt. False when the job is no longer queued.
    fn start(&self, id: Uuid, now: i64) -> RepoResult<bool>;
    /// Record the stage a running job has reached.
    fn progress(&self, id: Uuid, stage: &str, progress: f64, now: i64) -> RepoResult<()>;
    /// Mark running jobs as alive.
    fn heartbeat(&self, ids: &[Uuid], now: i64) -> RepoResult<()>;
    /// running → succeeded | failed. False when the job is no longer running (cancelled
    /// or deleted meanwhile).
    fn finish(&self, id: Uuid, finish: &Finish, now: i64) -> RepoResult<bool>;
    /// running → queued (to run again, e.g. after a shutdown interrupted it).
    fn requeue(&self, id: Uuid) -> RepoResult<bool>;
    /// queued | running → cancelled; returns the status it left, None if it was not
    /// cancellable (or does not exist).
    fn cancel(&self, id: Uuid, now: i64) -> RepoResult<Option<JobStatus>>;
    /// queued → failed (inputs lost, for example).
    fn fail_queued(&self, id: Uuid, problem: &Problem, now: i64) -> RepoResult<bool>;
    fn delete(&self, id: Uuid) -> RepoResult<bool>;
    /// Finished jobs whose `finished_at` is before `before`.
    fn expired(&self, before: i64, limit: usize) -> RepoResult<Vec<Uuid>>;
    fn counts(&self) -> RepoResult<Vec<(JobStatus, u64)>>;
    fn ids(&self) -> RepoResult<Vec<Uuid>>;
    /// Cheap round trip for readiness checks.
    fn ping(&self) -> RepoResult<()>;
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
];

/// [`JobRepo`] in a SQLite database file.
pub struct SqliteRepo {
    conn: Mutex<Connection>,
}

const COLUMNS: &str = "id, status, stage, progress, created_at, started_at, finished_at, \
     heartbeat_at, attempts, image_count, options, error, result, artifacts";

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
        return Err(RepoError(format!(
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
    })
}

struct RawRecord {
    id: String,
    status: String,
    stage: Option<String>,
    progress: f64,
    created_at: i64,
    started_at: Option<i64>,
    finished_at: Option<i64>,
    heartbeat_at: Option<i64>,
    attempts: i64,
    image_count: i64,
    options: String,
    error: Option<String>,
    result: Option<String>,
    artifacts: Option<String>,
}

impl RawRecord {
    fn decode(self) -> RepoResult<JobRecord> {
        let id = Uuid::parse_str(&self.id)
            .map_err(|e| RepoError(format!("stored job id {:?}: {e}", self.id)))?;
        let status = JobStatus::parse(&self.status)
            .ok_or_else(|| RepoError(format!("stored status {:?} of {id}", self.status)))?;
        Ok(JobRecord {
            id,
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
        })
    }
}

fn query_records(
    conn: &Connection,
    sql: &str,
    params: impl rusqlite::Params,
) -> RepoResult<Vec<JobRecord>> {
    let mut stmt = conn.prepare_cached(sql)?;
    let rows = stmt.query_map(params, read_record)?;
    let mut out = Vec::new();
    for raw in rows {
        out.push(raw?.decode()?);
    }
    Ok(out)
}

impl JobRepo for SqliteRepo {
    fn insert(&self, job: &JobRecord) -> RepoResult<()> {
        let options = serde_json::to_string(&job.options)?;
        let error = job.error.as_ref().map(serde_json::to_string).transpose()?;
        let result = job.result.as_ref().map(serde_json::to_string).transpose()?;
        let artifacts = serde_json::to_string(&job.artifacts)?;
        self.with(|c| {
            c.execute(
                &format!("INSERT INTO jobs ({COLUMNS}) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14)"),
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
                ],
            )?;
            Ok(())
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

    fn list(&self, limit: usize, before: Option<(i64, Uuid)>) -> RepoResult<Vec<JobRecord>> {
        let limit = limit as i64;
        self.with(|c| match before {
            None => query_records(
                c,
                &format!("SELECT {COLUMNS} FROM jobs ORDER BY created_at DESC, id DESC LIMIT ?1"),
                params![limit],
            ),
            Some((at, id)) => query_records(
                c,
                &format!(
                    "SELECT {COLUMNS} FROM jobs WHERE (created_at, id) < (?1, ?2) \
                     ORDER BY created_at DESC, id DESC LIMIT ?3"
                ),
                params![at, id.to_string(), limit],
            ),
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

    fn start(&self, id: Uuid, now: i64) -> RepoResult<bool> {
        self.with(|c| {
            let n = c.execute(
                "UPDATE jobs SET status = 'running', stage = NULL, progress = 0, \
                 started_at = ?2, heartbeat_at = ?2, attempts = attempts + 1 \
                 WHERE id = ?1 AND status = 'queued'",
                params![id.to_string(), now],
            )?;
            Ok(n == 1)
        })
    }

    fn progress(&self, id: Uuid, stage: &str, progress: f64, now: i64) -> RepoResult<()> {
        self.with(|c| {
            c.execute(
                "UPDATE jobs SET stage = ?2, progress = ?3, heartbeat_at = ?4 \
                 WHERE id = ?1 AND status = 'running'",
                params![id.to_string(), stage, progress, now],
            )?;
            Ok(())
        })
    }

    fn heartbeat(&self, ids: &[Uuid], now: i64) -> RepoResult<()> {
        self.with(|c| {
            let tx = c.transaction()?;
            for id in ids {
                tx.execute(
                    "UPDATE jobs SET heartbeat_at = ?2 WHERE id = ?1 AND status = 'running'",
                    params![id.to_string(), now],
                )?;
            }
            tx.commit()?;
            Ok(())
        })
    }

    fn finish(&self, id: Uuid, finish: &Finish, now: i64) -> RepoResult<bool> {
        let n = match finish {
            Finish::Succeeded { result, artifacts } => {
                let result = serde_json::to_string(result)?;
                let artifacts = serde_json::to_string(artifacts)?;
                self.with(|c| {
                    Ok(c.execute(
                        "UPDATE jobs SET status = 'succeeded', progress = 1, finished_at = ?2, \
                         heartbeat_at = ?2, result = ?3, artifacts = ?4, error = NULL \
                         WHERE id = ?1 AND status = 'running'",
                        params![id.to_string(), now, result, artifacts],
                    )?)
                })?
            }
            Finish::Failed(problem) => {
                let error = serde_json::to_string(problem)?;
                self.with(|c| {
                    Ok(c.execute(
                        "UPDATE jobs SET status = 'failed', finished_at = ?2, heartbeat_at = ?2, \
                         error = ?3 WHERE id = ?1 AND status = 'running'",
                        params![id.to_string(), now, error],
                    )?)
                })?
            }
        };
        Ok(n == 1)
    }

    fn requeue(&self, id: Uuid) -> RepoResult<bool> {
        self.with(|c| {
            let n = c.execute(
                "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0 \
                 WHERE id = ?1 AND status = 'running'",
                params![id.to_string()],
            )?;
            Ok(n == 1)
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
                "UPDATE jobs SET status = 'cancelled', finished_at = ?2 WHERE id = ?1",
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

    fn ids(&self) -> RepoResult<Vec<Uuid>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached("SELECT id FROM jobs")?;
            let ids = stmt
                .query_map([], |r| r.get::<_, String>(0))?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ids.iter().filter_map(|s| Uuid::parse_str(s).ok()).collect())
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
}

#[cfg(test)]
mod tests {
    use super::*;

    fn repo() -> (tempfile::TempDir, SqliteRepo) {
        let dir = tempfile::tempdir().unwrap();
        let repo = SqliteRepo::open(&dir.path().join("jobs.sqlite")).unwrap();
        (dir, repo)
    }

    #[test]
    fn lifecycle_and_races() {
        let (_dir, repo) = repo();
        let id = Uuid::new_v4();
        repo.insert(&JobRecord::new_queued(id, 1000, 4, serde_json::json!({})))
            .unwrap();
        assert!(repo.start(id, 2000).unwrap());
        assert!(!repo.start(id, 2001).unwrap(), "only a queued job starts");
        repo.progress(id, "solve", 0.25, 2100).unwrap();
        let rec = repo.get(id).unwrap().unwrap();
        assert_eq!(rec.status, JobStatus::Running);
        assert_eq!(rec.stage.as_deref(), Some("solve"));
        assert_eq!(rec.attempts, 1);
        assert_eq!(repo.cancel(id, 2200).unwrap(), Some(JobStatus::Running));
        let done = Finish::Succeeded {
            result: serde_json::json!({"width": 3}),
            artifacts: vec![],
        };
        assert!(!repo.finish(id, &done, 2300).unwrap(), "cancel wins");
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
            repo.insert(&JobRecord::new_queued(
                id,
                100 + i / 2,
                3,
                serde_json::json!({}),
            ))
            .unwrap();
            ids.push(id);
        }
        let mut seen = Vec::new();
        let mut cursor = None;
        loop {
            let page = repo.list(3, cursor).unwrap();
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
    }

    #[test]
    fn reopening_keeps_records_and_schema() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("jobs.sqlite");
        let id = Uuid::new_v4();
        {
            let repo = SqliteRepo::open(&path).unwrap();
            repo.insert(&JobRecord::new_queued(
                id,
                5,
                3,
                serde_json::json!({"solver": "l2"}),
            ))
            .unwrap();
        }
        let repo = SqliteRepo::open(&path).unwrap();
        let rec = repo.get(id).unwrap().unwrap();
        assert_eq!(rec.options, serde_json::json!({"solver": "l2"}));
        assert_eq!(repo.unfinished().unwrap().len(), 1);
    }
}
