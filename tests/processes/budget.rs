//! The memory budget and the shared slots, against the real binary: concurrent re-shades
//! of a 2048² job stay within the budget and give their memory back; one tenant's slow
//! uploads leave another's jobs and calibrations room; a calibration whose client went
//! away keeps its slot until its work ends; a job that does not fit the budget waits in
//! the queue; /metrics and /readyz tell.

use crate::binserver;
use crate::common;

use std::time::{Duration, Instant};

use binserver::BinServer;
use common::{expect_problem, file_part, folder_form, images_of, repo_root, synthetic_form};
use reqwest::multipart::Form;
use serde_json::Value;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

const MB: u64 = 1 << 20;

/// The value of an unlabelled (or fully labelled) sample line in Prometheus text.
async fn metric(s: &BinServer, line_start: &str) -> u64 {
    let text = s
        .client
        .get(s.url("/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(line_start)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {line_start} in /metrics:\n{text}"))
}

/// Forget the server's peak resident size (VmHWM starts again from VmRSS).
fn reset_peak(s: &BinServer) {
    std::fs::write(format!("/proc/{}/clear_refs", s.pid()), "5").expect("clear_refs");
}

fn chrome_form() -> Form {
    let dir = repo_root().join("res/chrome");
    let mut form = Form::new();
    for img in images_of(&dir) {
        form = form.part("images", file_part(&img));
    }
    form.text(
        "names",
        std::fs::read_to_string(dir.join("names.txt")).unwrap(),
    )
}

/// 40 re-shades of a 2048² job at once: each answer is the right picture or 503 with
/// Retry-After; the server's peak stays within the budget (and far below 40 decoded
/// copies of the maps), and what they used is given back.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_reshades_stay_within_the_budget_and_give_memory_back() {
    const BUDGET_MB: u64 = 640;
    let dir = tempfile::tempdir().unwrap();
    let budget = format!("{BUDGET_MB}MiB");
    let flags = [
        "--workers",
        "1",
        "--memory-budget",
        &budget,
        "--max-pixels",
        "4194304",
        "--max-reshades",
        "2",
    ];
    let s = BinServer::start(dir.path(), &flags);
    let id = s.submit(synthetic_form(2048, 4)).await;
    s.wait_json(&format!("/v1/jobs/{id}"), Duration::from_secs(300), |v| {
        assert_ne!(v["status"], "failed", "{v}");
        v["status"] == "succeeded"
    })
    .await;
    let path = format!("/v1/jobs/{id}/artifacts/shaded.png?light=0.3,-0.2,0.93");
    let first = s.client.get(s.url(&path)).send().await.unwrap();
    assert_eq!(first.status(), 200);
    let expected = first.bytes().await.unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;

    reset_peak(&s);
    let before = s.memory_kb("VmRSS") * 1024;
    let started = Instant::now();
    let answers = futures_util::future::join_all((0..40).map(|_| {
        let (client, url) = (s.client.clone(), s.url(&path));
        async move {
            let r = client.get(url).send().await.unwrap();
            let status = r.status().as_u16();
            if status == 503 {
                assert!(
                    r.headers().contains_key("retry-after"),
                    "503 without Retry-After"
                );
                let body = expect_problem(r, 503, &["re-shade", "retry later"]).await;
                return (status, body.to_string().into_bytes().into());
            }
            (status, r.bytes().await.unwrap())
        }
    }))
    .await;
    let took = started.elapsed();
    let peak = s.memory_kb("VmHWM") * 1024;
    let served = answers.iter().filter(|(st, _)| *st == 200).count();
    for (status, body) in &answers {
        match status {
            200 => assert!(body == &expected, "a re-shade differs from the first"),
            503 => {}
            other => panic!("a re-shade answered {other}"),
        }
    }
    // Given back: the pictures' memory returns to the kernel once they are sent.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let after = s.memory_kb("VmRSS") * 1024;
    println!(
        "40 re-shades of 2048² in {took:?}: {served} served, {} refused (503); server RSS {} MB before, peak {} MB, {} MB after (budget {BUDGET_MB} MB)",
        40 - served,
        before / MB,
        peak / MB,
        after / MB
    );
    assert!(served >= 2, "only {served} re-shades were served");
    assert!(
        peak < BUDGET_MB * MB,
        "peak {} MB over the budget",
        peak / MB
    );
    assert!(
        peak < before + 96 * MB,
        "the re-shades took the server from {} MB to {} MB",
        before / MB,
        peak / MB
    );
    assert!(
        after < before + 24 * MB,
        "the re-shades left {} MB held ({} MB before)",
        after / MB,
        before / MB
    );

    // /metrics shows the budget, nothing reserved once they are done, and the refusals.
    let budget_line = "photostereo_memory_budget_bytes";
    assert_eq!(metric(&s, budget_line).await, BUDGET_MB * MB);
    let reserved = "photostereo_memory_reserved_bytes{use=\"reshade\"}";
    assert_eq!(metric(&s, reserved).await, 0);
    assert_eq!(
        metric(&s, "photostereo_memory_reserved_bytes{use=\"job\"}").await,
        0
    );
    let refused = "photostereo_slot_refusals_total{slots=\"reshade\",reason=\"full\"}";
    assert_eq!(metric(&s, refused).await, (40 - served) as u64);
}

const BOUNDARY: &str = "budgettestboundary";

/// An upload that sends its head and first part, then nothing: it holds an upload slot
/// until the upload time limit.
async fn slow_upload(addr: &str, key: &str) -> TcpStream {
    let mut stream = TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {key}\r\nContent-Type: multipart/form-data; boundary={BOUNDARY}\r\nTransfer-Encoding: chunked\r\n\r\n"
    );
    let part = format!(
        "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"lights\"\r\n\r\na.png, 0, 0, 1\r\n"
    );
    let chunk = format!("{head}{:x}\r\n{part}\r\n", part.len());
    stream.write_all(chunk.as_bytes()).await.unwrap();
    stream
}

/// One tenant opening 64 slow uploads (the default --max-uploads) holds only its share
/// of the slots: another tenant's job and calibration go through, and /readyz says ready
/// until the slots are really all taken.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn one_tenants_slow_uploads_leave_room_for_another() {
    let dir = tempfile::tempdir().unwrap();
    let (key_a, key_b) = ("key-of-tenant-a-1", "key-of-tenant-b-1");
    let (api_a, api_b) = (format!("a:{key_a}"), format!("b:{key_b}"));
    let flags = [
        "--api-key",
        &api_a,
        "--api-key",
        &api_b,
        "--upload-timeout",
        "60s",
        "--tenant-submissions-per-minute",
        "0",
    ];
    let s = BinServer::start(dir.path(), &flags);
    let mut held = Vec::new();
    for _ in 0..64 {
        held.push(slow_upload(s.addr(), key_a).await);
    }
    // Every slow upload has been looked at: those past the share were refused.
    let start = Instant::now();
    while metric(&s, "photostereo_uploads_receiving").await < 32
        || metric(
            &s,
            "photostereo_slot_refusals_total{slots=\"upload\",reason=\"tenant_share\"}",
        )
        .await
            < 32
    {
        assert!(start.elapsed() < Duration::from_secs(20), "{}", s.logs());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(metric(&s, "photostereo_uploads_receiving").await, 32);
    let r = s.client.get(s.url("/readyz")).send().await.unwrap();
    assert_eq!(r.status(), 200, "half the slots are free");

    // Tenant a's next upload is refused, naming its share; tenant b's job and
    // calibration are taken at once.
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key_a)
        .multipart(folder_form(&repo_root().join("res/bump")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.headers()["retry-after"], "5");
    expect_problem(r, 503, &["tenant a", "share"]).await;
    let started = Instant::now();
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key_b)
        .multipart(folder_form(&repo_root().join("res/bump")))
        .send()
        .await
        .unwrap();
    let job_took = started.elapsed();
    let body: Value = r.json().await.unwrap();
    assert_eq!(body["status"], "queued", "tenant b's job: {body}");
    let started = Instant::now();
    let r = s
        .client
        .post(s.url("/v1/calibrations"))
        .bearer_auth(key_b)
        .multipart(chrome_form())
        .send()
        .await
        .unwrap();
    let calibration_took = started.elapsed();
    let status = r.status();
    let body: Value = r.json().await.unwrap();
    assert_eq!(status, 201, "tenant b's calibration: {body}");
    println!(
        "with tenant a's 64 slow uploads open: tenant b's job accepted in {job_took:?}, its calibration made in {calibration_took:?}"
    );

    // Tenant b takes the other half: every slot is taken, and /readyz says so.
    let mut more = Vec::new();
    for _ in 0..32 {
        more.push(slow_upload(s.addr(), key_b).await);
    }
    let start = Instant::now();
    while metric(&s, "photostereo_uploads_receiving").await < 64 {
        assert!(start.elapsed() < Duration::from_secs(20), "{}", s.logs());
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let r = s.client.get(s.url("/readyz")).send().await.unwrap();
    expect_problem(r, 503, &["every upload slot is taken"]).await;
    drop(more);
    drop(held);
    let start = Instant::now();
    loop {
        let r = s.client.get(s.url("/readyz")).send().await.unwrap();
        if r.status() == 200 {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "not ready again");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// With --workers 1, a calibration whose client went away keeps the only calibration
/// slot, and its uploaded images, until its work ends: a second calibration waits for
/// it, and never two compute at once; the first's files go when its work ends.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_calibration_keeps_its_slot_after_its_client_goes_away() {
    const DELAY: Duration = Duration::from_secs(4);
    let dir = tempfile::tempdir().unwrap();
    let s = BinServer::start(dir.path(), &["--workers", "1", "--stage-delay", "4s"]);
    let impatient = reqwest::Client::builder()
        .timeout(Duration::from_millis(1500))
        .build()
        .unwrap();
    let gone = {
        let url = s.url("/v1/calibrations");
        tokio::spawn(async move { impatient.post(url).multipart(chrome_form()).send().await })
    };
    let start = Instant::now();
    while metric(&s, "photostereo_calibrations_computing").await < 1 {
        assert!(start.elapsed() < Duration::from_secs(10), "{}", s.logs());
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let first_started = Instant::now();
    assert!(gone.await.unwrap().is_err(), "the client was to give up");
    // Its client is gone; its work is not, and neither are its slot and its images.
    assert_eq!(metric(&s, "photostereo_calibrations_computing").await, 1);
    assert_eq!(metric(&s, "photostereo_calibration_slots_taken").await, 1);
    // Time for the server to see the client gone and drop what the request held.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let calibrations = dir.path().join("calibrations");
    let staged = calibration_dirs(&calibrations);
    assert_eq!(staged.len(), 1, "{staged:?}");
    let images = std::fs::read_dir(staged[0].join("files.partial"))
        .map(|d| d.count())
        .unwrap_or(0);
    assert!(
        images > 0,
        "the work's uploaded images were removed under it"
    );

    let second = {
        let (client, url) = (s.client.clone(), s.url("/v1/calibrations"));
        tokio::spawn(async move {
            let r = client.post(url).multipart(chrome_form()).send().await;
            (r.unwrap().status().as_u16(), Instant::now())
        })
    };
    let start = Instant::now();
    while metric(&s, "photostereo_calibrations_waiting").await < 1 {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "the second calibration did not wait: {}",
            s.logs()
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let (status, answered) = second.await.unwrap();
    assert_eq!(status, 201);
    let waited = answered - first_started;
    println!("the second calibration was answered {waited:?} after the first began");
    // The first's pause, then the second's own.
    assert!(
        waited >= 2 * DELAY - Duration::from_millis(300),
        "the second calibration ran beside the first: answered after {waited:?}"
    );
    assert_eq!(
        metric(&s, "photostereo_calibrations_computing_max").await,
        1
    );
    // The first's files go once its work has ended; the second's stay.
    let start = Instant::now();
    while calibration_dirs(&calibrations).contains(&staged[0]) {
        assert!(start.elapsed() < Duration::from_secs(5), "{}", s.logs());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(calibration_dirs(&calibrations).len(), 1);
}

/// The calibrations' directories under `root`.
fn calibration_dirs(root: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut dirs: Vec<_> = std::fs::read_dir(root)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    dirs.sort();
    dirs
}

/// A job whose estimated peak does not fit beside a calibration's reservation waits in
/// the queue (a worker does not start it) and runs once the calibration ends.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_job_waits_queued_for_room_in_the_budget() {
    let dir = tempfile::tempdir().unwrap();
    // A job of 320×240 (the chrome set's size) may need 104 B/px, a 32 MiB band and 16 MiB:
    // 56 MiB; a calibration more: two do not fit in 64 MiB.
    let flags = [
        "--memory-budget",
        "64MiB",
        "--max-pixels",
        "76800",
        "--stage-delay",
        "3s",
    ];
    let s = BinServer::start(dir.path(), &flags);
    let calibration = {
        let (client, url) = (s.client.clone(), s.url("/v1/calibrations"));
        tokio::spawn(async move {
            let r = client.post(url).multipart(chrome_form()).send().await;
            r.unwrap().status().as_u16()
        })
    };
    let start = Instant::now();
    while metric(&s, "photostereo_calibrations_computing").await < 1 {
        assert!(start.elapsed() < Duration::from_secs(10), "{}", s.logs());
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(metric(&s, "photostereo_memory_reserved_bytes{use=\"calibration\"}").await > 0);
    let id = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let job: Value = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        job["status"], "queued",
        "the job started beside the calibration: {job}"
    );
    assert!(metric(&s, "photostereo_memory_waits_total{use=\"job\"}").await >= 1);
    let r = s.client.get(s.url("/readyz")).send().await.unwrap();
    expect_problem(r, 503, &["memory budget"]).await;
    assert_eq!(calibration.await.unwrap(), 201);
    s.wait_json(&format!("/v1/jobs/{id}"), Duration::from_secs(120), |v| {
        assert_ne!(v["status"], "failed", "{v}");
        v["status"] == "succeeded"
    })
    .await;
}
