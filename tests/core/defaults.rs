//! What the default solve promises on any capture: no threshold in absolute intensity
//! units (exposure and light intensity do not change the normals beyond quantisation),
//! and never less accurate than plain least squares on any rendered scene.

use std::path::Path;

use ndarray::{Array2, Array3};
use photostereo::core::intake::{self, Limits};
use photostereo::core::lights;
use photostereo::core::metrics;
use photostereo::core::options::Solver;
use photostereo::core::synth::{self, Capture, Scene};
use photostereo::core::{Options, Reconstruction, RunToEnd, reconstruct};

fn run(dir: &Path, opts: &Options, mask: &Array2<bool>) -> Reconstruction {
    let mut set = intake::load_dir(dir, intake::DirMask::Folder, &Limits::default()).unwrap();
    set.mask = Some(mask.clone());
    reconstruct(&set, opts, &mut RunToEnd).unwrap()
}

/// Mean angle in degrees between two normal maps over `mask`.
fn mean_angle(a: &Array3<f32>, b: &Array3<f32>, mask: &Array2<bool>) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for ((r, c), &m) in mask.indexed_iter() {
        if m {
            let dot: f64 = (0..3).map(|k| (a[[r, c, k]] * b[[r, c, k]]) as f64).sum();
            sum += dot.clamp(-1.0, 1.0).acos().to_degrees();
            n += 1;
        }
    }
    sum / n as f64
}

/// A glossy sphere with attached shadows, exposed at `exposure` times a base exposure
/// whose brightest value is about 1/6 of full scale (so 8 × clips only the highlights).
/// Returns the mask and the true normals.
fn exposed_set(dir: &Path, exposure: f64) -> (Array2<bool>, Array3<f32>) {
    let mut scene = Scene::sphere(96);
    scene.albedo.mapv_inplace(|a| a * 0.12 * exposure);
    let capture = Capture {
        specular: Some(synth::Specular::BlinnPhong {
            strength: 0.06 * exposure,
            shininess: 40.0,
        }),
        seed: 9,
        ..Capture::default()
    };
    synth::write_set(dir, &scene, &synth::light_rings(24, 10.0, 60.0), &capture).unwrap();
    (scene.mask, scene.normals.mapv(|v| v as f32))
}

/// Exposure-free means: what an exposure changes in the normals is no more than what
/// rounding to 16 bits at that exposure changes. That rounding effect is measured, not
/// assumed: the same capture exposed 3 % darker and 3 % brighter has the same signal but
/// re-rolled rounding, so the normals' change between them is the quantisation's own
/// effect at that level. A solver with a real exposure dependence (a threshold in counts)
/// would move far more over the 460-fold range from 0.01 × to 1 × than over a 3 % step.
/// The absolute caps keep a solver that quantisation shakes badly from passing on that
/// alone, and at every exposure the default stays more accurate than least squares.
#[test]
fn exposure_does_not_change_the_default_normals_beyond_quantisation() {
    let tmp = tempfile::tempdir().unwrap();
    let l2 = Options {
        solver: Solver::L2,
        ..Options::default()
    };
    let capture = |name: String, exposure: f64, opts: &Options| {
        let dir = tmp.path().join(name);
        let (mask, truth) = exposed_set(&dir, exposure);
        (run(&dir, opts, &mask), mask, truth)
    };
    let (base, mask, truth) = capture("base".into(), 1.0, &Options::default());
    // (exposure, cap): 0.01 × is about 60 counts of 16 bits at the brightest diffuse
    // value, where least squares itself moves 0.19°.
    for (exposure, cap) in [
        (0.01, 0.6),
        (0.1, 0.06),
        (0.5, 0.02),
        (2.0, 0.02),
        (8.0, 0.04),
    ] {
        let (rec, ..) = capture(format!("x{exposure}"), exposure, &Options::default());
        assert!(rec.report.warnings.is_empty(), "{:?}", rec.report.warnings);
        let shift = mean_angle(&rec.normals, &base.normals, &mask);
        let rounding = [0.97, 1.03]
            .map(|f| {
                let (near, ..) = capture(
                    format!("x{exposure}-{f}"),
                    exposure * f,
                    &Options::default(),
                );
                mean_angle(&rec.normals, &near.normals, &mask)
            })
            .into_iter()
            .fold(0.0, f64::max);
        assert!(
            shift <= 1.25 * rounding + 0.01,
            "exposure {exposure}: {shift:.4}° from the base exposure, but only {rounding:.4}° \
             from a 3 % different exposure (the rounding's own effect)"
        );
        assert!(
            shift < cap,
            "exposure {exposure}: {shift:.4}° from the base exposure (cap {cap}°)"
        );
        let (plain, ..) = capture(format!("l2-{exposure}"), exposure, &l2);
        let (d, p) = (
            mean_angle(&rec.normals, &truth, &mask),
            mean_angle(&plain.normals, &truth, &mask),
        );
        assert!(
            d <= p + 0.05,
            "exposure {exposure}: default {d:.3}° vs l2 {p:.3}°"
        );
    }
}

#[test]
fn light_intensity_scale_does_not_change_the_default_normals() {
    let tmp = tempfile::tempdir().unwrap();
    let (mask, _) = exposed_set(tmp.path(), 1.0);
    let base = run(tmp.path(), &Options::default(), &mask);
    // The same images with every light 7.5 × as strong in the table.
    let table = tmp.path().join(intake::LIGHTS_FILE);
    let lights = lights::parse(&std::fs::read_to_string(&table).unwrap()).unwrap();
    let rows: String = lights
        .iter()
        .map(|l| {
            let [x, y, z] = l.direction;
            format!("{}, {x}, {y}, {z}, 7.5\n", l.name)
        })
        .collect();
    std::fs::write(&table, rows).unwrap();
    let scaled = run(tmp.path(), &Options::default(), &mask);
    let diff = mean_angle(&scaled.normals, &base.normals, &mask);
    // Float rounding only: a few pixels at a threshold's edge may decide differently.
    assert!(diff < 0.01, "{diff}°");
}

#[test]
fn the_default_is_never_less_accurate_than_least_squares_on_a_rendered_scene() {
    let res = Path::new(env!("CARGO_MANIFEST_DIR")).join("res");
    let mut scenes: Vec<_> = std::fs::read_dir(&res)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("truth").is_dir())
        .collect();
    scenes.sort();
    assert!(scenes.len() >= 7, "{scenes:?}");
    let l2 = Options {
        solver: Solver::L2,
        ..Options::default()
    };
    for dir in scenes {
        let truth = synth::read_truth(&dir).unwrap();
        let score = |opts: &Options| {
            metrics::accuracy(&run(&dir, opts, &truth.mask), &truth, &truth.mask).mean_deg
        };
        let (default, plain) = (score(&Options::default()), score(&l2));
        assert!(
            default <= plain + 0.05,
            "{}: default {default:.3}° vs l2 {plain:.3}°",
            dir.display()
        );
    }
}
