//! Shared helpers of the HTTP API tests: a real server on 127.0.0.1:0, multipart forms and
//! zips, polling, problem bodies. Finding the seed data: `tests/seed/mod.rs`.

#![allow(dead_code)]

pub mod postgres;
pub mod raw_http;
pub mod weed;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use ndarray::Array2;
use photostereo::core::camera::Pinhole;
use photostereo::core::synth::{self, Capture, Scene};
use photostereo::service::{AppState, Config, serve_with};
use reqwest::multipart::{Form, Part};
use serde_json::Value;
use tokio::net::TcpListener;
use tokio::sync::oneshot;

pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Test settings: a fresh data directory, two workers, no disk-space floor.
pub fn config(dir: &Path) -> Config {
    let mut c = Config::new(dir);
    c.workers = 2;
    c.min_free_disk = 0;
    c.shutdown_grace = Duration::from_secs(30);
    c
}

/// A real server on an ephemeral port, stopped gracefully by [`TestServer::stop`].
pub struct TestServer {
    pub base: String,
    pub state: AppState,
    pub client: reqwest::Client,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<anyhow::Result<()>>,
}

impl TestServer {
    pub async fn start(config: Config) -> Self {
        let state = AppState::open(config)
            .await
            .expect("open the service state");
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let base = format!("http://{}", listener.local_addr().unwrap());
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(serve_with(listener, state.clone(), async move {
            let _ = rx.await;
        }));
        let client = reqwest::Client::builder()
            .timeout(Duration::from_secs(120))
            .build()
            .unwrap();
        Self {
            base,
            state,
            client,
            stop: Some(tx),
            task,
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// Graceful stop: no new connections, in-flight requests finish, jobs get the grace.
    pub async fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        drop(self.client);
        tokio::time::timeout(Duration::from_secs(60), self.task)
            .await
            .expect("the server stops within 60 s")
            .unwrap()
            .unwrap();
    }

    /// The `/metrics` text.
    pub async fn metrics_text(&self) -> String {
        let r = self.client.get(self.url("/metrics")).send().await.unwrap();
        assert_eq!(r.status(), 200, "GET /metrics");
        r.text().await.unwrap()
    }

    pub async fn get_json(&self, path: &str) -> Value {
        let r = self.client.get(self.url(path)).send().await.unwrap();
        assert_eq!(r.status(), 200, "GET {path}");
        r.json().await.unwrap()
    }

    pub async fn get_bytes(&self, path: &str) -> Vec<u8> {
        let r = self.client.get(self.url(path)).send().await.unwrap();
        assert_eq!(r.status(), 200, "GET {path}");
        r.bytes().await.unwrap().to_vec()
    }

    /// Submit a form; asserts 202 + Location and returns the job.
    pub async fn submit(&self, form: Form) -> Value {
        let r = self
            .client
            .post(self.url("/v1/jobs"))
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = r.status();
        let location = r
            .headers()
            .get("location")
            .map(|v| v.to_str().unwrap().to_string());
        let body: Value = r.json().await.unwrap();
        assert_eq!(status, 202, "submit: {body}");
        let id = body["id"].as_str().unwrap();
        assert_eq!(location.as_deref(), Some(format!("/v1/jobs/{id}").as_str()));
        assert_eq!(body["status"], "queued");
        body
    }

    /// Poll a job until `done(job)` or the timeout.
    pub async fn wait_for(
        &self,
        id: &str,
        timeout: Duration,
        done: impl Fn(&Value) -> bool,
    ) -> Value {
        let start = Instant::now();
        loop {
            let job = self.get_json(&format!("/v1/jobs/{id}")).await;
            if done(&job) {
                return job;
            }
            assert!(
                start.elapsed() < timeout,
                "job {id} still {job} after {timeout:?}"
            );
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    }

    /// Poll until the job is finished (succeeded, failed or cancelled).
    pub async fn wait_finished(&self, id: &str) -> Value {
        self.wait_for(id, Duration::from_secs(120), |j| {
            matches!(
                j["status"].as_str(),
                Some("succeeded" | "failed" | "cancelled")
            )
        })
        .await
    }

    pub async fn wait_succeeded(&self, id: &str) -> Value {
        let job = self.wait_finished(id).await;
        assert_eq!(job["status"], "succeeded", "job {id}: {job}");
        job
    }
}

/// A 128² sphere rendered under `lights` with a little noise (σ 0.002), and its truth:
/// the object a calibration's lights are checked on.
pub fn sphere_under(lights: &[[f64; 3]]) -> (tempfile::TempDir, synth::Truth) {
    let object = tempfile::tempdir().unwrap();
    let capture = Capture {
        noise_sigma: 0.002,
        ..Default::default()
    };
    synth::write_set(object.path(), &Scene::sphere(128), lights, &capture).unwrap();
    let truth = synth::read_truth(object.path()).unwrap();
    (object, truth)
}

/// The image files of a data-set folder, sorted by name.
pub fn images_of(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.is_file()
                && p.extension().is_some_and(|e| {
                    ["png", "bmp", "jpg", "jpeg", "tif", "tiff"]
                        .contains(&e.to_string_lossy().to_ascii_lowercase().as_str())
                })
        })
        .collect();
    files.sort();
    files
}

pub fn file_part(path: &Path) -> Part {
    Part::bytes(std::fs::read(path).unwrap())
        .file_name(path.file_name().unwrap().to_string_lossy().into_owned())
}

/// `lights` + one `images` part per image, as a client uploading a folder would.
pub fn folder_form(dir: &Path) -> Form {
    let mut form = Form::new().part("lights", file_part(&dir.join("light_directions.csv")));
    for img in images_of(dir) {
        form = form.part("images", file_part(&img));
    }
    form
}

/// A zip of a data-set folder, at the top or inside `top`.
pub fn zip_folder(dir: &Path, top: Option<&str>) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    if let Some(top) = top {
        w.add_directory(format!("{top}/"), opts).unwrap();
    }
    let mut files = images_of(dir);
    files.push(dir.join("light_directions.csv"));
    for f in files {
        let name = f.file_name().unwrap().to_string_lossy().into_owned();
        let name = match top {
            Some(t) => format!("{t}/{name}"),
            None => name,
        };
        w.start_file(name, opts).unwrap();
        w.write_all(&std::fs::read(&f).unwrap()).unwrap();
    }
    w.finish().unwrap().into_inner()
}

/// A zip with the given entries, as is.
pub fn zip_entries(entries: &[(&str, &[u8])]) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, data) in entries {
        w.start_file(*name, zip::write::SimpleFileOptions::default())
            .unwrap();
        w.write_all(data).unwrap();
    }
    w.finish().unwrap().into_inner()
}

pub fn archive_form(zip: Vec<u8>) -> Form {
    Form::new().part("archive", Part::bytes(zip).file_name("set.zip"))
}

/// Assert a problem+json answer with this status whose detail contains every needle;
/// returns the body.
pub async fn expect_problem(r: reqwest::Response, status: u16, needles: &[&str]) -> Value {
    assert_eq!(
        r.status().as_u16(),
        status,
        "expected {status}, got {} {:?}",
        r.status(),
        r.headers()
    );
    let ct = r
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    assert_eq!(ct, "application/problem+json");
    let body: Value = r.json().await.unwrap();
    assert_eq!(body["status"], status, "{body}");
    assert!(
        body["type"]
            .as_str()
            .unwrap()
            .starts_with("urn:photostereo:problem:"),
        "{body}"
    );
    assert!(!body["title"].as_str().unwrap().is_empty(), "{body}");
    let detail = body["detail"].as_str().unwrap();
    for n in needles {
        assert!(detail.contains(n), "detail {detail:?} lacks {n:?}");
    }
    body
}

/// A small gray PNG.
pub fn png(w: u32, h: u32, v: u8) -> Vec<u8> {
    let img = image::GrayImage::from_pixel(w, h, image::Luma([v]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// Append one PNG chunk (length, kind, data, CRC) to `out`.
pub fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    let crc = crc32fast::hash(&out[start..]);
    out.extend_from_slice(&crc.to_be_bytes());
}

/// A `w`×`h` 8-bit indexed PNG: pixel (x, y) is palette entry (x + y) % 4 of the gray
/// ramp 0, 85, 170, 255, with `extra` bytes appended to the PLTE chunk (its CRC still
/// right), so that `extra` = 1 or 2 gives a palette whose length is not a multiple of 3.
pub fn palette_png(w: u32, h: u32, extra: usize) -> Vec<u8> {
    let ramp: Vec<u8> = (0..4u8).flat_map(|i| [85 * i; 3]).collect();
    let mut encoded = Vec::new();
    let mut enc = png::Encoder::new(&mut encoded, w, h);
    enc.set_color(png::ColorType::Indexed);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_palette(ramp);
    let indices: Vec<u8> = (0..h)
        .flat_map(|y| (0..w).map(move |x| ((x + y) % 4) as u8))
        .collect();
    let mut writer = enc.write_header().unwrap();
    writer.write_image_data(&indices).unwrap();
    writer.finish().unwrap();
    // Re-emit the chunks, lengthening PLTE.
    let mut out = encoded[..8].to_vec();
    let mut at = 8;
    while at < encoded.len() {
        let len = u32::from_be_bytes(encoded[at..at + 4].try_into().unwrap()) as usize;
        let kind: [u8; 4] = encoded[at + 4..at + 8].try_into().unwrap();
        let mut data = encoded[at + 8..at + 8 + len].to_vec();
        if &kind == b"PLTE" {
            data.extend(std::iter::repeat_n(7u8, extra));
        }
        png_chunk(&mut out, &kind, &data);
        at += 12 + len;
    }
    out
}

/// A synthetic set of `n` lit images of a bump, `size`×`size`, with its light table.
pub fn synthetic_form(size: u32, n: usize) -> Form {
    let lights: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / n as f64;
            [0.5 * a.cos(), 0.5 * a.sin(), 1.0]
        })
        .collect();
    let mut table = String::new();
    let mut form = Form::new();
    let c = size as f64 / 2.0;
    for (i, l) in lights.iter().enumerate() {
        let name = format!("s{i}.png");
        table.push_str(&format!("{name}, {}, {}, {}\n", l[0], l[1], l[2]));
        let norm = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
        let img = image::GrayImage::from_fn(size, size, |x, y| {
            let (dx, dy) = ((x as f64 - c) / c, (y as f64 - c) / c);
            let (p, q) = (-0.6 * dx, -0.6 * dy);
            let n = [-p, -q, 1.0];
            let nn = (n[0] * n[0] + n[1] * n[1] + 1.0f64).sqrt();
            let s = (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]) / (nn * norm);
            image::Luma([(s.max(0.0) * 0.8 * 255.0) as u8])
        });
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        form = form.part("images", Part::bytes(bytes.into_inner()).file_name(name));
    }
    form.text("lights", table)
}

/// A sphere the project renders, written as the field's benchmark folder: RGB 16-bit
/// PNGs under lights of non-unit RGB intensities, `light_directions.txt` with y UP,
/// `light_intensities.txt`, `filenames.txt`, `mask.png`, and files beside them that are
/// not part of the set (a ground-truth normal map, a names file, a `.mat`).
pub fn benchmark_folder(dir: &Path) -> Scene {
    let scene = Scene::sphere(48);
    let dirs = synth::light_rings(12, 20.0, 50.0);
    let rgb: Vec<[f64; 3]> = (0..dirs.len())
        .map(|i| [0.6 + 0.04 * i as f64, 1.05 - 0.03 * i as f64, 0.8])
        .collect();
    let images = synth::render_rgb(&scene, [0.9, 0.75, 0.6], &dirs, &rgb, &Capture::default());
    let (mut directions, mut intensities, mut names) =
        (String::new(), String::new(), String::new());
    for (i, img) in images.iter().enumerate() {
        let name = format!("view_{:02}.png", i + 1);
        img.save(dir.join(&name)).unwrap();
        let [x, y, z] = dirs[i];
        directions += &format!("{x:.9} {:.9} {z:.9}\n", -y); // the format's y is up
        intensities += &format!("{} {} {}\n", rgb[i][0], rgb[i][1], rgb[i][2]);
        names += &format!("{name}\n");
    }
    std::fs::write(dir.join("light_directions.txt"), directions).unwrap();
    std::fs::write(dir.join("light_intensities.txt"), intensities).unwrap();
    std::fs::write(dir.join("filenames.txt"), names).unwrap();
    let (w, h) = (scene.width as u32, scene.height as u32);
    image::GrayImage::from_fn(w, h, |x, y| {
        image::Luma([if scene.mask[[y as usize, x as usize]] {
            255
        } else {
            0
        }])
    })
    .save(dir.join("mask.png"))
    .unwrap();
    image::RgbImage::from_pixel(w, h, image::Rgb([128, 128, 255]))
        .save(dir.join("Normal_gt.png"))
        .unwrap();
    std::fs::write(dir.join("names.txt"), "view_01.png\n").unwrap();
    std::fs::write(dir.join("Normal_gt.mat"), b"MATLAB 5.0 MAT-file").unwrap();
    scene
}

/// Mean angle, in degrees, between `normal.exr` (OpenGL convention: y up) and the scene's
/// normals (y down the rows), where the surface faces the camera within 37° (there every
/// light reaches it: no attached shadows to bias the plain solve).
pub fn mean_normal_error_deg(out: &Path, scene: &Scene) -> f64 {
    let exr = image::open(out.join("normal.exr")).unwrap().to_rgb32f();
    let (mut sum, mut count) = (0.0, 0);
    for ((r, c), &inside) in scene.mask.indexed_iter() {
        if inside && scene.normals[[r, c, 2]] > 0.8 {
            let p = exr.get_pixel(c as u32, r as u32).0;
            let got = [p[0] as f64, -p[1] as f64, p[2] as f64];
            let dot: f64 = (0..3).map(|k| got[k] * scene.normals[[r, c, k]]).sum();
            sum += dot.clamp(-1.0, 1.0).acos().to_degrees();
            count += 1;
        }
    }
    sum / count as f64
}

/// The camera of [`pinhole_sphere_set`]: a wide lens on a 64² frame.
pub const PINHOLE_K: &str = "80 0 31.5\n0 80 31.5\n0 0 1\n";

/// A sphere of radius 2 centred 6 units down the optical axis, seen through [`PINHOLE_K`]
/// and rendered (Lambertian, 12 lights, 16-bit) into `dir` with the camera as `K.txt`:
/// camera-frame normals, and depth along the optical axis as `truth/depth.exr`, as the
/// renderer writes a perspective set.
pub fn pinhole_sphere_set(dir: &Path) {
    let k = Pinhole::parse(PINHOLE_K).unwrap();
    let (rho, centre) = (2.0, [0.0, 0.0, -6.0]);
    // The near hit of pixel (x, y)'s ray: depth t and the outward normal (nz > 0 all over
    // a sphere centred on the axis).
    let hit = |x: f64, y: f64| {
        let d = k.ray(x, y);
        let dd: f64 = d.iter().map(|v| v * v).sum();
        let dc: f64 = d.iter().zip(centre).map(|(a, b)| a * b).sum();
        let cc: f64 = centre.iter().map(|v| v * v).sum();
        let disc = dc * dc - dd * (cc - rho * rho);
        (disc > 0.0).then(|| {
            let t = (dc - disc.sqrt()) / dd;
            let n = [0, 1, 2].map(|i| (d[i] * t - centre[i]) / rho);
            (t, n)
        })
    };
    // `from_fn` takes z and its slopes: the slopes (−nx/nz, −ny/nz) give back the normal.
    let scene = Scene::from_fn(
        64,
        64,
        |x, y| hit(x, y).map(|(t, n)| (t, -n[0] / n[2], -n[1] / n[2])),
        |x, _| 0.5 + 0.3 * x / 64.0,
    );
    let lights = synth::light_rings(12, 15.0, 45.0);
    synth::write_set(dir, &scene, &lights, &Capture::default()).unwrap();
    std::fs::write(dir.join("K.txt"), PINHOLE_K).unwrap();
}

/// A 16-bit normal map of project-frame normals `n(row, col)` (x right, y down, z towards
/// the camera), black where `None`, encoded as the project's `normal.png` is
/// (`v = (n + 1)/2 · 65535`): green = y up (OpenGL), or y down (DirectX) when `green_down`.
pub fn normal_map_png16(
    (w, h): (u32, u32),
    green_down: bool,
    n: impl Fn(u32, u32) -> Option<[f64; 3]>,
) -> Vec<u8> {
    let encode = |v: f64| ((v + 1.0) / 2.0 * 65535.0).round() as u16;
    let img = image::ImageBuffer::from_fn(w, h, |c, r| match n(r, c) {
        Some([x, y, z]) => image::Rgb([x, if green_down { y } else { -y }, z].map(encode)),
        None => image::Rgb([0u16; 3]),
    });
    photostereo::core::outputs::png_bytes(&img)
}

/// A sphere of radius `radius` px seen orthographically, centred in a `size²` frame: its
/// normal at (row, col), and its true height there (NaN off the disc).
pub fn ortho_sphere(
    size: u32,
    radius: f64,
) -> (impl Fn(u32, u32) -> Option<[f64; 3]>, Array2<f64>) {
    let c = (f64::from(size) - 1.0) / 2.0;
    let at = move |r: u32, col: u32| {
        let (x, y) = (f64::from(col) - c, f64::from(r) - c);
        let z2 = radius * radius - x * x - y * y;
        (z2 > 0.0).then(|| [x, y, z2.sqrt()])
    };
    let n = size as usize;
    let truth = Array2::from_shape_fn((n, n), |(r, col)| {
        at(r as u32, col as u32).map_or(f64::NAN, |p| p[2])
    });
    (
        move |r, col| at(r, col).map(|p| p.map(|v| v / radius)),
        truth,
    )
}

/// A sphere of radius 3 at depth 10 on the optical axis of `k`, in a 96 × 80 frame: a
/// 16-bit OpenGL normal map (black background) and its true depth (NaN off it).
pub fn pinhole_sphere_normal_map(k: &Pinhole) -> (Vec<u8>, Array2<f64>) {
    let (w, h, rho, dist) = (96u32, 80u32, 3.0, 10.0);
    let hit = |r: u32, c: u32| {
        let d = k.ray(c as f64, r as f64);
        let dd: f64 = d.iter().map(|v| v * v).sum();
        let dc = -d[2] * dist;
        let disc = dc * dc - dd * (dist * dist - rho * rho);
        (disc > 0.0).then(|| {
            let t = (dc - disc.sqrt()) / dd;
            let n = [d[0] * t / rho, d[1] * t / rho, (-t + dist) / rho];
            (t, n)
        })
    };
    let map = normal_map_png16((w, h), false, |r, c| hit(r, c).map(|(_, n)| n));
    let truth = Array2::from_shape_fn((h as usize, w as usize), |(r, c)| {
        hit(r as u32, c as u32).map_or(f64::NAN, |(t, _)| t)
    });
    (map, truth)
}
