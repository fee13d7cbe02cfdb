//! `--store s3://…` against a real S3 server (SeaweedFS `weed mini`, see
//! `common/weed.rs`): the store keeps the contract the data directory's keeps
//! (`store::contract`), jobs and calibrations whose bytes live in the bucket answer
//! exactly as on the data directory, the objects are really there and go with DELETE and
//! retention, and an outage answers 503 with Retry-After while accepted jobs wait it out.

use crate::common;
use crate::common::weed;

use std::collections::BTreeSet;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use common::*;
use photostereo::core::synth::ChromeSet;
use photostereo::service::Config;
use reqwest::multipart::Form;
use serde_json::Value;
use weed::{Weed, keys};

/// A server whose store is `prefix` in the weed bucket.
async fn s3_server(
    weed: &Weed,
    data: &Path,
    prefix: &str,
    tune: impl FnOnce(&mut Config),
) -> TestServer {
    let mut c = config(data);
    c.store = Some(weed.store_url(prefix));
    tune(&mut c);
    let _env = weed::ENV.lock().await;
    weed.set_env();
    TestServer::start(c).await
}

async fn get(s: &TestServer, path: &str, headers: &[(&str, &str)]) -> reqwest::Response {
    let mut r = s.client.get(s.url(path));
    for (k, v) in headers {
        r = r.header(*k, *v);
    }
    r.send().await.unwrap()
}

async fn bytes_of(s: &TestServer, path: &str) -> Vec<u8> {
    let r = get(s, path, &[]).await;
    assert_eq!(r.status(), 200, "GET {path}");
    r.bytes().await.unwrap().to_vec()
}

fn artifact_names(job: &Value) -> Vec<String> {
    job["artifacts"]
        .as_object()
        .unwrap()
        .keys()
        .cloned()
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_and_calibrations_in_s3_answer_as_on_the_data_directory() {
    let Some(weed) = Weed::start("jobs_and_calibrations_in_s3_answer_as_on_the_data_directory")
    else {
        return;
    };
    let bucket = weed.bucket();
    let (dir_data, s3_data) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let local = TestServer::start(config(dir_data.path())).await;
    // Stages last a while, so that the job's inputs can be seen in the bucket as it runs.
    let s3 = s3_server(&weed, s3_data.path(), "same", |c| {
        c.stage_delay = Duration::from_millis(300)
    })
    .await;

    let bump = repo_root().join("res/bump");
    let options = r#"{"outputs": ["albedo.png", "normal.png", "normal.exr", "height.exr", "mesh.glb", "result.json"]}"#;
    let on_dir = local
        .submit(folder_form(&bump).text("options", options))
        .await;
    let on_s3 = s3.submit(folder_form(&bump).text("options", options)).await;
    let (dir_id, s3_id) = (
        on_dir["id"].as_str().unwrap().to_string(),
        on_s3["id"].as_str().unwrap().to_string(),
    );
    // The inputs are objects (manifest last), and nothing of the job is on local disk
    // but the scratch copy of the running job.
    let inputs = keys(&bucket, &format!("same/jobs/{s3_id}/input")).await;
    let expect: BTreeSet<String> = [
        "000.img",
        "001.img",
        "002.img",
        "003.img",
        "lights.txt",
        "manifest.json",
    ]
    .iter()
    .map(|f| format!("same/jobs/{s3_id}/input/{f}"))
    .collect();
    assert_eq!(inputs, expect, "the job's inputs in the bucket");
    assert!(
        !s3_data.path().join("jobs").exists(),
        "no data-directory job files"
    );

    let dir_job = local.wait_succeeded(&dir_id).await;
    let s3_job = s3.wait_succeeded(&s3_id).await;
    let names = artifact_names(&s3_job);
    assert_eq!(names, artifact_names(&dir_job));
    assert_eq!(names.len(), 6, "{names:?}");

    // The artifacts are objects under one attempt's key; the inputs go once the worker
    // has recorded the job's end.
    let inputs_gone = std::time::Instant::now() + Duration::from_secs(10);
    while !keys(&bucket, &format!("same/jobs/{s3_id}/input"))
        .await
        .is_empty()
    {
        assert!(
            std::time::Instant::now() < inputs_gone,
            "inputs still stored"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let stored = keys(&bucket, &format!("same/jobs/{s3_id}")).await;
    let attempts: BTreeSet<&str> = stored
        .iter()
        .map(|k| {
            let rest = k
                .strip_prefix(&format!("same/jobs/{s3_id}/outputs/"))
                .unwrap_or_else(|| panic!("only outputs stay after success: {k}"));
            rest.split('/').next().unwrap()
        })
        .collect();
    assert_eq!(attempts.len(), 1, "one attempt's outputs: {stored:?}");
    let attempt = attempts.into_iter().next().unwrap().to_string();
    let listed: BTreeSet<String> = names
        .iter()
        .map(|n| format!("same/jobs/{s3_id}/outputs/{attempt}/{n}"))
        .collect();
    assert_eq!(stored, listed);
    eprintln!("objects of job {s3_id}: {stored:?}");

    // Downloads: whole, ranges, 304, 416, exactly as the directory store's.
    for name in &names {
        let from_s3 = bytes_of(&s3, &format!("/v1/jobs/{s3_id}/artifacts/{name}")).await;
        let from_dir = bytes_of(&local, &format!("/v1/jobs/{dir_id}/artifacts/{name}")).await;
        if name != "result.json" {
            // result.json holds the job's timings.
            assert!(from_s3 == from_dir, "{name} differs between the stores");
        }
        let path = format!("/v1/jobs/{s3_id}/artifacts/{name}");
        let whole = get(&s3, &path, &[]).await;
        let etag = whole.headers()["etag"].to_str().unwrap().to_string();
        assert_eq!(
            whole.headers()["cache-control"],
            "private, max-age=31536000, immutable"
        );
        assert_eq!(whole.headers()["accept-ranges"], "bytes");
        let len = from_s3.len();
        assert!(len > 100, "{name}: {len} bytes");
        let part = get(&s3, &path, &[("range", "bytes=10-99")]).await;
        assert_eq!(part.status(), 206, "{name}");
        assert_eq!(
            part.headers()["content-range"],
            format!("bytes 10-99/{len}").as_str()
        );
        assert_eq!(part.headers()["etag"], etag.as_str());
        assert_eq!(&part.bytes().await.unwrap()[..], &from_s3[10..100]);
        let tail = get(&s3, &path, &[("range", "bytes=-7")]).await;
        assert_eq!(tail.status(), 206);
        assert_eq!(&tail.bytes().await.unwrap()[..], &from_s3[len - 7..]);
        let past = get(&s3, &path, &[("range", &format!("bytes={len}-"))]).await;
        assert_eq!(past.status(), 416);
        assert_eq!(
            past.headers()["content-range"],
            format!("bytes */{len}").as_str()
        );
        let cached = get(&s3, &path, &[("if-none-match", &etag)]).await;
        assert_eq!(cached.status(), 304);
        // The directory store serves ranges the same way.
        let dir_part = get(
            &local,
            &format!("/v1/jobs/{dir_id}/artifacts/{name}"),
            &[("range", "bytes=10-99")],
        )
        .await;
        assert_eq!(dir_part.status(), 206);
    }
    let shade = "/artifacts/shaded.png?light=0.3,-0.2,1";
    assert!(
        bytes_of(&s3, &format!("/v1/jobs/{s3_id}{shade}")).await
            == bytes_of(&local, &format!("/v1/jobs/{dir_id}{shade}")).await,
        "re-shading from the bucket"
    );

    // DELETE removes the job's objects.
    let r = s3
        .client
        .delete(s3.url(&format!("/v1/jobs/{s3_id}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    assert!(
        keys(&bucket, &format!("same/jobs/{s3_id}"))
            .await
            .is_empty()
    );

    // A calibration's files are objects, served from the bucket, used by jobs, deleted
    // with it.
    let chrome = ChromeSet::standard(8, 71);
    let sphere = tempfile::tempdir().unwrap();
    chrome.write(sphere.path(), None).unwrap();
    let (object, truth) = sphere_under(&chrome.lights);
    let mut normals = Vec::new();
    for s in [&s3, &local] {
        let form = images_of(sphere.path())
            .iter()
            .fold(Form::new(), |f, p| f.part("images", file_part(p)))
            .text(
                "names",
                std::fs::read_to_string(sphere.path().join("names.txt")).unwrap(),
            );
        let r = s
            .client
            .post(s.url("/v1/calibrations"))
            .multipart(form)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
        let cal: Value = r.json().await.unwrap();
        let cal_id = cal["id"].as_str().unwrap().to_string();
        let job = images_of(object.path())
            .iter()
            .fold(Form::new(), |f, p| f.part("images", file_part(p)))
            .text("calibration", cal_id.clone())
            .text("options", r#"{"outputs": ["normal.exr"]}"#);
        let job = s.submit(job).await;
        let id = job["id"].as_str().unwrap().to_string();
        s.wait_succeeded(&id).await;
        normals.push(bytes_of(s, &format!("/v1/jobs/{id}/artifacts/normal.exr")).await);
        let csv = bytes_of(s, &format!("/v1/calibrations/{cal_id}/lights.csv")).await;
        let part = get(
            s,
            &format!("/v1/calibrations/{cal_id}/lights.csv"),
            &[("range", "bytes=0-3")],
        )
        .await;
        assert_eq!(part.status(), 206);
        assert_eq!(&part.bytes().await.unwrap()[..], &csv[..4]);
        if std::ptr::eq(s, &s3) {
            let files = keys(&bucket, &format!("same/calibrations/{cal_id}")).await;
            let expect: BTreeSet<String> = ["lights.csv", "lights.png", "overlay.png"]
                .iter()
                .map(|f| format!("same/calibrations/{cal_id}/{f}"))
                .collect();
            assert_eq!(files, expect);
            let r = s
                .client
                .delete(s.url(&format!("/v1/calibrations/{cal_id}")))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 204);
            assert!(
                keys(&bucket, &format!("same/calibrations/{cal_id}"))
                    .await
                    .is_empty()
            );
        }
    }
    assert!(
        normals[0] == normals[1],
        "the calibrated job's normals differ between the stores"
    );
    let n = image::load_from_memory_with_format(&normals[0], image::ImageFormat::OpenExr)
        .unwrap()
        .to_rgb32f();
    let mut errors = Vec::new();
    for ((r, c), &m) in truth.mask.indexed_iter() {
        if m {
            let p = n.get_pixel(c as u32, r as u32).0;
            let got = [p[0] as f64, -p[1] as f64, p[2] as f64];
            let t = [0, 1, 2].map(|k| truth.normals[[r, c, k]] as f64);
            let d: f64 = (0..3).map(|k| got[k] * t[k]).sum();
            errors.push(d.clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    eprintln!(
        "job with an S3-stored calibration: mean normal error {mean:.3}° over {} pixels",
        errors.len()
    );
    assert!(mean < 1.0, "mean normal error {mean}°");

    s3.stop().await;
    local.stop().await;

    // Retention deletes the expired job's objects.
    let data = tempfile::tempdir().unwrap();
    let s = s3_server(&weed, data.path(), "expiring", |c| {
        c.retention = Duration::from_secs(1);
        c.sweep_interval = Duration::from_millis(200);
    })
    .await;
    let job = s.submit(folder_form(&bump)).await;
    let id = job["id"].as_str().unwrap().to_string();
    s.wait_succeeded(&id).await;
    assert!(
        !keys(&bucket, &format!("expiring/jobs/{id}"))
            .await
            .is_empty()
    );
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        let gone = get(&s, &format!("/v1/jobs/{id}"), &[]).await.status() == 404;
        if gone
            && keys(&bucket, &format!("expiring/jobs/{id}"))
                .await
                .is_empty()
        {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "job {id} not expired with its objects"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_down_refuses_submissions_with_503_and_accepted_jobs_wait_it_out() {
    let Some(mut weed) =
        Weed::start("s3_down_refuses_submissions_with_503_and_accepted_jobs_wait_it_out")
    else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let s = s3_server(&weed, data.path(), "outage", |c| {
        c.workers = 1;
        c.stage_delay = Duration::from_millis(400);
    })
    .await;
    let bump = repo_root().join("res/bump");
    let a = s.submit(folder_form(&bump)).await;
    let b = s.submit(folder_form(&bump)).await;
    let weed_stopped = tokio::task::block_in_place(|| {
        weed.stop();
        std::time::Instant::now()
    });

    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(folder_form(&bump))
        .send()
        .await
        .unwrap();
    assert!(r.headers().contains_key("retry-after"), "{:?}", r.headers());
    expect_problem(r, 503, &["storage", "retry"]).await;
    let ready = get(&s, "/readyz", &[]).await;
    assert_eq!(ready.status(), 503);
    // Long enough for both jobs to meet the outage (each stage lasts 400 ms).
    tokio::time::sleep(Duration::from_secs(4).saturating_sub(weed_stopped.elapsed())).await;
    for id in [&a, &b] {
        let job = s
            .get_json(&format!("/v1/jobs/{}", id["id"].as_str().unwrap()))
            .await;
        assert!(
            matches!(job["status"].as_str(), Some("queued" | "running")),
            "an accepted job waits for the store: {job}"
        );
    }
    tokio::task::block_in_place(|| weed.restart());

    let mut attempts = Vec::new();
    for id in [&a, &b] {
        let id = id["id"].as_str().unwrap();
        let job = s.wait_succeeded(id).await;
        attempts.push(job["attempts"].as_u64().unwrap());
        for name in artifact_names(&job) {
            bytes_of(&s, &format!("/v1/jobs/{id}/artifacts/{name}")).await;
        }
    }
    eprintln!("attempts of the two jobs accepted before the outage: {attempts:?}");
    assert!(
        attempts.iter().any(|a| *a >= 2),
        "a job met the outage and ran again: {attempts:?}"
    );
    assert_eq!(get(&s, "/readyz", &[]).await.status(), 200);
    let c = s.submit(folder_form(&bump)).await;
    s.wait_succeeded(c["id"].as_str().unwrap()).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_file_larger_than_a_part_goes_up_in_parts_and_comes_back_whole() {
    use photostereo::service::store::{BlobStore, PART_BYTES, S3Store};
    let Some(weed) = Weed::start("a_file_larger_than_a_part_goes_up_in_parts_and_comes_back_whole")
    else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let store = {
        let _env = weed::ENV.lock().await;
        weed.set_env();
        let scratch = data.path().join("scratch");
        let rt = tokio::runtime::Handle::current();
        Arc::new(
            S3Store::open(
                &weed.store_url("parts"),
                &scratch,
                rt,
                Duration::from_secs(3600),
            )
            .unwrap(),
        )
    };
    let id = uuid::Uuid::new_v4();
    // Two and a half parts of bytes that do not repeat with the part size.
    let big: Vec<u8> = (0..PART_BYTES * 5 / 2)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    let (s, b) = (store.clone(), big.clone());
    tokio::task::spawn_blocking(move || {
        let staged = s.stage_inputs(id).unwrap();
        std::fs::write(staged.join("000.img"), &b).unwrap();
        std::fs::write(staged.join("manifest.json"), b"{}").unwrap();
        s.commit_inputs(id).unwrap();
        assert!(!staged.exists(), "the staged copy goes once committed");
    })
    .await
    .unwrap();
    let bucket = weed.bucket();
    let key = object_store::path::Path::from(format!("parts/jobs/{id}/input/000.img"));
    let meta = object_store::ObjectStoreExt::head(&*bucket, &key)
        .await
        .unwrap();
    assert_eq!(meta.size, big.len() as u64);
    let etag = meta.e_tag.unwrap_or_default();
    eprintln!("{key}: {} bytes, ETag {etag}", meta.size);
    assert!(
        etag.trim_matches('"').ends_with("-3"),
        "a 3-part multipart upload: {etag}"
    );
    let s = store.clone();
    tokio::task::spawn_blocking(move || {
        assert!(s.has_inputs(id).unwrap());
        // A worker that has the image already (its upload's scan) fetches the rest only.
        let dir = s.fetch_inputs(id, &|name| name == "000.img").unwrap();
        assert!(dir.join("manifest.json").is_file());
        assert!(
            !dir.join("000.img").exists(),
            "a file the worker has is not fetched"
        );
        let dir = s.fetch_inputs(id, &|_| false).unwrap();
        assert!(
            std::fs::read(dir.join("000.img")).unwrap() == big,
            "fetched back whole"
        );
        s.remove_job(id).unwrap();
        assert!(!s.has_inputs(id).unwrap());
    })
    .await
    .unwrap();
    assert!(keys(&bucket, &format!("parts/jobs/{id}")).await.is_empty());
}

/// The store's contract (the same suite the data directory's store runs in its unit
/// tests), on a prefix of its own in the bucket.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_keeps_the_store_contract() {
    use photostereo::service::store::{S3Store, contract};
    let Some(weed) = Weed::start("s3_keeps_the_store_contract") else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let rt = tokio::runtime::Handle::current();
    let store = {
        let _env = weed::ENV.lock().await;
        weed.set_env();
        // Settled at once: a start may take any job's objects for leftovers.
        S3Store::open(
            &weed.store_url("contract"),
            &data.path().join("scratch"),
            rt.clone(),
            Duration::ZERO,
        )
        .unwrap()
    };
    tokio::task::spawn_blocking(move || contract::run(&store, &rt))
        .await
        .unwrap();
}
