//! Where a job's and a calibration's files live, in a directory (the data directory, or a
//! remote store's scratch) and under an object store's prefix:
//!
//! ```text
//! jobs/{id}/input.partial/   an upload being received (removed if it fails)
//! jobs/{id}/input/           manifest.json, lights.txt, 000.img, 001.img, …, mask.img
//!                            (a normals job: manifest.json, normals.img, mask.img)
//! jobs/{id}/output.partial/  a reconstruction being written
//! jobs/{id}/output/          the finished artifacts (renamed from output.partial at once)
//! calibrations/{id}/files.partial/  a calibration's upload and files being made
//! calibrations/{id}/files/          its lights.csv, overlay.png, lights.png[, positions.csv]
//! ```
//!
//! ```text
//! {prefix}/jobs/{id}/input/{file}              a job's inputs (manifest.json uploaded last)
//! {prefix}/jobs/{id}/outputs/{attempt}/{name}  an attempt's artifacts (the record keeps each key)
//! {prefix}/calibrations/{id}/{name}            a calibration's lights.csv, overlay.png, lights.png[, positions.csv]
//! {prefix}/probes/{random}                     a readiness probe, removed at once
//! ```
//!
//! Nothing a caller sends ever becomes a path or a key: directories are named by the
//! job's UUID, files by the service.

use std::path::{Path, PathBuf};

use object_store::path::Path as Key;
use uuid::Uuid;

/// The top-level folders, in a directory and under a prefix alike.
pub(super) const JOBS: &str = "jobs";
pub(super) const CALIBRATIONS: &str = "calibrations";

/// A job's folders.
pub(super) const INPUT: &str = "input";
pub(super) const INPUT_PARTIAL: &str = "input.partial";
pub(super) const OUTPUT: &str = "output";
pub(super) const OUTPUT_PARTIAL: &str = "output.partial";
/// An object store's attempts, each under its own name.
pub(super) const OUTPUTS: &str = "outputs";

/// A calibration's folders in a directory.
pub(super) const FILES: &str = "files";
pub(super) const FILES_PARTIAL: &str = "files.partial";

/// Readiness probes under a prefix.
pub(super) const PROBES: &str = "probes";

/// The layout in a local directory.
#[derive(Debug, Clone)]
pub(super) struct Dirs {
    root: PathBuf,
}

impl Dirs {
    pub(super) fn new(root: &Path) -> Self {
        Self {
            root: root.to_path_buf(),
        }
    }

    pub(super) fn root(&self) -> &Path {
        &self.root
    }

    /// `jobs/`
    pub(super) fn jobs(&self) -> PathBuf {
        self.root.join(JOBS)
    }

    /// `calibrations/`
    pub(super) fn calibrations(&self) -> PathBuf {
        self.root.join(CALIBRATIONS)
    }

    /// `jobs/{id}/`
    pub(super) fn job(&self, id: Uuid) -> PathBuf {
        self.jobs().join(id.to_string())
    }

    /// `calibrations/{id}/`
    pub(super) fn calibration(&self, id: Uuid) -> PathBuf {
        self.calibrations().join(id.to_string())
    }
}

/// The layout under an object store's prefix.
#[derive(Debug, Clone)]
pub(super) struct Keys {
    /// The key prefix every object of this service starts with (may be empty).
    prefix: Key,
}

impl Keys {
    pub(super) fn new(prefix: &str) -> Self {
        Self {
            prefix: Key::from(prefix),
        }
    }

    /// `{prefix}/{parts…}`
    pub(super) fn key(&self, parts: &[&str]) -> Key {
        parts
            .iter()
            .fold(self.prefix.clone(), |key, part| key.join(*part))
    }

    /// `{prefix}/jobs/{id}/{parts…}`
    pub(super) fn job(&self, id: Uuid, parts: &[&str]) -> Key {
        self.under(JOBS, id, parts)
    }

    /// `{prefix}/calibrations/{id}/{parts…}`
    pub(super) fn calibration(&self, id: Uuid, parts: &[&str]) -> Key {
        self.under(CALIBRATIONS, id, parts)
    }

    fn under(&self, kind: &str, id: Uuid, parts: &[&str]) -> Key {
        let id = id.to_string();
        let mut all = vec![kind, id.as_str()];
        all.extend_from_slice(parts);
        self.key(&all)
    }
}
