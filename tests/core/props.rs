//! Property tests of the parsers that see client bytes first: the light table, the options
//! JSON, image intake and the service's zip reader. None may panic on any input; what
//! they accept must be usable, what they refuse is an input error (4xx), and each call
//! stays fast.

use crate::common;

use std::collections::HashSet;
use std::io::{Cursor, Write};
use std::time::{Duration, Instant};

use photostereo::core::intake::{self, Limits};
use photostereo::core::lights::{self, Light};
use photostereo::core::{InputError, Options};
use photostereo::service::{Config, parse_options, unpack_archive};
use proptest::prelude::*;
use proptest::test_runner::Config as PropConfig;
use serde_json::Value;

fn cases(n: u32) -> PropConfig {
    PropConfig {
        cases: n,
        failure_persistence: None,
        ..PropConfig::default()
    }
}

// ---------------------------------------------------------------------------------------
// Light tables.

/// What an accepted table must be: ≥ 3 rows, unique non-empty names, unit finite
/// directions, positive finite intensities.
fn check_table(table: &[Light]) {
    assert!(table.len() >= 3);
    let mut names = HashSet::new();
    for l in table {
        assert!(!l.name.is_empty());
        assert!(names.insert(l.name.clone()), "duplicate {:?}", l.name);
        let norm = l.direction.iter().map(|c| c * c).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-9, "{:?}: norm {norm}", l.direction);
        assert!(l.intensity.is_finite() && l.intensity > 0.0, "{l:?}");
    }
}

/// A refusal of a light table is one of the table's own errors, with a message.
fn check_table_error(e: &InputError) {
    assert!(
        matches!(
            e,
            InputError::Lights(_)
                | InputError::LightRow { .. }
                | InputError::DuplicateName { .. }
                | InputError::TooFewImages { .. }
        ),
        "unexpected error kind: {e:?}"
    );
    assert!(!e.to_string().is_empty());
}

fn parse_checked(bytes: &[u8]) -> Result<Vec<Light>, InputError> {
    let start = Instant::now();
    let r = lights::parse_bytes(bytes);
    assert!(
        start.elapsed() < Duration::from_secs(1),
        "parsing {} bytes took {:?}",
        bytes.len(),
        start.elapsed()
    );
    match &r {
        Ok(t) => check_table(t),
        Err(e) => check_table_error(e),
    }
    r
}

/// A number as a table might spell it, good or bad.
fn number_text() -> impl Strategy<Value = String> {
    prop_oneof![
        6 => (-1000.0f64..1000.0).prop_map(|v| v.to_string()),
        2 => (-5i32..5).prop_map(|v| v.to_string()),
        1 => any::<f64>().prop_map(|v| format!("{v:e}")),
        2 => prop::sample::select(vec![
            "NaN", "nan", "inf", "-inf", "infinity", "1e400", "-1e400", "1e200", "1e-320",
            "0", "-0", "", " ", "x", "1,5", "0x10", "1_000", "+1", ".5", "5.", "١",
        ])
        .prop_map(str::to_string),
    ]
}

fn name_text() -> impl Strategy<Value = String> {
    prop_oneof![
        8 => "[a-z][a-z0-9_]{0,6}\\.png",
        1 => Just(String::new()),
        1 => "[^,#\r\n]{1,12}",
    ]
}

/// A CSV row: `name, x, y, z[, intensity]`, its separators varied.
fn csv_row() -> impl Strategy<Value = String> {
    (
        name_text(),
        prop::collection::vec(number_text(), 3..=3),
        prop::option::of(number_text()),
        prop::sample::select(vec![",", ", ", " ,", " , ", "\t,"]),
        prop::option::of("[ -~]{0,10}"),
    )
        .prop_map(|(name, xyz, intensity, sep, comment)| {
            let mut row = name;
            for v in xyz.iter().chain(intensity.iter()) {
                row.push_str(sep);
                row.push_str(v);
            }
            if let Some(c) = comment {
                row.push_str(" #");
                row.push_str(&c);
            }
            row
        })
}

/// A CSV table with blank lines, comments and mixed line endings.
fn csv_table() -> impl Strategy<Value = String> {
    (
        prop::collection::vec(
            prop_oneof![
                8 => csv_row(),
                1 => Just(String::new()),
                1 => "#[ -~]{0,20}",
            ],
            0..12,
        ),
        prop::sample::select(vec!["\n", "\r\n", "\r"]),
        any::<bool>(),
    )
        .prop_map(|(rows, eol, bom)| {
            let mut t = if bom {
                "\u{feff}".to_string()
            } else {
                String::new()
            };
            t.push_str(&rows.join(eol));
            t
        })
}

/// Damage: delete, insert or overwrite bytes, or cut the text short.
fn perturb(bytes: Vec<u8>, edits: Vec<(usize, u8, u8)>) -> Vec<u8> {
    let mut b = bytes;
    for (pos, kind, byte) in edits {
        let at = if b.is_empty() { 0 } else { pos % (b.len() + 1) };
        match kind % 4 {
            0 if at < b.len() => {
                b.remove(at);
            }
            1 => b.insert(at, byte),
            2 if at < b.len() => b[at] = byte,
            3 => b.truncate(at),
            _ => {}
        }
    }
    b
}

fn edits() -> impl Strategy<Value = Vec<(usize, u8, u8)>> {
    prop::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 0..6)
}

/// A JSON table, sometimes with the wrong shapes.
fn json_table() -> impl Strategy<Value = Value> {
    let number = prop_oneof![
        6 => (-100.0f64..100.0).prop_map(Value::from),
        1 => Just(Value::from(0)),
        1 => Just(Value::Null),
        1 => Just(Value::from("1")),
        1 => Just(Value::from(1e300)),
    ];
    let row = (
        name_text(),
        prop::collection::vec(number.clone(), 0..5),
        prop::option::of(number),
        prop::option::of(Just(("extra", Value::from(1)))),
    )
        .prop_map(|(name, direction, intensity, extra)| {
            let mut o = serde_json::Map::new();
            o.insert("name".into(), Value::from(name));
            o.insert("direction".into(), Value::from(direction));
            if let Some(i) = intensity {
                o.insert("intensity".into(), i);
            }
            if let Some((k, v)) = extra {
                o.insert(k.into(), v);
            }
            Value::Object(o)
        });
    (prop::collection::vec(row, 0..8), any::<bool>()).prop_map(|(rows, wrapped)| {
        if wrapped {
            serde_json::json!({ "lights": rows })
        } else {
            Value::from(rows)
        }
    })
}

proptest! {
    #![proptest_config(cases(12_000))]

    #[test]
    fn lights_never_panic_on_arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let _ = parse_checked(&bytes);
    }

    #[test]
    fn lights_survive_damaged_csv(table in csv_table(), edits in edits()) {
        let _ = parse_checked(table.as_bytes());
        let _ = parse_checked(&perturb(table.into_bytes(), edits));
    }

    #[test]
    fn lights_survive_damaged_json(table in json_table(), edits in edits()) {
        let text = serde_json::to_vec(&table).unwrap();
        let _ = parse_checked(&text);
        let _ = parse_checked(&perturb(text, edits));
    }
}

proptest! {
    #![proptest_config(cases(2000))]

    /// Well-formed tables parse to exactly their rows, in order, whatever the spelling.
    #[test]
    fn wellformed_csv_parses_to_its_rows(
        rows in prop::collection::vec(
            (prop::array::uniform3(-50.0f64..50.0), prop::option::of(0.01f64..100.0)),
            3..20,
        ),
        crlf in any::<bool>(),
    ) {
        prop_assume!(rows.iter().all(|(v, _)| v.iter().map(|c| c * c).sum::<f64>() > 1e-6));
        let eol = if crlf { "\r\n" } else { "\n" };
        let mut text = String::from("# name, x, y, z, intensity");
        for (i, (v, intensity)) in rows.iter().enumerate() {
            text.push_str(eol);
            text.push_str(&format!(" img{i}.png , {}, {},{}", v[0], v[1], v[2]));
            if let Some(k) = intensity {
                text.push_str(&format!(", {k}"));
            }
        }
        let table = parse_checked(text.as_bytes()).unwrap();
        prop_assert_eq!(table.len(), rows.len());
        for (i, (l, (v, intensity))) in table.iter().zip(&rows).enumerate() {
            prop_assert_eq!(&l.name, &format!("img{i}.png"));
            prop_assert_eq!(l.intensity, intensity.unwrap_or(1.0));
            let norm = v.iter().map(|c| c * c).sum::<f64>().sqrt();
            for k in 0..3 {
                prop_assert!((l.direction[k] - v[k] / norm).abs() < 1e-9);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// Options.

const WORDS: &[&str] = &[
    "solver",
    "mask",
    "integration",
    "shading_light",
    "mesh",
    "max_condition",
    "outputs",
    "max_vertices",
    "step",
    "height_scale",
    "pixel_size",
    "normals",
    "l2",
    "robust",
    "weighted",
    "auto",
    "none",
    "given",
    "poisson",
    "frankot-chellappa",
    "path",
    "photometric",
    "geometric",
    "albedo.png",
    "mesh.glb",
    "result.json",
];

fn json_leaf() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        any::<f64>().prop_filter_map("finite", |f| serde_json::Number::from_f64(f)
            .map(Value::Number)),
        prop::sample::select(vec![1e39, -1e39, 1e300, 5e-324, 0.0, -0.0, 1e-40])
            .prop_map(Value::from),
        prop::sample::select(WORDS).prop_map(Value::from),
        ".{0,8}".prop_map(Value::String),
    ]
}

fn json_key() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::sample::select(WORDS).prop_map(str::to_string),
        1 => "[a-z_]{0,8}",
    ]
}

fn json_value() -> impl Strategy<Value = Value> {
    json_leaf().prop_recursive(4, 48, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..5).prop_map(Value::Array),
            prop::collection::vec((json_key(), inner), 0..6)
                .prop_map(|kv| Value::Object(kv.into_iter().collect())),
        ]
    })
}

/// An object with the real fields, each with a plausible or implausible value.
fn options_like() -> impl Strategy<Value = Value> {
    let field = (
        prop::sample::select(vec![
            "solver",
            "mask",
            "integration",
            "shading_light",
            "max_condition",
            "outputs",
        ]),
        json_value(),
    );
    let mesh_field = (
        prop::sample::select(vec![
            "max_vertices",
            "step",
            "height_scale",
            "pixel_size",
            "normals",
        ]),
        json_leaf(),
    );
    (
        prop::collection::vec(field, 0..5),
        prop::option::of(prop::collection::vec(mesh_field, 0..5)),
    )
        .prop_map(|(fields, mesh)| {
            let mut o: serde_json::Map<String, Value> = fields
                .into_iter()
                .map(|(k, v)| (k.to_string(), v))
                .collect();
            if let Some(m) = mesh {
                o.insert(
                    "mesh".into(),
                    Value::Object(m.into_iter().map(|(k, v)| (k.to_string(), v)).collect()),
                );
            }
            Value::Object(o)
        })
}

/// The core's parse never panics; the service's (`parse_options`, what the `options` part
/// goes through) accepts only options that survive the trip a job gives them: stored as
/// JSON in the job record, read back by the worker.
fn check_options(v: &Value) {
    let text = serde_json::to_vec(v).unwrap();
    let core = serde_json::from_slice::<Options>(&text);
    assert_eq!(
        core.is_ok(),
        serde_json::from_value::<Options>(v.clone()).is_ok(),
        "{v}"
    );
    match parse_options(&text) {
        Ok(options) => {
            assert!(
                core.is_ok(),
                "{v}: the service accepts what the core refuses"
            );
            let stored = serde_json::to_value(&options).unwrap();
            let again: Options = serde_json::from_value(stored.clone()).unwrap_or_else(|e| {
                panic!("{v} is accepted but its stored form {stored} is not: {e}")
            });
            assert_eq!(again, options, "{v}");
        }
        Err(e) => {
            assert_eq!(e.status().as_u16(), 422, "{v}: {e}");
            assert!(e.detail().starts_with("options: "), "{e}");
        }
    }
}

proptest! {
    #![proptest_config(cases(12_000))]

    #[test]
    fn options_never_panic_on_arbitrary_json(v in json_value()) {
        check_options(&v);
    }

    #[test]
    fn options_like_objects_round_trip(v in options_like()) {
        check_options(&v);
    }

    #[test]
    fn options_never_panic_on_arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        let _ = serde_json::from_slice::<Options>(&bytes);
    }
}

// ---------------------------------------------------------------------------------------
// Image intake.

const LIMITS: Limits = Limits {
    max_pixels_per_image: 1 << 20,
    max_images: 8,
};

/// Small images in every format and layout intake reads (made once).
fn seeds() -> &'static [(&'static str, Vec<u8>)] {
    static SEEDS: std::sync::OnceLock<Vec<(&'static str, Vec<u8>)>> = std::sync::OnceLock::new();
    SEEDS.get_or_init(make_seeds)
}

fn make_seeds() -> Vec<(&'static str, Vec<u8>)> {
    let gray = image::GrayImage::from_fn(13, 7, |x, y| image::Luma([(x * 17 + y * 5) as u8]));
    let gray16 = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(9, 6, |x, y| {
        image::Luma([(x * 4000 + y * 300) as u16])
    });
    let rgb = image::RgbImage::from_fn(8, 8, |x, y| image::Rgb([x as u8 * 30, y as u8 * 30, 7]));
    let rgba = image::RgbaImage::from_fn(5, 9, |x, y| {
        image::Rgba([x as u8 * 40, 9, y as u8 * 20, 200])
    });
    let encode = |img: image::DynamicImage, format| {
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        out.into_inner()
    };
    use image::ImageFormat::*;
    vec![
        ("gray.png", encode(gray.clone().into(), Png)),
        ("gray16.png", encode(gray16.clone().into(), Png)),
        ("rgb.png", encode(rgb.clone().into(), Png)),
        ("rgba.png", encode(rgba.clone().into(), Png)),
        ("gray.bmp", encode(gray.clone().into(), Bmp)),
        ("rgb.bmp", encode(rgb.clone().into(), Bmp)),
        ("rgba.bmp", encode(rgba.into(), Bmp)),
        ("rgb.jpg", encode(rgb.clone().into(), Jpeg)),
        ("gray16.tif", encode(gray16.into(), Tiff)),
        ("rgb.tif", encode(rgb.into(), Tiff)),
        ("gray.tif", encode(gray.into(), Tiff)),
    ]
}

fn decode_checked(name: &str, bytes: &[u8]) {
    let start = Instant::now();
    let r = intake::decode(name, bytes, &LIMITS);
    let took = start.elapsed();
    assert!(
        took < Duration::from_secs(2),
        "{name}: {} bytes took {took:?}",
        bytes.len()
    );
    match r {
        Ok(img) => {
            let (w, h) = (img.width() as usize, img.height() as usize);
            assert!((w * h) as u64 <= LIMITS.max_pixels_per_image);
            assert_eq!(intake::to_luma16(img).dim(), (h, w));
        }
        Err(e) => {
            assert!(
                matches!(
                    e,
                    InputError::Decode { .. }
                        | InputError::UnsupportedFormat { .. }
                        | InputError::TooLarge { .. }
                ),
                "{name}: {e:?}"
            );
            assert!(e.to_string().contains(name), "{e}");
        }
    }
}

/// The gray PNG seed with its IHDR rewritten (dimensions, depth, colour type) and its CRC
/// fixed, so the decoder believes the header.
fn png_with_header(w: u32, h: u32, depth: u8, colour: u8) -> Vec<u8> {
    let mut png = seeds()[0].1.clone();
    png[16..20].copy_from_slice(&w.to_be_bytes());
    png[20..24].copy_from_slice(&h.to_be_bytes());
    png[24] = depth;
    png[25] = colour;
    let crc = crc32fast::hash(&png[12..29]);
    png[29..33].copy_from_slice(&crc.to_be_bytes());
    png
}

proptest! {
    #![proptest_config(cases(5000))]

    #[test]
    fn intake_never_panics_on_damaged_images(
        which in 0usize..11,
        edits in edits(),
    ) {
        let (name, bytes) = &seeds()[which];
        decode_checked(name, &perturb(bytes.clone(), edits));
    }

    #[test]
    fn intake_never_panics_on_arbitrary_bytes(
        magic in prop::sample::select(vec![
            &b"\x89PNG\r\n\x1a\n"[..], b"BM", b"\xff\xd8\xff", b"II*\0", b"MM\0*",
            b"v/1\x01", b"GIF89a", b"", b"RIFF", b"\0\0\0\x0cjP  ",
        ]),
        rest in prop::collection::vec(any::<u8>(), 0..300),
    ) {
        let mut bytes = magic.to_vec();
        bytes.extend(rest);
        decode_checked("x.img", &bytes);
    }

    /// Headers that lie about the size: refused or decoded within the limit, never a
    /// huge allocation (a decompression bomb needs the header's size to be believed).
    #[test]
    fn intake_refuses_lying_headers(
        w in prop_oneof![1u32..64, 1u32..=u32::MAX],
        h in prop_oneof![1u32..64, 1u32..=u32::MAX],
        depth in prop::sample::select(vec![1u8, 2, 4, 8, 16, 3, 0, 255]),
        colour in prop::sample::select(vec![0u8, 2, 3, 4, 6, 1, 7]),
    ) {
        decode_checked("lying.png", &png_with_header(w, h, depth, colour));
    }
}

// ---------------------------------------------------------------------------------------
// The service's archive reader.

fn zip_of(entries: &[(String, Vec<u8>)], deflate: bool) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let method = if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let opts = zip::write::SimpleFileOptions::default().compression_method(method);
    let mut names = HashSet::new();
    for (name, data) in entries {
        if !names.insert(name) {
            continue; // the writer refuses duplicates
        }
        w.start_file(name.as_str(), opts).unwrap();
        w.write_all(data).unwrap();
    }
    w.finish().unwrap().into_inner()
}

fn entry_name() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::sample::select(vec!["a.png", "b.png", "c.png", "light_directions.csv"])
            .prop_map(str::to_string),
        1 => prop::sample::select(vec![
            "../a.png", "/a.png", "set/a.png", "set/b.png", "set/light_directions.csv",
            "x/y/a.png", "__MACOSX/._a.png", ".DS_Store", "C:\\a.png", "set/", "a.png/",
            "light_directions.json", "", "./a.png", "a\0.png",
        ])
        .prop_map(str::to_string),
        1 => "[ -~]{0,12}",
    ]
}

fn entry_data() -> impl Strategy<Value = Vec<u8>> {
    let png = seeds()[0].1.clone();
    prop_oneof![
        3 => Just(png.clone()),
        1 => (Just(png), edits()).prop_map(|(p, e)| perturb(p, e)),
        1 => Just(b"a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n".to_vec()),
        1 => prop::collection::vec(any::<u8>(), 0..64),
        1 => Just(vec![0u8; 200_000]),
    ]
}

struct Scratch {
    dir: tempfile::TempDir,
    config: Config,
}

fn scratch() -> Scratch {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::new(dir.path());
    config.max_parts = 8;
    config.max_unpacked_bytes = 100_000;
    config.max_images = 4;
    config.max_pixels = 4096;
    Scratch { dir, config }
}

fn unpack_checked(s: &Scratch, zip: &[u8]) {
    let path = s.dir.path().join("in.zip");
    let out = s.dir.path().join("out");
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir(&out).unwrap();
    std::fs::write(&path, zip).unwrap();
    let start = Instant::now();
    let r = unpack_archive(&path, &out, &s.config);
    assert!(
        start.elapsed() < Duration::from_secs(2),
        "{:?}",
        start.elapsed()
    );
    let mut total = 0;
    for e in std::fs::read_dir(&out).unwrap() {
        let e = e.unwrap();
        let name = e.file_name().to_string_lossy().into_owned();
        assert!(
            (name.len() == 7 && name.ends_with(".img") || name == "mask.img")
                && e.file_type().unwrap().is_file(),
            "unexpected {name:?} in the output"
        );
        total += e.metadata().unwrap().len();
    }
    assert!(
        total <= s.config.max_unpacked_bytes,
        "{total} bytes unpacked"
    );
    match r {
        Ok((images, table)) => {
            assert!(images.len() <= s.config.max_images);
            assert!(table.len() <= 1 << 20);
        }
        Err(e) => {
            assert!(e.status().is_client_error(), "{e}");
            assert!(!e.detail().is_empty());
        }
    }
}

proptest! {
    #![proptest_config(cases(1500))]

    #[test]
    fn archive_reader_never_panics_on_odd_zips(
        entries in prop::collection::vec((entry_name(), entry_data()), 0..10),
        deflate in any::<bool>(),
        edits in edits(),
    ) {
        let s = scratch();
        let zip = zip_of(&entries, deflate);
        unpack_checked(&s, &zip);
        unpack_checked(&s, &perturb(zip, edits));
    }

    #[test]
    fn archive_reader_never_panics_on_arbitrary_bytes(
        bytes in prop::collection::vec(any::<u8>(), 0..400),
        signature in any::<bool>(),
    ) {
        let s = scratch();
        let mut zip = if signature { b"PK\x03\x04".to_vec() } else { Vec::new() };
        zip.extend(bytes);
        unpack_checked(&s, &zip);
    }
}

#[test]
fn archive_reader_accepts_the_seed_layouts() {
    let s = scratch();
    let mut config = s.config.clone();
    config.max_pixels = 1 << 20;
    config.max_unpacked_bytes = 1 << 30;
    let s = Scratch { config, ..s };
    let bump = common::repo_root().join("res/bump");
    for top in [None, Some("bump")] {
        let path = s.dir.path().join("in.zip");
        let out = s.dir.path().join(format!("out-{top:?}"));
        std::fs::create_dir(&out).unwrap();
        std::fs::write(&path, common::zip_folder(&bump, top)).unwrap();
        let (images, table) = unpack_archive(&path, &out, &s.config).unwrap();
        assert_eq!(images, ["im1.png", "im2.png", "im3.png", "im4.png"]);
        assert_eq!(lights::parse_bytes(&table).unwrap().len(), 4);
    }
}
