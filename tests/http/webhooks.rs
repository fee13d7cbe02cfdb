//! Webhooks against a local receiver: a job's end is POSTed once, signed as documented,
//! retried after a 500, and retried after a restart when it was not delivered before the
//! stop (unless its retry window closed meanwhile); callback URLs off the allow-list are
//! refused at submission.

use crate::common;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::http::{HeaderMap, StatusCode};
use common::*;
use reqwest::multipart::{Form, Part};
use serde_json::Value;
use sha2::{Digest, Sha256};

const SECRET: &str = "whsec-alice";

/// What the receiver got, and how many requests it answers with 500 first.
#[derive(Default)]
struct Inbox {
    got: Vec<(HeaderMap, String)>,
    fail_first: usize,
}

/// A receiver on 127.0.0.1:0 at `/hook`; returns its URL.
async fn receiver(fail_first: usize) -> (String, Arc<Mutex<Inbox>>) {
    let inbox = Arc::new(Mutex::new(Inbox {
        got: Vec::new(),
        fail_first,
    }));
    let kept = inbox.clone();
    let app = axum::Router::new().route(
        "/hook",
        axum::routing::post(move |headers: HeaderMap, body: String| {
            let inbox = kept.clone();
            async move {
                let mut i = inbox.lock().unwrap();
                i.got.push((headers, body));
                if i.got.len() <= i.fail_first {
                    StatusCode::INTERNAL_SERVER_ERROR
                } else {
                    StatusCode::NO_CONTENT
                }
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await });
    (url, inbox)
}

fn webhook_config(dir: &std::path::Path) -> photostereo::service::Config {
    let mut c = config(dir);
    c.api_keys = vec!["alice:alice-key".into(), "bob:bob-key".into()];
    c.webhook_allow_hosts = vec!["127.0.0.1".into()];
    c.webhook_secrets = vec![format!("alice:{SECRET}")];
    c.webhook_first_retry = Duration::from_millis(100);
    c.webhook_retry_for = Duration::from_secs(30);
    c
}

/// The recipe docs/http-api.md gives: HMAC-SHA256 of `timestamp.body` under the secret, hex, as `v1=`.
fn expected_signature(secret: &str, timestamp: &str, body: &str) -> String {
    let mut key = [0u8; 64];
    key[..secret.len()].copy_from_slice(secret.as_bytes());
    let inner = Sha256::new()
        .chain_update(key.map(|b| b ^ 0x36))
        .chain_update(format!("{timestamp}.{body}"))
        .finalize();
    let mac = Sha256::new()
        .chain_update(key.map(|b| b ^ 0x5c))
        .chain_update(inner)
        .finalize();
    format!(
        "v1={}",
        mac.iter().map(|b| format!("{b:02x}")).collect::<String>()
    )
}

async fn submit_with_callback(
    s: &TestServer,
    key: &str,
    form: Form,
    url: &str,
) -> reqwest::Response {
    s.client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key)
        .multipart(form.text("callback_url", url.to_string()))
        .send()
        .await
        .unwrap()
}

async fn job_of(s: &TestServer, id: &str) -> Value {
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}")))
        .bearer_auth("alice-key")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    r.json().await.unwrap()
}

/// Wait until the job's callback is no longer pending.
async fn settled(s: &TestServer, id: &str) -> Value {
    let start = Instant::now();
    loop {
        let job = job_of(s, id).await;
        if job["callback"]["state"] != "pending" {
            return job;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "{job}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

fn header<'a>(h: &'a HeaderMap, name: &str) -> &'a str {
    h.get(name).map(|v| v.to_str().unwrap()).unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_end_is_delivered_signed_after_retries_once() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(webhook_config(dir.path())).await;
    let (url, inbox) = receiver(2).await;
    let r = submit_with_callback(
        &s,
        "alice-key",
        folder_form(&repo_root().join("res/bump")),
        &url,
    )
    .await;
    assert_eq!(r.status(), 202);
    let job: Value = r.json().await.unwrap();
    assert_eq!(job["callback"]["state"], "pending");
    assert_eq!(job["callback"]["url"], url);
    let id = job["id"].as_str().unwrap().to_string();

    let job = settled(&s, &id).await;
    assert_eq!(job["status"], "succeeded");
    assert_eq!(job["callback"]["state"], "delivered", "{job}");
    let statuses: Vec<u64> = job["callback"]["attempts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["status"].as_u64().unwrap())
        .collect();
    assert_eq!(statuses, [500, 500, 204]);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let got = std::mem::take(&mut inbox.lock().unwrap().got);
    assert_eq!(got.len(), 3, "delivered once: no request after the 2xx");
    for (headers, body) in &got {
        let ts = header(headers, "webhook-timestamp");
        let age = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_secs() as i64
            - ts.parse::<i64>().unwrap();
        assert!((0..60).contains(&age), "timestamp {ts}");
        assert_eq!(
            header(headers, "webhook-signature"),
            expected_signature(SECRET, ts, body)
        );
        assert_ne!(
            header(headers, "webhook-signature"),
            expected_signature("another-secret", ts, body)
        );
        assert_eq!(header(headers, "webhook-id"), id);
        assert_eq!(header(headers, "content-type"), "application/json");
        let delivered: Value = serde_json::from_str(body).unwrap();
        assert_eq!(delivered["id"], id.as_str());
        assert_eq!(delivered["status"], "succeeded");
        assert!(delivered["artifacts"]["albedo.png"].is_string());
    }
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_job_is_delivered_once_and_disallowed_urls_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(webhook_config(dir.path())).await;
    let (url, inbox) = receiver(0).await;
    // Coplanar lights: accepted, then the solve fails.
    let mut form = Form::new().text(
        "lights",
        "a.png, 1, 0, 1\nb.png, -1, 0, 1\nc.png, 0.5, 0, 1",
    );
    for (i, n) in ["a.png", "b.png", "c.png"].iter().enumerate() {
        form = form.part(
            "images",
            Part::bytes(png(16, 16, 40 + i as u8 * 30)).file_name(*n),
        );
    }
    let r = submit_with_callback(&s, "alice-key", form, &url).await;
    assert_eq!(r.status(), 202);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let job = settled(&s, &id).await;
    assert_eq!(job["status"], "failed");
    assert_eq!(job["callback"]["state"], "delivered");
    assert_eq!(job["callback"]["attempts"].as_array().unwrap().len(), 1);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let got = std::mem::take(&mut inbox.lock().unwrap().got);
    assert_eq!(got.len(), 1);
    let body: Value = serde_json::from_str(&got[0].1).unwrap();
    assert_eq!(body["status"], "failed");
    assert_eq!(body["error"]["status"], 422);

    // Off the allow-list, other schemes, and a tenant without a secret: 422 at once.
    let bump = || folder_form(&repo_root().join("res/bump"));
    let port = url
        .split(':')
        .nth(2)
        .unwrap()
        .split('/')
        .next()
        .unwrap()
        .to_string();
    for (key, bad, needle) in [
        (
            "alice-key",
            format!("http://127.0.0.2:{port}/hook"),
            "allow-list",
        ),
        (
            "alice-key",
            format!("http://localhost:{port}/hook"),
            "allow-list",
        ),
        (
            "alice-key",
            "http://169.254.169.254/latest/meta-data".to_string(),
            "allow-list",
        ),
        (
            "alice-key",
            format!("https://127.0.0.1:{port}/hook"),
            "scheme",
        ),
        ("alice-key", "not a url".to_string(), "callback_url"),
        ("bob-key", url.clone(), "no webhook secret"),
    ] {
        let r = submit_with_callback(&s, key, bump(), &bad).await;
        expect_problem(r, 422, &[needle]).await;
    }
    let list: Value = s
        .client
        .get(s.url("/v1/jobs"))
        .bearer_auth("alice-key")
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["jobs"].as_array().unwrap().len(), 1, "no job was made");
    assert!(inbox.lock().unwrap().got.is_empty());
    s.stop().await;
}

/// Submit res/bump with a callback to `url` and wait until its first delivery attempt is
/// recorded; returns the job's id.
async fn first_attempt_made(s: &TestServer, url: &str) -> String {
    let r = submit_with_callback(
        s,
        "alice-key",
        folder_form(&repo_root().join("res/bump")),
        url,
    )
    .await;
    assert_eq!(r.status(), 202);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let start = Instant::now();
    loop {
        let job = job_of(s, &id).await;
        if !job["callback"]["attempts"].as_array().unwrap().is_empty() {
            assert_eq!(job["status"], "succeeded");
            assert_eq!(job["callback"]["state"], "pending", "{job}");
            return id;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "{job}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

fn statuses(job: &Value) -> Vec<u64> {
    job["callback"]["attempts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["status"].as_u64().unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_undelivered_callback_is_delivered_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = webhook_config(dir.path());
    // The next retry would come long after the stop: only the restart can deliver it.
    c.webhook_first_retry = Duration::from_secs(120);
    c.webhook_retry_for = Duration::from_secs(600);
    let (url, inbox) = receiver(usize::MAX).await;
    let s = TestServer::start(c.clone()).await;
    let id = first_attempt_made(&s, &url).await;
    s.stop().await;

    // The receiver recovers while the service is stopped.
    inbox.lock().unwrap().fail_first = 1;
    let s = TestServer::start(c).await;
    let job = settled(&s, &id).await;
    assert_eq!(job["callback"]["state"], "delivered", "{job}");
    assert_eq!(statuses(&job), [500, 204]);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let got = std::mem::take(&mut inbox.lock().unwrap().got);
    assert_eq!(got.len(), 2, "one attempt before the stop, one after");
    let (headers, body) = &got[1];
    let ts = header(headers, "webhook-timestamp");
    assert_eq!(
        header(headers, "webhook-signature"),
        expected_signature(SECRET, ts, body)
    );
    let delivered: Value = serde_json::from_str(body).unwrap();
    assert_eq!(delivered["id"], id.as_str());
    assert_eq!(delivered["status"], "succeeded");
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_callback_whose_retry_window_closed_during_a_stop_is_given_up() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = webhook_config(dir.path());
    c.webhook_first_retry = Duration::from_secs(120);
    c.webhook_retry_for = Duration::from_secs(600);
    let (url, inbox) = receiver(usize::MAX).await;
    let s = TestServer::start(c.clone()).await;
    let id = first_attempt_made(&s, &url).await;
    s.stop().await;

    // Restarted with a window that closed a second after the job ended.
    inbox.lock().unwrap().fail_first = 0;
    tokio::time::sleep(Duration::from_millis(1100)).await;
    c.webhook_retry_for = Duration::from_secs(1);
    let s = TestServer::start(c).await;
    let job = job_of(&s, &id).await;
    assert_eq!(job["callback"]["state"], "failed", "{job}");
    assert_eq!(statuses(&job), [500], "no attempt after the window");
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(inbox.lock().unwrap().got.len(), 1);
    s.stop().await;
}
