//! Hostile clients against the real binary. Every case expects a 4xx
//! `application/problem+json` answer whose detail names the problem (at submission, or as
//! the failed job's error for what only the job decodes), then checks that
//! `GET /healthz` still answers and that the server's memory (VmHWM of the child process)
//! stayed under [`MEMORY_BOUND_KB`]. Also: the API key guards every /v1 route, and a
//! bounded load test (20 jobs and 1,000 status requests at once).

use crate::binserver;
use crate::common;
use crate::seed;

use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use binserver::BinServer;
use common::raw_http::read_answer;
use common::{
    archive_form, expect_problem, file_part, folder_form, images_of, palette_png, png, png_chunk,
    repo_root,
};
use reqwest::multipart::{Form, Part};
use seed::seed;
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Peak resident memory allowed to the server while it refuses hostile input.
const MEMORY_BOUND_KB: u64 = 300 * 1024;

/// Small limits where the case needs them; everything else at its default.
const FLAGS: &[&str] = &[
    "--workers",
    "2",
    "--upload-timeout",
    "2s",
    "--max-parts",
    "100",
    "--max-images",
    "200",
    "--max-unpacked-bytes",
    "64MiB",
];

fn start(dir: &Path) -> BinServer {
    BinServer::start(dir, FLAGS)
}

/// The server still answers /healthz and its peak memory is under the bound.
async fn assert_alive(s: &BinServer, case: &str) {
    let r = s
        .client
        .get(s.url("/healthz"))
        .send()
        .await
        .unwrap_or_else(|e| panic!("{case}: /healthz does not answer: {e}\n{}", s.logs()));
    assert_eq!(r.status(), 200, "{case}: /healthz");
    let hwm = s.memory_kb("VmHWM");
    println!("{case}: alive, peak RSS {} MB", hwm / 1024);
    assert!(
        hwm < MEMORY_BOUND_KB,
        "{case}: the server's peak memory is {hwm} kB, over {MEMORY_BOUND_KB} kB"
    );
}

/// POST a form to /v1/jobs.
async fn submit(s: &BinServer, case: &str, form: Form) -> reqwest::Response {
    s.client
        .post(s.url("/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .unwrap_or_else(|e| panic!("{case}: {e}"))
}

/// POST a form to /v1/jobs; expect a problem with `status` naming every needle; then the
/// server must be alive and lean.
async fn refused(s: &BinServer, case: &str, form: Form, status: u16, needles: &[&str]) -> Value {
    let r = submit(s, case, form).await;
    let body = expect_problem(r, status, needles).await;
    assert_alive(s, case).await;
    body
}

/// One case of a table of refusals: its name, the form, and the problem it must get (the
/// status and words of its detail).
type Refusal<'a> = (&'a str, Form, u16, &'a [&'a str]);

/// [`refused`] for each case in turn; returns the bodies.
async fn all_refused(s: &BinServer, cases: Vec<Refusal<'_>>) -> Vec<Value> {
    let mut bodies = Vec::new();
    for (case, form, status, needles) in cases {
        bodies.push(refused(s, case, form, status, needles).await);
    }
    bodies
}

/// No job was accepted and (after the refusals' clean-up) no job files are left.
async fn nothing_accepted(s: &BinServer) {
    let r: Value = s
        .client
        .get(s.url("/v1/jobs"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(r["jobs"].as_array().unwrap().len(), 0, "{r}");
    let jobs = s.data_dir.join("jobs");
    let start = Instant::now();
    loop {
        let left: Vec<_> = std::fs::read_dir(&jobs)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        if left.is_empty() {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "refused uploads left {left:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

const TABLE3: &str = "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n";

/// Three small gray PNGs named as in [`TABLE3`], with `table` as the lights part.
fn three_pngs(table: Part) -> Form {
    let mut f = Form::new().part("lights", table);
    for (i, name) in ["a.png", "b.png", "c.png"].iter().enumerate() {
        f = f.part(
            "images",
            Part::bytes(png(16, 16, 60 + 40 * i as u8)).file_name(*name),
        );
    }
    f
}

// ---------------------------------------------------------------------------------------
// Hand-made files.

/// A PNG whose header claims `w`×`h` 8-bit gray, followed by a small zlib stream of
/// zeros (what a decompression bomb looks like from the outside).
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    png_chunk(&mut out, b"IHDR", &ihdr);
    // zlib header, one fixed-Huffman block that never ends in time: mostly zero bits.
    let mut idat = vec![0x78, 0x9c, 0x63];
    idat.extend(std::iter::repeat_n(0u8, 4096));
    png_chunk(&mut out, b"IDAT", &idat);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

/// A BMP header claiming `w`×`h` at 24 bits, with a few bytes of pixels.
fn bmp_claiming(w: i32, h: i32) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(b"BM");
    out.extend_from_slice(&(54u32 + 64).to_le_bytes());
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(&54u32.to_le_bytes());
    out.extend_from_slice(&40u32.to_le_bytes());
    out.extend_from_slice(&w.to_le_bytes());
    out.extend_from_slice(&h.to_le_bytes());
    out.extend_from_slice(&1u16.to_le_bytes());
    out.extend_from_slice(&24u16.to_le_bytes());
    out.extend_from_slice(&[0; 24]);
    out.extend_from_slice(&[0; 64]);
    out
}

/// A 16-bit gray PNG.
fn png16(w: u32, h: u32, v: u16) -> Vec<u8> {
    let img = image::ImageBuffer::<image::Luma<u16>, _>::from_pixel(w, h, image::Luma([v]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A zip whose entry `name` inflates to `size` zero bytes (a few hundred kB on the wire).
fn zip_bomb(name: &str, size: usize) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(size as u64 > u32::MAX as u64);
    w.start_file(name, opts).unwrap();
    let block = vec![0u8; 1 << 20];
    for _ in 0..size >> 20 {
        w.write_all(&block).unwrap();
    }
    w.start_file(
        "light_directions.csv",
        zip::write::SimpleFileOptions::default(),
    )
    .unwrap();
    w.write_all(b"a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n")
        .unwrap();
    w.finish().unwrap().into_inner()
}

/// Rewrite every declared uncompressed size (local and central headers) to `size`: an
/// archive that lies about what it unpacks to.
fn lie_about_sizes(mut zip: Vec<u8>, size: u32) -> Vec<u8> {
    let mut i = 0;
    while i + 46 <= zip.len() {
        match &zip[i..i + 4] {
            b"PK\x03\x04" => zip[i + 22..i + 26].copy_from_slice(&size.to_le_bytes()),
            b"PK\x01\x02" => zip[i + 24..i + 28].copy_from_slice(&size.to_le_bytes()),
            _ => {}
        }
        i += 1;
    }
    zip
}

// ---------------------------------------------------------------------------------------
// A raw HTTP/1.1 client, for bodies no well-behaved client sends.

const BOUNDARY: &str = "hostile-boundary-7d1f";

fn multipart_head(addr: &str, extra: &str) -> String {
    format!(
        "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nContent-Type: multipart/form-data; boundary={BOUNDARY}\r\n{extra}\r\n"
    )
}

/// A multipart body: the table, then one image part per (name, bytes), closed.
fn multipart_body(table: &str, images: &[(&str, Vec<u8>)]) -> Vec<u8> {
    let mut b = format!(
        "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"lights\"\r\n\r\n{table}\r\n"
    )
    .into_bytes();
    for (name, bytes) in images {
        b.extend_from_slice(
            format!(
                "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"images\"; filename=\"{name}\"\r\nContent-Type: image/png\r\n\r\n"
            )
            .as_bytes(),
        );
        b.extend_from_slice(bytes);
        b.extend_from_slice(b"\r\n");
    }
    b.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    b
}

// ---------------------------------------------------------------------------------------
// The cases.

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn image_headers_claiming_huge_sizes_are_refused_before_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    let bomb = png_claiming(100_000, 100_000);
    let first = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(bomb.clone()).file_name("a.png"));
    // The same bomb as the third image, after two good ones.
    let third = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(png(16, 16, 9)).file_name("b.png"))
        .part("images", Part::bytes(png(16, 16, 9)).file_name("c.png"))
        .part("images", Part::bytes(bomb.clone()).file_name("a.png"));
    let mask = three_pngs(Part::text(TABLE3))
        .part("mask", Part::bytes(bomb.clone()).file_name("mask.png"));
    let zip = common::zip_entries(&[
        ("a.png", &bomb),
        ("b.png", &png(16, 16, 1)),
        ("c.png", &png(16, 16, 1)),
        ("light_directions.csv", TABLE3.as_bytes()),
    ]);
    all_refused(
        &s,
        vec![
            (
                "PNG claiming 100000×100000",
                first,
                413,
                &["\"a.png\"", "100000×100000", "10000000000"],
            ),
            (
                "PNG bomb third",
                third,
                413,
                &["\"a.png\"", "100000×100000"],
            ),
            ("PNG bomb mask", mask, 413, &["100000×100000"]),
            (
                "PNG bomb in a zip",
                archive_form(zip),
                413,
                &["\"a.png\"", "100000×100000"],
            ),
        ],
    )
    .await;

    // A BMP header, and a BMP with a negative (top-down) extreme height.
    for (w, h, needle) in [
        (100_000, 100_000, "100000×100000"),
        (100_000, -100_000, "100000×100000"),
        (i32::MAX, 1, "2147483647×1"),
    ] {
        let form = Form::new()
            .text("lights", TABLE3)
            .part("images", Part::bytes(bmp_claiming(w, h)).file_name("a.png"));
        let r = s
            .client
            .post(s.url("/v1/jobs"))
            .multipart(form)
            .send()
            .await
            .unwrap();
        // 413 when the header is read as such; 415 or 422 if the decoder refuses it.
        let status = r.status().as_u16();
        assert!(matches!(status, 413 | 415 | 422), "BMP {w}×{h}: {status}");
        let body = expect_problem(r, status, &["\"a.png\""]).await;
        if status == 413 {
            assert!(body["detail"].as_str().unwrap().contains(needle), "{body}");
        }
        assert_alive(&s, "BMP header").await;
    }
    nothing_accepted(&s).await;
}

/// A job is bounded by what it costs: its stored input bytes (the part that crosses the
/// bound is refused by name before the rest of the body is read, in a form or a zip) and
/// its output maps (pixels per image), each 413 naming the limit. The per-job pixel flag
/// it replaces is still accepted, with no effect.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_over_the_input_bytes_or_image_size_limits_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let small: Vec<Vec<u8>> = [60, 100, 140].map(|v| png(10, 20, v)).into();
    let limit = small.iter().map(|p| p.len()).sum::<usize>() + 16;
    // Noise does not compress: 16×16 at 16 bits is over 500 bytes, past the limit with a
    // and b before it.
    let mut x = 12345u32;
    let noise = image::ImageBuffer::from_fn(16, 16, |_, _| {
        x = x.wrapping_mul(1_103_515_245).wrapping_add(12345);
        image::Luma([(x >> 8) as u16])
    });
    let mut noisy = std::io::Cursor::new(Vec::new());
    noise.write_to(&mut noisy, image::ImageFormat::Png).unwrap();
    let noisy = noisy.into_inner();
    assert!(small[0].len() + small[1].len() + noisy.len() > limit);
    let limit_flag = limit.to_string();
    let flags: Vec<&str> = (FLAGS.iter().copied())
        .chain(["--max-input-bytes", &limit_flag, "--max-pixels", "300"])
        .chain(["--max-job-pixels", "100"])
        .collect();
    let s = BinServer::start(dir.path(), &flags);
    let over_bytes = [
        "\"c.png\"",
        "stored input files",
        &format!("limit of {limit} bytes"),
        "max-input-bytes",
    ];
    let form = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(small[0].clone()).file_name("a.png"))
        .part("images", Part::bytes(small[1].clone()).file_name("b.png"))
        .part("images", Part::bytes(noisy.clone()).file_name("c.png"));
    let zip = common::zip_entries(&[
        ("a.png", &small[0]),
        ("b.png", &small[1]),
        ("c.png", &noisy),
        ("light_directions.csv", TABLE3.as_bytes()),
    ]);
    // 20×20 is 400 pixels an image, over --max-pixels.
    let large = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(png(20, 20, 60)).file_name("a.png"));
    let over_pixels = ["\"a.png\"", "20×20", "limit of 300"];
    // A normal map is held to the same limit, and refused alike.
    let map = common::normal_map_png16((20, 20), false, |_, _| Some([0.0, 0.0, 1.0]));
    let map = Form::new().part("normals", Part::bytes(map).file_name("a.png"));
    all_refused(
        &s,
        vec![
            ("input bytes", form, 413, &over_bytes),
            ("input bytes in a zip", archive_form(zip), 413, &over_bytes),
            ("image size", large, 413, &over_pixels),
            ("normal map size", map, 413, &over_pixels),
        ],
    )
    .await;
    nothing_accepted(&s).await;

    // Under both (600 pixels in all, past the old per-job bound of 100): accepted.
    let mut form = Form::new().text("lights", TABLE3);
    for (p, name) in small.iter().zip(["a.png", "b.png", "c.png"]) {
        form = form.part("images", Part::bytes(p.clone()).file_name(name));
    }
    let r = submit(&s, "under the limits", form).await;
    assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
}

/// POST a form whose images are only decoded by the job (after the 202): the job must fail
/// with a 422 problem naming every needle, and the server must be alive and lean.
async fn job_fails(s: &BinServer, case: &str, form: Form, needles: &[&str]) {
    let r = submit(s, case, form).await;
    assert_eq!(r.status(), 202, "{case}");
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    let job = s
        .wait_json(&format!("/v1/jobs/{id}"), Duration::from_secs(30), |j| {
            j["status"] != "queued" && j["status"] != "running"
        })
        .await;
    assert_eq!(job["status"], "failed", "{case}: {job}");
    assert_eq!(job["error"]["status"], 422, "{case}: {job}");
    let detail = job["error"]["detail"].as_str().unwrap();
    for n in needles {
        assert!(detail.contains(n), "{case}: detail {detail:?} lacks {n:?}");
    }
    assert_alive(s, case).await;
}

/// A palette PNG whose PLTE chunk is 13 bytes long made the `png` crate panic on a rayon
/// thread, which aborted the whole server (found by the intake_decode fuzz target). Now
/// its job fails naming the file and the chunk, and the server goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ragged_png_palette_fails_its_job_by_name_and_the_server_lives() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    let ragged = palette_png(6, 5, 1);
    let needles = ["\"b.png\"", "PLTE", "13 bytes"];

    let form = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(png(6, 5, 9)).file_name("a.png"))
        .part("images", Part::bytes(ragged.clone()).file_name("b.png"))
        .part("images", Part::bytes(png(6, 5, 9)).file_name("c.png"));
    let zip = common::zip_entries(&[
        ("a.png", &png(6, 5, 1)),
        ("b.png", &ragged),
        ("c.png", &png(6, 5, 1)),
        ("light_directions.csv", TABLE3.as_bytes()),
    ]);
    let mask = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(png(6, 5, 9)).file_name("a.png"))
        .part("images", Part::bytes(png(6, 5, 9)).file_name("b.png"))
        .part("images", Part::bytes(png(6, 5, 9)).file_name("c.png"))
        .part("mask", Part::bytes(ragged).file_name("mask.png"));
    let cases: [(&str, Form, &[&str]); 3] = [
        ("ragged palette", form, &needles),
        ("ragged palette in a zip", archive_form(zip), &needles),
        ("ragged palette mask", mask, &["PLTE", "13 bytes"]),
    ];
    for (case, form, needles) in cases {
        job_fails(&s, case, form, needles).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zip_bombs_and_unsafe_entries_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    let p = png(8, 8, 50);

    // 256 MiB of zeros in a few hundred kB, against a 64 MiB unpacking cap.
    let bomb = zip_bomb("a.png", 256 << 20);
    assert!(bomb.len() < 2 << 20, "bomb is {} bytes", bomb.len());
    refused(
        &s,
        "zip bomb",
        archive_form(bomb.clone()),
        413,
        &["unpacks to more than 67108864 bytes"],
    )
    .await;
    // The same, its headers claiming 100 bytes: counted while streaming, not trusted.
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(archive_form(lie_about_sizes(bomb, 100)))
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    let needle = match status {
        413 => "unpacks to more than",
        422 => "\"a.png\"",
        other => panic!("lying bomb: {other}"),
    };
    println!("zip bomb with lying sizes: {status}");
    expect_problem(r, status, &[needle]).await;
    assert_alive(&s, "lying zip bomb").await;

    for (entry, needle) in [
        ("../a.png", "unsafe path"),
        ("set/../../a.png", "unsafe path"),
        ("/etc/a.png", "unsafe path"),
        ("\\windows\\a.png", "unsafe path"),
        ("C:/a.png", "unsafe path"),
        ("a/b/c/a.png", "out of place"),
    ] {
        let zip = common::zip_entries(&[
            (entry, &p),
            ("b.png", &p),
            ("c.png", &p),
            ("light_directions.csv", TABLE3.as_bytes()),
        ]);
        let body = refused(&s, entry, archive_form(zip), 422, &[needle]).await;
        assert!(
            body["detail"].as_str().unwrap().contains("archive entry"),
            "{entry}: {body}"
        );
    }

    // A symbolic link.
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default();
    w.add_symlink("a.png", "/etc/passwd", opts).unwrap();
    for (name, data) in [("b.png", &p[..]), ("c.png", &p[..])] {
        w.start_file(name, opts).unwrap();
        w.write_all(data).unwrap();
    }
    w.start_file("light_directions.csv", opts).unwrap();
    w.write_all(TABLE3.as_bytes()).unwrap();
    let symlink = w.finish().unwrap().into_inner();

    // More entries than parts allowed; a truncated archive; garbage after the signature.
    let many: Vec<(String, Vec<u8>)> = (0..150).map(|i| (format!("{i}.png"), p.clone())).collect();
    let refs: Vec<(&str, &[u8])> = many.iter().map(|(n, d)| (n.as_str(), &d[..])).collect();
    let zip = common::zip_entries(&refs);
    let cut = zip[..zip.len() / 2].to_vec();
    let mut junk = b"PK\x03\x04".to_vec();
    junk.extend(std::iter::repeat_n(0xA5u8, 100_000));
    all_refused(
        &s,
        vec![
            ("symlink", archive_form(symlink), 422, &["symbolic link"]),
            (
                "150 entries",
                archive_form(zip.clone()),
                413,
                &["150 entries", "limit of 100"],
            ),
            ("truncated zip", archive_form(cut), 422, &["archive"]),
            ("junk zip", archive_form(junk), 422, &["archive"]),
        ],
    )
    .await;
    nothing_accepted(&s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thousands_of_parts_and_broken_multipart_bodies() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());

    let tiny = png(1, 1, 7);
    let mut form = Form::new().text("lights", TABLE3);
    for i in 0..5000 {
        form = form.part(
            "images",
            Part::bytes(tiny.clone()).file_name(format!("p{i}.png")),
        );
    }
    refused(&s, "5000 parts", form, 413, &["more than 100 parts"]).await;

    // A body cut short in the middle of an image, its length declared honestly.
    let body = multipart_body(
        TABLE3,
        &[("a.png", png(64, 64, 1)), ("b.png", png(64, 64, 2))],
    );
    let cut = &body[..body.len() * 2 / 3];
    let mut stream = TcpStream::connect(s.addr()).await.unwrap();
    let head = multipart_head(
        s.addr(),
        &format!("Content-Length: {}\r\nConnection: close\r\n", cut.len()),
    );
    stream.write_all(head.as_bytes()).await.unwrap();
    stream.write_all(cut).await.unwrap();
    let answer = tokio::time::timeout(Duration::from_secs(10), read_answer(&mut stream))
        .await
        .expect("an answer to a truncated body")
        .expect("an HTTP answer");
    assert_eq!(answer.status, 400);
    assert!(answer.is_problem(), "{}", answer.head);
    let detail = answer.json()["detail"].as_str().unwrap().to_string();
    assert!(detail.contains("multipart"), "{detail}");
    assert_alive(&s, "truncated multipart").await;

    // A client that declares more than it sends and hangs up its side.
    let mut stream = TcpStream::connect(s.addr()).await.unwrap();
    let head = multipart_head(s.addr(), "Content-Length: 1000000\r\n");
    stream.write_all(head.as_bytes()).await.unwrap();
    stream.write_all(cut).await.unwrap();
    stream.shutdown().await.unwrap();
    let answer = tokio::time::timeout(Duration::from_secs(10), read_answer(&mut stream))
        .await
        .expect("the server answers or closes within 10 s");
    if let Some(a) = answer {
        assert!(a.status == 400 && a.is_problem(), "{} {}", a.status, a.head);
    }
    assert_alive(&s, "half-closed upload").await;

    // No closing boundary; a boundary that never appears; an empty body.
    let mut no_end = multipart_body(TABLE3, &[("a.png", png(8, 8, 1))]);
    no_end.truncate(no_end.len() - format!("--{BOUNDARY}--\r\n").len());
    for (case, body) in [
        ("no closing boundary", no_end),
        ("no boundary at all", b"just bytes, no parts".to_vec()),
        ("empty body", Vec::new()),
    ] {
        let r = s
            .client
            .post(s.url("/v1/jobs"))
            .header(
                "content-type",
                format!("multipart/form-data; boundary={BOUNDARY}"),
            )
            .body(body)
            .send()
            .await
            .unwrap();
        let status = r.status().as_u16();
        assert_eq!(status, 400, "{case}");
        expect_problem(r, 400, &[]).await;
        assert_alive(&s, case).await;
    }
    // Multipart without a boundary parameter.
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .header("content-type", "multipart/form-data")
        .body("x")
        .send()
        .await
        .unwrap();
    expect_problem(r, 400, &["multipart/form-data"]).await;

    // Oversized and countless headers are refused by the HTTP layer; the server lives on.
    let long = "x".repeat(1 << 20);
    let r = s
        .client
        .get(s.url("/healthz"))
        .header("x-long", long)
        .send()
        .await;
    assert!(
        r.as_ref()
            .map(|r| r.status().is_client_error())
            .unwrap_or(true),
        "{r:?}"
    );
    let mut req = s.client.get(s.url("/healthz"));
    for i in 0..500 {
        req = req.header(format!("x-h{i}"), "1");
    }
    let r = req.send().await;
    assert!(
        r.as_ref()
            .map(|r| r.status().is_client_error())
            .unwrap_or(true),
        "{r:?}"
    );
    assert_alive(&s, "huge headers").await;
    nothing_accepted(&s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_upload_gets_408_and_its_connection_is_closed() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    let mut stream = TcpStream::connect(s.addr()).await.unwrap();
    let head = multipart_head(s.addr(), "Transfer-Encoding: chunked\r\n");
    stream.write_all(head.as_bytes()).await.unwrap();
    let opening = format!(
        "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"lights\"\r\n\r\n{TABLE3}\r\n--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"images\"; filename=\"a.png\"\r\n\r\n"
    );
    let chunk = |data: &[u8]| {
        let mut c = format!("{:x}\r\n", data.len()).into_bytes();
        c.extend_from_slice(data);
        c.extend_from_slice(b"\r\n");
        c
    };
    stream.write_all(&chunk(opening.as_bytes())).await.unwrap();
    let (mut rd, mut wr) = stream.into_split();
    let started = Instant::now();
    // Ten bytes every 200 ms, for as long as the server lets us.
    let trickle = tokio::spawn(async move {
        let mut sent = 0usize;
        loop {
            tokio::time::sleep(Duration::from_millis(200)).await;
            if wr.write_all(&chunk(&[0x42; 10])).await.is_err() || sent > 60_000 {
                return sent;
            }
            sent += 10;
        }
    });
    let answer = tokio::time::timeout(Duration::from_secs(8), read_answer(&mut rd))
        .await
        .expect("an answer within 8 s")
        .expect("an HTTP answer");
    let answered = started.elapsed();
    assert_eq!(answer.status, 408, "{}", answer.head);
    assert!(answer.is_problem());
    let detail = answer.json()["detail"].as_str().unwrap().to_string();
    assert!(detail.contains("within 2s"), "{detail}");
    assert!(
        answered >= Duration::from_millis(1900) && answered < Duration::from_secs(5),
        "answered after {answered:?}"
    );
    // The connection is not held for ever: the server closes it while we still trickle.
    let mut rest = [0u8; 256];
    let closed = tokio::time::timeout(Duration::from_secs(15), async {
        loop {
            match rd.read(&mut rest).await {
                Ok(0) | Err(_) => return,
                Ok(_) => {}
            }
        }
    })
    .await;
    assert!(
        closed.is_ok(),
        "the connection is still open 15 s after the 408"
    );
    let held = started.elapsed();
    let _ = tokio::time::timeout(Duration::from_secs(5), trickle).await;
    println!("slow upload: 408 after {answered:?}, connection closed after {held:?}");
    assert_alive(&s, "slow upload").await;
    nothing_accepted(&s).await;
}

/// With `--max-uploads 1`, a second upload while one is being received gets 503 with
/// Retry-After; once the first connection goes away, uploads are taken again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_past_the_concurrency_limit_get_503() {
    let dir = tempfile::tempdir().unwrap();
    let flags: Vec<&str> = FLAGS
        .iter()
        .copied()
        .chain(["--max-uploads", "1"])
        .collect();
    let s = BinServer::start(dir.path(), &flags);
    let mut stream = TcpStream::connect(s.addr()).await.unwrap();
    let head = multipart_head(s.addr(), "Transfer-Encoding: chunked\r\n");
    stream.write_all(head.as_bytes()).await.unwrap();
    let opening = format!(
        "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"lights\"\r\n\r\n{TABLE3}\r\n"
    );
    let chunk = format!("{:x}\r\n{opening}\r\n", opening.len());
    stream.write_all(chunk.as_bytes()).await.unwrap();
    // The first upload holds the only permit once its first part is being read.
    tokio::time::sleep(Duration::from_millis(300)).await;

    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(three_pngs(Part::text(TABLE3)))
        .send()
        .await
        .unwrap();
    assert_eq!(r.headers()["retry-after"], "5");
    expect_problem(r, 503, &["1 uploads are being received", "retry later"]).await;
    assert_alive(&s, "concurrent uploads").await;

    drop(stream);
    let started = Instant::now();
    loop {
        let r = s
            .client
            .post(s.url("/v1/jobs"))
            .multipart(three_pngs(Part::text(TABLE3)))
            .send()
            .await
            .unwrap();
        if r.status() == 202 {
            break;
        }
        assert_eq!(r.status(), 503);
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "the abandoned upload still holds its permit"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A client that never finishes its request head (and one that never sends anything)
/// must not keep the server from stopping on SIGTERM.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_is_not_held_up_by_clients_that_never_finish_a_request() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = BinServer::start(dir.path(), &["--shutdown-grace", "2s"]);
    let mut slow = TcpStream::connect(s.addr()).await.unwrap();
    slow.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        .await
        .unwrap();
    let _silent = TcpStream::connect(s.addr()).await.unwrap();
    let mut upload = TcpStream::connect(s.addr()).await.unwrap();
    let head = multipart_head(s.addr(), "Content-Length: 100000\r\n");
    upload.write_all(head.as_bytes()).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_alive(&s, "before SIGTERM").await;
    let started = Instant::now();
    s.terminate();
    let status = tokio::task::block_in_place(|| s.wait_exit(Duration::from_secs(20)));
    let took = started.elapsed();
    println!("SIGTERM with three stuck connections: exited after {took:?}");
    let status = status.unwrap_or_else(|| panic!("still running 20 s after SIGTERM"));
    assert!(status.success(), "{status:?}\n{}", s.logs());
    assert!(took < Duration::from_secs(8), "took {took:?} to stop");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_light_tables() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    for (case, table, needles) in [
        (
            "NaN",
            "a.png, NaN, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1",
            &["row 1", "non-finite"][..],
        ),
        (
            "inf",
            "a.png, 0, 0, 1\nb.png, inf, 0, 1\nc.png, 0, 1, 1",
            &["row 2", "non-finite"],
        ),
        (
            "-infinity",
            "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, -infinity, 1",
            &["row 3", "non-finite"],
        ),
        (
            "1e400",
            "a.png, 0, 0, 1\nb.png, 1e400, 0, 1\nc.png, 0, 1, 1",
            &["row 2", "non-finite"],
        ),
        (
            "1e200",
            "a.png, 0, 0, 1\nb.png, 1e200, 0, 1\nc.png, 0, 1, 1",
            &["row 2", "too large"],
        ),
        (
            "NaN intensity",
            "a.png, 0, 0, 1, NaN\nb.png, 1, 0, 1\nc.png, 0, 1, 1",
            &["row 1", "intensity"],
        ),
        (
            "1e-320",
            "a.png, 1e-320, 0, 0\nb.png, 1, 0, 1\nc.png, 0, 1, 1",
            &["row 1", "zero"],
        ),
        (
            "JSON NaN",
            r#"[{"name":"a.png","direction":[NaN,0,1]}]"#,
            &["invalid JSON"],
        ),
        (
            "JSON 1e400",
            r#"[{"name":"a.png","direction":[1e400,0,1]},{"name":"b.png","direction":[1,0,1]},{"name":"c.png","direction":[0,1,1]}]"#,
            &["invalid JSON"],
        ),
        (
            "JSON string number",
            r#"[{"name":"a.png","direction":["1",0,1]}]"#,
            &["invalid JSON"],
        ),
        ("NUL bytes", "a.png\0, 0, 0, 1\n\0\0\0", &["row"]),
        ("only comments", "# nothing\n\n   \n# here", &["at least 3"]),
    ] {
        let body = refused(&s, case, three_pngs(Part::text(table)), 422, needles).await;
        assert_eq!(
            body["type"], "urn:photostereo:problem:invalid-input",
            "{case}"
        );
    }
    // Not UTF-8.
    let bad = b"a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, \xff\xfe\n".to_vec();
    // Deeply nested JSON: serde's recursion limit, not a stack overflow.
    let deep = format!("{}{}", "[".repeat(100_000), "]".repeat(100_000));
    // More rows than the parser takes, and more bytes than the part takes.
    let rows: String = (0..10_001)
        .map(|i| format!("i{i}.png, 0, 0, 1\n"))
        .collect();
    let huge = "# padding\n".repeat(200_000);
    all_refused(
        &s,
        vec![
            (
                "invalid UTF-8",
                three_pngs(Part::bytes(bad)),
                422,
                &["UTF-8", "offset 43"],
            ),
            (
                "nested JSON table",
                three_pngs(Part::text(deep)),
                422,
                &["invalid JSON"],
            ),
            (
                "10001 rows",
                three_pngs(Part::text(rows)),
                422,
                &["more than 10000 rows"],
            ),
            (
                "2 MB table",
                three_pngs(Part::text(huge)),
                413,
                &["lights part is larger than 1048576 bytes"],
            ),
        ],
    )
    .await;
    nothing_accepted(&s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_options() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    let with_options = |o: &str| three_pngs(Part::text(TABLE3)).text("options", o.to_string());
    for (case, options, needles) in [
        (
            "unknown field",
            r#"{"solver": "l2", "bogus": 1}"#,
            &["bogus"][..],
        ),
        (
            "unknown nested field",
            r#"{"mesh": {"colour": 1}}"#,
            &["colour"],
        ),
        (
            "wrong type",
            r#"{"max_condition": "high"}"#,
            &["max_condition"],
        ),
        ("wrong enum", r#"{"solver": "magic"}"#, &["magic"]),
        (
            "negative step",
            r#"{"mesh": {"step": -1}}"#,
            &["mesh", "-1"],
        ),
        (
            "short light",
            r#"{"shading_light": [1, 2]}"#,
            &["shading_light"],
        ),
        (
            "null light",
            r#"{"shading_light": null}"#,
            &["shading_light"],
        ),
        ("1e400", r#"{"max_condition": 1e400}"#, &["options"]),
        ("array", r#"[1, 2, 3]"#, &["options"]),
        ("not JSON", "{", &["not valid JSON"]),
        ("trailing junk", r#"{} {}"#, &["not valid JSON"]),
        (
            "bad output",
            r#"{"outputs": ["albedo.png", "../../etc/passwd"]}"#,
            &["../../etc/passwd"],
        ),
    ] {
        let body = refused(&s, case, with_options(options), 422, needles).await;
        assert_eq!(
            body["type"], "urn:photostereo:problem:invalid-input",
            "{case}"
        );
    }
    let deep_mesh = format!(
        "{{\"mesh\": {}{}}}",
        "[".repeat(100_000),
        "]".repeat(100_000)
    );
    let deep = format!("{}{}", "[".repeat(20_000), "]".repeat(20_000));
    let big = format!(r#"{{"solver": "l2"{}}}"#, " ".repeat(100_000));
    all_refused(
        &s,
        vec![
            (
                "nested options",
                with_options(&deep_mesh),
                413,
                &["options"],
            ),
            (
                "nested options",
                with_options(&deep),
                422,
                &["not valid JSON"],
            ),
            (
                "100 kB options",
                with_options(&big),
                413,
                &["options part is larger than 65536 bytes"],
            ),
        ],
    )
    .await;
    nothing_accepted(&s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mixed_sizes_and_bit_depths_are_refused_at_submission() {
    let (synth, dog) = (seed!("synth-images"), seed!("dog-images"));
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    // The synth set (100×100) with one of the dog's images (400×400) in its place.
    let dog = std::fs::read(dog.join("dog1.png")).unwrap();
    let mut form = Form::new().part("lights", file_part(&synth.join("light_directions.csv")));
    for img in images_of(&synth) {
        let name = img.file_name().unwrap().to_string_lossy().into_owned();
        let part = if name == "im3.png" {
            Part::bytes(dog.clone()).file_name(name)
        } else {
            file_part(&img)
        };
        form = form.part("images", part);
    }
    // 8-bit and 16-bit images of the same size.
    let depths = Form::new()
        .text("lights", TABLE3)
        .part("images", Part::bytes(png(16, 16, 90)).file_name("a.png"))
        .part(
            "images",
            Part::bytes(png16(16, 16, 30_000)).file_name("b.png"),
        )
        .part("images", Part::bytes(png(16, 16, 90)).file_name("c.png"));
    // The same in an archive.
    let zip = common::zip_entries(&[
        ("a.png", &png16(16, 16, 1000)),
        ("b.png", &png16(16, 16, 2000)),
        ("c.png", &png(16, 16, 90)),
        ("light_directions.csv", TABLE3.as_bytes()),
    ]);
    // A mask of another size.
    let mask = three_pngs(Part::text(TABLE3))
        .part("mask", Part::bytes(png(17, 16, 255)).file_name("m.png"));
    all_refused(
        &s,
        vec![
            (
                "mixed sizes",
                form,
                422,
                &["\"im3.png\"", "400×400", "100×100", "same size"],
            ),
            (
                "mixed bit depths",
                depths,
                422,
                &["\"b.png\"", "16-bit", "\"a.png\"", "8-bit", "bit depth"],
            ),
            (
                "mixed bit depths in a zip",
                archive_form(zip),
                422,
                &["\"c.png\"", "8-bit", "16-bit"],
            ),
            ("mask size", mask, 422, &["mask", "17×16"]),
        ],
    )
    .await;
    nothing_accepted(&s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_names_never_become_paths() {
    let dir = tempfile::tempdir().unwrap();
    let s = start(dir.path());
    let bump = repo_root().join("res/bump");
    let names = [
        "../../../../pwned-a.png",
        "/tmp/pwned-b.png",
        "....//pwned-c.png",
        "%2e%2e%2f%2e%2e%2fpwned-d.png",
    ];
    let rows: Vec<String> = table_rows(&bump);
    let mut table = String::new();
    let mut form = Form::new();
    for ((img, row), name) in images_of(&bump).iter().zip(&rows).zip(names) {
        table.push_str(&format!("{name}, {row}\n"));
        form = form.part(
            "images",
            Part::bytes(std::fs::read(img).unwrap()).file_name(name),
        );
    }
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .multipart(form.text("lights", table))
        .send()
        .await
        .unwrap();
    let status = r.status();
    let job: Value = r.json().await.unwrap();
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().unwrap();
    let done = s
        .wait_json(&format!("/v1/jobs/{id}"), Duration::from_secs(60), |j| {
            j["status"] != "queued" && j["status"] != "running"
        })
        .await;
    assert_eq!(done["status"], "succeeded", "{done}");
    for stray in [
        dir.path().join("../pwned-a.png"),
        "/pwned-a.png".into(),
        "/tmp/pwned-b.png".into(),
        dir.path().join("../pwned-c.png"),
        dir.path().join("../pwned-d.png"),
    ] {
        assert!(!stray.exists(), "{stray:?} was written");
    }
    // Artifact and job paths that try to leave their directory.
    for path in [
        format!("/v1/jobs/{id}/artifacts/..%2F..%2F..%2Fjobs.sqlite"),
        format!("/v1/jobs/{id}/artifacts/..%2Finput%2Fmanifest.json"),
        format!("/v1/jobs/{id}/artifacts/%2Fetc%2Fpasswd"),
        "/v1/jobs/..%2F..%2Fjobs.sqlite".to_string(),
        format!("/v1/jobs/{id}/artifacts/albedo.png%00.txt"),
    ] {
        let r = s.client.get(s.url(&path)).send().await.unwrap();
        expect_problem(r, 404, &[]).await;
    }
    assert_alive(&s, "path names").await;
}

/// "x, y, z" of each row of a light table in the seed's format, in image order.
fn table_rows(dir: &Path) -> Vec<String> {
    let table = std::fs::read_to_string(dir.join("light_directions.csv")).unwrap();
    let mut rows: Vec<(String, String)> = table
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|l| {
            let (name, rest) = l.split_once(',').unwrap();
            (name.trim().to_string(), rest.trim().to_string())
        })
        .collect();
    rows.sort();
    rows.into_iter().map(|(_, r)| r).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_key_guards_every_v1_route_and_leaves_probes_open() {
    let dir = tempfile::tempdir().unwrap();
    let mut flags = FLAGS.to_vec();
    flags.extend(["--api-key", "right-key-1234"]);
    let s = BinServer::start(dir.path(), &flags);
    let key = "right-key-1234";
    let r = s
        .client
        .post(s.url("/v1/jobs"))
        .bearer_auth(key)
        .multipart(folder_form(&repo_root().join("res/bump")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let job = format!("/v1/jobs/{id}");
    let artifact = format!("{job}/artifacts/albedo.png");
    let reshade = format!("{job}/artifacts/shaded.png?light=0,0,1");
    let routes: Vec<(reqwest::Method, &str)> = vec![
        (reqwest::Method::GET, "/v1/jobs"),
        (reqwest::Method::GET, "/v1/jobs?limit=1"),
        (reqwest::Method::POST, "/v1/jobs"),
        (reqwest::Method::GET, &job),
        (reqwest::Method::DELETE, &job),
        (reqwest::Method::GET, &artifact),
        (reqwest::Method::GET, &reshade),
    ];
    let wrong: [Option<&str>; 8] = [
        None,
        Some(""),
        Some("Bearer"),
        Some("Bearer "),
        Some("Bearer right-key-123"),
        Some("Bearer right-key-12345"),
        Some("Bearer RIGHT-KEY-1234"),
        Some("Basic cmlnaHQta2V5LTEyMzQ="),
    ];
    for (method, path) in &routes {
        for auth in wrong {
            let mut req = s.client.request(method.clone(), s.url(path));
            if let Some(a) = auth {
                req = req.header("authorization", a);
            }
            if *method == reqwest::Method::POST {
                req = req.multipart(folder_form(&repo_root().join("res/bump")));
            }
            let r = req.send().await.unwrap();
            assert_eq!(
                r.headers()
                    .get("www-authenticate")
                    .map(|v| v.to_str().unwrap()),
                Some("Bearer realm=\"photostereo\""),
                "{method} {path} with {auth:?}"
            );
            expect_problem(r, 401, &[]).await;
        }
    }
    for open in ["/healthz", "/readyz", "/metrics", "/openapi.json"] {
        let r = s.client.get(s.url(open)).send().await.unwrap();
        assert_eq!(r.status(), 200, "{open} needs no key");
    }
    // The refused DELETE did nothing; with the key everything answers.
    let r = s
        .client
        .get(s.url(&job))
        .bearer_auth(key)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let r = s
        .client
        .get(s.url("/v1/jobs"))
        .header("authorization", format!("bearer   {key}  "))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "the scheme is case-insensitive");
    let listed: Value = r.json().await.unwrap();
    assert_eq!(listed["jobs"].as_array().unwrap().len(), 1);
    assert_alive(&s, "api keys").await;
}

/// 20 jobs submitted at once, then 1,000 status requests at once while they run: every
/// request answers, every job succeeds. Prints the figures.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn load_twenty_jobs_and_a_thousand_status_requests() {
    let dir = tempfile::tempdir().unwrap();
    let s = BinServer::start(dir.path(), &["--workers", "2", "--queue-length", "64"]);
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(30))
        .pool_max_idle_per_host(1000)
        .build()
        .unwrap();
    let bump = repo_root().join("res/bump");
    let started = Instant::now();
    let submissions = (0..20).map(|_| {
        let (client, url, form) = (client.clone(), s.url("/v1/jobs"), folder_form(&bump));
        async move {
            let t = Instant::now();
            let r = client.post(url).multipart(form).send().await.unwrap();
            let status = r.status();
            let job: Value = r.json().await.unwrap();
            assert_eq!(status, 202, "{job}");
            (job["id"].as_str().unwrap().to_string(), t.elapsed())
        }
    });
    let accepted = futures_util::future::join_all(submissions).await;
    let submit_wall = started.elapsed();
    let ids: Vec<String> = accepted.iter().map(|(id, _)| id.clone()).collect();
    let submit_max = accepted.iter().map(|(_, d)| *d).max().unwrap();

    let status_started = Instant::now();
    let requests = (0..1000).map(|i| {
        let client = client.clone();
        let url = s.url(&format!("/v1/jobs/{}", ids[i % ids.len()]));
        async move {
            let t = Instant::now();
            let r = client.get(url).send().await;
            let ok = match r {
                Ok(r) if r.status() == 200 => r.json::<Value>().await.is_ok(),
                _ => false,
            };
            (ok, t.elapsed())
        }
    });
    let answers = futures_util::future::join_all(requests).await;
    let status_wall = status_started.elapsed();
    let failed = answers.iter().filter(|(ok, _)| !ok).count();
    let mut latencies: Vec<Duration> = answers.iter().map(|(_, d)| *d).collect();
    latencies.sort();
    let pct = |p: f64| latencies[((latencies.len() as f64 * p) as usize).min(latencies.len() - 1)];

    for id in &ids {
        let job = s
            .wait_json(&format!("/v1/jobs/{id}"), Duration::from_secs(60), |j| {
                j["status"] != "queued" && j["status"] != "running"
            })
            .await;
        assert_eq!(job["status"], "succeeded", "{job}");
    }
    let all_done = started.elapsed();
    let hwm = s.memory_kb("VmHWM");
    println!(
        "load: 20 submissions in {:.0} ms (slowest {:.0} ms); 1000 status requests in {:.0} ms \
         ({:.0} req/s; latency p50 {:.1} ms, p95 {:.1} ms, p99 {:.1} ms, max {:.1} ms), {failed} failed; \
         all 20 jobs succeeded after {:.1} s; server peak RSS {} MB",
        submit_wall.as_secs_f64() * 1e3,
        submit_max.as_secs_f64() * 1e3,
        status_wall.as_secs_f64() * 1e3,
        1000.0 / status_wall.as_secs_f64(),
        pct(0.5).as_secs_f64() * 1e3,
        pct(0.95).as_secs_f64() * 1e3,
        pct(0.99).as_secs_f64() * 1e3,
        latencies.last().unwrap().as_secs_f64() * 1e3,
        all_done.as_secs_f64(),
        hwm / 1024
    );
    assert_eq!(failed, 0, "status requests failed");
    assert!(all_done < Duration::from_secs(30), "took {all_done:?}");
}
