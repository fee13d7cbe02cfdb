//! `photostereo bench`: render synthetic sets, time the core and (optionally) the HTTP
//! service on them in this one process, and print the figures as Markdown tables next to
//! the project's performance targets.
//!
//! Everything lives in a temporary directory that is removed at the end (also on errors).
//! The HTTP side is a small HTTP/1.1 client written here on `tokio::net::TcpStream`
//! (multipart uploads streamed from disk, keep-alive status requests); it only ever talks
//! to its own server on 127.0.0.1 (in this process, or a child process for `--hostile`),
//! and every network wait has a timeout.
//!
//! The module reads downward: [`args`] holds the flags, [`sets`] renders the image sets,
//! [`timing`] times the core jobs on them (and measures their memory through [`memory`]),
//! [`http`] drives the in-process server with the small client in [`client`], [`sweep`]
//! runs the light-count sweep in child processes, [`integrators`] times the integrators
//! alone on normal maps, [`calibration`] times a chrome-ball calibration of camera-sized
//! images, [`near`] times a near-light job against the distant one on the same images,
//! [`hostile`] probes a `serve` child process
//! ([`child`]) with [`probe`] under hostile loads, and [`tables`] prints what was measured;
//! [`stats`] holds the medians and percentiles they share.

mod args;
mod calibration;
mod child;
mod client;
mod hostile;
mod http;
mod integrators;
mod memory;
mod near;
mod probe;
mod sets;
mod stats;
mod sweep;
mod tables;
mod timing;

use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::Context;

pub use args::BenchArgs;
use http::{Backend, LoadResult, Server};
use sets::SizeResult;

/// Render the sets, measure them, print the tables; the temporary directory goes either way.
pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    args.check()?;
    let parent = match &args.tmp_dir {
        Some(p) => p.clone(),
        None => std::env::temp_dir(),
    };
    let tmp = TempDir::new(&parent)?;
    eprintln!("bench: working in {}", tmp.0.display());

    let machine = machine();
    let load_at_start = load_average();
    if args.hostile {
        let run = hostile::run(&args, &tmp.0)?;
        let loads = (load_at_start.as_str(), load_average());
        print!(
            "{}",
            tables::hostile_table(&args, &machine, (loads.0, &loads.1), &run)
        );
        return Ok(());
    }
    if args.calibration {
        let measured = calibration::run(args.runs, &tmp.0)?;
        let loads = (load_at_start.as_str(), load_average());
        print!(
            "{}",
            tables::calibration_table(&args, &machine, (loads.0, &loads.1), &measured)
        );
        return Ok(());
    }
    if args.near {
        let rows = near::run(&args.sizes, args.runs, &tmp.0)?;
        let loads = (load_at_start.as_str(), load_average());
        print!(
            "{}",
            tables::near_table(&args, &machine, (loads.0, &loads.1), &rows)
        );
        return Ok(());
    }
    if args.integrators {
        let runs = integrators::run(&args.sizes, args.runs, args.normal_maps.as_deref())?;
        let loads = (load_at_start.as_str(), load_average());
        let tables = (runs.0.as_slice(), runs.1.as_slice());
        print!(
            "{}",
            tables::integrators_table(&args, &machine, (loads.0, &loads.1), tables)
        );
        return Ok(());
    }
    if !args.light_sweep.is_empty() {
        let against = args.against.as_deref();
        let options = &args.sweep_options;
        let points = sweep::run(
            &args.sizes,
            &args.light_sweep,
            args.runs,
            against,
            options,
            &tmp.0,
        )?;
        let loads = (load_at_start.as_str(), load_average());
        print!(
            "{}",
            tables::sweep_table(&args, &machine, (loads.0, &loads.1), &points)
        );
        return Ok(());
    }

    let mut sets = sets::render(&args.sizes, args.lights, &tmp.0)?;

    let server = if args.http || args.load {
        Some(Server::start(&args, &sets, &tmp.0, Backend::Local)?)
    } else {
        None
    };
    let shared = match (&args.database_url, &args.store) {
        (Some(database_url), Some(store)) => {
            let backend = Backend::Shared {
                database_url: database_url.clone(),
                store: store.clone(),
            };
            Some(Server::start(&args, &sets, &tmp.0, backend)?)
        }
        _ => None,
    };
    let outcome = measure(&args, &mut sets, server.as_ref(), shared.as_ref(), &tmp.0);
    for server in [server, shared].into_iter().flatten() {
        server.stop();
    }
    let load = outcome?;

    let load_at_end = load_average();
    print!(
        "{}",
        tables::tables(
            &args,
            &machine,
            (&load_at_start, &load_at_end),
            &sets,
            load.as_ref()
        )
    );
    Ok(())
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// Per set: integration alone; core and HTTP runs alternating (core, HTTP, core, HTTP, …,
/// and the PostgreSQL + S3 server's HTTP run after each HTTP one) so that a change in the
/// machine's background load hits all alike; the l2 and default jobs, one after the other
/// in each round. Then the load test.
fn measure(
    args: &BenchArgs,
    sets: &mut [SizeResult],
    server: Option<&Server>,
    shared: Option<&Server>,
    tmp: &Path,
) -> anyhow::Result<Option<LoadResult>> {
    for set in sets.iter_mut() {
        // Before the jobs, and dropped before them, so it stays out of their peak memory.
        let gradients = timing::Gradients::of_sphere(set.size);
        for _ in 0..args.runs {
            timing::integration_run(set, &gradients);
        }
        drop(gradients);
        for run in 0..args.runs {
            timing::core_run(set, run, args.runs, tmp)?;
            let rounds = (run, args.runs);
            if let (true, Some(server)) = (args.http, server) {
                let r =
                    (server.rt).block_on(http::http_run(set, "HTTP", rounds, server.addr, &[]))?;
                set.http_ms.push(r.total_ms);
                set.upload_ms.push(r.upload_ms);
                set.http_cpu_ms.push(r.cpu_ms);
                set.http_peak_bytes.extend(r.peak_bytes);
            }
            if let Some(shared) = shared {
                let label = "HTTP on PostgreSQL + S3";
                let r = (shared.rt).block_on(http::http_run(
                    set,
                    label,
                    rounds,
                    shared.addr,
                    &args.server_pids,
                ))?;
                set.shared_http_ms.push(r.total_ms);
                set.shared_upload_ms.push(r.upload_ms);
                set.shared_cpu_ms.push(r.cpu_ms);
                set.shared_servers_cpu_ms.push(r.servers_cpu_ms);
            }
        }
        for run in 0..args.runs {
            timing::default_against_l2_run(set, run, args.runs, tmp)?;
        }
    }
    match (args.load, server, sets.iter().max_by_key(|s| s.size)) {
        (true, Some(server), Some(big)) => server
            .rt
            .block_on(http::load_test(args, big, server.addr, server.workers))
            .map(Some),
        _ => Ok(None),
    }
}

/// A directory removed with everything in it when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(parent: &Path) -> anyhow::Result<Self> {
        let stamp = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        let path = parent.join(format!(
            "photostereo-bench-{}-{stamp:x}",
            std::process::id()
        ));
        std::fs::create_dir(&path)
            .with_context(|| format!("creating the temporary directory {}", path.display()))?;
        Ok(Self(path))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_dir_all(&self.0) {
            eprintln!("bench: could not remove {}: {e}", self.0.display());
        }
    }
}

/// "N × model, M GiB RAM".
fn machine() -> String {
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let mem = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("MemTotal:"))
                .and_then(|v| v.split_whitespace().next()?.parse::<f64>().ok())
        })
        .map(|kb| format!("{:.1} GiB RAM", kb / (1024.0 * 1024.0)))
        .unwrap_or_else(|| "unknown RAM".into());
    format!(
        "{cores} cores (nproc), {model}, {mem}, {} {}",
        std::env::consts::OS,
        std::env::consts::ARCH
    )
}
