//! Near lights on the renderer's rigs (`synth::ring_relief` and friends): the near-light
//! solve against the truth, and against the best distant table a user could give.

use ndarray::{Array2, Array3, Axis, Zip};
use photostereo::core::bands::InMemory;
use photostereo::core::intake::ImageSet;
use photostereo::core::near::{self, NearSettings};
use photostereo::core::options::{Integration, MaskMode, Options};
use photostereo::core::progress::NEVER;
use photostereo::core::synth::{self, NearRig};
use photostereo::core::{RunToEnd, reconstruct};

/// Angle (degrees) between two normal maps, per pixel.
fn angles(a: &Array3<f32>, b: &Array3<f32>) -> Array2<f64> {
    let mut out = Array2::zeros((a.dim().0, a.dim().1));
    Zip::from(&mut out)
        .and(a.lanes(Axis(2)))
        .and(b.lanes(Axis(2)))
        .for_each(|o, a, b| {
            let la = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            let lb = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
            let d = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / (la * lb);
            *o = f64::from(d.clamp(-1.0, 1.0)).acos().to_degrees();
        });
    out
}

fn mean_where(v: &Array2<f64>, on: &Array2<bool>) -> (f64, usize) {
    let (s, n) = (v.iter().zip(on))
        .filter(|(_, m)| **m)
        .fold((0.0, 0), |(s, n), (v, _)| (s + v, n + 1));
    (s / n.max(1) as f64, n)
}

fn percentile_where(v: &Array2<f64>, on: &Array2<bool>, p: f64) -> f64 {
    let mut x: Vec<f64> = (v.iter().zip(on))
        .filter(|(_, m)| **m)
        .map(|(v, _)| *v)
        .collect();
    if x.is_empty() {
        return 0.0;
    }
    let k = ((x.len() as f64 * p) as usize).min(x.len() - 1);
    *x.select_nth_unstable_by(k, f64::total_cmp).1
}

/// The pixels away from the frame's border (the integrators' boundary rows).
fn interior(rig: &NearRig, border: usize) -> Array2<bool> {
    let (h, w) = rig.mask.dim();
    Array2::from_shape_fn((h, w), |(r, c)| {
        rig.mask[[r, c]] && r >= border && c >= border && r + border < h && c + border < w
    })
}

/// The rig's images as a set under `lights`, with its mask.
fn set_of(rig: &NearRig, lights: Vec<photostereo::core::lights::Light>) -> ImageSet {
    let (h, w) = rig.mask.dim();
    ImageSet {
        width: w,
        height: h,
        bit_depth: 16,
        lights,
        planes: rig.images.clone(),
        colour_moments: None,
        mask: Some(rig.mask.clone()),
        mask_file: None,
        notes: Vec::new(),
    }
}

/// Today's distant solve (the default pipeline) of the rig's images under `lights`.
fn distant_normals(rig: &NearRig, lights: Vec<photostereo::core::lights::Light>) -> Array3<f32> {
    let set = set_of(rig, lights);
    let opts = Options {
        mask: MaskMode::Given,
        ..Options::default()
    };
    reconstruct(&set, &opts, &mut RunToEnd).unwrap().normals
}

/// The near solve of the rig's images under `lights` and `settings`, on its mask.
fn solve_with(
    rig: &NearRig,
    lights: Vec<photostereo::core::lights::Light>,
    settings: &NearSettings,
) -> near::NearSurface {
    let set = set_of(rig, lights);
    near::solve(&mut InMemory::new(set), Some(&rig.mask), settings, NEVER).unwrap()
}

/// The near solve with the rig's own lights, the alternation on a grid of at most
/// `coarse_pixels`.
fn near_solve(rig: &NearRig, integration: Integration, coarse_pixels: usize) -> near::NearSurface {
    let settings = NearSettings {
        integration,
        coarse_pixels,
        ..NearSettings::new(rig.camera, rig.distance)
    };
    solve_with(rig, rig.lights.clone(), &settings)
}

/// Where the best distant table is more than 5° wrong, the near solve is within 0.5°
/// (mean), and its metric depth within 0.5 % of the working distance (mean). The
/// alternation runs on at most `coarse_pixels`.
fn holds_on(rig: NearRig, integration: Integration, coarse_pixels: usize) {
    let inner = interior(&rig, 4);
    let distant = angles(&distant_normals(&rig, rig.distant_table()), &rig.normals);
    let solved = near_solve(&rig, integration, coarse_pixels);
    let err = angles(&solved.normals, &rig.normals);
    let far_off = Array2::from_shape_fn(inner.dim(), |p| inner[p] && distant[p] > 5.0);
    let (distant_mean, _) = mean_where(&distant, &inner);
    let (near_mean, _) = mean_where(&err, &inner);
    let (near_there, n) = mean_where(&err, &far_off);
    let p95 = percentile_where(&err, &far_off, 0.95);
    let depth_err = Array2::from_shape_fn(inner.dim(), |p| {
        f64::from((solved.depth[p] - rig.depth[p]).abs())
    });
    let (depth_mean, _) = mean_where(&depth_err, &inner);
    let depth_p95 = percentile_where(&depth_err, &inner, 0.95);
    println!(
        "{}: distant mean {distant_mean:.2}°, {n} px beyond 5°; near mean {near_mean:.3}°, there \
         {near_there:.3}° (p95 {p95:.3}°); depth mean {depth_mean:.3} mm (p95 {depth_p95:.3}) at \
         {} mm; iterations {:?}",
        rig.name, rig.distance, solved.iterations
    );
    assert!(
        n > inner.iter().filter(|m| **m).count() / 10,
        "{}: few pixels beyond 5°",
        rig.name
    );
    assert!(
        near_there <= 0.5,
        "{}: near {near_there}° (p95 {p95}°)",
        rig.name
    );
    assert!(
        depth_mean <= 0.005 * rig.distance,
        "{}: depth {depth_mean} mm",
        rig.name
    );
}

/// Images this size are solved whole by the alternation.
const WHOLE: usize = 160 * 160;

#[test]
fn a_ring_light_over_a_relief_plate() {
    holds_on(synth::ring_relief(160), Integration::default(), WHOLE);
}

#[test]
fn a_close_ring_with_strong_falloff() {
    holds_on(synth::close_ring(160), Integration::default(), WHOLE);
}

#[test]
fn a_dome_around_a_ball_before_a_plane() {
    holds_on(synth::dome_sphere(160), Integration::Bilateral, WHOLE);
}

/// Larger images: the alternation on the images shrunk (by 6; by 3), then the full
/// resolution fitted on its surface, as the solve does beyond its grid's budget.
#[test]
fn a_ring_light_from_a_shrunk_grid() {
    holds_on(synth::ring_relief(480), Integration::default(), 80 * 80);
}

#[test]
fn a_dome_from_a_shrunk_grid() {
    holds_on(synth::dome_sphere(480), Integration::Bilateral, WHOLE);
}

/// Lights ten thousand times farther than the ring's: the near solve is as accurate as
/// today's distant solve with the rig's distant table, and close to it.
#[test]
fn a_far_rig_gives_the_distant_result() {
    let rig = synth::far_ring(160);
    let inner = interior(&rig, 4);
    let distant = distant_normals(&rig, rig.distant_table());
    let solved = near_solve(&rig, Integration::default(), WHOLE);
    let (d_err, _) = mean_where(&angles(&distant, &rig.normals), &inner);
    let (n_err, _) = mean_where(&angles(&solved.normals, &rig.normals), &inner);
    let (apart, _) = mean_where(&angles(&solved.normals, &distant), &inner);
    println!("far-ring: distant {d_err:.3}°, near {n_err:.3}°, apart {apart:.3}°");
    assert!(d_err < 1.0, "the distant table fits a far rig: {d_err}°");
    assert!(
        apart < 0.02 && (n_err - d_err).abs() < 0.01,
        "near {n_err}° vs distant {d_err}°, {apart}° apart"
    );
}

/// `photostereo reconstruct <set> --out <out>`, its output.
fn reconstruct_cli(set: &std::path::Path, out: &std::path::Path) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_photostereo"))
        .arg("reconstruct")
        .arg(set)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

/// `photostereo reconstruct` on a folder whose table gives positions: the near solve, its
/// metric depth in result.json and depth.exr; a table without the distance is refused
/// naming it.
#[test]
fn the_cli_reconstructs_a_near_light_folder() {
    let rig = synth::ring_relief(96);
    let tmp = tempfile::tempdir().unwrap();
    let (set, out) = (tmp.path().join("ring"), tmp.path().join("out"));
    rig.write(&set).unwrap();
    let run = reconstruct_cli(&set, &out);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(report["lights"], "near");
    assert_eq!(report["unit"], "mm");
    assert_eq!(report["converged"], true, "{report}");
    let mut truth: Vec<f32> = rig.depth.iter().copied().collect();
    let mid = truth.len() / 2;
    let true_median = f64::from(*truth.select_nth_unstable_by(mid, f32::total_cmp).1);
    let median = report["median_depth"].as_f64().unwrap();
    assert!(
        (median - true_median).abs() < 0.005 * rig.distance,
        "median depth {median} mm, truth {true_median} mm"
    );
    for name in [
        "normal.png",
        "albedo.png",
        "depth.exr",
        "depth.png",
        "mesh.glb",
        "points.ply",
    ] {
        assert!(out.join(name).is_file(), "{name} written");
    }
    // The camera may come from the folder's K.txt (3 × 3, as the field ships it) instead
    // of the table: the same depth.
    let table = set.join("light_directions.json");
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&table).unwrap()).unwrap();
    json.as_object_mut().unwrap().remove("camera");
    std::fs::write(&table, serde_json::to_vec(&json).unwrap()).unwrap();
    let k = rig.camera;
    std::fs::write(
        set.join("K.txt"),
        format!("{} 0 {}\n0 {} {}\n0 0 1\n", k.fx, k.cx, k.fy, k.cy),
    )
    .unwrap();
    let from_folder = tmp.path().join("out-k");
    let run = reconstruct_cli(&set, &from_folder);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let again: serde_json::Value =
        serde_json::from_slice(&std::fs::read(from_folder.join("result.json")).unwrap()).unwrap();
    assert_eq!(again["median_depth"], report["median_depth"], "{again}");
    // Without a working distance the table cannot be solved: the error names it.
    json.as_object_mut().unwrap().remove("distance");
    std::fs::write(&table, serde_json::to_vec(&json).unwrap()).unwrap();
    let run = reconstruct_cli(&set, &out);
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && err.contains("distance"), "{err}");
}

/// The ring's LEDs differ by up to ±20 %; told none of it, the solve estimates each
/// within 2 % (relative, mean 1) and its normals stay within 0.3° of the solve that knew.
#[test]
fn unknown_intensities_are_estimated() {
    let rig = synth::ring_relief(160);
    let inner = interior(&rig, 4);
    let known = near_solve(&rig, Integration::default(), WHOLE);
    let mut unknown = rig.lights.clone();
    for l in &mut unknown {
        l.intensity = 1.0;
    }
    let settings = NearSettings {
        estimate_intensities: true,
        ..NearSettings::new(rig.camera, rig.distance)
    };
    let solved = solve_with(&rig, unknown, &settings);
    let estimated = solved.intensities.expect("estimated");
    let mean = rig.lights.iter().map(|l| l.intensity).sum::<f64>() / rig.lights.len() as f64;
    let worst = (rig.lights.iter().zip(&estimated))
        .map(|(l, e)| (e / (l.intensity / mean) - 1.0).abs())
        .fold(0.0, f64::max);
    let (apart, _) = mean_where(&angles(&solved.normals, &known.normals), &inner);
    let (err, _) = mean_where(&angles(&solved.normals, &rig.normals), &inner);
    println!(
        "intensities: worst {:.3} %, normals {apart:.3}° from the known solve ({err:.3}° from the truth), {} iterations",
        100.0 * worst,
        solved.iterations.len()
    );
    assert!(worst <= 0.02, "worst intensity {:.2} % off", 100.0 * worst);
    assert!(apart <= 0.3, "{apart}° from the known-intensity solve");
}

/// The whole path a rig's owner takes: photograph two chrome balls (24 mm, 48 mm apart,
/// at the plate's distance) with the same camera under the same LEDs, calibrate (balls
/// found, pinhole) to the LEDs' positions, write them in mm as a near-light table with the
/// LEDs' datasheet cone and no intensities, and reconstruct the relief plate with it. The
/// LEDs land within 1.5 % of their distance, the normals within 0.6° of the truth where
/// the best distant table is beyond 5° (the calibration's own error adds to the 0.5° of
/// the true positions), and depth within 0.5 % of the working distance.
#[test]
fn lights_placed_by_two_chrome_balls_reconstruct_the_ring() {
    use photostereo::core::calibrate::{self, CircleSource, Settings};
    use photostereo::core::lights;

    let size = 480;
    let rig = synth::ring_relief(size);
    let f = rig.camera.fx;
    let px_per_mm = f / rig.distance; // in the plane of the balls' centres, at the plate
    let c = 0.5 * (size as f64 - 1.0);
    let (ball_mm, apart_mm) = (12.0, 24.0);
    let r = ball_mm * px_per_mm;
    let (first, second) = (
        [c - apart_mm * px_per_mm, c + 3.0],
        [c + apart_mm * px_per_mm, c - 2.0],
    );
    // The LEDs in the chrome renderer's frame: pixels, its z = 0 plane at the plate.
    let positions: Vec<[f64; 3]> = (rig.lights.iter())
        .map(|l| {
            let p = l.emitter.unwrap().position;
            [
                c + p[0] * px_per_mm,
                c + p[1] * px_per_mm,
                f + p[2] * px_per_mm,
            ]
        })
        .collect();
    let count = positions.len();
    let chrome = synth::ChromeSet {
        width: size,
        height: size,
        centre: first,
        radius: r,
        extra_balls: vec![(second, r)],
        lights: (positions.iter())
            .map(|p| {
                let v = [p[0] - first[0], p[1] - first[1], p[2]];
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                v.map(|x| x / n)
            })
            .collect(),
        highlight: (0..count).map(|i| [0.9, 2.5][i % 2]).collect(),
        light_positions: Some(positions),
        light_size: 3.0 * px_per_mm,
        camera_distance: Some(f),
        distractors: false,
        ..synth::ChromeSet::standard(16, 5)
    };
    let dir = tempfile::tempdir().unwrap();
    chrome.write(dir.path(), None).unwrap();
    let folder = calibrate::load_dir(dir.path()).unwrap();
    let settings = Settings {
        circle: CircleSource::Fit,
        camera: calibrate::Camera::Perspective {
            focal_px: f,
            principal: [c, c],
        },
        skip_bad: false,
        budget: Default::default(),
        scratch: None,
    };
    let cal =
        calibrate::calibrate(&folder.images, folder.names.as_deref(), None, &settings).unwrap();
    assert!(!cal.more_circles.is_empty(), "the second ball is found");
    // The table: measured positions (ball radii → mm), the datasheet's cone, no intensity.
    let rows: Vec<serde_json::Value> = (cal.lights.iter().zip(&rig.lights))
        .map(|(m, truth)| {
            let p = m.position.expect("two balls place every light").position;
            let e = truth.emitter.unwrap();
            serde_json::json!({
                "name": truth.name,
                "position": p.map(|v| v * ball_mm),
                "axis": e.axis,
                "anisotropy": e.anisotropy,
            })
        })
        .collect();
    let table = serde_json::json!({
        "lights": rows,
        "camera": rig.camera,
        "distance": rig.distance,
        "unit": "mm",
    });
    let table = lights::parse_table(&table.to_string()).unwrap();
    let worst = (table.lights.iter().zip(&rig.lights))
        .map(|(m, t)| {
            let (a, b) = (m.emitter.unwrap().position, t.emitter.unwrap().position);
            let d = [0, 1, 2].map(|k| a[k] - b[k]);
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        })
        .fold(0.0, f64::max);

    let inner = interior(&rig, 4);
    let distant = angles(&distant_normals(&rig, rig.distant_table()), &rig.normals);
    let settings = NearSettings {
        estimate_intensities: true,
        ..NearSettings::new(rig.camera, rig.distance)
    };
    let solved = solve_with(&rig, table.lights, &settings);
    let err = angles(&solved.normals, &rig.normals);
    let far_off = Array2::from_shape_fn(inner.dim(), |p| inner[p] && distant[p] > 5.0);
    let (near_there, n) = mean_where(&err, &far_off);
    let depth_err = Array2::from_shape_fn(inner.dim(), |p| {
        f64::from((solved.depth[p] - rig.depth[p]).abs())
    });
    let (depth_mean, _) = mean_where(&depth_err, &inner);
    println!(
        "calibrated ring: LEDs placed within {worst:.2} mm; {n} px beyond 5° with the distant \
         table, near {near_there:.3}° there; depth mean {depth_mean:.3} mm at {} mm",
        rig.distance
    );
    assert!(worst <= 0.015 * rig.distance, "an LED {worst} mm off");
    assert!(n > 0 && near_there <= 0.6, "near {near_there}°");
    assert!(depth_mean <= 0.005 * rig.distance, "depth {depth_mean} mm");
}
