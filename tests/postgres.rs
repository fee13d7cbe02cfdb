//! `--database-url postgres://…` against a real PostgreSQL server (Debian's binaries, see
//! `common/postgres.rs`): the repo keeps the same records and state rules as SQLite,
//! claims are exclusive under concurrency, leases run out in the database's clock and
//! their late writes are refused, migrations are applied once however many instances
//! start together, and a service on it (with the S3 store, `common/weed.rs`) runs jobs
//! whose records survive a restart and an outage.

mod common;
#[path = "common/postgres.rs"]
mod postgres;
#[path = "common/weed.rs"]
mod weed;

use std::collections::HashSet;
use std::sync::Arc;
use std::time::Duration;

use common::*;
use photostereo::service::pg::PgRepo;
use photostereo::service::problem::Problem;
use photostereo::service::repo::{
    Admission, ArtifactInfo, CalibrationRecord, Finish, JobRecord, JobRepo, JobStatus, Lease,
    Remembered,
};
use postgres::Postgres;
use uuid::Uuid;
use weed::Weed;

const LEASE: Duration = Duration::from_secs(30);

fn claim(repo: &PgRepo, now: i64) -> Option<Lease> {
    repo.claim("test", LEASE, now).unwrap()
}

fn accepted(repo: &PgRepo, job: &JobRecord, max_active: usize) -> bool {
    repo.insert(job, max_active, 100).unwrap() == Admission::Accepted
}

fn job(tenant: &str, created_at: i64) -> JobRecord {
    JobRecord::new_queued(
        Uuid::new_v4(),
        tenant,
        created_at,
        4,
        serde_json::json!({"solver": "robust"}),
    )
}

/// Every state change is conditional on the state it leaves, as in SQLite.
#[test]
fn postgres_repo_keeps_records_and_state_rules() {
    let Some(pg) = Postgres::start("postgres_repo_keeps_records_and_state_rules") else {
        return;
    };
    let url = pg.database("rules");
    let repo = PgRepo::connect(&url).expect("connect and migrate");

    // Admission per tenant: at most `max_active` queued or running; at most
    // `max_queued` waiting in all.
    let a = job("acme", 1_000);
    assert!(accepted(&repo, &a, 2));
    assert!(accepted(&repo, &job("acme", 1_001), 2));
    assert_eq!(
        repo.insert(&job("acme", 1_002), 2, 100).unwrap(),
        Admission::TenantFull,
        "third active job refused"
    );
    assert_eq!(
        repo.insert(&job("other", 1_002), 2, 2).unwrap(),
        Admission::QueueFull
    );
    assert!(accepted(&repo, &job("other", 1_003), 2));
    assert_eq!(repo.active("acme").unwrap(), 2);
    assert_eq!(repo.queued().unwrap(), 3);

    // Lifecycle: claimed once (the oldest job), progress, heartbeat, finish once.
    assert_eq!(repo.get(a.id).unwrap().unwrap().status, JobStatus::Queued);
    let lease = claim(&repo, 2_000).unwrap();
    assert_eq!(lease.id, a.id);
    repo.cancel(
        claim(&repo, 2_001).expect("the other tenant's turn").id,
        2_001,
    )
    .unwrap();
    assert!(repo.progress(lease, "solve", 0.25, 2_100).unwrap());
    assert!(repo.heartbeat(&[lease], LEASE, 2_200).unwrap().is_empty());
    let rec = repo.get(a.id).unwrap().unwrap();
    assert_eq!(
        (rec.status, rec.stage.as_deref(), rec.progress, rec.attempts),
        (JobStatus::Running, Some("solve"), 0.25, 1)
    );
    assert_eq!(rec.heartbeat_at, Some(2_200));
    let artifacts = vec![ArtifactInfo {
        name: "normal.png".into(),
        bytes: 1234,
        etag: "\"e\"".into(),
        key: Some("attempt-1/normal.png".into()),
    }];
    let done = Finish::Succeeded {
        result: serde_json::json!({"width": 4}),
        artifacts: artifacts.clone(),
    };
    assert!(repo.finish(lease, &done, 3_000).unwrap());
    assert!(!repo.finish(lease, &done, 3_001).unwrap(), "finished once");
    let rec = repo.get(a.id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Succeeded);
    assert_eq!(rec.artifacts, artifacts);
    assert_eq!(rec.result, Some(serde_json::json!({"width": 4})));
    assert_eq!(repo.stored_bytes("acme").unwrap(), 1234);
    assert_eq!(repo.stored_bytes("other").unwrap(), 0);
    assert_eq!(
        repo.cancel(a.id, 3_100).unwrap(),
        None,
        "a finished job stays"
    );

    // Requeue and cancel race: whichever comes first wins.
    let b = job("other", 1_004);
    assert!(accepted(&repo, &b, 5));
    let acme_left = claim(&repo, 4_000).unwrap();
    assert_ne!(acme_left.id, b.id, "acme's turn");
    repo.cancel(acme_left.id, 4_000).unwrap();
    let lease = claim(&repo, 4_000).unwrap();
    assert_eq!(lease.id, b.id);
    assert!(repo.requeue(lease).unwrap());
    assert!(
        !repo.requeue(lease).unwrap(),
        "only a running job is requeued"
    );
    assert_eq!(repo.cancel(b.id, 4_100).unwrap(), Some(JobStatus::Queued));
    assert_eq!(claim(&repo, 4_200), None, "a cancelled job never starts");
    let failed = job("other", 1_005);
    assert!(accepted(&repo, &failed, 5));
    let problem = Problem {
        kind: "urn:photostereo:problem:invalid-input".into(),
        title: "Invalid input".into(),
        status: 422,
        detail: "three lights or more".into(),
        instance: None,
    };
    assert!(repo.fail_queued(failed.id, &problem, 4_300).unwrap());
    assert_eq!(repo.get(failed.id).unwrap().unwrap().error, Some(problem));

    // Counts, paging (newest first, from a cursor) and expiry.
    let counts = repo.counts().unwrap();
    let n = |s| counts.iter().find(|(k, _)| *k == s).unwrap().1;
    assert_eq!(
        (
            n(JobStatus::Queued),
            n(JobStatus::Succeeded),
            n(JobStatus::Cancelled)
        ),
        (0, 1, 3)
    );
    let page = repo.list(None, 3, None).unwrap();
    let times: Vec<i64> = page.iter().map(|j| j.created_at).collect();
    assert_eq!(times, vec![1_005, 1_004, 1_003]);
    let last = page.last().unwrap();
    let next = repo
        .list(None, 10, Some((last.created_at, last.id)))
        .unwrap();
    assert_eq!(next.len(), 2);
    assert!(next.iter().all(|j| j.created_at < 1_003));
    assert_eq!(repo.list(Some("acme"), 10, None).unwrap().len(), 2);
    assert_eq!(repo.unfinished().unwrap().len(), 0);
    let expired = repo.expired(5_000, 10).unwrap();
    assert_eq!(
        expired.len(),
        5,
        "succeeded, cancelled and failed jobs expire"
    );
    assert!(repo.delete(a.id).unwrap());
    assert!(repo.get(a.id).unwrap().is_none());
    assert_eq!(repo.ids().unwrap().len(), 4);

    // Idempotent answers: the first within the window is kept.
    let answer = |body: &str| Remembered {
        body_hash: "h".into(),
        status: 202,
        body: body.into(),
        location: Some("/v1/jobs/x".into()),
        created_at: 6_000,
    };
    assert_eq!(
        repo.remember("acme", "jobs", "k", &answer("one"), 0)
            .unwrap(),
        None
    );
    assert_eq!(
        repo.remember("acme", "jobs", "k", &answer("two"), 0)
            .unwrap(),
        Some(answer("one"))
    );
    assert_eq!(
        repo.idempotent("acme", "jobs", "k", 0).unwrap(),
        Some(answer("one"))
    );
    assert_eq!(repo.idempotent("other", "jobs", "k", 0).unwrap(), None);
    assert_eq!(repo.forget_idempotent(7_000).unwrap(), 1);

    // Calibrations.
    let cal = CalibrationRecord {
        id: Uuid::new_v4(),
        tenant: "acme".into(),
        created_at: 8_000,
        detail: serde_json::json!({"lights": 3}),
        table: "0 0 1\n".into(),
        artifacts: vec![],
    };
    repo.insert_calibration(&cal).unwrap();
    assert_eq!(repo.get_calibration(cal.id).unwrap(), Some(cal.clone()));
    assert_eq!(
        repo.list_calibrations(Some("acme"), 5, None).unwrap(),
        vec![cal.clone()]
    );
    assert!(
        repo.list_calibrations(Some("other"), 5, None)
            .unwrap()
            .is_empty()
    );
    assert_eq!(repo.calibration_ids().unwrap(), vec![cal.id]);
    assert!(repo.delete_calibration(cal.id).unwrap());
    repo.ping().unwrap();
}

/// Instances share a database: several connect (and migrate) at once; claims from many
/// threads over several connections each get a job of their own; a lease runs out in the
/// database's clock, the job goes back to the queue, and every write of the worker that
/// lost it is refused; on the last attempt an expired lease fails the job.
#[test]
fn postgres_claims_are_exclusive_and_leases_fence_late_writers() {
    let Some(pg) = Postgres::start("postgres_claims_are_exclusive_and_leases_fence_late_writers")
    else {
        return;
    };
    let url = pg.database("claims");
    let repos: Vec<Arc<PgRepo>> = std::thread::scope(|s| {
        let started: Vec<_> = (0..4).map(|_| s.spawn(|| PgRepo::connect(&url))).collect();
        started
            .into_iter()
            .map(|h| Arc::new(h.join().unwrap().expect("connect and migrate")))
            .collect()
    });
    for i in 0..40 {
        assert!(accepted(
            &repos[0],
            &job(["a", "b", "c"][i % 3], i as i64),
            100
        ));
    }
    let claimed: Vec<Uuid> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..8)
            .map(|w| {
                let repo = repos[w % 4].clone();
                s.spawn(move || {
                    let mut mine = Vec::new();
                    while let Some(l) = repo.claim(&format!("w{w}"), LEASE, 100).unwrap() {
                        mine.push(l.id);
                    }
                    mine
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|h| h.join().unwrap())
            .collect()
    });
    assert_eq!(claimed.len(), 40);
    assert_eq!(
        claimed.iter().collect::<HashSet<_>>().len(),
        40,
        "claimed twice"
    );

    let failure = |id: Uuid| Problem {
        kind: "urn:photostereo:problem:job-failed".into(),
        title: "Job failed".into(),
        status: 500,
        detail: format!("{id}: its worker stopped answering"),
        instance: None,
    };
    let lost = job("a", 50);
    assert!(accepted(&repos[0], &lost, 100));
    let short = Duration::from_secs(1);
    let first = repos[0].claim("dies", short, 200).unwrap().unwrap();
    assert!(repos[1].reap(3, &failure, 200).unwrap().requeued.is_empty());
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(repos[1].reap(3, &failure, 300).unwrap().requeued, [lost.id]);
    let second = repos[2].claim("takes over", LEASE, 400).unwrap().unwrap();
    assert_eq!(second.id, lost.id);
    assert!(second.token > first.token);
    // The first worker wakes up late: refused, whatever it writes.
    assert!(!repos[0].progress(first, "solve", 0.5, 500).unwrap());
    assert_eq!(repos[0].heartbeat(&[first], LEASE, 500).unwrap(), [first]);
    let done = |width| Finish::Succeeded {
        result: serde_json::json!({ "width": width }),
        artifacts: vec![],
    };
    assert!(!repos[0].finish(first, &done(1), 600).unwrap());
    assert!(!repos[0].requeue(first).unwrap());
    assert!(repos[2].finish(second, &done(2), 700).unwrap());
    let rec = repos[3].get(lost.id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Succeeded);
    assert_eq!(rec.attempts, 2);
    assert_eq!(rec.result, Some(serde_json::json!({"width": 2})));

    // An expired lease on the last attempt fails the job.
    let doomed = job("b", 60);
    assert!(accepted(&repos[0], &doomed, 100));
    repos[0].claim("dies", short, 800).unwrap().unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(repos[1].reap(1, &failure, 900).unwrap().failed, [doomed.id]);
    let rec = repos[1].get(doomed.id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Failed);
    assert!(rec.error.unwrap().detail.contains("stopped answering"));

    drop(repos);
    let again = PgRepo::connect(&url).expect("reconnect; the schema is kept");
    assert_eq!(again.get(lost.id).unwrap().unwrap().attempts, 2);
    let bad = PgRepo::connect("postgres://photostereo@127.0.0.1:1/none")
        .err()
        .expect("no server there");
    assert!(bad.to_string().contains("PostgreSQL"), "{bad}");
}

/// A service on `url` and a prefix of `weed`'s bucket.
async fn shared_server(
    url: &str,
    weed: &Weed,
    data: &std::path::Path,
    tune: impl FnOnce(&mut photostereo::service::Config),
) -> TestServer {
    let mut c = config(data);
    c.database_url = Some(url.to_string());
    c.store = Some(weed.store_url("shared"));
    tune(&mut c);
    let _env = weed::ENV.lock().await;
    weed.set_env();
    TestServer::start(c).await
}

/// The service on PostgreSQL: a job submitted over HTTP runs, its record and artifacts
/// are served, and after a restart the record is still there.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn service_on_postgres_runs_jobs_and_keeps_them_across_restarts() {
    let Some(pg) = Postgres::start("service_on_postgres_runs_jobs_and_keeps_them_across_restarts")
    else {
        return;
    };
    let Some(weed) = Weed::start("service_on_postgres_runs_jobs_and_keeps_them_across_restarts")
    else {
        return;
    };
    let url = pg.database("service");
    let data = tempfile::tempdir().unwrap();
    let server = shared_server(&url, &weed, data.path(), |_| {}).await;
    let bump = repo_root().join("res/bump");
    let job = server.submit(folder_form(&bump)).await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = server.wait_succeeded(&id).await;
    let normal = server
        .client
        .get(server.url(&format!("/v1/jobs/{id}/artifacts/normal.png")))
        .send()
        .await
        .unwrap();
    assert_eq!(normal.status(), 200);
    let bytes = normal.bytes().await.unwrap();
    server.stop().await;

    // Nothing of the job is in a SQLite file: the record lives in PostgreSQL.
    assert!(!data.path().join("jobs.sqlite").exists());
    let server = shared_server(&url, &weed, data.path(), |_| {}).await;
    let again = server.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(again["status"], "succeeded");
    assert_eq!(again["artifacts"], done["artifacts"]);
    let normal = server
        .client
        .get(server.url(&format!("/v1/jobs/{id}/artifacts/normal.png")))
        .send()
        .await
        .unwrap();
    assert_eq!(normal.bytes().await.unwrap(), bytes);
    server.stop().await;
}

/// PostgreSQL stopped while a job runs and started again: submissions during the outage
/// get 503 with Retry-After, the running job's outcome is recorded once the database
/// answers, and the service takes new jobs again without a restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_outage_answers_503_and_loses_nothing() {
    let Some(pg) = Postgres::start("postgres_outage_answers_503_and_loses_nothing") else {
        return;
    };
    let Some(weed) = Weed::start("postgres_outage_answers_503_and_loses_nothing") else {
        return;
    };
    let url = pg.database("outage");
    let data = tempfile::tempdir().unwrap();
    let server = shared_server(&url, &weed, data.path(), |c| {
        c.stage_delay = Duration::from_millis(400)
    })
    .await;
    let bump = repo_root().join("res/bump");
    let running = server.submit(folder_form(&bump)).await;
    let running = running["id"].as_str().unwrap().to_string();
    server
        .wait_for(&running, Duration::from_secs(30), |j| {
            j["status"] == "running"
        })
        .await;

    tokio::task::block_in_place(|| pg.stop());
    let r = server
        .client
        .post(server.url("/v1/jobs"))
        .multipart(folder_form(&bump))
        .send()
        .await
        .unwrap();
    let retry = r
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().to_string());
    expect_problem(r, 503, &["job database"]).await;
    assert!(retry.is_some(), "503 without Retry-After");
    let r = server
        .client
        .get(server.url(&format!("/v1/jobs/{running}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 503, "status reads wait for the database too");
    // Let the running job reach its end while the database is still down.
    tokio::time::sleep(Duration::from_secs(3)).await;
    tokio::task::block_in_place(|| pg.start_again());

    let done = server.wait_succeeded(&running).await;
    assert_eq!(done["status"], "succeeded");
    let next = server.submit(folder_form(&bump)).await;
    server.wait_succeeded(next["id"].as_str().unwrap()).await;
    server.stop().await;
}
