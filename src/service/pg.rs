//! [`JobRepo`] in PostgreSQL (`--database-url postgres://…`): the same records, states
//! and conditional updates as [`SqliteRepo`](super::repo::SqliteRepo), in a database
//! operators already run and back up.
//!
//! The repo keeps its connections (a `deadpool-postgres` pool) on a small runtime of its
//! own, so its blocking methods work from any thread, the async runtime's included.
//! Migrations run at start in one transaction under an advisory lock, so instances that
//! start together do not race. Jobs are still claimed the single-node way (`unfinished`
//! at start, `start(id)`), so one instance holds the database: a session advisory lock,
//! taken at start and kept, refuses a second one with a clear error.

use std::future::Future;
use std::sync::mpsc;

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod};
use tokio_postgres::{NoTls, Row};
use uuid::Uuid;

use super::error::Problem;
use super::repo::{
    CalibrationRecord, Callback, Finish, JobRecord, JobRepo, JobStatus, RawCalibration, RawRecord,
    Remembered, RepoError, RepoResult, decode_calibration,
};

/// Schema versions, applied in order; `photostereo_schema.version` is the number applied.
const MIGRATIONS: &[&str] = &[
    // 1: jobs, idempotent answers and calibrations, as SQLite's first five versions.
    "CREATE TABLE jobs (
        id           TEXT PRIMARY KEY NOT NULL,
        status       TEXT NOT NULL,
        stage        TEXT,
        progress     DOUBLE PRECISION NOT NULL DEFAULT 0,
        created_at   BIGINT NOT NULL,
        started_at   BIGINT,
        finished_at  BIGINT,
        heartbeat_at BIGINT,
        attempts     BIGINT NOT NULL DEFAULT 0,
        image_count  BIGINT NOT NULL DEFAULT 0,
        options      TEXT NOT NULL,
        error        TEXT,
        result       TEXT,
        artifacts    TEXT,
        tenant       TEXT NOT NULL DEFAULT 'default',
        callback     TEXT
    );
    CREATE INDEX jobs_by_created ON jobs (created_at DESC, id DESC);
    CREATE INDEX jobs_by_status ON jobs (status, finished_at);
    CREATE INDEX jobs_by_tenant ON jobs (tenant, created_at DESC, id DESC);
    CREATE TABLE idempotency (
        tenant     TEXT NOT NULL,
        scope      TEXT NOT NULL,
        key        TEXT NOT NULL,
        body_hash  TEXT NOT NULL,
        status     INTEGER NOT NULL,
        body       TEXT NOT NULL,
        location   TEXT,
        created_at BIGINT NOT NULL,
        PRIMARY KEY (tenant, scope, key)
    );
    CREATE INDEX idempotency_by_age ON idempotency (created_at);
    CREATE TABLE calibrations (
        id          TEXT PRIMARY KEY NOT NULL,
        tenant      TEXT NOT NULL,
        created_at  BIGINT NOT NULL,
        detail      TEXT NOT NULL,
        light_table TEXT NOT NULL,
        artifacts   TEXT NOT NULL
    );
    CREATE INDEX calibrations_by_created ON calibrations (created_at DESC, id DESC);
    CREATE INDEX calibrations_by_tenant ON calibrations (tenant, created_at DESC, id DESC);",
];

/// Advisory lock keys (any two fixed numbers; 0x7073 is "ps").
const MIGRATION_LOCK: i64 = 0x7073_0001;
const INSTANCE_LOCK: i64 = 0x7073_0002;

const COLUMNS: &str = "id, status, stage, progress, created_at, started_at, finished_at, \
     heartbeat_at, attempts, image_count, options, error, result, artifacts, tenant, callback";
const CALIBRATION_COLUMNS: &str = "id, tenant, created_at, detail, light_table, artifacts";

fn db_error(e: tokio_postgres::Error) -> RepoError {
    match e.as_db_error() {
        // Connection exceptions (08…) and a server shutting down or starting (57P0…) pass.
        Some(db) if is_transient(db.code().code()) => {
            RepoError::unavailable(format!("PostgreSQL: {}", db.message()))
        }
        Some(db) => RepoError::new(format!("PostgreSQL: {}", db.message())),
        // No answer from the server at all: a closed connection, a refused one.
        None => RepoError::unavailable(format!("PostgreSQL does not answer: {e}")),
    }
}

fn is_transient(sqlstate: &str) -> bool {
    sqlstate.starts_with("08") || sqlstate.starts_with("57P0")
}

fn pool_error(e: deadpool_postgres::PoolError) -> RepoError {
    match e {
        deadpool_postgres::PoolError::Backend(e) => db_error(e),
        deadpool_postgres::PoolError::Timeout(_) => {
            RepoError::unavailable(format!("PostgreSQL does not answer: {e}"))
        }
        e => RepoError::new(format!("PostgreSQL connection pool: {e}")),
    }
}

/// [`JobRepo`] in a PostgreSQL database.
pub struct PgRepo {
    /// Runs the pool's connections; shut down in the background on drop (dropping a
    /// runtime may not block inside another one).
    runtime: Option<tokio::runtime::Runtime>,
    pool: Pool,
    /// The connection that holds [`INSTANCE_LOCK`] while this repo lives.
    _instance: tokio_postgres::Client,
}

impl Drop for PgRepo {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl PgRepo {
    /// Connect to `url` (`postgres://user:password@host:port/database`), apply the
    /// migrations this program knows and take the database for this instance.
    pub fn connect(url: &str) -> RepoResult<Self> {
        let config: tokio_postgres::Config = url
            .parse()
            .map_err(|e| RepoError::new(format!("--database-url: {e}")))?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("photostereo-pg")
            .enable_all()
            .build()
            .map_err(|e| RepoError::new(format!("starting the database runtime: {e}")))?;
        let manager = Manager::from_config(
            config.clone(),
            NoTls,
            ManagerConfig {
                recycling_method: RecyclingMethod::Fast,
            },
        );
        let pool = Pool::builder(manager)
            .max_size(8)
            .runtime(deadpool_postgres::Runtime::Tokio1)
            .wait_timeout(Some(std::time::Duration::from_secs(10)))
            .create_timeout(Some(std::time::Duration::from_secs(10)))
            .build()
            .map_err(|e| RepoError::new(format!("PostgreSQL connection pool: {e}")))?;
        let instance = block(&runtime, async move {
            let (client, connection) = config.connect(NoTls).await.map_err(db_error)?;
            tokio::spawn(async move {
                if let Err(e) = connection.await {
                    tracing::error!(error = %e, "the database connection that holds this instance's lock ended");
                }
            });
            let held: bool = client
                .query_one("SELECT pg_try_advisory_lock($1)", &[&INSTANCE_LOCK])
                .await
                .map_err(db_error)?
                .get(0);
            if !held {
                return Err(RepoError::new(
                    "another photostereo instance uses this database; one instance per \
                     database for now"
                        .into(),
                ));
            }
            Ok(client)
        })?;
        let repo = Self {
            runtime: Some(runtime),
            pool,
            _instance: instance,
        };
        repo.run(|mut c| async move {
            let tx = c.transaction().await.map_err(db_error)?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])
                .await
                .map_err(db_error)?;
            tx.batch_execute(
                "CREATE TABLE IF NOT EXISTS photostereo_schema (version BIGINT NOT NULL);
                 INSERT INTO photostereo_schema SELECT 0
                 WHERE NOT EXISTS (SELECT 1 FROM photostereo_schema);",
            )
            .await
            .map_err(db_error)?;
            let version: i64 = tx
                .query_one("SELECT version FROM photostereo_schema", &[])
                .await
                .map_err(db_error)?
                .get(0);
            if version as usize > MIGRATIONS.len() {
                return Err(RepoError::new(format!(
                    "database schema version {version} is newer than this program ({}); \
                     upgrade photostereo",
                    MIGRATIONS.len()
                )));
            }
            for (i, sql) in MIGRATIONS.iter().enumerate().skip(version as usize) {
                tx.batch_execute(sql).await.map_err(db_error)?;
                tx.execute(
                    "UPDATE photostereo_schema SET version = $1",
                    &[&((i + 1) as i64)],
                )
                .await
                .map_err(db_error)?;
            }
            tx.commit().await.map_err(db_error)
        })?;
        Ok(repo)
    }

    /// Run `f` with a pooled connection on the repo's runtime and wait for its answer.
    fn run<T, F, Fut>(&self, f: F) -> RepoResult<T>
    where
        T: Send + 'static,
        F: FnOnce(deadpool_postgres::Object) -> Fut + Send + 'static,
        Fut: Future<Output = RepoResult<T>> + Send,
    {
        let pool = self.pool.clone();
        let runtime = self.runtime.as_ref().expect("present until drop");
        block(runtime, async move {
            let client = pool.get().await.map_err(pool_error)?;
            f(client).await
        })
    }
}

/// Run `fut` on `runtime` and wait for it from this thread, whatever runtime (if any)
/// this thread belongs to.
fn block<T: Send + 'static>(
    runtime: &tokio::runtime::Runtime,
    fut: impl Future<Output = RepoResult<T>> + Send + 'static,
) -> RepoResult<T> {
    let (tx, rx) = mpsc::sync_channel(1);
    runtime.spawn(async move {
        let _ = tx.send(fut.await);
    });
    rx.recv()
        .map_err(|_| RepoError::new("the database task ended without an answer".into()))?
}

fn read_record(row: &Row) -> RawRecord {
    RawRecord {
        id: row.get(0),
        status: row.get(1),
        stage: row.get(2),
        progress: row.get(3),
        created_at: row.get(4),
        started_at: row.get(5),
        finished_at: row.get(6),
        heartbeat_at: row.get(7),
        attempts: row.get(8),
        image_count: row.get(9),
        options: row.get(10),
        error: row.get(11),
        result: row.get(12),
        artifacts: row.get(13),
        tenant: row.get(14),
        callback: row.get(15),
    }
}

fn records(rows: Vec<Row>) -> RepoResult<Vec<JobRecord>> {
    rows.iter().map(|r| read_record(r).decode()).collect()
}

fn read_calibration(row: &Row) -> RawCalibration {
    (
        row.get(0),
        row.get(1),
        row.get(2),
        row.get(3),
        row.get(4),
        row.get(5),
    )
}

fn read_remembered(row: &Row) -> Remembered {
    Remembered {
        body_hash: row.get(0),
        status: row.get::<_, i32>(1).clamp(0, u16::MAX as i32) as u16,
        body: row.get(2),
        location: row.get(3),
        created_at: row.get(4),
    }
}

fn uuids(rows: Vec<Row>) -> Vec<Uuid> {
    rows.iter()
        .filter_map(|r| Uuid::parse_str(r.get::<_, &str>(0)).ok())
        .collect()
}

const REMEMBERED: &str = "SELECT body_hash, status, body, location, created_at FROM idempotency \
     WHERE tenant = $1 AND scope = $2 AND key = $3 AND created_at >= $4";

impl JobRepo for PgRepo {
    fn insert(&self, job: &JobRecord, max_active: usize) -> RepoResult<bool> {
        let options = serde_json::to_string(&job.options)?;
        let error = job.error.as_ref().map(serde_json::to_string).transpose()?;
        let result = job.result.as_ref().map(serde_json::to_string).transpose()?;
        let artifacts = serde_json::to_string(&job.artifacts)?;
        let callback = job
            .callback
            .as_ref()
            .map(serde_json::to_string)
            .transpose()?;
        let job = job.clone();
        self.run(move |mut c| async move {
            // The count and the insert are one step per tenant: concurrent submissions of
            // one tenant wait for each other's transaction.
            let tx = c.transaction().await.map_err(db_error)?;
            tx.execute(
                "SELECT pg_advisory_xact_lock(hashtextextended($1, 0))",
                &[&job.tenant],
            )
            .await
            .map_err(db_error)?;
            let n = tx
                .execute(
                    &format!(
                        "INSERT INTO jobs ({COLUMNS}) SELECT $1, $2, $3, $4, $5, $6, $7, $8, \
                         $9, $10, $11, $12, $13, $14, $15, $17 WHERE (SELECT COUNT(*) FROM jobs \
                         WHERE tenant = $15 AND status IN ('queued', 'running')) < $16"
                    ),
                    &[
                        &job.id.to_string(),
                        &job.status.as_str(),
                        &job.stage,
                        &job.progress,
                        &job.created_at,
                        &job.started_at,
                        &job.finished_at,
                        &job.heartbeat_at,
                        &i64::from(job.attempts),
                        &i64::from(job.image_count),
                        &options,
                        &error,
                        &result,
                        &artifacts,
                        &job.tenant,
                        &(max_active as i64),
                        &callback,
                    ],
                )
                .await
                .map_err(db_error)?;
            tx.commit().await.map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn active(&self, tenant: &str) -> RepoResult<u64> {
        let tenant = tenant.to_string();
        self.run(move |c| async move {
            let n: i64 = c
                .query_one(
                    "SELECT COUNT(*) FROM jobs WHERE tenant = $1 \
                     AND status IN ('queued', 'running')",
                    &[&tenant],
                )
                .await
                .map_err(db_error)?
                .get(0);
            Ok(n as u64)
        })
    }

    fn stored_bytes(&self, tenant: &str) -> RepoResult<u64> {
        let tenant = tenant.to_string();
        self.run(move |c| async move {
            let n: i64 = c
                .query_one(
                    "SELECT COALESCE(SUM((a ->> 'bytes')::BIGINT), 0)::BIGINT \
                     FROM jobs, jsonb_array_elements(jobs.artifacts::JSONB) AS a \
                     WHERE jobs.tenant = $1 AND jobs.artifacts IS NOT NULL",
                    &[&tenant],
                )
                .await
                .map_err(db_error)?
                .get(0);
            Ok(n.max(0) as u64)
        })
    }

    fn get(&self, id: Uuid) -> RepoResult<Option<JobRecord>> {
        self.run(move |c| async move {
            let row = c
                .query_opt(
                    &format!("SELECT {COLUMNS} FROM jobs WHERE id = $1"),
                    &[&id.to_string()],
                )
                .await
                .map_err(db_error)?;
            row.map(|r| read_record(&r).decode()).transpose()
        })
    }

    fn list(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<JobRecord>> {
        let tenant = tenant.map(str::to_string);
        let first = before.is_none();
        let (at, id) = before.map_or((0, String::new()), |(at, id)| (at, id.to_string()));
        self.run(move |c| async move {
            let rows = c
                .query(
                    &format!(
                        "SELECT {COLUMNS} FROM jobs WHERE ($1::TEXT IS NULL OR tenant = $1) \
                         AND ($2 OR (created_at, id) < ($3, $4)) \
                         ORDER BY created_at DESC, id DESC LIMIT $5"
                    ),
                    &[&tenant, &first, &at, &id, &(limit as i64)],
                )
                .await
                .map_err(db_error)?;
            records(rows)
        })
    }

    fn unfinished(&self) -> RepoResult<Vec<JobRecord>> {
        self.run(|c| async move {
            let rows = c
                .query(
                    &format!(
                        "SELECT {COLUMNS} FROM jobs WHERE status IN ('queued', 'running') \
                         ORDER BY created_at ASC, id ASC"
                    ),
                    &[],
                )
                .await
                .map_err(db_error)?;
            records(rows)
        })
    }

    fn start(&self, id: Uuid, now: i64) -> RepoResult<bool> {
        self.run(move |c| async move {
            let n = c
                .execute(
                    "UPDATE jobs SET status = 'running', stage = NULL, progress = 0, \
                     started_at = $2, heartbeat_at = $2, attempts = attempts + 1 \
                     WHERE id = $1 AND status = 'queued'",
                    &[&id.to_string(), &now],
                )
                .await
                .map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn progress(&self, id: Uuid, stage: &str, progress: f64, now: i64) -> RepoResult<()> {
        let stage = stage.to_string();
        self.run(move |c| async move {
            c.execute(
                "UPDATE jobs SET stage = $2, progress = $3, heartbeat_at = $4 \
                 WHERE id = $1 AND status = 'running'",
                &[&id.to_string(), &stage, &progress, &now],
            )
            .await
            .map_err(db_error)?;
            Ok(())
        })
    }

    fn heartbeat(&self, ids: &[Uuid], now: i64) -> RepoResult<()> {
        let ids: Vec<String> = ids.iter().map(Uuid::to_string).collect();
        self.run(move |c| async move {
            c.execute(
                "UPDATE jobs SET heartbeat_at = $2 WHERE id = ANY($1) AND status = 'running'",
                &[&ids, &now],
            )
            .await
            .map_err(db_error)?;
            Ok(())
        })
    }

    fn finish(&self, id: Uuid, finish: &Finish, now: i64) -> RepoResult<bool> {
        let (sql, fields) = match finish {
            Finish::Succeeded { result, artifacts } => (
                "UPDATE jobs SET status = 'succeeded', progress = 1, finished_at = $2, \
                 heartbeat_at = $2, result = $3, artifacts = $4, error = NULL \
                 WHERE id = $1 AND status = 'running'",
                vec![
                    serde_json::to_string(result)?,
                    serde_json::to_string(artifacts)?,
                ],
            ),
            Finish::Failed(problem) => (
                "UPDATE jobs SET status = 'failed', finished_at = $2, heartbeat_at = $2, \
                 error = $3 WHERE id = $1 AND status = 'running'",
                vec![serde_json::to_string(problem)?],
            ),
        };
        self.run(move |c| async move {
            let id = id.to_string();
            let mut params: Vec<&(dyn tokio_postgres::types::ToSql + Sync)> = vec![&id, &now];
            params.extend(
                fields
                    .iter()
                    .map(|f| f as &(dyn tokio_postgres::types::ToSql + Sync)),
            );
            let n = c.execute(sql, &params).await.map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn requeue(&self, id: Uuid) -> RepoResult<bool> {
        self.run(move |c| async move {
            let n = c
                .execute(
                    "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0 \
                     WHERE id = $1 AND status = 'running'",
                    &[&id.to_string()],
                )
                .await
                .map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn cancel(&self, id: Uuid, now: i64) -> RepoResult<Option<JobStatus>> {
        self.run(move |mut c| async move {
            let tx = c.transaction().await.map_err(db_error)?;
            let id = id.to_string();
            let row = tx
                .query_opt("SELECT status FROM jobs WHERE id = $1 FOR UPDATE", &[&id])
                .await
                .map_err(db_error)?;
            let Some(prev) = row.and_then(|r| JobStatus::parse(r.get::<_, &str>(0))) else {
                return Ok(None);
            };
            if prev.is_terminal() {
                return Ok(None);
            }
            tx.execute(
                "UPDATE jobs SET status = 'cancelled', finished_at = $2 WHERE id = $1",
                &[&id, &now],
            )
            .await
            .map_err(db_error)?;
            tx.commit().await.map_err(db_error)?;
            Ok(Some(prev))
        })
    }

    fn fail_queued(&self, id: Uuid, problem: &Problem, now: i64) -> RepoResult<bool> {
        let error = serde_json::to_string(problem)?;
        self.run(move |c| async move {
            let n = c
                .execute(
                    "UPDATE jobs SET status = 'failed', finished_at = $2, error = $3 \
                     WHERE id = $1 AND status = 'queued'",
                    &[&id.to_string(), &now, &error],
                )
                .await
                .map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn delete(&self, id: Uuid) -> RepoResult<bool> {
        self.run(move |c| async move {
            let n = c
                .execute("DELETE FROM jobs WHERE id = $1", &[&id.to_string()])
                .await
                .map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn expired(&self, before: i64, limit: usize) -> RepoResult<Vec<Uuid>> {
        self.run(move |c| async move {
            let rows = c
                .query(
                    "SELECT id FROM jobs WHERE status IN ('succeeded', 'failed', 'cancelled') \
                     AND finished_at < $1 ORDER BY finished_at ASC LIMIT $2",
                    &[&before, &(limit as i64)],
                )
                .await
                .map_err(db_error)?;
            Ok(uuids(rows))
        })
    }

    fn counts(&self) -> RepoResult<Vec<(JobStatus, u64)>> {
        let rows = self.run(|c| async move {
            let rows = c
                .query("SELECT status, COUNT(*) FROM jobs GROUP BY status", &[])
                .await
                .map_err(db_error)?;
            Ok(rows
                .iter()
                .map(|r| (r.get::<_, String>(0), r.get::<_, i64>(1)))
                .collect::<Vec<_>>())
        })?;
        Ok(JobStatus::ALL
            .iter()
            .map(|s| {
                let n = rows
                    .iter()
                    .find(|(name, _)| name == s.as_str())
                    .map_or(0, |(_, n)| *n as u64);
                (*s, n)
            })
            .collect())
    }

    fn counts_by_tenant(&self) -> RepoResult<Vec<(String, JobStatus, u64)>> {
        self.run(|c| async move {
            let rows = c
                .query(
                    "SELECT tenant, status, COUNT(*) FROM jobs GROUP BY tenant, status \
                     ORDER BY tenant, status",
                    &[],
                )
                .await
                .map_err(db_error)?;
            Ok(rows
                .iter()
                .filter_map(|r| {
                    let status = JobStatus::parse(r.get::<_, &str>(1))?;
                    Some((r.get::<_, String>(0), status, r.get::<_, i64>(2) as u64))
                })
                .collect())
        })
    }

    fn ids(&self) -> RepoResult<Vec<Uuid>> {
        self.run(|c| async move {
            let rows = c
                .query("SELECT id FROM jobs", &[])
                .await
                .map_err(db_error)?;
            Ok(uuids(rows))
        })
    }

    fn idempotent(
        &self,
        tenant: &str,
        scope: &str,
        key: &str,
        since: i64,
    ) -> RepoResult<Option<Remembered>> {
        let (tenant, scope, key) = (tenant.to_string(), scope.to_string(), key.to_string());
        self.run(move |c| async move {
            let row = c
                .query_opt(REMEMBERED, &[&tenant, &scope, &key, &since])
                .await
                .map_err(db_error)?;
            Ok(row.as_ref().map(read_remembered))
        })
    }

    fn remember(
        &self,
        tenant: &str,
        scope: &str,
        key: &str,
        answer: &Remembered,
        since: i64,
    ) -> RepoResult<Option<Remembered>> {
        let (tenant, scope, key) = (tenant.to_string(), scope.to_string(), key.to_string());
        let answer = answer.clone();
        self.run(move |mut c| async move {
            // One writer per key: the first answer within the window is the one kept.
            let tx = c.transaction().await.map_err(db_error)?;
            tx.execute(
                "SELECT pg_advisory_xact_lock(hashtextextended($1 || '/' || $2 || '/' || $3, 0))",
                &[&tenant, &scope, &key],
            )
            .await
            .map_err(db_error)?;
            if let Some(row) = tx
                .query_opt(REMEMBERED, &[&tenant, &scope, &key, &since])
                .await
                .map_err(db_error)?
            {
                return Ok(Some(read_remembered(&row)));
            }
            tx.execute(
                "INSERT INTO idempotency \
                 (tenant, scope, key, body_hash, status, body, location, created_at) \
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8) \
                 ON CONFLICT (tenant, scope, key) DO UPDATE SET body_hash = $4, status = $5, \
                 body = $6, location = $7, created_at = $8",
                &[
                    &tenant,
                    &scope,
                    &key,
                    &answer.body_hash,
                    &i32::from(answer.status),
                    &answer.body,
                    &answer.location,
                    &answer.created_at,
                ],
            )
            .await
            .map_err(db_error)?;
            tx.commit().await.map_err(db_error)?;
            Ok(None)
        })
    }

    fn forget_idempotent(&self, before: i64) -> RepoResult<usize> {
        self.run(move |c| async move {
            let n = c
                .execute("DELETE FROM idempotency WHERE created_at < $1", &[&before])
                .await
                .map_err(db_error)?;
            Ok(n as usize)
        })
    }

    fn set_callback(&self, id: Uuid, callback: &Callback) -> RepoResult<()> {
        let text = serde_json::to_string(callback)?;
        self.run(move |c| async move {
            c.execute(
                "UPDATE jobs SET callback = $2 WHERE id = $1",
                &[&id.to_string(), &text],
            )
            .await
            .map_err(db_error)?;
            Ok(())
        })
    }

    fn ping(&self) -> RepoResult<()> {
        self.run(|c| async move {
            c.query_one("SELECT COUNT(*) FROM jobs WHERE false", &[])
                .await
                .map_err(db_error)?;
            Ok(())
        })
    }

    fn insert_calibration(&self, cal: &CalibrationRecord) -> RepoResult<()> {
        let detail = serde_json::to_string(&cal.detail)?;
        let artifacts = serde_json::to_string(&cal.artifacts)?;
        let (id, tenant, created_at, table) = (
            cal.id.to_string(),
            cal.tenant.clone(),
            cal.created_at,
            cal.table.clone(),
        );
        self.run(move |c| async move {
            c.execute(
                &format!(
                    "INSERT INTO calibrations ({CALIBRATION_COLUMNS}) \
                     VALUES ($1, $2, $3, $4, $5, $6)"
                ),
                &[&id, &tenant, &created_at, &detail, &table, &artifacts],
            )
            .await
            .map_err(db_error)?;
            Ok(())
        })
    }

    fn get_calibration(&self, id: Uuid) -> RepoResult<Option<CalibrationRecord>> {
        self.run(move |c| async move {
            c.query_opt(
                &format!("SELECT {CALIBRATION_COLUMNS} FROM calibrations WHERE id = $1"),
                &[&id.to_string()],
            )
            .await
            .map_err(db_error)?
            .map(|r| decode_calibration(read_calibration(&r)))
            .transpose()
        })
    }

    fn list_calibrations(
        &self,
        tenant: Option<&str>,
        limit: usize,
        before: Option<(i64, Uuid)>,
    ) -> RepoResult<Vec<CalibrationRecord>> {
        let tenant = tenant.map(str::to_string);
        let first = before.is_none();
        let (at, id) = before.map_or((0, String::new()), |(at, id)| (at, id.to_string()));
        self.run(move |c| async move {
            let rows = c
                .query(
                    &format!(
                        "SELECT {CALIBRATION_COLUMNS} FROM calibrations \
                         WHERE ($1::TEXT IS NULL OR tenant = $1) \
                         AND ($2 OR (created_at, id) < ($3, $4)) \
                         ORDER BY created_at DESC, id DESC LIMIT $5"
                    ),
                    &[&tenant, &first, &at, &id, &(limit as i64)],
                )
                .await
                .map_err(db_error)?;
            rows.iter()
                .map(|r| decode_calibration(read_calibration(r)))
                .collect()
        })
    }

    fn delete_calibration(&self, id: Uuid) -> RepoResult<bool> {
        self.run(move |c| async move {
            let n = c
                .execute("DELETE FROM calibrations WHERE id = $1", &[&id.to_string()])
                .await
                .map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn calibration_ids(&self) -> RepoResult<Vec<Uuid>> {
        self.run(|c| async move {
            let rows = c
                .query("SELECT id FROM calibrations", &[])
                .await
                .map_err(db_error)?;
            Ok(uuids(rows))
        })
    }
}
