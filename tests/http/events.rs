//! `GET /v1/jobs/{id}/events` over HTTP: a job's events in order, a late subscriber, a
//! deleted job, an unknown one.

use crate::common;

use std::time::{Duration, Instant};

use common::*;
use serde_json::Value;

/// A server-sent event stream read one event at a time.
struct Events {
    response: reqwest::Response,
    buf: String,
}

impl Events {
    async fn open(s: &TestServer, id: &str) -> Self {
        let r = s
            .client
            .get(s.url(&format!("/v1/jobs/{id}/events")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], "text/event-stream");
        Self {
            response: r,
            buf: String::new(),
        }
    }

    /// The next event as (name, data), or None when the server ended the stream.
    async fn next(&mut self) -> Option<(String, Value)> {
        loop {
            if let Some(end) = self.buf.find("\n\n") {
                let block: String = self.buf.drain(..end + 2).collect();
                let (mut name, mut data) = (String::from("message"), String::new());
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        name = v.trim().to_string();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.trim_start());
                    }
                }
                if data.is_empty() {
                    continue; // a keep-alive comment
                }
                return Some((name, serde_json::from_str(&data).unwrap()));
            }
            let chunk = tokio::time::timeout(Duration::from_secs(60), self.response.chunk())
                .await
                .expect("an event or the end within 60 s")
                .unwrap()?;
            self.buf.push_str(std::str::from_utf8(&chunk).unwrap());
        }
    }

    /// Every event until the stream ends.
    async fn all(mut self) -> Vec<(String, Value)> {
        let mut out = Vec::new();
        while let Some(e) = self.next().await {
            out.push(e);
        }
        assert!(self.buf.trim().is_empty(), "left over: {:?}", self.buf);
        out
    }
}

const STATUSES: [&str; 3] = ["queued", "running", "succeeded"];
const STAGES: [&str; 5] = ["decode", "solve", "mask", "integrate", "mesh"];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jobs_events_arrive_in_order_and_end_with_succeeded() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    // Every stage lasts longer than the stream's reading interval, so each one shows.
    c.stage_delay = Duration::from_millis(400);
    let s = TestServer::start(c).await;
    let job = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    let id = job["id"].as_str().unwrap();
    let started = Instant::now();
    let events = Events::open(&s, id).await.all().await;
    let took = started.elapsed();

    assert!(events.iter().all(|(name, _)| name == "job"), "{events:?}");
    let jobs: Vec<&Value> = events.iter().map(|(_, j)| j).collect();
    assert!(jobs.iter().all(|j| j["id"] == id));
    let status = |j: &Value| {
        let s = j["status"].as_str().unwrap();
        STATUSES
            .iter()
            .position(|x| *x == s)
            .unwrap_or_else(|| panic!("status {s}"))
    };
    let stage = |j: &Value| {
        j["stage"]
            .as_str()
            .map(|s| STAGES.iter().position(|x| *x == s).unwrap())
    };
    for w in jobs.windows(2) {
        let (a, b) = (w[0], w[1]);
        assert!(status(a) <= status(b), "status went back: {a} then {b}");
        assert!(stage(a) <= stage(b), "stage went back: {a} then {b}");
        assert!(
            a["progress"].as_f64() <= b["progress"].as_f64(),
            "progress went back: {a} then {b}"
        );
        assert!(
            (
                a["status"].clone(),
                a["stage"].clone(),
                a["progress"].clone()
            ) != (
                b["status"].clone(),
                b["stage"].clone(),
                b["progress"].clone()
            ),
            "an event that changes nothing: {b}"
        );
    }
    // Each stage was seen, in the pipeline's order.
    let mut seen: Vec<&str> = jobs.iter().filter_map(|j| j["stage"].as_str()).collect();
    seen.dedup();
    assert_eq!(seen, STAGES);
    let last = jobs.last().unwrap();
    assert_eq!(last["status"], "succeeded");
    assert_eq!(last["progress"], 1.0);
    assert!(last["artifacts"]["albedo.png"].is_string(), "{last}");
    assert!(last["result"]["width"].is_u64(), "{last}");
    // At most a few a second.
    let limit = 1 + (took.as_secs_f64() * 4.0).ceil() as usize;
    assert!(events.len() <= limit, "{} events in {took:?}", events.len());
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_subscriber_gets_the_current_state_first() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.stage_delay = Duration::from_millis(300);
    let s = TestServer::start(c).await;
    let job = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    let id = job["id"].as_str().unwrap();

    let running = s
        .wait_for(id, Duration::from_secs(30), |j| j["stage"] == "solve")
        .await;
    let mut events = Events::open(&s, id).await;
    let (name, first) = events.next().await.unwrap();
    assert_eq!(name, "job");
    assert_eq!(first["status"], "running");
    assert!(
        first["progress"].as_f64() >= running["progress"].as_f64(),
        "{first}"
    );
    assert_ne!(first["stage"], "decode", "{first}");
    let rest = events.all().await;
    assert_eq!(rest.last().unwrap().1["status"], "succeeded");

    // After the end: the finished job once, then the stream ends.
    let after = Events::open(&s, id).await.all().await;
    assert_eq!(after.len(), 1, "{after:?}");
    assert_eq!(after[0].0, "job");
    assert_eq!(after[0].1["status"], "succeeded");
    assert_eq!(after[0].1, s.get_json(&format!("/v1/jobs/{id}")).await);
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deleted_job_ends_its_stream_and_unknown_jobs_get_404() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.stage_delay = Duration::from_secs(2);
    // Long enough between reads that the job is cancelled and deleted in between.
    c.event_interval = Duration::from_secs(2);
    let s = TestServer::start(c).await;
    let bump = repo_root().join("res/bump");
    let running = s.submit(folder_form(&bump)).await;
    let queued = s.submit(folder_form(&bump)).await;
    let id = queued["id"].as_str().unwrap();

    let mut events = Events::open(&s, id).await;
    let (name, first) = events.next().await.unwrap();
    assert_eq!(
        (name.as_str(), &first["status"]),
        ("job", &Value::from("queued"))
    );
    let url = s.url(&format!("/v1/jobs/{id}"));
    assert_eq!(s.client.delete(&url).send().await.unwrap().status(), 200);
    assert_eq!(s.client.delete(&url).send().await.unwrap().status(), 204);
    let rest = events.all().await;
    assert_eq!(rest.len(), 1, "{rest:?}");
    assert_eq!(rest[0].0, "deleted");
    assert_eq!(rest[0].1["id"], id);

    for bad in [uuid::Uuid::new_v4().to_string(), "not-a-uuid".to_string()] {
        let r = s
            .client
            .get(s.url(&format!("/v1/jobs/{bad}/events")))
            .send()
            .await
            .unwrap();
        expect_problem(r, 404, &[&bad]).await;
    }
    let other = running["id"].as_str().unwrap();
    s.client
        .delete(s.url(&format!("/v1/jobs/{other}")))
        .send()
        .await
        .unwrap();
    s.stop().await;
}
