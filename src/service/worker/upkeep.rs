//! The upkeep of the queue and the stored files: recovery at start, and the background
//! loop (every third of the job lease the heartbeat, the reaper and the prefetch tidy;
//! every sweep interval the retention sweep).

use std::collections::HashSet;
use std::sync::Arc;

use tokio::sync::watch;
use uuid::Uuid;

use crate::service::config::IDEMPOTENCY_WINDOW;
use crate::service::repo::JobStatus;
use crate::service::store;
use crate::service::util::now_ms;

use super::failure::Failure;
use super::runner::Runner;
use super::webhooks;

/// A job whose lease runs out on this attempt fails instead of running again: it may be
/// what kills its workers.
const MAX_ATTEMPTS: u32 = 3;

/// The background loop: the retention sweep, and every third of the lease the heartbeat,
/// the reaper and the prefetch tidy; until `stop` changes.
pub(super) fn spawn(runner: Arc<Runner>, mut stop: watch::Receiver<bool>) {
    tokio::spawn(async move {
        let mut sweep = tokio::time::interval(runner.config.sweep_interval);
        // Three beats to a lease: one late beat does not lose it.
        let mut beat = tokio::time::interval(runner.config.job_lease / 3);
        loop {
            tokio::select! {
                _ = sweep.tick() => {
                    let i = runner.clone();
                    let _ = tokio::task::spawn_blocking(move || sweep_expired(&i)).await;
                }
                _ = beat.tick() => {
                    let i = runner.clone();
                    let _ = tokio::task::spawn_blocking(move || {
                        heartbeat(&i);
                        reap(&i);
                        forget_prefetched(&i);
                    })
                    .await;
                }
                _ = stop.changed() => break,
            }
        }
    });
}

/// Startup: drop leftovers, put unfinished jobs back in the queue (oldest first).
pub(super) fn recover(runner: &Runner) -> anyhow::Result<usize> {
    let known: HashSet<Uuid> = runner.repo.ids()?.into_iter().collect();
    for id in listed(runner.store.job_ids(), "jobs") {
        let tidy = if known.contains(&id) {
            runner.store.remove_partials(id).and_then(|()| {
                // A stop between recording a job's end and removing its inputs.
                match runner.repo.get(id) {
                    Ok(Some(rec)) if rec.status.is_terminal() => runner.store.remove_inputs(id),
                    _ => Ok(()),
                }
            })
        } else {
            runner.store.remove_job(id) // an upload that never became a job
        };
        if let Err(e) = tidy {
            tracing::warn!(job = %id, error = %e, "cannot tidy job files");
        }
    }
    // Calibration files are committed before their record: files without one are a
    // calibration that was never answered.
    let calibrations: HashSet<Uuid> = runner.repo.calibration_ids()?.into_iter().collect();
    for id in listed(runner.store.calibration_ids(), "calibrations") {
        if !calibrations.contains(&id)
            && let Err(e) = runner.store.remove_calibration(id)
        {
            tracing::warn!(calibration = %id, error = %e, "cannot tidy calibration files");
        }
    }
    let queued = if runner.config.database_url.is_some() {
        // Other instances may hold running jobs: expired leases are the reaper's.
        0
    } else {
        // A single node: no one else holds a job, so every running one was cut off.
        runner.repo.release_running()?;
        let mut queued = 0;
        for rec in runner.repo.unfinished()? {
            // A store that does not answer now may later: the job stays queued and waits.
            if let Ok(false) = runner.store.has_inputs(rec.id) {
                let problem = runner.problem(
                    Failure::Failed(
                        "the job's input files are gone (the data directory changed while the service was stopped)".into(),
                    ),
                    &format!("/v1/jobs/{}", rec.id),
                );
                runner.repo.fail_queued(rec.id, &problem, now_ms())?;
                continue;
            }
            queued += 1;
        }
        queued
    };
    sweep_expired(runner);
    Ok(queued)
}

/// Extend the leases of the jobs running here; stop those no longer held (cancelled on
/// another instance, or reaped).
fn heartbeat(runner: &Runner) {
    let leases = runner.pool.leases();
    if leases.is_empty() {
        return;
    }
    let lost = match runner
        .repo
        .heartbeat(&leases, runner.config.job_lease, now_ms())
    {
        Ok(lost) => lost,
        Err(e) => {
            tracing::warn!(error = %e, "cannot extend the running jobs' leases");
            return;
        }
    };
    for lease in lost {
        let cancelled = matches!(
            runner.repo.get(lease.id),
            Ok(Some(rec)) if rec.status == JobStatus::Cancelled
        );
        if cancelled {
            runner.pool.cancel_running(lease.id);
        } else {
            runner.pool.lose(lease.id);
        }
    }
}

/// Drop the images decoded ahead for jobs another instance claimed (or that ended): only
/// the instance that received an upload has them, and any instance may claim its job.
fn forget_prefetched(runner: &Runner) {
    for id in runner.prefetch.parked() {
        if runner.pool.is_held(id) {
            continue;
        }
        match runner.repo.get(id) {
            Ok(Some(rec)) if rec.status == JobStatus::Queued => {}
            Ok(_) => runner.prefetch.discard(id),
            Err(e) => tracing::debug!(job = %id, error = %e, "cannot read the job"),
        }
    }
}

/// Put jobs whose lease ran out (their worker died, here or on another instance) back in
/// the queue, or fail them after their last attempt.
fn reap(runner: &Runner) {
    let failure = |id: Uuid| {
        runner.problem(
            Failure::Failed(format!(
                "the job's worker stopped answering on each of its {MAX_ATTEMPTS} attempts; it is not run again"
            )),
            &format!("/v1/jobs/{id}"),
        )
    };
    match runner.repo.reap(MAX_ATTEMPTS, &failure, now_ms()) {
        Ok(reaped) => {
            if !reaped.requeued.is_empty() {
                tracing::warn!(jobs = ?reaped.requeued, "leases ran out; the jobs run again");
                runner.pool.ring();
            }
            for id in reaped.failed {
                tracing::warn!(job = %id, "lease ran out on the last attempt; the job failed");
                if let Err(e) = runner.store.remove_inputs(id) {
                    tracing::warn!(job = %id, error = %e, "cannot remove the job's inputs");
                }
                webhooks::job_ended(runner, id);
            }
        }
        Err(e) => tracing::warn!(error = %e, "cannot reap expired leases"),
    }
}

/// What a store listing found; nothing (and a warning) when the store does not answer,
/// so that a start never waits for it.
fn listed(ids: store::Result<Vec<Uuid>>, what: &str) -> Vec<Uuid> {
    ids.unwrap_or_else(|e| {
        tracing::warn!(error = %e, "cannot list the stored {what}; leftovers stay");
        Vec::new()
    })
}

/// Delete finished jobs past the retention period: the record first (the job is gone from
/// the API at once), then the files.
fn sweep_expired(runner: &Runner) {
    let retention = i64::try_from(runner.config.retention.as_millis()).unwrap_or(i64::MAX);
    let cutoff = now_ms().saturating_sub(retention);
    let ids = match runner.repo.expired(cutoff, 1000) {
        Ok(ids) => ids,
        Err(e) => {
            tracing::warn!(error = %e, "cannot list expired jobs");
            return;
        }
    };
    let stale = now_ms() - IDEMPOTENCY_WINDOW.as_millis() as i64;
    if let Err(e) = runner.repo.forget_idempotent(stale) {
        tracing::warn!(error = %e, "cannot forget old idempotency keys");
    }
    for id in ids {
        match runner.repo.delete(id) {
            Ok(_) => {
                if let Err(e) = runner.store.remove_job(id) {
                    tracing::warn!(job = %id, error = %e, "cannot remove expired job files");
                } else {
                    tracing::info!(job = %id, "expired job removed");
                }
            }
            Err(e) => tracing::warn!(job = %id, error = %e, "cannot delete expired job"),
        }
    }
}
