//! Light calibration from a chrome sphere, against the true lights of rendered captures:
//! direction accuracy with the outline found automatically, the errors, `skip_bad`, the
//! matte sphere's intensities, and a calibrate → reconstruct round trip.

use std::path::Path;

use photostereo::core::calibrate::{
    self, Calibration, CalibrationError, CircleSource, Settings, SphereImage,
};
use photostereo::core::intake::{self, DirMask, Limits};
use photostereo::core::synth::{self, ChromeSet};
use photostereo::core::{Options, RunToEnd, lights, reconstruct};

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d: f64 = (0..3).map(|k| a[k] * b[k]).sum();
    d.clamp(-1.0, 1.0).acos().to_degrees()
}

fn auto() -> Settings {
    Settings {
        circle: CircleSource::Fit,
        camera: calibrate::Camera::Orthographic,
        skip_bad: false,
        budget: Default::default(),
        scratch: None,
    }
}

/// Render `set` into a temporary folder, read it back and calibrate it.
fn run(
    set: &ChromeSet,
    settings: &Settings,
) -> (tempfile::TempDir, Result<Calibration, CalibrationError>) {
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), None).unwrap();
    let f = calibrate::load_dir(dir.path()).unwrap();
    let result = calibrate::calibrate(&f.images, f.names.as_deref(), f.ambient_source(), settings);
    (dir, result)
}

/// Mean and max direction error (degrees) against the set's true lights, and the circle's
/// centre and radius errors (pixels). The set has one ball: exactly one is found.
fn errors(set: &ChromeSet, cal: &Calibration) -> (f64, f64, f64, f64) {
    assert_eq!(cal.lights.len(), set.lights.len());
    assert!(
        cal.more_circles.is_empty(),
        "a second ball: {:?}",
        cal.more_circles
    );
    let e: Vec<f64> = cal
        .lights
        .iter()
        .map(|l| angle_deg(l.highlight.direction, set.lights[l.index]))
        .collect();
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    let max = e.iter().cloned().fold(0.0, f64::max);
    let c = cal.circle;
    let centre = (c.cx - set.centre[0]).hypot(c.cy - set.centre[1]);
    (mean, max, centre, (c.r - set.radius).abs())
}

fn check_accuracy(name: &str, set: &ChromeSet) {
    let (_dir, cal) = run(set, &auto());
    let cal = cal.unwrap();
    let (mean, max, centre, radius) = errors(set, &cal);
    let clipped = cal.lights.iter().filter(|l| l.highlight.clipped).count();
    eprintln!(
        "{name}: direction error mean {mean:.3}° max {max:.3}°; circle centre off by {centre:.3} px, radius by {radius:.3} px; {clipped} of {} highlights clipped",
        cal.lights.len()
    );
    assert!(
        clipped >= 4 && clipped < cal.lights.len(),
        "{clipped} clipped"
    );
    assert!(mean < 0.3 && max < 1.0, "{name}: mean {mean}°, max {max}°");
}

#[test]
fn chrome_8_bit_off_centre_with_distractors_within_03_degree_mean_1_max() {
    check_accuracy("8-bit", &ChromeSet::standard(8, 41));
}

#[test]
fn chrome_16_bit_within_03_degree_mean_1_max() {
    check_accuracy("16-bit", &ChromeSet::standard(16, 43));
}

/// The usual capture rendered four times larger (1280 × 960, a ball 374 px across its
/// radius): at that size the backdrop's texture bends the outline's gradients enough to
/// scatter its centre votes, and only the votes counted per octave of distance find it.
#[test]
fn a_large_ball_on_a_textured_backdrop_within_03_degree_mean_1_max() {
    let mut set = ChromeSet::standard(8, 67);
    let k = 4.0;
    set.width *= 4;
    set.height *= 4;
    // Pixel centres at integers: a pixel's centre x maps to k (x + ½) − ½.
    set.centre = set.centre.map(|v| k * (v + 0.5) - 0.5);
    set.radius *= k;
    check_accuracy("4× larger, 8-bit", &set);
}

#[test]
fn chrome_ball_filling_a_dark_frame_within_03_degree_mean_1_max() {
    for bits in [8, 16] {
        check_accuracy(
            &format!("filling, {bits}-bit"),
            &ChromeSet::filling(bits, 47),
        );
    }
}

#[test]
fn a_given_circle_or_mask_overrides_the_fit() {
    let set = ChromeSet::standard(16, 53);
    let circle = calibrate::Circle {
        cx: set.centre[0],
        cy: set.centre[1],
        r: set.radius,
    };
    let given = Settings {
        circle: CircleSource::Given(circle),
        ..auto()
    };
    let (_dir, cal) = run(&set, &given);
    let cal = cal.unwrap();
    assert_eq!(cal.circle, circle);
    assert!(cal.outline.is_none());
    let (mean, max, _, _) = errors(&set, &cal);
    eprintln!("given circle: mean {mean:.3}° max {max:.3}°");
    assert!(mean < 0.3 && max < 1.0);
    let mask = ndarray::Array2::from_shape_fn((set.height, set.width), |(r, c)| {
        (c as f64 - set.centre[0]).hypot(r as f64 - set.centre[1]) <= set.radius
    });
    let masked = Settings {
        circle: CircleSource::Mask {
            name: "mask.png".into(),
            mask,
        },
        ..auto()
    };
    let (_dir, cal) = run(&set, &masked);
    let (mean, max, centre, radius) = errors(&set, &cal.unwrap());
    eprintln!("mask: mean {mean:.3}° max {max:.3}°, circle {centre:.3} / {radius:.3} px");
    assert!(mean < 0.3 && max < 1.0 && centre < 0.2 && radius < 0.2);
}

/// The set's images, decoded, with image `i` replaced by `f(images)`.
fn images_of(set: &ChromeSet) -> (tempfile::TempDir, Vec<SphereImage>) {
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), None).unwrap();
    let images = calibrate::load_dir(dir.path())
        .unwrap()
        .images
        .decode_all()
        .unwrap();
    (dir, images)
}

fn error_of(images: &[SphereImage], settings: &Settings) -> String {
    let images = images.to_vec();
    calibrate::calibrate(&images, None, None, settings)
        .unwrap_err()
        .to_string()
}

#[test]
fn bad_images_are_errors_naming_them_and_skip_bad_leaves_them_out() {
    let mut set = ChromeSet::standard(8, 59);
    set.lights.truncate(8);
    set.highlight.truncate(8);
    // Light 3 behind the ball: no highlight; image 6 gets a second light (below).
    set.lights[2] = [0.02, 0.0, -1.0];
    let (_dir, mut images) = images_of(&set);
    let mut twin = set.clone();
    twin.lights = vec![[-0.5, 0.3, 0.81]];
    twin.highlight = vec![2.5];
    let other = twin.render().remove(0).mapv(|v| v * 257);
    images[5]
        .plane
        .zip_mut_with(&other, |a, &b| *a = (*a).max(b));

    let e = error_of(&images, &auto());
    assert!(
        e.contains("ball03.png") && (e.contains("no highlight") || e.contains("environment")),
        "{e}"
    );
    let mut without_3 = images.clone();
    without_3.remove(2);
    let e = error_of(&without_3, &auto());
    assert!(
        e.contains("ball06.png") && e.contains("two highlights about equally strong"),
        "{e}"
    );

    let skip = Settings {
        skip_bad: true,
        ..auto()
    };
    let cal = calibrate::calibrate(&images, None, None, &skip).unwrap();
    let left_out: Vec<&str> = cal.skipped.iter().map(|s| s.image.as_str()).collect();
    assert_eq!(left_out, ["ball03.png", "ball06.png"]);
    assert_eq!(cal.lights.len(), 6);
    for l in &cal.lights {
        assert!(angle_deg(l.highlight.direction, set.lights[l.index]) < 1.0);
    }
    assert!(!cal.table().contains("ball03.png"));

    // Too few usable images, too few images, different sizes, a circle off the image.
    let e = calibrate::calibrate(&images[1..4].to_vec(), None, None, &skip)
        .unwrap_err()
        .to_string();
    assert!(e.contains("only 2 of 3") && e.contains("ball03.png"), "{e}");
    let e = error_of(&images[..2], &auto());
    assert!(e.contains("at least 3"), "{e}");
    let mut sizes = images.clone();
    sizes[4].plane = sizes[4].plane.slice(ndarray::s![..200, ..]).to_owned();
    let e = error_of(&sizes, &auto());
    assert!(e.contains("ball05.png") && e.contains("same size"), "{e}");
    let off = Settings {
        circle: CircleSource::Given(calibrate::Circle {
            cx: 400.0,
            cy: 100.0,
            r: 50.0,
        }),
        ..auto()
    };
    let e = error_of(&images, &off);
    assert!(e.contains("outside the 320×240 image"), "{e}");
}

#[test]
fn no_sphere_in_a_plain_backdrop_is_an_error() {
    let mut set = ChromeSet::standard(8, 61);
    set.radius = 0.0;
    set.lights.truncate(4);
    set.highlight.truncate(4);
    let (_dir, images) = images_of(&set);
    let e = error_of(&images, &auto());
    assert!(e.contains("no sphere found"), "{e}");
}

#[test]
fn matte_sphere_gives_relative_intensities_within_2_percent() {
    let set = ChromeSet::standard(16, 67);
    let k = synth::matte_intensities(set.lights.len(), 5);
    let dir = tempfile::tempdir().unwrap();
    set.write(dir.path(), Some(&k)).unwrap();
    let f = calibrate::load_dir(dir.path()).unwrap();
    let mut cal = calibrate::calibrate(&f.images, f.names.as_deref(), None, &auto()).unwrap();
    let matte = calibrate::load_images(&dir.path().join("matte")).unwrap();
    cal.fit_intensities(&matte, &auto()).unwrap();
    let mean = k.iter().sum::<f64>() / k.len() as f64;
    let worst = cal
        .lights
        .iter()
        .map(|l| (l.intensity.unwrap() / (k[l.index] / mean) - 1.0).abs())
        .fold(0.0, f64::max);
    eprintln!("matte intensities: worst relative error {:.4}", worst);
    assert!(worst < 0.02, "{worst}");
    // The table carries them as the fifth column, and reads back as is.
    let table = lights::parse(&cal.table()).unwrap();
    assert_eq!(table[0].name, "im1.png");
    assert!((table[3].intensity - cal.lights[3].intensity.unwrap()).abs() < 1e-3);
}

/// The normals reconstructed from `dir` with its own lights, or with `table`'s.
fn normals(dir: &Path, table: Option<&str>) -> ndarray::Array3<f32> {
    let mut set = intake::load_dir(dir, DirMask::Folder, &Limits::default()).unwrap();
    if let Some(t) = table {
        let calibrated = lights::parse(t).unwrap();
        for l in &mut set.lights {
            let c = calibrated.iter().find(|c| c.name == l.name).unwrap();
            l.direction = c.direction;
        }
    }
    reconstruct(&set, &Options::default(), &mut RunToEnd)
        .unwrap()
        .normals
}

#[test]
fn calibrated_lights_reconstruct_within_half_a_degree_of_the_true_lights() {
    let chrome = ChromeSet::standard(8, 71);
    let (_dir, cal) = run(&chrome, &auto());
    let cal = cal.unwrap();
    let table = cal.table();
    let object = tempfile::tempdir().unwrap();
    let capture = synth::Capture {
        noise_sigma: 0.002,
        ..Default::default()
    };
    synth::write_set(
        object.path(),
        &synth::Scene::sphere(128),
        &chrome.lights,
        &capture,
    )
    .unwrap();
    let truth = synth::read_truth(object.path()).unwrap();
    let (a, b) = (
        normals(object.path(), None),
        normals(object.path(), Some(&table)),
    );
    let mut diffs: Vec<f64> = Vec::new();
    for ((r, c), &m) in truth.mask.indexed_iter() {
        if m {
            let n = |x: &ndarray::Array3<f32>| [0, 1, 2].map(|k| x[[r, c, k]] as f64);
            diffs.push(angle_deg(n(&a), n(&b)));
        }
    }
    let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
    diffs.sort_by(f64::total_cmp);
    let p99 = diffs[diffs.len() * 99 / 100];
    let max = diffs[diffs.len() - 1];
    eprintln!(
        "calibrated vs true lights: normals differ by {mean:.3}° on average, {p99:.3}° at the 99th percentile, {max:.3}° at most (a rim pixel)"
    );
    assert!(
        mean < 0.5 && p99 < 0.5,
        "mean {mean}°, 99th percentile {p99}°"
    );
    // The same calibration written as a .lp file (y up) and read back as the light table
    // gives the same normals.
    let from_lp = normals(object.path(), Some(&cal.lp_table()));
    let worst = (0..b.len())
        .map(|i| (b.as_slice().unwrap()[i] - from_lp.as_slice().unwrap()[i]).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst < 1e-5,
        ".lp round trip moved a normal component by {worst}"
    );
}

#[test]
fn a_room_light_clipped_in_every_image_and_a_window_are_never_the_light() {
    let set = ChromeSet::real_room(8, 71);
    let (_dir, cal) = run(&set, &auto());
    let cal = cal.unwrap();
    let (mean, max, _, _) = errors(&set, &cal);
    eprintln!("real room: mean {mean:.3}° max {max:.3}°");
    assert!(mean < 0.3 && max < 1.0, "mean {mean}°, max {max}°");
    let least = cal
        .lights
        .iter()
        .map(|l| l.highlight.confidence)
        .fold(1.0, f64::min);
    assert!(
        least >= 0.5,
        "least confidence {least}\n{}",
        cal.quality_table()
    );
}

#[test]
fn large_area_lights_up_to_20_degrees_across_are_lights() {
    // 20° across (10° radius): large, and squeezed into long arcs towards the rim.
    let mut set = ChromeSet::standard(16, 73);
    set.light_radius_deg = 10.0;
    set.lights = synth::light_rings(12, 10.0, 60.0);
    set.highlight.truncate(12);
    let (_dir, cal) = run(&set, &auto());
    let cal = cal.unwrap();
    let (mean, max, _, _) = errors(&set, &cal);
    let longest = cal
        .lights
        .iter()
        .map(|l| l.highlight.elongation)
        .fold(0.0, f64::max);
    eprintln!("20° lights: mean {mean:.3}° max {max:.3}°, elongation up to {longest:.1}");
    assert!(mean < 0.5 && max < 1.5, "mean {mean}°, max {max}°");
}

#[test]
fn images_all_alike_are_refused_not_calibrated() {
    let set = ChromeSet::all_same_light(8, 75);
    let (_dir, images) = images_of(&set);
    let e = error_of(&images, &auto());
    assert!(e.contains("alike"), "{e}");
    // The same image copied is refused the same way.
    let copies = vec![images[0].clone(), images[0].clone(), images[0].clone()];
    let e = error_of(&copies, &auto());
    assert!(e.contains("alike"), "{e}");
}

/// Calibrate a two-ball near-light dome with its balls' true circles given.
fn near(distance: f64) -> (ChromeSet, Calibration) {
    let set = ChromeSet::near_dome(16, 77, distance);
    let circles = set
        .balls()
        .iter()
        .map(|&(c, r)| calibrate::Circle {
            cx: c[0],
            cy: c[1],
            r,
        })
        .collect();
    let settings = Settings {
        circle: CircleSource::Balls(circles),
        ..auto()
    };
    let (_dir, cal) = run(&set, &settings);
    (set, cal.unwrap())
}

/// The worst light position's distance from the true one, as a fraction of the light's
/// distance from between the balls, and the worst direction of a light from a ball (each
/// ball's own: from the point of the ball that shows the highlight to the light), degrees.
fn position_errors(set: &ChromeSet, cal: &Calibration) -> (f64, f64) {
    let positions = set.light_positions.as_ref().unwrap();
    let c0 = set.centre;
    let scale = set.balls().iter().map(|b| b.1).sum::<f64>() / 2.0;
    let mid = {
        let b = set.balls();
        [
            (b[0].0[0] + b[1].0[0]) / 2.0,
            (b[0].0[1] + b[1].0[1]) / 2.0,
            0.0,
        ]
    };
    let mut worst = 0.0f64;
    let mut dir_err = 0.0f64;
    for l in &cal.lights {
        let truth = positions[l.index];
        let p = l.position.expect("two balls place every light").position;
        // Ball radii from the first ball's centre, back to pixels.
        let got = [p[0] * scale + c0[0], p[1] * scale + c0[1], p[2] * scale];
        let dist = |a: [f64; 3], b: [f64; 3]| {
            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
        };
        worst = worst.max(dist(got, truth) / dist(truth, mid));
        for (hl, (c, r)) in std::iter::once(&l.highlight)
            .chain(&l.more)
            .zip(set.balls())
        {
            let (u, v) = ((hl.x - c[0]) / r, (hl.y - c[1]) / r);
            let point = [hl.x, hl.y, r * (1.0 - u * u - v * v).max(0.0).sqrt()];
            let to = [
                truth[0] - point[0],
                truth[1] - point[1],
                truth[2] - point[2],
            ];
            let n = (to[0] * to[0] + to[1] * to[1] + to[2] * to[2]).sqrt();
            dir_err = dir_err.max(angle_deg(hl.direction, to.map(|t| t / n)));
        }
    }
    (worst, dir_err)
}

#[test]
fn two_balls_under_near_leds_place_each_light_within_2_percent_of_its_distance() {
    for distance in [2.0, 3.0, 4.0] {
        let (set, cal) = near(distance);
        let (worst, dir_err) = position_errors(&set, &cal);
        eprintln!(
            "near lights at {distance} ball diameters: positions off by {:.2} % of the distance at most; directions per ball within {dir_err:.2}°",
            100.0 * worst
        );
        assert_eq!(cal.lights.len(), set.lights.len());
        assert!(worst < 0.02, "{distance}: {worst}");
        assert!(dir_err < 1.0, "{distance}: {dir_err}°");
    }
}

#[test]
fn two_balls_are_found_in_the_frame_and_place_each_light_within_2_percent() {
    for distance in [2.0, 3.0, 4.0] {
        let set = ChromeSet::near_dome(16, 77, distance);
        let (_dir, cal) = run(&set, &auto());
        let cal = cal.unwrap();
        // Both balls, left to right as the set lists them, each with its outline fit.
        let found: Vec<calibrate::Circle> = std::iter::once(cal.circle)
            .chain(cal.more_circles.iter().copied())
            .collect();
        assert_eq!(found.len(), 2, "{found:?}");
        assert_eq!(cal.more_outlines.len(), 1);
        assert!(cal.outline.is_some() && cal.not_balls.is_empty());
        let mut circle_err = (0.0f64, 0.0f64);
        for (c, (centre, r)) in found.iter().zip(set.balls()) {
            circle_err.0 = circle_err.0.max((c.cx - centre[0]).hypot(c.cy - centre[1]));
            circle_err.1 = circle_err.1.max((c.r - r).abs());
        }
        let (worst, dir_err) = position_errors(&set, &cal);
        let coverage: Vec<String> = std::iter::once(cal.outline.unwrap())
            .chain(cal.more_outlines.iter().copied())
            .map(|o| format!("{:.0} %", 100.0 * o.coverage))
            .collect();
        eprintln!(
            "two balls found, near lights at {distance} ball diameters: circles' centres within {:.3} px, radii within {:.3} px (outlines traced along {}); positions off by {:.2} % of the distance at most; directions per ball within {dir_err:.2}°",
            circle_err.0,
            circle_err.1,
            coverage.join(" and "),
            100.0 * worst
        );
        assert!(
            circle_err.0 < 0.3 && circle_err.1 < 0.3,
            "{distance}: {circle_err:?}"
        );
        assert_eq!(cal.lights.len(), set.lights.len());
        assert!(worst < 0.02, "{distance}: {worst}");
        assert!(dir_err < 1.0, "{distance}: {dir_err}°");
        assert!(cal.positions_table(None).is_some());
    }
}

#[test]
fn a_round_patch_beside_the_ball_that_shows_no_highlight_is_no_ball() {
    // The near dome's left ball alone, and where its right ball was a disc of that size
    // on the backdrop (a plate, a lens cap): a round outline as strong as a ball's, alike
    // in every image.
    let mut set = ChromeSet::near_dome(16, 77, 3.0);
    let (c, r) = set.extra_balls.pop().unwrap();
    let (_dir, mut images) = images_of(&set);
    let disc = ndarray::Array2::from_shape_fn((set.height, set.width), |(y, x)| {
        let inside = |i: usize, j: usize| {
            let (sx, sy) = (
                x as f64 - 0.375 + 0.25 * i as f64,
                y as f64 - 0.375 + 0.25 * j as f64,
            );
            (sx - c[0]).hypot(sy - c[1]) <= r
        };
        (0..16).filter(|k| inside(k % 4, k / 4)).count() as f64 / 16.0
    });
    for im in &mut images {
        im.plane.zip_mut_with(&disc, |p, &k| {
            *p = (k * 0.8 * 65535.0 + (1.0 - k) * *p as f64).round() as u16
        });
    }
    let cal = calibrate::calibrate(&images, None, None, &auto()).unwrap();
    let [patch] = cal.not_balls[..] else {
        panic!("{:?}", cal.not_balls);
    };
    eprintln!(
        "a disc beside the ball: left out at ({:.2}, {:.2}), radius {:.2} px; the ball at ({:.2}, {:.2}), radius {:.2} px",
        patch.cx, patch.cy, patch.r, cal.circle.cx, cal.circle.cy, cal.circle.r
    );
    assert!((patch.cx - c[0]).hypot(patch.cy - c[1]) < 0.5 && (patch.r - r).abs() < 0.5);
    assert!(cal.more_circles.is_empty() && cal.positions_table(None).is_none());
    let ball = (cal.circle.cx - set.centre[0]).hypot(cal.circle.cy - set.centre[1]);
    assert!(ball < 0.3 && (cal.circle.r - set.radius).abs() < 0.3);
    assert_eq!(cal.lights.len(), set.lights.len());
}

/// 1 MiB for the copies: the outline is fitted on 2× downscaled images and refined at
/// full resolution; 64 KiB for the windows: they are spilled and read back by bands.
fn small_budget() -> Settings {
    Settings {
        budget: calibrate::Budget {
            coarse_bytes: 1 << 20,
            crop_bytes: 64 << 10,
        },
        ..auto()
    }
}

#[test]
fn a_small_memory_budget_downscales_and_spills_with_the_same_accuracy() {
    small_budget_within_bounds(&[("8-bit", ChromeSet::standard(8, 41))]);
}

#[test]
fn a_small_memory_budget_finds_a_ball_filling_the_frame_or_in_a_room() {
    small_budget_within_bounds(&[
        ("filling, 16-bit", ChromeSet::filling(16, 47)),
        ("real room", ChromeSet::real_room(8, 71)),
    ]);
}

fn small_budget_within_bounds(sets: &[(&str, ChromeSet)]) {
    let small = small_budget();
    for (name, set) in sets {
        let (_dir, cal) = run(set, &small);
        let cal = cal.unwrap();
        let (mean, max, centre, radius) = errors(set, &cal);
        eprintln!(
            "{name}, small budget: direction error mean {mean:.3}° max {max:.3}°; circle centre off by {centre:.3} px, radius by {radius:.3} px"
        );
        assert!(mean < 0.3 && max < 1.0, "{name}: mean {mean}°, max {max}°");
        assert!(
            centre < 0.3 && radius < 0.3,
            "{name}: {centre} / {radius} px"
        );
    }
}
