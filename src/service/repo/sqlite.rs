//! [`JobRepo`](super::JobRepo) in one SQLite file (WAL, every commit synced): the
//! single-machine default. The connection is one, behind a mutex; a claim and an
//! admission are `IMMEDIATE` transactions, so the counts they read are the ones they
//! write against. Schema versions are the files in `sqlite/migrations/`, applied in
//! order; `PRAGMA user_version` is the number applied.

mod queue;

use std::path::Path;
use std::sync::Mutex;
use std::time::Duration;

use rusqlite::{Connection, OptionalExtension, Row, TransactionBehavior, params};
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

/// Schema versions, in order (version `i + 1` is `MIGRATIONS[i]`).
const MIGRATIONS: &[&str] = &[
    include_str!("sqlite/migrations/001_jobs.sql"),
    include_str!("sqlite/migrations/002_tenants.sql"),
    include_str!("sqlite/migrations/003_idempotency.sql"),
    include_str!("sqlite/migrations/004_callbacks.sql"),
    include_str!("sqlite/migrations/005_calibrations.sql"),
    include_str!("sqlite/migrations/006_leases.sql"),
];

/// [`JobRepo`](super::JobRepo) in a SQLite database file.
pub struct SqliteRepo {
    conn: Mutex<Connection>,
}

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

impl Jobs for SqliteRepo {
    fn insert(
        &self,
        job: &JobRecord,
        max_active: usize,
        max_queued: usize,
    ) -> RepoResult<Admission> {
        let row = RawRecord::encode(job)?;
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
                    row.id,
                    row.status,
                    row.stage,
                    row.progress,
                    row.created_at,
                    row.started_at,
                    row.finished_at,
                    row.heartbeat_at,
                    row.attempts,
                    row.image_count,
                    row.options,
                    row.error,
                    row.result,
                    row.artifacts,
                    row.tenant,
                    row.callback,
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
            Ok(uuids(ids.iter().map(String::as_str)))
        })
    }

    fn counts(&self) -> RepoResult<Vec<(JobStatus, u64)>> {
        self.with(|c| {
            let mut stmt = c.prepare_cached("SELECT status, COUNT(*) FROM jobs GROUP BY status")?;
            let rows = stmt
                .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))?
                .collect::<Result<Vec<_>, _>>()?;
            Ok(status_counts(&rows))
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
            Ok(uuids(ids.iter().map(String::as_str)))
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
}

impl Calibrations for SqliteRepo {
    fn insert_calibration(&self, cal: &CalibrationRecord) -> RepoResult<()> {
        let (id, tenant, created_at, detail, table, artifacts) = encode_calibration(cal)?;
        self.with(|c| {
            c.execute(
                &format!(
                    "INSERT INTO calibrations ({CALIBRATION_COLUMNS}) VALUES (?1, ?2, ?3, ?4, ?5, ?6)"
                ),
                params![id, tenant, created_at, detail, table, artifacts],
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
            Ok(uuids(ids.iter().map(String::as_str)))
        })
    }
}

impl Idempotency for SqliteRepo {
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
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::service::repo::JobRepo;
    use crate::service::repo::contract::{self, Backend, Clock};

    /// A file of its own per check, in a directory removed at the end.
    struct Files(tempfile::TempDir);

    impl Backend for Files {
        type Db = std::path::PathBuf;

        fn create(&self, check: &str) -> Self::Db {
            self.0.path().join(format!("{check}.sqlite"))
        }

        fn open(&self, db: &Self::Db) -> Arc<dyn JobRepo> {
            Arc::new(SqliteRepo::open(db).unwrap())
        }

        fn clock(&self) -> Clock {
            Clock::given(1000)
        }
    }

    #[test]
    fn keeps_the_repo_contract() {
        contract::run(&Files(tempfile::tempdir().unwrap()));
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
        // The open API's tenant (`tenants::OPEN_TENANT`, which checks that it is this one).
        assert_eq!(rec.tenant, "default");
        assert_eq!(repo.list(Some("default"), 5, None).unwrap().len(), 1);
    }
}
