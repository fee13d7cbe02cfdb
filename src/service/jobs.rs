//! The job queue and the worker pool.
//!
//! Accepted jobs wait in a bounded in-memory queue (its length is `--queue-length`; the
//! repo is the durable copy), one line per tenant: workers serve the tenants with waiting
//! jobs in turn (round-robin), so one tenant's backlog does not hold up another's next
//! job. `--workers` plain threads take jobs from it, so never more
//! than that many run at once; each fetches its stored inputs into local scratch, opens
//! them with `stream::open_with` (each image decoded once into a scratch file beside
//! them, read back band by band) and runs `pipeline::run` into a staged output directory
//! that the store commits when the job succeeds, under a key of this attempt's own. A
//! store that does not answer makes the job wait and run again, never fail. Progress goes to the
//! repo at every stage; the progress callback is also where cancellation, the time limit
//! and shutdown stop a job.

use std::collections::{HashMap, VecDeque};
use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use uuid::Uuid;

use crate::core::RunError;
use crate::core::error::panic_message;
use crate::core::intake::NamedFile;
use crate::core::lights;
use crate::core::outputs::ARTIFACTS;
use crate::core::pipeline;
use crate::core::progress::{Progress, Stage};
use crate::core::reconstruction::Report;
use crate::core::stream::{self, Streamed};
use crate::core::{InputError, Options};

use super::Inner;
use super::blobs::{LIGHTS_FILE, MANIFEST_FILE, Manifest, is_unavailable};
use super::error::ApiError;
use super::prefetch::Prefetch;
use super::repo::{ArtifactInfo, Finish, JobStatus, RepoResult};
use super::util::{crc32_file, format_duration, now_ms, strong_etag};

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

/// What a running job's worker watches for.
#[derive(Default)]
pub struct RunControl {
    /// A `DELETE` cancelled the job.
    cancel: AtomicBool,
    /// The service is stopping: stop and run the job again at the next start.
    interrupt: AtomicBool,
}

struct QueueState {
    /// Waiting jobs by tenant, each line oldest first.
    lines: HashMap<String, VecDeque<Uuid>>,
    /// The tenants with waiting jobs, in the order they are served next.
    turns: VecDeque<String>,
    /// Waiting jobs, all lines together.
    len: usize,
    closed: bool,
}

impl QueueState {
    fn push(&mut self, id: Uuid, tenant: &str) {
        match self.lines.get_mut(tenant) {
            Some(line) => line.push_back(id),
            None => {
                self.lines.insert(tenant.to_string(), VecDeque::from([id]));
                self.turns.push_back(tenant.to_string());
            }
        }
        self.len += 1;
    }

    /// The next tenant's oldest job, and the tenant, who goes to the back of the turns.
    fn pop(&mut self) -> Option<(Uuid, String)> {
        let tenant = self.turns.pop_front()?;
        let line = self.lines.get_mut(&tenant)?;
        let id = line.pop_front();
        if line.is_empty() {
            self.lines.remove(&tenant);
        } else {
            self.turns.push_back(tenant.clone());
        }
        self.len -= usize::from(id.is_some());
        Some((id?, tenant))
    }

    fn remove(&mut self, id: Uuid) -> bool {
        let Some(tenant) = self
            .lines
            .iter()
            .find(|(_, line)| line.contains(&id))
            .map(|(t, _)| t.clone())
        else {
            return false;
        };
        let line = self.lines.get_mut(&tenant).expect("found above");
        line.retain(|j| *j != id);
        if line.is_empty() {
            self.lines.remove(&tenant);
            self.turns.retain(|t| *t != tenant);
        }
        self.len -= 1;
        true
    }
}

/// Why a job could not be queued.
#[derive(Debug, PartialEq, Eq)]
pub enum PushError {
    Full,
    Closed,
}

/// The bounded queue, the running set and the pool's counters.
pub struct JobQueue {
    state: Mutex<QueueState>,
    ready: Condvar,
    limit: usize,
    running: Mutex<HashMap<Uuid, Arc<RunControl>>>,
    running_now: AtomicUsize,
    running_max: AtomicUsize,
    /// Workers holding a job (from taking it off the queue until done with it).
    busy: AtomicUsize,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl JobQueue {
    pub fn new(limit: usize) -> Self {
        Self {
            state: Mutex::new(QueueState {
                lines: HashMap::new(),
                turns: VecDeque::new(),
                len: 0,
                closed: false,
            }),
            ready: Condvar::new(),
            limit,
            running: Mutex::new(HashMap::new()),
            running_now: AtomicUsize::new(0),
            running_max: AtomicUsize::new(0),
            busy: AtomicUsize::new(0),
            threads: Mutex::new(Vec::new()),
        }
    }

    pub fn capacity(&self) -> usize {
        self.limit
    }

    pub fn depth(&self) -> usize {
        lock(&self.state).len
    }

    pub fn is_full(&self) -> bool {
        self.depth() >= self.limit
    }

    /// Queue a newly accepted job in its tenant's line, unless the queue is full or closed.
    pub fn try_push(&self, id: Uuid, tenant: &str) -> Result<(), PushError> {
        let mut s = lock(&self.state);
        if s.closed {
            return Err(PushError::Closed);
        }
        if s.len >= self.limit {
            return Err(PushError::Full);
        }
        s.push(id, tenant);
        drop(s);
        self.ready.notify_one();
        Ok(())
    }

    /// Queue a job regardless of the limit (jobs recovered at startup: a 202 is a promise).
    pub fn push(&self, id: Uuid, tenant: &str) {
        lock(&self.state).push(id, tenant);
        self.ready.notify_one();
    }

    /// Take a cancelled job out of the queue.
    pub fn remove(&self, id: Uuid) -> bool {
        lock(&self.state).remove(id)
    }

    /// Wait for the next job (and its tenant); None once the queue is closed.
    fn pop(&self) -> Option<(Uuid, String)> {
        let mut s = lock(&self.state);
        loop {
            if s.closed {
                return None;
            }
            if let Some(next) = s.pop() {
                self.busy.fetch_add(1, Ordering::SeqCst);
                return Some(next);
            }
            s = self.ready.wait(s).unwrap_or_else(|p| p.into_inner());
        }
    }

    /// Stop handing out jobs (those still queued stay queued in the repo).
    pub fn close(&self) {
        lock(&self.state).closed = true;
        self.ready.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        lock(&self.state).closed
    }

    pub fn running(&self) -> usize {
        self.running_now.load(Ordering::SeqCst)
    }

    /// The most jobs ever running at once since start.
    pub fn running_max(&self) -> usize {
        self.running_max.load(Ordering::SeqCst)
    }

    /// Workers busy with a job (including one just taken off the queue).
    pub fn busy(&self) -> usize {
        self.busy.load(Ordering::SeqCst)
    }

    pub fn running_ids(&self) -> Vec<Uuid> {
        lock(&self.running).keys().copied().collect()
    }

    /// Ask a running job to stop (within one step of work). False when no worker has it.
    pub fn cancel_running(&self, id: Uuid) -> bool {
        match lock(&self.running).get(&id) {
            Some(ctl) => {
                ctl.cancel.store(true, Ordering::SeqCst);
                true
            }
            None => false,
        }
    }

    /// Whether a worker still holds the job (it may be finishing a cancelled one).
    pub fn is_held(&self, id: Uuid) -> bool {
        lock(&self.running).contains_key(&id)
    }

    /// Ask every running job to stop and go back to the queue.
    pub fn interrupt_all(&self) {
        for ctl in lock(&self.running).values() {
            ctl.interrupt.store(true, Ordering::SeqCst);
        }
    }

    fn register(&self, id: Uuid) -> Arc<RunControl> {
        let ctl = Arc::new(RunControl::default());
        lock(&self.running).insert(id, ctl.clone());
        ctl
    }

    fn unregister(&self, id: Uuid) {
        lock(&self.running).remove(&id);
    }

    fn begin_running(&self) -> RunningGuard<'_> {
        let now = self.running_now.fetch_add(1, Ordering::SeqCst) + 1;
        self.running_max.fetch_max(now, Ordering::SeqCst);
        RunningGuard(self)
    }

    pub(crate) fn add_thread(&self, handle: std::thread::JoinHandle<()>) {
        lock(&self.threads).push(handle);
    }

    /// Join the worker threads that have exited (all of them after `close` once their
    /// jobs end).
    pub(crate) fn join_finished_threads(&self) {
        let mut threads = lock(&self.threads);
        let (done, alive): (Vec<_>, Vec<_>) = threads.drain(..).partition(|t| t.is_finished());
        *threads = alive;
        drop(threads);
        for t in done {
            let _ = t.join();
        }
    }
}

struct RunningGuard<'a>(&'a JobQueue);

impl Drop for RunningGuard<'_> {
    fn drop(&mut self) {
        self.0.running_now.fetch_sub(1, Ordering::SeqCst);
    }
}

/// A worker thread: run jobs until the queue closes.
pub(crate) fn worker_loop(inner: Arc<Inner>) {
    while let Some((id, tenant)) = inner.jobs.pop() {
        process(&inner, id, &tenant);
        inner.jobs.busy.fetch_sub(1, Ordering::SeqCst);
        super::util::release_free_heap();
    }
}

/// How long a job waits before it is queued again when the store or the job database
/// does not answer.
const STORE_RETRY: Duration = Duration::from_secs(2);

/// Sleep for `wait`, or less if the service starts to stop.
fn wait_unless_closing(inner: &Inner, wait: Duration) {
    let until = Instant::now() + wait;
    while Instant::now() < until && !inner.jobs.is_closed() {
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Run a repo write, again and again while the database does not answer, so that a job's
/// outcome is recorded once it does; at shutdown the last error stands (the job is then
/// still "running" in the database and runs again at the next start).
fn persist<T>(inner: &Inner, write: impl Fn() -> RepoResult<T>) -> RepoResult<T> {
    loop {
        match write() {
            Err(e) if e.is_unavailable() && !inner.jobs.is_closed() => {
                tracing::warn!(error = %e, "the job database does not answer; recording again");
                wait_unless_closing(inner, STORE_RETRY);
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
    Error(ApiError),
}

/// A store error: unavailable (the job waits) or the job's failure.
fn store_error(e: std::io::Error, doing: &str) -> Stop {
    if is_unavailable(&e) {
        Stop::StoreUnavailable(format!("{doing}: {e}"))
    } else {
        ApiError::internal(format!("{doing}: {e}")).into()
    }
}

impl From<ApiError> for Stop {
    fn from(e: ApiError) -> Self {
        Stop::Error(e)
    }
}

fn process(inner: &Inner, id: Uuid, tenant: &str) {
    // Registered before the repo says running, so a DELETE that sees "running" finds it.
    let ctl = inner.jobs.register(id);
    match inner.repo.start(id, now_ms()) {
        Ok(true) => {}
        Ok(false) => {
            inner.prefetch.discard(id);
            inner.jobs.unregister(id);
            return; // cancelled or deleted while queued
        }
        Err(e) if e.is_unavailable() => {
            // The job stays queued in the database; try it again once it answers.
            tracing::warn!(job = %id, error = %e, "the job database does not answer; the job waits");
            inner.jobs.unregister(id);
            wait_unless_closing(inner, STORE_RETRY);
            inner.jobs.push(id, tenant);
            return;
        }
        Err(e) => {
            tracing::error!(job = %id, error = %e, "cannot start job");
            inner.prefetch.discard(id);
            inner.jobs.unregister(id);
            return;
        }
    }
    let running = inner.jobs.begin_running();
    let started = Instant::now();
    let span = tracing::info_span!("job", job = %id);
    let _enter = span.enter();
    tracing::info!("job started");

    // A fresh id per attempt keys its outputs, so attempts never write over each other.
    let attempt = Uuid::new_v4().simple().to_string();
    let mut clock = StageClock {
        inner,
        id,
        ctl: &ctl,
        deadline: started + inner.config.job_timeout,
        current: None,
        timed_out: AtomicBool::new(false),
    };
    let outcome = std::panic::catch_unwind(AssertUnwindSafe(|| {
        execute(inner, id, &attempt, &mut clock)
    }))
    .unwrap_or_else(|panic| {
        let what = panic_message(&*panic);
        tracing::error!(panic = %what, "the reconstruction panicked");
        Err(Stop::Error(ApiError::job_failed(
            "internal error: the reconstruction crashed; see the server logs",
        )))
    });
    clock.close();
    let timed_out = clock.timed_out.load(Ordering::SeqCst);
    settle(
        inner,
        id,
        &attempt,
        &ctl,
        outcome,
        timed_out,
        started.elapsed(),
    );
    drop(running);
    inner.jobs.unregister(id);
}

/// Record how the job ended and tidy its files.
fn settle(
    inner: &Inner,
    id: Uuid,
    attempt: &str,
    ctl: &RunControl,
    outcome: Result<(serde_json::Value, Vec<ArtifactInfo>), Stop>,
    timed_out: bool,
    elapsed: Duration,
) {
    inner.prefetch.discard(id); // if the job stopped before taking it
    let instance = format!("/v1/jobs/{id}");
    let now = now_ms();
    let recorded = match outcome {
        Ok((result, artifacts)) => {
            let done = Finish::Succeeded { result, artifacts };
            persist(inner, || inner.repo.finish(id, &done, now))
                .map(|ok| ok.then_some(JobStatus::Succeeded))
        }
        Err(Stop::Stopped) if ctl.interrupt.load(Ordering::SeqCst) => {
            tracing::info!("job interrupted by shutdown; it runs again at the next start");
            persist(inner, || inner.repo.requeue(id)).map(|_| None)
        }
        Err(Stop::Stopped) if timed_out && !ctl.cancel.load(Ordering::SeqCst) => {
            let e = ApiError::job_timeout(format!(
                "the reconstruction did not finish within the job time limit of {}",
                format_duration(inner.config.job_timeout)
            ))
            .with_instance(&instance);
            let failed = Finish::Failed(e.problem());
            persist(inner, || inner.repo.finish(id, &failed, now))
                .map(|ok| ok.then_some(JobStatus::Failed))
        }
        Err(Stop::Stopped) => Ok(Some(JobStatus::Cancelled)), // the DELETE recorded it
        Err(Stop::StoreUnavailable(why)) => {
            tracing::warn!(error = %why, "the store does not answer; the job runs again");
            let until = Instant::now() + STORE_RETRY;
            while Instant::now() < until
                && !ctl.cancel.load(Ordering::SeqCst)
                && !ctl.interrupt.load(Ordering::SeqCst)
            {
                std::thread::sleep(Duration::from_millis(20));
            }
            persist(inner, || inner.repo.requeue(id)).and_then(|requeued| {
                if requeued
                    && !ctl.interrupt.load(Ordering::SeqCst)
                    && let Some(rec) = inner.repo.get(id)?
                {
                    inner.jobs.push(id, &rec.tenant);
                }
                Ok(None)
            })
        }
        Err(Stop::Error(e)) => {
            tracing::info!(
                status = e.status().as_u16(),
                detail = e.detail(),
                "job failed"
            );
            let failed = Finish::Failed(e.with_instance(&instance).problem());
            persist(inner, || inner.repo.finish(id, &failed, now))
                .map(|ok| ok.then_some(JobStatus::Failed))
        }
    };
    match recorded {
        Ok(Some(status)) => {
            tracing::info!(
                status = status.as_str(),
                seconds = elapsed.as_secs_f64(),
                "job finished"
            );
            inner.metrics.observe_finished(status, elapsed);
            super::webhooks::job_ended(inner, id);
        }
        Ok(None) => {}
        Err(e) => tracing::error!(error = %e, "cannot record the job's outcome"),
    }
    // Whatever the repo now says decides which files stay.
    let tidy = match inner.repo.get(id) {
        Ok(None) => inner.store.remove_job(id),
        Ok(Some(rec)) if rec.status == JobStatus::Succeeded => inner.store.remove_inputs(id),
        Ok(Some(rec)) if rec.status.is_terminal() => inner
            .store
            .remove_inputs(id)
            .and_then(|_| inner.store.discard_outputs(id, attempt)),
        Ok(Some(_)) => inner.store.discard_outputs(id, attempt),
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
    inner: &'a Inner,
    id: Uuid,
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
        self.ctl.cancel.load(Ordering::SeqCst) || self.ctl.interrupt.load(Ordering::SeqCst)
    }

    fn close(&mut self) {
        if let Some((stage, at)) = self.current.take() {
            self.inner
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
        if let Err(e) = self
            .inner
            .repo
            .progress(self.id, stage.as_str(), progress, now_ms())
        {
            tracing::warn!(error = %e, "cannot record progress");
        }
        tracing::debug!(stage = stage.as_str(), "stage");
        self.current = Some((stage, Instant::now()));
        let delay = self.inner.config.stage_delay;
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
    inner: &Inner,
    id: Uuid,
    attempt: &str,
    clock: &mut StageClock<'_>,
) -> Result<(serde_json::Value, Vec<ArtifactInfo>), Stop> {
    let record = inner
        .repo
        .get(id)
        .map_err(ApiError::from)?
        .ok_or(Stop::Stopped)?;
    let options: Options = serde_json::from_value(record.options)
        .map_err(|e| ApiError::invalid(format!("options: {e}")))?;
    let input = inner
        .store
        .fetch_inputs(id)
        .map_err(|e| store_error(e, "fetching the job's inputs"))?;
    let manifest: Manifest = std::fs::read(input.join(MANIFEST_FILE))
        .map_err(ApiError::from)
        .and_then(|b| {
            serde_json::from_slice(&b)
                .map_err(|e| ApiError::internal(format!("manifest of {id}: {e}")))
        })?;
    let table = std::fs::read(input.join(LIGHTS_FILE)).map_err(ApiError::from)?;

    if !clock.enter(Stage::Decode) {
        return Err(Stop::Stopped);
    }
    let lights = lights::parse_bytes(&table).map_err(ApiError::from)?;
    let set = open_inputs(inner, id, lights, &input, &manifest, clock)?;
    let set = set.noted(manifest.notes.clone());

    let out = inner.store.stage_outputs(id).map_err(ApiError::from)?;
    let report = pipeline::run(set, &options, &out, clock);
    clock.close();
    let report = match report {
        Ok(r) => r,
        Err(RunError::Cancelled) => return Err(Stop::Stopped),
        Err(e) => return Err(ApiError::from(e).into()),
    };
    let mut artifacts = list_artifacts(&out).map_err(ApiError::from)?;
    inner
        .store
        .commit_outputs(id, attempt, &mut artifacts)
        .map_err(|e| store_error(e, "committing the outputs"))?;
    Ok((summarize(&report), artifacts))
}

/// The first pass over the job's images, taking those scanned during the upload when
/// there are any; the solve reads the bands back from their scratch copies. Once `clock` says stop,
/// the images not yet started are not scanned and the set, which then holds a placeholder
/// error for them, is dropped.
fn open_inputs(
    inner: &Inner,
    id: Uuid,
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
    // Waits for scans still running (on rayon: this is a worker thread, not a pool one).
    let ready = Mutex::new(
        inner
            .prefetch
            .take(id)
            .map(Prefetch::finish)
            .unwrap_or_default(),
    );
    let taken = AtomicUsize::new(0);
    // The decoded images go beside the (fetched) inputs, as the upload's scans put them.
    let set = stream::open_with(
        lights,
        &files,
        mask.as_ref(),
        &inner.config.limits(),
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
    inner
        .metrics
        .prefetched_images
        .fetch_add(taken, Ordering::Relaxed);
    tracing::debug!(images = taken, "images scanned during the upload");
    Ok(set.map_err(ApiError::from)?)
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

/// The report's headline numbers (as in `result.json`).
fn summarize(report: &Report) -> serde_json::Value {
    const KEYS: [&str; 16] = [
        "width",
        "height",
        "light_count",
        "light_condition_number",
        "height_min",
        "height_max",
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tenants_take_turns_and_each_line_keeps_its_order() {
        let q = JobQueue::new(100);
        let a: Vec<Uuid> = (0..5).map(|_| Uuid::new_v4()).collect();
        let b: Vec<Uuid> = (0..2).map(|_| Uuid::new_v4()).collect();
        for id in &a {
            q.try_push(*id, "a").unwrap();
        }
        for id in &b {
            q.try_push(*id, "b").unwrap();
        }
        assert!(q.remove(a[1]));
        assert!(!q.remove(a[1]));
        assert_eq!(q.depth(), 6);
        let mut order = Vec::new();
        while q.depth() > 0 {
            order.push(q.pop().unwrap());
        }
        let t = |id: Uuid, tenant: &str| (id, tenant.to_string());
        assert_eq!(
            order,
            [
                t(a[0], "a"),
                t(b[0], "b"),
                t(a[2], "a"),
                t(b[1], "b"),
                t(a[3], "a"),
                t(a[4], "a")
            ]
        );
        let small = JobQueue::new(1);
        small.try_push(a[0], "a").unwrap();
        assert_eq!(small.try_push(b[0], "b"), Err(PushError::Full));
    }
}
