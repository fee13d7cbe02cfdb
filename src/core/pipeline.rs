//! From an image set to a [`Reconstruction`] (`reconstruct`) or to the written
//! artifacts (`run`, used by the CLI, the job worker and the bench): both are the same
//! steps (`prepare`, `Slopes`, `Prepared::finish`), `run` overlapping them.

use std::io::Write;
use std::ops::Range;
use std::path::Path;
use std::time::Instant;

use ndarray::{Array2, Array3, Zip, s};
use rayon::prelude::*;

use super::bands::{InMemory, Stack};
use super::commit::{self, Committer};
use super::error::InputError;
use super::error::RunError;
use super::intake::ImageSet;
use super::integrate::perspective;
use super::intensities::Estimated;
use super::lights::{self, Light};
use super::options::{Intensities, Options, Solver};
use super::outputs::{self, Maps};
use super::progress::{Halt, Progress, Stage};
use super::reconstruction::{Gloss, LightSummary, Reconstruction, Report, Timing};
use super::solve::{self, Surface};
use super::stream::BAND_BYTES;
use super::{heap, holdout, integrate, mask, robust};

/// The most [`run`] holds for a set of `pixels` per image, whatever the number of
/// images: its maps at the integration, one band of every image ([`BAND_BYTES`]) and
/// the decoders' and threads' state (a 2048² job grew by 63–80 bytes per pixel in all),
/// and with the `glossy` solver its lobe maps. The service reserves it before a job
/// starts; `tests/serial/bands_memory.rs` measures a job against it.
pub fn peak_bytes(pixels: u64, solver: Solver) -> u64 {
    let gloss = if solver == Solver::Glossy {
        Gloss::BYTES_PER_PIXEL
    } else {
        0
    };
    (80 + gloss) * pixels + BAND_BYTES as u64 + (16 << 20)
}

/// Reconstruct albedo, normals, mask and heights from a decoded image set.
pub fn reconstruct(
    set: &ImageSet,
    opts: &Options,
    progress: &mut dyn Progress,
) -> Result<Reconstruction, RunError> {
    let mut timings = Timings::default();
    let surface = prepare(&mut InMemory::new(set), opts, progress, &mut timings)?;
    step(progress, Stage::Integrate)?;
    let polled: &dyn Progress = progress;
    let (slopes, heights) = timings.time(Stage::Integrate, || {
        let slopes = Slopes::of(&surface, opts);
        let heights = slopes.integrate(&surface, opts, &|| polled.halted());
        (slopes, heights)
    });
    not_halted(polled)?;
    let curl = slopes.curl(&surface);
    Ok(surface.finish(curl, heights, opts, timings))
}

/// Everything recovered before integration: solved, masked and clipped to the mask.
struct Prepared {
    width: usize,
    height: usize,
    lights: Vec<Light>,
    /// Whether `lights`' intensities were estimated from the object.
    estimated: bool,
    condition: f64,
    clamped: usize,
    albedo: Array2<f32>,
    albedo_rgb: Option<Array3<f32>>,
    gloss: Option<Gloss>,
    normals: Array3<f32>,
    mask: Array2<bool>,
    confidence: Array2<f32>,
    unreliable: Array2<bool>,
    /// The solve's per-pixel figures the report needs only summed: their maps are gone
    /// before the integration, the job's peak (at 4096², 100 MB less).
    solve_sums: SolveSums,
    estimate: Option<robust::CaptureEstimate>,
    mask_file: Option<String>,
    notes: Vec<String>,
}

/// The solve and the mask stages.
fn prepare(
    stack: &mut dyn Stack,
    opts: &Options,
    progress: &mut dyn Progress,
    timings: &mut Timings,
) -> Result<Prepared, RunError> {
    if stack.info().lights.iter().any(|l| l.emitter.is_some()) {
        return Err(InputError::Lights(
            "lights given by position (near lights) are reconstructed by `photostereo \
             reconstruct` on a folder; this path takes directions"
                .into(),
        )
        .into());
    }
    let condition = lights::check_solvable(&stack.info().lights, opts.max_condition)?;
    if let Some(names) = &opts.outputs {
        outputs::check_selection(names)?;
    }
    opts.check_camera(stack.info().width, stack.info().height)?;

    step(progress, Stage::Solve)?;
    let polled: &dyn Progress = progress;
    let estimated = opts.intensities == Intensities::Estimate;
    let (surface, lights) = timings.time(Stage::Solve, || {
        let lights = match opts.intensities {
            Intensities::Table => stack.info().lights.clone(),
            Intensities::Estimate => estimated_lights(stack)?,
        };
        let surface = solve::solve(stack, &lights, opts.solver, &|| polled.halted())?;
        Ok::<_, InputError>((surface, lights))
    })?;
    not_halted(polled)?;
    let set = stack.info();
    let Surface {
        mut albedo,
        mut normals,
        residual,
        mut confidence,
        inliers,
        mut unreliable,
        estimate,
        mut albedo_rgb,
        mut gloss,
    } = surface;

    step(progress, Stage::Mask)?;
    let mask = timings.time(Stage::Mask, || {
        mask::build(opts.mask, &albedo, set.mask.as_ref())
    })?;
    // Clip every map to the mask, counting the albedo clamped to 1.
    let clamped = Zip::from(&mut albedo)
        .and(normals.rows_mut())
        .and(&mask)
        .par_fold(
            || 0,
            |clamped, a, mut n, &m| {
                if m {
                    let over = *a > 1.0;
                    *a = a.min(1.0);
                    return clamped + usize::from(over);
                }
                *a = 0.0;
                n.fill(0.0);
                clamped
            },
            |a, b| a + b,
        );
    Zip::from(&mut confidence)
        .and(&mut unreliable)
        .and(&mask)
        .par_for_each(|c, u, &m| {
            if !m {
                (*c, *u) = (0.0, false);
            }
        });
    let solve_sums = SolveSums::of(&mask, &residual, &inliers);
    drop((residual, inliers));
    if let Some(g) = &mut gloss {
        Zip::from(&mut g.specular)
            .and(&mut g.roughness)
            .and(&mut g.used)
            .and(&mut g.residual)
            .and(&mut g.lambertian_residual)
            .and(&mask)
            .par_for_each(|s, r, u, e, l, &m| {
                if !m {
                    (*s, *r, *u, *e, *l) = (0.0, 0.0, false, 0.0, 0.0);
                }
            });
        Zip::from(&mut g.beckmann)
            .and(&g.used)
            .par_for_each(|b, &u| *b &= u);
    }
    if let Some(rgb) = &mut albedo_rgb {
        Zip::from(rgb.rows_mut())
            .and(&mask)
            .par_for_each(|mut o, &m| {
                if !m {
                    o.fill(0.0);
                }
            });
    }
    Ok(Prepared {
        width: set.width,
        height: set.height,
        lights,
        estimated,
        condition,
        clamped,
        albedo,
        albedo_rgb,
        gloss,
        normals,
        mask,
        confidence,
        unreliable,
        solve_sums,
        estimate,
        mask_file: set.mask_file.clone(),
        notes: set.notes.clone(),
    })
}

/// The set's lights with their relative intensities estimated from the object (the
/// pre-pass's sampled pixels, [`robust::estimate_intensities`]).
fn estimated_lights(stack: &dyn Stack) -> Result<Vec<Light>, InputError> {
    let info = stack.info();
    let e = robust::estimate_intensities(&info.lights, info.bit_depth, stack.samples(), info.width)
        .ok_or_else(|| {
            InputError::Lights(
                "the lights' intensities cannot be estimated from this object: its lit pixels \
                 do not show normals of enough kinds to tell the lights apart (a plane, or \
                 too little of the object lit); give the intensities in the light table"
                    .into(),
            )
        })?;
    Ok((info.lights.iter().zip(&e))
        .map(|(l, &intensity)| Light {
            intensity,
            rgb: None,
            ..l.clone()
        })
        .collect())
}

/// The surface gradients integration starts from: of the heights (orthographic), or of
/// `ζ = −fx ln D` under a camera (`perspective::log_depth_gradients`), which the same
/// integrators integrate.
struct Slopes {
    p: Array2<f32>,
    q: Array2<f32>,
}

impl Slopes {
    fn of(surface: &Prepared, opts: &Options) -> Self {
        let (normals, mask) = (&surface.normals, &surface.mask);
        let (p, q) = match &opts.camera {
            None => integrate::gradients(normals, mask),
            Some(k) => perspective::log_depth_gradients(normals, mask, k),
        };
        Self { p, q }
    }

    /// Their curl, formed once the integration is done: during it, this map would add to
    /// the job's peak.
    fn curl(self, surface: &Prepared) -> Array2<f32> {
        integrate::curl(&self.p, &self.q, &surface.mask)
    }

    /// Heights, or depth along the optical axis under a camera (relative, or scaled to
    /// the working distance).
    fn integrate(&self, surface: &Prepared, opts: &Options, halt: Halt) -> Array2<f32> {
        let (slopes, mask) = ((&self.p, &self.q), &surface.mask);
        let (confidence, method) = (&surface.confidence, opts.integration);
        match &opts.camera {
            None => integrate::integrate_with_confidence(
                slopes.0, slopes.1, mask, method, confidence, halt,
            ),
            Some(k) => {
                let normals = &surface.normals;
                let c = Some(confidence);
                let given = integrate::Given {
                    slopes: Some(slopes),
                    start: None,
                };
                let z = integrate::integrate_log_depth(normals, mask, k, method, c, given, halt);
                perspective::depth_from_log(&z.zeta, mask, k, opts.distance)
            }
        }
    }
}

impl Prepared {
    /// The pictures' arrays before the heights (and the curl) exist.
    fn maps(&self) -> outputs::Maps<'_> {
        outputs::Maps {
            albedo: &self.albedo,
            albedo_rgb: self.albedo_rgb.as_ref(),
            normals: &self.normals,
            mask: &self.mask,
            curl: None,
            confidence: &self.confidence,
            unreliable: &self.unreliable,
            gloss: self.gloss.as_ref(),
            heights: None,
        }
    }

    /// The reconstruction and its report, once integrated.
    fn finish(
        self,
        curl: Array2<f32>,
        heights: Array2<f32>,
        opts: &Options,
        timings: Timings,
    ) -> Reconstruction {
        let sums = MaskSums::of(&self, &curl, &heights);
        let object = sums.object;
        let per_object = |v: f64| if object > 0 { v / object as f64 } else { 0.0 };
        let range = if object > 0 {
            (sums.low, sums.high)
        } else {
            (0.0, 0.0)
        };
        let (heights_range, depth_range) = match opts.camera {
            None => (Some(range), None),
            Some(_) => (None, Some(range)),
        };
        let warnings = robust::warnings(self.estimate.as_ref(), sums.unreliable, object);
        let report = Report {
            warnings,
            black_level: self.estimate.map(|e| e.black_level),
            noise_sigma: self.estimate.map(|e| e.noise_sigma),
            confidence_mean: per_object(sums.confidence),
            inliers_mean: per_object(self.solve_sums.inliers),
            unreliable_pixels: sums.unreliable,
            width: self.width,
            height: self.height,
            light_count: self.lights.len(),
            lights: self
                .lights
                .iter()
                .map(|l| LightSummary {
                    name: l.name.clone(),
                    direction: l.direction,
                    intensity: l.intensity,
                    intensity_rgb: l.rgb,
                })
                .collect(),
            options: opts.clone(),
            light_condition_number: self.condition,
            timings_ms: timings.0,
            height_min: heights_range.map(|r| r.0),
            height_max: heights_range.map(|r| r.1),
            depth_min: depth_range.map(|r| r.0),
            depth_max: depth_range.map(|r| r.1),
            integrability_rms: per_object(sums.curl2).sqrt(),
            reprojection_rms: per_object(self.solve_sums.residual2).sqrt(),
            clamped_albedo_pixels: self.clamped,
            background_pixels: self.mask.len() - object,
            object_pixels: object,
            artifacts: Vec::new(),
            mask_file: self.mask_file,
            glossy_pixels: (self.gloss.as_ref()).map(|g| g.used.iter().filter(|u| **u).count()),
            glossy_residual_rms: self.gloss.as_ref().and_then(|g| g.rms(&g.residual)),
            glossy_lambertian_rms: (self.gloss.as_ref())
                .and_then(|g| g.rms(&g.lambertian_residual)),
            glossy_material: self.gloss.as_ref().and_then(|g| g.material),
            holdout: None,
            estimated_intensities: self.estimated.then(|| {
                (self.lights.iter())
                    .map(|l| Estimated {
                        name: l.name.clone(),
                        intensity: l.intensity,
                    })
                    .collect()
            }),
            notes: self.notes,
        };
        Reconstruction {
            width: self.width,
            height: self.height,
            lights: self.lights,
            albedo: self.albedo,
            albedo_rgb: self.albedo_rgb,
            gloss: self.gloss,
            normals: self.normals,
            mask: self.mask,
            heights,
            curl,
            confidence: self.confidence,
            unreliable: self.unreliable,
            report,
        }
    }
}

/// The report's sums over the mask of the maps the integration leaves.
#[derive(Clone, Copy)]
struct MaskSums {
    object: usize,
    unreliable: usize,
    confidence: f64,
    curl2: f64,
    low: f32,
    high: f32,
}

impl MaskSums {
    const NONE: Self = Self {
        object: 0,
        unreliable: 0,
        confidence: 0.0,
        curl2: 0.0,
        low: f32::INFINITY,
        high: f32::NEG_INFINITY,
    };

    fn of(s: &Prepared, curl: &Array2<f32>, heights: &Array2<f32>) -> Self {
        let band = |r: Range<usize>| {
            let mut sums = Self::NONE;
            Zip::from(s.mask.slice(s![r.clone(), ..]))
                .and(heights.slice(s![r.clone(), ..]))
                .and(s.unreliable.slice(s![r.clone(), ..]))
                .and(s.confidence.slice(s![r.clone(), ..]))
                .and(curl.slice(s![r, ..]))
                .for_each(|&m, &z, &u, &c, &k| {
                    if m {
                        sums.object += 1;
                        sums.unreliable += usize::from(u);
                        sums.confidence += c as f64;
                        sums.curl2 += (k as f64).powi(2);
                        sums.low = sums.low.min(z);
                        sums.high = sums.high.max(z);
                    }
                });
            sums
        };
        by_bands(s.mask.nrows(), band, Self::NONE, |a, b| Self {
            object: a.object + b.object,
            unreliable: a.unreliable + b.unreliable,
            confidence: a.confidence + b.confidence,
            curl2: a.curl2 + b.curl2,
            low: a.low.min(b.low),
            high: a.high.max(b.high),
        })
    }
}

/// The report's sums over the mask of the solve's maps that are not kept.
#[derive(Clone, Copy)]
struct SolveSums {
    /// Of the inlier counts.
    inliers: f64,
    /// Of the squared per-pixel reprojection residuals.
    residual2: f64,
}

impl SolveSums {
    const NONE: Self = Self {
        inliers: 0.0,
        residual2: 0.0,
    };

    fn of(mask: &Array2<bool>, residual: &Array2<f32>, inliers: &Array2<u16>) -> Self {
        let band = |r: Range<usize>| {
            let mut sums = Self::NONE;
            Zip::from(mask.slice(s![r.clone(), ..]))
                .and(residual.slice(s![r.clone(), ..]))
                .and(inliers.slice(s![r, ..]))
                .for_each(|&m, &e, &k| {
                    if m {
                        sums.inliers += k as f64;
                        sums.residual2 += (e as f64).powi(2);
                    }
                });
            sums
        };
        by_bands(mask.nrows(), band, Self::NONE, |a, b| Self {
            inliers: a.inliers + b.inliers,
            residual2: a.residual2 + b.residual2,
        })
    }
}

/// `band` of each fixed band of rows, in parallel, then added in order, so that the sums
/// do not depend on how the bands were scheduled.
fn by_bands<S: Send>(
    rows: usize,
    band: impl Fn(Range<usize>) -> S + Sync,
    none: S,
    add: impl Fn(S, S) -> S,
) -> S {
    const BAND: usize = 64;
    let bands: Vec<S> = (0..rows.div_ceil(BAND))
        .into_par_iter()
        .map(|b| band(b * BAND..((b + 1) * BAND).min(rows)))
        .collect();
    bands.into_iter().fold(none, add)
}

/// Reconstruct and write every requested artifact into `dir` (each written under a
/// temporary name and renamed, `result.json` last). Returns the report. Takes the set by
/// value so that what it holds (a band per image, or a stack in memory) is freed right
/// after the solve.
///
/// The pictures that need no heights are written while the integration runs (both
/// stages start together); then the height pictures, the meshes and the preview go in
/// one parallel batch (the `mesh` stage).
pub fn run(
    mut stack: impl Stack + 'static,
    opts: &Options,
    dir: &Path,
    progress: &mut dyn Progress,
) -> Result<Report, RunError> {
    let camera = opts.camera.is_some();
    let wanted = |name: &str| outputs::wanted(opts.outputs.as_deref(), name, camera);
    let (late, early): (Vec<&str>, Vec<&str>) = outputs::ARTIFACTS
        .iter()
        .map(|(n, _)| *n)
        .filter(|n| n.ends_with(".png") || n.ends_with(".exr"))
        .filter(|n| *n != "preview.png" && wanted(n))
        .partition(|n| outputs::after_integration(n));

    let mut timings = Timings::default();
    // Before the job's own solve, so that one fold's maps at a time are held beside the
    // stack, never beside the job's.
    let holdout = if opts.holdout_lights {
        step(progress, Stage::Solve)?;
        let polled: &dyn Progress = progress;
        let score = timings.time(Stage::Holdout, || {
            holdout::holdout(&mut stack, opts, &|| polled.halted())
        })?;
        not_halted(polled)?;
        Some(score)
    } else {
        None
    };
    let surface = prepare(&mut stack, opts, progress, &mut timings)?;
    drop_aside(stack);
    let commits = Committer::new();
    std::fs::create_dir_all(dir).map_err(|e| RunError::Output {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })?;
    // Both stages start with the gradients: integration starts from them, and curl.png
    // shows their curl. Progress reports the overlap as `integrate`, the branch the job
    // waits for; the pictures written alongside it get their own timing below.
    step(progress, Stage::Integrate)?;
    let polled: &dyn Progress = progress;
    let halt = || polled.halted();
    let start = Instant::now();
    let slopes = Slopes::of(&surface, opts);
    // The integration is the job's peak: what the solve left in the allocator's arenas
    // would add to it.
    heap::release_free_heap();
    let (heights, pictures) = rayon::join(
        || {
            let heights = slopes.integrate(&surface, opts, &halt);
            (heights, Timing::new(Stage::Integrate, start))
        },
        || {
            let maps = surface.maps();
            let light = opts.shading_light;
            let written = outputs::write_pictures(&maps, &early, light, dir, &commits, &halt);
            (written, Timing::new(Stage::Outputs, start))
        },
    );
    timings.0.extend([heights.1, pictures.1]);
    let mut written = pictures.0?;
    not_halted(polled)?;
    let curl = slopes.curl(&surface);
    let mut rec = surface.finish(curl, heights.0, opts, timings);

    step(progress, Stage::Mesh)?;
    let polled: &dyn Progress = progress;
    let halt = || polled.halted();
    let start = Instant::now();
    let (pictures, meshes) = rayon::join(
        || {
            let maps = Maps::of(&rec);
            outputs::write_pictures(&maps, &late, opts.shading_light, dir, &commits, &halt)
        },
        || write_meshes(&rec, opts, dir, &wanted, &commits, &halt),
    );
    written.extend(pictures?.into_iter().chain(meshes?));
    not_halted(polled)?;
    rec.report.timings_ms.push(Timing::new(Stage::Mesh, start));

    if rec.report.estimated_intensities.is_some() {
        let table = lights::to_json(&rec.lights);
        commits.write(dir, "lights.json", &mut |f| f.write_all(&table))?;
        written.push("lights.json".into());
    }
    // In the order of ARTIFACTS, whichever batch wrote them.
    written.sort_by_key(|n| outputs::ARTIFACTS.iter().position(|(a, _)| a == n));
    written.push("result.json".into());
    rec.report.artifacts = written;
    rec.report.holdout = holdout;
    let json = serde_json::to_vec_pretty(&rec.report).expect("the report serialises");
    // Every artifact is durable and in place before the report that lists them.
    commits.finish()?;
    commit::write_atomic(dir, "result.json", &json)?;
    let report = std::mem::take(&mut rec.report);
    drop_aside(rec);
    Ok(report)
}

/// Free big buffers on a short-lived thread of their own: returning 200 MB of pages to
/// the kernel costs tens of milliseconds that the job need not wait for (the profile
/// showed it on the critical path twice: the image stack after the solve, the maps at
/// the end). Not on the rayon pool, whose busy workers could hold the memory for the
/// rest of the job. If no thread can be started, the value is dropped here.
fn drop_aside<T: Send + 'static>(value: T) {
    let _ = std::thread::Builder::new()
        .name("drop-aside".into())
        .spawn(move || drop(value));
}

/// The glTF files, the point cloud and the preview picture. A mask too small to
/// triangulate gives no mesh (and says so in the log of the caller) rather than failing
/// the whole job. One glTF document serves both mesh files; it, the point cloud and the
/// preview are built in parallel. Under a camera the vertices and points are unprojected
/// through it.
fn write_meshes(
    rec: &Reconstruction,
    opts: &Options,
    dir: &Path,
    wanted: &(dyn Fn(&str) -> bool + Sync),
    commits: &Committer,
    halt: Halt,
) -> Result<Vec<String>, RunError> {
    use super::commit::WriteSeek;
    use super::mesh::{self, Document, MeshError};
    let save = |name: &str, made: Result<Vec<u8>, MeshError>| match made {
        Ok(bytes) => {
            (commits.write(dir, name, &mut |f| f.write_all(&bytes))).map(|_| Some(name.to_string()))
        }
        Err(MeshError::EmptyMask | MeshError::NoTriangles { .. }) => Ok(None),
        Err(e @ (MeshError::Options(_) | MeshError::TooLarge { .. })) => {
            Err(InputError::Options(e.to_string()).into())
        }
        Err(e) => Err(RunError::Output {
            path: dir.join(name).display().to_string(),
            reason: e.to_string(),
        }),
    };
    // Each mesh file is streamed from the one document into its file; mesh errors that
    // are not I/O keep their kind for `save`'s mapping.
    let stream = |name: &str, write: &dyn Fn(&mut dyn Write) -> Result<(), MeshError>| {
        let mut failed = None;
        let written = commits.write(dir, name, &mut |out| {
            write(out).map_err(|e| match e {
                MeshError::Write(io) => io,
                other => {
                    let io = std::io::Error::other(other.to_string());
                    failed = Some(other);
                    io
                }
            })
        });
        match failed {
            Some(e) => save(name, Err(e)),
            None => written.map(|_| Some(name.to_string())),
        }
    };
    let (glb, gltf) = (
        wanted("mesh.glb") && !halt(),
        wanted("mesh.gltf") && !halt(),
    );
    let points = || {
        (wanted("points.ply") && !halt()).then(|| {
            let (z, normals, mask) = (&rec.heights, &rec.normals, &rec.mask);
            let write = &mut |f: &mut dyn WriteSeek| {
                mesh::write_points_ply(f, z, normals, mask, rec.camera())
            };
            (commits.write(dir, "points.ply", write)).map(|()| Some("points.ply".to_string()))
        })
    };
    let (meshes, (preview, points)) = rayon::join(
        || -> Vec<Result<Option<String>, RunError>> {
            if !(glb || gltf) {
                return Vec::new();
            }
            let doc = match Document::with_camera(rec, &opts.mesh, rec.camera()) {
                Ok(doc) => doc,
                Err(e) => return vec![save(if glb { "mesh.glb" } else { "mesh.gltf" }, Err(e))],
            };
            let (a, b) = rayon::join(
                || glb.then(|| stream("mesh.glb", &|out| doc.write_glb(out))),
                || gltf.then(|| stream("mesh.gltf", &|out| doc.write_gltf(out))),
            );
            a.into_iter().chain(b).collect()
        },
        || {
            let preview = || {
                (wanted("preview.png") && !halt()).then(|| {
                    let img = super::preview::preview(rec, PREVIEW_SIZE.0, PREVIEW_SIZE.1);
                    save("preview.png", Ok(outputs::png_bytes(&img)))
                })
            };
            rayon::join(preview, points)
        },
    );
    let mut written = Vec::new();
    for r in meshes.into_iter().chain(preview).chain(points) {
        written.extend(r?);
    }
    Ok(written)
}

/// Size of `preview.png`.
pub const PREVIEW_SIZE: (u32, u32) = (800, 600);

pub(super) fn step(progress: &mut dyn Progress, stage: Stage) -> Result<(), RunError> {
    if progress.enter(stage) {
        Ok(())
    } else {
        Err(RunError::Cancelled)
    }
}

/// After work that polled `halted` and may have cut itself short: its results are only
/// kept when the run was not stopped meanwhile.
pub(super) fn not_halted(progress: &dyn Progress) -> Result<(), RunError> {
    if progress.halted() {
        Err(RunError::Cancelled)
    } else {
        Ok(())
    }
}

#[derive(Default)]
struct Timings(Vec<Timing>);

impl Timings {
    fn time<T>(&mut self, stage: Stage, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let out = f();
        self.0.push(Timing::new(stage, start));
        out
    }
}
