//! [`BlobStore`] in a local directory: the data directory's `jobs/` and `calibrations/`
//! (see [`layout`](super::layout)), or a remote store's scratch. A commit syncs every
//! file and renames the staged directory into place at once.

use std::io;
use std::ops::Range;
use std::path::{Path, PathBuf};

use futures_util::future::BoxFuture;
use uuid::Uuid;

use super::error::Result;
use super::layout::{Dirs, FILES, FILES_PARTIAL, INPUT, INPUT_PARTIAL, OUTPUT, OUTPUT_PARTIAL};
use super::manifest::MANIFEST_FILE;
use super::traits::{BlobStore, ByteStream, LocalArtifacts, Served};
use crate::service::repo::ArtifactInfo;

/// [`BlobStore`] in a local directory.
pub struct LocalStore {
    dirs: Dirs,
    root: PathBuf,
    calibrations: PathBuf,
}

impl LocalStore {
    pub fn open(data_dir: &Path) -> io::Result<Self> {
        let dirs = Dirs::new(data_dir);
        let (root, calibrations) = (dirs.jobs(), dirs.calibrations());
        std::fs::create_dir_all(&root)?;
        std::fs::create_dir_all(&calibrations)?;
        Ok(Self {
            dirs,
            root,
            calibrations,
        })
    }

    fn job(&self, id: Uuid) -> PathBuf {
        self.dirs.job(id)
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
    fn stage_inputs(&self, id: Uuid) -> Result<PathBuf> {
        let dir = self.job(id).join(INPUT_PARTIAL);
        Self::fresh_dir(&dir)?;
        Ok(dir)
    }

    fn commit_inputs(&self, id: Uuid) -> Result<()> {
        let job = self.job(id);
        Self::commit_dir(&job.join(INPUT_PARTIAL), &job.join(INPUT))?;
        Ok(sync_dir(&self.root)?)
    }

    fn has_inputs(&self, id: Uuid) -> Result<bool> {
        Ok(self.job(id).join(INPUT).join(MANIFEST_FILE).is_file())
    }

    fn fetch_inputs(&self, id: Uuid, _have: &dyn Fn(&str) -> bool) -> Result<PathBuf> {
        Ok(self.job(id).join(INPUT))
    }

    fn remove_inputs(&self, id: Uuid) -> Result<()> {
        Ok(remove_dir_if_exists(&self.job(id).join(INPUT))?)
    }

    fn stage_outputs(&self, id: Uuid) -> Result<PathBuf> {
        let dir = self.job(id).join(OUTPUT_PARTIAL);
        Self::fresh_dir(&dir)?;
        Ok(dir)
    }

    /// One server per data directory runs a job's attempts one after another, so the
    /// attempt's outputs are the job's `output/`.
    fn commit_outputs(&self, id: Uuid, _: &str, _: &mut [ArtifactInfo]) -> Result<()> {
        let job = self.job(id);
        Ok(Self::commit_dir(
            &job.join(OUTPUT_PARTIAL),
            &job.join(OUTPUT),
        )?)
    }

    fn discard_outputs(&self, id: Uuid, _: &str) -> Result<()> {
        let job = self.job(id);
        remove_dir_if_exists(&job.join(OUTPUT_PARTIAL))?;
        Ok(remove_dir_if_exists(&job.join(OUTPUT))?)
    }

    fn read(
        &self,
        file: Served<'_>,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'static, Result<ByteStream>> {
        let path = match file {
            Served::Artifact { job, info } => self.job(job).join(OUTPUT).join(&info.name),
            Served::Calibration { id, info } => {
                self.dirs.calibration(id).join(FILES).join(&info.name)
            }
        };
        Box::pin(async move {
            use futures_util::{StreamExt, TryStreamExt};
            use tokio::io::{AsyncReadExt, AsyncSeekExt};
            let mut file = tokio::fs::File::open(&path).await?;
            let stream = match range {
                None => tokio_util::io::ReaderStream::new(file).boxed(),
                Some(r) => {
                    file.seek(io::SeekFrom::Start(r.start)).await?;
                    tokio_util::io::ReaderStream::new(file.take(r.end - r.start)).boxed()
                }
            };
            Ok(stream.map_err(Into::into).boxed())
        })
    }

    fn local_artifacts(&self, id: Uuid, _: &[&ArtifactInfo]) -> Result<LocalArtifacts> {
        Ok(LocalArtifacts::kept(self.job(id).join(OUTPUT)))
    }

    fn remove_job(&self, id: Uuid) -> Result<()> {
        Ok(remove_dir_if_exists(&self.job(id))?)
    }

    fn job_ids(&self) -> Result<Vec<Uuid>> {
        Ok(uuid_dirs(&self.root)?)
    }

    fn remove_partials(&self, id: Uuid) -> Result<()> {
        let job = self.job(id);
        remove_dir_if_exists(&job.join(INPUT_PARTIAL))?;
        Ok(remove_dir_if_exists(&job.join(OUTPUT_PARTIAL))?)
    }

    fn free_bytes(&self) -> Result<u64> {
        Ok(free_bytes(&self.root)?)
    }

    fn probe_writable(&self) -> Result<()> {
        let probe = self
            .root
            .join(format!(".probe-{}", Uuid::new_v4().simple()));
        std::fs::write(&probe, b"ok")?;
        Ok(std::fs::remove_file(&probe)?)
    }

    fn stage_calibration(&self, id: Uuid) -> Result<PathBuf> {
        let dir = self.dirs.calibration(id).join(FILES_PARTIAL);
        Self::fresh_dir(&dir)?;
        Ok(dir)
    }

    fn commit_calibration(&self, id: Uuid) -> Result<()> {
        let dir = self.dirs.calibration(id);
        Self::commit_dir(&dir.join(FILES_PARTIAL), &dir.join(FILES))?;
        Ok(sync_dir(&self.calibrations)?)
    }

    fn remove_calibration(&self, id: Uuid) -> Result<()> {
        Ok(remove_dir_if_exists(&self.dirs.calibration(id))?)
    }

    fn calibration_ids(&self) -> Result<Vec<Uuid>> {
        Ok(uuid_dirs(&self.calibrations)?)
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

/// Flush a directory's entries (new names, renames) to disk.
pub(super) fn sync_dir(path: &Path) -> io::Result<()> {
    #[cfg(unix)]
    {
        std::fs::File::open(path)?.sync_all()
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_store_contract() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        super::super::contract::run(&store, rt.handle());
    }

    /// A staged directory is renamed into place at commit: nothing of it shows before
    /// (the rest of this store's behaviour is the contract's).
    #[test]
    fn staged_dirs_commit_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let id = Uuid::new_v4();
        let staged = store.stage_inputs(id).unwrap();
        std::fs::write(staged.join("000.img"), b"x").unwrap();
        assert!(!store.job(id).join("input").exists());
        store.commit_inputs(id).unwrap();
        assert!(store.job(id).join("input/000.img").is_file());
        let out = store.stage_outputs(id).unwrap();
        std::fs::write(out.join("result.json"), b"{}").unwrap();
        assert!(!store.job(id).join("output").exists());
        store.commit_outputs(id, "1", &mut []).unwrap();
        assert!(store.job(id).join("output/result.json").is_file());
        assert!(!out.exists());
    }
}
