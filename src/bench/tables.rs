//! The printed Markdown tables, each figure beside its target: this file is the default
//! run's tables; each other mode's table is a file below it (`sweep`, `hostile`,
//! `integrators`, `near`, `calibration`), and `format` holds what they all share.

mod calibration;
mod format;
mod hostile;
mod integrators;
mod near;
mod sweep;

use std::fmt::Write as _;

pub(super) use calibration::calibration_table;
pub(super) use hostile::hostile_table;
pub(super) use integrators::integrators_table;
pub(super) use near::near_table;
pub(super) use sweep::sweep_table;

use super::args::BenchArgs;
use super::http::{LoadResult, POLL_EVERY};
use super::memory::{MB, online_cores};
use super::sets::SizeResult;
use super::stats::{max_of, median, percentile};
use format::{heading, mark, num, with_mark, zip2};

// The targets of issue 7.
const TARGET_FULL_OVER_DECODE: f64 = 1.5;
const TARGET_PEAK_MB: f64 = 480.0;
const TARGET_HTTP_OVER_CORE: f64 = 1.15;
/// The same HTTP job on PostgreSQL + S3 over SQLite + the data directory.
const TARGET_SHARED_OVER_LOCAL: f64 = 1.2;
const TARGET_LINEARITY: f64 = 0.25;
const TARGET_STATUS_P99_MS: f64 = 50.0;
const TARGET_POISSON_OVER_FC: f64 = 3.0;
const TARGET_SIZE: usize = 2048;
// The default solve's cost target, judged at TARGET_SIZE × TARGET_LIGHTS.
const TARGET_DEFAULT_OVER_L2: f64 = 1.25;
const TARGET_LIGHTS: usize = 24;

/// Every table, in the order printed.
pub(super) fn tables(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    sets: &[SizeResult],
    load: Option<&LoadResult>,
) -> String {
    let mut o = String::new();
    let sizes: Vec<String> = args.sizes.iter().map(|s| s.to_string()).collect();
    heading(
        &mut o,
        "photostereo bench",
        machine,
        (load_at_start, load_at_end),
    );
    let _ = writeln!(
        o,
        "- command: `photostereo bench --sizes {} --lights {} --runs {}{}{}`",
        sizes.join(","),
        args.lights,
        args.runs,
        match (args.http, &args.store) {
            (true, Some(store)) => format!(
                " --http --database-url postgres://… --store {store}{}",
                if args.server_pids.is_empty() {
                    ""
                } else {
                    " --server-pids …"
                }
            ),
            (true, None) => " --http".to_string(),
            _ => String::new(),
        },
        if args.load {
            format!(
                " --load --requests {} --connections {}",
                args.requests, args.connections
            )
        } else {
            String::new()
        }
    );
    let _ = writeln!(
        o,
        "- data: `synth::Scene::sphere(size)`, {} lights (`light_rings({}, 10, 60)`), 16-bit \
         gray PNG; default options (the default artifact set); \"every artifact\" = the same \
         job with `\"outputs\": [\"all\"]`; times are medians of {} run(s), peak RSS the \
         largest over both jobs; MB = 10⁶ bytes",
        args.lights, args.lights, args.runs
    );
    let _ = writeln!(
        o,
        "- full job = `intake::load_dir` + `pipeline::run`; decode = `load_dir` alone; peak \
         RSS = the process's VmHWM over the full job (reset through /proc/self/clear_refs), \
         baseline = VmRSS before it; own process = the peak RSS of the same default job run \
         as `photostereo reconstruct` in a child process (wait4's ru_maxrss; – where it is \
         below the bench process's own size, which Linux counts into a child's peak)"
    );
    if args.http {
        let _ = writeln!(
            o,
            "- HTTP = in-process server on 127.0.0.1 (workers = cores), multipart upload \
             streamed from disk, polled every {} ms: first byte sent → `succeeded`; core and \
             HTTP runs alternate",
            POLL_EVERY.as_millis()
        );
    }

    let reference = sets
        .iter()
        .find(|s| s.size == 512)
        .or_else(|| sets.iter().min_by_key(|s| s.size));
    let ref_ns = reference.and_then(|r| r.ns_per_pixel_image());
    let ref_label = reference.map_or("?".into(), |r| format!("{}²", r.size));
    // Linearity is judged only against a smaller set (with 2048² alone the reference is
    // the target itself).
    let smaller = reference.is_some_and(|r| r.size < TARGET_SIZE);

    // Time.
    let _ = writeln!(o, "\n### Time (medians)\n");
    let mut header = format!(
        "| size × lights | decode ms | full job ms | full / decode (≤ {TARGET_FULL_OVER_DECODE} at 2048²) | ns per pixel-image | vs {ref_label} (± {:.0} % at 2048²) | every artifact ms | every artifact / decode |",
        TARGET_LINEARITY * 100.0
    );
    let mut rule = "|---|---:|---:|---:|---:|---:|---:|---:|".to_string();
    if args.http {
        let _ = write!(
            header,
            " HTTP upload ms | HTTP job ms | HTTP / core (≤ {TARGET_HTTP_OVER_CORE}) |"
        );
        rule.push_str("---:|---:|---:|");
    }
    let _ = writeln!(o, "{header}\n{rule}");
    for s in sets {
        let decode = median(&s.decode_only_ms);
        let full = median(&s.full_ms);
        let ratio = zip2(full, decode, |f, d| f / d);
        let ns = s.ns_per_pixel_image();
        let lin = zip2(ns, ref_ns, |a, b| a / b);
        let judged = s.size == TARGET_SIZE;
        let all = median(&s.all_ms);
        let mut row = format!(
            "| {}² × {} | {} | {} | {} | {} | {} | {} | {} |",
            s.size,
            s.lights,
            num(decode, 0),
            num(full, 0),
            with_mark(ratio, 2, judged, |r| r <= TARGET_FULL_OVER_DECODE),
            num(ns, 1),
            with_mark(lin, 2, judged && smaller, linear_enough),
            num(all, 0),
            num(zip2(all, decode, |a, d| a / d), 2),
        );
        if args.http {
            let http = median(&s.http_ms);
            let _ = write!(
                row,
                " {} | {} | {} |",
                num(median(&s.upload_ms), 0),
                num(http, 0),
                with_mark(zip2(http, full, |h, c| h / c), 2, true, |r| r
                    <= TARGET_HTTP_OVER_CORE),
            );
        }
        let _ = writeln!(o, "{row}");
    }

    if args.database_url.is_some() {
        // The floor holds when the job and the servers share every core; when this process
        // may run on only some of them (taskset), the servers may have the others.
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let online = online_cores();
        let shared_cores = cores >= online;
        let floor_note = if shared_cores {
            format!(
                "floor = all that CPU spread over the {cores} cores, the least wall time the \
                 job could take on this machine"
            )
        } else {
            format!(
                "no floor: this process runs on {cores} of the machine's {online} cores, so \
                 the servers may have cores of their own"
            )
        };
        let _ = writeln!(
            o,
            "\n### HTTP: PostgreSQL + S3 against SQLite + data directory (medians)\n\n\
             Two in-process servers, the same workers; each round runs the job on the \
             SQLite + data directory server, then on the `--database-url` + `--store` one. \
             CPU = this process's (servers and client) over the job; servers' CPU = that of \
             `--server-pids` and their children; {floor_note}.\n"
        );
        let _ = writeln!(
            o,
            "| size × lights | SQLite + dir: upload ms | job ms | CPU ms | PostgreSQL + S3: upload ms | job ms | CPU ms | servers' CPU ms | floor ms | ratio (≤ {TARGET_SHARED_OVER_LOCAL}) | floor / SQLite + dir job |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        for s in sets {
            let (local, shared) = (median(&s.http_ms), median(&s.shared_http_ms));
            let servers = median(&s.shared_servers_cpu_ms).filter(|_| !args.server_pids.is_empty());
            let floor = (median(&s.shared_cpu_ms))
                .filter(|_| shared_cores)
                .map(|cpu| (cpu + servers.unwrap_or(0.0)) / cores as f64);
            let _ = writeln!(
                o,
                "| {}² × {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                s.size,
                s.lights,
                num(median(&s.upload_ms), 0),
                num(local, 0),
                num(median(&s.http_cpu_ms), 0),
                num(median(&s.shared_upload_ms), 0),
                num(shared, 0),
                num(median(&s.shared_cpu_ms), 0),
                num(servers, 0),
                num(floor, 0),
                with_mark(zip2(shared, local, |a, b| a / b), 2, true, |r| r
                    <= TARGET_SHARED_OVER_LOCAL),
                num(zip2(floor, local, |a, b| a / b), 2),
            );
        }
    }

    // Memory.
    let _ = writeln!(o, "\n### Memory (largest over the runs)\n");
    let mut header = format!(
        "| size × lights | 16-bit stack MB | peak RSS MB (≤ {TARGET_PEAK_MB:.0} at 2048² × 24) | baseline RSS MB | peak − baseline MB | own process: peak RSS MB |"
    );
    let mut rule = "|---|---:|---:|---:|---:|---:|".to_string();
    if args.http {
        header.push_str(" peak RSS over the HTTP job MB |");
        rule.push_str("---:|");
    }
    let _ = writeln!(o, "{header}\n{rule}");
    for s in sets {
        let at_target = s.size == TARGET_SIZE && s.lights == 24;
        let mut row = format!(
            "| {}² × {} | {:.1} | {} | {} | {} | {} |",
            s.size,
            s.lights,
            s.stack_bytes() / MB,
            with_mark(max_of(&s.peak_bytes).map(|b| b / MB), 0, at_target, |p| p
                <= TARGET_PEAK_MB),
            num(max_of(&s.base_bytes).map(|b| b / MB), 0),
            num(max_of(&s.growth_bytes).map(|b| b / MB), 0),
            with_mark(
                max_of(&s.alone_peak_bytes).map(|b| b / MB),
                0,
                at_target,
                |p| p <= TARGET_PEAK_MB
            ),
        );
        if args.http {
            let _ = write!(
                row,
                " {} |",
                num(max_of(&s.http_peak_bytes).map(|b| b / MB), 0)
            );
        }
        let _ = writeln!(o, "{row}");
    }

    // Stages.
    let _ = writeln!(o, "\n### Where the full job's time goes (ms, medians)\n");
    let _ = writeln!(
        o,
        "| size | decode | solve | mask | integrate | outputs | mesh | other | full job |"
    );
    let _ = writeln!(o, "|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for s in sets {
        let full = median(&s.full_ms);
        let cell = |v: Option<f64>| match (v, full) {
            (Some(v), Some(f)) if f > 0.0 => format!("{v:.0} ({:.0} %)", 100.0 * v / f),
            _ => num(v, 0),
        };
        let mut row = format!("| {}² | {} |", s.size, cell(median(&s.job_decode_ms)));
        for stage in &s.stage_ms {
            let _ = write!(row, " {} |", cell(median(stage)));
        }
        let _ = write!(row, " {} | {} |", cell(median(&s.other_ms)), num(full, 0));
        let _ = writeln!(o, "{row}");
    }
    let _ = writeln!(
        o,
        "\n(decode = `load_dir` inside the full job; outputs = the pictures that need no \
         heights, written while integrate runs, so the stages can sum to more than the \
         job; mesh = meshes, preview and the height pictures together; other = the rest \
         of the job, outside the longer of integrate and outputs: light check, masking the \
         arrays, the report, result.json)"
    );

    let _ = writeln!(
        o,
        "\n### Integration alone (ms, medians; the sphere's exact gradients)\n"
    );
    let _ = writeln!(
        o,
        "| size | poisson (mask-aware) | frankot-chellappa (full frame) | poisson / FC (≤ {TARGET_POISSON_OVER_FC} at 2048²) | robust-poisson | robust / poisson |"
    );
    let _ = writeln!(o, "|---|---:|---:|---:|---:|---:|");
    for s in sets {
        let (p, f, r) = (
            median(&s.poisson_ms),
            median(&s.fc_ms),
            median(&s.robust_ms),
        );
        let _ = writeln!(
            o,
            "| {}² | {} | {} | {} | {} | {} |",
            s.size,
            num(p, 0),
            num(f, 0),
            with_mark(zip2(p, f, |p, f| p / f), 2, s.size == TARGET_SIZE, |r| {
                r <= TARGET_POISSON_OVER_FC
            }),
            num(r, 0),
            num(zip2(r, p, |r, p| r / p), 2),
        );
    }

    // The default job against the l2 job.
    let _ = writeln!(
        o,
        "\n### The default job against the l2 job (ms, medians)\n"
    );
    let _ = writeln!(
        o,
        "| size × lights | l2 job ms | default job ms | default / l2 (≤ {TARGET_DEFAULT_OVER_L2} at {TARGET_SIZE}² × {TARGET_LIGHTS}) | median of the rounds' default / l2 |"
    );
    let _ = writeln!(o, "|---|---:|---:|---:|---:|");
    for s in sets {
        let (l2, default) = (median(&s.l2_job_ms), median(&s.default_job_ms));
        // Each round's two jobs ran back to back: their ratio cancels most of the
        // machine's drift between rounds (shown beside the target's ratio of medians).
        let rounds: Vec<f64> = (s.default_job_ms.iter().zip(&s.l2_job_ms))
            .map(|(d, l)| d / l)
            .collect();
        let _ = writeln!(
            o,
            "| {}² × {} | {} | {} | {} | {} |",
            s.size,
            s.lights,
            num(l2, 0),
            num(default, 0),
            with_mark(
                zip2(default, l2, |d, l| d / l),
                2,
                s.size == TARGET_SIZE && s.lights == TARGET_LIGHTS,
                |r| r <= TARGET_DEFAULT_OVER_L2
            ),
            num(median(&rounds), 2),
        );
    }
    let _ = writeln!(
        o,
        "\n(l2 job = `Options {{ solver: l2, integration: poisson, ..default }}`, the default \
         job before the robust solve became the default; default job = `Options::default()`; each is decode + \
         `pipeline::run` with the default artifacts; {} round(s), the two jobs one after \
         the other, l2 first in odd rounds and default first in even ones)",
        args.runs
    );
    let default_over_l2 = default_over_l2(sets);
    let (measured, met) = match default_over_l2 {
        Some(r) => (format!("{r:.2} ×"), mark(r <= TARGET_DEFAULT_OVER_L2)),
        None => (
            format!("not measured (no {TARGET_SIZE}² × {TARGET_LIGHTS} set)"),
            "–",
        ),
    };
    let _ = writeln!(
        o,
        "\ndefault ≤ {TARGET_DEFAULT_OVER_L2} × l2 at {TARGET_SIZE}² × {TARGET_LIGHTS}: {measured} {met}"
    );

    // Load.
    if let Some(l) = load {
        let _ = writeln!(
            o,
            "\n### Status requests while all {} workers run {}² jobs\n",
            l.workers, l.size
        );
        let _ = writeln!(
            o,
            "| requests | connections | p50 ms | p99 ms (< {TARGET_STATUS_P99_MS:.0}) | max ms | failed | jobs still running after |"
        );
        let _ = writeln!(o, "|---:|---:|---:|---:|---:|---:|---:|");
        let p99 = percentile(&l.latencies_ms, 99.0);
        let _ = writeln!(
            o,
            "| {} | {} | {:.1} | {} | {:.1} | {} {} | {} / {} |",
            l.requests,
            l.connections,
            percentile(&l.latencies_ms, 50.0),
            with_mark(Some(p99), 1, true, |p| p < TARGET_STATUS_P99_MS),
            max_of(&l.latencies_ms).unwrap_or(f64::NAN),
            l.failed,
            mark(l.failed == 0),
            l.running_after,
            l.workers
        );
        if let Some(f) = &l.first_failure {
            let _ = writeln!(o, "\nfirst failed request: {f}");
        }
    }

    // Targets.
    let _ = writeln!(o, "\n### Targets\n");
    let _ = writeln!(o, "| target | measured | met |");
    let _ = writeln!(o, "|---|---:|:---:|");
    let target = sets.iter().find(|s| s.size == TARGET_SIZE);
    let mut line = |name: &str, value: Option<f64>, digits: usize, unit: &str, ok: bool| {
        let (measured, met) = match value {
            Some(v) if v.is_finite() => (format!("{v:.digits$}{unit}"), mark(ok)),
            _ => ("not measured".to_string(), "–"),
        };
        let _ = writeln!(o, "| {name} | {measured} | {met} |");
    };
    let t_ratio =
        target.and_then(|s| zip2(median(&s.full_ms), median(&s.decode_only_ms), |f, d| f / d));
    line(
        &format!("full job ≤ {TARGET_FULL_OVER_DECODE} × decode at 2048²"),
        t_ratio,
        2,
        " ×",
        t_ratio.is_some_and(|r| r <= TARGET_FULL_OVER_DECODE),
    );
    let at_target = target.filter(|s| s.lights == 24);
    for (peaks, whose) in [
        (at_target.map(|s| &s.peak_bytes), ""),
        (
            at_target.map(|s| &s.alone_peak_bytes),
            ", the job in its own process",
        ),
    ] {
        let peak = peaks.and_then(|p| max_of(p)).map(|b| b / MB);
        line(
            &format!("peak RSS ≤ {TARGET_PEAK_MB:.0} MB at 2048² × 24{whose}"),
            peak,
            0,
            " MB",
            peak.is_some_and(|p| p <= TARGET_PEAK_MB),
        );
    }
    for s in sets.iter().filter(|_| args.http) {
        let r = zip2(median(&s.http_ms), median(&s.full_ms), |h, c| h / c);
        line(
            &format!("HTTP ≤ {TARGET_HTTP_OVER_CORE} × core at {}²", s.size),
            r,
            2,
            " ×",
            r.is_some_and(|r| r <= TARGET_HTTP_OVER_CORE),
        );
    }
    for s in sets.iter().filter(|s| !s.shared_http_ms.is_empty()) {
        let r = zip2(median(&s.shared_http_ms), median(&s.http_ms), |a, b| a / b);
        line(
            &format!(
                "HTTP on PostgreSQL + S3 ≤ {TARGET_SHARED_OVER_LOCAL} × on SQLite + data directory at {}²",
                s.size
            ),
            r,
            2,
            " ×",
            r.is_some_and(|r| r <= TARGET_SHARED_OVER_LOCAL),
        );
    }
    let t_fc = target.and_then(|s| zip2(median(&s.poisson_ms), median(&s.fc_ms), |p, f| p / f));
    line(
        &format!("poisson ≤ {TARGET_POISSON_OVER_FC} × frankot-chellappa at 2048²"),
        t_fc,
        2,
        " ×",
        t_fc.is_some_and(|r| r <= TARGET_POISSON_OVER_FC),
    );
    let t_lin = (target.filter(|_| smaller))
        .and_then(|s| zip2(s.ns_per_pixel_image(), ref_ns, |a, b| a / b));
    line(
        &format!(
            "time per pixel-image at 2048² within {:.0} % of {ref_label}",
            TARGET_LINEARITY * 100.0
        ),
        t_lin,
        2,
        " ×",
        t_lin.is_some_and(linear_enough),
    );
    line(
        &format!(
            "default job ≤ {TARGET_DEFAULT_OVER_L2} × the l2 job at {TARGET_SIZE}² × {TARGET_LIGHTS}"
        ),
        default_over_l2,
        2,
        " ×",
        default_over_l2.is_some_and(|r| r <= TARGET_DEFAULT_OVER_L2),
    );
    if let Some(l) = load {
        let p99 = percentile(&l.latencies_ms, 99.0);
        line(
            &format!("status p99 < {TARGET_STATUS_P99_MS:.0} ms under load"),
            Some(p99),
            1,
            " ms",
            p99 < TARGET_STATUS_P99_MS,
        );
        line(
            "failed status requests = 0",
            Some(l.failed as f64),
            0,
            "",
            l.failed == 0,
        );
    } else {
        line("status p99 < 50 ms under load", None, 0, "", false);
    }
    o
}

/// The default job's median time over the l2 job's at the size and light count the target
/// judges.
fn default_over_l2(sets: &[SizeResult]) -> Option<f64> {
    let s = (sets.iter()).find(|s| s.size == TARGET_SIZE && s.lights == TARGET_LIGHTS)?;
    zip2(median(&s.default_job_ms), median(&s.l2_job_ms), |d, l| {
        d / l
    })
}

/// Per-pixel-image time within ±25 % of the reference (faster by more also passes: the
/// target is about staying linear, not getting slower per pixel).
fn linear_enough(ratio: f64) -> bool {
    ratio <= 1.0 + TARGET_LINEARITY
}
