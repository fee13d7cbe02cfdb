//! A near-light set reconstructed and written: [`super::solve`] on the set's bands,
//! then the pictures (`albedo.png`, `normal.png`, `mask.png`, `depth.exr`, `depth.png`),
//! `points.ply` and `mesh.glb` unprojected through the camera, and `result.json`
//! ([`NearReport`]): those of [`selection::ARTIFACTS`] the `outputs` selection names (all
//! without one). Depth is metric, in the table's unit.

use std::path::Path;
use std::time::Instant;

use ndarray::Array2;
use serde::Serialize;

use super::selection;
use super::solve::solve;
use super::surface::{Iteration, NearSettings};
use crate::core::bands::{SetInfo, Stack};
use crate::core::camera::Pinhole;
use crate::core::commit::{self, Committer};
use crate::core::error::RunError;
use crate::core::intensities::Estimated;
use crate::core::options::{Integration, Intensities, MaskMode, Options};
use crate::core::outputs::{self, Heights, Maps};
use crate::core::pipeline::{not_halted, step};
use crate::core::progress::{Progress, Stage};
use crate::core::reconstruction::{Reconstruction, Report as RunReport, Timing};
use crate::core::stream::BAND_BYTES;

/// What a near-light reconstruction wrote: `result.json`.
#[derive(Debug, Clone, Serialize)]
pub struct NearReport {
    pub width: usize,
    pub height: usize,
    pub light_count: usize,
    /// Always `near`: lights given by position.
    pub lights: &'static str,
    pub camera: Pinhole,
    /// The working distance given (the first surface).
    pub distance: f64,
    /// The unit of positions, distance and depth, as the table gives it.
    pub unit: Option<String>,
    pub method: Integration,
    /// Median depth over the mask of the surface recovered, and its range.
    pub median_depth: f64,
    pub depth_min: f32,
    pub depth_max: f32,
    /// Each alternation of solve and integration, and whether the normals settled.
    pub iterations: Vec<Iteration>,
    pub converged: bool,
    /// The lights' relative intensities (mean 1) estimated from the object, when the
    /// table did not give them all; `lights.json` is then the table with them.
    pub estimated_intensities: Option<Vec<Estimated>>,
    pub timings_ms: Vec<Timing>,
    pub artifacts: Vec<String>,
    pub notes: Vec<String>,
}

/// The most [`run`] holds for a set of `pixels` per image, whatever the number of
/// images: its maps, the surface and the log-depth integration of each full-resolution
/// pass, one band of every image and the decoders' and threads' state (a 2048² job grew
/// by 80–100 bytes per pixel in all, 1.15–1.25 × a distant job). The service reserves it before a
/// near job starts; `tests/serial/bands_memory.rs` measures a job against it.
pub fn peak_bytes(pixels: u64) -> u64 {
    104 * pixels + BAND_BYTES as u64 + (16 << 20)
}

/// Reconstruct `stack` (lights with positions) under `camera` from the working
/// `distance`, and write its artifacts into `dir`. The mask is the set's own with
/// `--mask given`, else every pixel with three lit observations; `opts` gives the
/// integration, mesh and outputs (the fields of [`selection::OPTIONS`]; the camera and
/// distance are the caller's to resolve).
pub fn run(
    stack: &mut dyn Stack,
    camera: Pinhole,
    distance: f64,
    unit: Option<String>,
    opts: &Options,
    dir: &Path,
    progress: &mut dyn Progress,
) -> Result<NearReport, RunError> {
    let mut timings = Vec::new();
    let set = stack.info().clone();
    super::model::check_cones(&set.lights, &camera, distance, (set.width, set.height))?;
    let mut notes = set.notes.clone();
    step(progress, Stage::Solve)?;
    let start = Instant::now();
    let mask = match (&set.mask, opts.mask) {
        (Some(m), MaskMode::Given | MaskMode::Auto) => Some(m),
        _ => None,
    };
    // An LED whose table gave no intensity is estimated, and then every one is (relative).
    let estimate = opts.intensities == Intensities::Estimate
        || (set.lights.iter()).any(|l| l.emitter.is_some_and(|e| !e.intensity_known));
    let settings = NearSettings {
        integration: opts.integration,
        estimate_intensities: estimate,
        ..NearSettings::new(camera, distance)
    };
    let polled: &dyn Progress = progress;
    let surface = solve(stack, mask, &settings, &|| polled.halted())?;
    not_halted(polled)?;
    let mask = surface.mask;
    timings.push(timing("solve and integrate", start));
    if !surface.converged {
        notes.push(format!(
            "the normals still moved {:.3}° on average after {} iterations",
            surface.iterations.last().map_or(0.0, |i| i.mean_change_deg),
            surface.iterations.len()
        ));
    }

    step(progress, Stage::Outputs)?;
    let start = Instant::now();
    let (min, max) = (surface.depth.iter().zip(&mask))
        .filter(|(d, m)| **m && d.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), (d, _)| {
            (a.min(*d), b.max(*d))
        });
    std::fs::create_dir_all(dir).map_err(|e| RunError::Output {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })?;
    let dim = mask.dim();
    let rec = Reconstruction {
        width: set.width,
        height: set.height,
        lights: set.lights.clone(),
        albedo: surface.albedo.mapv(|a| a.clamp(0.0, 1.0)),
        albedo_rgb: None,
        gloss: None,
        confidence: mask.mapv(f32::from),
        unreliable: Array2::from_elem(dim, false),
        curl: Array2::zeros(dim),
        normals: surface.normals,
        mask,
        heights: surface.depth,
        report: RunReport {
            options: Options {
                camera: Some(camera),
                distance: Some(distance),
                ..opts.clone()
            },
            ..RunReport::default()
        },
    };
    // The selection, `all` standing for everything; the default writes everything too.
    let wanted = |name: &str| {
        (opts.outputs.as_deref()).is_none_or(|o| o.iter().any(|s| s == name || s == outputs::ALL))
    };
    let pictures: Vec<&str> = selection::pictures().filter(|n| wanted(n)).collect();
    let maps = Maps {
        heights: Some(Heights {
            z: &rec.heights,
            min,
            max,
        }),
        ..Maps::of(&rec)
    };
    let commits = Committer::new();
    let polled: &dyn Progress = progress;
    let halt = || polled.halted();
    let mut written = outputs::write_pictures(&maps, &pictures, [0.0; 3], dir, &commits, &halt)?;
    not_halted(polled)?;
    step(progress, Stage::Mesh)?;
    written.extend(outputs::write_geometry(
        &rec,
        &opts.mesh,
        Some(&camera),
        &wanted,
        (dir, &commits),
        &mut notes,
    )?);
    let estimated: Option<Vec<Estimated>> = surface.intensities.as_ref().map(|e| {
        (set.lights.iter().zip(e))
            .map(|(l, &intensity)| Estimated {
                name: l.name.clone(),
                intensity,
            })
            .collect()
    });
    if let Some(e) = &estimated {
        let table = table_json(&set, e, camera, distance, unit.as_deref());
        commits.write(dir, "lights.json", &mut |f| f.write_all(&table))?;
        written.push("lights.json".to_string());
    }
    timings.push(timing("outputs", start));
    written.push("result.json".into());
    let report = NearReport {
        width: set.width,
        height: set.height,
        light_count: set.lights.len(),
        lights: "near",
        camera,
        distance,
        unit,
        method: opts.integration,
        median_depth: surface
            .iterations
            .last()
            .map_or(distance, |i| i.median_depth),
        depth_min: min,
        depth_max: max,
        iterations: surface.iterations,
        converged: surface.converged,
        estimated_intensities: estimated,
        timings_ms: timings,
        artifacts: written,
        notes,
    };
    let json = serde_json::to_vec_pretty(&report).expect("the report serialises");
    commits.finish()?;
    commit::write_atomic(dir, "result.json", &json)?;
    Ok(report)
}

/// The set's light table with the estimated intensities, as `reconstruct` reads it.
fn table_json(
    set: &SetInfo,
    estimated: &[Estimated],
    camera: Pinhole,
    distance: f64,
    unit: Option<&str>,
) -> Vec<u8> {
    let lights: Vec<serde_json::Value> = (set.lights.iter().zip(estimated))
        .filter_map(|(l, e)| {
            let em = l.emitter?;
            Some(serde_json::json!({
                "name": l.name,
                "position": em.position,
                "axis": em.axis,
                "anisotropy": em.anisotropy,
                "intensity": e.intensity,
            }))
        })
        .collect();
    let table = serde_json::json!({
        "lights": lights,
        "camera": camera,
        "distance": distance,
        "unit": unit,
    });
    serde_json::to_vec_pretty(&table).expect("the table serialises")
}

fn timing(stage: &'static str, start: Instant) -> Timing {
    Timing {
        stage,
        ms: start.elapsed().as_secs_f64() * 1e3,
    }
}
