//! Several instances on one PostgreSQL database and one S3 bucket (real servers: see
//! `common/postgres.rs` and `common/weed.rs`).
//!
//! - Three instances: jobs submitted round-robin each run once, on one of them, never
//!   more at once than an instance's pool; any instance answers for any job (status,
//!   events, artifacts, shading on request) with the same bytes.
//! - The real binary: an instance killed (`kill -9`) in the middle of a job loses it to
//!   another once its lease runs out; an instance paused past its lease wakes to find the
//!   job taken over, and what it writes late is refused; a job cancelled on one instance
//!   stops on the one running it within a heartbeat; PostgreSQL stopped and started
//!   under the running cluster loses no accepted job, submissions meanwhile get 503, and
//!   the instances go on without a restart.

use crate::binserver;
use crate::common;
use crate::common::postgres;
use crate::common::weed;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use binserver::BinServer;
use common::*;
use postgres::Postgres;
use serde_json::Value;
use weed::{Weed, keys};

/// The bucket prefix the instances share.
const SHARED: &str = "cluster";

/// The attempts whose outputs are stored for job `id`.
async fn output_attempts(weed: &Weed, id: &str) -> BTreeSet<String> {
    let prefix = format!("{SHARED}/jobs/{id}/outputs/");
    keys(&weed.bucket(), &prefix)
        .await
        .iter()
        .filter_map(|k| {
            k.strip_prefix(&prefix)?
                .split('/')
                .next()
                .map(str::to_string)
        })
        .collect()
}

async fn bytes(client: &reqwest::Client, url: &str) -> Vec<u8> {
    let r = client.get(url).send().await.unwrap();
    assert_eq!(r.status(), 200, "GET {url}");
    r.bytes().await.unwrap().to_vec()
}

/// Jobs this server's process ran to success (its metrics).
async fn succeeded_here(s: &TestServer) -> u64 {
    let metrics = s.metrics_text().await;
    metrics
        .lines()
        .find_map(|l| {
            l.strip_prefix("photostereo_jobs_finished_seconds_count{status=\"succeeded\"} ")
        })
        .map_or(0, |n| n.trim().parse().unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn three_instances_share_one_queue_and_answer_for_every_job() {
    const NAME: &str = "three_instances_share_one_queue_and_answer_for_every_job";
    let (Some(pg), Some(weed)) = (Postgres::start(NAME), Weed::start(NAME)) else {
        return;
    };
    let url = pg.database("three");
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    let mut servers = Vec::new();
    for dir in &dirs {
        let mut c = config(dir.path());
        c.database_url = Some(url.clone());
        c.store = Some(weed.store_url(SHARED));
        c.workers = 1;
        let _env = weed::ENV.lock().await;
        weed.set_env();
        servers.push(TestServer::start(c).await);
    }
    let bump = repo_root().join("res/bump");
    let mut ids = Vec::new();
    for i in 0..30 {
        let job = servers[i % 3].submit(folder_form(&bump)).await;
        ids.push(job["id"].as_str().unwrap().to_string());
    }
    let mut finished = Vec::new();
    for (i, id) in ids.iter().enumerate() {
        // Watched from an instance other than the one it was submitted to.
        let job = servers[(i + 1) % 3].wait_succeeded(id).await;
        assert_eq!(job["attempts"], 1, "{job}");
        finished.push(job);
    }
    let mut ran = Vec::new();
    for s in &servers {
        assert!(s.state.max_running() <= 1, "an instance ran past its pool");
        ran.push(succeeded_here(s).await);
    }
    assert_eq!(ran.iter().sum::<u64>(), 30, "each job ran once: {ran:?}");
    assert!(
        ran.iter().filter(|n| **n > 0).count() >= 2,
        "the work was not shared: {ran:?}"
    );

    let light = "shaded.png?light=0.3,-0.2,0.93";
    for (id, job) in ids.iter().zip(&finished) {
        assert_eq!(
            output_attempts(&weed, id).await.len(),
            1,
            "one artifact set"
        );
        let mut names: Vec<String> = job["artifacts"]
            .as_object()
            .unwrap()
            .keys()
            .cloned()
            .collect();
        names.push(light.to_string());
        for name in &names {
            let path = format!("/v1/jobs/{id}/artifacts/{name}");
            let first = bytes(&servers[0].client, &servers[0].url(&path)).await;
            for s in &servers[1..] {
                assert!(
                    bytes(&s.client, &s.url(&path)).await == first,
                    "{path} differs"
                );
            }
        }
    }
    // The event stream of a job, from every instance, ends with its success.
    for s in &servers {
        let r = s
            .client
            .get(s.url(&format!("/v1/jobs/{}/events", ids[0])))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        let text = tokio::time::timeout(Duration::from_secs(20), r.text())
            .await
            .expect("the stream of a finished job ends")
            .unwrap();
        assert!(text.contains("succeeded"), "{text}");
    }
    for s in servers {
        s.stop().await;
    }
}

/// Submit res/bump to a binary server; the id of its 202.
async fn submit(s: &BinServer) -> String {
    s.submit(folder_form(&repo_root().join("res/bump"))).await
}

fn signal(s: &BinServer, sig: libc::c_int) {
    // SAFETY: kill(2) on our own child's pid with a valid signal number.
    assert_eq!(unsafe { libc::kill(s.pid() as libc::pid_t, sig) }, 0);
}

async fn job(s: &BinServer, id: &str, timeout: Duration, done: impl Fn(&Value) -> bool) -> Value {
    s.wait_json(&format!("/v1/jobs/{id}"), timeout, done).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_or_paused_instance_loses_its_job_and_an_outage_loses_nothing() {
    const NAME: &str = "a_dead_or_paused_instance_loses_its_job_and_an_outage_loses_nothing";
    let (Some(pg), Some(weed)) = (Postgres::start(NAME), Weed::start(NAME)) else {
        return;
    };
    let url = pg.database("takeover");
    let store = weed.store_url(SHARED);
    // Six stages of 700 ms each: jobs are found running; leases of 2 s run out quickly.
    let flags = [
        "--database-url",
        &url,
        "--store",
        &store,
        "--workers",
        "1",
        "--job-lease",
        "2s",
        "--stage-delay",
        "700ms",
        "--shutdown-grace",
        "1s",
    ];
    let env = weed.env();
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    let start = |i: usize| BinServer::start_with_env(dirs[i].path(), &flags, &env);
    let long = Duration::from_secs(90);

    // kill -9 in the middle of a job: another instance takes it over and it succeeds.
    let mut a = start(0);
    let first = submit(&a).await;
    job(&a, &first, long, |j| j["stage"] == "solve").await;
    let b = start(1);
    a.kill();
    let done = job(&b, &first, long, |j| j["status"] == "succeeded").await;
    assert_eq!(done["attempts"], 2, "{done}");
    assert_eq!(output_attempts(&weed, &first).await.len(), 1);

    // Paused past its lease: the job goes to another instance; woken, the paused one
    // records nothing.
    let c = start(2);
    signal(&c, libc::SIGSTOP); // so that b claims the next job
    let second = submit(&b).await;
    job(&b, &second, long, |j| j["stage"] == "solve").await;
    signal(&c, libc::SIGCONT);
    signal(&b, libc::SIGSTOP);
    job(&c, &second, long, |j| {
        j["attempts"] == 2 && j["status"] == "running"
    })
    .await;
    signal(&b, libc::SIGCONT);
    let done = job(&c, &second, long, |j| j["status"] == "succeeded").await;
    assert_eq!(done["attempts"], 2, "{done}");
    let deadline = Instant::now() + Duration::from_secs(20);
    while !b.logs().contains("lease ran out; another worker runs it") {
        assert!(Instant::now() < deadline, "b never noticed:\n{}", b.logs());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        output_attempts(&weed, &second).await.len(),
        1,
        "b's attempt left outputs"
    );
    let path = format!("/v1/jobs/{second}/artifacts/normal.png");
    assert_eq!(
        bytes(&b.client, &b.url(&path)).await,
        bytes(&c.client, &c.url(&path)).await
    );

    // DELETE on one instance stops the job running on another within a heartbeat (a
    // third of the lease).
    signal(&c, libc::SIGSTOP); // so that b claims it
    let third = submit(&b).await;
    job(&b, &third, long, |j| j["stage"] == "solve").await;
    signal(&c, libc::SIGCONT);
    let asked = Instant::now();
    let r = c
        .client
        .delete(c.url(&format!("/v1/jobs/{third}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "cancel a running job");
    let cancelled_on_b = "photostereo_jobs_finished_seconds_count{status=\"cancelled\"} 1";
    loop {
        let metrics = b.client.get(b.url("/metrics")).send().await.unwrap();
        if metrics.text().await.unwrap().contains(cancelled_on_b) {
            break;
        }
        assert!(asked.elapsed() < long, "b never stopped the cancelled job");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let took = asked.elapsed();
    assert!(
        took < Duration::from_millis(1500),
        "b stopped it after {took:?}"
    );

    // PostgreSQL stopped and started under the running cluster.
    let mut accepted = Vec::new();
    for s in [&b, &c, &b, &c] {
        accepted.push(submit(s).await);
    }
    job(&b, &accepted[0], long, |j| j["status"] == "running").await;
    tokio::task::block_in_place(|| pg.stop());
    for s in [&b, &c] {
        let r = s
            .client
            .post(s.url("/v1/jobs"))
            .multipart(folder_form(&repo_root().join("res/bump")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 503, "a submission while the database is down");
        assert!(r.headers().contains_key("retry-after"));
    }
    tokio::time::sleep(Duration::from_secs(3)).await;
    tokio::task::block_in_place(|| pg.start_again());
    accepted.push(submit(&b).await);
    accepted.push(submit(&c).await);
    for id in &accepted {
        job(&c, id, long, |j| j["status"] == "succeeded").await;
    }
    drop(b);
    drop(c);
}
