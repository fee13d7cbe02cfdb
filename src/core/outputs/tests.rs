//! The encoders' round trips and the pictures' pixel rules.

use std::io::Cursor;

use exr::prelude::{SpecificChannels, Vec2};
use image::ImageFormat;
use ndarray::{Array2, Array3};

use super::encoding::*;
use super::names::*;
use super::pictures::*;
use super::reshade::*;
use crate::core::commit::Committer;
use crate::core::progress::NEVER;

#[test]
fn unit16_rounds_like_f32_round() {
    let edges = (0..=65535u32).flat_map(|k| {
        let x = k as f32 / 65535.0;
        [x, x + 0.5 / 65535.0, (k as f32 + 0.5).next_down() / 65535.0]
    });
    for v in edges.chain([-1.0, 2.0, f32::NAN, f32::INFINITY]) {
        let expected = (v.clamp(0.0, 1.0) * 65535.0).round() as u16;
        assert_eq!(unit16(v), expected, "{v}");
    }
}

#[test]
fn png16_rows_decode_to_their_samples() {
    let mask = Array2::from_shape_fn((3, 4), |(r, c)| r != c);
    let plane = |k: usize| Array2::from_shape_fn((3, 4), |(r, c)| (r * 4 + c + k) as f32 / 20.0);
    let (a, b, c) = (plane(0), plane(1), plane(2));
    let flip = |k: usize, v: f32| if k == 1 { 1.0 - v } else { v };
    let mut rgb = Vec::new();
    png16_to(&mut rgb, &mask, [a.view(), b.view(), c.view()], flip).unwrap();
    let rgb = decode_png16(&rgb).unwrap().into_rgb16();
    let mut gray = Vec::new();
    png16_to(&mut gray, &mask, [a.view()], |_, v| v).unwrap();
    let gray = decode_png16(&gray).unwrap().into_luma16();
    for ((r, col), &m) in mask.indexed_iter() {
        let want = |k: usize, v: f32| if m { unit16(flip(k, v)) } else { 0 };
        let px = rgb.get_pixel(col as u32, r as u32).0;
        assert_eq!(
            px,
            [0, 1, 2].map(|k| want(k, plane(k)[[r, col]])),
            "({r}, {col})"
        );
        assert_eq!(
            gray.get_pixel(col as u32, r as u32).0,
            [want(0, a[[r, col]])]
        );
    }
}

/// A hemisphere of varying albedo on a disc mask, in the seed frame.
fn dome(n: usize) -> (Array2<f32>, Array3<f32>, Array2<bool>) {
    let c = (n as f32 - 1.0) / 2.0;
    let mask = Array2::from_shape_fn((n, n), |(r, col)| {
        (r as f32 - c).hypot(col as f32 - c) < 0.45 * n as f32
    });
    let mut normals = Array3::zeros((n, n, 3));
    let mut albedo = Array2::zeros((n, n));
    for ((r, col), &m) in mask.indexed_iter() {
        if m {
            let (x, y) = (
                (col as f32 - c) / (0.5 * n as f32),
                (r as f32 - c) / (0.5 * n as f32),
            );
            let z = (1.0 - x * x - y * y).sqrt();
            normals[[r, col, 0]] = x;
            normals[[r, col, 1]] = y;
            normals[[r, col, 2]] = z;
            albedo[[r, col]] = 0.3 + 0.6 * (col as f32 / n as f32);
        }
    }
    (albedo, normals, mask)
}

#[test]
fn reshading_from_the_pictures_matches_shaded_png() {
    let (albedo, normals, mask) = dome(48);
    let zero = Array2::zeros(mask.dim());
    let no = Array2::from_elem(mask.dim(), false);
    let maps = Maps {
        albedo: &albedo,
        albedo_rgb: None,
        normals: &normals,
        mask: &mask,
        curl: None,
        confidence: &zero,
        unreliable: &no,
        gloss: None,
        heights: None,
    };
    let dir = tempfile::tempdir().unwrap();
    let light = [-1.0, 0.5, 2.0];
    let names = ["albedo.png", "normal.png", "shaded.png"];
    write_pictures(&maps, &names, light, dir.path(), &Committer::new(), NEVER).unwrap();
    let direct = image::open(dir.path().join("shaded.png"))
        .unwrap()
        .into_luma16();
    let again = decode_png16(&shaded_png_from_dir(dir.path(), light).unwrap())
        .unwrap()
        .into_luma16();
    let worst = direct
        .pixels()
        .zip(again.pixels())
        .map(|(a, b)| a.0[0].abs_diff(b.0[0]))
        .max()
        .unwrap();
    // 16-bit albedo and normals: a few units in the last bit, nothing more.
    assert!(worst <= 4, "re-shaded differs by {worst} / 65535");
    assert!(direct.pixels().any(|p| p.0[0] > 10_000), "the dome is lit");
}

#[test]
fn the_default_selection_is_the_default_set_and_all_is_everything() {
    let all = [ALL.to_string()];
    for name in UNSELECTED {
        assert!(!wanted(Some(&all), name, false) && !wanted(Some(&all), name, true));
    }
    for (name, _) in ARTIFACTS.iter().filter(|(n, _)| !UNSELECTED.contains(n)) {
        assert_eq!(
            wanted(None, name, false),
            DEFAULT_OUTPUTS.contains(name) && !name.starts_with("depth."),
            "{name}"
        );
        assert!(wanted(Some(&all), name, false) || name.starts_with("depth."));
        // Under a camera: depth in place of heights, and the point cloud.
        let depth = DEFAULT_OUTPUTS.contains(name) || DEFAULT_DEPTH_OUTPUTS.contains(name);
        assert_eq!(
            wanted(None, name, true),
            depth && !name.starts_with("height."),
            "{name}"
        );
        assert!(wanted(Some(&all), name, true) || name.starts_with("height."));
    }
    let some = ["mesh.gltf".to_string()];
    assert!(wanted(Some(&some), "mesh.gltf", false) && !wanted(Some(&some), "albedo.png", false));
    let mut defaults = DEFAULT_OUTPUTS.iter().chain(DEFAULT_DEPTH_OUTPUTS);
    assert!(defaults.all(|n| content_type(n).is_some()));
    assert!(check_selection(&[ALL.to_string(), "height.exr".into()]).is_ok());
    assert!(check_selection(&["everything".to_string()]).is_err());
}

#[test]
fn exr_files_round_trip() {
    let (rows, cols) = (3, 5);
    let rgb = |r: usize, c: usize| [r as f32, c as f32 * 0.5, -1.25];
    let mut out = Cursor::new(Vec::new());
    let n = SpecificChannels::rgb(|p: Vec2<usize>| rgb(p.y(), p.x()).into());
    exr_to(&mut out, &exr_image((rows, cols), n)).unwrap();
    // An RGB file reads back through the image crate too.
    let img = image::load_from_memory_with_format(out.get_ref(), ImageFormat::OpenExr)
        .unwrap()
        .to_rgb32f();
    assert_eq!(img.dimensions(), (cols as u32, rows as u32));
    for (c, r, px) in img.enumerate_pixels() {
        assert_eq!(px.0, rgb(r as usize, c as usize), "({r}, {c})");
    }

    let z = Array2::from_shape_fn((rows, cols), |(r, c)| r as f32 - c as f32 * 0.25);
    let mut out = Cursor::new(Vec::new());
    let y = SpecificChannels::build()
        .with_channel("Y")
        .with_pixel_fn(|p: Vec2<usize>| (z[[p.y(), p.x()]],));
    exr_to(&mut out, &exr_image((rows, cols), y)).unwrap();
    assert_eq!(decode_height_exr(out.get_ref()).unwrap(), z);
}
