//! A job run: a worker thread claims the next job and runs it.
//!
//! The queue is the repo's: `--workers` plain threads each claim the next queued job
//! (tenants take turns, see [`Queue::claim`](super::repo::Queue::claim)), so never
//! more than that many run here at once. A claim is a lease: the background heartbeat
//! extends the leases of the jobs held here, and learns there of jobs cancelled on
//! another instance or lost (reaped after their lease ran out). Idle workers wait for the
//! bell (a submission here, a requeue, another instance's announcement) or a short poll.
//!
//! Each job's inputs are fetched into local scratch, opened with `stream::open_with`
//! (each image decoded once into a scratch file beside them, read back band by band) and
//! run by `pipeline::run` into a staged output directory that the store commits when the
//! job succeeds, under a key of this attempt's own; a normals job's map is decoded by
//! `normalmap::decode` and integrated by `normals_in::run` in its place; a job whose
//! light table gives positions (near lights) is opened the same way and run by
//! `near::run`. Every write about the job carries the lease's token, so a worker that lost its lease records nothing. A
//! store that does not answer makes the job wait and run again, never fail. Progress goes
//! to the repo at every stage; the progress callback is also where cancellation, the time
//! limit, shutdown and a lost lease stop a job.

use std::collections::HashMap;
use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use uuid::Uuid;

use crate::core::bands::Stack;
use crate::core::camera::Pinhole;
use crate::core::error::RunError;
use crate::core::error::panic_message;
use crate::core::intake::{Limits, NamedFile};
use crate::core::lights;
use crate::core::near::{self, NearReport};
use crate::core::normalmap::{self, Lens, MaskInput, NormalMap};
use crate::core::normals_in;
use crate::core::outputs::ARTIFACTS;
use crate::core::pipeline;
use crate::core::progress::{Progress, Stage};
use crate::core::stream::{self, Prescanned, Streamed};
use crate::core::{InputError, Options};
use crate::service::budget::{self, Reservation, Use};
use crate::service::repo::{ArtifactInfo, Finish, JobStatus, Lease, RepoResult};
use crate::service::store::{
    self, LIGHTS_FILE, MANIFEST_FILE, Manifest, ManifestEntry, NormalsEntry,
};
use crate::service::util::{crc32_file, format_duration, now_ms, strong_etag};

use super::failure::Failure;
use super::pool::{RunControl, lock};
use super::prefetch::Prefetch;
use super::runner::Runner;
use super::webhooks;

/// The pipeline's stages in order; progress is the index of the stage reached over
/// their number.
pub const STAGES: [Stage; 6] = [
    Stage::Decode,
    Stage::Solve,
    Stage::Mask,
    Stage::Integrate,
    Stage::Outputs,
    Stage::Mesh,
];

/// How long an idle worker waits before it looks at the queue again unrung: the fallback
/// should an announcement from another instance be missed.
const POLL: Duration = Duration::from_secs(2);

/// A worker thread: claim and run jobs until the pool closes.
pub(super) fn worker_loop(runner: Arc<Runner>) {
    let pool = &runner.pool;
    while !pool.is_closed() {
        let seen = pool.rung();
        if let Ok(0) = runner.repo.queued() {
            pool.wait_for_ring(seen, POLL);
            continue;
        }
        // Room in the memory budget for the largest job a worker may claim, before it
        // claims one: until it fits, the job stays queued.
        let worst = budget::job_worst_bytes(&runner.config);
        let closed = || pool.is_closed();
        let Some(mut memory) = runner.budget.reserve_blocking(Use::Job, worst, closed) else {
            continue;
        };
        // Busy from the claim on, so that a shutdown waits for a job claimed meanwhile.
        pool.busy.fetch_add(1, Ordering::SeqCst);
        let claimed = runner
            .repo
            .claim(&runner.owner, runner.config.job_lease, now_ms());
        if let Ok(Some(lease)) = claimed {
            process(&runner, lease, &mut memory);
        }
        pool.busy.fetch_sub(1, Ordering::SeqCst);
        if let Ok(Some(_)) = claimed {
            crate::core::heap::release_free_heap();
        }
        drop(memory);
        match claimed {
            Ok(Some(_)) => {}
            Ok(None) => pool.wait_for_ring(seen, POLL),
            Err(e) => {
                tracing::warn!(error = %e, "cannot claim a job; trying again");
                wait_unless_closing(&runner, STORE_RETRY);
            }
        }
    }
}

/// How long a job waits before it is queued again when the store or the job database
/// does not answer.
const STORE_RETRY: Duration = Duration::from_secs(2);

/// Sleep for `wait`, or less if the service starts to stop.
fn wait_unless_closing(runner: &Runner, wait: Duration) {
    let until = Instant::now() + wait;
    while Instant::now() < until && !runner.pool.is_closed() {
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Run a repo write, again and again while the database does not answer, so that a job's
/// outcome is recorded once it does; at shutdown the last error stands (the job is then
/// still "running" in the database and runs again at the next start).
fn persist<T>(runner: &Runner, write: impl Fn() -> RepoResult<T>) -> RepoResult<T> {
    loop {
        match write() {
            Err(e) if e.is_unavailable() && !runner.pool.is_closed() => {
                tracing::warn!(error = %e, "the job database does not answer; recording again");
                wait_unless_closing(runner, STORE_RETRY);
            }
            other => return other,
        }
    }
}

/// Why a job stopped without a result.
enum Stop {
    /// The progress callback said stop (cancel, interrupt or time limit).
    Stopped,
    /// The store did not answer: the job goes back to the queue.
    StoreUnavailable(String),
    Error(Failure),
}

/// A store error: unavailable (the job waits) or the job's failure.
fn store_error(e: store::Error, doing: &str) -> Stop {
    if e.is_unavailable() {
        Stop::StoreUnavailable(format!("{doing}: {e}"))
    } else {
        Failure::Internal(format!("{doing}: {e}")).into()
    }
}

impl From<Failure> for Stop {
    fn from(e: Failure) -> Self {
        Stop::Error(e)
    }
}

fn process(runner: &Runner, lease: Lease, memory: &mut Reservation) {
    let id = lease.id;
    // Registered before anything else, so that a DELETE or a heartbeat finds it.
    let ctl = runner.pool.register(lease);
    if runner.pool.is_closed() {
        // Claimed as the service began to stop: back to the queue at once.
        ctl.interrupt.store(true, Ordering::SeqCst);
    }
    let running = runner.pool.begin_running();
    let started = Instant::now();
    let span = tracing::info_span!("job", job = %id);
    let _enter = span.enter();
    tracing::info!("job started");

    // A fresh id per attempt keys its outputs, so attempts never write over each other.
    let attempt = Uuid::new_v4().simple().to_string();
    let mut clock = StageClock {
        runner,
        lease,
        ctl: &ctl,
        deadline: started + runner.config.job_timeout,
        current: None,
        timed_out: AtomicBool::new(false),
    };
    let outcome = std::panic::catch_unwind(AssertUnwindSafe(|| {
        execute(runner, id, &attempt, &mut clock, memory)
    }))
    .unwrap_or_else(|panic| {
        let what = panic_message(&*panic);
        tracing::error!(panic = %what, "the reconstruction panicked");
        Err(Stop::Error(Failure::Failed(
            "internal error: the reconstruction crashed; see the server logs".into(),
        )))
    });
    clock.close();
    let timed_out = clock.timed_out.load(Ordering::SeqCst);
    settle(
        runner,
        lease,
        &attempt,
        &ctl,
        outcome,
        timed_out,
        started.elapsed(),
    );
    drop(running);
    runner.pool.unregister(id);
}

/// Record how the job ended and tidy its files.
fn settle(
    runner: &Runner,
    lease: Lease,
    attempt: &str,
    ctl: &RunControl,
    outcome: Result<(serde_json::Value, Vec<ArtifactInfo>), Stop>,
    timed_out: bool,
    elapsed: Duration,
) {
    let id = lease.id;
    runner.prefetch.discard(id); // if the job stopped before taking it
    let instance = format!("/v1/jobs/{id}");
    let now = now_ms();
    let recorded = match outcome {
        Err(_) if ctl.lost.load(Ordering::SeqCst) => {
            tracing::warn!("the job's lease ran out; another worker runs it");
            Ok(None)
        }
        Ok((result, artifacts)) => {
            let done = Finish::Succeeded { result, artifacts };
            persist(runner, || runner.repo.finish(lease, &done, now))
                .map(|ok| ok.then_some(JobStatus::Succeeded))
        }
        Err(Stop::Stopped) if ctl.interrupt.load(Ordering::SeqCst) => {
            tracing::info!("job interrupted by shutdown; it runs again");
            persist(runner, || runner.repo.requeue(lease)).map(|_| None)
        }
        Err(Stop::Stopped) if timed_out && !ctl.cancel.load(Ordering::SeqCst) => {
            let e = Failure::TimedOut(format!(
                "the reconstruction did not finish within the job time limit of {}",
                format_duration(runner.config.job_timeout)
            ));
            let failed = Finish::Failed(runner.problem(e, &instance));
            persist(runner, || runner.repo.finish(lease, &failed, now))
                .map(|ok| ok.then_some(JobStatus::Failed))
        }
        Err(Stop::Stopped) => Ok(Some(JobStatus::Cancelled)), // the DELETE recorded it
        Err(Stop::StoreUnavailable(why)) => {
            tracing::warn!(error = %why, "the store does not answer; the job runs again");
            let until = Instant::now() + STORE_RETRY;
            while Instant::now() < until
                && !ctl.cancel.load(Ordering::SeqCst)
                && !ctl.interrupt.load(Ordering::SeqCst)
                && !ctl.lost.load(Ordering::SeqCst)
            {
                std::thread::sleep(Duration::from_millis(20));
            }
            persist(runner, || runner.repo.requeue(lease)).map(|requeued| {
                if requeued {
                    runner.pool.ring();
                }
                None
            })
        }
        Err(Stop::Error(e)) => {
            let problem = runner.problem(e, &instance);
            tracing::info!(
                status = problem.status,
                detail = problem.detail.as_str(),
                "job failed"
            );
            let failed = Finish::Failed(problem);
            persist(runner, || runner.repo.finish(lease, &failed, now))
                .map(|ok| ok.then_some(JobStatus::Failed))
        }
    };
    // Only this attempt's own success keeps its outputs.
    let ours = matches!(recorded, Ok(Some(JobStatus::Succeeded)));
    match recorded {
        Ok(Some(status)) => {
            tracing::info!(
                status = status.as_str(),
                seconds = elapsed.as_secs_f64(),
                "job finished"
            );
            runner.metrics.observe_finished(status, elapsed);
            webhooks::job_ended(runner, id);
        }
        Ok(None) => {}
        Err(e) => tracing::error!(error = %e, "cannot record the job's outcome"),
    }
    // Whatever the repo now says decides which files stay.
    let tidy = match runner.repo.get(id) {
        Ok(None) => runner.store.remove_job(id),
        Ok(Some(rec)) if rec.status == JobStatus::Succeeded && ours => {
            runner.store.remove_inputs(id)
        }
        Ok(Some(rec)) if rec.status.is_terminal() => runner
            .store
            .remove_inputs(id)
            .and_then(|_| runner.store.discard_outputs(id, attempt)),
        Ok(Some(_)) => runner.store.discard_outputs(id, attempt),
        Err(e) => {
            tracing::error!(error = %e, "cannot read the job back");
            Ok(())
        }
    };
    if let Err(e) = tidy {
        tracing::warn!(error = %e, "cannot tidy the job's files");
    }
}

/// Times stages, records progress, and decides whether to go on.
struct StageClock<'a> {
    runner: &'a Runner,
    lease: Lease,
    ctl: &'a RunControl,
    deadline: Instant,
    current: Option<(Stage, Instant)>,
    /// Set by whichever thread first sees the deadline passed.
    timed_out: AtomicBool,
}

impl StageClock<'_> {
    fn should_stop(&self) -> bool {
        if Instant::now() >= self.deadline {
            self.timed_out.store(true, Ordering::SeqCst);
            return true;
        }
        [&self.ctl.cancel, &self.ctl.interrupt, &self.ctl.lost]
            .iter()
            .any(|flag| flag.load(Ordering::SeqCst))
    }

    fn close(&mut self) {
        if let Some((stage, at)) = self.current.take() {
            self.runner
                .metrics
                .observe_stage(stage.as_str(), at.elapsed());
        }
    }
}

impl Progress for StageClock<'_> {
    /// A stage starts: false means stop.
    fn enter(&mut self, stage: Stage) -> bool {
        if self.current.map(|(s, _)| s) == Some(stage) {
            return !self.should_stop(); // the pipeline re-announced the stage we report
        }
        self.close();
        if self.should_stop() {
            return false;
        }
        let index = STAGES.iter().position(|s| *s == stage).unwrap_or(0);
        let progress = index as f64 / STAGES.len() as f64;
        // A refusal (the lease is gone) is left to the next heartbeat to tell apart.
        if let Err(e) = self
            .runner
            .repo
            .progress(self.lease, stage.as_str(), progress, now_ms())
        {
            tracing::warn!(error = %e, "cannot record progress");
        }
        tracing::debug!(stage = stage.as_str(), "stage");
        self.current = Some((stage, Instant::now()));
        let delay = self.runner.config.stage_delay;
        if !delay.is_zero() {
            let until = Instant::now() + delay;
            while Instant::now() < until && !self.should_stop() {
                std::thread::sleep(Duration::from_millis(5).min(delay));
            }
        }
        !self.should_stop()
    }

    /// Polled inside the long stages, from the pool's threads.
    fn halted(&self) -> bool {
        self.should_stop()
    }
}

/// Load the job's inputs and reconstruct; on success the outputs are committed.
fn execute(
    runner: &Runner,
    id: Uuid,
    attempt: &str,
    clock: &mut StageClock<'_>,
    memory: &mut Reservation,
) -> Result<(serde_json::Value, Vec<ArtifactInfo>), Stop> {
    let record = runner
        .repo
        .get(id)
        .map_err(Failure::from)?
        .ok_or(Stop::Stopped)?;
    let options: Options = serde_json::from_value(record.options)
        .map_err(|e| Failure::Invalid(format!("options: {e}")))?;
    // The images the upload already decoded on this instance need not be fetched again.
    // Waits for scans still running (on rayon: this is a worker thread, not a pool one).
    let scanned = runner
        .prefetch
        .take(id)
        .map(Prefetch::finish)
        .unwrap_or_default();
    let input = runner
        .store
        .fetch_inputs(id, &|name| scanned.contains_key(name))
        .map_err(|e| store_error(e, "fetching the job's inputs"))?;
    let manifest: Manifest = std::fs::read(input.join(MANIFEST_FILE))
        .map_err(Failure::from)
        .and_then(|b| {
            serde_json::from_slice(&b)
                .map_err(|e| Failure::Internal(format!("manifest of {id}: {e}")))
        })?;

    if !clock.enter(Stage::Decode) {
        return Err(Stop::Stopped);
    }
    let out = runner.store.stage_outputs(id).map_err(Failure::from)?;
    let summary = match &manifest.normals {
        Some(map) => {
            let limits = runner.config.limits();
            let map = read_normal_map(&input, map, manifest.mask.as_ref(), &options, &limits)?;
            memory.shrink_to(normals_in::peak_bytes((map.width * map.height) as u64));
            let settings = normals_in::Settings::of(&options);
            let report = normals_in::run(map, &settings, &out, clock);
            summarize(&finished(report, clock)?)
        }
        None => {
            let table = std::fs::read(input.join(LIGHTS_FILE)).map_err(Failure::from)?;
            let table = lights::parse_table_bytes(&table).map_err(Failure::from)?;
            let near = table.is_near().then(|| table.rig.clone());
            let set = open_inputs(runner, scanned, table.lights, &input, &manifest, clock)?;
            let set = set.noted(manifest.notes.clone());
            // The images' size and the job's kind are known now: keep the job's own bound.
            let pixels = (set.info().width * set.info().height) as u64;
            memory.shrink_to(match near {
                Some(_) => near::peak_bytes(pixels),
                None => pipeline::peak_bytes(pixels, options.solver),
            });
            if let Some(rig) = near {
                let report = run_near(set, rig, &options, &out, clock);
                return commit(runner, id, attempt, &out, summarize_near(&report?));
            }
            let report = pipeline::run(set, &options, &out, clock);
            summarize(&finished(report, clock)?)
        }
    };
    commit(runner, id, attempt, &out, summary)
}

/// The staged outputs in `out` made the job's artifacts; the job's result.
fn commit(
    runner: &Runner,
    id: Uuid,
    attempt: &str,
    out: &Path,
    summary: serde_json::Value,
) -> Result<(serde_json::Value, Vec<ArtifactInfo>), Stop> {
    let mut artifacts = list_artifacts(out).map_err(Failure::from)?;
    runner
        .store
        .commit_outputs(id, attempt, &mut artifacts)
        .map_err(|e| store_error(e, "committing the outputs"))?;
    Ok((summary, artifacts))
}

/// A near-light job (its table gives positions): `near::run` on the job's images, read
/// in bands as a distant job's are, under the camera and working distance the upload
/// checked (the job's, else the table's).
fn run_near(
    mut set: Streamed,
    rig: lights::Rig,
    options: &Options,
    out: &Path,
    clock: &mut StageClock<'_>,
) -> Result<NearReport, Stop> {
    let (width, height) = (set.info().width, set.info().height);
    let (camera, distance) =
        near_rig(options, &rig, &set.info().lights, (width, height)).map_err(Failure::from)?;
    let report = near::run(&mut set, camera, distance, rig.unit, options, out, clock);
    finished(report, clock)
}

/// A run's report, once its last stage is timed; a stopped run is [`Stop::Stopped`].
fn finished<R>(report: Result<R, RunError>, clock: &mut StageClock<'_>) -> Result<R, Stop> {
    clock.close();
    match report {
        Ok(r) => Ok(r),
        Err(RunError::Cancelled) => Err(Stop::Stopped),
        Err(e) => Err(Failure::from(e).into()),
    }
}

/// A normals job's map (and mask) decoded under the job's camera and the server's pixel
/// limit (which may be lower than when the job was accepted): a 422 naming the problem
/// when it holds no usable normals, a 413 over the limit.
fn read_normal_map(
    input: &Path,
    map: &NormalsEntry,
    mask: Option<&ManifestEntry>,
    options: &Options,
    limits: &Limits,
) -> Result<NormalMap, Failure> {
    let bytes = std::fs::read(input.join(&map.file))?;
    let mask_bytes = match mask {
        Some(m) => Some(std::fs::read(input.join(&m.file))?),
        None => None,
    };
    let mask = mask.zip(mask_bytes.as_deref()).map(|(m, bytes)| MaskInput {
        name: &m.name,
        bytes,
    });
    let lens = options.camera.map(Lens::Pinhole);
    Ok(normalmap::decode(
        &map.name,
        &bytes,
        mask,
        map.convention,
        lens,
        limits,
    )?)
}

/// The first pass over the job's images, taking those the upload scanned (`scanned`, by
/// file name) when there are any; the solve reads the bands back from their scratch
/// copies. Once `clock` says stop, the images not yet started are not scanned and the set,
/// which then holds a placeholder error for them, is dropped.
fn open_inputs(
    runner: &Runner,
    scanned: HashMap<String, Prescanned>,
    lights: Vec<lights::Light>,
    input: &Path,
    manifest: &Manifest,
    clock: &StageClock<'_>,
) -> Result<Streamed, Stop> {
    let files: Vec<NamedFile> = manifest
        .images
        .iter()
        .map(|e| NamedFile {
            name: e.name.clone(),
            path: input.join(&e.file),
        })
        .collect();
    let mask = manifest.mask.as_ref().map(|m| NamedFile {
        name: m.name.clone(),
        path: input.join(&m.file),
    });
    let ready = Mutex::new(scanned);
    let taken = AtomicUsize::new(0);
    // The decoded images go beside the (fetched) inputs, as the upload's scans put them.
    let set = stream::open_with(
        lights,
        &files,
        mask.as_ref(),
        &runner.config.limits(),
        input,
        |i| {
            if clock.halted() {
                return Some(Err(InputError::Decode {
                    name: files[i].name.clone(),
                    reason: "not decoded: the job was stopped".into(),
                }));
            }
            let found = lock(&ready).remove(&manifest.images[i].file)?;
            taken.fetch_add(1, Ordering::Relaxed);
            Some(Ok(found))
        },
    );
    if clock.halted() {
        return Err(Stop::Stopped);
    }
    let taken = taken.into_inner() as u64;
    runner
        .metrics
        .prefetched_images
        .fetch_add(taken, Ordering::Relaxed);
    tracing::debug!(images = taken, "images scanned during the upload");
    Ok(set.map_err(Failure::from)?)
}

/// Every artifact that exists in `dir`, with its size and a content-hash ETag. The files
/// are hashed in parallel: at 2048² they are ~120 MB, read back from the page cache.
fn list_artifacts(dir: &std::path::Path) -> std::io::Result<Vec<ArtifactInfo>> {
    use rayon::prelude::*;
    let found: Vec<Option<ArtifactInfo>> = ARTIFACTS
        .par_iter()
        .map(|(name, _)| {
            let path = dir.join(name);
            match std::fs::metadata(&path) {
                Ok(meta) if meta.is_file() => Ok(Some(ArtifactInfo {
                    name: name.to_string(),
                    bytes: meta.len(),
                    etag: strong_etag(crc32_file(&path)?, meta.len()),
                    key: None,
                })),
                _ => Ok(None),
            }
        })
        .collect::<std::io::Result<_>>()?;
    Ok(found.into_iter().flatten().collect())
}

/// A near-light job's headline numbers: [`summarize`]'s, that it was one (`lights`:
/// `near`), the number of iterations, whether they converged, the median depth and unit.
fn summarize_near(report: &NearReport) -> serde_json::Value {
    let mut out = summarize(report);
    if let serde_json::Value::Object(fields) = &mut out {
        let more = [
            ("lights", serde_json::json!(report.lights)),
            ("iterations", serde_json::json!(report.iterations.len())),
            ("converged", serde_json::json!(report.converged)),
            ("median_depth", serde_json::json!(report.median_depth)),
            ("unit", serde_json::json!(report.unit)),
        ];
        for (key, value) in more {
            fields.insert(key.to_string(), value);
        }
    }
    out
}

/// The report's headline numbers (as in `result.json`).
fn summarize(report: &impl serde::Serialize) -> serde_json::Value {
    const KEYS: [&str; 24] = [
        "width",
        "height",
        "light_count",
        "light_condition_number",
        "height_min",
        "height_max",
        "depth_min",
        "depth_max",
        "integrability_rms",
        "reprojection_rms",
        "object_pixels",
        "background_pixels",
        "clamped_albedo_pixels",
        "confidence_mean",
        "inliers_mean",
        "unreliable_pixels",
        "black_level",
        "noise_sigma",
        "counts",
        "estimated_intensities",
        "glossy_pixels",
        "glossy_residual_rms",
        "glossy_lambertian_rms",
        "glossy_material",
    ];
    let full = serde_json::to_value(report).unwrap_or_default();
    let mut out = serde_json::Map::new();
    for key in KEYS {
        if let Some(v) = full.get(key) {
            out.insert(key.to_string(), v.clone());
        }
    }
    serde_json::Value::Object(out)
}

/// The camera and working distance of a near-light job: the job's (`camera` part or
/// option, `distance` option) or else its light table's; a 422 naming what neither gives,
/// a camera that cannot have taken the `width × height` images, or an LED of `lights`
/// facing away from the object.
pub(crate) fn near_rig(
    options: &Options,
    rig: &lights::Rig,
    lights: &[lights::Light],
    (width, height): (usize, usize),
) -> Result<(Pinhole, f64), InputError> {
    let camera = options.camera.or(rig.camera);
    let distance = options.distance.or(rig.distance);
    let mut missing = Vec::new();
    if camera.is_none() {
        missing.push(
            "the camera (\"camera\": {\"fx\", \"fy\", \"cx\", \"cy\"} in the light table, or the job's camera part or `camera` option)",
        );
    }
    if distance.is_none() {
        missing.push(
            "the working distance to the object along the optical axis (\"distance\" in the light table, or the job's `distance` option)",
        );
    }
    let (Some(camera), Some(distance)) = (camera, distance) else {
        return Err(InputError::Lights(format!(
            "lights given by position (near lights) need {}",
            missing.join(" and ")
        )));
    };
    camera.check(width, height).map_err(InputError::from)?;
    crate::core::options::check_distance(Some(distance), Some(&camera))?;
    crate::core::near::check_cones(lights, &camera, distance, (width, height))?;
    Ok((camera, distance))
}
