//! The tables' shared formatting: numbers or a dash, ✓/✗ marks, and each table's heading.

use std::fmt::Write as _;

pub(super) fn zip2(a: Option<f64>, b: Option<f64>, f: impl Fn(f64, f64) -> f64) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b != 0.0 => Some(f(a, b)),
        _ => None,
    }
}

pub(super) fn num(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(v) if v.is_finite() => format!("{v:.digits$}"),
        _ => "–".into(),
    }
}

pub(super) fn mark(ok: bool) -> &'static str {
    if ok { "✓" } else { "✗" }
}

/// The number, followed by ✓/✗ when `judged`.
pub(super) fn with_mark(
    v: Option<f64>,
    digits: usize,
    judged: bool,
    ok: impl Fn(f64) -> bool,
) -> String {
    match v {
        Some(x) if x.is_finite() && judged => format!("{x:.digits$} {}", mark(ok(x))),
        _ => num(v, digits),
    }
}

/// A table's title and the machine line: what ran it, and its load before and after.
pub(super) fn heading(o: &mut String, title: &str, machine: &str, (start, end): (&str, &str)) {
    let _ = writeln!(o, "## {title}\n");
    let _ = writeln!(
        o,
        "- machine: {machine}; load average {start} at the start, {end} at the end"
    );
}
