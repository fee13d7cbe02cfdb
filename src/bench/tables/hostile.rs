//! `bench --hostile`: a row per scenario, the health and status probes' percentiles and
//! the server's memory before, during and after.

use std::fmt::Write as _;

use super::format::{heading, num};
use crate::bench::args::BenchArgs;
use crate::bench::hostile::{ANSWER_TIMEOUT, HostileRun};
use crate::bench::memory::MB;
use crate::bench::probe::{PROBE_TIMEOUT, Probes};

/// `bench --hostile`: a row per scenario.
pub(crate) fn hostile_table(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    run: &HostileRun,
) -> String {
    let mut o = String::new();
    let scenarios: Vec<String> = args
        .scenarios
        .iter()
        .map(|s| {
            clap::ValueEnum::to_possible_value(s)
                .map(|v| v.get_name().to_string())
                .unwrap_or_default()
        })
        .collect();
    let serve_args = if args.serve_args.is_empty() {
        String::new()
    } else {
        format!(" --serve-args '{}'", args.serve_args.join(" "))
    };
    let timeout_ms = PROBE_TIMEOUT.as_millis();
    heading(
        &mut o,
        "photostereo bench --hostile",
        machine,
        (load_at_start, load_at_end),
    );
    let _ = writeln!(
        o,
        "- command: `photostereo bench --hostile --scenarios {} --hostile-seconds {} \
         --hostile-connections {} --probe-ms {}{serve_args}`",
        scenarios.join(","),
        args.hostile_seconds,
        args.hostile_connections,
        args.probe_ms
    );
    let _ = writeln!(
        o,
        "- server: this binary's `serve` as a child process on 127.0.0.1, default limits{}, \
         two tenants' keys (`--api-key a:… --api-key b:…`), a fresh data directory per \
         scenario; its open-file limit {}",
        if serve_args.is_empty() {
            ""
        } else {
            " and the --serve-args"
        },
        run.server_open_files
            .map_or("unknown".to_string(), |n| n.to_string())
    );
    let _ = writeln!(
        o,
        "- load: {} s, or until the last of its requests is answered (each given up to \
         {} s); probes every {} ms meanwhile, `GET /healthz` and tenant B's `GET \
         /v1/jobs/{{id}}` (a finished job, with B's key), each on a new connection with a \
         {timeout_ms} ms timeout; a failed probe counts as {timeout_ms} ms in the \
         percentiles",
        args.hostile_seconds,
        ANSWER_TIMEOUT.as_secs(),
        args.probe_ms
    );
    let _ = writeln!(
        o,
        "- memory: the server's VmRSS just before the load, its VmHWM over the load (reset \
         through /proc/<pid>/clear_refs; * where that failed, the peak since it started) \
         and its VmRSS 2 s after the load; MB = 10⁶ bytes\n"
    );
    let _ = writeln!(
        o,
        "| scenario | health p50 ms | health p99 ms | status p99 ms | probe errors / timeouts | RSS before MB | peak RSS MB | RSS after MB | outcome |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---|"
    );
    for row in &run.rows {
        let p = &row.probes;
        let (errors, timeouts) = p.failures();
        let latency = |probes: &[crate::bench::probe::Probe], q: f64| {
            let v = Probes::percentile(probes, q);
            if v >= timeout_ms as f64 {
                format!("≥ {timeout_ms}")
            } else {
                num(Some(v), 1)
            }
        };
        let mb = |b: Option<f64>| num(b.map(|b| b / MB), 0);
        let _ = writeln!(
            o,
            "| {} | {} | {} | {} | {errors} / {timeouts} of {} | {} | {}{} | {} | {} |",
            row.scenario,
            latency(&p.health, 50.0),
            latency(&p.health, 99.0),
            latency(&p.status, 99.0),
            p.health.len() + p.status.len(),
            mb(row.before_bytes),
            mb(row.peak_bytes),
            if row.peak_reset { "" } else { " *" },
            mb(row.after_bytes),
            row.outcome.replace('|', "\\|")
        );
    }
    o
}
