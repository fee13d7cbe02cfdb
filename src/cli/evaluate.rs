//! `photostereo render` and `photostereo evaluate`: the project's own data sets with
//! their ground truth, and every solver scored on them, or on one capture by its
//! held-out lights.

use std::path::PathBuf;

use photostereo::core::intake::{self, DirMask, Limits};
use photostereo::core::options::{Integration, Solver};
use photostereo::core::{Options, metrics, pipeline, synth};

pub(crate) fn render(dir: PathBuf, only: Vec<String>) -> anyhow::Result<()> {
    for (name, scene, lights, capture) in synth::catalogue() {
        if !only.is_empty() && !only.iter().any(|o| o == name) {
            continue;
        }
        let out = dir.join(name);
        synth::write_set(&out, &scene, &lights, &capture)?;
        println!("{}", out.display());
    }
    for (name, set) in synth::chrome_catalogue() {
        if !only.is_empty() && !only.iter().any(|o| o == name) {
            continue;
        }
        let out = dir.join(name);
        set.write(&out, None)?;
        println!("{}", out.display());
    }
    Ok(())
}

pub(crate) fn evaluate(dir: PathBuf, integration: Integration) -> anyhow::Result<()> {
    use photostereo::core::camera::Pinhole;
    use photostereo::core::metrics::Align;
    let mut sets: Vec<PathBuf> = std::fs::read_dir(&dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("truth").is_dir())
        .collect();
    sets.sort();
    println!(
        "| scene | solver | mean ° | median ° | depth MAE | depth RMS | depth in | solve ms |"
    );
    println!("|---|---|---:|---:|---:|---:|---|---:|");
    for set_dir in sets {
        let truth = synth::read_truth(&set_dir)?;
        let mut set = intake::load_dir(&set_dir, DirMask::Folder, &Limits::default())?;
        set.mask = Some(truth.mask.clone());
        // A set with a camera is perspective: its truth is depth along the optical axis.
        let camera = Pinhole::in_folder(&set_dir)?;
        let (align, unit) = match camera {
            None => (Align::Offset, "px, offset"),
            Some(_) => (Align::Scale, "truth's unit, scaled"),
        };
        for solver in [Solver::L2, Solver::Weighted, Solver::Robust, Solver::Glossy] {
            let opts = Options {
                solver,
                integration,
                camera,
                ..Options::default()
            };
            let rec = pipeline::reconstruct(&set, &opts, &mut photostereo::core::RunToEnd)?;
            let acc = metrics::accuracy(&rec, &truth, &truth.mask);
            let depth = metrics::depth_error(&rec.heights, &truth.depth, &truth.mask, align);
            let solve_ms = rec
                .report
                .timings_ms
                .iter()
                .find(|t| t.stage == "solve")
                .map_or(0.0, |t| t.ms);
            println!(
                "| {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {unit} | {:.0} |",
                set_dir.file_name().unwrap_or_default().to_string_lossy(),
                serde_json::to_value(solver)?.as_str().unwrap_or_default(),
                acc.mean_deg,
                acc.median_deg,
                depth.mean_abs,
                depth.rms,
                solve_ms
            );
        }
    }
    println!(
        "\nDepth: heights aligned by the median of (true − estimated), in pixels; under a \
         camera (a set with camera.json or K.txt), depth scaled by the median of \
         (true / estimated), in the truth's unit, MAE being the field's MADE."
    );
    Ok(())
}

/// `evaluate --holdout-lights`: each solver's prediction of left-out images of one capture.
pub(crate) fn evaluate_holdout(dir: PathBuf) -> anyhow::Result<()> {
    use photostereo::core::bands::InMemory;
    use photostereo::core::holdout;
    let set = intake::load_dir(&dir, DirMask::Folder, &Limits::default())?;
    anyhow::ensure!(
        set.lights.len() >= holdout::MIN_IMAGES,
        "--holdout-lights needs at least {} images (each quarter of the lights is left \
         out in turn); {} has {}",
        holdout::MIN_IMAGES,
        dir.display(),
        set.lights.len()
    );
    println!("| solver | median relative error | mean | as the table says | observations |");
    println!("|---|---:|---:|---:|---:|");
    for solver in [Solver::L2, Solver::Robust, Solver::Glossy] {
        let opts = Options {
            solver,
            ..Options::default()
        };
        let score = holdout::holdout(&mut InMemory::new(&set), &opts, &|| false)?;
        println!(
            "| {} | {:.4} | {:.4} | {:.4} | {} |",
            serde_json::to_value(solver)?.as_str().unwrap_or_default(),
            score.median_relative,
            score.mean_relative,
            score.median_relative_table,
            score.observations
        );
    }
    println!(
        "\nEach quarter of the lights (every 4th) left out in turn; the rest reconstructed \
         (auto mask); left-out object pixels neither clipped nor darker than 2 % scored, \
         relative error, each left-out light's intensity fitted (one scale per image; \
         \"as the table says\": the median with the table's intensities)."
    );
    Ok(())
}
