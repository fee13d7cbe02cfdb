use image::{ImageBuffer, Rgb};
use ndarray::Array2;

use super::*;
use crate::core::intake::Limits;
use crate::core::normalmap::{self, Lens};
use crate::core::outputs::png_bytes;
use crate::core::progress::{NEVER, RunToEnd};

/// A 16-bit OpenGL normal map of `normals` (project frame), black where `None`.
fn png16(size: (usize, usize), n: impl Fn(usize, usize) -> Option<[f64; 3]>) -> Vec<u8> {
    let (h, w) = size;
    let img = ImageBuffer::from_fn(w as u32, h as u32, |c, r| match n(r as usize, c as usize) {
        Some([x, y, z]) => Rgb([x, -y, z].map(|v| ((v + 1.0) / 2.0 * 65535.0).round() as u16)),
        None => Rgb([0; 3]),
    });
    png_bytes(&img)
}

/// A sphere of radius `radius` px seen orthographically, centred in an `n × n` frame:
/// its normal map and its true heights (NaN off the disc).
fn ortho_sphere(n: usize, radius: f64) -> (Vec<u8>, Array2<f64>) {
    let c = (n as f64 - 1.0) / 2.0;
    let at = |r: usize, col: usize| {
        let (x, y) = (col as f64 - c, r as f64 - c);
        let z2 = radius * radius - x * x - y * y;
        (z2 > 0.0).then(|| (x, y, z2.sqrt()))
    };
    let map = png16((n, n), |r, col| {
        at(r, col).map(|(x, y, z)| [x / radius, y / radius, z / radius])
    });
    let truth = Array2::from_shape_fn((n, n), |(r, col)| at(r, col).map_or(f64::NAN, |p| p.2));
    (map, truth)
}

/// A sphere of radius `rho` centred at (0, 0, −`dist`) in the camera frame, seen through
/// `k` in a `w × h` frame: its normal map and its true depth along the optical axis.
fn pinhole_sphere(
    k: &Pinhole,
    (h, w): (usize, usize),
    rho: f64,
    dist: f64,
) -> (Vec<u8>, Array2<f64>) {
    let centre = [0.0, 0.0, -dist];
    let hit = |r: usize, c: usize| {
        let d = k.ray(c as f64, r as f64);
        let dd: f64 = d.iter().map(|v| v * v).sum();
        let dc: f64 = d.iter().zip(centre).map(|(a, b)| a * b).sum();
        let disc = dc * dc - dd * (dist * dist - rho * rho);
        (disc > 0.0).then(|| {
            let t = (dc - disc.sqrt()) / dd; // the near intersection; depth = t
            let x = d.map(|v| v * t);
            let n = [0, 1, 2].map(|i| (x[i] - centre[i]) / rho);
            (t, n)
        })
    };
    let map = png16((h, w), |r, c| hit(r, c).map(|(_, n)| n));
    let truth = Array2::from_shape_fn((h, w), |(r, c)| hit(r, c).map_or(f64::NAN, |(t, _)| t));
    (map, truth)
}

/// RMS and largest difference between `z` and `truth` over `region`, after removing the
/// mean offset there.
fn offset_errors(z: &Array2<f32>, truth: &Array2<f64>, region: &Array2<bool>) -> (f64, f64) {
    let pairs: Vec<(f64, f64)> = (z.iter().zip(truth).zip(region))
        .filter(|(_, m)| **m)
        .map(|((z, t), _)| (f64::from(*z), *t))
        .collect();
    let offset = pairs.iter().map(|(z, t)| t - z).sum::<f64>() / pairs.len() as f64;
    let errors: Vec<f64> = pairs.iter().map(|(z, t)| (z + offset - t).abs()).collect();
    let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    (rms, errors.iter().copied().fold(0.0, f64::max))
}

#[test]
fn an_orthographic_spheres_normal_map_integrates_to_the_sphere() {
    let (n, radius) = (96, 40.0);
    let (bytes, truth) = ortho_sphere(n, radius);
    let map = normalmap::decode(
        "sphere.png",
        &bytes,
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    )
    .unwrap();
    assert_eq!(
        map.counts.used,
        truth.iter().filter(|t| t.is_finite()).count()
    );
    let z = surface(&map, &Settings::default(), NEVER);
    // Away from the silhouette (within 0.9 of the radius), where slopes stay below ~2.
    let c = (n as f64 - 1.0) / 2.0;
    let inner = Array2::from_shape_fn((n, n), |(r, col)| {
        (r as f64 - c).hypot(col as f64 - c) < 0.9 * radius
    });
    let (rms, worst) = offset_errors(&z, &truth, &inner);
    // Heights span 40 px: within 1 % RMS, 2 % at worst.
    assert!(
        rms < 0.4 && worst < 0.8,
        "height error RMS {rms:.3} px, worst {worst:.3} px"
    );
}

#[test]
fn a_spheres_normal_map_under_a_pinhole_integrates_to_its_depth() {
    let k = Pinhole {
        fx: 120.0,
        fy: 110.0,
        cx: 45.0,
        cy: 50.0,
    };
    let (size, rho, dist) = ((96, 96), 3.0, 10.0);
    let (bytes, truth) = pinhole_sphere(&k, size, rho, dist);
    let lens = Some(Lens::Pinhole(k));
    let map = normalmap::decode(
        "sphere.png",
        &bytes,
        None,
        Convention::Opengl,
        lens,
        &Limits::default(),
    )
    .unwrap();
    assert_eq!(map.counts.back_facing, 0);
    // Metric: the median true depth over the mask as the working distance.
    let mut on: Vec<f64> = truth.iter().copied().filter(|t| t.is_finite()).collect();
    let mid = on.len() / 2;
    let median = *on.select_nth_unstable_by(mid, f64::total_cmp).1;
    let settings = Settings {
        distance: Some(median),
        ..Settings::default()
    };
    let depth = surface(&map, &settings, NEVER);
    assert!(
        (depth.iter().zip(&map.mask)).all(|(d, m)| d.is_finite() == *m),
        "NaN exactly off the mask"
    );
    // Where the surface faces the camera within ~70° (cos > 0.35 along the ray).
    let inner = Array2::from_shape_fn(size, |(r, c)| {
        let d = k.ray(c as f64, r as f64);
        let len = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let n = [0, 1, 2].map(|i| f64::from(map.normals[[r, c, i]]));
        map.mask[[r, c]] && -(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / len > 0.35
    });
    // Compare without the offset-free median scale: relative error, no re-fit.
    let worst = (depth.iter().zip(&truth).zip(&inner))
        .filter(|(_, m)| **m)
        .map(|((d, t), _)| (f64::from(*d) - t).abs() / t)
        .fold(0.0, f64::max);
    // The sphere's depth varies by 25 % over its face (7.5 to ~9.5): within 0.5 %.
    assert!(worst < 5e-3, "largest relative depth error {worst:.5}");
    let (rms, _) = offset_errors(&depth, &truth, &inner);
    assert!(
        rms < 0.01,
        "depth RMS {rms:.4} (units of the 3-unit radius)"
    );
}

#[test]
fn run_writes_every_artifact_and_a_report_that_lists_them() {
    let k = Pinhole::centred(150.0, 64, 48);
    let (bytes, truth) = pinhole_sphere(&k, (48, 64), 2.0, 9.0);
    let map = normalmap::decode(
        "sphere.png",
        &bytes,
        None,
        Convention::Opengl,
        Some(Lens::Centred { focal_px: 150.0 }),
        &Limits::default(),
    )
    .unwrap();
    let used = map.counts.used;
    let dir = tempfile::tempdir().unwrap();
    let settings = Settings {
        distance: Some(8.0),
        ..Settings::default()
    };
    let report = run(map, &settings, dir.path(), &mut RunToEnd).unwrap();
    let expected = [
        "mask.png",
        "normal.png",
        "depth.exr",
        "depth.png",
        "points.ply",
        "mesh.glb",
        "result.json",
    ];
    assert_eq!(report.artifacts, expected);
    for name in expected {
        assert!(dir.path().join(name).is_file(), "{name}");
    }
    let depth = outputs::decode_height_exr(&std::fs::read(dir.path().join("depth.exr")).unwrap());
    let depth = depth.unwrap();
    assert_eq!(depth.dim(), (48, 64));
    assert_eq!(
        depth.iter().filter(|d| d.is_finite()).count(),
        truth.iter().filter(|t| t.is_finite()).count()
    );
    let (lo, hi) = (report.depth_min.unwrap(), report.depth_max.unwrap());
    assert!(
        lo < 8.0 && 8.0 < hi && report.height_min.is_none(),
        "{lo}..{hi}"
    );
    // depth.png: near is bright.
    let png = image::open(dir.path().join("depth.png"))
        .unwrap()
        .into_luma16();
    let (r, c) = (24, 32); // near the sphere's nearest point
    let nearest = png.get_pixel(c, r).0[0];
    assert!(nearest > 60_000, "{nearest}");
    // points.ply: a header and one 24-byte vertex per used pixel, unprojected.
    let ply = std::fs::read(dir.path().join("points.ply")).unwrap();
    let end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = std::str::from_utf8(&ply[..end]).unwrap();
    assert!(
        header.contains(&format!("element vertex {used}\n")),
        "{header}"
    );
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
    assert_eq!(ply.len() - end, used * 24);
    let first: Vec<f32> = (ply[end..end + 24].chunks(4))
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert!(
        first[2] < -6.0 && first[5] > 0.0,
        "z = −depth, normal towards the camera: {first:?}"
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("result.json")).unwrap()).unwrap();
    assert_eq!(json["camera"]["fx"], 150.0);
    assert_eq!(json["distance"], 8.0);
    assert_eq!(json["method"], "robust-poisson");
    assert_eq!(json["convention"], "opengl");
    assert_eq!(json["output"], "depth");
    assert_eq!(json["counts"]["used"], used);

    // Orthographic: heights instead of depth.
    let (bytes, _) = ortho_sphere(40, 15.0);
    let map = normalmap::decode(
        "s.png",
        &bytes,
        None,
        Convention::Opengl,
        None,
        &Limits::default(),
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let report = run(map, &Settings::default(), dir.path(), &mut RunToEnd).unwrap();
    assert_eq!(
        report.artifacts,
        [
            "mask.png",
            "normal.png",
            "height.png",
            "height.exr",
            "points.ply",
            "mesh.glb",
            "result.json"
        ]
    );
    assert!(report.camera.is_none() && report.depth_min.is_none());
    let (lo, hi) = (report.height_min.unwrap(), report.height_max.unwrap());
    assert!(hi - lo > 10.0, "{lo}..{hi}");
}

#[test]
fn a_distance_needs_a_camera_and_must_be_positive() {
    let with = |d| Settings {
        distance: Some(d),
        ..Settings::default()
    };
    let k = Pinhole::centred(100.0, 10, 10);
    assert!(with(2.0).check(Some(&k)).is_ok());
    assert!(
        with(2.0)
            .check(None)
            .unwrap_err()
            .to_string()
            .contains("needs a camera")
    );
    assert!(with(-1.0).check(Some(&k)).is_err());
    assert!(with(f64::NAN).check(Some(&k)).is_err());
    assert!(Settings::default().check(None).is_ok());
}

#[test]
fn a_camera_file_beside_the_map_is_noted_not_used() {
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("n.png");
    assert_eq!(unused_camera_note(&map), None);
    std::fs::write(dir.path().join("K.txt"), "100 0 5 0 100 5 0 0 1").unwrap();
    let note = unused_camera_note(&map).unwrap();
    assert!(
        note.contains("K.txt") && note.contains("--camera"),
        "{note}"
    );
}

#[test]
fn an_outputs_selection_writes_only_what_it_names_and_the_report() {
    let (bytes, _) = ortho_sphere(40, 15.0);
    let limits = Limits::default();
    let map = normalmap::decode("s.png", &bytes, None, Convention::Opengl, None, &limits);
    let dir = tempfile::tempdir().unwrap();
    let settings = Settings {
        outputs: Some(vec!["height.exr".into(), "mesh.glb".into()]),
        ..Settings::default()
    };
    let report = run(map.unwrap(), &settings, dir.path(), &mut RunToEnd).unwrap();
    assert_eq!(report.artifacts, ["height.exr", "mesh.glb", "result.json"]);
    let mut written: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    written.sort();
    assert_eq!(written, ["height.exr", "mesh.glb", "result.json"]);
    // `all` is every artifact of the projection.
    let all = Settings {
        outputs: Some(vec!["all".into()]),
        ..Settings::default()
    };
    assert!(
        ["height.png", "points.ply", "mask.png"]
            .iter()
            .all(|n| all.wants(n))
    );
}

#[test]
fn outputs_a_normals_job_cannot_write_are_refused_naming_why() {
    let names = |n: &[&str]| n.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let refused = |n: &[&str], camera: bool| check_outputs(&names(n), camera).unwrap_err();
    assert!(check_outputs(&names(&["all", "height.png", "mesh.glb"]), false).is_ok());
    assert!(check_outputs(&names(&["depth.exr", "points.ply"]), true).is_ok());
    let e = refused(&["mesh.glb", "albedo.png"], false).to_string();
    assert!(
        e.contains("`outputs`") && e.contains("\"albedo.png\""),
        "{e}"
    );
    assert!(
        e.contains("mask.png, normal.png, height.png, height.exr, points.ply"),
        "{e}"
    );
    let e = refused(&["depth.exr"], false).to_string();
    assert!(
        e.contains("\"depth.exr\"") && e.contains("needs a camera"),
        "{e}"
    );
    let e = refused(&["height.png"], true).to_string();
    assert!(
        e.contains("\"height.png\"") && e.contains("under a camera"),
        "{e}"
    );
    // Unknown names get the general refusal; Settings::check applies the selection.
    assert!(
        refused(&["selfie.jpg"], false)
            .to_string()
            .contains("unknown output")
    );
    let depth = Settings {
        outputs: Some(names(&["depth.png"])),
        ..Settings::default()
    };
    let k = Pinhole::centred(100.0, 10, 10);
    assert!(depth.check(Some(&k)).is_ok() && depth.check(None).is_err());
}
