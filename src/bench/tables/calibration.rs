//! `bench --calibration`: one calibration's time and peak memory against the targets.

use std::fmt::Write as _;

use super::format::heading;
use crate::bench::args::BenchArgs;
use crate::bench::memory::MB;

/// `bench --calibration`: time and peak memory of one calibration, against the targets.
pub(crate) fn calibration_table(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    m: &crate::bench::calibration::Measured,
) -> String {
    use crate::bench::calibration::{HEIGHT, WIDTH};
    let mut o = String::new();
    heading(
        &mut o,
        "photostereo bench: calibration",
        machine,
        (load_at_start, load_at_end),
    );
    let _ = writeln!(
        o,
        "- command: `photostereo bench --calibration --runs {}`",
        args.runs
    );
    let _ = writeln!(
        o,
        "- `photostereo calibrate` in a child process, the ball's true circle given (median \
         of {} run(s)) and its outline found automatically (one run): wall clock, peak \
         resident memory, the lights' error against the rendered truth\n",
        args.runs
    );
    let _ = writeln!(
        o,
        "| images | size | outline | seconds | target s | peak MB | target MB | lights mean / max ° |"
    );
    let _ = writeln!(o, "|---:|---|---|---:|---:|---:|---:|---|");
    let size = format!("{WIDTH}×{HEIGHT} ({:.0} MP, 8-bit JPEG)", m.megapixels);
    let (seconds, peak) = m.given_medians();
    let lights =
        |r: &crate::bench::calibration::Run| format!("{:.3} / {:.3}", r.mean_deg, r.max_deg);
    let _ = writeln!(
        o,
        "| {} | {size} | given, median of {} | {seconds:.2} | 15 | {:.0} | 1500 | {} |",
        m.images,
        m.given.len(),
        peak / MB,
        m.given.last().map_or("–".into(), lights)
    );
    match &m.automatic {
        Ok(r) => {
            let _ = writeln!(
                o,
                "| {} | {size} | found, 1 run | {:.2} | 15 | {:.0} | 1500 | {} |",
                m.images,
                r.seconds,
                r.peak_bytes.unwrap_or(f64::NAN) / MB,
                lights(r)
            );
        }
        Err(e) => {
            let _ = writeln!(
                o,
                "| {} | {size} | found: **failed** | – | 15 | – | 1500 | {} |",
                m.images,
                e.replace('|', "/")
            );
        }
    }
    o
}
