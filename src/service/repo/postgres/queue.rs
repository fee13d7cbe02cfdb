//! The PostgreSQL repo's queue: claims with `FOR UPDATE SKIP LOCKED`, leases in the
//! database's clock, the tenants' turns from a sequence, and `LISTEN`/`NOTIFY` so that
//! every instance's workers hear of a new or requeued job.

use std::sync::Arc;
use std::time::Duration;

use tokio_postgres::NoTls;
use uuid::Uuid;

use super::{NOTIFY, PostgresRepo};
use crate::service::repo::error::RepoResult;
use crate::service::repo::model::{Finish, Lease, Problem, Reaped};
use crate::service::repo::rows::job_id;
use crate::service::repo::traits::Queue;

/// The channel new and requeued jobs are announced on.
const CHANNEL: &str = "photostereo_jobs";

impl Queue for PostgresRepo {
    fn release_running(&self) -> RepoResult<usize> {
        self.run(|c| async move {
            let n = c
                .execute(
                    "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                     owner = NULL, lease_until = NULL WHERE status = 'running'",
                    &[],
                )
                .await?;
            Ok(n as usize)
        })
    }

    fn claim(&self, owner: &str, lease: Duration, now: i64) -> RepoResult<Option<Lease>> {
        let owner = owner.to_string();
        let secs = lease.as_secs_f64();
        self.run(move |mut c| async move {
            let tx = c.transaction().await?;
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
                .await?;
            let Some(row) = row else {
                return Ok(None);
            };
            let (id, tenant, token): (String, String, i64) = (row.get(0), row.get(1), row.get(2));
            tx.execute(
                "INSERT INTO turns (tenant, served) VALUES ($1, nextval('turn_seq')) \
                 ON CONFLICT (tenant) DO UPDATE SET served = EXCLUDED.served",
                &[&tenant],
            )
            .await?;
            tx.commit().await?;
            Ok(Some(Lease {
                id: job_id(&id)?,
                token,
            }))
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
                .await?;
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
                .await?;
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
            let n = c.execute(sql, &params).await?;
            Ok(n == 1)
        })
    }

    fn requeue(&self, lease: Lease) -> RepoResult<bool> {
        self.run(move |mut c| async move {
            let tx = c.transaction().await?;
            let n = tx
                .execute(
                    "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                     owner = NULL, lease_until = NULL \
                     WHERE id = $1 AND token = $2 AND status = 'running'",
                    &[&lease.id.to_string(), &lease.token],
                )
                .await?;
            tx.execute(NOTIFY, &[]).await?;
            tx.commit().await?;
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
                .await?;
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
            let tx = c.transaction().await?;
            let mut reaped = Reaped::default();
            for (id, token, error) in plan {
                // Still expired and still that attempt: a heartbeat or a cancel in between wins.
                let guard = "id = $1 AND token = $2 AND status = 'running' AND lease_until < now()";
                let n = match &error {
                    Some(error) => {
                        tx.execute(
                            &format!(
                                "UPDATE jobs SET status = 'failed', finished_at = $3, \
                                 error = $4, lease_until = NULL WHERE {guard}"
                            ),
                            &[&id.to_string(), &token, &now, error],
                        )
                        .await?
                    }
                    None => {
                        tx.execute(
                            &format!(
                                "UPDATE jobs SET status = 'queued', stage = NULL, progress = 0, \
                                 owner = NULL, lease_until = NULL WHERE {guard}"
                            ),
                            &[&id.to_string(), &token],
                        )
                        .await?
                    }
                };
                match (n, &error) {
                    (0, _) => {}
                    (_, Some(_)) => reaped.failed.push(id),
                    (_, None) => reaped.requeued.push(id),
                }
            }
            if !reaped.requeued.is_empty() {
                tx.execute(NOTIFY, &[]).await?;
            }
            tx.commit().await?;
            Ok(reaped)
        })
    }

    fn subscribe(&self, wake: Arc<dyn Fn() + Send + Sync>) {
        let config = self.config.clone();
        let runtime = self.runtime.as_ref().expect("present until drop");
        runtime.spawn(listen(config, wake));
    }
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
