//! The `photostereo` binary end to end: the seed's three sets and res/ through
//! `reconstruct`, and `render` reproducing res/.

use crate::seed;

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common;

use common::{PINHOLE_K, benchmark_folder, mean_normal_error_deg, pinhole_sphere_set};
use photostereo::core::{outputs, synth};
use seed::{SEED_SETS, seed};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_photostereo"))
}

fn res(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("res").join(name)
}

fn reconstruct(dir: &Path, extra: &[&str]) -> (tempfile::TempDir, serde_json::Value) {
    let out = tempfile::tempdir().unwrap();
    let status = bin()
        .arg("reconstruct")
        .arg(dir)
        .arg("--out")
        .arg(out.path())
        .args(extra)
        .status()
        .unwrap();
    assert!(status.success(), "reconstruct {} failed", dir.display());
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("result.json")).unwrap()).unwrap();
    (out, report)
}

#[test]
fn seed_sets_reconstruct_with_every_output_decodable() {
    for name in SEED_SETS {
        let (out, report) = reconstruct(&seed!(name), &["--outputs", outputs::ALL]);
        let artifacts = report["artifacts"].as_array().unwrap();
        for required in [
            "albedo.png",
            "normal.png",
            "normal_x.png",
            "normal_y.png",
            "normal_z.png",
            "height.png",
            "normal.exr",
            "height.exr",
            "needle.png",
            "curl.png",
            "shaded.png",
            "mask.png",
            "result.json",
        ] {
            assert!(
                artifacts.iter().any(|a| a == required),
                "{name}: {required} missing from {artifacts:?}"
            );
        }
        for a in artifacts {
            let a = a.as_str().unwrap();
            let path = out.path().join(a);
            assert!(path.is_file(), "{name}: {a} not written");
            if a == "height.exr" {
                let z = outputs::decode_height_exr(&std::fs::read(&path).unwrap())
                    .unwrap_or_else(|e| panic!("{name}: {a} does not decode: {e}"));
                assert_eq!(
                    z.dim(),
                    (
                        report["height"].as_u64().unwrap() as usize,
                        report["width"].as_u64().unwrap() as usize
                    )
                );
            } else if a.ends_with(".png") || a.ends_with(".exr") {
                image::open(&path).unwrap_or_else(|e| panic!("{name}: {a} does not decode: {e}"));
            }
        }
        let albedo = image::open(out.path().join("albedo.png")).unwrap();
        assert_eq!(albedo.color(), image::ColorType::L16);
        let normal = image::open(out.path().join("normal.png")).unwrap();
        assert_eq!(normal.color(), image::ColorType::Rgb16);
        assert!(report["height_max"].as_f64().unwrap() > report["height_min"].as_f64().unwrap());
        assert_eq!(report["light_count"], 4);
    }
}

#[test]
fn without_a_selection_the_default_set_is_written() {
    let (out, report) = reconstruct(&res("bump"), &[]);
    let mut written: Vec<String> = std::fs::read_dir(out.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    written.sort();
    let mut expected: Vec<String> = (outputs::DEFAULT_OUTPUTS.iter())
        // Gray inputs, and the default solver, which writes no material maps.
        .filter(|n| **n != "albedo_rgb.png" && !outputs::GLOSSY_OUTPUTS.contains(n))
        .map(|n| n.to_string())
        .collect();
    expected.sort();
    assert_eq!(written, expected);
    let listed: Vec<&str> = (report["artifacts"].as_array().unwrap().iter())
        .map(|a| a.as_str().unwrap())
        .collect();
    assert_eq!(listed.len(), expected.len(), "{listed:?}");
}

#[test]
fn normal_png_uses_the_opengl_convention() {
    // A sphere: above the centre the normal tilts up the image, so green > half.
    let (out, _) = reconstruct(&res("sphere"), &["--outputs", "normal.png,mask.png"]);
    let n = image::open(out.path().join("normal.png"))
        .unwrap()
        .to_rgb16();
    let mask = image::open(out.path().join("mask.png")).unwrap().to_luma8();
    let (mut sx, mut sy, mut count) = (0u64, 0u64, 0u64);
    for (x, y, p) in mask.enumerate_pixels() {
        if p.0[0] > 0 {
            sx += x as u64;
            sy += y as u64;
            count += 1;
        }
    }
    let (cx, cy) = ((sx / count) as u32, (sy / count) as u32);
    let r = ((count as f64 / std::f64::consts::PI).sqrt() * 0.5) as u32;
    let top = n.get_pixel(cx, cy - r).0;
    let bottom = n.get_pixel(cx, cy + r).0;
    let right = n.get_pixel(cx + r, cy).0;
    assert!(
        top[1] > 40000 && bottom[1] < 25000,
        "green: top {top:?} bottom {bottom:?}"
    );
    assert!(right[0] > 40000, "red: right {right:?}");
}

#[test]
fn render_reproduces_the_committed_res_sets() {
    let out = tempfile::tempdir().unwrap();
    let status = bin()
        .arg("render")
        .arg(out.path())
        .args(["--only", "bump"])
        .status()
        .unwrap();
    assert!(status.success());
    let committed = Path::new(env!("CARGO_MANIFEST_DIR")).join("res/bump");
    for f in [
        "im1.png",
        "im2.png",
        "im3.png",
        "im4.png",
        "light_directions.csv",
        "truth/normal.exr",
        "truth/depth.exr",
    ] {
        let a = std::fs::read(out.path().join("bump").join(f)).unwrap();
        let b = std::fs::read(committed.join(f)).unwrap();
        assert!(
            a == b,
            "{f} differs from res/bump: rerun `photostereo render res`"
        );
    }
}

/// The bench end to end on tiny sets: every table, a row per size, the HTTP columns, the
/// job in its own process (a child `photostereo reconstruct`, which must succeed), the
/// default job timed against the l2 job, and nothing left in its temporary directory.
#[test]
fn bench_prints_its_tables_and_cleans_up() {
    let tmp = tempfile::tempdir().unwrap();
    let out = bin()
        .args([
            "bench", "--sizes", "32,64", "--lights", "4", "--runs", "1", "--http",
        ])
        .arg("--tmp-dir")
        .arg(tmp.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for needle in [
        "### Time (medians)",
        "### Memory (largest over the runs)",
        "own process: peak RSS MB",
        "### Where the full job's time goes",
        "### Integration alone",
        "### Targets",
        "| 32² × 4 |",
        "| 64² × 4 |",
        "HTTP / core",
        "### The default job against the l2 job",
        "default ≤ 1.25 × l2 at 2048² × 24: not measured",
    ] {
        assert!(stdout.contains(needle), "no {needle:?} in\n{stdout}");
    }
    // Both jobs timed at every size: l2 ms, default ms, their ratio and the median of the
    // rounds' ratios are numbers.
    let versus = stdout
        .split("### The default job against the l2 job")
        .nth(1)
        .unwrap();
    for size in ["32", "64"] {
        let row = versus
            .lines()
            .find(|l| l.starts_with(&format!("| {size}² × 4 |")))
            .unwrap_or_else(|| panic!("no {size}² row in\n{versus}"));
        let cells: Vec<f64> = row
            .split('|')
            .skip(2)
            .filter(|c| !c.trim().is_empty())
            .map(|c| c.trim().parse().unwrap_or(f64::NAN))
            .collect();
        assert!(cells.len() == 4 && cells.iter().all(|v| *v > 0.0), "{row}");
    }
    let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// `--light x,y,z` as the help and docs/usage.md write it: the default light gives the default
/// picture, another light (negative components too) another one, and lights that cannot
/// shade are refused by name.
#[test]
fn light_flag_takes_x_y_z() {
    let bump = Path::new(env!("CARGO_MANIFEST_DIR")).join("res/bump");
    let shaded = |extra: &[&str]| {
        let mut args = vec!["--outputs", "shaded.png"];
        args.extend_from_slice(extra);
        let (out, _) = reconstruct(&bump, &args);
        std::fs::read(out.path().join("shaded.png")).unwrap()
    };
    let default = shaded(&[]);
    assert_eq!(shaded(&["--light", "1,2,3"]), default);
    assert_ne!(shaded(&["--light", "-1,0.5,2"]), default);
    for (light, said) in [
        ("0,0,0", "shading_light"),
        ("1,2", "x,y,z"),
        ("1,2,z", "\"z\""),
    ] {
        let out = bin()
            .arg("reconstruct")
            .arg(&bump)
            .args(["--out", "/tmp/never", "--light", light])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(said),
            "{light}: {err}"
        );
    }
}

#[test]
fn bad_input_fails_with_a_message_naming_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("light_directions.csv"),
        "a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n",
    )
    .unwrap();
    let out = bin()
        .arg("reconstruct")
        .arg(dir.path())
        .args(["--out", "/tmp/never"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("\"a.png\"") && err.contains("not provided"),
        "{err}"
    );
}

/// A reader that stops early (`photostereo openapi | head`) ends the command quietly, as it
/// ends any Unix tool (killed by SIGPIPE), not with a panic on the broken pipe. The
/// document is larger than a pipe's buffer, so the write meets the closed pipe.
#[test]
fn a_closed_pipe_ends_the_output_without_a_panic() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let mut child = bin()
        .arg("openapi")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(
        out.status.signal(),
        Some(libc::SIGPIPE),
        "{:?}: {err}",
        out.status
    );
}

/// `--max-pixels`, as the server's flag: an image over it is refused by name before it is
/// decoded.
#[test]
fn max_pixels_refuses_larger_images() {
    let (w, h) = image::image_dimensions(res("bump").join("im1.png")).unwrap();
    let limit = (w * h - 1).to_string();
    let err = failure(&["--max-pixels", &limit], &res("bump"));
    let size = format!("{w}×{h}");
    assert!(
        err.contains(".png\"") && err.contains(&size) && err.contains(&format!("limit of {limit}")),
        "{err}"
    );
}

/// The stderr of a run that must fail.
fn failure(args: &[&str], dir: &Path) -> String {
    let out = bin()
        .arg("reconstruct")
        .arg(dir)
        .args(["--out", "/tmp/never"])
        .args(args)
        .output()
        .unwrap();
    assert!(!out.status.success(), "{args:?} succeeded");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn a_set_under_a_camera_reconstructs_to_depth_and_evaluates_by_scale() {
    use photostereo::core::metrics::{self, Align};
    let sets = tempfile::tempdir().unwrap();
    let dir = sets.path().join("pinhole-sphere");
    std::fs::create_dir(&dir).unwrap();
    pinhole_sphere_set(&dir);
    let truth = photostereo::core::synth::read_truth(&dir).unwrap();

    // The folder's K.txt is the camera when no flag names one.
    let (out, report) = reconstruct(&dir, &[]);
    let artifacts = report["artifacts"].as_array().unwrap();
    for name in ["depth.exr", "depth.png", "points.ply", "mesh.glb"] {
        assert!(artifacts.iter().any(|a| a == name), "{name}: {artifacts:?}");
        assert!(out.path().join(name).is_file(), "{name}");
    }
    assert!(!out.path().join("height.png").exists());
    assert_eq!(report["options"]["camera"]["fx"], 80.0);
    assert!(report["height_min"].is_null() && report["depth_max"].as_f64().is_some());
    let notes = report["notes"].to_string();
    assert!(
        notes.contains("camera from") && notes.contains("K.txt"),
        "{notes}"
    );
    let depth =
        outputs::decode_height_exr(&std::fs::read(out.path().join("depth.exr")).unwrap()).unwrap();
    let error = metrics::depth_error(&depth, &truth.depth, &truth.mask, Align::Scale);
    // The sphere's depth spans 4 to ~5.6 units: within a thousandth of it.
    assert!(error.mean_abs < 2e-3 && error.rms < 4e-3, "{error:?}");

    // --focal-length and --distance: metric depth, its median the distance.
    let (out, report) = reconstruct(&dir, &["--focal-length", "80", "--distance", "5"]);
    assert_eq!(report["options"]["distance"], 5.0);
    assert!(report["notes"].to_string().contains("not used"), "{report}");
    let depth =
        outputs::decode_height_exr(&std::fs::read(out.path().join("depth.exr")).unwrap()).unwrap();
    let mut on: Vec<f32> = depth.iter().copied().filter(|d| d.is_finite()).collect();
    let k = on.len() / 2;
    let median = *on.select_nth_unstable_by(k, f32::total_cmp).1;
    assert!((median - 5.0).abs() < 1e-4, "median depth {median}");

    // Cameras that cannot have taken the images, and a distance without a camera.
    let err = failure(&["--camera", "80,80,31.5,90"], &dir);
    assert!(
        err.contains("principal point") && err.contains("64 × 64"),
        "{err}"
    );
    let err = failure(&["--camera", "80,80,31.5"], &dir);
    assert!(err.contains("3 numbers"), "{err}");
    let err = failure(&["--focal-length", "0"], &dir);
    assert!(err.contains("fx must be a focal length"), "{err}");
    let err = failure(&["--distance", "2"], &res("bump"));
    assert!(err.contains("distance needs a camera"), "{err}");
    let err = failure(&["--distance", "-1", "--camera", PINHOLE_K], &dir);
    assert!(err.contains("positive"), "{err}");

    // evaluate scores it by scale, in the truth's unit.
    let out = bin().arg("evaluate").arg(sets.path()).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let table = String::from_utf8(out.stdout).unwrap();
    let row = (table.lines())
        .find(|l| l.starts_with("| pinhole-sphere | robust |"))
        .unwrap_or_else(|| panic!("{table}"));
    assert!(row.contains("truth's unit, scaled"), "{row}");
    let made: f64 = row.split('|').nth(5).unwrap().trim().parse().unwrap();
    assert!(made < 2e-3, "{row}");
}

#[test]
fn readme_walkthrough_is_the_script_the_api_tests_run() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let script = std::fs::read_to_string(root.join("tests/walkthrough.sh")).unwrap();
    let body = &script[script.find("BASE=${1:-").expect("script sets BASE")..];
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    assert!(
        readme.contains(body.trim_end()),
        "README's walk-through differs from tests/walkthrough.sh"
    );
}

#[test]
fn a_benchmark_layout_folder_reconstructs_in_the_projects_frame() {
    let dir = tempfile::tempdir().unwrap();
    let scene = benchmark_folder(dir.path());
    let (out, report) = reconstruct(dir.path(), &["--outputs", "normal.exr,albedo_rgb.png"]);
    let err = mean_normal_error_deg(out.path(), &scene);
    assert!(err < 0.5, "mean normal error {err}°");
    assert_eq!(report["light_count"], 12);
    assert_eq!(report["mask_file"], "mask.png");
    assert_eq!(report["options"]["mask"], "given");
    let inside = scene.mask.iter().filter(|m| **m).count();
    assert_eq!(report["object_pixels"].as_u64().unwrap() as usize, inside);
    let notes: Vec<&str> = (report["notes"].as_array().unwrap().iter())
        .map(|n| n.as_str().unwrap())
        .collect();
    assert_eq!(notes.len(), 1, "{notes:?}");
    assert!(notes[0].contains("Normal_gt.png"), "{notes:?}");
    assert_eq!(report["lights"][0]["intensity_rgb"][0], 0.6);
    // The balanced colour: albedo_rgb.png follows the tint, not the lights' colour.
    let albedo = image::open(out.path().join("albedo_rgb.png"))
        .unwrap()
        .to_rgb16();
    let p = albedo.get_pixel(24, 24).0.map(|v| v as f64 / 65535.0);
    let truth = scene.albedo[[24, 24, 0]];
    for (c, tint) in [0.9, 0.75, 0.6].iter().enumerate() {
        assert!(
            (p[c] - truth * tint).abs() < 0.01,
            "channel {c}: {p:?} vs {truth}"
        );
    }
}

#[test]
fn a_folder_mask_png_is_the_mask_unless_a_mode_is_chosen() {
    let dir = tempfile::tempdir().unwrap();
    let bump = Path::new(env!("CARGO_MANIFEST_DIR")).join("res/bump");
    for entry in std::fs::read_dir(&bump).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, dir.path().join(path.file_name().unwrap())).unwrap();
        }
    }
    let first = image::open(dir.path().join("im1.png")).unwrap();
    let (w, h) = (first.width(), first.height());
    // The left half is the object.
    image::GrayImage::from_fn(w, h, |x, _| image::Luma([if x < w / 2 { 255 } else { 0 }]))
        .save(dir.path().join("mask.png"))
        .unwrap();
    let (_, report) = reconstruct(dir.path(), &["--outputs", "mask.png"]);
    assert_eq!(report["mask_file"], "mask.png");
    assert_eq!(report["options"]["mask"], "given");
    assert_eq!(report["object_pixels"], (w / 2 * h) as u64);
    assert_eq!(report["notes"].as_array().unwrap().len(), 0, "{report}");

    let (_, report) = reconstruct(dir.path(), &["--outputs", "mask.png", "--mask", "none"]);
    assert!(report["mask_file"].is_null(), "{report}");
    assert_eq!(report["object_pixels"], (w * h) as u64);
    assert!(
        report["notes"][0].as_str().unwrap().contains("mask.png"),
        "{report}"
    );
}

#[test]
fn a_folder_in_no_layout_is_refused_naming_the_layouts() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("lights.csv"), "a.png, 0, 0, 1\n").unwrap();
    let out = bin()
        .arg("reconstruct")
        .arg(dir.path())
        .args(["--out", "/tmp/never"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    for name in [
        "light_directions.csv",
        "light_directions.txt",
        "filenames.txt",
    ] {
        assert!(err.contains(name), "{err}");
    }
}

#[test]
fn calibrate_measures_the_lights_of_the_committed_chrome_set() {
    let out = tempfile::tempdir().unwrap();
    let (table, overlay, diagram) = (
        out.path().join("lights.csv"),
        out.path().join("overlay.png"),
        out.path().join("lights.png"),
    );
    let run = bin()
        .arg("calibrate")
        .arg(res("chrome"))
        .arg("--out")
        .arg(&table)
        .arg("--overlay")
        .arg(&overlay)
        .arg("--lights-png")
        .arg(&diagram)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(
        stderr.contains("sphere: centre") && stderr.contains("ball12.png"),
        "{stderr}"
    );
    let got = photostereo::core::lights::parse(&std::fs::read_to_string(&table).unwrap()).unwrap();
    let truth = photostereo::core::lights::parse(
        &std::fs::read_to_string(res("chrome").join("truth-lights/light_directions.csv")).unwrap(),
    )
    .unwrap();
    assert_eq!(got.len(), truth.len());
    for (g, t) in got.iter().zip(&truth) {
        assert_eq!(g.name, t.name);
        let cos: f64 = (0..3).map(|k| g.direction[k] * t.direction[k]).sum();
        let err = cos.clamp(-1.0, 1.0).acos().to_degrees();
        assert!(err < 1.0, "{}: {err}°", g.name);
    }
    let (w, h) = image::image_dimensions(&overlay).unwrap();
    assert_eq!((w, h), (320, 240));
    assert!(image::open(&diagram).is_ok());

    let bad = bin()
        .arg("calibrate")
        .arg(res("chrome"))
        .arg("--out")
        .arg(&table)
        .args(["--circle", "400,100,50"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && stderr.contains("outside the 320×240 image"),
        "{stderr}"
    );
}

#[test]
fn calibrate_finds_two_balls_by_itself_and_writes_the_lights_positions() {
    let set = photostereo::core::synth::ChromeSet::near_dome(16, 77, 3.0);
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), None).unwrap();
    let out = tempfile::tempdir().unwrap();
    let (table, positions) = (out.path().join("lights.csv"), out.path().join("p.csv"));
    let run = bin()
        .arg("calibrate")
        .arg(dir.path())
        .arg("--out")
        .arg(&table)
        .arg("--positions")
        .arg(&positions)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(
        stderr.contains("sphere 1: centre (120.") && stderr.contains("sphere 2: centre (359."),
        "{stderr}"
    );
    // Each light where it is, within 2 % of its distance from between the balls: in ball
    // radii from the first (left) ball's centre.
    let csv = std::fs::read_to_string(&positions).unwrap();
    assert!(csv.starts_with("# light positions in ball radii"), "{csv}");
    let balls = set.balls();
    let radius = (balls[0].1 + balls[1].1) / 2.0;
    let mid = [
        (balls[0].0[0] + balls[1].0[0]) / 2.0,
        (balls[0].0[1] + balls[1].0[1]) / 2.0,
        0.0,
    ];
    let dist = |a: [f64; 3], b: [f64; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt();
    let rows: Vec<&str> = csv.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(rows.len(), set.lights.len(), "{csv}");
    for (row, truth) in rows.iter().zip(set.light_positions.as_ref().unwrap()) {
        let v: Vec<f64> = row
            .split(',')
            .skip(1)
            .map(|f| f.trim().parse().unwrap())
            .collect();
        let got = [
            v[0] * radius + balls[0].0[0],
            v[1] * radius + balls[0].0[1],
            v[2] * radius,
        ];
        assert!(
            dist(got, *truth) < 0.02 * dist(*truth, mid),
            "{row} vs {truth:?}"
        );
    }

    // One ball found: --positions is refused, saying so, and nothing is written.
    let one = out.path().join("one.csv");
    let run = bin()
        .arg("calibrate")
        .arg(res("chrome"))
        .arg("--out")
        .arg(&one)
        .arg("--positions")
        .arg(out.path().join("one-positions.csv"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        !run.status.success() && stderr.contains("one ball was found"),
        "{stderr}"
    );
    assert!(!one.exists());
    // One ball given: refused before anything is read.
    let run = bin()
        .arg("calibrate")
        .arg(res("chrome"))
        .arg("--out")
        .arg(&one)
        .args(["--circle", "187.3,109.6,93.4", "--positions", "p.csv"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        !run.status.success() && stderr.contains("two balls or more"),
        "{stderr}"
    );
}

/// `--intensities estimate` writes the estimated table as lights.json and lists the
/// estimates in result.json; `--intensities` takes only its two values.
#[test]
fn intensities_estimate_writes_the_table_it_estimated() {
    let (out, report) = reconstruct(&res("sphere"), &["--intensities", "estimate"]);
    let estimated = report["estimated_intensities"]
        .as_array()
        .expect("estimates");
    assert_eq!(
        estimated.len() as u64,
        report["light_count"].as_u64().unwrap()
    );
    let table: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("lights.json")).unwrap()).unwrap();
    assert_eq!(table.as_array().unwrap().len(), estimated.len());
    assert!(
        report["artifacts"]
            .as_array()
            .unwrap()
            .iter()
            .any(|a| a == "lights.json")
    );
    let e = failure(&["--intensities", "guess"], &res("sphere"));
    assert!(e.contains("--intensities") && e.contains("estimate"), "{e}");
}

/// `--solver glossy` writes the material maps by default, result.json says where the
/// lobe was kept and how much of the residual it explains, and the roughness it fits on
/// the rendered glossy sphere is the renderer's (the median over the pixels where the
/// lobe was kept, within 15 %).
#[test]
fn the_glossy_solver_writes_its_material_maps() {
    let (out, report) = reconstruct(&res("glossy"), &["--solver", "glossy"]);
    let listed: Vec<&str> = (report["artifacts"].as_array().unwrap().iter())
        .map(|a| a.as_str().unwrap())
        .collect();
    for name in outputs::GLOSSY_OUTPUTS {
        assert!(listed.contains(&name), "{name} not in {listed:?}");
    }
    let truth = synth::catalogue()
        .into_iter()
        .find(|(name, ..)| *name == "glossy")
        .and_then(|(.., capture)| match capture.specular {
            Some(synth::Specular::CookTorrance { alpha, .. }) => Some(alpha.sqrt()),
            _ => None,
        })
        .expect("the glossy set's GGX lobe");
    let roughness = image::open(out.path().join("roughness.png"))
        .unwrap()
        .into_luma16();
    let mut kept: Vec<f64> = (roughness.pixels())
        .map(|p| p.0[0] as f64 / 65535.0)
        .filter(|&r| r > 0.0)
        .collect();
    assert!(kept.len() > 1000, "the lobe kept at {} pixels", kept.len());
    assert_eq!(
        report["glossy_pixels"],
        kept.len(),
        "result.json counts them"
    );
    // The fit's residual there: the lobe explains the highlights the Lambertian fit left.
    let rms = |key: &str| report[key].as_f64().unwrap_or_else(|| panic!("no {key}"));
    let (lobe, lambert) = (rms("glossy_residual_rms"), rms("glossy_lambertian_rms"));
    assert!(
        lobe < 0.25 * lambert,
        "residual {lobe} vs Lambertian {lambert}"
    );
    let mid = kept.len() / 2;
    let median = *kept.select_nth_unstable_by(mid, f64::total_cmp).1;
    assert!(
        (median - truth).abs() <= 0.15 * truth,
        "roughness {median:.3}, truth {truth}"
    );
    // One material for the whole coat: GGX, at the coat's roughness.
    let material = &report["glossy_material"];
    assert_eq!(material["facets"], "ggx", "{material}");
    let shared = material["roughness"]
        .as_f64()
        .expect("the shared roughness");
    assert!(
        (shared - truth).abs() <= 0.05 * truth,
        "shared roughness {shared:.3}, truth {truth}"
    );
}

/// `evaluate --holdout-lights` scores each solver on a capture by the images it was not
/// given: on the rendered glossy sphere the glossy solver predicts them best.
#[test]
fn holdout_lights_rank_the_glossy_solver_first_on_a_glossy_set() {
    let output = bin()
        .args(["evaluate", "--holdout-lights"])
        .arg(res("glossy"))
        .output()
        .unwrap();
    assert!(output.status.success(), "{output:?}");
    let table = String::from_utf8(output.stdout).unwrap();
    let median = |solver: &str| -> f64 {
        let row = (table.lines())
            .find(|l| l.starts_with(&format!("| {solver} |")))
            .unwrap_or_else(|| panic!("no {solver} row in\n{table}"));
        row.split('|').nth(2).unwrap().trim().parse().unwrap()
    };
    let (robust, glossy) = (median("robust"), median("glossy"));
    assert!(
        glossy < 0.5 * robust,
        "glossy {glossy}, robust {robust}\n{table}"
    );
}

/// `reconstruct --holdout-lights` puts the same score in result.json (the glossy row of
/// `evaluate --holdout-lights`), timed; a set too small to split is refused by name.
#[test]
fn holdout_lights_on_request_go_into_result_json() {
    let (_out, report) = reconstruct(&res("glossy"), &["--solver", "glossy", "--holdout-lights"]);
    let holdout = &report["holdout"];
    let median = holdout["median_relative"].as_f64().unwrap();
    let output = bin()
        .args(["evaluate", "--holdout-lights"])
        .arg(res("glossy"))
        .output()
        .unwrap();
    let table = String::from_utf8(output.stdout).unwrap();
    let row = (table.lines().find(|l| l.starts_with("| glossy |"))).unwrap();
    let evaluated: f64 = row.split('|').nth(2).unwrap().trim().parse().unwrap();
    assert!(
        (median - evaluated).abs() < 1e-4,
        "{median} vs {evaluated}\n{table}"
    );
    assert_eq!(
        holdout["observations"].as_u64(),
        row.split('|').nth(5).unwrap().trim().parse().ok()
    );
    assert!(
        (report["timings_ms"].as_array().unwrap().iter()).any(|t| t["stage"] == "holdout"),
        "{report}"
    );
    let e = failure(&["--holdout-lights"], &res("bump"));
    assert!(e.contains("holdout_lights needs at least 8 images"), "{e}");
}

/// `evaluate --holdout-lights` needs enough images to leave some out.
#[test]
fn holdout_lights_refuse_a_set_too_small_to_split() {
    let output = bin()
        .args(["evaluate", "--holdout-lights"])
        .arg(res("bump"))
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--holdout-lights needs at least 8 images"),
        "{stderr}"
    );
}
