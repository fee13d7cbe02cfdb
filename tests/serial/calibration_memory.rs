//! A calibration's memory against the real binary: 24 all-black 5792 × 5792 PNGs (about
//! 0.8 MB sent, 3.2 GB once decoded as 16-bit planes) must be answered, with the server's
//! peak resident memory (VmHWM) within its resident memory at start plus the documented
//! peak of one calibration, `core::calibrate::peak_bytes(--max-pixels)`.
//! It takes its turn with the `serial` program's other tests (`crate::ONE_AT_A_TIME`), which
//! measure this process: its own allocations stay out of their figures.

use crate::binserver;

use binserver::BinServer;
use photostereo::core::calibrate;
use reqwest::multipart::{Form, Part};

/// The case: the largest square image `--max-pixels`' default allows.
const SIDE: u32 = 5792;
const IMAGES: usize = 24;
/// `--max-pixels`' default.
const MAX_PIXELS: u64 = 33_554_432;

/// An all-black 8-bit gray PNG, compressed as far as it goes (about 33 KB).
fn black_png(side: u32) -> Vec<u8> {
    let mut out = Vec::new();
    let mut e = png::Encoder::new(&mut out, side, side);
    e.set_color(png::ColorType::Grayscale);
    e.set_depth(png::BitDepth::Eight);
    e.set_compression(png::Compression::High);
    let mut w = e.write_header().unwrap();
    let mut s = w.stream_writer().unwrap();
    let row = vec![0u8; side as usize];
    for _ in 0..side {
        std::io::Write::write_all(&mut s, &row).unwrap();
    }
    s.finish().unwrap();
    w.finish().unwrap();
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn black_5792_square_images_stay_within_the_documented_calibration_peak() {
    let _turn = crate::ONE_AT_A_TIME.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let s = BinServer::start(dir.path(), &["--workers", "2"]);
    let start_kb = s.memory_kb("VmRSS");
    let png = black_png(SIDE);
    let mut form = Form::new();
    for i in 0..IMAGES {
        form = form.part(
            "images",
            Part::bytes(png.clone())
                .file_name(format!("ball{i:02}.png"))
                .mime_str("image/png")
                .unwrap(),
        );
    }
    let sent = IMAGES * png.len();
    let started = std::time::Instant::now();
    let r = s
        .client
        .post(s.url("/v1/calibrations"))
        .multipart(form)
        .timeout(std::time::Duration::from_secs(600))
        .send()
        .await
        .unwrap();
    let status = r.status();
    let ct = r
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    let body = r.text().await.unwrap();
    let took = started.elapsed();
    let hwm_kb = s.memory_kb("VmHWM");
    let peak = calibrate::peak_bytes(MAX_PIXELS);
    let allowed_kb = start_kb + peak / 1024;
    println!(
        "{IMAGES} black {SIDE}² PNGs ({:.1} MB sent): {status} in {:.1} s; server RSS at start {} MB, peak {} MB; allowed {} MB (start + documented peak {} MB)",
        sent as f64 / 1e6,
        took.as_secs_f64(),
        start_kb / 1024,
        hwm_kb / 1024,
        allowed_kb / 1024,
        peak >> 20
    );
    assert_eq!(status, 422, "{body}");
    assert!(ct.starts_with("application/problem+json"), "{ct}");
    assert!(
        body.contains("no sphere found") || body.contains("alike"),
        "{body}"
    );
    assert!(
        hwm_kb <= allowed_kb,
        "peak RSS {} MB over the allowed {} MB",
        hwm_kb / 1024,
        allowed_kb / 1024
    );
    let health = s.client.get(s.url("/healthz")).send().await.unwrap();
    assert_eq!(health.status(), 200);
}
