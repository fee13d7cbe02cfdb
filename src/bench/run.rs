//! The bench from start to end: the mode its flags choose (hostile, calibration, near,
//! integrators, light sweep, or the default run of core, HTTP and load measurements), run
//! in a temporary directory, and its table printed.

use std::path::Path;

use super::args::BenchArgs;
use super::http::{self, Backend, LoadResult, Server};
use super::machine::{load_average, machine};
use super::sets::{self, SizeResult};
use super::temp_dir::TempDir;
use super::{calibration, hostile, integrators, near, sweep, tables, timing};

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
            (options, args.sweep_scene),
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
