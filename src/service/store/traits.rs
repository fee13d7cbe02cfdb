//! What a store does ([`BlobStore`]) and the values its methods take and give.
//!
//! The reconstruction core reads and writes local files, so every store stages uploads
//! and outputs in local directories and hands a job its inputs as one; a remote store
//! ([`S3Store`](super::S3Store)) uploads them at commit and fetches a job's inputs back
//! for its worker. The methods block (callers are worker threads and the blocking pool),
//! except [`BlobStore::read`], which serves downloads from the async handlers.

use std::ops::Range;
use std::path::{Path, PathBuf};

use axum::body::Bytes;
use futures_util::future::BoxFuture;
use futures_util::stream::BoxStream;
use uuid::Uuid;

use super::error::Result;
use crate::service::repo::ArtifactInfo;

/// A stored file that the service serves.
#[derive(Debug, Clone, Copy)]
pub enum Served<'a> {
    /// A succeeded job's artifact, as its record lists it.
    Artifact { job: Uuid, info: &'a ArtifactInfo },
    /// One of a calibration's files, as its record lists it.
    Calibration { id: Uuid, info: &'a ArtifactInfo },
}

impl Served<'_> {
    pub fn info(&self) -> &ArtifactInfo {
        match self {
            Served::Artifact { info, .. } | Served::Calibration { info, .. } => info,
        }
    }
}

/// A download's bytes, in order.
pub type ByteStream = BoxStream<'static, Result<Bytes>>;

/// Artifacts in a local directory, for the code that reads files (re-shading). A copy
/// fetched from a remote store is removed on drop.
pub struct LocalArtifacts {
    dir: PathBuf,
    fetched: bool,
}

impl LocalArtifacts {
    /// A copy made for this caller, removed on drop.
    pub(super) fn fetched(dir: PathBuf) -> Self {
        Self { dir, fetched: true }
    }

    /// The store's own directory, kept.
    pub(super) fn kept(dir: PathBuf) -> Self {
        Self {
            dir,
            fetched: false,
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

impl Drop for LocalArtifacts {
    fn drop(&mut self) {
        if self.fetched {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// Where job inputs, artifacts and calibration files live.
pub trait BlobStore: Send + Sync + 'static {
    /// A fresh, empty local directory to receive a job's upload into.
    fn stage_inputs(&self, id: Uuid) -> Result<PathBuf>;
    /// Make the staged upload the job's inputs (durably).
    fn commit_inputs(&self, id: Uuid) -> Result<()>;
    /// Whether the job's committed inputs are there (its manifest is written last).
    fn has_inputs(&self, id: Uuid) -> Result<bool>;
    /// The committed inputs in a local directory, fetched from the store when it keeps
    /// them elsewhere (for the worker that runs the job), except the files `have(name)`
    /// says the worker needs no copy of (images the upload's first pass already decoded).
    fn fetch_inputs(&self, id: Uuid, have: &dyn Fn(&str) -> bool) -> Result<PathBuf>;
    fn remove_inputs(&self, id: Uuid) -> Result<()>;
    /// A fresh, empty local directory for a reconstruction to write into.
    fn stage_outputs(&self, id: Uuid) -> Result<PathBuf>;
    /// Make the staged outputs the job's artifacts for this attempt, all at once
    /// (durably), setting each one's `key` where the store keeps it under its own name.
    fn commit_outputs(&self, id: Uuid, attempt: &str, artifacts: &mut [ArtifactInfo])
    -> Result<()>;
    /// Remove the attempt's staged and committed outputs.
    fn discard_outputs(&self, id: Uuid, attempt: &str) -> Result<()>;
    /// Bytes `range` (all when `None`) of a stored file.
    fn read(
        &self,
        file: Served<'_>,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'static, Result<ByteStream>>;
    /// A succeeded job's artifacts in a local directory.
    fn local_artifacts(&self, id: Uuid, artifacts: &[&ArtifactInfo]) -> Result<LocalArtifacts>;
    /// Remove everything of a job, every attempt's outputs too (a missing job is not an
    /// error).
    fn remove_job(&self, id: Uuid) -> Result<()>;
    /// Every job that has files which no upload in flight can still be writing.
    fn job_ids(&self) -> Result<Vec<Uuid>>;
    /// Remove what an interrupted upload or reconstruction left behind.
    fn remove_partials(&self, id: Uuid) -> Result<()>;
    /// Bytes available to this process on the local file system it stages on.
    fn free_bytes(&self) -> Result<u64>;
    /// Write and remove a probe (locally, and in the store).
    fn probe_writable(&self) -> Result<()>;
    /// A fresh, empty local directory to receive a calibration's upload and make its
    /// files in.
    fn stage_calibration(&self, id: Uuid) -> Result<PathBuf>;
    /// Make the staged directory the calibration's files (durably).
    fn commit_calibration(&self, id: Uuid) -> Result<()>;
    /// Remove everything of a calibration (a missing one is not an error).
    fn remove_calibration(&self, id: Uuid) -> Result<()>;
    /// Every calibration that has files which no upload in flight can still be writing.
    fn calibration_ids(&self) -> Result<Vec<Uuid>>;
}
