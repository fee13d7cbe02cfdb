//! The seed's real data (../shared/seed-data, or `PHOTOSTEREO_SEED_DATA`), which is not in
//! the repository: a test that needs it skips on a fresh clone, saying so in one line, and
//! fails instead when `CI=true`, so that CI can never pass without running it.

#![allow(dead_code)]

use std::io::Write;
use std::path::PathBuf;

pub const SEED_SETS: [&str; 3] = ["synth-images", "sphere-images", "dog-images"];

/// A seed data set, or `None` (after printing the skip line) when it is missing outside CI.
pub fn seed_or_skip(name: &str) -> Option<PathBuf> {
    let root = std::env::var_os("PHOTOSTEREO_SEED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/seed-data"));
    let dir = root.join(name);
    if dir.join("light_directions.csv").is_file() {
        return Some(dir);
    }
    assert!(
        std::env::var("CI").as_deref() != Ok("true"),
        "seed data missing: {} (CI=true needs it; set PHOTOSTEREO_SEED_DATA=/path/to/seed-data)",
        dir.display()
    );
    let thread = std::thread::current();
    let test = thread.name().unwrap_or("a test");
    // Straight to the stderr handle: libtest captures eprintln! of passing tests, and a
    // skip nobody sees looks like a pass.
    // One write: the line must not interleave with another test's output.
    let line = format!(
        "SKIPPED {test}: no seed data at {} (set PHOTOSTEREO_SEED_DATA=/path/to/seed-data)\n",
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
    let root = std::env::var_os("PHOTOSTEREO_REAL_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/real"));
    let dir = root.join(name);
    if dir.join("NOTE.txt").is_file() {
        return Some(dir);
    }
    assert!(
        std::env::var("CI").as_deref() != Ok("true"),
        "real captures missing: {} (CI=true needs them; set PHOTOSTEREO_REAL_DATA=/path/to/real)",
        dir.display()
    );
    let thread = std::thread::current();
    let test = thread.name().unwrap_or("a test");
    let line = format!(
        "SKIPPED {test}: no real captures at {} (set PHOTOSTEREO_REAL_DATA=/path/to/real)\n",
        root.display()
    );
    let _ = std::io::stderr().write_all(line.as_bytes());
    None
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
