//! "Normals in": a normal map ([`normalmap`](super::normalmap)) integrated into heights
//! (orthographic) or depth (under a pinhole camera), with the reconstruction's
//! integrators and writers. `photostereo integrate` and the service's normals jobs call
//! [`run`]; it takes no HTTP types.
//!
//! - **Orthographic** (no camera): `integrate::gradients` and the integrator give heights
//!   in pixels → `height.png` (16-bit, 0..65535 ↔ [`height_min`, `height_max`] of
//!   `result.json`) and `height.exr` (f32, channel `Y`; off the mask the lowest height).
//! - **Perspective**: `perspective::log_depth_gradients`, the integrator, then
//!   `depth_from_log` give depth along the optical axis → `depth.exr` (f32, channel `Y`,
//!   NaN off the mask; median 1 over the mask, or the working `distance`) and `depth.png`
//!   (16-bit, **near = bright**: 65535..0 ↔ [`depth_min`, `depth_max`], 0 off the mask).
//! - Both: `mask.png`, `normal.png` (the normals as read, 16-bit OpenGL encoding),
//!   `mesh.glb` (heights, or vertices unprojected through the camera), `points.ply` and
//!   `result.json` ([`Report`]).
//!
//! All of them unless [`Settings::outputs`] names some ([`ARTIFACTS`]); `result.json` is
//! always written.

use std::path::Path;
use std::time::Instant;

use ndarray::Array2;
use serde::Serialize;

use super::camera::Pinhole;
use super::commit::{self, Committer};
use super::error::{InputError, RunError};
use super::integrate::{self, perspective};
use super::normalmap::{Convention, Counts, NormalMap};
use super::options::{self, Integration, MeshOptions, Options};
use super::outputs::{self, Heights, Maps};
use super::pipeline::{not_halted, step};
use super::progress::{Halt, Progress, Stage};
use super::reconstruction::{Reconstruction, Report as RunReport, Timing};

/// The job options (`Options` fields) a normal map's integration takes; the others are
/// the photometric reconstruction's.
pub const OPTIONS: [&str; 5] = ["integration", "mesh", "camera", "distance", "outputs"];

/// Every artifact [`run`] can write, in the order it writes them: the height pictures
/// without a camera, the depth pictures under one ([`outputs::fits_surface`]).
pub const ARTIFACTS: [&str; 9] = [
    "mask.png",
    "normal.png",
    "height.png",
    "height.exr",
    "depth.exr",
    "depth.png",
    "points.ply",
    "mesh.glb",
    "result.json",
];

/// The artifacts a map integrates into, orthographic or under a `camera`.
pub fn artifacts(camera: bool) -> impl Iterator<Item = &'static str> {
    ARTIFACTS
        .into_iter()
        .filter(move |n| outputs::fits_surface(n, camera))
}

/// Refuses an `outputs` selection that names what a normal map's integration never
/// writes (the photometric maps: it has no albedo, confidence or images), or the surface
/// of the other projection: depth needs a camera, and under one there are no heights.
pub fn check_outputs(names: &[String], camera: bool) -> Result<(), InputError> {
    outputs::check_selection(names)?;
    let refuse = |why: String| Err(InputError::Options(format!("field `outputs`: {why}")));
    for name in names.iter().map(String::as_str) {
        if name == outputs::ALL || artifacts(camera).any(|a| a == name) {
            continue;
        }
        if !ARTIFACTS.contains(&name) {
            return refuse(format!(
                "integrating a normal map writes no {name:?} (there are no images); it writes {}, or {:?} for all of them",
                artifacts(camera).collect::<Vec<_>>().join(", "),
                outputs::ALL
            ));
        }
        return refuse(if camera {
            format!(
                "{name:?} cannot be written: under a camera the normal map integrates into depth (depth.png, depth.exr), not heights"
            )
        } else {
            format!(
                "{name:?} cannot be written: without a camera the normal map integrates into heights (height.png, height.exr); depth needs a camera"
            )
        });
    }
    Ok(())
}

/// How a normal map is integrated.
#[derive(Debug, Clone, Default)]
pub struct Settings {
    pub integration: Integration,
    /// Perspective only: the median depth over the mask, in the caller's unit (metric
    /// depth); without it depth is relative, median 1.
    pub distance: Option<f64>,
    pub mesh: MeshOptions,
    /// Passed on to `result.json` (e.g. a camera file left unused).
    pub notes: Vec<String>,
    /// The artifacts to write (`"all"` for every one, `result.json` always); `None`: all.
    pub outputs: Option<Vec<String>>,
}

impl Settings {
    /// The settings of a job's `options` (the fields of [`OPTIONS`]; the camera goes to
    /// the reader as its [`Lens`](super::normalmap::Lens)).
    pub fn of(options: &Options) -> Self {
        Self {
            integration: options.integration,
            distance: options.distance,
            mesh: options.mesh.clone(),
            notes: Vec::new(),
            outputs: options.outputs.clone(),
        }
    }

    /// Refuses what cannot be used: a distance that is not a positive number, or one
    /// given without a camera (orthographic heights have no depth to scale); outputs
    /// that [`check_outputs`] refuses.
    pub fn check(&self, camera: Option<&Pinhole>) -> Result<(), InputError> {
        options::check_distance(self.distance, camera)?;
        match &self.outputs {
            Some(names) => check_outputs(names, camera.is_some()),
            None => Ok(()),
        }
    }

    /// Whether artifact `name` is to be written (`result.json` always is).
    pub fn wants(&self, name: &str) -> bool {
        name == "result.json"
            || (self.outputs.as_deref())
                .is_none_or(|names| names.iter().any(|n| n == name || n == outputs::ALL))
    }
}

/// What the integration wrote into `dir`: `result.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub width: usize,
    pub height: usize,
    /// The normal map read.
    pub source: String,
    pub mask_file: Option<String>,
    /// 8 or 16 (PNG), 32 (float EXR).
    pub bits: u8,
    pub convention: Convention,
    /// The pinhole camera; null when orthographic.
    pub camera: Option<Pinhole>,
    /// The median depth asked for (perspective); null for relative depth (median 1).
    pub distance: Option<f64>,
    pub method: Integration,
    /// `height` (orthographic, pixels) or `depth` (perspective, along the optical axis).
    pub output: &'static str,
    /// What the reader did with each pixel.
    pub counts: Counts,
    /// Height range over the mask, pixels (orthographic; `height.png` spans it).
    pub height_min: Option<f32>,
    pub height_max: Option<f32>,
    /// Depth range over the mask (perspective; `depth.png` spans it, near = bright).
    pub depth_min: Option<f32>,
    pub depth_max: Option<f32>,
    pub timings_ms: Vec<Timing>,
    pub artifacts: Vec<String>,
    pub notes: Vec<String>,
}

/// A note for the caller when the map's folder holds a camera file that was not asked
/// for: only an explicit camera makes the integration perspective.
pub fn unused_camera_note(map: &Path) -> Option<String> {
    let dir = map.parent()?;
    ["camera.json", "K.txt"]
        .into_iter()
        .map(|name| dir.join(name))
        .find(|p| p.is_file())
        .map(|p| {
            format!(
                "{} was not used: the integration is orthographic unless a camera is given \
                 (--camera {})",
                p.display(),
                p.display()
            )
        })
}

/// The integrated surface: heights in pixels (orthographic, off the mask the lowest
/// height) or depth along the optical axis (perspective, NaN off the mask). The iterative
/// integrators stop early (with meaningless values) once `halt` says stop.
pub fn surface(map: &NormalMap, settings: &Settings, halt: Halt) -> Array2<f32> {
    let (normals, mask) = (&map.normals, &map.mask);
    match &map.camera {
        None => {
            let (p, q) = integrate::gradients(normals, mask);
            integrate::integrate_until(&p, &q, mask, settings.integration, halt)
        }
        Some(k) => {
            let zeta = integrate::integrate_log_depth(
                normals,
                mask,
                k,
                settings.integration,
                None,
                Default::default(),
                halt,
            )
            .zeta;
            perspective::depth_from_log(&zeta, mask, k, settings.distance)
        }
    }
}

/// The most [`run`] holds for a normal map of `pixels`, with the map itself: the
/// integration's arrays and the pictures', and the decoder's and threads' state (a 2048²
/// map grew by 55–75 bytes per pixel in all). The service reserves it before a normals job
/// starts; `tests/serial/bands_memory.rs` measures a job against it.
pub fn peak_bytes(pixels: u64) -> u64 {
    80 * pixels + (32 << 20)
}

/// Integrate `map` and write its artifacts into `dir` (created if need be; each artifact
/// atomically, `result.json` last). Returns the report written. The stages (integrate,
/// outputs, mesh) are announced to `progress`, which is polled within them: once it says
/// stop, the run ends [`RunError::Cancelled`].
pub fn run(
    map: NormalMap,
    settings: &Settings,
    dir: &Path,
    progress: &mut dyn Progress,
) -> Result<Report, RunError> {
    let mut timings = Vec::new();
    step(progress, Stage::Integrate)?;
    let start = Instant::now();
    let polled: &dyn Progress = progress;
    let z = surface(&map, settings, &|| polled.halted());
    not_halted(polled)?;
    timings.push(timing("integrate", start));
    step(progress, Stage::Outputs)?;

    let start = Instant::now();
    let on = z
        .iter()
        .zip(&map.mask)
        .filter(|(_, m)| **m)
        .map(|(z, _)| *z);
    let (min, max) = on.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let perspective = map.camera.is_some();
    std::fs::create_dir_all(dir).map_err(|e| RunError::Output {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })?;
    let commits = Committer::new();
    let (camera, dim) = (map.camera, map.mask.dim());
    // The writers take a reconstruction: a white albedo (the mesh's texture).
    let rec = Reconstruction {
        width: map.width,
        height: map.height,
        lights: Vec::new(),
        albedo: map.mask.mapv(f32::from),
        albedo_rgb: None,
        gloss: None,
        confidence: map.mask.mapv(f32::from),
        unreliable: Array2::from_elem(dim, false),
        curl: Array2::zeros(dim),
        normals: map.normals,
        mask: map.mask,
        heights: z,
        report: RunReport {
            options: Options {
                integration: settings.integration,
                mesh: settings.mesh.clone(),
                camera,
                distance: settings.distance,
                ..Options::default()
            },
            ..RunReport::default()
        },
    };
    let mut notes = settings.notes.clone();
    let pictures: Vec<&str> = artifacts(perspective)
        .filter(|n| n.ends_with(".png") || n.ends_with(".exr"))
        .filter(|n| settings.wants(n))
        .collect();
    let maps = Maps {
        heights: Some(Heights {
            z: &rec.heights,
            min,
            max,
        }),
        ..Maps::of(&rec)
    };
    let polled: &dyn Progress = progress;
    let halt = || polled.halted();
    let mut written = outputs::write_pictures(&maps, &pictures, [0.0; 3], dir, &commits, &halt)?;
    not_halted(polled)?;
    step(progress, Stage::Mesh)?;
    let wanted = |name: &str| settings.wants(name);
    written.extend(outputs::write_geometry(
        &rec,
        &settings.mesh,
        camera.as_ref(),
        &wanted,
        (dir, &commits),
        &mut notes,
    )?);
    timings.push(timing("outputs", start));
    written.push("result.json".into());
    let range = (min <= max).then_some((min, max));
    let (heights, depths) = if perspective {
        (None, range)
    } else {
        (range, None)
    };
    let report = Report {
        width: map.width,
        height: map.height,
        source: map.name,
        mask_file: map.mask_name,
        bits: map.bits,
        convention: map.convention,
        camera,
        distance: settings.distance.filter(|_| perspective),
        method: settings.integration,
        output: if perspective { "depth" } else { "height" },
        counts: map.counts,
        height_min: heights.map(|r| r.0),
        height_max: heights.map(|r| r.1),
        depth_min: depths.map(|r| r.0),
        depth_max: depths.map(|r| r.1),
        timings_ms: timings,
        artifacts: written,
        notes,
    };
    let json = serde_json::to_vec_pretty(&report).expect("the report serialises");
    commits.finish()?;
    commit::write_atomic(dir, "result.json", &json)?;
    Ok(report)
}

fn timing(stage: &'static str, start: Instant) -> Timing {
    Timing {
        stage,
        ms: start.elapsed().as_secs_f64() * 1e3,
    }
}

#[cfg(test)]
mod tests;
