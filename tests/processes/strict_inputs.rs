//! Values the service must check before it works or stores anything, against the real
//! binary: calibration numbers and names, webhook ports and receivers' status lines,
//! duplicate `Authorization` headers, a stored record that cannot be read back, and an
//! `Idempotency-Key` replayed after its job or calibration was deleted.

use crate::binserver;
use crate::common;

use std::path::Path;
use std::time::{Duration, Instant};

use binserver::BinServer;
use common::{expect_problem, file_part, images_of, repo_root, synthetic_form};
use reqwest::header::AUTHORIZATION;
use reqwest::multipart::Form;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

const KEYS: &[&str] = &["--api-key", "alice:alice-key", "--api-key", "bob:bob-key"];

/// `res/chrome`'s sphere images and names, plus `extra` text parts.
fn chrome_form(extra: &[(&str, &str)]) -> Form {
    let dir = repo_root().join("res/chrome");
    let mut form = Form::new();
    for img in images_of(&dir) {
        form = form.part("images", file_part(&img));
    }
    let names = std::fs::read_to_string(dir.join("names.txt")).unwrap();
    let mut form = form.text("names", names);
    for (k, v) in extra {
        form = form.text(k.to_string(), v.to_string());
    }
    form
}

async fn post(s: &BinServer, path: &str, form: Form, key: &str) -> reqwest::Response {
    s.client
        .post(s.url(path))
        .bearer_auth(key)
        .multipart(form)
        .send()
        .await
        .unwrap()
}

async fn get(s: &BinServer, path: &str, key: &str) -> reqwest::Response {
    s.client
        .get(s.url(path))
        .bearer_auth(key)
        .send()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calibration_numbers_and_names_are_checked_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let s = BinServer::start(dir.path(), KEYS);
    for (value, needle) in [
        ("1e10", "focal_length"),
        ("1e300", "focal_length"),
        ("inf", "focal_length"),
        ("0.5", "focal_length"),
        ("-3", "focal_length"),
    ] {
        let r = post(
            &s,
            "/v1/calibrations",
            chrome_form(&[("focal_length", value)]),
            "alice-key",
        )
        .await;
        expect_problem(r, 422, &[needle]).await;
    }
    for circle in ["1e400,2,3", "10,10,NaN", "10,10"] {
        let r = post(
            &s,
            "/v1/calibrations",
            chrome_form(&[("circle", circle)]),
            "alice-key",
        )
        .await;
        expect_problem(r, 422, &["circle"]).await;
    }
    // Names a light table could not read back as themselves.
    let count = images_of(&repo_root().join("res/chrome")).len();
    for bad in ["a,b", "#1", "say \"hi\"", "tab\there"] {
        let names: String = (0..count)
            .map(|i| {
                if i == 3 {
                    bad.to_string()
                } else {
                    format!("L{i}")
                }
            })
            .collect::<Vec<_>>()
            .join("\n");
        let dir = repo_root().join("res/chrome");
        let mut form = Form::new();
        for img in images_of(&dir) {
            form = form.part("images", file_part(&img));
        }
        let r = post(
            &s,
            "/v1/calibrations",
            form.text("names", names),
            "alice-key",
        )
        .await;
        expect_problem(r, 422, &["names, line 4"]).await;
    }
    // Nothing was stored, and the listing answers.
    let list: Value = get(&s, "/v1/calibrations", "alice-key")
        .await
        .json()
        .await
        .unwrap();
    assert_eq!(list["calibrations"].as_array().unwrap().len(), 0, "{list}");
    // A long lens inside the range calibrates to finite directions.
    let r = post(
        &s,
        "/v1/calibrations",
        chrome_form(&[("focal_length", "1e7")]),
        "alice-key",
    )
    .await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let cal: Value = r.json().await.unwrap();
    for l in cal["lights"].as_array().unwrap() {
        for v in l["direction"].as_array().unwrap() {
            assert!(v.as_f64().is_some_and(f64::is_finite), "{l}");
        }
    }
}

/// Overwrite a column of the first row of `table` in the server's SQLite database.
fn corrupt(data_dir: &Path, sql: &str) {
    let db = rusqlite::Connection::open(data_dir.join("jobs.sqlite")).unwrap();
    assert_eq!(db.execute(sql, []).unwrap(), 1, "{sql}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_record_that_cannot_be_read_never_breaks_a_list() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = BinServer::start(dir.path(), KEYS);
    let mut cals = Vec::new();
    for _ in 0..2 {
        let r = post(&s, "/v1/calibrations", chrome_form(&[]), "alice-key").await;
        assert_eq!(r.status(), 201);
        cals.push(
            r.json::<Value>().await.unwrap()["id"]
                .as_str()
                .unwrap()
                .to_string(),
        );
    }
    let mut jobs = Vec::new();
    for _ in 0..2 {
        let r = post(&s, "/v1/jobs", synthetic_form(32, 4), "alice-key").await;
        assert_eq!(r.status(), 202);
        jobs.push(
            r.json::<Value>().await.unwrap()["id"]
                .as_str()
                .unwrap()
                .to_string(),
        );
    }
    s.terminate();
    s.wait_exit(Duration::from_secs(20)).expect("stopped");
    // What a bug or an older version could have left: numbers that are not numbers, a
    // status no version knows.
    corrupt(
        dir.path(),
        &format!(
            "UPDATE calibrations SET detail = json_set(detail, '$.lights[0].direction[0]', NULL) WHERE id = '{}'",
            cals[0]
        ),
    );
    corrupt(
        dir.path(),
        &format!("UPDATE jobs SET status = 'bogus' WHERE id = '{}'", jobs[0]),
    );
    let s = BinServer::start(dir.path(), KEYS);
    let r = get(&s, "/v1/calibrations", "alice-key").await;
    assert_eq!(r.status(), 200);
    let list: Value = r.json().await.unwrap();
    let ids: Vec<&str> = list["calibrations"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["id"].as_str().unwrap())
        .collect();
    assert_eq!(ids, [cals[1].as_str()], "the readable one only: {list}");
    let r = get(&s, "/v1/jobs", "alice-key").await;
    assert_eq!(r.status(), 200);
    let list: Value = r.json().await.unwrap();
    let ids: Vec<&str> = list["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["id"].as_str().unwrap())
        .collect();
    assert_eq!(ids, [jobs[1].as_str()], "{list}");
    let metrics = s.client.get(s.url("/metrics")).send().await.unwrap();
    let text = metrics.text().await.unwrap();
    let unreadable = text
        .lines()
        .find_map(|l| l.strip_prefix("photostereo_unreadable_records_total "))
        .and_then(|v| v.parse::<u64>().ok())
        .unwrap_or_else(|| panic!("no unreadable counter in\n{text}"));
    assert!(unreadable >= 2, "{unreadable}");
    assert!(s.logs().contains("cannot be read"), "{}", s.logs());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn webhook_ports_and_receivers_status_lines_are_read_strictly() {
    let dir = tempfile::tempdir().unwrap();
    let flags = [
        KEYS,
        &[
            "--webhook-allow-host",
            "127.0.0.1",
            "--webhook-secret",
            "alice:s3cret",
        ],
    ]
    .concat();
    let s = BinServer::start(dir.path(), &flags);
    for port in ["99999", "65616", "0", "65536"] {
        let form =
            synthetic_form(32, 4).text("callback_url", format!("http://127.0.0.1:{port}/hook"));
        let r = post(&s, "/v1/jobs", form, "alice-key").await;
        expect_problem(r, 422, &["callback_url", port]).await;
    }
    // A receiver whose status line has a four-digit code: not a 2xx answer.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", listener.local_addr().unwrap());
    let hits = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let counted = hits.clone();
    tokio::spawn(async move {
        loop {
            let Ok((mut conn, _)) = listener.accept().await else {
                return;
            };
            counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65536];
                let _ = tokio::time::timeout(Duration::from_millis(300), conn.read(&mut buf)).await;
                let _ = conn
                    .write_all(b"HTTP/1.1 2000 OK\r\nContent-Length: 0\r\n\r\n")
                    .await;
            });
        }
    });
    let form = synthetic_form(32, 4).text("callback_url", url);
    let r = post(&s, "/v1/jobs", form, "alice-key").await;
    assert_eq!(r.status(), 202);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let start = Instant::now();
    let job = loop {
        let job: Value = get(&s, &format!("/v1/jobs/{id}"), "alice-key")
            .await
            .json()
            .await
            .unwrap();
        if job["callback"]["attempts"]
            .as_array()
            .is_some_and(|a| !a.is_empty())
        {
            break job;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "{job}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(hits.load(std::sync::atomic::Ordering::SeqCst) >= 1);
    assert_ne!(job["callback"]["state"], "delivered", "{job}");
    let attempt = &job["callback"]["attempts"][0];
    assert!(attempt["status"].is_null(), "{attempt}");
    assert!(
        attempt["error"]
            .as_str()
            .unwrap_or_default()
            .contains("status line"),
        "{attempt}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_authorization_headers_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let s = BinServer::start(dir.path(), KEYS);
    for (first, second) in [
        ("Bearer alice-key", "Bearer bob-key"),
        ("Bearer nobody", "Bearer alice-key"),
        ("Bearer alice-key", "Bearer alice-key"),
    ] {
        let r = s
            .client
            .get(s.url("/v1/jobs"))
            .header(AUTHORIZATION, first)
            .header(AUTHORIZATION, second)
            .send()
            .await
            .unwrap();
        expect_problem(r, 400, &["one Authorization header"]).await;
    }
    let r = get(&s, "/v1/jobs", "alice-key").await;
    assert_eq!(r.status(), 200);
}

/// Post `form` with `key` as its Idempotency-Key; the answer's status and id.
async fn post_once(s: &BinServer, path: &str, form: Form, key: &str) -> (u16, String) {
    let r = s
        .client
        .post(s.url(path))
        .bearer_auth("alice-key")
        .header("Idempotency-Key", key)
        .multipart(form)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    let body: Value = r.json().await.unwrap();
    (status, body["id"].as_str().unwrap_or_default().to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idempotency_key_replays_only_while_its_resource_exists() {
    let dir = tempfile::tempdir().unwrap();
    let s = BinServer::start(dir.path(), KEYS);
    let (status, first) = post_once(&s, "/v1/jobs", synthetic_form(32, 4), "job-key").await;
    assert_eq!(status, 202);
    let (status, again) = post_once(&s, "/v1/jobs", synthetic_form(32, 4), "job-key").await;
    assert_eq!(
        (status, again.as_str()),
        (202, first.as_str()),
        "a replay while it exists"
    );
    let start = Instant::now();
    loop {
        let job: Value = get(&s, &format!("/v1/jobs/{first}"), "alice-key")
            .await
            .json()
            .await
            .unwrap();
        if job["status"] == "succeeded" {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "{job}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let r = s
        .client
        .delete(s.url(&format!("/v1/jobs/{first}")))
        .bearer_auth("alice-key")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    let (status, fresh) = post_once(&s, "/v1/jobs", synthetic_form(32, 4), "job-key").await;
    assert_eq!(status, 202);
    assert_ne!(
        fresh, first,
        "a fresh submission, not the deleted job's answer"
    );
    assert_eq!(
        get(&s, &format!("/v1/jobs/{fresh}"), "alice-key")
            .await
            .status(),
        200
    );
    // The key now stands for the fresh job.
    let (_, replayed) = post_once(&s, "/v1/jobs", synthetic_form(32, 4), "job-key").await;
    assert_eq!(replayed, fresh);

    let (status, cal) = post_once(&s, "/v1/calibrations", chrome_form(&[]), "cal-key").await;
    assert_eq!(status, 201);
    let r = s
        .client
        .delete(s.url(&format!("/v1/calibrations/{cal}")))
        .bearer_auth("alice-key")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    let (status, fresh) = post_once(&s, "/v1/calibrations", chrome_form(&[]), "cal-key").await;
    assert_eq!(status, 201);
    assert_ne!(fresh, cal);
    assert_eq!(
        get(&s, &format!("/v1/calibrations/{fresh}"), "alice-key")
            .await
            .status(),
        200
    );
}
