//! In-process counters rendered as Prometheus text at `GET /metrics`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use super::repo::JobStatus;

#[derive(Default, Clone, Copy)]
struct SumCount {
    count: u64,
    sum: f64,
}

/// Counters the service updates as it works.
#[derive(Default)]
pub struct Metrics {
    /// (method, route, status) → requests and seconds.
    http: Mutex<BTreeMap<(String, String, u16), SumCount>>,
    /// stage → durations.
    stages: Mutex<BTreeMap<String, SumCount>>,
    /// final status → jobs (whole-job durations).
    finished: Mutex<BTreeMap<&'static str, SumCount>>,
    pub submitted: AtomicU64,
    pub rejected_queue_full: AtomicU64,
    /// Images jobs took decoded ahead (during their upload).
    pub prefetched_images: AtomicU64,
    /// (tenant, limit) → submissions refused with 429.
    quota_refusals: Mutex<BTreeMap<(String, &'static str), u64>>,
    /// The HTTP server's connections (kept by `connections`).
    pub connections: Arc<ConnectionCounters>,
}

/// What the accept loop and its connections count.
#[derive(Default)]
pub struct ConnectionCounters {
    pub open: AtomicU64,
    pub limit: AtomicU64,
    pub accepted: AtomicU64,
    /// Idle connections closed to make room for a new one.
    pub evicted: AtomicU64,
    /// Connections answered 503 at the cap, every open one having a request in flight.
    pub refused: AtomicU64,
    pub header_timeouts: AtomicU64,
    pub keep_alive_timeouts: AtomicU64,
    pub send_timeouts: AtomicU64,
}

/// Gauges read at scrape time.
pub struct Snapshot {
    pub jobs_by_status: Vec<(JobStatus, u64)>,
    pub jobs_by_tenant: Vec<(String, JobStatus, u64)>,
    pub queue_depth: usize,
    pub queue_capacity: usize,
    pub running: usize,
    pub running_max: usize,
    pub workers: usize,
    pub free_disk_bytes: Option<u64>,
    pub prefetch_sets: usize,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Metrics {
    pub fn observe_http(&self, method: &str, route: &str, status: u16, elapsed: Duration) {
        let mut m = lock(&self.http);
        let e = m
            .entry((method.to_string(), route.to_string(), status))
            .or_default();
        e.count += 1;
        e.sum += elapsed.as_secs_f64();
    }

    pub fn observe_stage(&self, stage: &str, elapsed: Duration) {
        let mut m = lock(&self.stages);
        let e = m.entry(stage.to_string()).or_default();
        e.count += 1;
        e.sum += elapsed.as_secs_f64();
    }

    pub fn observe_quota_refusal(&self, tenant: &str, limit: &'static str) {
        *lock(&self.quota_refusals)
            .entry((tenant.to_string(), limit))
            .or_default() += 1;
    }

    pub fn observe_finished(&self, status: JobStatus, elapsed: Duration) {
        let mut m = lock(&self.finished);
        let e = m.entry(status.as_str()).or_default();
        e.count += 1;
        e.sum += elapsed.as_secs_f64();
    }

    /// Prometheus text exposition format 0.0.4.
    pub fn render(&self, snap: &Snapshot) -> String {
        let mut out = String::new();
        let _ = writeln!(
            out,
            "# HELP photostereo_jobs Jobs in the repository by status.\n# TYPE photostereo_jobs gauge"
        );
        for (status, n) in &snap.jobs_by_status {
            let _ = writeln!(
                out,
                "photostereo_jobs{{status=\"{}\"}} {n}",
                status.as_str()
            );
        }
        let _ = writeln!(
            out,
            "# HELP photostereo_tenant_jobs Jobs in the repository by tenant and status.\n# TYPE photostereo_tenant_jobs gauge"
        );
        for (tenant, status, n) in &snap.jobs_by_tenant {
            let _ = writeln!(
                out,
                "photostereo_tenant_jobs{{tenant=\"{tenant}\",status=\"{}\"}} {n}",
                status.as_str()
            );
        }
        let _ = writeln!(
            out,
            "# HELP photostereo_tenant_quota_refusals_total Submissions refused (429) by tenant and limit.\n# TYPE photostereo_tenant_quota_refusals_total counter"
        );
        for ((tenant, limit), n) in lock(&self.quota_refusals).iter() {
            let _ = writeln!(
                out,
                "photostereo_tenant_quota_refusals_total{{tenant=\"{tenant}\",limit=\"{limit}\"}} {n}"
            );
        }
        let gauges: [(&str, &str, u64); 6] = [
            (
                "photostereo_queue_depth",
                "Accepted jobs waiting for a worker.",
                snap.queue_depth as u64,
            ),
            (
                "photostereo_queue_capacity",
                "Queue length past which submissions get 503.",
                snap.queue_capacity as u64,
            ),
            (
                "photostereo_workers",
                "Size of the worker pool.",
                snap.workers as u64,
            ),
            (
                "photostereo_workers_running",
                "Workers reconstructing a job now.",
                snap.running as u64,
            ),
            (
                "photostereo_workers_running_max",
                "Most workers ever reconstructing at once since start.",
                snap.running_max as u64,
            ),
            (
                "photostereo_prefetch_sets",
                "Uploads whose images are held decoded ahead of their job.",
                snap.prefetch_sets as u64,
            ),
        ];
        for (name, help, v) in gauges {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        }
        if let Some(free) = snap.free_disk_bytes {
            let _ = writeln!(
                out,
                "# HELP photostereo_free_disk_bytes Free space on the data directory's file system.\n# TYPE photostereo_free_disk_bytes gauge\nphotostereo_free_disk_bytes {free}"
            );
        }
        for (name, help, v) in [
            (
                "photostereo_jobs_submitted_total",
                "Jobs accepted (202).",
                self.submitted.load(Ordering::Relaxed),
            ),
            (
                "photostereo_jobs_rejected_queue_full_total",
                "Submissions refused because the queue was full (503).",
                self.rejected_queue_full.load(Ordering::Relaxed),
            ),
            (
                "photostereo_prefetched_images_total",
                "Images jobs took decoded ahead, during their upload.",
                self.prefetched_images.load(Ordering::Relaxed),
            ),
            (
                "photostereo_unreadable_records_total",
                "Stored records left out of listings because they could not be read (each logged).",
                super::repo::unreadable_records(),
            ),
        ] {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}"
            );
        }
        self.render_connections(&mut out);

        let _ = writeln!(
            out,
            "# HELP photostereo_jobs_finished_seconds Wall time of jobs run by this process, by final status.\n# TYPE photostereo_jobs_finished_seconds summary"
        );
        for (status, sc) in lock(&self.finished).iter() {
            let _ = writeln!(
                out,
                "photostereo_jobs_finished_seconds_sum{{status=\"{status}\"}} {}\nphotostereo_jobs_finished_seconds_count{{status=\"{status}\"}} {}",
                sc.sum, sc.count
            );
        }
        let _ = writeln!(
            out,
            "# HELP photostereo_stage_seconds Time spent in each reconstruction stage.\n# TYPE photostereo_stage_seconds summary"
        );
        for (stage, sc) in lock(&self.stages).iter() {
            let _ = writeln!(
                out,
                "photostereo_stage_seconds_sum{{stage=\"{stage}\"}} {}\nphotostereo_stage_seconds_count{{stage=\"{stage}\"}} {}",
                sc.sum, sc.count
            );
        }
        let _ = writeln!(
            out,
            "# HELP photostereo_http_requests_total HTTP requests by method, route and status.\n# TYPE photostereo_http_requests_total counter"
        );
        let http = lock(&self.http).clone();
        for ((method, route, status), sc) in &http {
            let _ = writeln!(
                out,
                "photostereo_http_requests_total{{method=\"{method}\",route=\"{route}\",status=\"{status}\"}} {}",
                sc.count
            );
        }
        let _ = writeln!(
            out,
            "# HELP photostereo_http_request_seconds Time to answer HTTP requests (until the response head).\n# TYPE photostereo_http_request_seconds summary"
        );
        for ((method, route, status), sc) in &http {
            let labels = format!("method=\"{method}\",route=\"{route}\",status=\"{status}\"");
            let _ = writeln!(
                out,
                "photostereo_http_request_seconds_sum{{{labels}}} {}\nphotostereo_http_request_seconds_count{{{labels}}} {}",
                sc.sum, sc.count
            );
        }
        out
    }

    fn render_connections(&self, out: &mut String) {
        let c = &*self.connections;
        let read = |n: &AtomicU64| n.load(Ordering::Relaxed);
        for (name, kind, help, v) in [
            (
                "photostereo_connections_open",
                "gauge",
                "HTTP connections open now.",
                read(&c.open),
            ),
            (
                "photostereo_connections_max",
                "gauge",
                "Most HTTP connections open at once (--max-connections).",
                read(&c.limit),
            ),
            (
                "photostereo_connections_accepted_total",
                "counter",
                "HTTP connections accepted and served.",
                read(&c.accepted),
            ),
            (
                "photostereo_connections_evicted_total",
                "counter",
                "Idle HTTP connections closed to make room for a new one at the cap.",
                read(&c.evicted),
            ),
            (
                "photostereo_connections_refused_total",
                "counter",
                "HTTP connections answered 503 at the cap, every open one busy.",
                read(&c.refused),
            ),
        ] {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {v}"
            );
        }
        let _ = writeln!(
            out,
            "# HELP photostereo_connections_timed_out_total HTTP connections closed by a timeout.\n# TYPE photostereo_connections_timed_out_total counter"
        );
        for (timeout, n) in [
            ("header", &c.header_timeouts),
            ("keep_alive", &c.keep_alive_timeouts),
            ("send", &c.send_timeouts),
        ] {
            let _ = writeln!(
                out,
                "photostereo_connections_timed_out_total{{timeout=\"{timeout}\"}} {}",
                read(n)
            );
        }
    }
}
