//! `--database-url postgres://…` against a real PostgreSQL server (Debian's binaries, see
//! `common/postgres.rs`): the repo keeps the contract SQLite keeps (`repo::contract`:
//! records and state rules, exclusive claims under concurrency, leases that run out in
//! the database's clock and fence late writers, migrations applied once however many
//! instances start together), and a service on it (with the S3 store, `common/weed.rs`)
//! runs jobs whose records survive a restart and an outage.

use crate::common;
use crate::common::postgres;
use crate::common::weed;

use std::sync::Arc;
use std::time::Duration;

use common::*;
use photostereo::service::repo::contract::{self, Backend, Clock};
use photostereo::service::repo::{JobRepo, PostgresRepo};
use postgres::Postgres;
use weed::Weed;

/// A database of its own per check on one cluster; instances that start together connect
/// (and migrate) at once, from threads of their own.
struct Cluster(Postgres);

impl Backend for Cluster {
    type Db = String;

    fn create(&self, check: &str) -> String {
        self.0.database(check)
    }

    fn open(&self, url: &String) -> Arc<dyn JobRepo> {
        Arc::new(PostgresRepo::connect(url).expect("connect and migrate"))
    }

    fn open_many(&self, url: &String, n: usize) -> Vec<Arc<dyn JobRepo>> {
        std::thread::scope(|s| {
            let started: Vec<_> = (0..n)
                .map(|_| s.spawn(|| PostgresRepo::connect(url)))
                .collect();
            started
                .into_iter()
                .map(|h| Arc::new(h.join().unwrap().expect("connect and migrate")) as _)
                .collect()
        })
    }

    fn clock(&self) -> Clock {
        Clock::Wall
    }
}

/// The repo's contract (the same suite SQLite's unit tests run): the records and state
/// rules, exclusive claims from several instances, leases that run out in the database's
/// clock and fence late writers, migrations applied once however many instances start
/// together.
#[test]
fn postgres_keeps_the_repo_contract() {
    let Some(pg) = Postgres::start("postgres_keeps_the_repo_contract") else {
        return;
    };
    contract::run(&Cluster(pg));
}

/// A server that is not there is named as PostgreSQL's.
#[test]
fn postgres_unreachable_is_named() {
    let bad = PostgresRepo::connect("postgres://photostereo@127.0.0.1:1/none")
        .err()
        .expect("no server there");
    assert!(bad.to_string().contains("PostgreSQL"), "{bad}");
    assert!(bad.is_unavailable(), "{bad}");
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
