//! Depth steps kept (issue 42): on the renderer's perspective scenes with exact normals and
//! depth (`synth::depth_scenes`), the discontinuity-preserving integrator (`bilateral`)
//! must leave a depth error well below Poisson's where the scene has depth steps, and no
//! worse than Poisson's where it is smooth; likewise for an orthographic step scene.
//!
//! Depth error as the field measures it: MADE, the mean absolute depth error over the mask
//! after scaling the estimate by `s = median(true / estimated)`; `rel` is MADE over the
//! scene's depth range. Orthographic heights have an unknown offset instead of a scale: the
//! estimate is shifted by `median(true − estimated)`.
//!
//! `cargo test --release --test core depth_steps:: -- --nocapture` prints the tables.

use std::sync::Mutex;
use std::time::Instant;

use ndarray::Array2;
use photostereo::core::integrate::perspective::depth_from_log;
use photostereo::core::integrate::{Cuts, LogDepth, integrate, integrate_log_depth};
use photostereo::core::metrics::{Align, depth_error};
use photostereo::core::options::Integration;
use photostereo::core::progress::NEVER;
use photostereo::core::synth::{self, DepthScene};

/// Side of the scenes, pixels.
const SIZE: usize = 256;
/// Methods compared, Poisson first.
const METHODS: [Integration; 3] = [
    Integration::Poisson,
    Integration::RobustPoisson,
    Integration::Bilateral,
];
/// On step scenes bilateral's MADE must be at most this fraction of Poisson's.
const STEP_RATIO: f64 = 0.5;
/// On smooth scenes bilateral's MADE must be at most this multiple of Poisson's, plus
/// [`SMOOTH_EPS`] of the depth range.
const SMOOTH_RATIO: f64 = 1.05;
const SMOOTH_EPS: f64 = 1e-5;

/// MADE under a camera (the estimate scaled by median(true / estimated)), or the mean
/// absolute error after the median offset for orthographic heights: `metrics::depth_error`,
/// which `photostereo evaluate` reports. The estimate must be finite on the whole mask.
fn made(est: &Array2<f32>, scene: &DepthScene) -> f64 {
    let finite = (est.iter().zip(&scene.mask)).all(|(e, m)| !*m || e.is_finite());
    assert!(
        finite,
        "{}: the estimate is not finite everywhere on the mask",
        scene.name
    );
    let align = match scene.camera {
        Some(_) => Align::Scale,
        None => Align::Offset,
    };
    depth_error(est, &scene.depth, &scene.mask, align).mean_abs
}

/// Log depth from the scene's exact normals under its camera, as a job or `photostereo
/// integrate` integrates it.
fn log_depth(scene: &DepthScene, method: Integration) -> LogDepth {
    let camera = scene.camera.expect("a perspective scene");
    let given = Default::default();
    integrate_log_depth(
        &scene.normals,
        &scene.mask,
        &camera,
        method,
        None,
        given,
        NEVER,
    )
}

/// The steps `bilateral` keeps on the scene.
fn bilateral_cuts(scene: &DepthScene) -> Cuts {
    let surface = log_depth(scene, Integration::Bilateral);
    surface.cuts.expect("bilateral reports its cuts")
}

/// The scene integrated by `method` from its exact normals as a job or `photostereo
/// integrate` does: perspective (log depth from the normals and the camera, then depth)
/// with a camera, else orthographic heights in pixels.
fn reconstruct(scene: &DepthScene, method: Integration) -> Array2<f32> {
    match scene.camera {
        Some(camera) => {
            let zeta = log_depth(scene, method).zeta;
            depth_from_log(&zeta, &scene.mask, &camera, None)
        }
        None => {
            let (p, q) = scene.gradients();
            integrate(&p, &q, &scene.mask, method)
        }
    }
}

/// The measuring tests take turns, so that their timings are not shared with another's
/// and their tables print whole.
static TURN: Mutex<()> = Mutex::new(());

/// MADE per method (in [`METHODS`]' order) for each scene, with the table printed.
fn measure(scenes: &[DepthScene]) -> Vec<[f64; 3]> {
    let _turn = TURN.lock().unwrap_or_else(|e| e.into_inner());
    let mut table = String::from(
        "| scene | method | MADE | rel (of depth range) | ms |\n|---|---|---:|---:|---:|\n",
    );
    let figures = scenes
        .iter()
        .map(|scene| {
            let range = scene.depth_range();
            METHODS.map(|method| {
                let start = Instant::now();
                let est = reconstruct(scene, method);
                let ms = start.elapsed().as_secs_f64() * 1e3;
                let e = made(&est, scene);
                table += &format!(
                    "| {} | {method:?} | {e:.5} | {:.5} | {ms:.0} |\n",
                    scene.name,
                    e / range
                );
                e
            })
        })
        .collect();
    println!("{table}");
    figures
}

/// Bilateral against Poisson on every scene, all figures in the panic message.
fn hold(scenes: &[DepthScene], figures: &[[f64; 3]]) {
    let mut failed = Vec::new();
    for (scene, [poisson, _, bilateral]) in scenes.iter().zip(figures) {
        let range = scene.depth_range();
        let (bound, kind) = if scene.smooth {
            (SMOOTH_RATIO * poisson + SMOOTH_EPS * range, "smooth")
        } else {
            (STEP_RATIO * poisson, "steps")
        };
        if bilateral > &bound {
            failed.push(format!(
                "{} ({kind}): bilateral MADE {bilateral:.5} > {bound:.5} (Poisson {poisson:.5}, ratio {:.3})",
                scene.name,
                bilateral / poisson
            ));
        }
    }
    assert!(failed.is_empty(), "{}", failed.join("\n"));
}

/// The scenes of `synth::depth_scenes` with these names, in this order.
fn named(names: &[&str]) -> Vec<DepthScene> {
    let all = synth::depth_scenes(SIZE);
    (names.iter())
        .map(|n| (all.iter().find(|s| s.name == *n).cloned()).unwrap_or_else(|| panic!("{n}")))
        .collect()
}

/// Steps at occluding contours, where the normals turn away from the camera before the
/// surface breaks: what real objects show and what bilateral weighting is built for.
#[test]
fn bilateral_keeps_perspective_depth_steps_far_better_than_poisson() {
    let scenes = named(&["sphere-in-front", "two-objects"]);
    let figures = measure(&scenes);
    hold(&scenes, &figures);
}

#[test]
fn bilateral_is_as_accurate_as_poisson_on_a_smooth_perspective_scene() {
    let scenes = named(&["bumps"]);
    let figures = measure(&scenes);
    hold(&scenes, &figures);
}

/// Not met yet (issue 42): a thin panel hinged on a plate steps along edges whose normals
/// do not turn, so nothing marks the break in the normals but the path dependence; the
/// bilateral weights never form there and the depth stays as smeared as Poisson's
/// (MADE 0.201 vs 0.197 perspective, 8.45 vs 8.91 px orthographic), while Poisson with
/// the true steps cut recovers it (`without_the_steps_poisson_is_nearly_exact`).
#[test]
#[ignore = "issue 42, not met: bilateral ≈ Poisson on the hinged panel's steps"]
fn bilateral_keeps_a_hinged_panels_steps_far_better_than_poisson() {
    let scenes = [
        named(&["step-plate"]).remove(0),
        synth::ortho_step_plate(SIZE),
    ];
    let figures = measure(&scenes);
    hold(&scenes, &figures);
}

/// Not met yet (issue 42): on a lone sphere down to its steep rim, bilateral's MADE is
/// 33 × Poisson's (1.7e-3 vs 5e-5 of a depth range of 2), both small. Part of
/// it is there before any pixel takes a side: bilateral's system solved once at shares
/// ½ gives 4.7e-4 (9.5 ×; 5.4e-4 with each edge's slope the plain mean of its ends), as
/// its facing weights (`perspective::Facing`) hold the grazing rim's equations loosely.
/// The rest comes with the rounds: the rim pixels choose their side by `n_z²`, and some
/// side with the wrong neighbour; with the ray's cosine there too it was 8.5 ×, but a
/// near-light dome's ball then stays hung on the plane behind it (`near_lights`).
#[test]
#[ignore = "issue 42, not met: bilateral 33 × Poisson on the sphere's steep rim"]
fn bilateral_is_as_accurate_as_poisson_on_a_lone_sphere() {
    let scenes = named(&["sphere"]);
    let figures = measure(&scenes);
    hold(&scenes, &figures);
}

/// The bound is within reach: the normals fix the depth (every step ends somewhere), and
/// Poisson on the mask without the steps' pixels recovers it there to a small fraction
/// of its error on the whole mask (a tenth at most).
#[test]
fn without_the_steps_poisson_is_nearly_exact() {
    let scenes = (synth::depth_scenes(SIZE).into_iter())
        .filter(|s| !s.smooth)
        .chain([synth::ortho_step_plate(SIZE)]);
    for scene in scenes {
        let steps = scene.steps();
        let cut = DepthScene {
            mask: Array2::from_shape_fn(steps.dim(), |i| scene.mask[i] && !steps[i]),
            ..scene.clone()
        };
        let whole = made(&reconstruct(&scene, Integration::Poisson), &scene);
        let around = made(&reconstruct(&cut, Integration::Poisson), &cut);
        println!(
            "{}: Poisson MADE {whole:.5}, without the steps' pixels {around:.5}",
            scene.name
        );
        assert!(around < 0.1 * whole, "{}", scene.name);
    }
}

/// The steps bilateral keeps are the scenes' own: on the scenes with steps at occluding
/// contours, nearly every edge across which the true `ζ` steps (by more than a pixel
/// beyond both ends' slopes) has a cut on it or beside it along its axis (the rim pixel
/// itself, whose normal grazes the ray, may side either way), and nearly none of the cuts
/// lies away from the steps' pixels (`DepthScene::steps`, widened by one). Measured:
/// 83 % and 79 % of the step edges cut, 15 % and 9 % of the cuts away (sphere-in-front,
/// two-objects); on the smooth scene, no cut.
#[test]
fn bilateral_cuts_where_the_depth_steps() {
    for scene in named(&["bumps"]) {
        let cuts = bilateral_cuts(&scene);
        let cut = cuts.east.iter().chain(&cuts.south).filter(|c| **c).count();
        assert_eq!(cut, 0, "{}: {cut} cuts on a smooth surface", scene.name);
    }
    for scene in named(&["sphere-in-front", "two-objects"]) {
        let camera = scene.camera.expect("a perspective scene");
        let cuts = bilateral_cuts(&scene);
        let (p, q) = scene.gradients();
        let zeta = scene.depth.mapv(|d| -camera.fx * f64::from(d).ln());
        let (h, w) = scene.mask.dim();
        let on_step = scene.steps();
        let near_step = |r: usize, c: usize| {
            (r.saturating_sub(1)..(r + 2).min(h))
                .any(|r| (c.saturating_sub(1)..(c + 2).min(w)).any(|c| on_step[[r, c]]))
        };
        let (mut steps, mut kept, mut cut, mut stray) = (0usize, 0usize, 0usize, 0usize);
        for (r, c) in (0..h).flat_map(|r| (0..w).map(move |c| (r, c))) {
            let i = r * w + c;
            // Each edge from (r, c): its far end, slopes, cuts, and stride along its axis.
            for ((rr, cc), g, edges, stride) in [
                ((r, c + 1), &p, &cuts.east, 1),
                ((r + 1, c), &q, &cuts.south, w),
            ] {
                if rr >= h || cc >= w || !scene.mask[[r, c]] || !scene.mask[[rr, cc]] {
                    continue;
                }
                let slope = 0.5 * f64::from(g[[r, c]] + g[[rr, cc]]);
                let step = (zeta[[rr, cc]] - zeta[[r, c]] - slope).abs() > 1.0;
                let beside = [i.checked_sub(stride), Some(i), Some(i + stride)]
                    .into_iter()
                    .flatten()
                    .any(|k| edges.get(k).copied().unwrap_or(false));
                steps += usize::from(step);
                kept += usize::from(step && beside);
                cut += usize::from(edges[i]);
                stray += usize::from(edges[i] && !near_step(r, c) && !near_step(rr, cc));
            }
        }
        println!(
            "{}: {kept} of {steps} step edges cut on or beside; {cut} cuts, {stray} away from a step",
            scene.name
        );
        assert!(
            kept as f64 >= 0.7 * steps as f64,
            "{}: {kept} of {steps} step edges cut",
            scene.name
        );
        assert!(
            stray as f64 <= 0.2 * cut as f64,
            "{}: {stray} of {cut} cuts away from a step",
            scene.name
        );
    }
}
