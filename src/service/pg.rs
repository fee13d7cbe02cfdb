//! [`JobRepo`] in PostgreSQL (`--database-url postgres://…`): the same records, states
//! and conditional updates as [`SqliteRepo`](super::repo::SqliteRepo), in a database
//! operators already run and back up.
//!
//! The repo keeps its connections (a `deadpool-postgres` pool) on a small runtime of its
//! own, so its blocking methods work from any thread, the async runtime's included.
//! Migrations run at start in one transaction under an advisory lock, so instances that
//! start together do not race. Any number of instances share the database: workers claim
//! jobs with `FOR UPDATE SKIP LOCKED`, leases run out in the database's clock (`now()`),
//! and a new or requeued job is announced with `NOTIFY` to every instance's listener.

use std::future::Future;
use std::sync::{Arc, mpsc};
use std::time::Duration;

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod};
use tokio_postgres::{NoTls, Row};
use uuid::Uuid;

use super::problem::Problem;
use super::repo::{
    Admission, CalibrationRecord, Callback, Finish, JobRecord, JobRepo, JobStatus, Lease,
    RawCalibration, RawRecord, Reaped, Remembered, RepoError, RepoResult, decode_calibration,
    readable,
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
    // 2: leases (the claiming worker, its fencing token, when the lease runs out in the
    // database's clock) and the tenants' turns.
    "ALTER TABLE jobs ADD COLUMN owner TEXT;
    ALTER TABLE jobs ADD COLUMN token BIGINT NOT NULL DEFAULT 0;
    ALTER TABLE jobs ADD COLUMN lease_until TIMESTAMPTZ;
    CREATE INDEX jobs_by_lease ON jobs (lease_until) WHERE status = 'running';
    CREATE TABLE turns (tenant TEXT PRIMARY KEY NOT NULL, served BIGINT NOT NULL);
    CREATE SEQUENCE turn_seq;",
];

/// Advisory lock keys (any two fixed numbers; 0x7073 is "ps").
const MIGRATION_LOCK: i64 = 0x7073_0001;
/// Held by a submission while it counts and inserts, so the queue and tenant limits hold
/// across instances.
const ADMISSION_LOCK: i64 = 0x7073_0002;

/// The channel new and requeued jobs are announced on.
const CHANNEL: &str = "photostereo_jobs";
const NOTIFY: &str = "SELECT pg_notify('photostereo_jobs', '')";

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
    /// For the listener's connection of its own.
    config: tokio_postgres::Config,
}

impl Drop for PgRepo {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl PgRepo {
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

/// Call `wake` on every announcement of a new or requeued job, and once each time the
/// listener (re)connects, since jobs may have come while it was not listening. Runs for
/// the repo's life, reconnecting after a lost connection.
async fn listen(config: tokio_postgres::Config, wake: Arc<dyn Fn() + Send + Sync>) {
    use futures_util::StreamExt;
    loop {
        match config.connect(NoTls).await {
            Ok((client, mut connection)) => {
                let on_message = wake.clone();
                let driver = tokio::spawn(async move {
                    let mut messages =
                        futures_util::stream::poll_fn(move |cx| connection.poll_message(cx));
                    while let Some(Ok(message)) = messages.next().await {
                        if matches!(message, tokio_postgres::AsyncMessage::Notification(_)) {
                            on_message();
                        }
                    }
                });
                match client.batch_execute(&format!("LISTEN {CHANNEL}")).await {
                    Ok(()) => {
                        wake();
                        let _ = driver.await;
                        tracing::warn!(
                            "the job listener's database connection ended; reconnecting"
                        );
                    }
                    Err(e) => {
                        driver.abort();
                        tracing::warn!(error = %e, "cannot listen for new jobs");
                    }
                }
            }
            Err(e) => tracing::debug!(error = %e, "the job listener cannot connect yet"),
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
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

fn uuids(rows: Vec<Row>) -> Vec<Uuid> {
    rows.iter()
        .filter_map(|r| Uuid::parse_str(r.get::<_, &str>(0)).ok())
        .collect()
}

const REMEMBERED: &str = "SELECT body_hash, status, body, location, created_at FROM idempotency \
     WHERE tenant = $1 AND scope = $2 AND key = $3 AND created_at >= $4";

impl JobRepo for PgRepo {
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
        let job = job.clone();
        self.run(move |mut c| async move {
            // The counts and the insert are one step: concurrent submissions, on any
            // instance, wait for each other's transaction.
            let tx = c.transaction().await.map_err(db_error)?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&ADMISSION_LOCK])
                .await
                .map_err(db_error)?;
            let counts = tx
                .query_one(
                    "SELECT COUNT(*) FILTER (WHERE tenant = $1 AND status IN ('queued', 'running')), \
                     COUNT(*) FILTER (WHERE status = 'queued') FROM jobs",
                    &[&job.tenant],
                )
                .await
                .map_err(db_error)?;
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
                    &callback,
                ],
            )
            .await
            .map_err(db_error)?;
            tx.execute(NOTIFY, &[]).await.map_err(db_error)?;
            tx.commit().await.map_err(db_error)?;
            Ok(Admission::Accepted)
        })
    }

    fn queued(&self) -> RepoResult<u64> {
        self.run(|c| async move {
            let n: i64 = c
                .query_one("SELECT COUNT(*) FROM jobs WHERE status = 'queued'", &[])
                .await
                .map_err(db_error)?
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

    fn release_running(&self) -> RepoResult<usize> {
        self.run(|c| async move {
            let n = c
                .execute(
                    "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                     owner = NULL, lease_until = NULL WHERE status = 'running'",
                    &[],
                )
                .await
                .map_err(db_error)?;
            Ok(n as usize)
        })
    }

    fn claim(&self, owner: &str, lease: Duration, now: i64) -> RepoResult<Option<Lease>> {
        let owner = owner.to_string();
        let secs = lease.as_secs_f64();
        self.run(move |mut c| async move {
            let tx = c.transaction().await.map_err(db_error)?;
            // Locked rows are another instance's claim in progress: skipped, not waited for.
            let row = tx
                .query_opt(
                    "WITH next AS ( \
                       SELECT j.id FROM jobs j LEFT JOIN turns t ON t.tenant = j.tenant \
                       WHERE j.status = 'queued' \
                       ORDER BY COALESCE(t.served, 0), j.created_at, j.id \
                       LIMIT 1 FOR UPDATE OF j SKIP LOCKED) \
                     UPDATE jobs SET status = 'running', stage = NULL, progress = 0, \
                       started_at = $1, heartbeat_at = $1, attempts = attempts + 1, \
                       token = token + 1, owner = $2, \
                       lease_until = now() + make_interval(secs => $3) \
                     FROM next WHERE jobs.id = next.id \
                     RETURNING jobs.id, jobs.tenant, jobs.token",
                    &[&now, &owner, &secs],
                )
                .await
                .map_err(db_error)?;
            let Some(row) = row else {
                return Ok(None);
            };
            let (id, tenant, token): (String, String, i64) = (row.get(0), row.get(1), row.get(2));
            tx.execute(
                "INSERT INTO turns (tenant, served) VALUES ($1, nextval('turn_seq')) \
                 ON CONFLICT (tenant) DO UPDATE SET served = EXCLUDED.served",
                &[&tenant],
            )
            .await
            .map_err(db_error)?;
            tx.commit().await.map_err(db_error)?;
            let id = Uuid::parse_str(&id)
                .map_err(|e| RepoError::new(format!("stored job id {id:?}: {e}")))?;
            Ok(Some(Lease { id, token }))
        })
    }

    fn progress(&self, lease: Lease, stage: &str, progress: f64, now: i64) -> RepoResult<bool> {
        let stage = stage.to_string();
        self.run(move |c| async move {
            let n = c
                .execute(
                    "UPDATE jobs SET stage = $3, progress = $4, heartbeat_at = $5 \
                     WHERE id = $1 AND token = $2 AND status = 'running'",
                    &[&lease.id.to_string(), &lease.token, &stage, &progress, &now],
                )
                .await
                .map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn heartbeat(&self, leases: &[Lease], lease: Duration, now: i64) -> RepoResult<Vec<Lease>> {
        let leases = leases.to_vec();
        let ids: Vec<String> = leases.iter().map(|l| l.id.to_string()).collect();
        let tokens: Vec<i64> = leases.iter().map(|l| l.token).collect();
        let secs = lease.as_secs_f64();
        self.run(move |c| async move {
            let rows = c
                .query(
                    "UPDATE jobs SET heartbeat_at = $3, \
                     lease_until = now() + make_interval(secs => $4) \
                     WHERE status = 'running' \
                     AND (id, token) IN (SELECT * FROM unnest($1::TEXT[], $2::BIGINT[])) \
                     RETURNING id, token",
                    &[&ids, &tokens, &now, &secs],
                )
                .await
                .map_err(db_error)?;
            let held: Vec<(String, i64)> = rows.iter().map(|r| (r.get(0), r.get(1))).collect();
            Ok(leases
                .into_iter()
                .filter(|l| !held.contains(&(l.id.to_string(), l.token)))
                .collect())
        })
    }

    fn finish(&self, lease: Lease, finish: &Finish, now: i64) -> RepoResult<bool> {
        let (sql, fields) = match finish {
            Finish::Succeeded { result, artifacts } => (
                "UPDATE jobs SET status = 'succeeded', progress = 1, finished_at = $3, \
                 heartbeat_at = $3, result = $4, artifacts = $5, error = NULL, \
                 lease_until = NULL WHERE id = $1 AND token = $2 AND status = 'running'",
                vec![
                    serde_json::to_string(result)?,
                    serde_json::to_string(artifacts)?,
                ],
            ),
            Finish::Failed(problem) => (
                "UPDATE jobs SET status = 'failed', finished_at = $3, heartbeat_at = $3, \
                 error = $4, lease_until = NULL \
                 WHERE id = $1 AND token = $2 AND status = 'running'",
                vec![serde_json::to_string(problem)?],
            ),
        };
        self.run(move |c| async move {
            let id = lease.id.to_string();
            let mut params: Vec<&(dyn tokio_postgres::types::ToSql + Sync)> =
                vec![&id, &lease.token, &now];
            params.extend(
                fields
                    .iter()
                    .map(|f| f as &(dyn tokio_postgres::types::ToSql + Sync)),
            );
            let n = c.execute(sql, &params).await.map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn requeue(&self, lease: Lease) -> RepoResult<bool> {
        self.run(move |mut c| async move {
            let tx = c.transaction().await.map_err(db_error)?;
            let n = tx
                .execute(
                    "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                     owner = NULL, lease_until = NULL \
                     WHERE id = $1 AND token = $2 AND status = 'running'",
                    &[&lease.id.to_string(), &lease.token],
                )
                .await
                .map_err(db_error)?;
            tx.execute(NOTIFY, &[]).await.map_err(db_error)?;
            tx.commit().await.map_err(db_error)?;
            Ok(n == 1)
        })
    }

    fn reap(
        &self,
        max_attempts: u32,
        failure: &dyn Fn(Uuid) -> Problem,
        now: i64,
    ) -> RepoResult<Reaped> {
        // Which leases have run out is the database's to say (its clock); the failures are
        // written in a second step, conditional on the token seen here.
        let expired: Vec<(String, i64, i64)> = self.run(|c| async move {
            let rows = c
                .query(
                    "SELECT id, token, attempts FROM jobs \
                     WHERE status = 'running' AND lease_until < now()",
                    &[],
                )
                .await
                .map_err(db_error)?;
            Ok(rows
                .iter()
                .map(|r| (r.get(0), r.get(1), r.get(2)))
                .collect())
        })?;
        if expired.is_empty() {
            return Ok(Reaped::default());
        }
        let mut plan = Vec::new();
        for (id, token, attempts) in expired {
            let Ok(uuid) = Uuid::parse_str(&id) else {
                continue;
            };
            let error = (attempts >= i64::from(max_attempts))
                .then(|| serde_json::to_string(&failure(uuid)))
                .transpose()?;
            plan.push((uuid, token, error));
        }
        self.run(move |mut c| async move {
            let tx = c.transaction().await.map_err(db_error)?;
            let mut reaped = Reaped::default();
            for (id, token, error) in plan {
                // Still expired and still that attempt: a heartbeat or a cancel in between wins.
                let guard = "id = $1 AND token = $2 AND status = 'running' AND lease_until < now()";
                let n = match &error {
                    Some(error) => tx
                        .execute(
                            &format!(
                                "UPDATE jobs SET status = 'failed', finished_at = $3, \
                                 error = $4, lease_until = NULL WHERE {guard}"
                            ),
                            &[&id.to_string(), &token, &now, error],
                        )
                        .await
                        .map_err(db_error)?,
                    None => tx
                        .execute(
                            &format!(
                                "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                                 owner = NULL, lease_until = NULL WHERE {guard}"
                            ),
                            &[&id.to_string(), &token],
                        )
                        .await
                        .map_err(db_error)?,
                };
                match (n, &error) {
                    (0, _) => {}
                    (_, Some(_)) => reaped.failed.push(id),
                    (_, None) => reaped.requeued.push(id),
                }
            }
            if !reaped.requeued.is_empty() {
                tx.execute(NOTIFY, &[]).await.map_err(db_error)?;
            }
            tx.commit().await.map_err(db_error)?;
            Ok(reaped)
        })
    }

    fn subscribe(&self, wake: Arc<dyn Fn() + Send + Sync>) {
        let config = self.config.clone();
        let runtime = self.runtime.as_ref().expect("present until drop");
        runtime.spawn(listen(config, wake));
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
                "UPDATE jobs SET status = 'cancelled', finished_at = $2, lease_until = NULL \
                 WHERE id = $1",
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
