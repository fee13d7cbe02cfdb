//! Calibrations over HTTP: `POST /v1/calibrations` on rendered chrome-sphere captures
//! against their true lights, the files it keeps, its errors, tenants, idempotency, a
//! restart, and jobs that take a calibration's lights instead of a light table.

use crate::common;

use std::path::Path;

use common::*;
use photostereo::core::lights;
use photostereo::core::synth::ChromeSet;
use reqwest::Method;
use reqwest::multipart::{Form, Part};
use serde_json::Value;

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d: f64 = (0..3).map(|k| a[k] * b[k]).sum();
    d.clamp(-1.0, 1.0).acos().to_degrees()
}

fn direction(light: &Value) -> [f64; 3] {
    let d = light["direction"].as_array().unwrap();
    [0, 1, 2].map(|k| d[k].as_f64().unwrap())
}

/// The sphere images of a chrome folder (every PNG, in name order) and its `names.txt`.
fn chrome_form(dir: &Path) -> Form {
    let mut form = Form::new();
    for img in images_of(dir) {
        form = form.part("images", file_part(&img));
    }
    form.text(
        "names",
        std::fs::read_to_string(dir.join("names.txt")).unwrap(),
    )
}

/// A chrome set rendered into a temporary folder.
fn rendered(set: &ChromeSet) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), None).unwrap();
    dir
}

async fn post(s: &TestServer, form: Form, key: Option<&str>) -> reqwest::Response {
    let mut r = s.client.post(s.url("/v1/calibrations")).multipart(form);
    if let Some(k) = key {
        r = r.bearer_auth(k);
    }
    r.send().await.unwrap()
}

/// Create a calibration; asserts 201 + Location and returns it.
async fn create(s: &TestServer, form: Form, key: Option<&str>) -> Value {
    let r = post(s, form, key).await;
    let status = r.status();
    let location = r
        .headers()
        .get("location")
        .map(|v| v.to_str().unwrap().to_string());
    let body: Value = r.json().await.unwrap();
    assert_eq!(status, 201, "{body}");
    let id = body["id"].as_str().unwrap();
    assert_eq!(
        location.as_deref(),
        Some(format!("/v1/calibrations/{id}").as_str())
    );
    body
}

/// Mean and max direction error (degrees) of a calibration's lights against a true table.
fn errors_against(cal: &Value, truth: &[lights::Light]) -> (f64, f64) {
    let lights = cal["lights"].as_array().unwrap();
    assert_eq!(lights.len(), truth.len(), "{cal}");
    let e: Vec<f64> = lights
        .iter()
        .map(|l| {
            let t = truth.iter().find(|t| t.name == l["name"]).unwrap();
            let t = t.direction.map(f64::from);
            angle_deg(direction(l), t)
        })
        .collect();
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    (mean, e.iter().cloned().fold(0.0, f64::max))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn res_chrome_calibrates_to_its_true_lights_and_keeps_its_files() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let chrome = repo_root().join("res/chrome");
    let cal = create(&s, chrome_form(&chrome), None).await;
    let id = cal["id"].as_str().unwrap();
    let truth = lights::parse(
        &std::fs::read_to_string(chrome.join("truth-lights/light_directions.csv")).unwrap(),
    )
    .unwrap();
    let (mean, max) = errors_against(&cal, &truth);
    let circle: Vec<f64> = std::fs::read_to_string(chrome.join("truth-lights/circle.txt"))
        .unwrap()
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect();
    let c = &cal["circle"];
    let centre_off =
        (c["cx"].as_f64().unwrap() - circle[0]).hypot(c["cy"].as_f64().unwrap() - circle[1]);
    eprintln!(
        "res/chrome over HTTP: direction error mean {mean:.3}°, max {max:.3}°; circle centre off by {centre_off:.3} px"
    );
    assert!(mean < 0.3 && max < 1.0, "mean {mean}°, max {max}°");
    assert!(centre_off < 0.5, "{c}");
    assert_eq!(c["source"], "fitted");
    assert_eq!(cal["tenant"], "default");
    assert_eq!(
        (cal["width"].as_u64(), cal["height"].as_u64()),
        (Some(320), Some(240))
    );
    assert_eq!(cal["image_count"], 12);
    assert_eq!(cal["skipped"].as_array().unwrap().len(), 0);
    let first = &cal["lights"][0];
    assert_eq!(first["name"], "im1.png");
    assert_eq!(first["image"], "ball01.png");
    assert_eq!(first["number"], 1);
    assert!(first["highlight"]["pixels"].as_u64().unwrap() > 0);
    assert!(first["highlight"]["rim_distance"].as_f64().unwrap() > 0.0);

    // The resource reads back as created, and is listed.
    let got = s.get_json(&format!("/v1/calibrations/{id}")).await;
    assert_eq!(got, cal);
    let list = s.get_json("/v1/calibrations").await;
    assert_eq!(list["calibrations"][0]["id"], id);

    // lights.csv is the light table reconstruct reads: the resource's lights, in order.
    let r = s
        .client
        .get(s.url(&format!("/v1/calibrations/{id}/lights.csv")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert!(
        r.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/csv")
    );
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    let table = lights::parse(&r.text().await.unwrap()).unwrap();
    assert_eq!(table.len(), 12);
    for (row, l) in table.iter().zip(cal["lights"].as_array().unwrap()) {
        assert_eq!(row.name, l["name"].as_str().unwrap());
        let d = row.direction.map(f64::from);
        assert!(angle_deg(d, direction(l)) < 1e-3, "{row:?} vs {l}");
    }
    let r = s
        .client
        .get(s.url(&format!("/v1/calibrations/{id}/lights.csv")))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);

    // The overlay is a PNG of the images' size; the diagram a PNG.
    for (name, size) in [("overlay.png", Some((320, 240))), ("lights.png", None)] {
        let r = s
            .client
            .get(s.url(&format!("/v1/calibrations/{id}/{name}")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{name}");
        assert_eq!(r.headers()["content-type"], "image/png");
        let bytes = r.bytes().await.unwrap();
        let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).unwrap();
        if let Some((w, h)) = size {
            assert_eq!((img.width(), img.height()), (w, h), "{name}");
        }
    }

    // Deleted: gone from every route.
    let r = s
        .client
        .delete(s.url(&format!("/v1/calibrations/{id}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    for path in ["", "/lights.csv", "/overlay.png"] {
        let r = s
            .client
            .get(s.url(&format!("/v1/calibrations/{id}{path}")))
            .send()
            .await
            .unwrap();
        expect_problem(r, 404, &[id]).await;
    }
    assert!(!dir.path().join("calibrations").join(id).exists());
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_calibrations_are_422_naming_the_image() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let chrome = repo_root().join("res/chrome");
    let balls = images_of(&chrome);

    // Too few images.
    let form = Form::new()
        .part("images", file_part(&balls[0]))
        .part("images", file_part(&balls[1]));
    expect_problem(post(&s, form, None).await, 422, &["at least 3"]).await;

    // Different sizes: answered at the image that differs.
    let mut form = Form::new();
    for (i, b) in balls.iter().take(6).enumerate() {
        form = form.part(
            "images",
            if i == 4 {
                Part::bytes(png(100, 80, 30)).file_name("ball05.png")
            } else {
                file_part(b)
            },
        );
    }
    expect_problem(
        post(&s, form, None).await,
        422,
        &["ball05.png", "same size"],
    )
    .await;

    // A given circle off the image.
    let form = chrome_form(&chrome).text("circle", "400,100,50");
    expect_problem(
        post(&s, form, None).await,
        422,
        &["circle", "outside the 320×240 image"],
    )
    .await;
    let form = chrome_form(&chrome).text("circle", "1,2");
    expect_problem(post(&s, form, None).await, 422, &["cx,cy,r"]).await;

    // No sphere in the frame.
    let mut empty = ChromeSet::standard(8, 61);
    empty.radius = 0.0;
    empty.lights.truncate(4);
    empty.highlight.truncate(4);
    let d = rendered(&empty);
    let form = images_of(d.path())
        .iter()
        .fold(Form::new(), |f, p| f.part("images", file_part(p)));
    expect_problem(post(&s, form, None).await, 422, &["no sphere found"]).await;

    // A light behind the ball: no highlight in its image, named; skip_bad leaves it out.
    let mut behind = ChromeSet::standard(8, 59);
    behind.lights.truncate(5);
    behind.highlight.truncate(5);
    behind.lights[2] = [0.02, 0.0, -1.0];
    let d = rendered(&behind);
    let form = |skip: bool| {
        let f = images_of(d.path())
            .iter()
            .fold(Form::new(), |f, p| f.part("images", file_part(p)));
        if skip { f.text("skip_bad", "true") } else { f }
    };
    expect_problem(
        post(&s, form(false), None).await,
        422,
        &["ball03.png", "no highlight"],
    )
    .await;
    let cal = create(&s, form(true), None).await;
    assert_eq!(cal["skipped"][0]["image"], "ball03.png", "{cal}");
    assert_eq!(cal["lights"].as_array().unwrap().len(), 4);
    assert_eq!(cal["image_count"], 5);

    // Names not one per image; parts the form does not have.
    let form = chrome_form(&repo_root().join("res/chrome")).text("names", "a.png\nb.png\n");
    let r = post(&s, form, None).await;
    expect_problem(r, 400, &["names part appears more than once"]).await;
    let form = images_of(&chrome)
        .iter()
        .fold(Form::new(), |f, p| f.part("images", file_part(p)))
        .text("names", "a.png\nb.png\n");
    expect_problem(post(&s, form, None).await, 422, &["2 names for 12"]).await;
    let form = chrome_form(&chrome).text("lights", "x");
    expect_problem(
        post(&s, form, None).await,
        400,
        &["unknown part \"lights\""],
    )
    .await;
    // Nothing refused is kept.
    assert_eq!(
        s.get_json("/v1/calibrations").await["calibrations"]
            .as_array()
            .unwrap()
            .len(),
        1
    );
    // (A refused upload's directory is removed in the background, just after the answer.)
    let dirs = || {
        std::fs::read_dir(dir.path().join("calibrations"))
            .unwrap()
            .count()
    };
    let start = std::time::Instant::now();
    while dirs() != 1 && start.elapsed() < std::time::Duration::from_secs(10) {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(dirs(), 1);
    s.stop().await;
}

const ALICE: &str = "alice-secret";
const BOB: &str = "bob-secret";
const OPS: &str = "ops-secret";

async fn call(s: &TestServer, method: Method, path: &str, key: &str) -> reqwest::Response {
    s.client
        .request(method, s.url(path))
        .bearer_auth(key)
        .send()
        .await
        .unwrap()
}

/// A job form: the images of `dir` with a `calibration` part.
fn job_with_calibration(dir: &Path, id: &str) -> Form {
    images_of(dir)
        .iter()
        .fold(Form::new(), |f, p| f.part("images", file_part(p)))
        .text("calibration", id.to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn other_tenants_calibrations_do_not_exist_for_them() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys");
    std::fs::write(
        &keys,
        format!("alice {ALICE}\nbob {BOB}\nops {OPS} admin\n"),
    )
    .unwrap();
    let mut c = config(dir.path());
    c.api_keys_file = Some(keys);
    let s = TestServer::start(c).await;
    let chrome = repo_root().join("res/chrome");
    let cal = create(&s, chrome_form(&chrome), Some(ALICE)).await;
    assert_eq!(cal["tenant"], "alice");
    let id = cal["id"].as_str().unwrap();
    let never = uuid::Uuid::new_v4().to_string();

    // Every route answers bob as for an id that never existed, and changes nothing.
    for (method, tail) in [
        (Method::GET, ""),
        (Method::GET, "/lights.csv"),
        (Method::GET, "/overlay.png"),
        (Method::GET, "/lights.png"),
        (Method::DELETE, ""),
    ] {
        let path = format!("/v1/calibrations/{id}{tail}");
        let theirs = expect_problem(call(&s, method.clone(), &path, BOB).await, 404, &[]).await;
        let missing = expect_problem(
            call(&s, method.clone(), &path.replace(id, &never), BOB).await,
            404,
            &[],
        )
        .await;
        assert_eq!(
            theirs.to_string().replace(id, &never),
            missing.to_string(),
            "{method} {path}"
        );
        // The admin sees it (without deleting it yet).
        if method == Method::GET {
            assert_eq!(call(&s, method, &path, OPS).await.status(), 200, "{path}");
        }
    }
    let r = call(&s, Method::GET, &format!("/v1/calibrations/{id}"), ALICE).await;
    assert_eq!(r.json::<Value>().await.unwrap(), cal);
    let listed = |v: Value| -> Vec<String> {
        v["calibrations"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["id"].as_str().unwrap().to_string())
            .collect()
    };
    let list = |key: &'static str| {
        let s = &s;
        async move {
            call(s, Method::GET, "/v1/calibrations", key)
                .await
                .json::<Value>()
                .await
                .unwrap()
        }
    };
    assert!(listed(list(BOB).await).is_empty());
    assert_eq!(listed(list(ALICE).await), [id]);
    assert_eq!(listed(list(OPS).await), [id]);

    // Bob's job cannot use alice's calibration: the same 422 as an unknown id.
    let object = repo_root().join("res/bump");
    let submit = |key: &'static str, cal_id: String| {
        let s = &s;
        let object = object.clone();
        async move {
            s.client
                .post(s.url("/v1/jobs"))
                .bearer_auth(key)
                .multipart(job_with_calibration(&object, &cal_id))
                .send()
                .await
                .unwrap()
        }
    };
    let theirs = expect_problem(submit(BOB, id.to_string()).await, 422, &["calibration"]).await;
    let unknown = expect_problem(submit(BOB, never.clone()).await, 422, &[]).await;
    assert_eq!(
        theirs["detail"].as_str().unwrap().replace(id, &never),
        unknown["detail"].as_str().unwrap()
    );
    // Alice's own gets further: res/bump has 4 of the calibration's 12 images.
    expect_problem(
        submit(ALICE, id.to_string()).await,
        422,
        &[
            "do not match",
            "no image for its lights im5.png",
            "im12.png",
        ],
    )
    .await;

    // The admin may delete it.
    let r = call(&s, Method::DELETE, &format!("/v1/calibrations/{id}"), OPS).await;
    assert_eq!(r.status(), 204);
    let r = call(&s, Method::GET, &format!("/v1/calibrations/{id}"), ALICE).await;
    expect_problem(r, 404, &[]).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retries_with_an_idempotency_key_and_a_restart_keep_one_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let chrome = repo_root().join("res/chrome");
    let keyed = |form: Form, key: &str| {
        let key = key.to_string();
        move |s: &TestServer| {
            s.client
                .post(s.url("/v1/calibrations"))
                .header("idempotency-key", key)
                .multipart(form)
                .send()
        }
    };
    let s = TestServer::start(config(dir.path())).await;
    let first = keyed(chrome_form(&chrome), "cal-1")(&s).await.unwrap();
    assert_eq!(first.status(), 201);
    let first: Value = first.json().await.unwrap();
    let again = keyed(chrome_form(&chrome), "cal-1")(&s).await.unwrap();
    assert_eq!(again.status(), 201);
    assert_eq!(again.json::<Value>().await.unwrap(), first);
    let other = keyed(chrome_form(&chrome).text("skip_bad", "true"), "cal-1")(&s)
        .await
        .unwrap();
    expect_problem(other, 422, &["Idempotency-Key"]).await;
    // The key is the calibrations' own: a job with it is not a replay.
    let id = first["id"].as_str().unwrap().to_string();
    let csv = s
        .client
        .get(s.url(&format!("/v1/calibrations/{id}/lights.csv")))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert_eq!(
        s.get_json("/v1/calibrations").await["calibrations"]
            .as_array()
            .unwrap()
            .len(),
        1
    );
    s.stop().await;

    // Reopened on the same data directory: the calibration, its files and the key remain.
    let s = TestServer::start(config(dir.path())).await;
    assert_eq!(s.get_json(&format!("/v1/calibrations/{id}")).await, first);
    let after = s
        .client
        .get(s.url(&format!("/v1/calibrations/{id}/lights.csv")))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert_eq!(after, csv);
    let replay = keyed(chrome_form(&chrome), "cal-1")(&s).await.unwrap();
    assert_eq!(replay.status(), 201);
    assert_eq!(replay.json::<Value>().await.unwrap(), first);
    assert_eq!(
        s.get_json("/v1/calibrations").await["calibrations"]
            .as_array()
            .unwrap()
            .len(),
        1
    );
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_refuses_a_calibration_with_lights_or_unmatched_names() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let cal = create(&s, chrome_form(&repo_root().join("res/chrome")), None).await;
    let id = cal["id"].as_str().unwrap();
    let tiny = |names: &[&str]| {
        names.iter().fold(Form::new(), |f, n| {
            f.part(
                "images",
                Part::bytes(png(8, 8, 100)).file_name(n.to_string()),
            )
        })
    };
    let mut names: Vec<String> = (1..=11).map(|i| format!("im{i}.png")).collect();
    names.push("extra.png".into());
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    let post_job = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form).send();
    expect_problem(
        post_job(tiny(&refs).text("calibration", id.to_string()))
            .await
            .unwrap(),
        422,
        &[id, "no image for its lights im12.png", "images extra.png"],
    )
    .await;
    expect_problem(
        post_job(
            tiny(&refs)
                .text("calibration", id.to_string())
                .text("lights", "im1.png, 0, 0, 1\n"),
        )
        .await
        .unwrap(),
        422,
        &["not both"],
    )
    .await;
    expect_problem(
        post_job(tiny(&refs).text("calibration", "not-an-id"))
            .await
            .unwrap(),
        422,
        &["there is no calibration \"not-an-id\""],
    )
    .await;
    expect_problem(
        post_job(
            archive_form(zip_folder(&repo_root().join("res/bump"), None))
                .text("calibration", id.to_string()),
        )
        .await
        .unwrap(),
        422,
        &["archive"],
    )
    .await;
    s.stop().await;
}

/// The normals of a job's `normal.exr` (y down, as the truth), per pixel.
async fn normals_of(s: &TestServer, id: &str) -> image::Rgb32FImage {
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/normal.exr")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let bytes = r.bytes().await.unwrap();
    image::load_from_memory_with_format(&bytes, image::ImageFormat::OpenExr)
        .unwrap()
        .to_rgb32f()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_with_a_calibration_matches_the_job_with_the_true_lights_within_half_a_degree() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    // A chrome capture and an object under the same 24 lights.
    let chrome = ChromeSet::standard(8, 71);
    let sphere_dir = rendered(&chrome);
    let (object, truth) = sphere_under(&chrome.lights);

    let cal = create(&s, chrome_form(sphere_dir.path()), None).await;
    let cal_id = cal["id"].as_str().unwrap();
    let options = r#"{"outputs": ["normal.exr"]}"#;
    let calibrated = s
        .submit(job_with_calibration(object.path(), cal_id).text("options", options))
        .await;
    let with_truth = s
        .submit(folder_form(object.path()).text("options", options))
        .await;
    let (a, b) = (
        calibrated["id"].as_str().unwrap(),
        with_truth["id"].as_str().unwrap(),
    );
    s.wait_succeeded(a).await;
    s.wait_succeeded(b).await;
    let (na, nb) = (normals_of(&s, a).await, normals_of(&s, b).await);
    let mut diffs = Vec::new();
    let mut to_truth = Vec::new();
    for ((r, c), &m) in truth.mask.indexed_iter() {
        if m {
            let n = |img: &image::Rgb32FImage| {
                let p = img.get_pixel(c as u32, r as u32).0;
                [p[0] as f64, -p[1] as f64, p[2] as f64] // normal.exr has y up
            };
            diffs.push(angle_deg(n(&na), n(&nb)));
            let t = [0, 1, 2].map(|k| truth.normals[[r, c, k]] as f64);
            to_truth.push(angle_deg(n(&na), t));
        }
    }
    let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
    let mean_truth = to_truth.iter().sum::<f64>() / to_truth.len() as f64;
    diffs.sort_by(f64::total_cmp);
    let p99 = diffs[diffs.len() * 99 / 100];
    eprintln!(
        "job with calibration {cal_id} vs job with the true lights: normals differ by {mean:.3}° on average ({p99:.3}° at the 99th percentile) over {} mask pixels; {mean_truth:.3}° from the true normals",
        diffs.len()
    );
    assert!(mean < 0.5, "mean {mean}°");
    assert!(
        mean > 0.0,
        "the two jobs must differ a little: the lights are measured"
    );
}

/// A `circle` part per ball of a rendered set, the first ball first.
fn with_circles(form: Form, set: &ChromeSet) -> Form {
    set.balls().iter().fold(form, |f, (c, r)| {
        f.text("circle", format!("{},{},{r}", c[0], c[1]))
    })
}

async fn get_text(s: &TestServer, path: &str) -> (String, String) {
    let r = s.client.get(s.url(path)).send().await.unwrap();
    assert_eq!(r.status(), 200, "GET {path}");
    let content_type = r.headers()["content-type"].to_str().unwrap().to_string();
    (content_type, r.text().await.unwrap())
}

/// The worst distance between a calibration's light positions and the true ones, as a
/// fraction of the light's distance from between the balls; `per_radius` is the
/// positions' unit per ball radius (1 in ball radii).
fn position_errors(set: &ChromeSet, cal: &Value, per_radius: f64) -> f64 {
    let truth = set.light_positions.as_ref().unwrap();
    let balls = set.balls();
    let radius = balls.iter().map(|b| b.1).sum::<f64>() / balls.len() as f64;
    let c0 = set.centre;
    let mid = [
        (balls[0].0[0] + balls[1].0[0]) / 2.0,
        (balls[0].0[1] + balls[1].0[1]) / 2.0,
        0.0,
    ];
    let dist = |a: [f64; 3], b: [f64; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt();
    let lights = cal["lights"].as_array().unwrap();
    assert_eq!(lights.len(), truth.len(), "{cal}");
    let mut worst = 0.0f64;
    for l in lights {
        let p = &l["position"];
        assert!(p.is_object(), "two balls place every light: {l}");
        let at = |k: &str| p[k].as_f64().unwrap() / per_radius * radius;
        // Orthographic: from the first ball's centre, back to pixels.
        let got = [at("x") + c0[0], at("y") + c0[1], at("z")];
        let t = truth[l["number"].as_u64().unwrap() as usize - 1];
        worst = worst.max(dist(got, t) / dist(t, mid));
        let more = l["more_highlights"].as_array().unwrap();
        assert_eq!(more.len(), 1, "{l}");
        let confidence = more[0]["highlight"]["confidence"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&confidence), "{l}");
        assert!(angle_deg(direction(&more[0]), direction(l)) > 1.0, "{l}");
    }
    worst
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_balls_place_each_light_within_2_percent_of_its_distance_and_keep_positions_csv() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let set = ChromeSet::near_dome(16, 77, 3.0);
    let d = rendered(&set);
    let balls = set.balls();

    // In ball radii.
    let cal = create(&s, with_circles(chrome_form(d.path()), &set), None).await;
    let id = cal["id"].as_str().unwrap();
    assert_eq!(cal["circle"]["source"], "given");
    let more = cal["more_circles"].as_array().unwrap();
    assert_eq!(more.len(), 1, "{cal}");
    assert_eq!(more[0]["cx"].as_f64(), Some(balls[1].0[0]));
    assert_eq!(more[0]["r"].as_f64(), Some(balls[1].1));
    assert_eq!(cal["position_unit"], "ball_radii");
    assert_eq!(cal["position_origin"], "first_ball");
    assert!(cal["ball_diameter"].is_null(), "{cal}");
    let worst = position_errors(&set, &cal, 1.0);
    eprintln!(
        "two balls over HTTP, near lights at 3 ball diameters: positions off by {:.2} % of the distance at most",
        100.0 * worst
    );
    assert!(worst < 0.02, "{worst}");
    assert_eq!(s.get_json(&format!("/v1/calibrations/{id}")).await, cal);

    // positions.csv: the resource's positions, a row per light.
    let url = format!("/v1/calibrations/{id}/positions.csv");
    assert_eq!(cal["files"]["positions.csv"], url.as_str());
    let (content_type, csv) = get_text(&s, &url).await;
    assert!(content_type.starts_with("text/csv"), "{content_type}");
    assert!(csv.starts_with("# light positions in ball radii"), "{csv}");
    let rows: Vec<Vec<&str>> = (csv.lines())
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(',').map(str::trim).collect())
        .collect();
    let lights = cal["lights"].as_array().unwrap();
    assert_eq!(rows.len(), lights.len(), "{csv}");
    for (row, l) in rows.iter().zip(lights) {
        assert_eq!(row[0], l["name"].as_str().unwrap());
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            let v: f64 = row[k + 1].parse().unwrap();
            assert!(
                (v - l["position"][axis].as_f64().unwrap()).abs() < 1e-5,
                "{row:?} vs {l}"
            );
        }
    }

    // The overlay rings the second ball too (each ring starts at angle 0: (cx + r, cy)).
    let r = s
        .client
        .get(s.url(&format!("/v1/calibrations/{id}/overlay.png")))
        .send()
        .await
        .unwrap();
    let overlay = image::load_from_memory(&r.bytes().await.unwrap())
        .unwrap()
        .to_rgb8();
    let ((c, radius), outline) = (balls[1], image::Rgb([40, 220, 90]));
    let at = ((c[0] + radius).round() as u32, c[1].round() as u32);
    assert_eq!(*overlay.get_pixel(at.0, at.1), outline, "{at:?}");

    // With the balls' diameter (25.4 mm): positions in its unit, 12.7 per ball radius.
    let form = with_circles(chrome_form(d.path()), &set).text("ball_diameter", "25.4");
    let mm = create(&s, form, None).await;
    assert_eq!(mm["position_unit"], "ball_diameter");
    assert_eq!(mm["ball_diameter"].as_f64(), Some(25.4));
    let worst = position_errors(&set, &mm, 12.7);
    assert!(worst < 0.02, "{worst}");
    let (a, b) = (&cal["lights"][0]["position"], &mm["lights"][0]["position"]);
    for k in ["x", "y", "z", "residual"] {
        let (a, b) = (a[k].as_f64().unwrap(), b[k].as_f64().unwrap());
        assert!(
            (b - 12.7 * a).abs() <= 1e-9 * b.abs().max(1.0),
            "{k}: {a} vs {b}"
        );
    }
    let mm_id = mm["id"].as_str().unwrap();
    let (_, csv) = get_text(&s, &format!("/v1/calibrations/{mm_id}/positions.csv")).await;
    assert!(
        csv.starts_with("# light positions in the unit of the balls' diameter"),
        "{csv}"
    );

    // No circle part: both balls are found (the left one first, each with its outline
    // fit), and ball_diameter is taken.
    let form = chrome_form(d.path()).text("ball_diameter", "25.4");
    let found = create(&s, form, None).await;
    let more = found["more_circles"].as_array().unwrap();
    assert_eq!(more.len(), 1, "{found}");
    let mut circle_err = 0.0f64;
    for (view, (c, r)) in [&found["circle"], &more[0]].into_iter().zip(&balls) {
        assert_eq!(view["source"], "fitted", "{view}");
        assert!(view["coverage"].as_f64().unwrap() > 0.5, "{view}");
        let at = |k: &str| view[k].as_f64().unwrap();
        circle_err = circle_err
            .max((at("cx") - c[0]).hypot(at("cy") - c[1]))
            .max((at("r") - r).abs());
    }
    let worst = position_errors(&set, &found, 12.7);
    eprintln!(
        "two balls found over HTTP: circles within {circle_err:.3} px; positions off by {:.2} % of the distance at most",
        100.0 * worst
    );
    assert!(circle_err < 0.3 && worst < 0.02, "{circle_err} px, {worst}");
    assert!(found["files"]["positions.csv"].is_string(), "{found}");

    // One ball: no positions, and no positions.csv.
    let one = create(&s, chrome_form(&repo_root().join("res/chrome")), None).await;
    assert!(
        one["position_unit"].is_null() && one["lights"][0]["position"].is_null(),
        "{one}"
    );
    assert_eq!(one["more_circles"], serde_json::json!([]));
    assert!(one["files"].get("positions.csv").is_none(), "{one}");
    let r = s
        .client
        .get(s.url(&format!("{}/positions.csv", one["url"].as_str().unwrap())))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, &["positions.csv"]).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_ball_diameters_and_too_many_circles_are_422_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let chrome = repo_root().join("res/chrome");
    let two = || {
        chrome_form(&chrome)
            .text("circle", "80,110,60")
            .text("circle", "240,110,60")
    };
    for bad in ["0", "-25.4", "NaN", "inf", "1e400", "25mm", ""] {
        let form = two().text("ball_diameter", bad);
        let body = expect_problem(post(&s, form, None).await, 422, &["ball_diameter"]).await;
        assert!(
            body["detail"].as_str().unwrap().contains("positive number"),
            "{bad}: {body}"
        );
    }
    // Positions need two balls, as the CLI's --positions does: one circle or a mask is
    // refused, and so is no circle when one ball is found.
    for form in [
        chrome_form(&chrome).text("circle", "187.3,109.6,93.4"),
        chrome_form(&chrome).part("mask", file_part(&images_of(&chrome)[0])),
    ] {
        let form = form.text("ball_diameter", "25.4");
        expect_problem(
            post(&s, form, None).await,
            422,
            &["ball_diameter", "two balls or more"],
        )
        .await;
    }
    let form = chrome_form(&chrome).text("ball_diameter", "25.4");
    expect_problem(
        post(&s, form, None).await,
        422,
        &["ball_diameter", "two balls or more", "one ball was found"],
    )
    .await;
    // At most 16 balls, answered at the 17th circle.
    let form = (0..17).fold(chrome_form(&chrome), |f, i| {
        f.text("circle", format!("{},{},5", 10 + 15 * i, 20))
    });
    expect_problem(post(&s, form, None).await, 422, &["circle", "at most 16"]).await;
    // Several circles and a mask are refused together, as one circle and a mask are.
    let form = two().part("mask", file_part(&images_of(&chrome)[0]));
    expect_problem(post(&s, form, None).await, 422, &["circle or as a mask"]).await;
    assert_eq!(
        s.get_json("/v1/calibrations").await["calibrations"]
            .as_array()
            .unwrap()
            .len(),
        0
    );
    s.stop().await;
}
