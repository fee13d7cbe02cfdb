//! `--database-url postgres://…` against a real PostgreSQL server (Debian's binaries, see
//! `common/postgres.rs`): the repo keeps the same records and state rules as SQLite, its
//! migrations are applied once, a second instance on the same database is refused, and
//! a service on it runs jobs whose records survive a restart.

mod common;
#[path = "common/postgres.rs"]
mod postgres;

use common::*;
use photostereo::service::error::Problem;
use photostereo::service::pg::PgRepo;
use photostereo::service::repo::{
    ArtifactInfo, CalibrationRecord, Finish, JobRecord, JobRepo, JobStatus, Remembered,
};
use postgres::Postgres;
use uuid::Uuid;

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

    // Admission per tenant: at most `max_active` queued or running.
    let a = job("acme", 1_000);
    assert!(repo.insert(&a, 2).unwrap());
    assert!(repo.insert(&job("acme", 1_001), 2).unwrap());
    assert!(
        !repo.insert(&job("acme", 1_002), 2).unwrap(),
        "third active job refused"
    );
    assert!(repo.insert(&job("other", 1_003), 2).unwrap());
    assert_eq!(repo.active("acme").unwrap(), 2);

    // Lifecycle: start once, progress, heartbeat, finish once.
    assert_eq!(repo.get(a.id).unwrap().unwrap().status, JobStatus::Queued);
    assert!(repo.start(a.id, 2_000).unwrap());
    assert!(
        !repo.start(a.id, 2_001).unwrap(),
        "a running job is not started twice"
    );
    repo.progress(a.id, "solve", 0.25, 2_100).unwrap();
    repo.heartbeat(&[a.id], 2_200).unwrap();
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
    assert!(repo.finish(a.id, &done, 3_000).unwrap());
    assert!(!repo.finish(a.id, &done, 3_001).unwrap(), "finished once");
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
    assert!(repo.insert(&b, 5).unwrap());
    assert!(repo.start(b.id, 4_000).unwrap());
    assert!(repo.requeue(b.id).unwrap());
    assert!(
        !repo.requeue(b.id).unwrap(),
        "only a running job is requeued"
    );
    assert_eq!(repo.cancel(b.id, 4_100).unwrap(), Some(JobStatus::Queued));
    assert!(
        !repo.start(b.id, 4_200).unwrap(),
        "a cancelled job never starts"
    );
    let failed = job("other", 1_005);
    assert!(repo.insert(&failed, 5).unwrap());
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
        (2, 1, 1)
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
    assert_eq!(repo.unfinished().unwrap().len(), 2);
    let expired = repo.expired(5_000, 10).unwrap();
    assert_eq!(
        expired.len(),
        3,
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

/// One instance per database: a second is refused while the first lives; the schema is
/// migrated once and kept across reconnects.
#[test]
fn postgres_holds_one_instance_and_migrates_once() {
    let Some(pg) = Postgres::start("postgres_holds_one_instance_and_migrates_once") else {
        return;
    };
    let url = pg.database("instances");
    let first = PgRepo::connect(&url).expect("first instance");
    let kept = job("default", 1);
    assert!(first.insert(&kept, 10).unwrap());
    let second = PgRepo::connect(&url)
        .err()
        .expect("a second instance is refused");
    assert!(
        second.to_string().contains("another photostereo instance"),
        "{second}"
    );
    drop(first);
    let again = PgRepo::connect(&url).expect("free again once the first is gone");
    assert_eq!(again.get(kept.id).unwrap().unwrap().id, kept.id);
    let bad = PgRepo::connect("postgres://photostereo@127.0.0.1:1/none")
        .err()
        .expect("no server there");
    assert!(bad.to_string().contains("PostgreSQL"), "{bad}");
}

/// The service on PostgreSQL: a job submitted over HTTP runs, its record and artifacts
/// are served, and after a restart the record is still there.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn service_on_postgres_runs_jobs_and_keeps_them_across_restarts() {
    let Some(pg) = Postgres::start("service_on_postgres_runs_jobs_and_keeps_them_across_restarts")
    else {
        return;
    };
    let url = pg.database("service");
    let data = tempfile::tempdir().unwrap();
    let mut c = config(data.path());
    c.database_url = Some(url.clone());
    let server = TestServer::start(c.clone()).await;
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
    let server = TestServer::start(c).await;
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
    let url = pg.database("outage");
    let data = tempfile::tempdir().unwrap();
    let mut c = config(data.path());
    c.database_url = Some(url);
    c.stage_delay = std::time::Duration::from_millis(400);
    let server = TestServer::start(c).await;
    let bump = repo_root().join("res/bump");
    let running = server.submit(folder_form(&bump)).await;
    let running = running["id"].as_str().unwrap().to_string();
    server
        .wait_for(&running, std::time::Duration::from_secs(30), |j| {
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
    tokio::time::sleep(std::time::Duration::from_secs(3)).await;
    tokio::task::block_in_place(|| pg.start_again());

    let done = server.wait_succeeded(&running).await;
    assert_eq!(done["status"], "succeeded");
    let next = server.submit(folder_form(&bump)).await;
    server.wait_succeeded(next["id"].as_str().unwrap()).await;
    server.stop().await;
}
