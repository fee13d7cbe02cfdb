//! The seed's real data (../shared/seed-data, or `PHOTOSTEREO_SEED_DATA`), which is not in
//! the repository: a test that needs it skips on a fresh clone, saying so in one line, and
//! fails instead when `CI=true`, so that CI can never pass without running it.

#![allow(dead_code)]

use std::io::Write;
use std::path::PathBuf;

pub const SEED_SETS: [&str; 3] = ["synth-images", "sphere-images", "dog-images"];

/// A seed data set, or `None` (after printing the skip line) when it is missing outside CI.
pub fn seed_or_skip(name: &str) -> Option<PathBuf> {
    found_or_skip(
        "PHOTOSTEREO_SEED_DATA",
        "seed-data",
        name,
        "light_directions.csv",
        "seed data",
    )
}

/// `root/name` when it holds `marker` (root: `$env`, or `../shared/<shared>` beside the
/// crate); otherwise fail under `CI=true`, or print the skip line and return `None`.
fn found_or_skip(env: &str, shared: &str, name: &str, marker: &str, what: &str) -> Option<PathBuf> {
    let root = std::env::var_os(env).map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../shared")
            .join(shared)
    });
    let dir = root.join(name);
    if dir.join(marker).is_file() {
        return Some(dir);
    }
    assert!(
        std::env::var("CI").as_deref() != Ok("true"),
        "{what} missing: {} (CI=true needs it; set {env}=/path/to/{shared})",
        dir.display()
    );
    let thread = std::thread::current();
    let test = thread.name().unwrap_or("a test");
    // Straight to the stderr handle, in one write: libtest captures eprintln! of passing
    // tests, and a skip nobody sees (or split by another test's output) looks like a pass.
    let line = format!(
        "SKIPPED {test}: no {what} at {} (set {env}=/path/to/{shared})\n",
        root.display()
    );
    let _ = std::io::stderr().write_all(line.as_bytes());
    None
}

/// `seed!("synth-images")`: the set's path, or return from the test (skipped).
#[allow(unused_macros)]
macro_rules! seed {
    ($name:expr) => {
        match $crate::seed::seed_or_skip($name) {
            Some(dir) => dir,
            None => return,
        }
    };
}
#[allow(unused_imports)]
pub(crate) use seed;

/// A real capture under `../shared/real` (or `PHOTOSTEREO_REAL_DATA`), e.g.
/// `chrome/psbox-probe1`, found and skipped exactly as the seed data is.
pub fn real_or_skip(name: &str) -> Option<PathBuf> {
    found_or_skip(
        "PHOTOSTEREO_REAL_DATA",
        "real",
        name,
        "NOTE.txt",
        "real captures",
    )
}

/// `real!("chrome/psbox-probe1")`: the capture's path, or return from the test (skipped).
#[allow(unused_macros)]
macro_rules! real {
    ($name:expr) => {
        match $crate::seed::real_or_skip($name) {
            Some(dir) => dir,
            None => return,
        }
    };
}
#[allow(unused_imports)]
pub(crate) use real;
