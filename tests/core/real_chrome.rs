//! Light calibration on real chrome-ball photographs (../shared/real/chrome, never in the
//! repository), against the lights their authors measured (`truth_lights.csv`: the median
//! of the ball's pixels at 250 of 255 or more, mirrored; orthographic) and the circle they
//! fitted by hand (`sphere.json`). Skipped with a message on a fresh clone; required
//! under `CI=true`.

use crate::seed;

use std::path::Path;

use photostereo::core::calibrate::{self, Budget, Calibration, Circle, CircleSource, Settings};

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d: f64 = (0..3).map(|k| a[k] * b[k]).sum();
    d.clamp(-1.0, 1.0).acos().to_degrees()
}

fn truth(dir: &Path) -> Vec<(String, [f64; 3])> {
    std::fs::read_to_string(dir.join("truth_lights.csv"))
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split(',').map(str::trim).collect();
            let v = |i: usize| f[i].parse::<f64>().unwrap();
            (f[0].to_string(), [v(1), v(2), v(3)])
        })
        .collect()
}

fn hand_fitted(dir: &Path) -> Circle {
    let j: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("sphere.json")).unwrap()).unwrap();
    let f = |k: &str| j[k].as_f64().unwrap();
    Circle {
        cx: f("x"),
        cy: f("y"),
        r: f("radius"),
    }
}

fn calibrate(dir: &Path, circle: CircleSource) -> Calibration {
    calibrate_within(dir, circle, Budget::default())
}

fn calibrate_within(dir: &Path, circle: CircleSource, budget: Budget) -> Calibration {
    let f = calibrate::load_dir(dir).unwrap();
    let settings = Settings {
        circle,
        camera: calibrate::Camera::Orthographic,
        skip_bad: false,
        budget,
        scratch: None,
    };
    calibrate::calibrate(&f.images, f.names.as_deref(), f.ambient_source(), &settings).unwrap()
}

/// Mean and max direction error against the authors' lights, degrees; every image has
/// its light, and every light a confident highlight.
fn errors(name: &str, how: &str, dir: &Path, cal: &Calibration) -> (f64, f64) {
    let truth = truth(dir);
    assert_eq!(
        cal.lights.len(),
        truth.len(),
        "{name}: every image calibrated"
    );
    let e: Vec<f64> = cal
        .lights
        .iter()
        .map(|l| {
            let (_, want) = truth.iter().find(|(n, _)| *n == l.image).unwrap();
            angle_deg(l.highlight.direction, *want)
        })
        .collect();
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    let max = e.iter().copied().fold(0.0, f64::max);
    let least = cal
        .lights
        .iter()
        .map(|l| l.highlight.confidence)
        .fold(1.0, f64::min);
    let c = cal.circle;
    eprintln!(
        "{name} ({how}): mean {mean:.3}° max {max:.3}°; circle ({:.2}, {:.2}) r {:.2}; least confidence {least:.2}",
        c.cx, c.cy, c.r
    );
    assert!(least >= 0.7, "{name}: a light's confidence is {least}");
    assert!(
        cal.more_circles.is_empty(),
        "{name}: one ball, not {:?} beside it",
        cal.more_circles
    );
    (mean, max)
}

fn check(name: &str, dir: &Path, auto_mean: f64, given_mean: f64) {
    let hand = hand_fitted(dir);
    let cal = calibrate(dir, CircleSource::Fit);
    let (mean, max) = errors(name, "outline found automatically", dir, &cal);
    let c = cal.circle;
    let off = (c.cx - hand.cx).hypot(c.cy - hand.cy);
    eprintln!(
        "{name}: the fitted outline is {off:.2} px from the hand-fitted centre, radius {:+.2} px",
        c.r - hand.r
    );
    assert!(
        mean <= auto_mean && max <= 2.0,
        "{name}: mean {mean}°, max {max}°"
    );
    let cal = calibrate(dir, CircleSource::Given(hand));
    let (mean, max) = errors(name, "the authors' circle", dir, &cal);
    assert!(
        mean <= given_mean && max <= 2.0,
        "{name}: mean {mean}°, max {max}°"
    );
    // Budgets small enough that the outline is fitted on copies downscaled 5× or more and
    // refined at full resolution, and the ball's windows are spilled to a scratch file:
    // the path of many large images, held to the same bounds.
    let small = Budget {
        coarse_bytes: 2 << 20,
        crop_bytes: 1 << 20,
    };
    let cal = calibrate_within(dir, CircleSource::Fit, small);
    let (mean, max) = errors(name, "downscaled and spilled", dir, &cal);
    let off = (cal.circle.cx - hand.cx).hypot(cal.circle.cy - hand.cy);
    eprintln!(
        "{name}: downscaled, the outline is {off:.2} px from the hand-fitted centre, radius {:+.2} px",
        cal.circle.r - hand.r
    );
    assert!(
        mean <= auto_mean && max <= 2.0,
        "{name} (downscaled): mean {mean}°, max {max}°"
    );
}

// The target (issue 40): a mean of 0.6° at most and a max of 2°, with the outline found
// automatically, on each capture; with the authors' hand-fitted circles the lights come
// out at about half of that.

#[test]
fn real_psbox_ball_12_lights_within_2_degrees() {
    let dir = seed::real!("chrome/psbox-probe1");
    check("psbox-probe1", &dir, 0.60, 0.30);
}

#[test]
fn real_harvard_ball_with_a_room_light_20_lights_within_2_degrees() {
    // Besides the light, each image clips where the light shines on something to the
    // ball's right (near (985, 570), moving with the light): an echo of the light that the
    // environment cannot explain. The median takes it in by its share of the light, as
    // the authors' rule does.
    let dir = seed::real!("chrome/harvard-cat-probe1");
    check("harvard-cat-probe1", &dir, 0.60, 0.35);
}
