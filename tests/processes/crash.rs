//! Crash recovery of the real binary: `photostereo serve` is SIGKILLed at several points
//! (right after accepting jobs, while jobs run, in the middle of a slow upload, while
//! artifacts are being written, and at arbitrary moments), restarted on the same data
//! directory each time, and in the end every job that was answered 202 has succeeded
//! exactly once, with artifacts that decode. Meanwhile a watcher keeps downloading the
//! artifacts of succeeded jobs: a half-written artifact is never served, and an artifact
//! never changes once served.

use crate::binserver;
use crate::common;

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use binserver::BinServer;
use common::{archive_form, folder_form, repo_root, zip_folder};
use photostereo::core::outputs;
use reqwest::multipart::{Form, Part};
use serde_json::Value;

/// One worker, so that jobs queue up and a kill finds some queued and one running.
const FLAGS: &[&str] = &["--workers", "1", "--shutdown-grace", "1s"];

/// The job forms used, round-robin: three of the project's rendered sets (16- and 8-bit,
/// 4 and 24 images) as files and res/bump as a zip.
fn form(i: usize) -> Form {
    let res = repo_root().join("res");
    match i % 4 {
        0 => folder_form(&res.join("sphere")),
        1 => folder_form(&res.join("shadows-noisy")),
        2 => folder_form(&res.join("bump-noisy")),
        _ => archive_form(zip_folder(&res.join("bump"), Some("bump"))),
    }
}

/// Every job the server lists, following the cursor.
async fn list_all(client: &reqwest::Client, base: &str) -> Result<Vec<Value>, String> {
    let mut out = Vec::new();
    let mut url = format!("{base}/v1/jobs?limit=100");
    loop {
        let r = client.get(&url).send().await.map_err(|e| e.to_string())?;
        if r.status() != 200 {
            return Err(format!("GET {url}: {}", r.status()));
        }
        let page: Value = r.json().await.map_err(|e| e.to_string())?;
        out.extend(page["jobs"].as_array().cloned().unwrap_or_default());
        match page["next_cursor"].as_str() {
            Some(c) => url = format!("{base}/v1/jobs?limit=100&cursor={c}"),
            None => return Ok(out),
        }
    }
}

/// Whether a downloaded artifact is whole: PNG and EXR decode, JSON parses, GLB's header
/// length matches.
fn check_artifact(name: &str, bytes: &[u8]) -> Result<(), String> {
    let ext = name.rsplit('.').next().unwrap_or_default();
    match ext {
        "png" => image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
            .map(|_| ())
            .map_err(|e| e.to_string()),
        // height.exr has one channel `Y`, which the image crate does not read.
        "exr" if name == "height.exr" => outputs::decode_height_exr(bytes)
            .map(|_| ())
            .map_err(|e| e.to_string()),
        "exr" => image::load_from_memory_with_format(bytes, image::ImageFormat::OpenExr)
            .map(|_| ())
            .map_err(|e| e.to_string()),
        "json" | "gltf" => serde_json::from_slice::<Value>(bytes)
            .map(|_| ())
            .map_err(|e| e.to_string()),
        "glb" => {
            let ok = bytes.len() >= 12
                && &bytes[..4] == b"glTF"
                && u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize == bytes.len();
            ok.then_some(()).ok_or_else(|| "bad glb header".to_string())
        }
        other => Err(format!("unexpected artifact type {other}")),
    }
}

/// Downloads the artifacts of succeeded jobs over and over, across restarts (it follows
/// `base`), recording any artifact that does not decode or that changes.
struct Watcher {
    base: Arc<Mutex<String>>,
    stop: Arc<AtomicBool>,
    failures: Arc<Mutex<Vec<String>>>,
    seen: Arc<Mutex<HashMap<(String, String), String>>>,
    task: tokio::task::JoinHandle<()>,
}

impl Watcher {
    fn start() -> Self {
        let base = Arc::new(Mutex::new(String::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let failures = Arc::new(Mutex::new(Vec::new()));
        let seen: Arc<Mutex<HashMap<(String, String), String>>> = Arc::default();
        let (b, st, f, sn) = (base.clone(), stop.clone(), failures.clone(), seen.clone());
        let task = tokio::spawn(async move {
            let client = reqwest::Client::builder()
                .timeout(Duration::from_secs(10))
                .build()
                .unwrap();
            while !st.load(Ordering::SeqCst) {
                let base = b.lock().unwrap().clone();
                if !base.is_empty() {
                    watch_once(&client, &base, &f, &sn).await;
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        });
        Self {
            base,
            stop,
            failures,
            seen,
            task,
        }
    }

    fn follow(&self, s: &BinServer) {
        *self.base.lock().unwrap() = s.base.clone();
    }

    async fn finish(self) -> (Vec<String>, usize) {
        self.stop.store(true, Ordering::SeqCst);
        self.task.await.unwrap();
        let failures = self.failures.lock().unwrap().clone();
        let checked = self.seen.lock().unwrap().len();
        (failures, checked)
    }
}

/// One pass: every artifact of every succeeded job not checked yet. Transport errors (the
/// server being killed) are ignored; a complete 200 answer must be a whole artifact.
async fn watch_once(
    client: &reqwest::Client,
    base: &str,
    failures: &Mutex<Vec<String>>,
    seen: &Mutex<HashMap<(String, String), String>>,
) {
    let Ok(jobs) = list_all(client, base).await else {
        return;
    };
    for job in jobs {
        if job["status"] != "succeeded" {
            continue;
        }
        let id = job["id"].as_str().unwrap().to_string();
        let Some(artifacts) = job["artifacts"].as_object() else {
            failures
                .lock()
                .unwrap()
                .push(format!("{id}: succeeded without artifacts"));
            continue;
        };
        for (name, url) in artifacts {
            let key = (id.clone(), name.clone());
            if seen.lock().unwrap().contains_key(&key) {
                continue;
            }
            let Ok(r) = client
                .get(format!("{base}{}", url.as_str().unwrap()))
                .send()
                .await
            else {
                return;
            };
            if r.status() != 200 {
                failures
                    .lock()
                    .unwrap()
                    .push(format!("{id}/{name}: {}", r.status()));
                continue;
            }
            let etag = r.headers()["etag"].to_str().unwrap().to_string();
            let Ok(bytes) = r.bytes().await else {
                return; // cut off by a kill
            };
            if let Err(e) = check_artifact(name, &bytes) {
                failures
                    .lock()
                    .unwrap()
                    .push(format!("{id}/{name} served broken: {e}"));
            }
            seen.lock().unwrap().insert(key, etag);
        }
    }
}

/// Job directories that hold a directory called `what` with at least `min_files` files.
fn partial_dirs(data: &Path, what: &str, min_files: usize) -> Vec<String> {
    let Ok(jobs) = std::fs::read_dir(data.join("jobs")) else {
        return Vec::new();
    };
    jobs.filter_map(|e| {
        let dir = e.ok()?.path().join(what);
        let n = std::fs::read_dir(&dir).ok()?.count();
        (n >= min_files).then(|| dir.display().to_string())
    })
    .collect()
}

/// Poll until `cond` holds (checked every millisecond); false on timeout.
async fn until(timeout: Duration, mut cond: impl FnMut() -> bool) -> bool {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if cond() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    false
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_at_any_point_loses_no_accepted_job_and_serves_no_torn_artifact() {
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path();
    let watcher = Watcher::start();
    let mut accepted: Vec<String> = Vec::new();
    let mut next_form = 0;
    let mut kills: Vec<String> = Vec::new();

    // 1. Right after accepting jobs.
    let mut s = BinServer::start(data, FLAGS);
    watcher.follow(&s);
    for _ in 0..4 {
        accepted.push(s.submit(form(next_form)).await);
        next_form += 1;
    }
    s.kill();
    kills.push("right after four 202s".into());

    // 2. While a job runs (its stage past decoding).
    let mut s = BinServer::start(data, FLAGS);
    watcher.follow(&s);
    let running = s
        .wait_json("/v1/jobs?limit=100", Duration::from_secs(20), |page| {
            page["jobs"].as_array().unwrap().iter().any(|j| {
                j["status"] == "running"
                    && matches!(j["stage"].as_str(), Some("solve" | "mask" | "integrate"))
            })
        })
        .await;
    s.kill();
    let interrupted: Vec<String> = running["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|j| j["status"] == "running")
        .map(|j| j["id"].as_str().unwrap().to_string())
        .collect();
    kills.push(format!("while {interrupted:?} ran"));

    // 3. In the middle of a slow streamed upload.
    let mut s = BinServer::start(data, FLAGS);
    watcher.follow(&s);
    for _ in 0..2 {
        accepted.push(s.submit(form(next_form)).await);
        next_form += 1;
    }
    let png = std::fs::read(repo_root().join("res/bump-noisy/im1.png")).unwrap();
    let trickle = futures_util::stream::unfold(0usize, move |i| {
        let png = png.clone();
        async move {
            if i > 0 {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            let chunk = png.get(i * 256..((i + 1) * 256).min(png.len()))?.to_vec();
            Some((Ok::<_, std::io::Error>(chunk), i + 1))
        }
    });
    let slow_form = Form::new()
        .text(
            "lights",
            "im1.png, 0, 0, 1\nim2.png, 1, 0, 1\nim3.png, 0, 1, 1",
        )
        .part(
            "images",
            Part::stream(reqwest::Body::wrap_stream(trickle)).file_name("im1.png"),
        );
    let upload = tokio::spawn({
        let (client, url) = (s.client.clone(), s.url("/v1/jobs"));
        async move { client.post(url).multipart(slow_form).send().await }
    });
    assert!(
        until(Duration::from_secs(10), || !partial_dirs(
            data,
            "input.partial",
            1
        )
        .is_empty())
        .await,
        "the slow upload never reached the disk"
    );
    s.kill();
    let answer = upload.await.unwrap();
    assert!(
        answer.as_ref().map(|r| r.status() != 202).unwrap_or(true),
        "a killed upload was accepted: {answer:?}"
    );
    kills.push("in the middle of a slow upload".into());

    // 4. While a job's artifacts are being written.
    let mut s = BinServer::start(data, FLAGS);
    watcher.follow(&s);
    for _ in 0..2 {
        accepted.push(s.submit(form(next_form)).await);
        next_form += 1;
    }
    assert!(
        until(Duration::from_secs(20), || !partial_dirs(
            data,
            "output.partial",
            1
        )
        .is_empty())
        .await,
        "no job wrote artifacts within 20 s"
    );
    let writing = partial_dirs(data, "output.partial", 1);
    s.kill();
    kills.push(format!("while writing {writing:?}"));

    // 5. At arbitrary moments, each with a fresh job on top.
    for delay_ms in [40u64, 230, 470, 820] {
        let mut s = BinServer::start(data, FLAGS);
        watcher.follow(&s);
        accepted.push(s.submit(form(next_form)).await);
        next_form += 1;
        tokio::time::sleep(Duration::from_millis(delay_ms)).await;
        s.kill();
        kills.push(format!("{delay_ms} ms after a submission"));
    }

    // The last start runs everything that is left.
    let s = BinServer::start(data, FLAGS);
    watcher.follow(&s);
    let expected: HashSet<&str> = accepted.iter().map(String::as_str).collect();
    assert_eq!(expected.len(), accepted.len(), "job ids are unique");
    let finished = s
        .wait_json("/v1/jobs?limit=100", Duration::from_secs(60), |page| {
            page["jobs"].as_array().unwrap().iter().all(|j| {
                matches!(
                    j["status"].as_str(),
                    Some("succeeded" | "failed" | "cancelled")
                )
            })
        })
        .await;
    assert!(finished["next_cursor"].is_null());
    let jobs = list_all(&s.client, &s.base).await.unwrap();
    let mut by_id: BTreeMap<String, usize> = BTreeMap::new();
    for j in &jobs {
        *by_id
            .entry(j["id"].as_str().unwrap().to_string())
            .or_default() += 1;
        assert_eq!(
            j["status"],
            "succeeded",
            "job {j} did not succeed; kills: {kills:?}\n{}",
            s.logs()
        );
    }
    assert!(
        by_id.values().all(|&n| n == 1),
        "a job is listed twice: {by_id:?}"
    );
    for id in &accepted {
        assert!(
            by_id.contains_key(id),
            "accepted job {id} is gone; kills: {kills:?}"
        );
    }
    // The only jobs besides the accepted ones could be submissions cut off between their
    // record and their 202; none of the kills above lands there.
    assert_eq!(jobs.len(), accepted.len(), "{by_id:?}");
    let retried = jobs
        .iter()
        .filter(|j| j["attempts"].as_u64().unwrap() >= 2)
        .count();
    assert!(retried >= 1, "no job was interrupted while running");

    // Every artifact of every job decodes now, and none changed since the watcher saw it.
    let mut downloaded = 0;
    for j in &jobs {
        let id = j["id"].as_str().unwrap();
        for (name, url) in j["artifacts"].as_object().unwrap() {
            let r = s
                .client
                .get(s.url(url.as_str().unwrap()))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200, "{id}/{name}");
            let etag = r.headers()["etag"].to_str().unwrap().to_string();
            let bytes = r.bytes().await.unwrap();
            check_artifact(name, &bytes).unwrap_or_else(|e| panic!("{id}/{name}: {e}"));
            if let Some(before) = watcher
                .seen
                .lock()
                .unwrap()
                .get(&(id.to_string(), name.clone()))
            {
                assert_eq!(before, &etag, "{id}/{name} changed after it was served");
            }
            downloaded += 1;
        }
    }

    // Nothing half-done is left on disk: no staging directories, inputs removed.
    let leftovers: Vec<String> = ["input.partial", "output.partial", "input"]
        .iter()
        .flat_map(|what| partial_dirs(data, what, 0))
        .collect();
    assert!(leftovers.is_empty(), "left on disk: {leftovers:?}");
    let dirs = std::fs::read_dir(data.join("jobs")).unwrap().count();
    assert_eq!(dirs, accepted.len(), "one directory per job");

    // A kill between recording a job's end and removing its inputs, staged by hand: the
    // next start removes them.
    drop(s);
    let stale = data.join("jobs").join(&accepted[0]).join("input");
    std::fs::create_dir(&stale).unwrap();
    std::fs::write(stale.join("000.img"), b"left over").unwrap();
    let s = BinServer::start(data, FLAGS);
    assert!(
        !stale.exists(),
        "inputs of a finished job survive a restart"
    );
    assert_eq!(
        list_all(&s.client, &s.base).await.unwrap().len(),
        accepted.len()
    );

    let (failures, watched) = watcher.finish().await;
    assert!(failures.is_empty(), "served while crashing: {failures:?}");
    println!(
        "{} jobs, {} kills ({}), {retried} jobs run more than once, {watched} artifacts watched, {downloaded} checked at the end, {:.1} s",
        accepted.len(),
        kills.len(),
        kills.join("; "),
        started.elapsed().as_secs_f64()
    );
    drop(s);
}
