//! `bench --light-sweep`: per size, each light count's time, time per pixel-image and
//! peak memory against the fewest lights, and the jobs of an `--against` binary beside.

use std::fmt::Write as _;

use super::format::heading;
use crate::bench::args::{BenchArgs, SweepScene};
use crate::bench::memory::MB;
use crate::bench::stats::{max_of, median};

// The light-count sweep's targets: memory that does not grow with the image count, and a
// cost per pixel-image that stays flat.
const TARGET_SWEEP_PEAK_RATIO: f64 = 1.3;
const TARGET_SWEEP_FLAT: f64 = 0.25;

/// The `--light-sweep` table: per size, each light count's median time, time per
/// pixel-image and peak RSS, against the fewest lights of that size.
pub(crate) fn sweep_table(
    args: &BenchArgs,
    machine: &str,
    (load_at_start, load_at_end): (&str, &str),
    points: &[crate::bench::sweep::Point],
) -> String {
    let mut o = String::new();
    let list = |v: &[usize]| {
        v.iter()
            .map(|s| s.to_string())
            .collect::<Vec<_>>()
            .join(",")
    };
    heading(
        &mut o,
        "photostereo bench: light-count sweep",
        machine,
        (load_at_start, load_at_end),
    );
    // The scene's flag on the command line, and what it renders.
    let (flag, scene) = match args.sweep_scene {
        SweepScene::Sphere => ("", "`synth::Scene::sphere(size)` (matte)"),
        SweepScene::Glossy => (
            " --sweep-scene glossy",
            "`synth::Scene::dark_sphere(size)` under `synth::glossy_coat()` (res/glossy's GGX coat)",
        ),
    };
    let _ = writeln!(
        o,
        "- command: `photostereo bench --sizes {} --light-sweep {} --runs {}{}{}{}`",
        list(&args.sizes),
        list(&args.light_sweep),
        args.runs,
        args.against
            .as_ref()
            .map_or(String::new(), |p| format!(" --against {}", p.display())),
        if args.sweep_options.is_empty() {
            String::new()
        } else {
            format!(" --sweep-options '{}'", args.sweep_options.join(" "))
        },
        flag,
    );
    let _ = writeln!(
        o,
        "- each run: the default job (with --sweep-options) as `photostereo reconstruct` in a process of its own on \
         {scene} under `light_rings(n, 10, 60)` (16-bit gray PNG); wall \
         time of the process and its peak RSS (`wait4`); medians of {} run(s); MB = 10⁶ bytes",
        args.runs
    );
    let _ = writeln!(
        o,
        "- stages per pixel: mask, integration (with the pictures written beside it) and mesh, \
         from each run's result.json, paid once whatever the image count; each added image: \
         the step in the median job time from the row above, over the pixel-images added\n"
    );
    let _ = writeln!(
        o,
        "| size × lights | job ms | stages per pixel ms | job: ns per pixel-image | × fewest lights | each added image: ns per pixel-image | × first step | peak RSS MB | × fewest lights |"
    );
    let _ = writeln!(o, "|---|---|---|---|---|---|---|---|---|");
    let mut verdicts = Vec::new();
    for &size in &args.sizes {
        let of_size: Vec<_> = points.iter().filter(|p| p.size == size).collect();
        let Some(first) = of_size.first() else {
            continue;
        };
        let job = |p: &crate::bench::sweep::Point| median(&p.ms).map(|m| p.ns_per_pixel_image(m));
        // None for the first light count, and for a second one when only one was swept.
        let added = |i: usize| {
            let before = of_size.get(i.checked_sub(1)?)?;
            of_size.get(i)?.ns_per_added_pixel_image(before)
        };
        let first_step = added(1);
        let peak = |p: &crate::bench::sweep::Point| max_of(&p.peak_bytes);
        let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) if b > 0.0 => Some(a / b),
            _ => None,
        };
        let (mut job_low, mut job_high) = (1f64, 1f64);
        let (mut added_off, mut worst_peak) = (0f64, 0f64);
        for (i, p) in of_size.iter().enumerate() {
            let tj = ratio(job(p), job(first));
            let ta = ratio(added(i), first_step);
            let m = ratio(peak(p), peak(first));
            job_low = job_low.min(tj.unwrap_or(1.0));
            job_high = job_high.max(tj.unwrap_or(1.0));
            added_off = added_off.max(ta.map_or(0.0, |r| (r - 1.0).abs()));
            worst_peak = worst_peak.max(m.unwrap_or(0.0));
            let f = |v: Option<f64>, d: usize| v.map_or("–".into(), |v| format!("{v:.d$}"));
            let _ = writeln!(
                o,
                "| {size}² × {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                p.lights,
                f(median(&p.ms), 0),
                f(median(&p.per_pixel_ms), 0),
                f(job(p), 2),
                f(tj, 2),
                f(added(i), 2),
                f(ta, 2),
                f(peak(p).map(|b| b / MB), 0),
                f(m, 2),
            );
        }
        let met = |ok: bool| if ok { "met" } else { "not met" };
        let flat = if of_size.len() < 3 {
            "not measured: it takes three light counts or more".to_string()
        } else {
            format!(
                "within {:.0} % of the first step (target ≤ {:.0} %: {})",
                added_off * 100.0,
                TARGET_SWEEP_FLAT * 100.0,
                met(added_off <= TARGET_SWEEP_FLAT),
            )
        };
        verdicts.push(format!(
            "- {size}²: peak RSS at most {worst_peak:.2} × that of {} lights (target ≤ \
             {TARGET_SWEEP_PEAK_RATIO}: {}); time per pixel-image of each added image {flat}; \
             of the whole job, {job_low:.2}–{job_high:.2} × that of {} lights (its stages per \
             pixel are paid once, whatever the image count)",
            first.lights,
            met(worst_peak <= TARGET_SWEEP_PEAK_RATIO),
            first.lights,
        ));
    }
    let _ = writeln!(o);
    for v in verdicts {
        let _ = writeln!(o, "{v}");
    }
    if let Some(other) = &args.against {
        against_table(&mut o, other, points);
    }
    o
}

/// The same jobs by the `--against` binary, run alternately with this one's.
fn against_table(o: &mut String, other: &std::path::Path, points: &[crate::bench::sweep::Point]) {
    let _ = writeln!(
        o,
        "\nAgainst `{}` (each round runs both binaries, which goes first alternating):\n",
        other.display()
    );
    let _ = writeln!(
        o,
        "| size × lights | job ms | --against job ms | job / --against | peak RSS MB | --against peak RSS MB |"
    );
    let _ = writeln!(o, "|---|---|---|---|---|---|");
    let f = |v: Option<f64>, d: usize| v.map_or("–".into(), |v| format!("{v:.d$}"));
    for p in points {
        let (a, b) = (median(&p.ms), median(&p.against_ms));
        let ratio = a.zip(b).map(|(a, b)| a / b);
        let _ = writeln!(
            o,
            "| {}² × {} | {} | {} | {} | {} | {} |",
            p.size,
            p.lights,
            f(a, 0),
            f(b, 0),
            f(ratio, 2),
            f(max_of(&p.peak_bytes).map(|b| b / MB), 0),
            f(max_of(&p.against_peak_bytes).map(|b| b / MB), 0),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::args::parse;
    use crate::bench::sweep::Point;

    fn point(lights: usize, ms: f64) -> Point {
        Point {
            size: 64,
            lights,
            ms: vec![ms],
            per_pixel_ms: vec![1.0],
            peak_bytes: vec![2e7],
            against_ms: Vec::new(),
            against_peak_bytes: Vec::new(),
        }
    }

    /// One light count has no added image to show, and three show each step.
    #[test]
    fn the_table_takes_any_number_of_light_counts() {
        let args = parse(&["--sizes", "64", "--light-sweep", "24"]).unwrap();
        let one = sweep_table(&args, "test", ("0", "0"), &[point(24, 10.0)]);
        assert!(one.contains("| 64² × 24 | 10 |"), "{one}");
        assert!(
            one.contains("not measured: it takes three light counts"),
            "{one}"
        );
        let three = [point(8, 5.0), point(16, 8.0), point(24, 11.0)];
        let table = sweep_table(&args, "test", ("0", "0"), &three);
        assert_eq!(table.matches("| 64² × ").count(), 3, "{table}");
        assert!(table.contains("within 0 % of the first step"), "{table}");
        let glossy = parse(&[
            "--sizes",
            "64",
            "--light-sweep",
            "24",
            "--sweep-scene",
            "glossy",
        ]);
        let glossy = sweep_table(&glossy.unwrap(), "test", ("0", "0"), &three);
        assert!(
            glossy.contains("--runs 3 --sweep-scene glossy`"),
            "{glossy}"
        );
        assert!(glossy.contains("under `synth::glossy_coat()`"), "{glossy}");
    }
}
