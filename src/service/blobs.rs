//! Job bytes behind [`BlobStore`]; [`LocalStore`] keeps them under `{data}/jobs/{id}/`:
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
//! The reconstruction core reads and writes local files, so every store stages uploads
//! and outputs in local directories and hands a job its inputs as one; a remote store
//! ([`super::s3::S3Store`]) uploads them at commit and fetches a job's inputs back for
//! its worker. Nothing a caller sends ever becomes a path or a key: directories are
//! named by the job's UUID, files by the service.
//!
//! The methods block (callers are worker threads and the blocking pool), except
//! [`BlobStore::read`], which serves downloads from the async handlers.

use std::io;
use std::ops::Range;
use std::path::{Path, PathBuf};

use axum::body::Bytes;
use futures_util::future::BoxFuture;
use futures_util::stream::BoxStream;
use serde::{Deserialize, Serialize};
use uuid::Uuid;

use super::repo::ArtifactInfo;
use super::util::sync_dir;
use crate::core::normalmap::Convention;

/// File names inside a job's input directory.
pub const MANIFEST_FILE: &str = "manifest.json";
pub const LIGHTS_FILE: &str = "lights.txt";
pub const MASK_FILE: &str = "mask.img";
pub const NORMALS_FILE: &str = "normals.img";

/// Name of the `i`-th stored input image.
pub fn image_file(i: usize) -> String {
    format!("{i:03}.img")
}

/// What the input directory holds: table names → stored files.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub images: Vec<ManifestEntry>,
    pub mask: Option<ManifestEntry>,
    /// A normals job's normal map (its `images` are then empty and there is no light
    /// table).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normals: Option<NormalsEntry>,
    /// What the upload ignored or chose (an archive's unnamed images, say), for the
    /// job's `result.json`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ManifestEntry {
    /// The name the light table uses (or the mask part's file name).
    pub name: String,
    /// The stored file, relative to the input directory.
    pub file: String,
}

/// A normals job's normal map and how its green channel points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalsEntry {
    /// The `normals` part's file name.
    pub name: String,
    /// The stored file, relative to the input directory.
    pub file: String,
    pub convention: Convention,
}

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
pub type ByteStream = BoxStream<'static, io::Result<Bytes>>;

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

/// The object store did not answer (or refused): the request may succeed later, so the
/// service answers 503 and a job waits rather than fails. Carried inside an
/// [`io::Error`]; see [`is_unavailable`].
#[derive(Debug, thiserror::Error)]
#[error("the object store is unavailable: {0}")]
pub struct Unavailable(pub String);

/// Whether `e` says the store is unavailable for now.
pub fn is_unavailable(e: &io::Error) -> bool {
    e.get_ref().is_some_and(|inner| inner.is::<Unavailable>())
}

/// Where job inputs, artifacts and calibration files live.
pub trait BlobStore: Send + Sync + 'static {
    /// A fresh, empty local directory to receive a job's upload into.
    fn stage_inputs(&self, id: Uuid) -> io::Result<PathBuf>;
    /// Make the staged upload the job's inputs (durably).
    fn commit_inputs(&self, id: Uuid) -> io::Result<()>;
    /// Whether the job's committed inputs are there (its manifest is written last).
    fn has_inputs(&self, id: Uuid) -> io::Result<bool>;
    /// The committed inputs in a local directory, fetched from the store when it keeps
    /// them elsewhere (for the worker that runs the job), except the files `have(name)`
    /// says the worker needs no copy of (images the upload's first pass already decoded).
    fn fetch_inputs(&self, id: Uuid, have: &dyn Fn(&str) -> bool) -> io::Result<PathBuf>;
    fn remove_inputs(&self, id: Uuid) -> io::Result<()>;
    /// A fresh, empty local directory for a reconstruction to write into.
    fn stage_outputs(&self, id: Uuid) -> io::Result<PathBuf>;
    /// Make the staged outputs the job's artifacts for this attempt, all at once
    /// (durably), setting each one's `key` where the store keeps it under its own name.
    fn commit_outputs(
        &self,
        id: Uuid,
        attempt: &str,
        artifacts: &mut [ArtifactInfo],
    ) -> io::Result<()>;
    /// Remove the attempt's staged and committed outputs.
    fn discard_outputs(&self, id: Uuid, attempt: &str) -> io::Result<()>;
    /// Bytes `range` (all when `None`) of a stored file.
    fn read(
        &self,
        file: Served<'_>,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'static, io::Result<ByteStream>>;
    /// A succeeded job's artifacts in a local directory.
    fn local_artifacts(&self, id: Uuid, artifacts: &[&ArtifactInfo]) -> io::Result<LocalArtifacts>;
    /// Remove everything of a job, every attempt's outputs too (a missing job is not an
    /// error).
    fn remove_job(&self, id: Uuid) -> io::Result<()>;
    /// Every job that has files which no upload in flight can still be writing.
    fn job_ids(&self) -> io::Result<Vec<Uuid>>;
    /// Remove what an interrupted upload or reconstruction left behind.
    fn remove_partials(&self, id: Uuid) -> io::Result<()>;
    /// Bytes available to this process on the local file system it stages on.
    fn free_bytes(&self) -> io::Result<u64>;
    /// Write and remove a probe (locally, and in the store).
    fn probe_writable(&self) -> io::Result<()>;
    /// A fresh, empty local directory to receive a calibration's upload and make its
    /// files in.
    fn stage_calibration(&self, id: Uuid) -> io::Result<PathBuf>;
    /// Make the staged directory the calibration's files (durably).
    fn commit_calibration(&self, id: Uuid) -> io::Result<()>;
    /// Remove everything of a calibration (a missing one is not an error).
    fn remove_calibration(&self, id: Uuid) -> io::Result<()>;
    /// Every calibration that has files which no upload in flight can still be writing.
    fn calibration_ids(&self) -> io::Result<Vec<Uuid>>;
}

/// [`BlobStore`] in a local directory.
pub struct LocalStore {
    root: PathBuf,
    calibrations: PathBuf,
}

impl LocalStore {
    pub fn open(data_dir: &Path) -> io::Result<Self> {
        let root = data_dir.join("jobs");
        let calibrations = data_dir.join("calibrations");
        std::fs::create_dir_all(&root)?;
        std::fs::create_dir_all(&calibrations)?;
        Ok(Self { root, calibrations })
    }

    fn job(&self, id: Uuid) -> PathBuf {
        self.root.join(id.to_string())
    }

    fn fresh_dir(path: &Path) -> io::Result<()> {
        remove_dir_if_exists(path)?;
        std::fs::create_dir_all(path)
    }

    /// Sync every file in `dir`, then rename it to `to` and sync the parent.
    fn commit_dir(from: &Path, to: &Path) -> io::Result<()> {
        for entry in std::fs::read_dir(from)? {
            let entry = entry?;
            if entry.file_type()?.is_file() {
                std::fs::File::open(entry.path())?.sync_all()?;
            }
        }
        sync_dir(from)?;
        remove_dir_if_exists(to)?;
        std::fs::rename(from, to)?;
        if let Some(parent) = to.parent() {
            sync_dir(parent)?;
        }
        Ok(())
    }
}

fn remove_dir_if_exists(path: &Path) -> io::Result<()> {
    match std::fs::remove_dir_all(path) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

impl BlobStore for LocalStore {
    fn stage_inputs(&self, id: Uuid) -> io::Result<PathBuf> {
        let dir = self.job(id).join("input.partial");
        Self::fresh_dir(&dir)?;
        Ok(dir)
    }

    fn commit_inputs(&self, id: Uuid) -> io::Result<()> {
        let job = self.job(id);
        Self::commit_dir(&job.join("input.partial"), &job.join("input"))?;
        sync_dir(&self.root)
    }

    fn has_inputs(&self, id: Uuid) -> io::Result<bool> {
        Ok(self.job(id).join("input").join(MANIFEST_FILE).is_file())
    }

    fn fetch_inputs(&self, id: Uuid, _have: &dyn Fn(&str) -> bool) -> io::Result<PathBuf> {
        Ok(self.job(id).join("input"))
    }

    fn remove_inputs(&self, id: Uuid) -> io::Result<()> {
        remove_dir_if_exists(&self.job(id).join("input"))
    }

    fn stage_outputs(&self, id: Uuid) -> io::Result<PathBuf> {
        let dir = self.job(id).join("output.partial");
        Self::fresh_dir(&dir)?;
        Ok(dir)
    }

    /// One server per data directory runs a job's attempts one after another, so the
    /// attempt's outputs are the job's `output/`.
    fn commit_outputs(&self, id: Uuid, _: &str, _: &mut [ArtifactInfo]) -> io::Result<()> {
        let job = self.job(id);
        Self::commit_dir(&job.join("output.partial"), &job.join("output"))
    }

    fn discard_outputs(&self, id: Uuid, _: &str) -> io::Result<()> {
        let job = self.job(id);
        remove_dir_if_exists(&job.join("output.partial"))?;
        remove_dir_if_exists(&job.join("output"))
    }

    fn read(
        &self,
        file: Served<'_>,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'static, io::Result<ByteStream>> {
        let path = match file {
            Served::Artifact { job, info } => self.job(job).join("output").join(&info.name),
            Served::Calibration { id, info } => self
                .calibrations
                .join(id.to_string())
                .join("files")
                .join(&info.name),
        };
        Box::pin(async move {
            use futures_util::StreamExt;
            use tokio::io::{AsyncReadExt, AsyncSeekExt};
            let mut file = tokio::fs::File::open(&path).await?;
            let stream = match range {
                None => tokio_util::io::ReaderStream::new(file).boxed(),
                Some(r) => {
                    file.seek(io::SeekFrom::Start(r.start)).await?;
                    tokio_util::io::ReaderStream::new(file.take(r.end - r.start)).boxed()
                }
            };
            Ok(stream)
        })
    }

    fn local_artifacts(&self, id: Uuid, _: &[&ArtifactInfo]) -> io::Result<LocalArtifacts> {
        Ok(LocalArtifacts {
            dir: self.job(id).join("output"),
            fetched: false,
        })
    }

    fn remove_job(&self, id: Uuid) -> io::Result<()> {
        remove_dir_if_exists(&self.job(id))
    }

    fn job_ids(&self) -> io::Result<Vec<Uuid>> {
        uuid_dirs(&self.root)
    }

    fn remove_partials(&self, id: Uuid) -> io::Result<()> {
        let job = self.job(id);
        remove_dir_if_exists(&job.join("input.partial"))?;
        remove_dir_if_exists(&job.join("output.partial"))
    }

    fn free_bytes(&self) -> io::Result<u64> {
        free_bytes(&self.root)
    }

    fn probe_writable(&self) -> io::Result<()> {
        let probe = self
            .root
            .join(format!(".probe-{}", Uuid::new_v4().simple()));
        std::fs::write(&probe, b"ok")?;
        std::fs::remove_file(&probe)
    }

    fn stage_calibration(&self, id: Uuid) -> io::Result<PathBuf> {
        let dir = self.calibrations.join(id.to_string()).join("files.partial");
        Self::fresh_dir(&dir)?;
        Ok(dir)
    }

    fn commit_calibration(&self, id: Uuid) -> io::Result<()> {
        let dir = self.calibrations.join(id.to_string());
        Self::commit_dir(&dir.join("files.partial"), &dir.join("files"))?;
        sync_dir(&self.calibrations)
    }

    fn remove_calibration(&self, id: Uuid) -> io::Result<()> {
        remove_dir_if_exists(&self.calibrations.join(id.to_string()))
    }

    fn calibration_ids(&self) -> io::Result<Vec<Uuid>> {
        uuid_dirs(&self.calibrations)
    }
}

/// The directories of `root` named by a UUID.
fn uuid_dirs(root: &Path) -> io::Result<Vec<Uuid>> {
    let mut ids = Vec::new();
    for entry in std::fs::read_dir(root)? {
        let entry = entry?;
        if let Some(id) = entry
            .file_name()
            .to_str()
            .and_then(|s| Uuid::parse_str(s).ok())
        {
            ids.push(id);
        }
    }
    Ok(ids)
}

#[cfg(unix)]
fn free_bytes(path: &Path) -> io::Result<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c_path = std::ffi::CString::new(path.as_os_str().as_bytes())
        .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
    // SAFETY: `c_path` is a valid NUL-terminated string and `stat` a properly sized,
    // zero-initialised out-parameter that statvfs fills in.
    let mut stat: libc::statvfs = unsafe { std::mem::zeroed() };
    let rc = unsafe { libc::statvfs(c_path.as_ptr(), &mut stat) };
    if rc != 0 {
        return Err(io::Error::last_os_error());
    }
    #[allow(clippy::unnecessary_cast)] // the field types differ between platforms
    Ok((stat.f_bavail as u64).saturating_mul(stat.f_frsize as u64))
}

#[cfg(not(unix))]
fn free_bytes(_path: &Path) -> io::Result<u64> {
    Ok(u64::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn staged_dirs_commit_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let id = Uuid::new_v4();
        let staged = store.stage_inputs(id).unwrap();
        std::fs::write(staged.join("000.img"), b"x").unwrap();
        store.commit_inputs(id).unwrap();
        assert!(
            store
                .fetch_inputs(id, &|_| false)
                .unwrap()
                .join("000.img")
                .is_file()
        );
        assert!(!staged.exists());
        let out = store.stage_outputs(id).unwrap();
        std::fs::write(out.join("result.json"), b"{}").unwrap();
        assert!(!store.job(id).join("output").exists());
        store.commit_outputs(id, "1", &mut []).unwrap();
        assert!(store.job(id).join("output/result.json").is_file());
        assert_eq!(store.job_ids().unwrap(), vec![id]);
        assert!(store.free_bytes().unwrap() > 0);
        store.probe_writable().unwrap();
        store.remove_job(id).unwrap();
        store.remove_job(id).unwrap();
        assert!(store.job_ids().unwrap().is_empty());
    }

    #[test]
    fn manifests_without_normals_still_read_and_a_normals_job_round_trips() {
        let old = br#"{"images": [{"name": "a.png", "file": "000.img"}], "mask": null}"#;
        let manifest: Manifest = serde_json::from_slice(old).unwrap();
        assert_eq!((manifest.images.len(), manifest.normals), (1, None));
        let normals = Manifest {
            images: Vec::new(),
            mask: None,
            normals: Some(NormalsEntry {
                name: "n.png".into(),
                file: NORMALS_FILE.into(),
                convention: Convention::Directx,
            }),
            notes: Vec::new(),
        };
        let json = serde_json::to_vec(&normals).unwrap();
        assert_eq!(serde_json::from_slice::<Manifest>(&json).unwrap(), normals);
    }
}
