//! Accuracy against ground truth: the project's rendered sets in res/ and the seed's real
//! data in ../shared/seed-data.

use crate::seed;

use std::path::{Path, PathBuf};

use ndarray::Array2;
use photostereo::core::intake::{self, Limits};
use photostereo::core::metrics::{self, Accuracy};
use photostereo::core::options::{Integration, Intensities, MaskMode, Solver};
use photostereo::core::synth::{self, Truth};
use photostereo::core::{Options, Reconstruction, RunToEnd, mask, reconstruct};
use seed::seed;

fn res(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("res").join(name)
}

fn run(dir: &Path, opts: &Options, mask: Option<&Array2<bool>>) -> Reconstruction {
    let mut set = intake::load_dir(dir, intake::DirMask::Folder, &Limits::default()).unwrap();
    set.mask = mask.cloned();
    reconstruct(&set, opts, &mut RunToEnd).unwrap()
}

fn check(rec: &Reconstruction, truth: &Truth) -> Accuracy {
    metrics::accuracy(rec, truth, &truth.mask)
}

#[test]
fn shadow_free_16_bit_bump_normals_within_005_degree_and_depth_within_half_pixel() {
    let dir = res("bump");
    let truth = synth::read_truth(&dir).unwrap();
    let rec = run(&dir, &Options::default(), None);
    assert!(rec.mask.iter().all(|m| *m), "the bump fills the frame");
    let acc = check(&rec, &truth);
    assert!(acc.mean_deg < 0.05, "{acc:?}");
    assert!(acc.depth_rms < 0.5, "{acc:?}");
    // The truth albedo is recovered too.
    let worst = rec
        .albedo
        .iter()
        .zip(truth.albedo.iter())
        .map(|(a, t)| (a - t).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-3, "albedo error {worst}");
}

#[test]
fn weighted_solver_is_less_accurate_than_l2_on_noisy_shadow_free_data() {
    let dir = tempfile::tempdir().unwrap();
    let capture = synth::Capture {
        bit_depth: 8,
        noise_sigma: 0.01,
        seed: 5,
        ..Default::default()
    };
    let lights = synth::light_rings(12, 5.0, 25.0);
    synth::write_set(dir.path(), &synth::Scene::bump(96), &lights, &capture).unwrap();
    let truth = synth::read_truth(dir.path()).unwrap();
    let opts = |solver| Options {
        solver,
        ..Options::default()
    };
    let l2 = check(&run(dir.path(), &opts(Solver::L2), None), &truth);
    let weighted = check(&run(dir.path(), &opts(Solver::Weighted), None), &truth);
    assert!(
        weighted.mean_deg > l2.mean_deg,
        "weighted {weighted:?} vs l2 {l2:?}"
    );
}

#[test]
fn mask_aware_poisson_beats_frankot_chellappa_on_a_masked_sphere() {
    let dir = res("sphere");
    let truth = synth::read_truth(&dir).unwrap();
    // The robust solver gets the rim right, so the integrators are what differs.
    let with = |integration| Options {
        integration,
        solver: Solver::Robust,
        ..Options::default()
    };
    let poisson = check(
        &run(&dir, &with(Integration::Poisson), Some(&truth.mask)),
        &truth,
    );
    let fc = check(
        &run(
            &dir,
            &with(Integration::FrankotChellappa),
            Some(&truth.mask),
        ),
        &truth,
    );
    assert!(poisson.mean_deg < 0.5, "{poisson:?}");
    assert!(
        poisson.depth_rms < fc.depth_rms,
        "poisson {poisson:?} vs frankot-chellappa {fc:?}"
    );
}

#[test]
fn seed_sphere_normals_point_outward_and_its_auto_mask_is_one_disc() {
    let rec = run(&seed!("sphere-images"), &Options::default(), None);
    let (labels, sizes) = mask::components(&rec.mask);
    assert_eq!(sizes.len(), 2, "one component, got sizes {sizes:?}");
    assert!(
        mask::fill_holes(&rec.mask) == rec.mask,
        "no holes in the disc"
    );
    // Centre and radius from the mask.
    let (mut sr, mut sc, mut n) = (0.0, 0.0, 0.0);
    for ((r, c), &l) in labels.indexed_iter() {
        if l == 1 {
            sr += r as f64;
            sc += c as f64;
            n += 1.0;
        }
    }
    let (cr, cc, radius) = (sr / n, sc / n, (n / std::f64::consts::PI).sqrt());
    let at = |dr: f64, dc: f64| {
        let (r, c) = (
            (cr + dr * radius * 0.6) as usize,
            (cc + dc * radius * 0.6) as usize,
        );
        [0, 1, 2].map(|k| rec.normals[[r, c, k]])
    };
    let (left, right, top, bottom) = (at(0.0, -1.0), at(0.0, 1.0), at(-1.0, 0.0), at(1.0, 0.0));
    assert!(
        left[0] < -0.3 && right[0] > 0.3,
        "x: left {left:?} right {right:?}"
    );
    assert!(
        top[1] < -0.3 && bottom[1] > 0.3,
        "y (down): top {top:?} bottom {bottom:?}"
    );
    for n in [left, right, top, bottom] {
        assert!(n[2] > 0.3, "faces the camera: {n:?}");
    }
    // Heights: the centre stands above the rim.
    let centre = rec.heights[[cr as usize, cc as usize]];
    let rim = rec.heights[[cr as usize, (cc + radius * 0.9) as usize]];
    assert!(
        centre > rim + 0.2 * radius as f32,
        "centre {centre} rim {rim}"
    );
}

#[test]
fn seed_dog_auto_mask_fills_the_eye_holes() {
    let dir = seed!("dog-images");
    let rec = run(&dir, &Options::default(), None);
    // The plain threshold leaves holes (the eyes); the auto mask has none.
    let set = intake::load_dir(&dir, intake::DirMask::Folder, &Limits::default()).unwrap();
    let raw = reconstruct(
        &set,
        &Options {
            mask: MaskMode::None,
            ..Options::default()
        },
        &mut RunToEnd,
    )
    .unwrap();
    let t = mask::auto_threshold(&raw.albedo);
    let thresholded = raw.albedo.mapv(|a| a > t);
    let holes = |m: &Array2<bool>| {
        mask::fill_holes(m)
            .iter()
            .zip(m.iter())
            .filter(|(f, o)| **f && !**o)
            .count()
    };
    assert!(
        holes(&thresholded) > 10,
        "the dog's thresholded albedo has holes"
    );
    assert_eq!(holes(&rec.mask), 0, "auto mask has its holes filled");
    assert!(rec.report.object_pixels > 10_000 && rec.report.background_pixels > 10_000);
}

#[test]
fn seed_synth_reconstructs_a_bump_with_varying_albedo() {
    let rec = run(&seed!("synth-images"), &Options::default(), None);
    let inside: Vec<f32> = rec.albedo.iter().copied().filter(|a| *a > 0.0).collect();
    let (lo, hi) = inside
        .iter()
        .fold((1f32, 0f32), |(l, h), a| (l.min(*a), h.max(*a)));
    assert!(lo < 0.35 && hi > 0.65, "albedo range {lo}..{hi}");
    let (low, high) = rec.report.surface_range();
    assert!(high - low > 1.0);
}

/// Mean angle between two reconstructions' normals over `region`, degrees.
fn apart_deg(a: &Reconstruction, b: &Reconstruction, region: &Array2<bool>) -> f64 {
    let (mut sum, mut count) = (0.0, 0usize);
    for ((r, c), &m) in region.indexed_iter() {
        if !m {
            continue;
        }
        let dot: f32 = (0..3)
            .map(|k| a.normals[[r, c, k]] * b.normals[[r, c, k]])
            .sum();
        sum += f64::from(dot.clamp(-1.0, 1.0)).acos().to_degrees();
        count += 1;
    }
    sum / count.max(1) as f64
}

/// Lights 30 % apart in brightness, a table that does not say so: `intensities:
/// estimate` finds them from the object (shadows cast, highlights, noise) within 2 % and
/// solves within 0.3° of the solve that knew them; the table it writes back gives that
/// solve again.
#[test]
fn unknown_intensities_of_distant_lights_are_estimated_from_the_object() {
    let dir = tempfile::tempdir().unwrap();
    let count = 16;
    let gray: Vec<[f64; 3]> = synth::light_colours(count, 0.7, 1.3, 11)
        .into_iter()
        .map(|c| [c[0]; 3])
        .collect();
    let capture = synth::Capture {
        bit_depth: 16,
        noise_sigma: 0.002,
        cast_shadows: true,
        specular: Some(synth::Specular::BlinnPhong {
            strength: 0.15,
            shininess: 60.0,
        }),
        light_colours: Some(gray.clone()),
        seed: 3,
        ..Default::default()
    };
    let lights = synth::light_rings(count, 10.0, 60.0);
    synth::write_set(dir.path(), &synth::Scene::shadows(128), &lights, &capture).unwrap();
    let truth = synth::read_truth(dir.path()).unwrap();
    let known = run(dir.path(), &Options::default(), None);

    let mut set =
        intake::load_dir(dir.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    for l in &mut set.lights {
        (l.intensity, l.rgb) = (1.0, None);
    }
    let opts = Options {
        intensities: Intensities::Estimate,
        ..Options::default()
    };
    let out = tempfile::tempdir().unwrap();
    let report = photostereo::core::pipeline::run(
        photostereo::core::bands::InMemory::new(set),
        &opts,
        out.path(),
        &mut RunToEnd,
    )
    .unwrap();
    let estimated = report.estimated_intensities.expect("estimated");
    let mean = gray.iter().map(|g| g[0]).sum::<f64>() / count as f64;
    let worst = (estimated.iter().zip(&gray))
        .map(|(e, g)| (e.intensity / (g[0] / mean) - 1.0).abs())
        .fold(0.0, f64::max);

    // The written table, read back as a job's table, is the estimate's solve.
    std::fs::copy(
        out.path().join("lights.json"),
        dir.path().join("light_directions.json"),
    )
    .unwrap();
    std::fs::remove_file(dir.path().join("light_directions.csv")).unwrap();
    let reread = run(dir.path(), &Options::default(), None);
    let region = &truth.mask & &known.mask;
    let apart = apart_deg(&known, &reread, &region);
    let err = check(&reread, &truth).mean_deg;
    eprintln!(
        "intensities: worst {:.3} % off; normals {apart:.3}° from the known-intensity solve ({err:.3}° from the truth, known {:.3}°)",
        100.0 * worst,
        check(&known, &truth).mean_deg
    );
    assert!(worst <= 0.02, "worst intensity {:.2} % off", 100.0 * worst);
    assert!(apart <= 0.3, "{apart}° from the known-intensity solve");
}

/// A plane shows one normal: it cannot tell the lights' intensities apart, and says so
/// instead of guessing.
#[test]
fn a_plane_refuses_to_estimate_intensities() {
    let dir = tempfile::tempdir().unwrap();
    let plane = synth::Scene::from_fn(
        64,
        64,
        |x, y| Some((0.1 * x + 0.05 * y, 0.1, 0.05)),
        |_, _| 0.8,
    );
    synth::write_set(
        dir.path(),
        &plane,
        &synth::light_rings(8, 10.0, 50.0),
        &synth::Capture {
            noise_sigma: 0.002,
            ..Default::default()
        },
    )
    .unwrap();
    let set = intake::load_dir(dir.path(), intake::DirMask::Folder, &Limits::default()).unwrap();
    let opts = Options {
        intensities: Intensities::Estimate,
        ..Options::default()
    };
    let err = reconstruct(&set, &opts, &mut RunToEnd)
        .unwrap_err()
        .to_string();
    assert!(err.contains("cannot be estimated"), "{err}");
}
