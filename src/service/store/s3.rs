//! [`BlobStore`] in an S3-compatible object store (`--store s3://bucket/prefix`), through
//! the `object_store` crate, so that every instance sharing the bucket can serve every
//! job's artifacts and every calibration's files (the keys: [`layout`](super::layout)).
//!
//! Uploads and reconstructions are staged in a local scratch directory
//! (`{data}/scratch/`, laid out as [`LocalStore`]'s and emptied at start); a commit streams
//! each staged file up, as one PUT when it fits one part and otherwise as a multipart
//! upload of [`PART_BYTES`] parts with at most [`PARTS_IN_FLIGHT`] in flight, so no file is
//! ever whole in memory. A job's worker fetches its inputs back into the scratch
//! directory, but for the images its upload's first pass already decoded on the same
//! instance (the service's prefetch). Files go up and come back [`FILES_IN_FLIGHT`] at a
//! time. An attempt writes under a key of its own and its keys are recorded with the job,
//! so nothing is renamed and no half-written artifact can be served.
//!
//! The store's API is async; its callers here are blocking threads, which drive each
//! call with the runtime's [`Handle::block_on`]. Only [`BlobStore::read`] (serving) is
//! async. Every failure to reach the store is [`Error::Unavailable`].

use std::io::{self, Read, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use futures_util::future::BoxFuture;
use futures_util::{StreamExt, TryStreamExt};
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::path::Path as Key;
use object_store::{
    BackoffConfig, ClientConfigKey, GetOptions, GetRange, ObjectStore, ObjectStoreExt, PutPayload,
    RetryConfig, WriteMultipart,
};
use tokio::runtime::Handle;
use uuid::Uuid;

use super::error::{Error, Result};
use super::layout::{
    CALIBRATIONS, Dirs, FILES_PARTIAL, INPUT, INPUT_PARTIAL, JOBS, Keys, OUTPUT_PARTIAL, OUTPUTS,
    PROBES,
};
use super::local::LocalStore;
use super::manifest::MANIFEST_FILE;
use super::traits::{BlobStore, ByteStream, LocalArtifacts, Served};
use crate::service::repo::ArtifactInfo;

/// Size of one part of a multipart upload (S3's smallest part but the last is 5 MiB).
pub const PART_BYTES: usize = 5 << 20;
/// Parts of one file's upload sent at once: it holds at most this many plus one in memory.
pub const PARTS_IN_FLIGHT: usize = 2;
/// Files sent or fetched at once: a commit holds at most this many files'
/// `PARTS_IN_FLIGHT + 1` parts in memory (60 MiB).
const FILES_IN_FLIGHT: usize = 4;

/// The store behind `--store s3://…`.
pub struct S3Store {
    store: Arc<dyn ObjectStore>,
    /// Where objects go under the bucket's prefix.
    keys: Keys,
    /// Staging and a running job's files.
    scratch: LocalStore,
    /// The scratch directory's layout.
    dirs: Dirs,
    rt: Handle,
    /// How old a job's or calibration's newest object must be before a start may take
    /// it, without a record, for an abandoned upload (another instance may be committing
    /// one now).
    settle: Duration,
}

/// `s3://bucket[/prefix]` → bucket, prefix.
pub fn parse_url(url: &str) -> anyhow::Result<(String, String)> {
    let rest = url.strip_prefix("s3://").with_context(|| {
        format!(
            "--store must be s3://bucket[/prefix] (or absent for the data directory), not {url:?}"
        )
    })?;
    let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
    anyhow::ensure!(!bucket.is_empty(), "--store {url:?} names no bucket");
    Ok((bucket.to_string(), prefix.trim_matches('/').to_string()))
}

impl S3Store {
    /// Connect to `url`'s bucket with the standard `AWS_*` settings from the environment
    /// (`AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`,
    /// `AWS_ALLOW_HTTP`; path-style requests unless `AWS_VIRTUAL_HOSTED_STYLE_REQUEST`),
    /// and empty the scratch directory. Nothing is sent to the store yet.
    pub fn open(url: &str, scratch: &Path, rt: Handle, settle: Duration) -> anyhow::Result<Self> {
        let (bucket, prefix) = parse_url(url)?;
        // Fail fast when the store is down: a submission answers 503 within seconds, and
        // a job waits and is tried again (see `jobs`).
        let retry = RetryConfig {
            backoff: BackoffConfig {
                init_backoff: Duration::from_millis(100),
                max_backoff: Duration::from_secs(1),
                base: 2.0,
            },
            max_retries: 2,
            retry_timeout: Duration::from_secs(10),
        };
        let store = AmazonS3Builder::from_env()
            .with_bucket_name(bucket)
            .with_config(
                AmazonS3ConfigKey::Client(ClientConfigKey::ConnectTimeout),
                "3s",
            )
            .with_config(AmazonS3ConfigKey::Client(ClientConfigKey::Timeout), "5m")
            .with_retry(retry)
            .build()
            .with_context(|| format!("configuring the object store {url}"))?;
        match std::fs::remove_dir_all(scratch) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => {
                return Err(e).with_context(|| format!("emptying {}", scratch.display()));
            }
            _ => {}
        }
        let local = LocalStore::open(scratch)
            .with_context(|| format!("creating the scratch directory {}", scratch.display()))?;
        Ok(Self {
            store: Arc::new(store),
            keys: Keys::new(&prefix),
            scratch: local,
            dirs: Dirs::new(scratch),
            rt,
            settle,
        })
    }

    /// Upload every file of `dir` under `to`, `last` after all the others.
    fn upload_dir(&self, dir: &Path, to: &Key, last: Option<&str>) -> Result<()> {
        let mut names: Vec<String> = Vec::new();
        for entry in std::fs::read_dir(dir)? {
            let entry = entry?;
            if entry.file_type()?.is_file()
                && let Some(name) = entry.file_name().to_str()
            {
                names.push(name.to_string());
            }
        }
        let (last, rest): (Vec<String>, Vec<String>) =
            names.into_iter().partition(|n| Some(n.as_str()) == last);
        let files = |names: Vec<String>| {
            names
                .into_iter()
                .map(|n| (dir.join(&n), to.clone().join(n.as_str())))
                .collect::<Vec<_>>()
        };
        self.upload_files(files(rest))?;
        self.upload_files(files(last))
    }

    /// Stream local files to their keys, [`FILES_IN_FLIGHT`] at a time.
    fn upload_files(&self, files: Vec<(PathBuf, Key)>) -> Result<()> {
        self.rt.block_on(async {
            futures_util::stream::iter(files.iter().map(|(path, key)| self.put_file(path, key)))
                .buffer_unordered(FILES_IN_FLIGHT)
                .try_collect::<Vec<()>>()
                .await
                .map(|_| ())
        })
    }

    /// Stream one local file to `key`.
    async fn put_file(&self, path: &Path, key: &Key) -> Result<()> {
        let mut file = std::fs::File::open(path)?;
        let len = file.metadata()?.len();
        {
            if len <= PART_BYTES as u64 {
                let mut bytes = Vec::with_capacity(len as usize);
                file.read_to_end(&mut bytes)?;
                self.store
                    .put(key, PutPayload::from(bytes))
                    .await
                    .map_err(Error::from)?;
                return Ok(());
            }
            let upload = self.store.put_multipart(key).await.map_err(Error::from)?;
            let mut parts = WriteMultipart::new_with_chunk_size(upload, PART_BYTES);
            let mut buf = vec![0u8; 1 << 20];
            let sent: Result<()> = async {
                loop {
                    let n = file.read(&mut buf)?;
                    if n == 0 {
                        return Ok(());
                    }
                    parts
                        .wait_for_capacity(PARTS_IN_FLIGHT)
                        .await
                        .map_err(Error::from)?;
                    parts.write(&buf[..n]);
                }
            }
            .await;
            match sent {
                Ok(()) => parts.finish().await.map(|_| ()).map_err(Error::from),
                Err(e) => {
                    let _ = parts.abort().await;
                    Err(e)
                }
            }
        }
    }

    /// Fetch `key` into the local file `to`.
    async fn download(&self, key: Key, to: PathBuf) -> Result<()> {
        let got = self.store.get(&key).await.map_err(Error::from)?;
        let mut chunks = got.into_stream();
        let mut file = std::fs::File::create(&to)?;
        while let Some(chunk) = chunks.next().await {
            file.write_all(&chunk.map_err(Error::from)?)?;
        }
        Ok(())
    }

    /// Delete every object under `prefix`.
    fn delete_under(&self, prefix: &Key) -> Result<()> {
        self.rt.block_on(async {
            let found = self
                .store
                .list(Some(prefix))
                .map_ok(|meta| meta.location)
                .boxed();
            self.store
                .delete_stream(found)
                .try_collect::<Vec<_>>()
                .await
                .map_err(Error::from)?;
            Ok(())
        })
    }

    /// The ids under `{prefix}/{kind}/` whose newest object is older than `settle`, and
    /// the newest object time of the others.
    fn settled_ids(&self, kind: &str) -> Result<Vec<Uuid>> {
        let root = self.keys.key(&[kind]);
        let newest = self.rt.block_on(async {
            let mut newest = std::collections::HashMap::<Uuid, i64>::new();
            let mut listing = self.store.list(Some(&root));
            while let Some(meta) = listing.next().await {
                let meta = meta.map_err(Error::from)?;
                let id = meta
                    .location
                    .prefix_match(&root)
                    .and_then(|mut parts| parts.next())
                    .and_then(|part| Uuid::parse_str(part.as_ref()).ok());
                if let Some(id) = id {
                    let at = meta.last_modified.timestamp_millis();
                    let slot = newest.entry(id).or_insert(at);
                    *slot = (*slot).max(at);
                }
            }
            Ok::<_, Error>(newest)
        })?;
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as i64);
        let cutoff = now - self.settle.as_millis() as i64;
        Ok(newest
            .into_iter()
            .filter(|(_, at)| *at < cutoff)
            .map(|(id, _)| id)
            .collect())
    }

    fn staged(&self, id: Uuid, what: &str) -> PathBuf {
        self.dirs.job(id).join(what)
    }
}

fn union(mut a: Vec<Uuid>, b: Vec<Uuid>) -> Vec<Uuid> {
    a.extend(b);
    a.sort();
    a.dedup();
    a
}

impl BlobStore for S3Store {
    fn stage_inputs(&self, id: Uuid) -> Result<PathBuf> {
        self.scratch.stage_inputs(id)
    }

    fn commit_inputs(&self, id: Uuid) -> Result<()> {
        let staged = self.staged(id, INPUT_PARTIAL);
        self.upload_dir(&staged, &self.keys.job(id, &[INPUT]), Some(MANIFEST_FILE))?;
        self.scratch.remove_job(id)
    }

    fn has_inputs(&self, id: Uuid) -> Result<bool> {
        let key = self.keys.job(id, &[INPUT, MANIFEST_FILE]);
        match self.rt.block_on(self.store.head(&key)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(e.into()),
        }
    }

    fn fetch_inputs(&self, id: Uuid, have: &dyn Fn(&str) -> bool) -> Result<PathBuf> {
        let dir = self.staged(id, INPUT);
        match std::fs::remove_dir_all(&dir) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e.into()),
            _ => {}
        }
        std::fs::create_dir_all(&dir)?;
        let root = self.keys.job(id, &[INPUT]);
        self.rt.block_on(async {
            let keys: Vec<Key> = self
                .store
                .list(Some(&root))
                .map_ok(|meta| meta.location)
                .try_collect()
                .await
                .map_err(Error::from)?;
            futures_util::stream::iter(keys.into_iter().filter_map(|key| {
                let name = key.filename().filter(|n| !have(n))?.to_string();
                Some(self.download(key, dir.join(name)))
            }))
            .buffer_unordered(FILES_IN_FLIGHT)
            .try_collect::<Vec<()>>()
            .await
        })?;
        Ok(dir)
    }

    fn remove_inputs(&self, id: Uuid) -> Result<()> {
        self.scratch.remove_inputs(id)?;
        self.delete_under(&self.keys.job(id, &[INPUT]))
    }

    fn stage_outputs(&self, id: Uuid) -> Result<PathBuf> {
        self.scratch.stage_outputs(id)
    }

    fn commit_outputs(
        &self,
        id: Uuid,
        attempt: &str,
        artifacts: &mut [ArtifactInfo],
    ) -> Result<()> {
        let staged = self.staged(id, OUTPUT_PARTIAL);
        let mut files = Vec::new();
        for info in artifacts.iter_mut() {
            let key = self.keys.job(id, &[OUTPUTS, attempt, &info.name]);
            info.key = Some(key.to_string());
            files.push((staged.join(&info.name), key));
        }
        self.upload_files(files)?;
        self.scratch.discard_outputs(id, attempt)
    }

    fn discard_outputs(&self, id: Uuid, attempt: &str) -> Result<()> {
        self.scratch.discard_outputs(id, attempt)?;
        self.delete_under(&self.keys.job(id, &[OUTPUTS, attempt]))
    }

    fn read(
        &self,
        file: Served<'_>,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'static, Result<ByteStream>> {
        let key = match file {
            Served::Artifact { info, .. } => info.key.as_deref().map(Key::from),
            Served::Calibration { id, info } => Some(self.keys.calibration(id, &[&info.name])),
        };
        let store = self.store.clone();
        Box::pin(async move {
            let key = key.ok_or_else(|| {
                Error::from(io::Error::new(
                    io::ErrorKind::NotFound,
                    "the artifact has no object key",
                ))
            })?;
            let options = GetOptions {
                range: range.map(GetRange::Bounded),
                ..GetOptions::default()
            };
            let got = store.get_opts(&key, options).await.map_err(Error::from)?;
            Ok(got.into_stream().map_err(Error::from).boxed())
        })
    }

    fn local_artifacts(&self, _id: Uuid, artifacts: &[&ArtifactInfo]) -> Result<LocalArtifacts> {
        let dir = self
            .dirs
            .root()
            .join(format!("fetched-{}", Uuid::new_v4().simple()));
        std::fs::create_dir_all(&dir)?;
        let local = LocalArtifacts::fetched(dir.clone());
        for info in artifacts {
            let key = info.key.as_deref().map(Key::from).ok_or_else(|| {
                Error::from(io::Error::new(
                    io::ErrorKind::NotFound,
                    "the artifact has no object key",
                ))
            })?;
            self.rt.block_on(self.download(key, dir.join(&info.name)))?;
        }
        Ok(local)
    }

    fn remove_job(&self, id: Uuid) -> Result<()> {
        self.scratch.remove_job(id)?;
        self.delete_under(&self.keys.job(id, &[]))
    }

    fn job_ids(&self) -> Result<Vec<Uuid>> {
        Ok(union(self.scratch.job_ids()?, self.settled_ids(JOBS)?))
    }

    fn remove_partials(&self, id: Uuid) -> Result<()> {
        self.scratch.remove_partials(id)
    }

    fn free_bytes(&self) -> Result<u64> {
        self.scratch.free_bytes()
    }

    fn probe_writable(&self) -> Result<()> {
        self.scratch.probe_writable()?;
        let key = self
            .keys
            .key(&[PROBES, &Uuid::new_v4().simple().to_string()]);
        self.rt.block_on(async {
            self.store
                .put(&key, PutPayload::from_static(b"ok"))
                .await
                .map_err(Error::from)?;
            self.store.delete(&key).await.map_err(Error::from)
        })
    }

    fn stage_calibration(&self, id: Uuid) -> Result<PathBuf> {
        self.scratch.stage_calibration(id)
    }

    fn commit_calibration(&self, id: Uuid) -> Result<()> {
        let staged = self.dirs.calibration(id).join(FILES_PARTIAL);
        self.upload_dir(&staged, &self.keys.calibration(id, &[]), None)?;
        self.scratch.remove_calibration(id)
    }

    fn remove_calibration(&self, id: Uuid) -> Result<()> {
        self.scratch.remove_calibration(id)?;
        self.delete_under(&self.keys.calibration(id, &[]))
    }

    fn calibration_ids(&self) -> Result<Vec<Uuid>> {
        Ok(union(
            self.scratch.calibration_ids()?,
            self.settled_ids(CALIBRATIONS)?,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn store_urls() {
        assert_eq!(
            parse_url("s3://b/a/p/").unwrap(),
            ("b".to_string(), "a/p".to_string())
        );
        assert_eq!(parse_url("s3://b").unwrap(), ("b".into(), String::new()));
        assert!(parse_url("s3:///p").is_err());
        let e = parse_url("file:///tmp").unwrap_err().to_string();
        assert!(e.contains("s3://bucket"), "{e}");
    }
}
