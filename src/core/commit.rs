//! Writing artifacts so that a reader never sees a partial one, and a crash never leaves a
//! visible one that is not on disk: each is streamed into a temporary file, fsynced, then
//! renamed into place.
//!
//! A job's artifacts go through a [`Committer`]: the caller's thread streams the bytes and
//! a thread of the committer's own does the fsync and the rename. An fsync waits for the
//! disk (milliseconds on a local SSD, tens on network volumes); done inline it idled a
//! rayon worker in the middle of the integration, which the pictures are written beside.

use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::thread::JoinHandle;

use super::error::RunError;

/// What an artifact is written to: seekable, since the EXR writer goes back to fill in its
/// offset table.
pub trait WriteSeek: Write + Seek {}

impl<T: Write + Seek> WriteSeek for T {}

/// Write `bytes` to `dir/name` (see the module docs), on this thread.
pub fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), RunError> {
    Pending::write(dir, name, &mut |f| f.write_all(bytes))?.commit()
}

/// An artifact written to its temporary file, not yet durable or visible.
struct Pending {
    file: File,
    tmp: PathBuf,
    path: PathBuf,
}

impl Pending {
    fn write(
        dir: &Path,
        name: &str,
        write: &mut dyn FnMut(&mut dyn WriteSeek) -> std::io::Result<()>,
    ) -> Result<Self, RunError> {
        let tmp = dir.join(format!(".{name}.tmp"));
        let path = dir.join(name);
        let written = (|| {
            let mut f = BufWriter::with_capacity(1 << 20, File::create(&tmp)?);
            write(&mut f)?;
            f.into_inner().map_err(|e| e.into_error())
        })();
        match written {
            Ok(file) => Ok(Self { file, tmp, path }),
            Err(e) => Err(Self::failed(&tmp, &path, e)),
        }
    }

    /// fsync, then rename into place.
    fn commit(self) -> Result<(), RunError> {
        let Self { file, tmp, path } = self;
        (file.sync_all())
            .and_then(|()| std::fs::rename(&tmp, &path))
            .map_err(|e| Self::failed(&tmp, &path, e))
    }

    /// A failed artifact leaves nothing behind, not even its temporary file.
    fn failed(tmp: &Path, path: &Path, e: std::io::Error) -> RunError {
        let _ = std::fs::remove_file(tmp);
        RunError::Output {
            path: path.display().to_string(),
            reason: e.to_string(),
        }
    }
}

/// Commits one job's artifacts on a thread of its own, in the order they were written.
/// [`Committer::finish`] waits for all of them; dropping the committer waits too, so an
/// artifact written before an error or a cancellation is still committed or removed.
pub struct Committer {
    queue: Option<mpsc::Sender<Pending>>,
    worker: Option<JoinHandle<Result<(), RunError>>>,
}

impl Committer {
    /// Without a thread (none could be started), artifacts are committed inline.
    pub fn new() -> Self {
        let (queue, pending) = mpsc::channel::<Pending>();
        let worker = std::thread::Builder::new()
            .name("commit".into())
            .spawn(move || {
                // Commit everything even after a failure; report the first failure.
                (pending.into_iter().map(Pending::commit)).fold(Ok(()), Result::and)
            });
        match worker {
            Ok(worker) => Self {
                queue: Some(queue),
                worker: Some(worker),
            },
            Err(_) => Self {
                queue: None,
                worker: None,
            },
        }
    }

    /// Stream an artifact into `dir/name` on this thread; it is made durable and visible
    /// later, by [`Committer::finish`] at the latest.
    pub fn write(
        &self,
        dir: &Path,
        name: &str,
        write: &mut dyn FnMut(&mut dyn WriteSeek) -> std::io::Result<()>,
    ) -> Result<(), RunError> {
        let pending = Pending::write(dir, name, write)?;
        match &self.queue {
            Some(queue) => queue.send(pending).or_else(|unsent| unsent.0.commit()),
            None => pending.commit(),
        }
    }

    /// Wait until every artifact written so far is durable and in place; the first
    /// failure, if any.
    pub fn finish(mut self) -> Result<(), RunError> {
        self.wait()
    }

    fn wait(&mut self) -> Result<(), RunError> {
        drop(self.queue.take());
        match self.worker.take().map(JoinHandle::join) {
            None => Ok(()),
            Some(Ok(result)) => result,
            Some(Err(panic)) => Err(RunError::Output {
                path: "(committing artifacts)".into(),
                reason: super::error::panic_message(panic.as_ref()).to_string(),
            }),
        }
    }
}

impl Default for Committer {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for Committer {
    fn drop(&mut self) {
        let _ = self.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committed_artifacts_appear_whole_and_failures_leave_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let commits = Committer::new();
        commits
            .write(dir.path(), "a.bin", &mut |f| f.write_all(b"abc"))
            .unwrap();
        let refused = commits.write(dir.path(), "b.bin", &mut |f| {
            f.write_all(b"partial")?;
            Err(std::io::Error::other("encoder gave up"))
        });
        assert!(
            matches!(refused, Err(RunError::Output { ref reason, .. }) if reason.contains("gave up"))
        );
        commits.finish().unwrap();
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["a.bin"], "no temporary or partial file is left");
        assert_eq!(std::fs::read(dir.path().join("a.bin")).unwrap(), b"abc");
    }

    #[test]
    fn a_failed_commit_is_reported_by_finish() {
        let dir = tempfile::tempdir().unwrap();
        let commits = Committer::new();
        commits
            .write(dir.path(), "a.bin", &mut |f| f.write_all(b"abc"))
            .unwrap();
        // The rename into place fails once its target is a non-empty directory.
        std::fs::create_dir(dir.path().join("b.bin")).unwrap();
        std::fs::write(dir.path().join("b.bin").join("x"), b"x").unwrap();
        commits
            .write(dir.path(), "b.bin", &mut |f| f.write_all(b"def"))
            .unwrap();
        let err = commits.finish().unwrap_err();
        assert!(
            matches!(err, RunError::Output { ref path, .. } if path.ends_with("b.bin")),
            "{err:?}"
        );
        assert_eq!(std::fs::read(dir.path().join("a.bin")).unwrap(), b"abc");
        assert!(!dir.path().join(".b.bin.tmp").exists());
    }
}
