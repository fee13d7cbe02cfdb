use std::io::Cursor;

use image::{ImageBuffer, ImageFormat, Luma, Rgb, Rgb32FImage, Rgba};
use ndarray::{Array2, Array3};

use super::*;
use crate::core::outputs::png_bytes;

const W: usize = 24;
const H: usize = 16;

/// Unit normals in the project's frame (y down), all facing the camera, every direction
/// of x and y represented.
fn field() -> Array3<f32> {
    let mut n = Array3::zeros((H, W, 3));
    for r in 0..H {
        for c in 0..W {
            let x = (c as f32 - 11.5) / 16.0;
            let y = (r as f32 - 7.5) / 12.0;
            let z = (1.0 - x * x - y * y).sqrt();
            n[[r, c, 0]] = x;
            n[[r, c, 1]] = y;
            n[[r, c, 2]] = z;
        }
    }
    n
}

/// A vector in `convention`'s y direction.
fn stored(n: [f32; 3], convention: Convention) -> [f32; 3] {
    match convention {
        Convention::Opengl => [n[0], -n[1], n[2]],
        Convention::Directx => n,
    }
}

/// A PNG of `n` in `convention`, with `max` = 255 (8-bit) or 65535 (16-bit).
fn png(n: &Array3<f32>, convention: Convention, max: f32) -> Vec<u8> {
    let sample = |r: u32, c: u32| {
        let v = stored(
            [0, 1, 2].map(|k| n[[r as usize, c as usize, k]]),
            convention,
        );
        v.map(|v| ((v + 1.0) / 2.0 * max).round() as u16)
    };
    let (w, h) = (W as u32, H as u32);
    if max > 255.0 {
        png_bytes(&ImageBuffer::from_fn(w, h, |c, r| Rgb(sample(r, c))))
    } else {
        png_bytes(&ImageBuffer::from_fn(w, h, |c, r| {
            Rgb(sample(r, c).map(|v| v as u8))
        }))
    }
}

fn png16(n: &Array3<f32>, convention: Convention) -> Vec<u8> {
    png(n, convention, 65535.0)
}

fn exr(f: impl Fn(usize, usize) -> [f32; 3]) -> Vec<u8> {
    let img = Rgb32FImage::from_fn(W as u32, H as u32, |c, r| Rgb(f(r as usize, c as usize)));
    let mut out = Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb32F(img)
        .write_to(&mut out, ImageFormat::OpenExr)
        .unwrap();
    out.into_inner()
}

fn largest_difference(a: &Array3<f32>, b: &Array3<f32>) -> f32 {
    a.iter()
        .zip(b.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn each_convention_and_encoding_round_trips_into_the_project_frame() {
    let n = field();
    for convention in [Convention::Opengl, Convention::Directx] {
        let exr_bytes = exr(|r, c| stored([0, 1, 2].map(|k| n[[r, c, k]]), convention));
        for (bits, bytes, tolerance) in [
            (8, png(&n, convention, 255.0), 6e-3),
            (16, png16(&n, convention), 3e-5),
            (32, exr_bytes, 1e-6),
        ] {
            let map = decode("n", &bytes, None, convention, None, &Limits::default()).unwrap();
            assert_eq!(map.bits, bits);
            assert_eq!((map.width, map.height), (W, H));
            assert_eq!(map.counts.used, W * H, "{convention:?} {bits}-bit");
            assert_eq!(map.counts.back_facing + map.counts.not_unit, 0);
            let worst = largest_difference(&map.normals, &n);
            assert!(
                worst < tolerance,
                "{convention:?} {bits}-bit: off by {worst}"
            );
            for v in map.normals.lanes(ndarray::Axis(2)) {
                assert!((v.dot(&v).sqrt() - 1.0).abs() < 1e-5);
            }
        }
    }
    // Read in the other convention, y comes back mirrored.
    let map = decode(
        "n",
        &png16(&n, Convention::Opengl),
        None,
        Convention::Directx,
        None,
        &Limits::default(),
    );
    let y = map.unwrap().normals[[0, 0, 1]];
    assert!((y + n[[0, 0, 1]]).abs() < 1e-4, "{y} vs {}", n[[0, 0, 1]]);
}

#[test]
fn the_project_and_benchmark_conventions_are_opengl() {
    for alias in ["opengl", "project", "benchmark"] {
        let c: Convention = serde_json::from_value(serde_json::json!(alias)).unwrap();
        assert_eq!(c, Convention::Opengl);
        assert_eq!(
            <Convention as clap::ValueEnum>::from_str(alias, false),
            Ok(Convention::Opengl)
        );
    }
    assert_eq!(Convention::default(), Convention::Opengl);
    assert_eq!(
        serde_json::to_value(Convention::Directx).unwrap(),
        "directx"
    );
}

#[test]
fn background_and_odd_pixels_are_counted_each_once() {
    let n = field();
    // 16-bit RGBA: black, mid-grey, transparent and back-facing pixels, and a mask that
    // leaves out the last row.
    let img = ImageBuffer::from_fn(W as u32, H as u32, |c, r| {
        let (r, c) = (r as usize, c as usize);
        let v = stored([0, 1, 2].map(|k| n[[r, c, k]]), Convention::Opengl);
        let mut px = v.map(|v| ((v + 1.0) / 2.0 * 65535.0).round() as u16);
        let mut alpha = 65535;
        match (r, c) {
            (0, 0..=2) => px = [0; 3],
            (1, 0..=1) => px = [32768; 3],
            (2, 0) => alpha = 0,
            // z < 0: faces away; and a vector of length ~0.5.
            (3, 0) => px = [32768, 32768, 0],
            (4, 0) => px = [49152, 32768, 32768],
            _ => {}
        }
        Rgba([px[0], px[1], px[2], alpha])
    });
    let mask = ImageBuffer::from_fn(W as u32, H as u32, |_, r| {
        Luma([if r as usize == H - 1 { 0u8 } else { 255 }])
    });
    let m = png_bytes(&mask);
    let mask = Some(MaskInput {
        name: "m.png",
        bytes: &m,
    });
    let map = decode(
        "n.png",
        &png_bytes(&img),
        mask,
        Convention::Opengl,
        None,
        &Limits::default(),
    )
    .unwrap();
    let k = map.counts;
    assert_eq!(
        (k.black, k.zero_length, k.transparent, k.outside_mask),
        (3, 2, 1, W)
    );
    assert_eq!((k.back_facing, k.not_unit, k.non_finite), (1, 1, 0));
    assert_eq!(k.used, W * H - 3 - 2 - 1 - W);
    assert_eq!(k.pixels, W * H);
    assert!(!map.mask[[0, 0]] && !map.mask[[1, 1]] && !map.mask[[H - 1, 5]]);
    assert!(map.mask[[3, 0]] && map.mask[[4, 0]]);
    assert_eq!(map.normals[[3, 0, 2]], -1.0, "kept, unit length");
    assert_eq!(map.normals[[4, 0, 0]], 1.0, "renormalised");
    assert_eq!(map.normals[[0, 0, 2]], 0.0, "zero off the mask");

    // Float: NaN and infinite vectors are off; black is black; no length check.
    let bytes = exr(|r, c| match (r, c) {
        (0, 0) => [f32::NAN, 0.0, 1.0],
        (0, 1) => [0.0, f32::INFINITY, 1.0],
        (0, 2) => [0.0; 3],
        (0, 3) => [0.0, 0.0, 3.0],
        _ => [0.0, 0.0, 1.0],
    });
    let map = decode(
        "n.exr",
        &bytes,
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    )
    .unwrap();
    let k = map.counts;
    assert_eq!((k.non_finite, k.black, k.not_unit), (2, 1, 1));
    assert_eq!(map.normals[[0, 3, 2]], 1.0);
}

#[test]
fn under_a_camera_back_facing_is_judged_along_each_ray() {
    // Tilted 84° towards +x: towards an orthographic camera, but facing away from the
    // rays on the right of a wide-angle one.
    let t = [0.995f32, 0.0, 0.0995];
    let bytes = exr(|_, _| t);
    let ortho = decode(
        "n.exr",
        &bytes,
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    )
    .unwrap();
    assert_eq!(ortho.counts.back_facing, 0);
    let lens = Lens::Centred { focal_px: 20.0 };
    let wide = decode(
        "n.exr",
        &bytes,
        None,
        Convention::Opengl,
        Some(lens),
        &Limits::default(),
    )
    .unwrap();
    // n·d = 0.995 (u − cx)/20 − 0.0995 > 0 once u − cx > 2: columns 14 to 23.
    assert_eq!(wide.counts.back_facing, 10 * H);
    assert_eq!(wide.camera, Some(Pinhole::centred(20.0, W, H)));
}

#[test]
fn bad_inputs_get_errors_naming_the_file_and_the_problem() {
    let n = field();
    let good = png16(&n, Convention::Opengl);
    let err = |r: Result<NormalMap, NormalMapError>| r.unwrap_err();

    // A mask of another size.
    let small = png_bytes(&ImageBuffer::from_pixel(8, 8, Luma([255u8])));
    let mask = Some(MaskInput {
        name: "small.png",
        bytes: &small,
    });
    let e = err(decode(
        "n.png",
        &good,
        mask,
        Convention::Opengl,
        None,
        &Limits::default(),
    ));
    assert!(matches!(e, NormalMapError::MaskSize { .. }), "{e}");
    let text = e.to_string();
    assert!(text.contains("small.png") && text.contains("8×8") && text.contains("24×16"));

    // A photo, not a normal map: lengths all over the place.
    let photo = ImageBuffer::from_fn(W as u32, H as u32, |c, r| {
        let v = ((c * 37 + r * 91) % 200 + 30) as u8;
        Rgb([v, v / 2, 255 - v])
    });
    let e = err(decode(
        "photo.png",
        &png_bytes(&photo),
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    ));
    assert!(matches!(e, NormalMapError::NotUnitLength { .. }), "{e}");
    assert!(e.to_string().contains("photo.png") && e.to_string().contains("not a normal map"));

    // Nothing usable.
    let black = png_bytes(&ImageBuffer::from_pixel(W as u32, H as u32, Rgb([0u16; 3])));
    let e = err(decode(
        "black.png",
        &black,
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    ));
    assert!(
        matches!(e, NormalMapError::NoUsablePixel { black, .. } if black == W * H),
        "{e}"
    );

    // A camera for another image.
    let k = Pinhole {
        fx: 500.0,
        fy: 500.0,
        cx: 305.9,
        cy: 255.1,
    };
    let e = err(decode(
        "n.png",
        &good,
        None,
        Convention::Opengl,
        Some(Lens::Pinhole(k)),
        &Limits::default(),
    ));
    assert!(matches!(e, NormalMapError::Camera { .. }), "{e}");
    assert!(e.to_string().contains("principal point") && e.to_string().contains("n.png"));

    // Gray pictures have no normals; garbage is no picture; a missing file.
    let gray = png_bytes(&ImageBuffer::from_pixel(4, 4, Luma([128u8])));
    let e = err(decode(
        "gray.png",
        &gray,
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    ));
    assert!(matches!(e, NormalMapError::Unsupported { .. }), "{e}");
    assert!(e.to_string().contains("RGB"));
    let e = err(decode(
        "junk.png",
        b"not an image",
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    ));
    assert!(matches!(e, NormalMapError::Unsupported { .. }), "{e}");
    let e = err(read(
        Path::new("/nonexistent/n.png"),
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    ));
    assert!(matches!(e, NormalMapError::Unreadable { .. }), "{e}");
    assert!(e.to_string().contains("/nonexistent/n.png"));
}

#[test]
fn maps_and_masks_over_the_pixel_limit_are_refused_as_images_are() {
    let good = png16(&field(), Convention::Opengl);
    let limits = |max: usize| Limits {
        max_pixels_per_image: max as u64,
        ..Limits::default()
    };
    let e = decode(
        "n.png",
        &good,
        None,
        Convention::Opengl,
        None,
        &limits(W * H - 1),
    );
    let e = e.unwrap_err();
    assert!(
        matches!(&e, NormalMapError::TooLarge(i) if i.is_too_large()),
        "{e}"
    );
    let text = e.to_string();
    assert!(
        text.contains("\"n.png\"") && text.contains("24×16"),
        "{text}"
    );
    assert!(text.contains(&format!("limit of {}", W * H - 1)), "{text}");
    // At the limit the map is read; its mask is held to the same limit.
    assert!(
        decode(
            "n.png",
            &good,
            None,
            Convention::Opengl,
            None,
            &limits(W * H)
        )
        .is_ok()
    );
    let big = png_bytes(&ImageBuffer::from_pixel(
        W as u32 + 1,
        H as u32,
        Luma([255u8]),
    ));
    let mask = Some(MaskInput {
        name: "big.png",
        bytes: &big,
    });
    let e = decode(
        "n.png",
        &good,
        mask,
        Convention::Opengl,
        None,
        &limits(W * H),
    );
    let e = e.unwrap_err();
    assert!(matches!(e, NormalMapError::TooLarge(_)), "{e}");
    assert!(e.to_string().contains("\"big.png\""), "{e}");
}

#[test]
fn a_masked_map_keeps_only_the_masks_pixels() {
    let n = field();
    let mask = Array2::from_shape_fn((H, W), |(r, c)| (r + c) % 3 == 0);
    let img = ImageBuffer::from_fn(W as u32, H as u32, |c, r| {
        Luma([u8::from(mask[[r as usize, c as usize]]) * 255])
    });
    let m = png_bytes(&img);
    let given = Some(MaskInput {
        name: "m.png",
        bytes: &m,
    });
    let map = decode(
        "n",
        &png16(&n, Convention::Opengl),
        given,
        Convention::Opengl,
        None,
        &Limits::default(),
    );
    let map = map.unwrap();
    assert_eq!(map.mask, mask);
    assert_eq!(map.mask_name.as_deref(), Some("m.png"));
}
