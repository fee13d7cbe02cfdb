//! Every bad input the core refuses, with a message that names the problem.

use std::path::Path;

use crate::common;

use image::{GrayImage, ImageBuffer, Luma, Rgb, RgbImage};
use photostereo::core::intake::{self, Limits};
use photostereo::core::{Options, RunToEnd, reconstruct};

fn gray(path: &Path, w: u32, h: u32) {
    GrayImage::from_pixel(w, h, Luma([100])).save(path).unwrap();
}

/// A folder with `names` as 8×8 gray PNGs and the given light table.
fn folder(names: &[&str], table: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for n in names {
        gray(&dir.path().join(n), 8, 8);
    }
    std::fs::write(dir.path().join("light_directions.csv"), table).unwrap();
    dir
}

const TABLE: &str = "a.png, 0, 0, 1\nb.png, 0.5, 0, 1\nc.png, 0, 0.5, 1\n";

fn load_err(dir: &Path) -> String {
    intake::load_dir(dir, intake::DirMask::Folder, &Limits::default())
        .unwrap_err()
        .to_string()
}

#[test]
fn a_good_folder_loads() {
    let d = folder(&["a.png", "b.png", "c.png"], TABLE);
    let set = intake::load_dir(d.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    assert_eq!(
        (set.width, set.height, set.planes.len(), set.bit_depth),
        (8, 8, 3, 8)
    );
    assert_eq!(set.planes[0][[0, 0]], 100 * 257);
}

#[test]
fn fewer_than_three_images() {
    let d = folder(&["a.png", "b.png"], "a.png, 0, 0, 1\nb.png, 0.5, 0, 1\n");
    assert!(load_err(d.path()).contains("at least 3 images with lights, got 2"));
}

#[test]
fn image_named_but_missing_and_the_reverse() {
    let d = folder(&["a.png", "b.png"], TABLE);
    let e = load_err(d.path());
    assert!(e.contains("\"c.png\"") && e.contains("not provided"), "{e}");
    // An image the table does not name is ignored, and said so once.
    let d = folder(&["a.png", "b.png", "c.png", "extra.png", "more.png"], TABLE);
    let set = intake::load_dir(d.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    assert_eq!(set.planes.len(), 3);
    assert_eq!(set.notes.len(), 1, "{:?}", set.notes);
    assert!(
        set.notes[0].contains("extra.png, more.png"),
        "{:?}",
        set.notes
    );
}

#[test]
fn a_folder_in_no_layout_lists_the_layouts() {
    let dir = tempfile::tempdir().unwrap();
    for n in ["a.png", "b.png", "c.png"] {
        gray(&dir.path().join(n), 8, 8);
    }
    std::fs::write(dir.path().join("lights.csv"), TABLE).unwrap();
    let e = load_err(dir.path());
    for name in [
        "light_directions.csv",
        "light_directions.json",
        "light_directions.txt",
        "filenames.txt",
        "light_intensities.txt",
    ] {
        assert!(e.contains(name), "{e}");
    }
}

#[test]
fn images_of_different_sizes() {
    let d = folder(&["a.png", "b.png"], TABLE);
    gray(&d.path().join("c.png"), 9, 8);
    let e = load_err(d.path());
    assert!(e.contains("\"c.png\" is 9×8") && e.contains("8×8"), "{e}");
}

#[test]
fn mixed_bit_depths() {
    let d = folder(&["a.png", "b.png"], TABLE);
    ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(8, 8, Luma([1000]))
        .save(d.path().join("c.png"))
        .unwrap();
    let e = load_err(d.path());
    assert!(
        e.contains("\"c.png\" is 16-bit") && e.contains("8-bit"),
        "{e}"
    );
}

#[test]
fn undecodable_and_unsupported_files() {
    let d = folder(&["a.png", "b.png"], TABLE);
    std::fs::write(d.path().join("c.png"), b"\x89PNG\r\n\x1a\n truncated").unwrap();
    let e = load_err(d.path());
    assert!(e.contains("\"c.png\" cannot be decoded"), "{e}");
    std::fs::write(d.path().join("c.png"), b"just some text, not an image").unwrap();
    let e = load_err(d.path());
    assert!(
        e.contains("\"c.png\" is not a supported image format"),
        "{e}"
    );
}

#[test]
fn bad_vectors_and_duplicates() {
    for (table, needle) in [
        (
            "a.png, 0, 0, 0\nb.png, 0.5, 0, 1\nc.png, 0, 0.5, 1\n",
            "row 1: light vector of \"a.png\" is zero",
        ),
        (
            "a.png, 0, 0, 1\nb.png, nan, 0, 1\nc.png, 0, 0.5, 1\n",
            "row 2: light vector of \"b.png\" has a non-finite",
        ),
        (
            "a.png, 0, 0, 1\nb.png, 0.5, 0, 1\nc.png, 0, up, 1\n",
            "row 3: y of \"c.png\" is not a number: \"up\"",
        ),
        (
            "a.png, 0, 0, 1\nb.png, 0.5, 0, 1\na.png, 0, 0.5, 1\n",
            "\"a.png\" appears twice in the light table (rows 1 and 3)",
        ),
    ] {
        let d = folder(&["a.png", "b.png", "c.png"], table);
        let e = load_err(d.path());
        assert!(e.contains(needle), "{e} should contain {needle}");
    }
}

#[test]
fn decompression_bomb_header_is_refused_before_decoding() {
    let d = folder(&["a.png", "b.png", "c.png"], TABLE);
    let limits = Limits {
        max_pixels_per_image: 32,
        ..Limits::default()
    };
    let e = intake::load_dir(d.path(), intake::DirMask::Folder, &limits).unwrap_err();
    assert!(e.is_too_large());
    assert!(
        e.to_string()
            .contains("\"a.png\" is 8×8 = 64 pixels, over the limit of 32"),
        "{e}"
    );
}

#[test]
fn palette_pngs_decode_and_a_ragged_palette_is_refused() {
    // A well-formed palette: entry (x + y) % 4 of the ramp 0, 85, 170, 255.
    let plane = intake::to_luma16(
        intake::decode("a.png", &common::palette_png(6, 5, 0), &Limits::default()).unwrap(),
    );
    assert_eq!(plane.dim(), (5, 6));
    for ((y, x), &v) in plane.indexed_iter() {
        assert_eq!(v, ((x + y) % 4) as u16 * 85 * 257, "({x}, {y})");
    }
    // 13 or 14 bytes: the png crate would panic expanding it.
    for extra in [1, 2] {
        let e = intake::decode(
            "a.png",
            &common::palette_png(6, 5, extra),
            &Limits::default(),
        )
        .unwrap_err()
        .to_string();
        let len = 12 + extra;
        assert!(e.contains("\"a.png\""), "{e}");
        assert!(
            e.contains(&format!("PLTE (palette) chunk is {len} bytes long")),
            "{e}"
        );
    }
}

#[test]
fn ill_conditioned_and_rank_deficient_light_sets() {
    let coplanar = "a.png, 1, 0, 1\nb.png, -1, 0, 1\nc.png, 0, 0, 1\n";
    let d = folder(&["a.png", "b.png", "c.png"], coplanar);
    let set = intake::load_dir(d.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    let e = reconstruct(&set, &Options::default(), &mut RunToEnd)
        .unwrap_err()
        .to_string();
    assert!(e.contains("rank 2"), "{e}");

    let narrow = "a.png, 0, 0, 1\nb.png, 0.001, 0, 1\nc.png, 0, 0.001, 1\n";
    let d = folder(&["a.png", "b.png", "c.png"], narrow);
    let set = intake::load_dir(d.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    let e = reconstruct(&set, &Options::default(), &mut RunToEnd)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ill-conditioned") && e.contains("exceeds the limit 100.0"),
        "{e}"
    );
}

#[test]
fn mask_of_the_wrong_size() {
    let d = folder(&["a.png", "b.png", "c.png"], TABLE);
    let m = d.path().join("mask.bmp");
    gray(&m, 4, 4);
    let e = intake::load_dir(d.path(), intake::DirMask::File(&m), &Limits::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("mask") && e.contains("4×4"), "{e}");
}

#[test]
fn colour_inputs_keep_per_channel_albedo() {
    let d = tempfile::tempdir().unwrap();
    let table = "a.png, 0, 0, 1\nb.png, 0.5, 0, 1\nc.png, 0, 0.5, 1\n";
    std::fs::write(d.path().join("light_directions.csv"), table).unwrap();
    // A flat reddish plate facing the camera: intensity = albedo_c · l_z.
    for (name, lz) in [
        ("a.png", 1.0f64),
        ("b.png", 1.0 / 1.25f64.sqrt()),
        ("c.png", 1.0 / 1.25f64.sqrt()),
    ] {
        let px = [0.8, 0.4, 0.2].map(|a| (a * lz * 255.0).round() as u8);
        RgbImage::from_pixel(6, 6, Rgb(px))
            .save(d.path().join(name))
            .unwrap();
    }
    let set = intake::load_dir(d.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    let rec = reconstruct(&set, &Options::default(), &mut RunToEnd).unwrap();
    let rgb = rec.albedo_rgb.expect("colour inputs give albedo_rgb");
    for (k, want) in [0.8f32, 0.4, 0.2].iter().enumerate() {
        assert!(
            (rgb[[3, 3, k]] - want).abs() < 0.01,
            "channel {k}: {}",
            rgb[[3, 3, k]]
        );
    }
}

/// The light table and the images of a folder, as `intake::load` takes them.
fn table_and_files(
    dir: &Path,
) -> (
    Vec<photostereo::core::lights::Light>,
    Vec<intake::NamedFile>,
) {
    let table = std::fs::read(dir.join("light_directions.csv")).unwrap();
    let lights = photostereo::core::lights::parse_bytes(&table).unwrap();
    let files = lights
        .iter()
        .map(|l| intake::NamedFile {
            name: l.name.clone(),
            path: dir.join(&l.name),
        })
        .collect();
    (lights, files)
}

/// `intake::predecode` of a file, as a service would do it with the bytes it received.
fn predecode(
    file: &intake::NamedFile,
    limits: &Limits,
) -> Option<Result<intake::Decoded, photostereo::core::InputError>> {
    intake::predecode(&file.name, &std::fs::read(&file.path).unwrap(), limits)
}

#[test]
fn predecoded_images_give_the_same_set() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("res/bump");
    let limits = Limits::default();
    let (lights, files) = table_and_files(&dir);
    let plain = intake::load(lights.clone(), &files, None, &limits).unwrap();
    // Every image ready-made, and only some of them.
    for every in [1, 2] {
        let set = intake::load_with(lights.clone(), &files, None, &limits, |i| {
            (i % every == 0).then(|| predecode(&files[i], &limits).unwrap())
        })
        .unwrap();
        assert_eq!(set.planes, plain.planes);
        assert_eq!(
            (set.width, set.height, set.bit_depth),
            (plain.width, plain.height, plain.bit_depth)
        );
        assert!(set.colour_moments.is_none() && plain.colour_moments.is_none());
    }
}

#[test]
fn predecoded_errors_are_the_load_errors_in_table_order() {
    let d = folder(&["a.png"], TABLE);
    std::fs::write(d.path().join("b.png"), b"\x89PNG\r\n\x1a\n truncated").unwrap();
    std::fs::write(d.path().join("c.png"), b"just some text, not an image").unwrap();
    let limits = Limits::default();
    let (lights, files) = table_and_files(d.path());
    let plain = intake::load(lights.clone(), &files, None, &limits)
        .unwrap_err()
        .to_string();
    assert!(plain.contains("\"b.png\" cannot be decoded"), "{plain}");
    // c.png's error decoded ahead, b.png's found by the load: still b.png's.
    for ahead in [vec![2], vec![1, 2], vec![0, 1, 2]] {
        let e = intake::load_with(lights.clone(), &files, None, &limits, |i| {
            ahead
                .contains(&i)
                .then(|| predecode(&files[i], &limits).unwrap())
        })
        .unwrap_err()
        .to_string();
        assert_eq!(e, plain, "ahead: {ahead:?}");
    }
}

#[test]
fn colour_images_are_left_to_the_load() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("a.png");
    RgbImage::from_pixel(4, 4, Rgb([200, 100, 50]))
        .save(&path)
        .unwrap();
    let limits = Limits::default();
    let file = intake::NamedFile {
        name: "a.png".into(),
        path: path.clone(),
    };
    assert!(predecode(&file, &limits).is_none());
    // A gray picture stored as RGB is gray: decoded ahead like any other.
    RgbImage::from_pixel(4, 4, Rgb([90, 90, 90]))
        .save(&path)
        .unwrap();
    let ready = predecode(&file, &limits).unwrap().unwrap();
    assert_eq!((ready.depth, ready.plane[[0, 0]]), (8, 90 * 257));
}
