//! `photostereo integrate` end to end: normal maps written here (and the real DiLiGenT
//! maps under ../shared/real/normals) through the real binary.

use crate::common;
use crate::seed;

use std::path::Path;
use std::process::{Command, Output};

use common::pinhole_sphere_normal_map;
use image::{ImageBuffer, Luma, Rgb};
use photostereo::core::camera::Pinhole;
use photostereo::core::outputs::{self, png_bytes};

fn integrate(map: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_photostereo"))
        .arg("integrate")
        .arg(map)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

const K: Pinhole = Pinhole {
    fx: 120.0,
    fy: 120.0,
    cx: 48.0,
    cy: 38.0,
};

#[test]
fn a_written_normal_map_integrates_to_its_depth_through_the_binary() {
    let dir = tempfile::tempdir().unwrap();
    let (bytes, truth) = pinhole_sphere_normal_map(&K);
    let map = dir.path().join("sphere.png");
    std::fs::write(&map, bytes).unwrap();
    std::fs::write(dir.path().join("K.txt"), "120 0 48\n0 120 38\n0 0 1\n").unwrap();
    let mut on: Vec<f64> = truth.iter().copied().filter(|t| t.is_finite()).collect();
    let mid = on.len() / 2;
    let median = *on.select_nth_unstable_by(mid, f64::total_cmp).1;
    let out = dir.path().join("out");
    let k = dir.path().join("K.txt");
    let o = integrate(
        &map,
        &out,
        &[
            "--camera",
            k.to_str().unwrap(),
            "--distance",
            &median.to_string(),
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    for name in [
        "depth.exr",
        "depth.png",
        "mask.png",
        "normal.png",
        "mesh.glb",
        "points.ply",
        "result.json",
    ] {
        assert!(out.join(name).is_file(), "{name} missing");
    }
    let depth = outputs::decode_height_exr(&std::fs::read(out.join("depth.exr")).unwrap()).unwrap();
    assert_eq!(depth.dim(), (80, 96));
    let mut worst = 0f64;
    for ((d, t), (r, c)) in depth.iter().zip(&truth).zip(ndarray::indices((80, 96))) {
        assert_eq!(d.is_finite(), t.is_finite(), "mask at ({r}, {c})");
        // Away from the silhouette (within 0.8 of the disc's radius in the image).
        let (u, v) = (c as f64 - K.cx, r as f64 - K.cy);
        if t.is_finite() && u.hypot(v) < 0.8 * 120.0 * 3.0 / 91f64.sqrt() {
            worst = worst.max((f64::from(*d) - t).abs() / t);
        }
    }
    assert!(worst < 5e-3, "largest relative depth error {worst:.5}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(report["camera"]["cx"], 48.0);
    assert_eq!(report["output"], "depth");
    assert!(report["notes"].as_array().unwrap().is_empty());

    // The same map without --camera: orthographic heights, and the unused K.txt noted.
    let out = dir.path().join("ortho");
    let o = integrate(&map, &out, &["--integration", "poisson"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("K.txt was not used"), "{}", stderr(&o));
    assert!(out.join("height.exr").is_file() && !out.join("depth.exr").exists());
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
    assert!(report["camera"].is_null());
    assert_eq!(report["method"], "poisson");
    assert!(report["notes"][0].as_str().unwrap().contains("K.txt"));

    // --outputs: only the artifacts named, and result.json, which lists them.
    let out = dir.path().join("some");
    let o = integrate(
        &map,
        &out,
        &[
            "--camera",
            "120,120,48,38",
            "--outputs",
            "depth.exr,mesh.glb",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let mut written: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    written.sort();
    assert_eq!(written, ["depth.exr", "mesh.glb", "result.json"]);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(
        report["artifacts"],
        serde_json::json!(["depth.exr", "mesh.glb", "result.json"])
    );

    // The four numbers and --focal-length work too.
    let o = integrate(&map, &dir.path().join("b"), &["--camera", "120,120,48,38"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = integrate(
        &map,
        &dir.path().join("c"),
        &["--focal-length", "120", "--normal-convention", "benchmark"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn bad_inputs_exit_non_zero_naming_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let (bytes, _) = pinhole_sphere_normal_map(&K);
    let map = dir.path().join("sphere.png");
    std::fs::write(&map, bytes).unwrap();
    let out = dir.path().join("out");
    let fails = |extra: &[&str], map: &Path, wanted: &[&str]| {
        let o = integrate(map, &out, extra);
        let text = stderr(&o);
        assert!(!o.status.success(), "{extra:?} succeeded");
        for w in wanted {
            assert!(text.contains(w), "{extra:?}: {w:?} not in {text}");
        }
    };
    // A mask of another size.
    let mask = dir.path().join("mask.png");
    std::fs::write(
        &mask,
        png_bytes(&ImageBuffer::from_pixel(50, 40, Luma([255u8]))),
    )
    .unwrap();
    fails(
        &["--mask", mask.to_str().unwrap()],
        &map,
        &["mask.png", "50×40", "96×80"],
    );
    // Not a normal map: a photo-like picture.
    let photo = dir.path().join("photo.png");
    let img = ImageBuffer::from_fn(64, 64, |c, r| {
        let v = ((c * 37 + r * 91) % 200 + 30) as u8;
        Rgb([v, v / 2, 255 - v])
    });
    std::fs::write(&photo, png_bytes(&img)).unwrap();
    fails(&[], &photo, &["photo.png", "not a normal map"]);
    // A principal point outside the image.
    fails(
        &["--camera", "500,500,305.9,255.1"],
        &map,
        &["principal point", "outside"],
    );
    // A distance without a camera; a camera that is neither file nor numbers.
    fails(&["--distance", "3"], &map, &["needs a camera"]);
    fails(
        &["--camera", "nowhere/K.txt"],
        &map,
        &["neither a file nor fx,fy,cx,cy"],
    );
    // Outputs it never writes, or depth without a camera; a map over --max-pixels.
    fails(
        &["--outputs", "mesh.glb,albedo.png"],
        &map,
        &["`outputs`", "\"albedo.png\"", "height.exr, points.ply"],
    );
    fails(
        &["--outputs", "depth.exr"],
        &map,
        &["\"depth.exr\"", "needs a camera"],
    );
    fails(
        &["--max-pixels", "7679"],
        &map,
        &["sphere.png", "96×80", "limit of 7679 pixels"],
    );
    assert!(
        !out.join("result.json").exists(),
        "nothing written on failure"
    );
}

/// The real DiLiGenT maps integrate under their K: a 612 × 512 depth.exr whose finite
/// pixels are the mask's (accuracy is measured elsewhere).
#[test]
fn the_diligent_normal_maps_integrate_under_their_camera() {
    for name in ["cat", "pot2", "harvest"] {
        let Some(set) = seed::real_or_skip(&format!("normals/diligent-{name}")) else {
            return;
        };
        let out = tempfile::tempdir().unwrap();
        let k = set.join("K.txt");
        let mask = set.join("mask.png");
        let o = integrate(
            &set.join("normal_map.png"),
            out.path(),
            &[
                "--camera",
                k.to_str().unwrap(),
                "--mask",
                mask.to_str().unwrap(),
                "--normal-convention",
                "benchmark",
            ],
        );
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let depth =
            outputs::decode_height_exr(&std::fs::read(out.path().join("depth.exr")).unwrap())
                .unwrap();
        assert_eq!(depth.dim(), (512, 612), "{name}");
        let given = image::open(&mask).unwrap().into_luma16();
        let written = image::open(out.path().join("mask.png"))
            .unwrap()
            .into_luma8();
        let (mut in_given, mut differ) = (0usize, 0usize);
        for ((c, r, g), w) in given.enumerate_pixels().zip(written.pixels()) {
            let d = depth[[r as usize, c as usize]];
            assert_eq!(
                d.is_finite(),
                w.0[0] > 0,
                "{name}: depth vs mask.png at ({r}, {c})"
            );
            assert!(
                !d.is_finite() || g.0[0] > 0,
                "{name}: depth outside the given mask"
            );
            in_given += usize::from(g.0[0] > 0);
            differ += usize::from((g.0[0] > 0) != d.is_finite());
        }
        // Only pixels without a usable normal leave the given mask.
        assert!(
            differ * 1000 <= in_given,
            "{name}: {differ} of {in_given} mask pixels lost"
        );
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.path().join("result.json")).unwrap())
                .unwrap();
        assert_eq!(report["width"], 612);
        assert!(report["camera"]["fx"].as_f64().unwrap() > 1000.0, "{name}");
        assert!(report["depth_min"].as_f64().unwrap() > 0.0);
    }
}
