//! `bench --integrators`: each integrator's seconds on the rendered scene and on the real
//! maps.

use std::fmt::Write as _;

use super::format::heading;
use crate::bench::args::BenchArgs;

/// `bench --integrators`: the integrators' seconds per method on the rendered scene (with
/// the ratio to the orthographic `robust-poisson` reference) and on the real maps.
pub(crate) fn integrators_table(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    (rendered, real): (
        &[crate::bench::integrators::Row],
        &[crate::bench::integrators::Row],
    ),
) -> String {
    use crate::bench::integrators::METHODS;
    let mut o = String::new();
    let sizes: Vec<String> = args.sizes.iter().map(|s| s.to_string()).collect();
    heading(
        &mut o,
        "photostereo bench: integrators",
        machine,
        (load_at_start, load_at_end),
    );
    let _ = writeln!(
        o,
        "- command: `photostereo bench --integrators --sizes {} --runs {}{}`",
        sizes.join(","),
        args.runs,
        args.normal_maps
            .as_ref()
            .map_or(String::new(), |p| format!(" --normal-maps {}", p.display()))
    );
    let _ = writeln!(
        o,
        "- seconds of the integration alone (gradients, integrator, depth), median of {} \
         run(s); perspective through the scene's or the map's camera; × = over the \
         orthographic `robust-poisson` of the same normals\n",
        args.runs
    );
    let names: Vec<String> = METHODS
        .iter()
        .map(|m| serde_json::to_value(m).map_or_else(|_| format!("{m:?}"), |v| v.to_string()))
        .map(|n| n.trim_matches('"').to_string())
        .collect();
    let _ = writeln!(
        o,
        "| normals | size | orthographic robust-poisson s | {} |",
        names
            .iter()
            .map(|n| format!("perspective {n} s (×)"))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(o, "|---|---|---:|{}", "---:|".repeat(METHODS.len()));
    for row in rendered {
        let reference = row.reference.unwrap_or(f64::NAN);
        let cells: Vec<String> = (row.seconds.iter())
            .map(|s| format!("{s:.3} ({:.2}×)", s / reference))
            .collect();
        let _ = writeln!(
            o,
            "| {} | {}×{} | {reference:.3} | {} |",
            row.name,
            row.size.0,
            row.size.1,
            cells.join(" | ")
        );
    }
    if !real.is_empty() {
        let _ = writeln!(
            o,
            "\n| normal map | size | {} |",
            names
                .iter()
                .map(|n| format!("perspective {n} s"))
                .collect::<Vec<_>>()
                .join(" | ")
        );
        let _ = writeln!(o, "|---|---|{}", "---:|".repeat(METHODS.len()));
        let mut sums = vec![0.0; METHODS.len()];
        for row in real {
            for (sum, s) in sums.iter_mut().zip(&row.seconds) {
                *sum += s;
            }
            let cells: Vec<String> = row.seconds.iter().map(|s| format!("{s:.3}")).collect();
            let _ = writeln!(
                o,
                "| {} | {}×{} | {} |",
                row.name,
                row.size.0,
                row.size.1,
                cells.join(" | ")
            );
        }
        let means: Vec<String> = (sums.iter())
            .map(|s| format!("{:.3}", s / real.len() as f64))
            .collect();
        let _ = writeln!(o, "| mean | | {} |", means.join(" | "));
    }
    o
}
