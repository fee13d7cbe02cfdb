//! The SQLite repo's queue: claims in `IMMEDIATE` transactions, leases in the callers'
//! clock (`now`), the tenants' turns in the `turns` table.

use std::time::Duration;

use rusqlite::{OptionalExtension, TransactionBehavior, params};
use uuid::Uuid;

use super::SqliteRepo;
use crate::service::repo::error::RepoResult;
use crate::service::repo::model::{Finish, Lease, Problem, Reaped};
use crate::service::repo::rows::job_id;
use crate::service::repo::traits::Queue;

impl Queue for SqliteRepo {
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
            Ok(Some(Lease {
                id: job_id(&id)?,
                token,
            }))
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
}
