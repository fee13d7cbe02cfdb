//! `bench --near`: the near-light job against the distant one, per size.

use std::fmt::Write as _;

use super::format::heading;
use crate::bench::args::BenchArgs;
use crate::bench::memory::MB;

/// `bench --near`: the near-light job against the distant one, per size.
pub(crate) fn near_table(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    rows: &[crate::bench::near::Row],
) -> String {
    let mut o = String::new();
    heading(
        &mut o,
        "photostereo bench: near lights",
        machine,
        (load_at_start, load_at_end),
    );
    let sizes: Vec<String> = args.sizes.iter().map(|s| s.to_string()).collect();
    let _ = writeln!(
        o,
        "- command: `photostereo bench --near --sizes {} --runs {}`",
        sizes.join(","),
        args.runs
    );
    let _ = writeln!(
        o,
        "- `photostereo reconstruct` in a child process on the rendered ring of {} LEDs over a \
         relief plate: with the LEDs' positions (near) and with the best distant table \
         (distant), the same 16-bit images; medians of {} run(s), alternating; wall clock and \
         peak resident memory\n",
        crate::bench::near::LEDS,
        args.runs
    );
    let _ = writeln!(
        o,
        "| size | distant s | near s | × | distant peak MB | near peak MB | × |"
    );
    let _ = writeln!(o, "|---|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let _ = writeln!(
            o,
            "| {0}×{0} | {1:.2} | {2:.2} | {3:.2} | {4:.0} | {5:.0} | {6:.2} |",
            r.size,
            r.distant.0,
            r.near.0,
            r.near.0 / r.distant.0,
            r.distant.1 / MB,
            r.near.1 / MB,
            r.near.1 / r.distant.1
        );
    }
    o
}
