//! The streamed set against the set intake loads whole: the same planes and results,
//! spills gone after success, error and cancel, prescans, and errors named as intake
//! names them.

use std::io::Seek;

use image::ImageBuffer;

use super::file_bands::rows_of;
use super::*;
use crate::core::lights::{Intensity, make_light};

/// A band cut from a decoded image is the cropped view's pixels, for every layout.
#[test]
fn rows_of_matches_a_cropped_copy() {
    let base = DynamicImage::ImageRgb16(ImageBuffer::from_fn(5, 7, |x, y| {
        image::Rgb([(x * 1000 + y) as u16, (y * 300) as u16, (x + y) as u16 * 77])
    }));
    for img in [
        DynamicImage::ImageLuma8(base.to_luma8()),
        DynamicImage::ImageLumaA8(base.to_luma_alpha8()),
        DynamicImage::ImageRgb8(base.to_rgb8()),
        DynamicImage::ImageRgba8(base.to_rgba8()),
        DynamicImage::ImageLuma16(base.to_luma16()),
        DynamicImage::ImageLumaA16(base.to_luma_alpha16()),
        base.clone(),
        DynamicImage::ImageRgba16(base.to_rgba16()),
        DynamicImage::ImageRgb32F(base.to_rgb32f()),
        DynamicImage::ImageRgba32F(base.to_rgba32f()),
    ] {
        for (first, n) in [(0, 7), (2, 3), (6, 1)] {
            let band = rows_of(&img, first, n);
            assert_eq!(band, img.crop_imm(0, first, 5, n), "{:?}", img.color());
        }
    }
}

/// Images of every kind the reader handles: 8- and 16-bit gray PNG, 8- and 16-bit RGB
/// PNG (colour), 16-bit RGBA PNG (read by rows); palette PNG, TIFF and BMP (decoded
/// whole).
fn write_set(
    dir: &Path,
    kind: &str,
    count: usize,
    rgb_light: bool,
) -> (Vec<Light>, Vec<NamedFile>) {
    let (w, h) = (37u32, 29u32);
    let mut lights = Vec::new();
    let mut files = Vec::new();
    for i in 0..count {
        let v = |x: u32, y: u32, c: u32| ((x * 7 + y * 13 + c * 5 + i as u32 * 11) % 256) as u8;
        let ext = match kind {
            "bmp" => "bmp",
            "tiff" => "tiff",
            _ => "png",
        };
        let name = format!("{i}.{ext}");
        let path = dir.join(&name);
        match kind {
            "gray8" => image::GrayImage::from_fn(w, h, |x, y| image::Luma([v(x, y, 0)]))
                .save(&path)
                .unwrap(),
            "rgb16" | "tiff" => image::ImageBuffer::from_fn(w, h, |x, y| {
                let c = |k| v(x, y, k) as u16 * 250 + y as u16;
                image::Rgb([c(0), c(1), c(2)])
            })
            .save(&path)
            .unwrap(),
            "palette" => write_palette_png(&path, w, h, |x, y| v(x, y, 0) % 16),
            "gray16" => image::ImageBuffer::from_fn(w, h, |x, y| {
                image::Luma([v(x, y, 0) as u16 * 250 + x as u16])
            })
            .save(&path)
            .unwrap(),
            "rgb8" | "bmp" => image::RgbImage::from_fn(w, h, |x, y| {
                image::Rgb([v(x, y, 0), v(x, y, 1), v(x, y, 2)])
            })
            .save(&path)
            .unwrap(),
            "rgba16" => image::ImageBuffer::from_fn(w, h, |x, y| {
                let c = |k| v(x, y, k) as u16 * 257;
                image::Rgba([c(0), c(0), c(0), 65535])
            })
            .save(&path)
            .unwrap(),
            _ => unreachable!(),
        }
        let a = i as f64 * 2.1;
        let d = [0.3 * a.cos(), 0.3 * a.sin(), 1.0];
        let intensity = rgb_light.then_some(Intensity::Rgb([0.9, 0.6 + 0.01 * i as f64, 0.4]));
        lights.push(make_light(i + 1, &name, d, intensity).unwrap());
        files.push(NamedFile { name, path });
    }
    (lights, files)
}

/// An 8-bit palette PNG of 16 colours (indices from `index`).
fn write_palette_png(path: &Path, w: u32, h: u32, index: impl Fn(u32, u32) -> u8) {
    let mut e = png::Encoder::new(std::io::BufWriter::new(File::create(path).unwrap()), w, h);
    e.set_color(png::ColorType::Indexed);
    e.set_depth(png::BitDepth::Eight);
    let palette: Vec<u8> = (0..16u8)
        .flat_map(|k| [k * 16, 255 - k * 9, k * 5])
        .collect();
    e.set_palette(palette);
    let mut writer = e.write_header().unwrap();
    let data: Vec<u8> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| index(x, y))
        .collect();
    writer.write_image_data(&data).unwrap();
}

/// Open descriptors of this process that point into `dir` (the spills, which are
/// unlinked, show as `dir/#inode (deleted)` or a deleted named file).
fn spills_open(dir: &Path) -> usize {
    (std::fs::read_dir("/proc/self/fd").unwrap())
        .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter(|target| target.starts_with(dir))
        .count()
}

/// Waits up to 5 s for every spill in `dir` to be closed (a run drops its set on a
/// thread of its own), and that nothing is left in it.
fn assert_no_spills(dir: &Path, when: &str) {
    let start = std::time::Instant::now();
    while spills_open(dir) > 0 && start.elapsed().as_secs() < 5 {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    assert_eq!(spills_open(dir), 0, "spills still open after {when}");
    let left: Vec<_> = std::fs::read_dir(dir).unwrap().collect();
    assert!(
        left.is_empty(),
        "left in the scratch directory after {when}: {left:?}"
    );
}

/// Every band read in order, concatenated per image; and the moments.
fn read_all(s: &mut Streamed) -> (Vec<Vec<u16>>, Vec<f32>) {
    let (h, step) = (s.info.height, s.band_rows());
    let mut planes = vec![Vec::new(); s.images.len()];
    let mut moments = Vec::new();
    for r0 in (0..h).step_by(step) {
        let band = s.band(r0..(r0 + step).min(h)).unwrap();
        for (p, b) in planes.iter_mut().zip(&band.planes) {
            p.extend_from_slice(b);
        }
        moments.extend_from_slice(band.moments.unwrap_or_default());
    }
    (planes, moments)
}

#[test]
fn bands_are_the_planes_intake_decodes_whole() {
    for (kind, rgb_light) in [
        ("gray8", false),
        ("gray16", false),
        ("rgb8", true),
        ("rgb8", false),
        ("rgb16", true),
        ("rgba16", false),
        ("palette", true),
        ("tiff", true),
        ("bmp", true),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let scratch = tempfile::tempdir().unwrap();
        let (lights, files) = write_set(dir.path(), kind, 5, rgb_light);
        let whole = intake::load(lights.clone(), &files, None, &Limits::default()).unwrap();
        let mut s = open(lights, &files, None, &Limits::default(), scratch.path()).unwrap();
        assert_eq!(spills_open(scratch.path()), 5, "{kind}: one spill an image");
        // Small bands, so that the reader is asked for many.
        s.band_rows = 4;
        assert_eq!(s.info.bit_depth, whole.bit_depth, "{kind}");
        assert_eq!(s.info.colour, whole.colour_moments.is_some(), "{kind}");
        for (a, b) in s.info.lights.iter().zip(&whole.lights) {
            assert_eq!(a.intensity, b.intensity, "{kind}");
        }
        let sampled = crate::core::bands::InMemory::new(&whole);
        assert_eq!(s.samples.planes, sampled.samples().planes, "{kind}");
        let (planes, moments) = read_all(&mut s);
        for (p, w) in planes.iter().zip(&whole.planes) {
            assert_eq!(p.as_slice(), w.as_slice().unwrap(), "{kind}");
        }
        if let Some(m) = &whole.colour_moments {
            // Both add each image's moments in table order: the same sums, bit for bit.
            assert_eq!(
                m.as_slice().unwrap(),
                moments.as_slice(),
                "{kind}: moments differ"
            );
        }
        drop(s);
        assert_no_spills(scratch.path(), kind);
    }
}

/// A spilled set's job writes exactly the artifacts of the set loaded whole.
#[test]
fn spilled_sets_reconstruct_bit_identically() {
    use crate::core::{Options, RunToEnd, bands::InMemory, pipeline};
    for (kind, rgb_light) in [("gray16", false), ("rgb8", true), ("tiff", true)] {
        let dir = tempfile::tempdir().unwrap();
        let scratch = tempfile::tempdir().unwrap();
        let out = tempfile::tempdir().unwrap();
        let (lights, files) = write_set(dir.path(), kind, 6, rgb_light);
        let limits = Limits::default();
        let opts = Options::default();
        let whole = intake::load(lights.clone(), &files, None, &limits).unwrap();
        let (a, b) = (out.path().join("whole"), out.path().join("spilled"));
        pipeline::run(InMemory::new(whole), &opts, &a, &mut RunToEnd).unwrap();
        let s = open(lights, &files, None, &limits, scratch.path()).unwrap();
        pipeline::run(s, &opts, &b, &mut RunToEnd).unwrap();
        let mut compared = 0;
        for entry in std::fs::read_dir(&a).unwrap() {
            let name = entry.unwrap().file_name();
            if name == "result.json" {
                continue; // its timings differ
            }
            let (x, y) = (std::fs::read(a.join(&name)), std::fs::read(b.join(&name)));
            let (x, y) = (x.unwrap(), y.unwrap());
            assert!(x == y, "{kind}: {name:?} differs");
            compared += 1;
        }
        assert!(compared >= 3, "{kind}: {compared} artifacts");
        assert_no_spills(scratch.path(), kind);
    }
}

/// Spills are closed, and nothing is left in the scratch directory, after a run that
/// succeeds, a set that fails to open and a run that is stopped.
#[test]
fn spills_go_after_success_error_and_cancel() {
    use crate::core::progress::Stage;
    use crate::core::{Options, RunError, RunToEnd, pipeline};
    let dir = tempfile::tempdir().unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let out = tempfile::tempdir().unwrap();
    let limits = Limits::default();
    let (lights, files) = write_set(dir.path(), "gray16", 6, false);

    let s = open(lights.clone(), &files, None, &limits, scratch.path()).unwrap();
    assert_eq!(spills_open(scratch.path()), 6);
    let opts = Options::default();
    pipeline::run(s, &opts, &out.path().join("a"), &mut RunToEnd).unwrap();
    assert_no_spills(scratch.path(), "success");

    let s = open(lights.clone(), &files, None, &limits, scratch.path()).unwrap();
    let mut stop = |stage: Stage| stage != Stage::Integrate;
    let stopped = pipeline::run(s, &opts, &out.path().join("b"), &mut stop);
    assert!(matches!(stopped, Err(RunError::Cancelled)), "{stopped:?}");
    assert_no_spills(scratch.path(), "cancel");

    // The last image broken: the others were spilled before its error.
    let bytes = std::fs::read(&files[5].path).unwrap();
    std::fs::write(&files[5].path, &bytes[..bytes.len() / 2]).unwrap();
    let e = open(lights, &files, None, &limits, scratch.path()).err();
    assert!(e.expect("a broken image").to_string().contains("5.png"));
    assert_no_spills(scratch.path(), "error");
}

/// A scratch directory that cannot take the spills is an error naming it.
#[test]
fn a_scratch_directory_that_fails_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (lights, files) = write_set(dir.path(), "gray16", 3, false);
    let missing = dir.path().join("no-such-dir");
    let e = open(lights, &files, None, &Limits::default(), &missing)
        .err()
        .expect("no scratch directory")
        .to_string();
    assert!(e.contains("no-such-dir") && e.contains("scratch"), "{e}");
}

#[test]
fn prescanned_images_give_the_same_set() {
    let dir = tempfile::tempdir().unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let limits = Limits::default();
    for kind in ["rgb8", "bmp"] {
        let (lights, files) = write_set(dir.path(), kind, 4, true);
        let mut plain = open(lights.clone(), &files, None, &limits, scratch.path()).unwrap();
        let ahead = |i: usize| {
            let mut f = File::open(&files[i].path).unwrap();
            // Read from its start, wherever the handle stands.
            f.seek(std::io::SeekFrom::End(0)).unwrap();
            i.is_multiple_of(2)
                .then(|| Ok(prescan(f, &limits, scratch.path()).expect("scanned ahead")))
        };
        let mut prescanned =
            open_with(lights, &files, None, &limits, scratch.path(), ahead).unwrap();
        assert_eq!(plain.samples.planes, prescanned.samples.planes);
        assert_eq!(read_all(&mut plain), read_all(&mut prescanned));
    }
    // Errors are left to the set.
    std::fs::write(dir.path().join("junk"), b"not an image").unwrap();
    let junk = File::open(dir.path().join("junk")).unwrap();
    assert!(prescan(junk, &limits, scratch.path()).is_none());
    assert_no_spills(scratch.path(), "prescans dropped");
}

#[test]
fn bands_out_of_order_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (lights, files) = write_set(dir.path(), "gray16", 3, false);
    let mut s = open(lights, &files, None, &Limits::default(), dir.path()).unwrap();
    assert!(s.band(0..5).is_ok());
    let e = s.band(10..12).err().expect("a skipped band").to_string();
    assert!(e.contains("out of order"), "{e}");
}

#[test]
fn a_broken_png_gets_the_error_intake_gives() {
    let dir = tempfile::tempdir().unwrap();
    let (lights, files) = write_set(dir.path(), "gray16", 4, false);
    let bytes = std::fs::read(&files[2].path).unwrap();
    std::fs::write(&files[2].path, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let whole = intake::load(lights.clone(), &files, None, &Limits::default());
    let streamed = open(lights, &files, None, &Limits::default(), dir.path());
    let (a, b) = (
        whole.err().unwrap().to_string(),
        streamed.err().unwrap().to_string(),
    );
    assert_eq!(a, b);
    assert!(a.contains("2.png"), "{a}");
}
