//! [`JobRepo`](super::JobRepo) in PostgreSQL (`--database-url postgres://…`): the same
//! records, states and conditional updates as [`SqliteRepo`](super::SqliteRepo), in a
//! database operators already run and back up.
//!
//! The repo keeps its connections (a `deadpool-postgres` pool) on a small runtime of its
//! own, so its blocking methods work from any thread, the async runtime's included.
//! Migrations (the files in `postgres/migrations/`) run at start in one transaction under
//! an advisory lock, so instances that start together do not race. Any number of
//! instances share the database: workers claim jobs with `FOR UPDATE SKIP LOCKED`, leases
//! run out in the database's clock (`now()`), and a new or requeued job is announced with
//! `NOTIFY` to every instance's listener (see `postgres/queue.rs`).

mod queue;

use std::future::Future;
use std::sync::mpsc;
use std::time::Duration;

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod};
use tokio_postgres::{NoTls, Row};
use uuid::Uuid;

use super::error::{RepoError, RepoResult};
use super::model::{
    Admission, CalibrationRecord, Callback, JobRecord, JobStatus, Problem, Remembered,
};
use super::rows::{
    CALIBRATION_COLUMNS, COLUMNS, RawCalibration, RawRecord, decode_calibration,
    encode_calibration, readable, status_counts, uuids,
};
use super::traits::{Calibrations, Idempotency, Jobs};

/// Schema versions, in order (version `i + 1` is `MIGRATIONS[i]`);
/// `photostereo_schema.version` is the number applied.
const MIGRATIONS: &[&str] = &[
    include_str!("postgres/migrations/001_jobs_idempotency_calibrations.sql"),
    include_str!("postgres/migrations/002_leases.sql"),
];

/// Advisory lock keys (any two fixed numbers; 0x7073 is "ps").
const MIGRATION_LOCK: i64 = 0x7073_0001;
/// Held by a submission while it counts and inserts, so the queue and tenant limits hold
/// across instances.
const ADMISSION_LOCK: i64 = 0x7073_0002;

const NOTIFY: &str = "SELECT pg_notify('photostereo_jobs', '')";

/// [`JobRepo`](super::JobRepo) in a PostgreSQL database.
pub struct PostgresRepo {
    /// Runs the pool's connections; shut down in the background on drop (dropping a
    /// runtime may not block inside another one).
    runtime: Option<tokio::runtime::Runtime>,
    pool: Pool,
    /// For the listener's connection of its own.
    config: tokio_postgres::Config,
}

impl Drop for PostgresRepo {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl PostgresRepo {
    /// Connect to `url` (`postgres://user:password@host:port/database`) and apply the
    /// migrations this program knows.
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
            .wait_timeout(Some(Duration::from_secs(10)))
            .create_timeout(Some(Duration::from_secs(10)))
            .build()
            .map_err(|e| RepoError::new(format!("PostgreSQL connection pool: {e}")))?;
        let repo = Self {
            runtime: Some(runtime),
            pool,
            config,
        };
        repo.run(|mut c| async move {
            let tx = c.transaction().await?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])
                .await?;
            tx.batch_execute(
                "CREATE TABLE IF NOT EXISTS photostereo_schema (version BIGINT NOT NULL);
                 INSERT INTO photostereo_schema SELECT 0
                 WHERE NOT EXISTS (SELECT 1 FROM photostereo_schema);",
            )
            .await?;
            let version: i64 = tx
                .query_one("SELECT version FROM photostereo_schema", &[])
                .await?
                .get(0);
            if version as usize > MIGRATIONS.len() {
                return Err(RepoError::new(format!(
                    "database schema version {version} is newer than this program ({}); \
                     upgrade photostereo",
                    MIGRATIONS.len()
                )));
            }
            for (i, sql) in MIGRATIONS.iter().enumerate().skip(version as usize) {
                tx.batch_execute(sql).await?;
                tx.execute(
                    "UPDATE photostereo_schema SET version = $1",
                    &[&((i + 1) as i64)],
                )
                .await?;
            }
            Ok(tx.commit().await?)
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
            let client = pool.get().await?;
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
    Ok(readable(
        rows.iter().map(|r| read_record(r).decode()),
        "job",
    ))
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

/// The ids in the first column of `rows`.
fn ids(rows: &[Row]) -> Vec<Uuid> {
    uuids(rows.iter().map(|r| r.get::<_, &str>(0)))
}

const REMEMBERED: &str = "SELECT body_hash, status, body, location, created_at FROM idempotency \
     WHERE tenant = $1 AND scope = $2 AND key = $3 AND created_at >= $4";

impl Jobs for PostgresRepo {
    fn insert(
        &self,
        job: &JobRecord,
        max_active: usize,
        max_queued: usize,
    ) -> RepoResult<Admission> {
        let row = RawRecord::encode(job)?;
        self.run(move |mut c| async move {
            // The counts and the insert are one step: concurrent submissions, on any
            // instance, wait for each other's transaction.
            let tx = c.transaction().await?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&ADMISSION_LOCK])
                .await?;
            let counts = tx
                .query_one(
                    "SELECT COUNT(*) FILTER (WHERE tenant = $1 AND status IN ('queued', 'running')), \
                     COUNT(*) FILTER (WHERE status = 'queued') FROM jobs",
                    &[&row.tenant],
                )
                .await?;
            let (active, queued): (i64, i64) = (counts.get(0), counts.get(1));
            if active >= max_active as i64 {
                return Ok(Admission::TenantFull);
            }
            if queued >= max_queued as i64 {
                return Ok(Admission::QueueFull);
            }
            tx.execute(
                &format!(
                    "INSERT INTO jobs ({COLUMNS}) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, \
                     $10, $11, $12, $13, $14, $15, $16)"
                ),
                &[
                    &row.id,
                    &row.status,
                    &row.stage,
                    &row.progress,
                    &row.created_at,
                    &row.started_at,
                    &row.finished_at,
                    &row.heartbeat_at,
                    &row.attempts,
                    &row.image_count,
                    &row.options,
                    &row.error,
                    &row.result,
                    &row.artifacts,
                    &row.tenant,
                    &row.callback,
                ],
            )
            .await?;
            tx.execute(NOTIFY, &[]).await?;
            tx.commit().await?;
            Ok(Admission::Accepted)
        })
    }

    fn queued(&self) -> RepoResult<u64> {
        self.run(|c| async move {
            let n: i64 = c
                .query_one("SELECT COUNT(*) FROM jobs WHERE status = 'queued'", &[])
                .await?
                .get(0);
            Ok(n as u64)
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
                .await?
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
                .await?
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
                .await?;
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
                .await?;
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
                .await?;
            records(rows)
        })
    }

    fn cancel(&self, id: Uuid, now: i64) -> RepoResult<Option<JobStatus>> {
        self.run(move |mut c| async move {
            let tx = c.transaction().await?;
            let id = id.to_string();
            let row = tx
                .query_opt("SELECT status FROM jobs WHERE id = $1 FOR UPDATE", &[&id])
                .await?;
            let Some(prev) = row.and_then(|r| JobStatus::parse(r.get::<_, &str>(0))) else {
                return Ok(None);
            };
            if prev.is_terminal() {
                return Ok(None);
            }
            tx.execute(
                "UPDATE jobs SET status = 'cancelled', finished_at = $2, lease_until = NULL \
                 WHERE id = $1",
                &[&id, &now],
            )
            .await?;
            tx.commit().await?;
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
                .await?;
            Ok(n == 1)
        })
    }

    fn delete(&self, id: Uuid) -> RepoResult<bool> {
        self.run(move |c| async move {
            let n = c
                .execute("DELETE FROM jobs WHERE id = $1", &[&id.to_string()])
                .await?;
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
                .await?;
            Ok(ids(&rows))
        })
    }

    fn counts(&self) -> RepoResult<Vec<(JobStatus, u64)>> {
        let rows = self.run(|c| async move {
            let rows = c
                .query("SELECT status, COUNT(*) FROM jobs GROUP BY status", &[])
                .await?;
            Ok(rows
                .iter()
                .map(|r| (r.get::<_, String>(0), r.get::<_, i64>(1)))
                .collect::<Vec<_>>())
        })?;
        Ok(status_counts(&rows))
    }

    fn counts_by_tenant(&self) -> RepoResult<Vec<(String, JobStatus, u64)>> {
        self.run(|c| async move {
            let rows = c
                .query(
                    "SELECT tenant, status, COUNT(*) FROM jobs GROUP BY tenant, status \
                     ORDER BY tenant, status",
                    &[],
                )
                .await?;
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
            let rows = c.query("SELECT id FROM jobs", &[]).await?;
            Ok(ids(&rows))
        })
    }

    fn set_callback(&self, id: Uuid, callback: &Callback) -> RepoResult<()> {
        let text = serde_json::to_string(callback)?;
        self.run(move |c| async move {
            c.execute(
                "UPDATE jobs SET callback = $2 WHERE id = $1",
                &[&id.to_string(), &text],
            )
            .await?;
            Ok(())
        })
    }

    fn ping(&self) -> RepoResult<()> {
        self.run(|c| async move {
            c.query_one("SELECT COUNT(*) FROM jobs WHERE false", &[])
                .await?;
            Ok(())
        })
    }
}

impl Calibrations for PostgresRepo {
    fn insert_calibration(&self, cal: &CalibrationRecord) -> RepoResult<()> {
        let (id, tenant, created_at, detail, table, artifacts) = encode_calibration(cal)?;
        self.run(move |c| async move {
            c.execute(
                &format!(
                    "INSERT INTO calibrations ({CALIBRATION_COLUMNS}) \
                     VALUES ($1, $2, $3, $4, $5, $6)"
                ),
                &[&id, &tenant, &created_at, &detail, &table, &artifacts],
            )
            .await?;
            Ok(())
        })
    }

    fn get_calibration(&self, id: Uuid) -> RepoResult<Option<CalibrationRecord>> {
        self.run(move |c| async move {
            c.query_opt(
                &format!("SELECT {CALIBRATION_COLUMNS} FROM calibrations WHERE id = $1"),
                &[&id.to_string()],
            )
            .await?
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
                .await?;
            Ok(readable(
                rows.iter().map(|r| decode_calibration(read_calibration(r))),
                "calibration",
            ))
        })
    }

    fn delete_calibration(&self, id: Uuid) -> RepoResult<bool> {
        self.run(move |c| async move {
            let n = c
                .execute("DELETE FROM calibrations WHERE id = $1", &[&id.to_string()])
                .await?;
            Ok(n == 1)
        })
    }

    fn calibration_ids(&self) -> RepoResult<Vec<Uuid>> {
        self.run(|c| async move {
            let rows = c.query("SELECT id FROM calibrations", &[]).await?;
            Ok(ids(&rows))
        })
    }
}

impl Idempotency for PostgresRepo {
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
                .await?;
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
            let tx = c.transaction().await?;
            tx.execute(
                "SELECT pg_advisory_xact_lock(hashtextextended($1 || '/' || $2 || '/' || $3, 0))",
                &[&tenant, &scope, &key],
            )
            .await?;
            if let Some(row) = tx
                .query_opt(REMEMBERED, &[&tenant, &scope, &key, &since])
                .await?
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
            .await?;
            tx.commit().await?;
            Ok(None)
        })
    }

    fn forget_idempotent(&self, before: i64) -> RepoResult<usize> {
        self.run(move |c| async move {
            let n = c
                .execute("DELETE FROM idempotency WHERE created_at < $1", &[&before])
                .await?;
            Ok(n as usize)
        })
    }
}
