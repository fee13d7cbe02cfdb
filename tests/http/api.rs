//! The HTTP API end to end: a real server on 127.0.0.1:0 and a real HTTP client.

use crate::common;
use crate::seed;

use std::collections::{BTreeMap, HashSet};
use std::time::Duration;

use common::*;
use photostereo::core::outputs::{self, ARTIFACTS};
use photostereo::service::{AppState, healthcheck, openapi_json, router};
use reqwest::multipart::{Form, Part};
use seed::{SEED_SETS, seed};
use serde_json::Value;

/// Download every artifact a succeeded job links and check each one: status, Content-Type,
/// caching headers, and that it decodes. Returns name → bytes.
async fn check_artifacts(s: &TestServer, job: &Value) -> BTreeMap<String, Vec<u8>> {
    let artifacts = job["artifacts"]
        .as_object()
        .expect("artifacts of a succeeded job");
    let (w, h) = (
        job["result"]["width"].as_u64().unwrap() as u32,
        job["result"]["height"].as_u64().unwrap() as u32,
    );
    // Exactly the selection (`albedo_rgb.png` only for colour inputs, the material maps
    // only from the glossy solver; depth pictures in place of height pictures under a
    // camera).
    let selection: Option<Vec<String>> =
        serde_json::from_value(job["options"]["outputs"].clone()).unwrap();
    let camera = job["options"]["camera"].is_object();
    for (name, _) in ARTIFACTS {
        let selected = outputs::wanted(selection.as_deref(), name, camera);
        if *name != "albedo_rgb.png" && !outputs::GLOSSY_OUTPUTS.contains(name) {
            assert_eq!(
                artifacts.contains_key(*name),
                selected,
                "{name} in {artifacts:?}"
            );
        }
    }
    let mut out = BTreeMap::new();
    for (name, url) in artifacts {
        let url = url.as_str().unwrap();
        assert_eq!(
            url,
            format!("/v1/jobs/{}/artifacts/{name}", job["id"].as_str().unwrap())
        );
        let r = s.client.get(s.url(url)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{name}");
        let expected_type = ARTIFACTS.iter().find(|(n, _)| n == name).unwrap().1;
        assert_eq!(r.headers()["content-type"], expected_type, "{name}");
        let etag = r.headers()["etag"].to_str().unwrap().to_string();
        assert!(
            etag.starts_with('"') && etag.ends_with('"'),
            "strong etag {etag}"
        );
        assert!(
            r.headers()["cache-control"]
                .to_str()
                .unwrap()
                .contains("immutable")
        );
        let bytes = r.bytes().await.unwrap().to_vec();
        match name.rsplit('.').next().unwrap() {
            "png" => {
                let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
                    .unwrap_or_else(|e| panic!("{name}: {e}"));
                if [
                    "albedo.png",
                    "normal.png",
                    "height.png",
                    "depth.png",
                    "mask.png",
                    "shaded.png",
                ]
                .contains(&name.as_str())
                {
                    assert_eq!((img.width(), img.height()), (w, h), "{name}");
                }
            }
            "exr" => {
                assert_eq!(&bytes[..4], &[0x76, 0x2f, 0x31, 0x01], "{name}: EXR magic");
                if name == "height.exr" || name == "depth.exr" {
                    let z = outputs::decode_height_exr(&bytes)
                        .unwrap_or_else(|e| panic!("{name}: {e}"));
                    assert_eq!(z.dim(), (h as usize, w as usize), "{name}");
                } else {
                    image::load_from_memory_with_format(&bytes, image::ImageFormat::OpenExr)
                        .unwrap_or_else(|e| panic!("{name}: {e}"));
                }
            }
            "glb" => {
                assert_eq!(&bytes[..4], b"glTF", "{name}: glb magic");
                assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().unwrap()), 2);
                assert_eq!(
                    u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
                    bytes.len()
                );
            }
            "gltf" => {
                let doc: Value = serde_json::from_slice(&bytes).unwrap();
                assert!(doc["asset"]["version"].is_string(), "{name}");
            }
            "ply" => {
                assert!(
                    bytes.starts_with(b"ply\nformat binary_little_endian 1.0\n"),
                    "{name}"
                );
            }
            "json" => {
                let report: Value = serde_json::from_slice(&bytes).unwrap();
                assert_eq!(report["width"], job["result"]["width"]);
                assert_eq!(report["height"], job["result"]["height"]);
            }
            other => panic!("unexpected artifact type {other}"),
        }
        // A cached copy is still good.
        let r = s
            .client
            .get(s.url(url))
            .header("if-none-match", &etag)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 304, "{name}");
        assert_eq!(r.headers()["etag"].to_str().unwrap(), etag);
        out.insert(name.clone(), bytes);
    }
    out
}

fn expected_size(set: &str) -> u64 {
    match set {
        "synth-images" => 100,
        "sphere-images" => 460,
        "dog-images" => 400,
        _ => unreachable!(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn seed_sets_as_files_produce_their_selected_artifacts() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let mut ids = Vec::new();
    for (i, set) in SEED_SETS.iter().enumerate() {
        // The first set asks for every artifact, the others get the default set.
        let form = match i {
            0 => folder_form(&seed!(set)).text("options", r#"{"outputs": ["all"]}"#),
            _ => folder_form(&seed!(set)),
        };
        let job = s.submit(form).await;
        assert_eq!(job["image_count"], 4);
        ids.push((set, job["id"].as_str().unwrap().to_string()));
    }
    for (set, id) in &ids {
        let job = s.wait_succeeded(id).await;
        let size = expected_size(set);
        assert_eq!(job["result"]["width"], size, "{set}: {job}");
        assert_eq!(job["result"]["height"], size, "{set}");
        assert_eq!(job["result"]["light_count"], 4, "{set}");
        assert!(
            job["result"]["height_max"].as_f64().is_some(),
            "{set}: {job}"
        );
        assert_eq!(job["progress"], 1.0);
        for t in ["created_at", "started_at", "finished_at"] {
            let v = job[t].as_str().unwrap();
            assert!(v.ends_with('Z') && v.len() == 24, "{t} = {v}");
        }
        assert!(job.get("error").is_none());
        check_artifacts(&s, &job).await;
    }

    // Re-shading on request, and its light checked.
    let (_, id) = &ids[0];
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/shaded.png?light=0,0,1")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "image/png");
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    let png = r.bytes().await.unwrap();
    let img = image::load_from_memory(&png).unwrap();
    assert_eq!((img.width(), img.height()), (100, 100));
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/shaded.png?light=0,0,1")))
        .header("if-none-match", etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    for bad in ["0,0,0", "1,2", "a,b,c", "inf,0,1"] {
        let r = s
            .client
            .get(s.url(&format!("/v1/jobs/{id}/artifacts/shaded.png?light={bad}")))
            .send()
            .await
            .unwrap();
        expect_problem(r, 422, &["light"]).await;
    }
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/albedo.png?light=0,0,1")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 400, &["shaded.png"]).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_selection_writes_only_its_artifacts_and_reshading_names_what_it_lacks() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let form = folder_form(&repo_root().join("res/bump"))
        .text("options", r#"{"outputs": ["albedo.png", "shaded.png"]}"#);
    let id = s.submit(form).await["id"].as_str().unwrap().to_string();
    let job = s.wait_succeeded(&id).await;
    let names: Vec<&String> = job["artifacts"].as_object().unwrap().keys().collect();
    assert_eq!(names, ["albedo.png", "result.json", "shaded.png"]);
    let get = |path: String| s.client.get(s.url(&path)).send();
    let r = get(format!("/v1/jobs/{id}/artifacts/normal.png"))
        .await
        .unwrap();
    expect_problem(r, 404, &["normal.png"]).await;
    let r = get(format!("/v1/jobs/{id}/artifacts/shaded.png?light=0,0,1"))
        .await
        .unwrap();
    expect_problem(r, 404, &["normal.png", "re-shading"]).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn seed_sets_as_zip_archives() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let layouts = [
        ("synth-images", None),
        ("sphere-images", Some("sphere")),
        ("dog-images", Some("dog-images")),
    ];
    let mut ids = Vec::new();
    for (set, top) in layouts {
        let zip = zip_folder(&seed!(set), top);
        let form = archive_form(zip).text("options", r#"{"integration": "frankot-chellappa"}"#);
        let job = s.submit(form).await;
        assert_eq!(job["options"]["integration"], "frankot-chellappa");
        ids.push((set, job["id"].as_str().unwrap().to_string()));
    }
    for (set, id) in ids {
        let job = s.wait_succeeded(&id).await;
        assert_eq!(job["result"]["width"], expected_size(set), "{set}");
        check_artifacts(&s, &job).await;
    }
    s.stop().await;
}

/// One refused request of a table: a label (printed before it is sent, so that a failure
/// names its case), the request, and the problem it must get: the status and words of its
/// detail.
type Refusal<'a> = (&'a str, reqwest::RequestBuilder, u16, &'a [&'a str]);

/// Send each case's request in turn and check its problem answer; returns the bodies.
async fn expect_refusals(cases: Vec<Refusal<'_>>) -> Vec<Value> {
    let mut bodies = Vec::new();
    for (case, request, status, needles) in cases {
        println!("case: {case}");
        let r = request
            .send()
            .await
            .unwrap_or_else(|e| panic!("{case}: {e}"));
        bodies.push(expect_problem(r, status, needles).await);
    }
    bodies
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_requests_get_400() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let bump = repo_root().join("res/bump");
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);

    let mut no_lights = Form::new();
    for img in images_of(&bump) {
        no_lights = no_lights.part("images", file_part(&img));
    }
    let mut cases: Vec<Refusal> = vec![
        (
            "JSON body",
            s.client
                .post(s.url("/v1/jobs"))
                .json(&serde_json::json!({"images": []})),
            400,
            &["multipart/form-data"],
        ),
        ("no lights", post(no_lights), 400, &["lights"]),
        (
            "only lights",
            post(Form::new().part("lights", file_part(&bump.join("light_directions.csv")))),
            400,
            &["images"],
        ),
        (
            "unknown part",
            post(folder_form(&bump).text("colour", "red")),
            400,
            &["\"colour\""],
        ),
        (
            "nameless image",
            post(
                Form::new()
                    .part("lights", file_part(&bump.join("light_directions.csv")))
                    .part("images", Part::bytes(png(4, 4, 9))),
            ),
            400,
            &["file name"],
        ),
        (
            "lights twice",
            post(folder_form(&bump).text("lights", "a.png, 0, 0, 1")),
            400,
            &["lights", "more than once"],
        ),
        (
            "files and an archive",
            post(folder_form(&bump).part(
                "archive",
                Part::bytes(zip_folder(&bump, None)).file_name("a.zip"),
            )),
            400,
            &["either an archive"],
        ),
        (
            "unfinished multipart",
            s.client
                .post(s.url("/v1/jobs"))
                .header("content-type", "multipart/form-data; boundary=XYZ")
                .body("--XYZ\r\nContent-Disposition: form-data; name=\"lights\"\r\n\r\nabc"),
            400,
            &["multipart"],
        ),
    ];
    for q in ["limit=0", "limit=101", "limit=ten", "cursor=nonsense"] {
        let request = s.client.get(s.url(&format!("/v1/jobs?{q}")));
        cases.push((q, request, 400, &[]));
    }
    expect_refusals(cases).await;
    // Nothing was accepted, and nothing was left on disk.
    assert_eq!(
        s.get_json("/v1/jobs").await["jobs"]
            .as_array()
            .unwrap()
            .len(),
        0
    );
    tokio::time::sleep(Duration::from_millis(200)).await;
    let leftovers = std::fs::read_dir(dir.path().join("jobs")).unwrap().count();
    assert_eq!(leftovers, 0, "refused uploads leave no files");
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limits_get_413() {
    let (sphere, synth) = (seed!("sphere-images"), seed!("synth-images"));
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.max_body_bytes = 300_000;
    c.max_images = 3;
    c.max_parts = 5;
    c.max_pixels = 150 * 150;
    c.upload_timeout = Duration::from_millis(300);
    let s = TestServer::start(c).await;
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);

    // The same sphere image twice, streamed without a length.
    let big = std::fs::read(sphere.join("real1.bmp")).unwrap();
    let chunks: Vec<Result<Vec<u8>, std::io::Error>> = big
        .repeat(2)
        .chunks(16 * 1024)
        .map(|c| Ok(c.to_vec()))
        .collect();
    let stream = Part::stream(reqwest::Body::wrap_stream(futures_util::stream::iter(
        chunks,
    )))
    .file_name("real1.bmp");
    let streamed = Form::new()
        .text("lights", "real1.bmp, 0, 0, 1")
        .part("images", stream);
    let mut too_many_parts = Form::new()
        .text("lights", "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1")
        .text("options", "{}")
        .part("mask", Part::bytes(png(8, 8, 255)).file_name("mask.png"));
    for name in ["a.png", "b.png", "c.png"] {
        too_many_parts = too_many_parts.part("images", Part::bytes(png(8, 8, 100)).file_name(name));
    }
    let over_pixels = Form::new()
        .text("lights", "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1")
        .part("images", Part::bytes(png(200, 200, 10)).file_name("a.png"));
    expect_refusals(vec![
        // The sphere set is 4 × 212 kB: over the body limit (declared length).
        (
            "body over the limit, declared",
            post(folder_form(&sphere)),
            413,
            &["300000 bytes"],
        ),
        // The same, streamed without a length: caught while reading.
        (
            "body over the limit, streamed",
            post(streamed),
            413,
            &["larger than the limit"],
        ),
        // Four images where three are allowed.
        (
            "four images",
            post(folder_form(&synth)),
            413,
            &["limit of 3 images"],
        ),
        (
            "too many parts",
            post(too_many_parts),
            413,
            &["more than 5 parts"],
        ),
        (
            "an image over the pixel limit",
            post(over_pixels),
            413,
            &["\"a.png\"", "200×200", "22500"],
        ),
    ])
    .await;

    // An upload slower than the upload time limit, answered in time.
    let slow = futures_util::stream::unfold(0u32, |i| async move {
        if i == 8 {
            return None;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        Some((Ok::<_, std::io::Error>(vec![0u8; 1024]), i + 1))
    });
    let form = Form::new().text("lights", "a.png, 0, 0, 1").part(
        "images",
        Part::stream(reqwest::Body::wrap_stream(slow)).file_name("a.png"),
    );
    let started = std::time::Instant::now();
    expect_problem(post(form).send().await.unwrap(), 408, &["within 300ms"]).await;
    assert!(started.elapsed() < Duration::from_secs(5));
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unsupported_formats_get_415() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);
    let table = "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1";
    let image = |bytes: Vec<u8>| {
        Form::new()
            .text("lights", table)
            .part("images", Part::bytes(bytes).file_name("a.png"))
    };
    let gif = b"GIF89a\x01\x00\x01\x00\x80\x00\x00\x00\x00\x00\xff\xff\xff!\xf9\x04\x01\x00\x00\x00\x00,\x00\x00\x00\x00\x01\x00\x01\x00\x00\x02\x02D\x01\x00;".to_vec();
    let p = png(8, 8, 50);
    // A readme beside the images is skipped; an image the table names must be one.
    let zip = zip_entries(&[
        ("a.png", b"hello"),
        ("b.png", &p),
        ("c.png", &p),
        ("readme.txt", b"hello"),
        ("light_directions.csv", table.as_bytes()),
    ]);
    expect_refusals(vec![
        (
            "text as an image",
            post(image(b"just some notes".to_vec())),
            415,
            &["\"a.png\"", "not a supported image format"],
        ),
        ("a GIF", post(image(gif)), 415, &["\"a.png\""]),
        (
            "a PDF as the archive",
            post(Form::new().part(
                "archive",
                Part::bytes(b"%PDF-1.4".to_vec()).file_name("set.zip"),
            )),
            415,
            &["not a zip"],
        ),
        (
            "text as an image in a zip",
            post(archive_form(zip)),
            415,
            &["\"a.png\""],
        ),
    ])
    .await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_inputs_get_422_with_the_cores_message() {
    let (synth, dog) = (seed!("synth-images"), seed!("dog-images"));
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);
    let with_table = |table: &str| {
        let mut f = Form::new().text("lights", table.to_string());
        for img in images_of(&synth) {
            f = f.part("images", file_part(&img));
        }
        post(f)
    };
    let with_options =
        |options: &str| post(folder_form(&synth).text("options", options.to_string()));

    // A 400×400 dog image posing as im4.png among 100×100 images.
    let mut sizes = Form::new().part("lights", file_part(&synth.join("light_directions.csv")));
    for img in images_of(&synth).iter().take(3) {
        sizes = sizes.part("images", file_part(img));
    }
    let dog1 = std::fs::read(dog.join("dog1.png")).unwrap();
    sizes = sizes.part("images", Part::bytes(dog1).file_name("im4.png"));

    let p = png(8, 8, 50);
    let table = b"a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1";
    let evil = zip_entries(&[
        ("../a.png", &p),
        ("b.png", &p),
        ("c.png", &p),
        ("light_directions.csv", table),
    ]);
    let nested = zip_entries(&[
        ("x/y/a.png", &p),
        ("x/y/b.png", &p),
        ("x/y/c.png", &p),
        ("x/y/light_directions.csv", table),
    ]);
    let no_table = zip_entries(&[("a.png", &p), ("b.png", &p), ("c.png", &p)]);

    expect_refusals(vec![
        (
            "bad number",
            with_table("im1.png, 0, 0, 1\nim2.png, x, 0, 1\nim3.png, 0, 1, 1\nim4.png, 1, 1, 1"),
            422,
            &["row 2", "\"x\""],
        ),
        (
            "zero direction",
            with_table("im1.png, 0, 0, 0\nim2.png, 1, 0, 1\nim3.png, 0, 1, 1\nim4.png, 1, 1, 1"),
            422,
            &["row 1", "zero"],
        ),
        (
            "a row without its image",
            with_table(
                "im1.png, 0, 0, 1\nim2.png, 1, 0, 1\nim3.png, 0, 1, 1\nim4.png, 1, 1, 1\nim5.png, -1, 0, 1",
            ),
            422,
            &["\"im5.png\"", "not provided"],
        ),
        (
            "an image without its row",
            with_table("im1.png, 0, 0, 1\nim2.png, 1, 0, 1\nim3.png, 0, 1, 1"),
            422,
            &["\"im4.png\"", "no row"],
        ),
        (
            "bad JSON table",
            with_table(r#"[{"name": "im1.png", "direction": [0, 0]}]"#),
            422,
            &["invalid JSON"],
        ),
        (
            "unknown option",
            with_options(r#"{"solver": "l2", "colour": true}"#),
            422,
            &["options", "colour"],
        ),
        (
            "option of the wrong type",
            with_options(r#"{"integration": 7}"#),
            422,
            &["options", "integration"],
        ),
        ("options not JSON", with_options("{not json"), 422, &["options"]),
        (
            "a holdout score of 4 images",
            with_options(r#"{"holdout_lights": true}"#),
            422,
            &["holdout_lights", "at least 8 images", "has 4"],
        ),
        (
            "unknown output",
            with_options(r#"{"outputs": ["albedo.png", "portrait.jpg"]}"#),
            422,
            &["portrait.jpg"],
        ),
        (
            "a given mask without one",
            with_options(r#"{"mask": "given"}"#),
            422,
            &["mask"],
        ),
        (
            "mask of another size",
            post(folder_form(&synth).part("mask", Part::bytes(png(50, 50, 255)).file_name("mask.png"))),
            422,
            &["mask", "50×50", "100×100"],
        ),
        (
            "images of two sizes",
            post(sizes),
            422,
            &["\"im4.png\"", "400×400", "same size"],
        ),
        (
            "unsafe archive path",
            post(archive_form(evil)),
            422,
            &["unsafe path"],
        ),
        (
            "archive nested two deep",
            post(archive_form(nested)),
            422,
            &["one folder"],
        ),
        (
            "archive without a table",
            post(archive_form(no_table)),
            422,
            &["light_directions.csv"],
        ),
    ])
    .await;

    assert_eq!(
        s.get_json("/v1/jobs").await["jobs"]
            .as_array()
            .unwrap()
            .len(),
        0
    );
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_things_get_404_and_unfinished_jobs_409() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.stage_delay = Duration::from_millis(400);
    let s = TestServer::start(c).await;

    expect_refusals(vec![
        (
            "unknown job",
            s.client
                .get(s.url(&format!("/v1/jobs/{}", uuid::Uuid::new_v4()))),
            404,
            &["no job"],
        ),
        (
            "not a job id",
            s.client.get(s.url("/v1/jobs/not-a-uuid")),
            404,
            &["not-a-uuid"],
        ),
        (
            "deleting an unknown job",
            s.client
                .delete(s.url(&format!("/v1/jobs/{}", uuid::Uuid::new_v4()))),
            404,
            &["no job"],
        ),
        (
            "unknown path",
            s.client.get(s.url("/v2/anything")),
            404,
            &["/v2/anything"],
        ),
        (
            "unknown method",
            s.client.put(s.url("/v1/jobs")),
            405,
            &["PUT"],
        ),
    ])
    .await;

    let job = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    let id = job["id"].as_str().unwrap();
    expect_refusals(vec![
        (
            "unknown artifact",
            s.client
                .get(s.url(&format!("/v1/jobs/{id}/artifacts/secrets.txt"))),
            404,
            &["secrets.txt", "albedo.png"],
        ),
        (
            "artifact path leaving its folder",
            s.client
                .get(s.url(&format!("/v1/jobs/{id}/artifacts/..%2F..%2Fjobs.sqlite"))),
            404,
            &[],
        ),
    ])
    .await;

    let running = s
        .wait_for(id, Duration::from_secs(30), |j| {
            j["status"] == "running" && j["stage"].is_string()
        })
        .await;
    assert!(running["progress"].as_f64().unwrap() < 1.0);
    assert!(running["started_at"].is_string());
    assert_eq!(running["attempts"], 1);
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/albedo.png")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 409, &["running"]).await;

    let done = s.wait_succeeded(id).await;
    assert_eq!(done["progress"], 1.0);
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/albedo.png")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_queue_gets_503_and_low_disk_507() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.queue_length = 1;
    c.stage_delay = Duration::from_millis(300);
    let s = TestServer::start(c).await;
    let bump = repo_root().join("res/bump");

    let a = s.submit(folder_form(&bump)).await;
    let a = a["id"].as_str().unwrap().to_string();
    s.wait_for(&a, Duration::from_secs(30), |j| j["status"] == "running")
        .await;
    let b = s.submit(folder_form(&bump)).await;
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(folder_form(&bump))
        .send()
        .await
        .unwrap();
    let retry = r
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().to_string());
    expect_problem(r, 503, &["queue is full"]).await;
    assert!(retry.unwrap().parse::<u64>().unwrap() > 0);
    let metrics = s.metrics_text().await;
    assert!(
        metrics.contains("photostereo_jobs_rejected_queue_full_total 1"),
        "{metrics}"
    );
    assert!(metrics.contains("photostereo_queue_depth 1"), "{metrics}");

    // Cancelling the queued job frees its slot.
    let r = s
        .client
        .delete(s.url(&format!("/v1/jobs/{}", b["id"].as_str().unwrap())))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    s.submit(folder_form(&bump)).await;
    s.stop().await;

    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.min_free_disk = u64::MAX;
    let s = TestServer::start(c).await;
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(folder_form(&bump))
        .send()
        .await
        .unwrap();
    expect_problem(r, 507, &["free"]).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_keys_guard_v1_only() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.api_keys = vec!["first-key".into(), "second-key".into()];
    let s = TestServer::start(c).await;

    let r = s.client.get(s.url("/v1/jobs")).send().await.unwrap();
    assert_eq!(
        r.headers()["www-authenticate"],
        "Bearer realm=\"photostereo\""
    );
    expect_problem(r, 401, &["Bearer"]).await;
    let list = || s.client.get(s.url("/v1/jobs"));
    expect_refusals(vec![
        (
            "a wrong key",
            list().bearer_auth("second-kez"),
            401,
            &["not valid"],
        ),
        (
            "basic auth",
            list().header("authorization", "Basic Zmlyc3Qta2V5"),
            401,
            &[],
        ),
        (
            "a submission without a key",
            s.client
                .post(s.url("/v1/jobs"))
                .multipart(folder_form(&repo_root().join("res/bump"))),
            401,
            &[],
        ),
    ])
    .await;

    let r = s
        .client
        .get(s.url("/v1/jobs"))
        .bearer_auth("second-key")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth("first-key")
        .multipart(folder_form(&repo_root().join("res/bump")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    for open in ["/healthz", "/readyz", "/metrics", "/openapi.json"] {
        let r = s.client.get(s.url(open)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{open}");
    }
    // The browser app learns without a key that it needs one.
    let r = s.client.get(s.url("/app/auth.json")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let auth: Value = r.json().await.unwrap();
    assert_eq!(auth, serde_json::json!({ "api_key_required": true }));
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_jobs_at_once_all_finish_within_the_pool_size() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 2;
    c.queue_length = 32;
    c.stage_delay = Duration::from_millis(5);
    let s = TestServer::start(c).await;
    let bump = repo_root().join("res/bump");
    let submissions = (0..20).map(|_| {
        let client = s.client.clone();
        let url = s.url("/v1/jobs");
        let form = folder_form(&bump);
        async move { client.post(url).multipart(form).send().await.unwrap() }
    });
    let answers = futures_util::future::join_all(submissions).await;
    let mut ids = HashSet::new();
    for r in answers {
        assert_eq!(r.status(), 202);
        let job: Value = r.json().await.unwrap();
        ids.insert(job["id"].as_str().unwrap().to_string());
    }
    assert_eq!(ids.len(), 20);
    for id in &ids {
        s.wait_succeeded(id).await;
    }
    let max = s.state.max_running();
    assert!((1..=2).contains(&max), "max running {max}");
    let metrics = s.metrics_text().await;
    assert!(
        metrics.contains(&format!("photostereo_workers_running_max {max}")),
        "{metrics}"
    );
    assert!(
        metrics.contains("photostereo_jobs{status=\"succeeded\"} 20"),
        "{metrics}"
    );
    assert!(
        metrics.contains("photostereo_stage_seconds_count{stage=\"solve\"} 20"),
        "{metrics}"
    );
    assert!(
        metrics.contains(
            "photostereo_http_requests_total{method=\"POST\",route=\"/v1/jobs\",status=\"202\"} 20"
        ),
        "{metrics}"
    );

    // Paging sees every job once, newest first.
    let mut seen = Vec::new();
    let mut url = "/v1/jobs?limit=7".to_string();
    loop {
        let page = s.get_json(&url).await;
        for j in page["jobs"].as_array().unwrap() {
            seen.push((
                j["created_at"].as_str().unwrap().to_string(),
                j["id"].as_str().unwrap().to_string(),
            ));
        }
        match page["next_cursor"].as_str() {
            Some(c) => url = format!("/v1/jobs?limit=7&cursor={c}"),
            None => break,
        }
    }
    assert_eq!(seen.len(), 20);
    assert_eq!(
        seen.iter()
            .map(|(_, id)| id.clone())
            .collect::<HashSet<_>>(),
        ids
    );
    assert!(seen.windows(2).all(|w| w[0].0 >= w[1].0), "newest first");
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_cancels_running_and_queued_jobs_then_removes_them() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.workers = 1;
    c.stage_delay = Duration::from_millis(500);
    let s = TestServer::start(c).await;

    let running = s.submit(synthetic_form(256, 6)).await;
    let running = running["id"].as_str().unwrap().to_string();
    let queued = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    let queued = queued["id"].as_str().unwrap().to_string();
    s.wait_for(&running, Duration::from_secs(30), |j| {
        j["status"] == "running"
    })
    .await;

    // The queued job first: once the running one is cancelled, the worker is free to start
    // whatever is still queued (a CI run once saw it start in between the two requests).
    let r = s
        .client
        .delete(s.url(&format!("/v1/jobs/{queued}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.json::<Value>().await.unwrap()["status"], "cancelled");

    let r = s
        .client
        .delete(s.url(&format!("/v1/jobs/{running}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let job: Value = r.json().await.unwrap();
    assert_eq!(job["status"], "cancelled");
    assert!(job["finished_at"].is_string());

    // The worker lets go of the running job at its next stage; nothing runs afterwards.
    let start = std::time::Instant::now();
    while s.state.workers().busy() > 0 {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "the worker did not stop"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    for id in [&running, &queued] {
        let job = s.get_json(&format!("/v1/jobs/{id}")).await;
        assert_eq!(job["status"], "cancelled", "{job}");
        assert!(job.get("artifacts").is_none());
        let r = s
            .client
            .get(s.url(&format!("/v1/jobs/{id}/artifacts/albedo.png")))
            .send()
            .await
            .unwrap();
        expect_problem(r, 409, &["cancelled"]).await;
    }
    assert_eq!(
        s.get_json(&format!("/v1/jobs/{queued}")).await["attempts"],
        0
    );
    assert!(
        !dir.path()
            .join("jobs")
            .join(&running)
            .join("output")
            .exists()
    );

    // A finished job is deleted with its files.
    let r = s
        .client
        .delete(s.url(&format!("/v1/jobs/{running}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 204);
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{running}")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, &[]).await;
    assert!(!dir.path().join("jobs").join(&running).exists());
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_over_its_time_limit_fails_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.job_timeout = Duration::from_millis(200);
    c.stage_delay = Duration::from_millis(300);
    let s = TestServer::start(c).await;
    let job = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    let job = s.wait_finished(job["id"].as_str().unwrap()).await;
    assert_eq!(job["status"], "failed", "{job}");
    assert_eq!(job["error"]["type"], "urn:photostereo:problem:job-timeout");
    assert!(
        job["error"]["detail"]
            .as_str()
            .unwrap()
            .contains("time limit of 200ms"),
        "{job}"
    );
    assert!(job.get("artifacts").is_none());
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failed_reconstructions_report_a_problem() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    // Coplanar lights: the table parses, the images match, but normals cannot be solved.
    let table = "a.png, 1, 0, 1\nb.png, -1, 0, 1\nc.png, 0.5, 0, 1";
    let mut form = Form::new().text("lights", table);
    for (i, n) in ["a.png", "b.png", "c.png"].iter().enumerate() {
        form = form.part(
            "images",
            Part::bytes(png(16, 16, 40 + i as u8 * 30)).file_name(*n),
        );
    }
    let job = s.submit(form).await;
    let id = job["id"].as_str().unwrap();
    let job = s.wait_finished(id).await;
    assert_eq!(job["status"], "failed", "{job}");
    assert_eq!(job["error"]["status"], 422, "{job}");
    assert_eq!(job["error"]["instance"], format!("/v1/jobs/{id}"));
    assert!(!job["error"]["detail"].as_str().unwrap().is_empty());
    let r = s
        .client
        .get(s.url(&format!("/v1/jobs/{id}/artifacts/albedo.png")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 409, &["failed"]).await;
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restart_serves_finished_jobs_unchanged_and_runs_queued_ones() {
    let (synth, dog) = (seed!("synth-images"), seed!("dog-images"));
    let dir = tempfile::tempdir().unwrap();

    // First life: one job finishes; one is interrupted by the stop; two never start.
    let mut c = config(dir.path());
    c.workers = 1;
    let s = TestServer::start(c.clone()).await;
    let done = s.submit(folder_form(&dog)).await;
    let done_id = done["id"].as_str().unwrap().to_string();
    let done = s.wait_succeeded(&done_id).await;
    let before = check_artifacts(&s, &done).await;
    s.stop().await;

    let mut slow = c.clone();
    slow.stage_delay = Duration::from_millis(400);
    slow.shutdown_grace = Duration::from_millis(100);
    let s = TestServer::start(slow).await;
    let mut pending = Vec::new();
    for _ in 0..3 {
        let job = s.submit(folder_form(&synth)).await;
        pending.push(job["id"].as_str().unwrap().to_string());
    }
    s.wait_for(&pending[0], Duration::from_secs(30), |j| {
        j["status"] == "running"
    })
    .await;
    s.stop().await;

    // Second life on the same data directory.
    let s = TestServer::start(c).await;
    let again = s.get_json(&format!("/v1/jobs/{done_id}")).await;
    assert_eq!(again["status"], "succeeded");
    assert_eq!(again["finished_at"], done["finished_at"]);
    let after = check_artifacts(&s, &again).await;
    assert_eq!(
        before, after,
        "artifacts are served byte for byte as before"
    );
    for id in &pending {
        let job = s.wait_succeeded(id).await;
        check_artifacts(&s, &job).await;
    }
    let first = s.get_json(&format!("/v1/jobs/{}", pending[0])).await;
    assert_eq!(
        first["attempts"], 2,
        "the interrupted job ran again: {first}"
    );
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operations_endpoints_and_request_ids() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let r = s.client.get(s.url("/healthz")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.headers().contains_key("x-request-id"));
    assert_eq!(r.json::<Value>().await.unwrap()["status"], "ok");
    let r = s
        .client
        .get(s.url("/readyz"))
        .header("x-request-id", "abc-123")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["x-request-id"], "abc-123");

    let r = s.client.get(s.url("/metrics")).send().await.unwrap();
    assert!(
        r.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/plain")
    );
    let text = r.text().await.unwrap();
    for family in [
        "photostereo_jobs{status=\"queued\"}",
        "photostereo_queue_depth",
        "photostereo_workers_running",
        "photostereo_workers_running_max",
        "photostereo_http_requests_total",
        "# TYPE photostereo_stage_seconds summary",
    ] {
        assert!(text.contains(family), "{family} missing from\n{text}");
    }

    let r = s.client.get(s.url("/docs/")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.text().await.unwrap().contains("swagger"));
    // The root is the browser app: its page, script and style, compiled in, under a strict
    // Content-Security-Policy, revalidated by ETag; the page links the API reference.
    let r = s.client.get(s.url("/")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "text/html; charset=utf-8");
    let csp = r.headers()["content-security-policy"]
        .to_str()
        .unwrap()
        .to_string();
    for directive in [
        "default-src 'none'",
        "script-src 'self'",
        "style-src 'self'",
        "connect-src 'self'",
    ] {
        assert!(csp.contains(directive), "{csp}");
    }
    assert!(!csp.contains("unsafe"), "{csp}");
    assert_eq!(r.headers()["x-content-type-options"], "nosniff");
    assert_eq!(r.headers()["cache-control"], "no-cache");
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    let page = r.text().await.unwrap();
    assert!(
        page.contains("href=\"/docs/\""),
        "the app links the API reference"
    );
    assert!(
        !page.contains("<script>") && !page.contains("style="),
        "nothing inline"
    );
    let r = s
        .client
        .get(s.url("/"))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    for (file, kind) in [
        ("app.js", "text/javascript"),
        ("app.css", "text/css"),
        ("mesh.js", "text/javascript"),
    ] {
        let r = s
            .client
            .get(s.url(&format!("/app/{file}")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{file}");
        assert!(
            r.headers()["content-type"]
                .to_str()
                .unwrap()
                .starts_with(kind),
            "{file}"
        );
        assert!(
            page.contains(&format!("/app/{file}")) || file.ends_with(".js"),
            "{file}"
        );
    }
    let r = s.client.get(s.url("/app/auth.json")).send().await.unwrap();
    assert_eq!(r.headers()["cache-control"], "no-store");
    let auth: Value = r.json().await.unwrap();
    assert_eq!(auth, serde_json::json!({ "api_key_required": false }));
    let r = s
        .client
        .get(s.url("/app/secrets.txt"))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, &["secrets.txt"]).await;
    let no_follow = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .unwrap();
    let r = no_follow.post(s.url("/")).send().await.unwrap();
    expect_problem(r, 405, &[]).await;

    healthcheck(&s.url("/healthz")).await.unwrap();
    assert!(healthcheck(&s.url("/nope")).await.is_err());

    // Stopping: not ready, and no new jobs.
    s.state.begin_shutdown();
    let r = s.client.get(s.url("/readyz")).send().await.unwrap();
    expect_problem(r, 503, &["shutting down"]).await;
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(folder_form(&repo_root().join("res/bump")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 503, &["shutting down"]).await;
    s.stop().await;
    let closed = format!(
        "http://{}/healthz",
        std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
    );
    assert!(healthcheck(&closed).await.is_err());
}

#[tokio::test]
async fn router_answers_in_process() {
    use tower::ServiceExt;
    let dir = tempfile::tempdir().unwrap();
    let state = AppState::open(config(dir.path())).await.unwrap();
    let app = router(state.clone());
    let req = axum::http::Request::get("/nowhere")
        .body(axum::body::Body::empty())
        .unwrap();
    let res = app.clone().oneshot(req).await.unwrap();
    assert_eq!(res.status(), 404);
    assert_eq!(res.headers()["content-type"], "application/problem+json");
    let req = axum::http::Request::get("/v1/jobs")
        .body(axum::body::Body::empty())
        .unwrap();
    let res = app.oneshot(req).await.unwrap();
    assert_eq!(res.status(), 200);
    state.shutdown().await;
}

#[tokio::test]
async fn served_openapi_document_is_the_checked_in_one() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let r = s.client.get(s.url("/openapi.json")).send().await.unwrap();
    assert_eq!(r.headers()["content-type"], "application/json");
    let served = r.text().await.unwrap();
    assert_eq!(served, openapi_json());
    let doc: Value = serde_json::from_str(&served).unwrap();
    for path in [
        "/v1/jobs",
        "/v1/jobs/{id}",
        "/v1/jobs/{id}/artifacts/{name}",
        "/healthz",
        "/readyz",
        "/metrics",
        "/openapi.json",
    ] {
        assert!(doc["paths"][path].is_object(), "{path} missing");
    }
    // The browser's pages are not API operations.
    for path in ["/", "/app/{name}", "/docs", "/docs/"] {
        assert!(doc["paths"].get(path).is_none(), "{path} documented");
    }
    for schema in ["Problem", "JobView", "JobList", "Options", "JobStatus"] {
        assert!(
            doc["components"]["schemas"][schema].is_object(),
            "{schema} missing"
        );
    }
    // Artifact names are enums from the code's one list, so clients generated from the
    // spec know them all (the download route's description once missed two).
    let names: Vec<&str> = ARTIFACTS.iter().map(|(n, _)| *n).collect();
    let download = &doc["paths"]["/v1/jobs/{id}/artifacts/{name}"]["get"]["parameters"];
    let name = (download.as_array().unwrap().iter())
        .find(|p| p["name"] == "name")
        .unwrap();
    assert_eq!(name["schema"]["enum"], serde_json::json!(names));
    let mut selectable = names.clone();
    selectable.push(outputs::ALL);
    assert_eq!(
        doc["components"]["schemas"]["Options"]["properties"]["outputs"]["items"]["enum"],
        serde_json::json!(selectable)
    );
    let file = repo_root().join("openapi/openapi.json");
    if std::env::var_os("UPDATE_OPENAPI").is_some_and(|v| v == "1") {
        std::fs::create_dir_all(file.parent().unwrap()).unwrap();
        std::fs::write(&file, &served).unwrap();
    }
    let checked_in = std::fs::read_to_string(&file).unwrap_or_default();
    assert!(
        checked_in == served,
        "openapi/openapi.json is out of date: run `UPDATE_OPENAPI=1 cargo test --release --test http served_openapi` and commit it"
    );
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readme_walkthrough_script_runs_against_a_real_server() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let work = tempfile::tempdir().unwrap();
    let bump = repo_root().join("res/bump");
    assert!(
        bump.join("light_directions.csv").is_file(),
        "res/bump missing: render it with `photostereo render res`"
    );
    std::os::unix::fs::symlink(repo_root().join("res"), work.path().join("res")).unwrap();
    let script = repo_root().join("tests/walkthrough.sh");
    let base = s.base.clone();
    let cwd = work.path().to_path_buf();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("bash")
            .arg(script)
            .arg(base)
            .current_dir(cwd)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let log = format!(
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "walkthrough failed:\n{log}");
    for f in ["albedo.png", "normal.png", "height.png"] {
        let bytes =
            std::fs::read(work.path().join(f)).unwrap_or_else(|e| panic!("{f}: {e}\n{log}"));
        image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).unwrap();
    }
    let glb = std::fs::read(work.path().join("mesh.glb")).unwrap();
    assert_eq!(&glb[..4], b"glTF");
    s.stop().await;
}

#[test]
fn documented_walkthrough_is_the_scripts_text() {
    let script = std::fs::read_to_string(repo_root().join("tests/walkthrough.sh")).unwrap();
    let commands = &script[script.find("BASE=").expect("the script sets BASE")..];
    let docs: Vec<_> = ["README.md", "docs/http-api.md"]
        .iter()
        .filter_map(|p| {
            std::fs::read_to_string(repo_root().join(p))
                .ok()
                .map(|t| (p, t))
        })
        .filter(|(_, text)| text.contains("-F lights=@res/bump/light_directions.csv"))
        .collect();
    assert!(!docs.is_empty(), "no document shows the curl walk-through");
    for (path, text) in docs {
        assert!(
            text.contains(commands),
            "{path}: the curl walk-through differs from tests/walkthrough.sh"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_jobs_expire_after_the_retention_period() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.retention = Duration::from_millis(300);
    c.sweep_interval = Duration::from_millis(100);
    let s = TestServer::start(c).await;
    let job = s.submit(folder_form(&repo_root().join("res/bump"))).await;
    let id = job["id"].as_str().unwrap().to_string();
    s.wait_succeeded(&id).await;
    let start = std::time::Instant::now();
    loop {
        let r = s
            .client
            .get(s.url(&format!("/v1/jobs/{id}")))
            .send()
            .await
            .unwrap();
        if r.status() == 404 {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "job {id} never expired"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The record goes first, then the files.
    let files = dir.path().join("jobs").join(&id);
    while files.exists() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "{files:?} never removed"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_data_directory_serves_one_server_at_a_time() {
    let dir = tempfile::tempdir().unwrap();
    let first = AppState::open(config(dir.path())).await.unwrap();
    let err = match AppState::open(config(dir.path())).await {
        Ok(_) => panic!("a second server opened a data directory in use"),
        Err(e) => format!("{e:#}"),
    };
    assert!(
        err.contains("in use by another photostereo server"),
        "{err}"
    );
    first.shutdown().await;
    let again = AppState::open(config(dir.path())).await.unwrap();
    again.shutdown().await;
}

/// A metric's value in the `/metrics` text.
async fn metric(s: &TestServer, name: &str) -> f64 {
    let text = s.metrics_text().await;
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("{name} missing from\n{text}"))
}

/// Every artifact of a succeeded job, with `result.json`'s timings left out.
async fn artifacts_without_timings(s: &TestServer, job: &Value) -> BTreeMap<String, Vec<u8>> {
    let mut out = check_artifacts(s, job).await;
    let mut report: Value = serde_json::from_slice(&out["result.json"]).unwrap();
    report.as_object_mut().unwrap().remove("timings_ms");
    out.insert("result.json".into(), serde_json::to_vec(&report).unwrap());
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn images_decoded_during_the_upload_give_the_same_results() {
    let (dir_ahead, dir_plain) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let ahead = TestServer::start(config(dir_ahead.path())).await;
    let mut plain_config = config(dir_plain.path());
    plain_config.decode_ahead = 0;
    let plain = TestServer::start(plain_config).await;
    let set = repo_root().join("res/bump");

    let mut results = Vec::new();
    for s in [&ahead, &plain] {
        let job = s.submit(folder_form(&set)).await;
        let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
        results.push(artifacts_without_timings(s, &job).await);
    }
    assert_eq!(
        metric(&ahead, "photostereo_prefetched_images_total").await,
        4.0
    );
    assert_eq!(
        metric(&plain, "photostereo_prefetched_images_total").await,
        0.0
    );
    assert_eq!(
        results[0].keys().collect::<Vec<_>>(),
        results[1].keys().collect::<Vec<_>>()
    );
    for (name, bytes) in &results[0] {
        assert!(
            bytes == &results[1][name],
            "{name} differs with images decoded ahead"
        );
    }

    // A set that cannot be decoded fails with the same error either way: the first bad
    // image in table order (the headers are fine, the data cut short: the upload's probe
    // lets them through).
    // (Cut into the pixel data: without only its last bytes, the zlib checksum and IEND,
    // every row still reads and the job reads no more than its rows.)
    let mut cut = png(16, 16, 90);
    cut.truncate(cut.len() - 30);
    let table = "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\nd.png, 1, 1, 1";
    let mut errors = Vec::new();
    for s in [&ahead, &plain] {
        let form = Form::new()
            .text("lights", table)
            .part(
                "images",
                Part::bytes(cut[..cut.len() - 10].to_vec()).file_name("d.png"),
            )
            .part("images", Part::bytes(png(16, 16, 30)).file_name("a.png"))
            .part("images", Part::bytes(cut.clone()).file_name("c.png"))
            .part("images", Part::bytes(png(16, 16, 60)).file_name("b.png"));
        let job = s.submit(form).await;
        let job = s.wait_finished(job["id"].as_str().unwrap()).await;
        assert_eq!(job["status"], "failed", "{job}");
        let mut error = job["error"].clone();
        error.as_object_mut().unwrap().remove("instance");
        errors.push(error.to_string());
    }
    assert_eq!(errors[0], errors[1]);
    assert!(errors[0].contains("c.png"), "{}", errors[0]);

    // Every set was taken by its job or dropped with it.
    assert_eq!(metric(&ahead, "photostereo_prefetch_sets").await, 0.0);
    ahead.stop().await;
    plain.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_upload_drops_its_decoded_images() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.decode_ahead = 1;
    let s = TestServer::start(c).await;
    let set = repo_root().join("res/bump");
    // Every image arrives (and is decoded ahead), then a part the API does not know.
    let form = folder_form(&set).text("bogus", "x");
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    expect_problem(r, 400, &["bogus"]).await;
    assert_eq!(metric(&s, "photostereo_prefetch_sets").await, 0.0);
    // The one slot is free again: the next upload is decoded ahead.
    let job = s.submit(folder_form(&set)).await;
    s.wait_succeeded(job["id"].as_str().unwrap()).await;
    assert_eq!(metric(&s, "photostereo_prefetched_images_total").await, 4.0);
    assert_eq!(metric(&s, "photostereo_prefetch_sets").await, 0.0);
    s.stop().await;
}

/// A zip of a folder in the field's benchmark layout (y-up `light_directions.txt`, RGB
/// intensities, `filenames.txt`, `mask.png`, and files that are not part of the set):
/// accepted, read in the project's frame, its mask used, the unnamed image noted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_benchmark_layout_archive_reconstructs_in_the_projects_frame() {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("bench");
    std::fs::create_dir(&folder).unwrap();
    let scene = benchmark_folder(&folder);
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default();
    let mut files: Vec<_> = std::fs::read_dir(&folder)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    for f in files {
        let name = format!("bench/{}", f.file_name().unwrap().to_string_lossy());
        w.start_file(name, opts).unwrap();
        std::io::Write::write_all(&mut w, &std::fs::read(&f).unwrap()).unwrap();
    }
    let zip = w.finish().unwrap().into_inner();

    let s = TestServer::start(config(&dir.path().join("data"))).await;
    let form = archive_form(zip).text("options", r#"{"outputs": ["normal.exr"]}"#);
    let job = s.submit(form).await;
    assert_eq!(job["options"]["mask"], "given");
    let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
    let inside = scene.mask.iter().filter(|m| **m).count() as u64;
    assert_eq!(job["result"]["object_pixels"], inside);
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let mut report = Value::Null;
    for name in ["normal.exr", "result.json"] {
        let url = job["artifacts"][name].as_str().unwrap();
        let r = s.client.get(s.url(url)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{name}");
        let bytes = r.bytes().await.unwrap();
        std::fs::write(out.join(name), &bytes).unwrap();
        if name == "result.json" {
            report = serde_json::from_slice(&bytes).unwrap();
        }
    }
    let err = mean_normal_error_deg(&out, &scene);
    assert!(err < 0.5, "mean normal error {err}°");
    assert_eq!(report["mask_file"], "mask.png");
    let notes = report["notes"].as_array().unwrap();
    assert!(
        notes.len() == 1 && notes[0].as_str().unwrap().contains("Normal_gt.png"),
        "{notes:?}"
    );
    s.stop().await;
}

/// A `lights` part in the relighting tools' `.lp` format (y up, names with paths), known
/// by its file name or, as a text part, by its first line: the same job as the CSV's,
/// artifact for artifact; a bad one refused at once, naming its line.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_lp_lights_part_runs_the_job_of_its_csv() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let set = repo_root().join("res/bump");
    let csv = std::fs::read_to_string(set.join("light_directions.csv")).unwrap();
    let rows: Vec<(String, [f64; 3])> = (csv.lines())
        .map(|l| {
            let f: Vec<&str> = l.split(',').map(str::trim).collect();
            let v = [1, 2, 3].map(|k| f[k].parse::<f64>().unwrap());
            (format!("./jpeg-exports/{}", f[0]), v)
        })
        .collect();
    let lp = photostereo::core::lights::lp::format(&rows).replace('\n', "\r\n");
    let images = || {
        let mut form = Form::new();
        for img in images_of(&set) {
            form = form.part("images", file_part(&img));
        }
        form
    };
    let mut results = Vec::new();
    for form in [
        folder_form(&set),
        images().part("lights", Part::text(lp.clone()).file_name("bump.lp")),
        images().text("lights", lp.clone()),
    ] {
        let job = s.submit(form).await;
        let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
        results.push(artifacts_without_timings(&s, &job).await);
    }
    for other in &results[1..] {
        assert_eq!(results[0], *other, "the .lp job's artifacts differ");
    }

    let bad = lp.replacen("-0.2", "left", 1);
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(images().part("lights", Part::text(bad).file_name("bump.lp")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 422, &["bump.lp line 3", "\"left\""]).await;
    // Named .lp, its first line is the count or the table is refused as an .lp.
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(images().part("lights", Part::text(csv).file_name("bump.lp")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 422, &["bump.lp line 1", "number of lights"]).await;
    s.stop().await;
}

/// A camera as the `camera` option, as a `camera` part (a K.txt) or as the archive's own
/// K.txt gives the same depth job, its new artifacts downloadable; a camera that cannot
/// be, or cannot have taken the images, is refused before the job is queued, naming why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_makes_depth_and_bad_cameras_get_422() {
    let set = tempfile::tempdir().unwrap();
    pinhole_sphere_set(set.path());
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let k_part = || Part::bytes(PINHOLE_K.as_bytes().to_vec()).file_name("K.txt");
    let mut entries: Vec<(String, Vec<u8>)> = images_of(set.path())
        .into_iter()
        .chain([
            set.path().join("light_directions.csv"),
            set.path().join("K.txt"),
        ])
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect();
    let zip = |entries: &[(String, Vec<u8>)]| {
        let refs: Vec<(&str, &[u8])> = (entries.iter())
            .map(|(n, b)| (n.as_str(), b.as_slice()))
            .collect();
        zip_entries(&refs)
    };
    let forms = [
        folder_form(set.path()).text(
            "options",
            r#"{"camera": {"fx": 80, "fy": 80, "cx": 31.5, "cy": 31.5}, "distance": 5}"#,
        ),
        folder_form(set.path())
            .part("camera", k_part())
            .text("options", r#"{"distance": 5}"#),
        archive_form(zip(&entries)).text("options", r#"{"distance": 5}"#),
    ];
    let mut ids = Vec::new();
    for form in forms {
        let job = s.submit(form).await;
        assert_eq!(job["options"]["camera"]["fx"], 80.0, "{job}");
        ids.push(job["id"].as_str().unwrap().to_string());
    }
    let mut depths = Vec::new();
    for id in &ids {
        let job = s.wait_succeeded(id).await;
        assert!(job["result"]["height_min"].is_null(), "{job}");
        let (near, far) = (&job["result"]["depth_min"], &job["result"]["depth_max"]);
        assert!(
            near.as_f64().unwrap() < 5.0 && 5.0 < far.as_f64().unwrap(),
            "{job}"
        );
        let files = check_artifacts(&s, &job).await;
        for name in ["depth.exr", "depth.png", "points.ply", "mesh.glb"] {
            assert!(files.contains_key(name), "{name}: {:?}", files.keys());
        }
        assert!(!files.contains_key("height.png"));
        let report: Value = serde_json::from_slice(&files["result.json"]).unwrap();
        assert_eq!(report["options"]["distance"], 5.0);
        depths.push(outputs::decode_height_exr(&files["depth.exr"]).unwrap());
        if id == &ids[2] {
            let notes = report["notes"].to_string();
            assert!(
                notes.contains("camera from K.txt in the archive"),
                "{notes}"
            );
        }
    }
    assert!(depths.windows(2).all(|d| {
        d[0].iter()
            .zip(d[1].iter())
            .all(|(a, b)| a.to_bits() == b.to_bits())
    }));

    // Refusals, each a 422 naming the problem.
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);
    let mut cases: Vec<Refusal> = Vec::new();
    for (options, needles) in [
        (
            r#"{"camera": {"fx": 80, "fy": 80, "cx": 100, "cy": 31.5}}"#,
            &["principal point", "64 × 64"][..],
        ),
        (
            r#"{"camera": {"fx": 0, "fy": 80, "cx": 31.5, "cy": 31.5}}"#,
            &["camera", "fx must be a focal length"],
        ),
        (r#"{"camera": "80 80 31.5"}"#, &["camera", "3 numbers"]),
        (
            r#"{"camera": "80,80,inf,31.5"}"#,
            &["camera", "cx must be a finite number"],
        ),
        (r#"{"camera": {"fx": 80, "fy": 80}}"#, &["camera", "cx"]),
        (r#"{"camera": 7}"#, &["camera", "fx,fy,cx,cy"]),
        (r#"{"distance": 5}"#, &["distance needs a camera"]),
        (
            r#"{"camera": "80,80,31.5,31.5", "distance": 0}"#,
            &["distance must be a positive number"],
        ),
    ] {
        let form = folder_form(set.path()).text("options", options.to_string());
        cases.push((options, post(form), 422, needles));
    }
    let part = |text: &str| post(folder_form(set.path()).text("camera", text.to_string()));
    let both = folder_form(set.path())
        .part("camera", k_part())
        .text("options", r#"{"camera": "80,80,31.5,31.5"}"#);
    // The archive's K.txt for another resolution.
    entries.retain(|(n, _)| n != "K.txt");
    entries.push(("K.txt".into(), b"80 0 319.5\n0 80 239.5\n0 0 1\n".to_vec()));
    cases.extend([
        (
            "a camera part with NaN",
            part("nan 0 1 0 80 2 0 0 1"),
            422,
            &["camera part", "fx"][..],
        ),
        (
            "a camera part of words",
            part("hello"),
            422,
            &["camera part", "not a number"],
        ),
        ("a camera part and option", post(both), 422, &["not both"]),
        (
            "the archive's K.txt for another resolution",
            post(archive_form(zip(&entries))),
            422,
            &["principal point", "another resolution"],
        ),
    ]);
    expect_refusals(cases).await;
    s.stop().await;
}

/// A `normals` part of `bytes` named `name`.
fn normals_part(bytes: Vec<u8>, name: &str) -> Part {
    Part::bytes(bytes).file_name(name.to_string())
}

/// Every artifact of a succeeded normals job, fetched: exactly `expected`, each with its
/// content type.
async fn normals_artifacts(
    s: &TestServer,
    job: &Value,
    expected: &[&str],
) -> BTreeMap<String, Vec<u8>> {
    let artifacts = job["artifacts"].as_object().expect("artifacts");
    let names: HashSet<&str> = artifacts.keys().map(String::as_str).collect();
    assert_eq!(names, expected.iter().copied().collect(), "{job}");
    let mut out = BTreeMap::new();
    for (name, url) in artifacts {
        let r = s
            .client
            .get(s.url(url.as_str().unwrap()))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{name}");
        let content_type = outputs::content_type(name).unwrap();
        assert_eq!(r.headers()["content-type"], content_type, "{name}");
        out.insert(name.clone(), r.bytes().await.unwrap().to_vec());
    }
    out
}

const HEIGHT_ARTIFACTS: [&str; 7] = [
    "height.png",
    "height.exr",
    "mask.png",
    "normal.png",
    "mesh.glb",
    "points.ply",
    "result.json",
];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_normals_job_integrates_heights_as_the_cli_does() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let (size, radius) = (72, 30.0);
    let (normal, truth) = ortho_sphere(size, radius);
    let opengl = normal_map_png16((size, size), false, &normal);
    let directx = normal_map_png16((size, size), true, &normal);
    let options = r#"{"integration": "poisson"}"#;
    let job = s
        .submit(
            Form::new()
                .part("normals", normals_part(opengl.clone(), "sphere.png"))
                .text("options", options),
        )
        .await;
    assert_eq!(job["image_count"], 0, "{job}");
    let flipped = s
        .submit(
            Form::new()
                .part("normals", normals_part(directx, "sphere-dx.png"))
                .text("convention", "directx")
                .text(
                    "options",
                    r#"{"integration": "poisson", "outputs": ["height.exr"]}"#,
                ),
        )
        .await;
    let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
    assert!(job["result"]["depth_min"].is_null(), "{job}");
    // The reader's counts: the disc used, the rest black background.
    let (pixels, used) = (
        (size * size) as usize,
        truth.iter().filter(|t| t.is_finite()).count(),
    );
    let counts = &job["result"]["counts"];
    assert_eq!(counts["pixels"], pixels, "{job}");
    assert_eq!(counts["used"], used, "{job}");
    assert_eq!(counts["black"], pixels - used, "{job}");
    for kind in [
        "back_facing",
        "not_unit",
        "zero_length",
        "non_finite",
        "transparent",
        "outside_mask",
    ] {
        assert_eq!(counts[kind], 0, "{kind}: {job}");
    }
    let span = |key: &str| job["result"][key].as_f64().unwrap();
    assert!(span("height_max") - span("height_min") > 20.0, "{job}");
    let files = normals_artifacts(&s, &job, &HEIGHT_ARTIFACTS).await;
    let report: Value = serde_json::from_slice(&files["result.json"]).unwrap();
    assert_eq!(report["source"], "sphere.png");
    assert_eq!(
        &report["counts"], counts,
        "the summary's counts are result.json's"
    );
    assert_eq!(report["output"], "height");
    assert_eq!(report["method"], "poisson");
    let served = outputs::decode_height_exr(&files["height.exr"]).unwrap();

    // The CLI on the same file.
    let map = dir.path().join("sphere.png");
    std::fs::write(&map, &opengl).unwrap();
    let out = dir.path().join("cli");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_photostereo"))
        .args([
            "integrate",
            map.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--integration", "poisson"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cli = outputs::decode_height_exr(&std::fs::read(out.join("height.exr")).unwrap()).unwrap();
    let worst = (served.iter().zip(&cli)).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        worst < 1e-3,
        "heights differ from the CLI's by up to {worst} px"
    );
    // …and they are the sphere's, up to an offset (away from the silhouette).
    let inner = |r: usize, c: usize| {
        let mid = (f64::from(size) - 1.0) / 2.0;
        (r as f64 - mid).hypot(c as f64 - mid) < 0.8 * radius
    };
    let offsets: Vec<f64> = (ndarray::indices(truth.dim()).into_iter())
        .filter(|&(r, c)| inner(r, c))
        .map(|(r, c)| truth[[r, c]] - f64::from(served[[r, c]]))
        .collect();
    let mean = offsets.iter().sum::<f64>() / offsets.len() as f64;
    let spread = offsets.iter().fold(0f64, |m, o| m.max((o - mean).abs()));
    assert!(
        spread < 0.8,
        "heights off the sphere's by up to {spread} px"
    );

    // The DirectX map with its convention gives the same heights; its job wrote only the
    // outputs it named, and result.json.
    let flipped = s.wait_succeeded(flipped["id"].as_str().unwrap()).await;
    let files = normals_artifacts(&s, &flipped, &["height.exr", "result.json"]).await;
    let report: Value = serde_json::from_slice(&files["result.json"]).unwrap();
    assert_eq!(
        report["artifacts"],
        serde_json::json!(["height.exr", "result.json"])
    );
    let heights = outputs::decode_height_exr(&files["height.exr"]).unwrap();
    let worst = (heights.iter().zip(&served)).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        worst < 1e-3,
        "the DirectX map's heights differ by {worst} px"
    );
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_normals_job_with_a_camera_gives_depth() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let k = photostereo::core::camera::Pinhole::parse("120 0 48\n0 120 38\n0 0 1\n").unwrap();
    let (map, truth) = pinhole_sphere_normal_map(&k);
    // A mask that keeps the left half of the sphere, whose median true depth is the
    // working distance.
    let mask =
        image::GrayImage::from_fn(96, 80, |c, _| image::Luma([if c < 48 { 255 } else { 0 }]));
    let mut kept: Vec<f64> = (ndarray::indices(truth.dim()).into_iter())
        .filter(|&(r, c)| c < 48 && truth[[r, c]].is_finite())
        .map(|(r, c)| truth[[r, c]])
        .collect();
    let mid = kept.len() / 2;
    let median = *kept.select_nth_unstable_by(mid, f64::total_cmp).1;
    let form = Form::new()
        .part("normals", normals_part(map, "sphere.png"))
        .part(
            "mask",
            Part::bytes(outputs::png_bytes(&mask)).file_name("mask.png"),
        )
        .part(
            "camera",
            Part::bytes(b"120,120,48,38".to_vec()).file_name("camera.txt"),
        )
        .text("options", format!(r#"{{"distance": {median}}}"#));
    let job = s.submit(form).await;
    assert_eq!(job["options"]["camera"]["fx"], 120.0, "{job}");
    let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
    assert!(job["result"]["height_min"].is_null(), "{job}");
    // The mask's right half is counted outside it, before any other kind.
    let counts = &job["result"]["counts"];
    assert_eq!(counts["pixels"], 96 * 80, "{job}");
    assert_eq!(counts["used"], kept.len(), "{job}");
    assert_eq!(counts["outside_mask"], 48 * 80, "{job}");
    let expected = [
        "depth.png",
        "depth.exr",
        "mask.png",
        "normal.png",
        "mesh.glb",
        "points.ply",
        "result.json",
    ];
    let files = normals_artifacts(&s, &job, &expected).await;
    let report: Value = serde_json::from_slice(&files["result.json"]).unwrap();
    assert_eq!(report["output"], "depth");
    assert_eq!(&report["counts"], counts);
    assert_eq!(report["mask_file"], "mask.png");
    assert_eq!(report["distance"], median);
    let depth = outputs::decode_height_exr(&files["depth.exr"]).unwrap();
    let mut worst = 0f64;
    for ((d, t), (r, c)) in depth.iter().zip(&truth).zip(ndarray::indices((80, 96))) {
        assert_eq!(d.is_finite(), t.is_finite() && c < 48, "mask at ({r}, {c})");
        if d.is_finite() && (c as f64 - 48.0).hypot(r as f64 - 38.0) < 30.0 {
            worst = worst.max((f64::from(*d) - t).abs() / t);
        }
    }
    assert!(worst < 0.01, "largest relative depth error {worst:.4}");
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn normals_jobs_refuse_mixed_parts_and_bad_maps_naming_them() {
    let synth = seed!("synth-images");
    let dir = tempfile::tempdir().unwrap();
    let mut c = config(dir.path());
    c.max_pixels = 100 * 100; // the synth set's images
    let s = TestServer::start(c).await;
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);
    let (normal, _) = ortho_sphere(40, 15.0);
    let map = || normals_part(normal_map_png16((40, 40), false, &normal), "sphere.png");
    let normals = || Form::new().part("normals", map());
    let images = || images_of(&synth).into_iter().map(|p| file_part(&p));
    let archive = zip_folder(&synth, None);
    let map_of = |part: Part| post(Form::new().part("normals", part));
    let with_options = |options: &str| post(normals().text("options", options.to_string()));
    let writes = "mask.png, normal.png, height.png, height.exr, points.ply, mesh.glb, result.json";
    expect_refusals(vec![
        // Parts of an image job, before or after the map.
        (
            "images, then a map",
            post(folder_form(&synth).part("normals", map())),
            422,
            &["both a normals part and images"],
        ),
        (
            "a map, then an image",
            post(normals().part("images", images().next().unwrap())),
            422,
            &["both a normals part and images"],
        ),
        (
            "a map and lights",
            post(normals().text("lights", "a.png, 0, 0, 1")),
            422,
            &["both a normals part and", "lights"],
        ),
        (
            "a map and a calibration",
            post(normals().text("calibration", "0b6f2a43")),
            422,
            &["both a normals part and", "calibration"],
        ),
        (
            "a map and an archive",
            post(normals().part("archive", Part::bytes(archive).file_name("set.zip"))),
            422,
            &["normals part and archive"],
        ),
        // Maps that are no normal maps, or too large.
        (
            "a gray map",
            map_of(Part::bytes(png(40, 40, 128)).file_name("gray.png")),
            422,
            &["\"gray.png\"", "L8", "RGB"],
        ),
        (
            "text as a map",
            map_of(Part::bytes(b"hello".to_vec()).file_name("n.txt")),
            422,
            &["\"n.txt\"", "not a format that can be read"],
        ),
        (
            "a map over the pixel limit",
            map_of(normals_part(
                normal_map_png16((120, 120), false, |_, _| Some([0.0, 0.0, 1.0])),
                "big.png",
            )),
            413,
            &["big.png", "120×120"],
        ),
        // A mask of another size, options a normals job does not take, a bad convention, a
        // convention without a map, a camera that does not fit the map.
        (
            "a mask of another size",
            post(normals().part("mask", Part::bytes(png(30, 20, 255)).file_name("mask.png"))),
            422,
            &["mask \"mask.png\" is 30×20", "\"sphere.png\" is 40×40"],
        ),
        (
            "a solver",
            with_options(r#"{"solver": "l2"}"#),
            422,
            &["`solver` does not apply to a normals job"],
        ),
        // Outputs it never writes, or of the other projection, judged against its camera.
        (
            "outputs it never writes",
            with_options(r#"{"outputs": ["mesh.glb", "albedo.png"]}"#),
            422,
            &["`outputs`", "\"albedo.png\"", writes],
        ),
        (
            "depth without a camera",
            with_options(r#"{"outputs": ["depth.exr"]}"#),
            422,
            &["`outputs`", "\"depth.exr\"", "needs a camera"],
        ),
        (
            "heights under a camera",
            post(
                normals()
                    .text("camera", "50,50,20,20")
                    .text("options", r#"{"outputs": ["depth.exr", "height.png"]}"#),
            ),
            422,
            &["`outputs`", "\"height.png\"", "under a camera"],
        ),
        (
            "an unknown convention",
            post(normals().text("convention", "sideways")),
            422,
            &["\"sideways\"", "opengl", "directx"],
        ),
        (
            "a convention without a map",
            post(folder_form(&synth).text("convention", "directx")),
            422,
            &["convention part goes with a normals part"],
        ),
        (
            "a camera that does not fit the map",
            post(normals().text("camera", "500,500,300,250")),
            422,
            &["principal point"],
        ),
        (
            "a distance without a camera",
            with_options(r#"{"distance": 3}"#),
            422,
            &["distance needs a camera"],
        ),
    ])
    .await;

    // What only decoding finds fails the job, naming it: vectors that are not unit
    // length, no usable pixel.
    let grey = normal_map_png16((40, 40), false, |_, _| Some([0.8, -0.8, 0.8]));
    let black = normal_map_png16((40, 40), false, |_, _| None);
    for (bytes, needle) in [
        (grey, "does not decode to unit normals"),
        (black, "has no usable pixel"),
    ] {
        let job = s
            .submit(Form::new().part("normals", normals_part(bytes, "bad.png")))
            .await;
        let id = job["id"].as_str().unwrap();
        let job = s.wait_finished(id).await;
        assert_eq!(job["status"], "failed", "{job}");
        assert_eq!(job["error"]["status"], 422, "{job}");
        let detail = job["error"]["detail"].as_str().unwrap();
        assert!(
            detail.contains("\"bad.png\"") && detail.contains(needle),
            "{detail}"
        );
    }
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_interrupted_normals_job_runs_again_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let mut slow = config(dir.path());
    slow.workers = 1;
    slow.stage_delay = Duration::from_millis(400);
    slow.shutdown_grace = Duration::from_millis(100);
    let s = TestServer::start(slow.clone()).await;
    let (normal, _) = ortho_sphere(48, 20.0);
    let map = normal_map_png16((48, 48), false, &normal);
    let job = s
        .submit(Form::new().part("normals", normals_part(map, "sphere.png")))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    s.wait_for(&id, Duration::from_secs(30), |j| j["status"] == "running")
        .await;
    s.stop().await;

    let s = TestServer::start(config(dir.path())).await;
    let job = s.wait_succeeded(&id).await;
    assert_eq!(job["attempts"], 2, "the interrupted job ran again: {job}");
    normals_artifacts(&s, &job, &HEIGHT_ARTIFACTS).await;
    s.stop().await;
}

/// A normals job decodes its map under the server's pixel limit, not the core's larger
/// default: a job accepted under one limit and run after a restart under a lower one
/// fails with the 413 that an upload of that map now gets.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_normals_job_is_held_to_the_servers_pixel_limit() {
    let dir = tempfile::tempdir().unwrap();
    let mut slow = config(dir.path());
    slow.workers = 1;
    slow.stage_delay = Duration::from_millis(400);
    slow.shutdown_grace = Duration::from_millis(100);
    let s = TestServer::start(slow).await;
    let (normal, _) = ortho_sphere(48, 20.0);
    let map = normal_map_png16((48, 48), false, &normal);
    let form = || Form::new().part("normals", normals_part(map.clone(), "sphere.png"));
    let job = s.submit(form()).await;
    let id = job["id"].as_str().unwrap().to_string();
    s.wait_for(&id, Duration::from_secs(30), |j| j["status"] == "running")
        .await;
    s.stop().await;

    let mut small = config(dir.path());
    small.max_pixels = 40 * 40;
    let s = TestServer::start(small).await;
    let job = s.wait_finished(&id).await;
    assert_eq!(job["status"], "failed", "{job}");
    assert_eq!(job["error"]["status"], 413, "{job}");
    let needles = ["\"sphere.png\"", "48×48", "limit of 1600 pixels"];
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(form())
        .send()
        .await
        .unwrap();
    let refused = expect_problem(r, 413, &needles).await;
    assert_eq!(job["error"]["detail"], refused["detail"], "{job}");
    s.stop().await;
}

/// The median of `values` (the upper one of an even count).
fn median_of(mut values: Vec<f64>) -> f64 {
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// A ring of LEDs over a relief plate, uploaded as its images and its table of positions
/// (or as a zip of its folder), is a near-light job: its summary says so, with the
/// iterations and the median depth (within 0.5 % of the truth) in the table's unit, and
/// depth.exr is an artifact. The camera and working distance may come from the job
/// instead of the table; without either, the upload is refused naming it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_near_light_table_makes_a_near_light_job() {
    let rig = photostereo::core::synth::ring_relief(64);
    let set = tempfile::tempdir().unwrap();
    rig.write(set.path()).unwrap();
    let table_file = set.path().join("light_directions.json");
    let table: Value = serde_json::from_slice(&std::fs::read(&table_file).unwrap()).unwrap();
    let without = |key: &str| {
        let mut t = table.clone();
        assert!(t.as_object_mut().unwrap().remove(key).is_some(), "{key}");
        t
    };
    let form = |table: &Value| {
        let text = serde_json::to_string(table).unwrap();
        let mut form = Form::new().part(
            "lights",
            Part::text(text).file_name("light_directions.json"),
        );
        for img in images_of(set.path()) {
            form = form.part("images", file_part(&img));
        }
        form
    };
    let truth = median_of(
        (rig.depth.iter().zip(&rig.mask))
            .filter(|(_, m)| **m)
            .map(|(d, _)| f64::from(*d))
            .collect(),
    );
    let camera = &table["camera"];
    let camera_text = format!(
        "{},{},{},{}",
        camera["fx"], camera["fy"], camera["cx"], camera["cy"]
    );
    let distance = format!(r#"{{"distance": {}}}"#, table["distance"]);
    let mut entries: Vec<(String, Vec<u8>)> = images_of(set.path())
        .into_iter()
        .chain([table_file.clone()])
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect();
    entries.push(("notes.txt".into(), b"skipped".to_vec()));
    let refs: Vec<(&str, &[u8])> = (entries.iter())
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();

    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let forms = [
        form(&table),
        archive_form(zip_entries(&refs)),
        form(&without("distance")).text("options", distance.clone()),
        form(&without("camera")).text("camera", camera_text.clone()),
    ];
    let mut ids = Vec::new();
    for form in forms {
        let job = s.submit(form).await;
        assert_eq!(job["image_count"], rig.lights.len(), "{job}");
        ids.push(job["id"].as_str().unwrap().to_string());
    }
    for id in &ids {
        let job = s.wait_succeeded(id).await;
        let result = &job["result"];
        assert_eq!(result["lights"], "near", "{job}");
        assert_eq!(result["unit"], "mm", "{job}");
        assert_eq!(result["converged"], true, "{job}");
        assert_eq!(
            (result["width"].as_u64(), result["height"].as_u64()),
            (Some(64), Some(64))
        );
        assert!(result["iterations"].as_u64().unwrap() >= 1, "{job}");
        assert!(result["light_condition_number"].is_null(), "{job}");
        let median = result["median_depth"].as_f64().unwrap();
        assert!(
            (median - truth).abs() <= 0.005 * truth,
            "median depth {median} mm, truth {truth} mm"
        );
        let (near, far) = (
            result["depth_min"].as_f64().unwrap(),
            result["depth_max"].as_f64().unwrap(),
        );
        assert!(near < median && median < far, "{job}");
        let url = job["artifacts"]["depth.exr"].as_str().expect("depth.exr");
        let r = s.client.get(s.url(url)).send().await.unwrap();
        assert_eq!(r.status(), 200);
        let depth = outputs::decode_height_exr(&r.bytes().await.unwrap()).unwrap();
        assert_eq!(depth.dim(), (64, 64));
        let exr_median = median_of(
            (depth.iter())
                .filter(|d| d.is_finite())
                .map(|d| f64::from(*d))
                .collect(),
        );
        assert!(
            (exr_median - truth).abs() <= 0.01 * truth,
            "depth.exr median {exr_median} mm, truth {truth} mm"
        );
        let r = s
            .client
            .get(s.url(job["artifacts"]["result.json"].as_str().unwrap()));
        let report: Value = r.send().await.unwrap().json().await.unwrap();
        assert_eq!(report["lights"], "near");
        assert_eq!(report["median_depth"], result["median_depth"]);
    }

    // Without a working distance or a camera, refused before the job is queued, naming
    // what is missing (and only that).
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form);
    // A light behind the camera: the parser's refusal, naming the row.
    let mut behind = table.clone();
    behind["lights"][1]["position"][2] = serde_json::json!(5.0);
    let bodies = expect_refusals(vec![
        (
            "no distance",
            post(form(&without("distance"))),
            422,
            &["distance"],
        ),
        (
            "no camera",
            post(form(&without("camera"))),
            422,
            &["camera"],
        ),
        (
            "a light behind the camera",
            post(form(&behind)),
            422,
            &["row 2", "behind the camera"],
        ),
        // A camera that cannot have taken 64 × 64 images.
        (
            "a camera for other images",
            post(form(&without("camera")).text("camera", "80,80,300,31.5")),
            422,
            &["principal point"],
        ),
    ])
    .await;
    for (body, given) in bodies.iter().zip(["camera", "distance"]) {
        assert!(!body["detail"].as_str().unwrap().contains(given), "{body}");
    }
    s.stop().await;
}

/// A near-light job takes the options it reads (mask, integration, mesh, outputs, camera,
/// distance): one of the distant solve's is refused before the 202 naming the field and
/// what the job takes, and so is an `outputs` selection naming what it never writes; a
/// selection of what it writes is honoured.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_near_light_job_refuses_options_and_outputs_it_cannot_honour() {
    let rig = photostereo::core::synth::ring_relief(64);
    let set = tempfile::tempdir().unwrap();
    rig.write(set.path()).unwrap();
    let form = |options: &str| {
        let mut form = Form::new()
            .part(
                "lights",
                file_part(&set.path().join("light_directions.json")),
            )
            .text("options", options.to_string());
        for img in images_of(set.path()) {
            form = form.part("images", file_part(&img));
        }
        form
    };
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let post = |form: Form| s.client.post(s.url("/v1/jobs")).multipart(form).send();
    let takes = "which takes mask, integration, mesh, outputs, camera, distance";
    for field in [
        r#""solver": "l2""#,
        r#""shading_light": [0, 0, 1]"#,
        r#""max_condition": 1e6"#,
    ] {
        let name = field.split('"').nth(1).unwrap();
        let r = post(form(&format!("{{{field}}}"))).await.unwrap();
        let needle = format!("field `{name}` does not apply to a near-light job");
        expect_problem(r, 422, &[&needle, takes]).await;
    }
    let writes =
        "albedo.png, normal.png, mask.png, depth.exr, depth.png, points.ply, mesh.glb, result.json";
    let r = post(form(r#"{"outputs": ["height.png"]}"#)).await.unwrap();
    expect_problem(r, 422, &["field `outputs`", "\"height.png\"", writes]).await;
    let r = post(form(r#"{"outputs": ["depth.exr", "lights.json"]}"#))
        .await
        .unwrap();
    expect_problem(r, 422, &["field `outputs`", "\"lights.json\""]).await;

    // An LED aimed back at the camera lights nothing it sees: refused before the job.
    let table = std::fs::read_to_string(set.path().join("light_directions.json")).unwrap();
    let mut table: Value = serde_json::from_str(&table).unwrap();
    table["lights"][3]["axis"] = serde_json::json!([0.0, 0.0, 1.0]);
    let name = table["lights"][3]["name"].as_str().unwrap().to_string();
    let mut flipped = Form::new().part(
        "lights",
        Part::text(table.to_string()).file_name("lights.json"),
    );
    for img in images_of(set.path()) {
        flipped = flipped.part("images", file_part(&img));
    }
    let r = post(flipped).await.unwrap();
    expect_problem(r, 422, &["faces away", &name]).await;

    // What it takes, with a selection of what it writes: only those are written.
    let options = r#"{"mask": "auto", "integration": "poisson", "mesh": {"max_vertices": 2000}, "outputs": ["depth.exr", "mesh.glb"]}"#;
    let job = s.submit(form(options)).await;
    let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
    let artifacts = job["artifacts"].as_object().unwrap();
    for name in ["depth.exr", "mesh.glb", "result.json"] {
        assert!(artifacts.contains_key(name), "{name}: {job}");
    }
    for name in [
        "albedo.png",
        "normal.png",
        "mask.png",
        "depth.png",
        "points.ply",
    ] {
        assert!(!artifacts.contains_key(name), "{name}: {job}");
    }
    s.stop().await;
}

/// `intensities: estimate` on a distant-light job: the summary lists each light's
/// estimated intensity, `lights.json` is an artifact, and as the light table of a job it
/// gives the normals of the estimate's job.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_estimates_its_lights_intensities_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let s = TestServer::start(config(dir.path())).await;
    let set = repo_root().join("res/sphere");
    let form = folder_form(&set).text("options", r#"{"intensities": "estimate"}"#);
    let job = s.submit(form).await;
    let job = s.wait_succeeded(job["id"].as_str().unwrap()).await;
    let estimated = job["result"]["estimated_intensities"]
        .as_array()
        .unwrap_or_else(|| panic!("no estimated intensities in {job}"));
    assert_eq!(
        estimated.len() as u64,
        job["result"]["light_count"].as_u64().unwrap()
    );
    for e in estimated {
        let i = e["intensity"].as_f64().unwrap();
        assert!((i - 1.0).abs() < 0.01, "the set's lights are equal: {job}");
    }
    let artifact = |job: &Value, name: &str| {
        (job["artifacts"][name].as_str())
            .unwrap_or_else(|| panic!("no {name} in {job}"))
            .to_string()
    };
    let table = s.get_bytes(&artifact(&job, "lights.json")).await;
    let normals = s.get_bytes(&artifact(&job, "normal.png")).await;

    let mut form = Form::new();
    for img in images_of(&set) {
        form = form.part("images", file_part(&img));
    }
    let form = form.part("lights", Part::bytes(table).file_name("lights.json"));
    let again = s.submit(form).await;
    let again = s.wait_succeeded(again["id"].as_str().unwrap()).await;
    assert!(
        again["result"]["estimated_intensities"].is_null(),
        "{again}"
    );
    let reread = s.get_bytes(&artifact(&again, "normal.png")).await;
    assert_eq!(
        normals, reread,
        "lights.json as the table gives other normals"
    );
    s.stop().await;
}
