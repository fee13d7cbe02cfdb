//! Tenants over HTTP: each API key's tenant sees only its own jobs (another tenant's are
//! answered exactly like ids that never existed), admins see all, keys files re-read on
//! SIGHUP.

use crate::binserver;
use crate::common;

use std::time::Duration;

use common::*;
use reqwest::Method;
use serde_json::Value;

const ALICE: &str = "alice-secret";
const BOB: &str = "bob-secret";
const OPS: &str = "ops-secret";

/// A keys file: alice and bob are members, ops is an admin.
fn keys_file(dir: &std::path::Path) -> std::path::PathBuf {
    let path = dir.join("keys");
    std::fs::write(
        &path,
        format!("# tenant secret [role]\nalice {ALICE}\nbob {BOB}\nops {OPS} admin\n"),
    )
    .unwrap();
    path
}

async fn call(s: &TestServer, method: Method, path: &str, key: &str) -> reqwest::Response {
    s.client
        .request(method, s.url(path))
        .bearer_auth(key)
        .send()
        .await
        .unwrap()
}

async fn json_as(s: &TestServer, path: &str, key: &str) -> Value {
    let r = call(s, Method::GET, path, key).await;
    assert_eq!(r.status(), 200, "GET {path}");
    r.json().await.unwrap()
}

async fn submit_as(s: &TestServer, key: &str) -> String {
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key)
        .multipart(folder_form(&repo_root().join("res/bump")))
        .send()
        .await
        .unwrap();
    let body: Value = r.json().await.unwrap();
    body["id"].as_str().expect("a job id").to_string()
}

async fn wait_status_as(s: &TestServer, id: &str, key: &str, want: &[&str]) -> Value {
    let start = std::time::Instant::now();
    loop {
        let job = json_as(s, &format!("/v1/jobs/{id}"), key).await;
        if want.contains(&job["status"].as_str().unwrap()) {
            return job;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "{job}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

fn ids_of(list: &Value) -> Vec<String> {
    list["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_str().unwrap().to_string())
        .collect()
}

/// `path` asked by `key` gets a 404 whose body is, byte for byte, what the same route
/// answers for a job id that never existed (with that id in the place of `id`).
async fn hidden(s: &TestServer, method: Method, path: &str, id: &str, key: &str) {
    let never = uuid::Uuid::new_v4().to_string();
    let r = call(s, method.clone(), path, key).await;
    let body = expect_problem(r, 404, &[]).await;
    let r = call(s, method.clone(), &path.replace(id, &never), key).await;
    let other = expect_problem(r, 404, &[]).await;
    assert_eq!(
        body.to_string().replace(id, &never),
        other.to_string(),
        "{method} {path}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tenants_cannot_see_or_touch_each_others_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.api_keys_file = Some(keys_file(dir.path()));
    c.api_keys = vec!["carol:carol-secret".into()];
    let s = TestServer::start(c).await;

    // Alice's finished job, and her job held running by a slow stage.
    let done = submit_as(&s, ALICE).await;
    let done_job = wait_status_as(&s, &done, ALICE, &["succeeded"]).await;
    assert_eq!(done_job["tenant"], "alice");
    let before = done_job.to_string();
    let albedo = call(
        &s,
        Method::GET,
        &format!("/v1/jobs/{done}/artifacts/albedo.png"),
        ALICE,
    )
    .await
    .bytes()
    .await
    .unwrap();
    let bob_job = submit_as(&s, BOB).await;
    wait_status_as(&s, &bob_job, BOB, &["succeeded"]).await;
    let carol_job = submit_as(&s, "carol-secret").await;
    assert_eq!(
        json_as(&s, &format!("/v1/jobs/{carol_job}"), "carol-secret").await["tenant"],
        "carol"
    );

    // Every route that names a job answers bob as if alice's job did not exist.
    let routes = [
        (Method::GET, format!("/v1/jobs/{done}")),
        (Method::GET, format!("/v1/jobs/{done}/artifacts/albedo.png")),
        (
            Method::GET,
            format!("/v1/jobs/{done}/artifacts/result.json"),
        ),
        (
            Method::GET,
            format!("/v1/jobs/{done}/artifacts/shaded.png?light=0,0,1"),
        ),
        (Method::GET, format!("/v1/jobs/{done}/events")),
        (Method::DELETE, format!("/v1/jobs/{done}")),
    ];
    for (method, path) in &routes {
        hidden(&s, method.clone(), path, &done, BOB).await;
        hidden(&s, method.clone(), path, &done, "carol-secret").await;
    }
    // Lists hold only the caller's own.
    assert_eq!(
        ids_of(&json_as(&s, "/v1/jobs", BOB).await),
        std::slice::from_ref(&bob_job)
    );
    assert_eq!(
        ids_of(&json_as(&s, "/v1/jobs", ALICE).await),
        std::slice::from_ref(&done)
    );
    // Nothing changed for alice.
    let after = json_as(&s, &format!("/v1/jobs/{done}"), ALICE).await;
    assert_eq!(after.to_string(), before);
    let again = call(
        &s,
        Method::GET,
        &format!("/v1/jobs/{done}/artifacts/albedo.png"),
        ALICE,
    )
    .await
    .bytes()
    .await
    .unwrap();
    assert_eq!(albedo, again);
    // Her own event stream still answers (a finished job: one event, then the end).
    let events = call(&s, Method::GET, &format!("/v1/jobs/{done}/events"), ALICE).await;
    assert_eq!(events.status(), 200);
    let text = events.text().await.unwrap();
    assert!(text.contains("succeeded"), "{text}");

    // A running job cannot be cancelled by another tenant either.
    let slow = {
        let r = s
            .client
            .post(s.url("/v1/jobs"))
            .bearer_auth(ALICE)
            .multipart(synthetic_form(512, 6))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 202);
        r.json::<Value>().await.unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string()
    };
    let queued = submit_as(&s, ALICE).await;
    hidden(
        &s,
        Method::DELETE,
        &format!("/v1/jobs/{queued}"),
        &queued,
        BOB,
    )
    .await;
    hidden(&s, Method::DELETE, &format!("/v1/jobs/{slow}"), &slow, BOB).await;
    let q = json_as(&s, &format!("/v1/jobs/{queued}"), ALICE).await;
    assert_ne!(q["status"], "cancelled", "{q}");
    let slow_job = wait_status_as(&s, &slow, ALICE, &["succeeded", "failed"]).await;
    assert_eq!(slow_job["status"], "succeeded", "{slow_job}");
    wait_status_as(&s, &queued, ALICE, &["succeeded"]).await;

    // The admin sees every tenant's jobs and manages them.
    let all = ids_of(&json_as(&s, "/v1/jobs?limit=100", OPS).await);
    for id in [&done, &bob_job, &carol_job, &slow, &queued] {
        assert!(all.contains(id), "{id} in {all:?}");
    }
    assert_eq!(all.len(), 5);
    let seen = json_as(&s, &format!("/v1/jobs/{bob_job}"), OPS).await;
    assert_eq!(seen["tenant"], "bob");
    let r = call(
        &s,
        Method::GET,
        &format!("/v1/jobs/{bob_job}/artifacts/albedo.png"),
        OPS,
    )
    .await;
    assert_eq!(r.status(), 200);
    let r = call(&s, Method::DELETE, &format!("/v1/jobs/{bob_job}"), OPS).await;
    assert_eq!(r.status(), 204);
    let r = call(&s, Method::GET, &format!("/v1/jobs/{bob_job}"), BOB).await;
    expect_problem(r, 404, &["no job"]).await;

    // Alice deletes her own.
    let r = call(&s, Method::DELETE, &format!("/v1/jobs/{done}"), ALICE).await;
    assert_eq!(r.status(), 204);
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_re_read_keys_file_takes_effect_and_a_broken_one_keeps_the_keys() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    let file = keys_file(dir.path());
    c.api_keys_file = Some(file.clone());
    let s = TestServer::start(c).await;
    assert_eq!(call(&s, Method::GET, "/v1/jobs", ALICE).await.status(), 200);

    std::fs::write(&file, "dave dave-secret\nbob bob-secret\n").unwrap();
    assert_eq!(s.state.reload_keys().unwrap(), 2);
    let r = call(&s, Method::GET, "/v1/jobs", ALICE).await;
    expect_problem(r, 401, &["not valid"]).await;
    assert_eq!(
        call(&s, Method::GET, "/v1/jobs", "dave-secret")
            .await
            .status(),
        200
    );

    std::fs::write(&file, "dave\n").unwrap();
    let e = s.state.reload_keys().unwrap_err().to_string();
    assert!(e.contains("line 1"), "{e}");
    assert_eq!(
        call(&s, Method::GET, "/v1/jobs", "dave-secret")
            .await
            .status(),
        200
    );

    // A keys file with no keys left closes the API; it does not open it.
    std::fs::write(&file, "# nobody\n").unwrap();
    assert_eq!(s.state.reload_keys().unwrap(), 0);
    let r = s.client.get(s.url("/v1/jobs")).send().await.unwrap();
    expect_problem(r, 401, &[]).await;
    s.stop().await;
}

/// The real binary re-reads its keys file on SIGHUP, and never logs a secret.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_re_reads_the_keys_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = keys_file(dir.path());
    let data = dir.path().join("data");
    let server = binserver::BinServer::start(
        &data,
        &[
            "--api-keys-file",
            file.to_str().unwrap(),
            "--api-key",
            "flag-tenant:flag-secret",
        ],
    );
    let get = |key: &'static str| {
        let r = server
            .client
            .get(server.url("/v1/jobs"))
            .bearer_auth(key)
            .send();
        async move { r.await.unwrap().status().as_u16() }
    };
    assert_eq!(get(ALICE).await, 200);
    assert_eq!(get("flag-secret").await, 200);
    assert_eq!(get("erin-secret").await, 401);
    std::fs::write(&file, "erin erin-secret\n").unwrap();
    // SAFETY: kill(2) with our own child's pid and a valid signal number.
    let rc = unsafe { libc::kill(server.pid() as libc::pid_t, libc::SIGHUP) };
    assert_eq!(rc, 0);
    let start = std::time::Instant::now();
    while get("erin-secret").await != 200 {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "{}",
            server.logs()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(get(ALICE).await, 401);
    assert_eq!(get("flag-secret").await, 200, "flags stay");
    let logs = server
        .logs_with("API keys re-read", Duration::from_secs(10))
        .await;
    for secret in [ALICE, BOB, OPS, "erin-secret", "flag-secret"] {
        assert!(!logs.contains(secret), "{secret} logged");
    }
}

async fn post_as(s: &TestServer, key: &str, form: reqwest::multipart::Form) -> reqwest::Response {
    s.client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key)
        .multipart(form)
        .send()
        .await
        .unwrap()
}

fn bump() -> reqwest::multipart::Form {
    folder_form(&repo_root().join("res/bump"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quotas_refuse_with_429_naming_the_limit_and_spare_other_tenants() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.api_keys_file = Some(keys_file(dir.path()));
    c.tenant_max_jobs = 2;
    c.tenant_submissions_per_minute = 4;
    c.stage_delay = Duration::from_millis(200);
    let s = TestServer::start(c).await;

    let first = submit_as(&s, ALICE).await;
    let second = submit_as(&s, ALICE).await;
    let r = post_as(&s, ALICE, bump()).await;
    let retry = r
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().to_string());
    expect_problem(r, 429, &["alice", "2 jobs queued or running", "limit"]).await;
    assert!(retry.unwrap().parse::<u64>().unwrap() >= 1);
    // Bob is not held back by alice's quota.
    let bob = post_as(&s, BOB, bump()).await;
    assert_eq!(bob.status(), 202);
    // Once one of alice's jobs is cancelled, she may submit again.
    let r = call(&s, Method::DELETE, &format!("/v1/jobs/{second}"), ALICE).await;
    assert_eq!(r.status(), 200);
    let third = post_as(&s, ALICE, bump()).await;
    assert_eq!(third.status(), 202);
    // Four submissions a minute: the refused one counted too, so the fifth is refused.
    let r = post_as(&s, ALICE, bump()).await;
    let retry = r
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().to_string());
    expect_problem(r, 429, &["alice", "4 submissions in the last minute"]).await;
    let secs = retry.unwrap().parse::<u64>().unwrap();
    assert!((1..=60).contains(&secs), "Retry-After {secs}");

    let metrics = s.metrics_text().await;
    for line in [
        "photostereo_tenant_quota_refusals_total{tenant=\"alice\",limit=\"active_jobs\"} 1",
        "photostereo_tenant_quota_refusals_total{tenant=\"alice\",limit=\"submissions_per_minute\"} 1",
        "photostereo_tenant_jobs{tenant=\"alice\",status=\"cancelled\"} 1",
    ] {
        assert!(metrics.contains(line), "{line} in\n{metrics}");
    }
    assert!(!metrics.contains("tenant=\"bob\",limit"), "{metrics}");
    wait_status_as(&s, &first, ALICE, &["succeeded"]).await;
    s.stop().await;

    // Stored bytes: once alice's artifacts reach the limit, her next submission is refused.
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.api_keys_file = Some(keys_file(dir.path()));
    c.tenant_max_stored_bytes = 1;
    let s = TestServer::start(c).await;
    let id = submit_as(&s, ALICE).await;
    wait_status_as(&s, &id, ALICE, &["succeeded"]).await;
    let r = post_as(&s, ALICE, bump()).await;
    expect_problem(r, 429, &["alice", "stores", "bytes"]).await;
    assert_eq!(post_as(&s, BOB, bump()).await.status(), 202);
    assert_eq!(
        call(&s, Method::DELETE, &format!("/v1/jobs/{id}"), ALICE)
            .await
            .status(),
        204
    );
    assert_eq!(post_as(&s, ALICE, bump()).await.status(), 202);
    s.stop().await;
}

/// Tenant A queues 20 jobs, then B 2: with one worker, B's jobs start while most of A's
/// are still waiting (first come, first served would run all of A's first).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_queue_serves_tenants_in_turn() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.api_keys_file = Some(keys_file(dir.path()));
    c.stage_delay = Duration::from_millis(25);
    let s = TestServer::start(c).await;
    let mut a = Vec::new();
    for _ in 0..20 {
        a.push(submit_as(&s, ALICE).await);
    }
    let b = [submit_as(&s, BOB).await, submit_as(&s, BOB).await];
    let mut started = Vec::new();
    for (id, key) in a
        .iter()
        .map(|id| (id, ALICE))
        .chain(b.iter().map(|id| (id, BOB)))
    {
        let job = wait_status_as(&s, id, key, &["succeeded"]).await;
        started.push((job["started_at"].as_str().unwrap().to_string(), key));
    }
    started.sort();
    let order: Vec<&str> = started
        .iter()
        .map(|(_, k)| if *k == BOB { "B" } else { "a" })
        .collect();
    let last_b = order.iter().rposition(|k| *k == "B").unwrap();
    let a_after = order[last_b..].iter().filter(|k| **k == "a").count();
    assert!(a_after >= 10, "start order {}", order.concat());
    s.stop().await;
}

async fn post_keyed(
    s: &TestServer,
    key: &str,
    idem: &str,
    form: reqwest::multipart::Form,
) -> (u16, Option<String>, String) {
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key)
        .header("idempotency-key", idem)
        .multipart(form)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    let location = r
        .headers()
        .get("location")
        .map(|v| v.to_str().unwrap().to_string());
    (status, location, r.text().await.unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idempotency_key_replays_the_first_answer_even_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.api_keys_file = Some(keys_file(dir.path()));
    // One job at a time per tenant: a retry is answered even when the quota is full.
    c.tenant_max_jobs = 1;
    c.workers = 1;
    c.stage_delay = Duration::from_millis(400);
    let s = TestServer::start(c.clone()).await;

    let first = post_keyed(&s, ALICE, "order-17", bump()).await;
    assert_eq!(first.0, 202, "{}", first.2);
    let job: Value = serde_json::from_str(&first.2).unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(first.1.as_deref(), Some(format!("/v1/jobs/{id}").as_str()));
    // The same request again (a new multipart boundary, same parts): the same answer.
    let again = post_keyed(&s, ALICE, "order-17", bump()).await;
    assert_eq!(again, first);
    // The same key with another body: 422, and no job.
    let other = synthetic_form(32, 4);
    let (status, _, body) = post_keyed(&s, ALICE, "order-17", other).await;
    assert_eq!(status, 422, "{body}");
    assert!(body.contains("different request"), "{body}");
    // Another tenant's key space is its own.
    let bobs = post_keyed(&s, BOB, "order-17", bump()).await;
    assert_eq!(bobs.0, 202);
    assert_ne!(bobs.2, first.2);
    // Without a key, alice's quota (1 active job) refuses.
    let r = post_as(&s, ALICE, bump()).await;
    assert_eq!(r.status(), 429);
    let list = json_as(&s, "/v1/jobs", ALICE).await;
    assert_eq!(
        ids_of(&list),
        std::slice::from_ref(&id),
        "one job for alice"
    );
    wait_status_as(&s, &id, ALICE, &["succeeded"]).await;
    s.stop().await;

    // After a restart the key still answers with the first answer.
    let s = TestServer::start(c).await;
    let after = post_keyed(&s, ALICE, "order-17", bump()).await;
    assert_eq!(after, first);
    let (status, _, _) = post_keyed(&s, ALICE, "order-17", synthetic_form(32, 4)).await;
    assert_eq!(status, 422);
    assert_eq!(ids_of(&json_as(&s, "/v1/jobs", ALICE).await), [id]);
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth(ALICE)
        .header("idempotency-key", "")
        .multipart(bump())
        .send()
        .await
        .unwrap();
    expect_problem(r, 400, &["Idempotency-Key"]).await;
    s.stop().await;
}
