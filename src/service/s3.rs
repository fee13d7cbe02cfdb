//! [`BlobStore`] in an S3-compatible object store (`--store s3://bucket/prefix`), through
//! the `object_store` crate, so that every instance sharing the bucket can serve every
//! job's artifacts and every calibration's files:
//!
//! ```text
//! {prefix}/jobs/{id}/input/{file}              a job's inputs (manifest.json uploaded last)
//! {prefix}/jobs/{id}/outputs/{attempt}/{name}  an attempt's artifacts (the record keeps each key)
//! {prefix}/calibrations/{id}/{name}            a calibration's lights.csv, overlay.png, lights.png[, positions.csv]
//! ```
//!
//! Uploads and reconstructions are staged in a local scratch directory
//! (`{data}/scratch/`, laid out as [`LocalStore`]'s and emptied at start); a commit streams
//! each staged file up, as one PUT when it fits one part and otherwise as a multipart
//! upload of [`PART_BYTES`] parts with at most [`PARTS_IN_FLIGHT`] in flight, so no file is
//! ever whole in memory. A job's worker fetches its inputs back into the scratch
//! directory, but for the images its upload's first pass already decoded on the same
//! instance ([`super::prefetch`]). Files go up and come back [`FILES_IN_FLIGHT`] at a
//! time. An attempt writes under a key of its own and its keys are recorded with the job,
//! so nothing is renamed and no half-written artifact can be served.
//!
//! The store's API is async; its callers here are blocking threads, which drive each
//! call with the runtime's [`Handle::block_on`]. Only [`BlobStore::read`] (serving) is
//! async. Every failure to reach the store is [`Unavailable`].

use std::io::{self, Read, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

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

use super::blobs::{
    BlobStore, ByteStream, LocalArtifacts, LocalStore, MANIFEST_FILE, Served, Unavailable,
};
use super::repo::ArtifactInfo;
use super::util::now_ms;

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
    /// The key prefix every object of this service starts with (may be empty).
    prefix: Key,
    /// Staging and a running job's files.
    scratch: LocalStore,
    scratch_root: PathBuf,
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
            prefix: Key::from(prefix),
            scratch: local,
            scratch_root: scratch.to_path_buf(),
            rt,
            settle,
        })
    }

    fn key(&self, parts: &[&str]) -> Key {
        parts
            .iter()
            .fold(self.prefix.clone(), |key, part| key.join(*part))
    }

    fn job_key(&self, id: Uuid, parts: &[&str]) -> Key {
        let id = id.to_string();
        let mut all = vec!["jobs", id.as_str()];
        all.extend_from_slice(parts);
        self.key(&all)
    }

    fn calibration_key(&self, id: Uuid, parts: &[&str]) -> Key {
        let id = id.to_string();
        let mut all = vec!["calibrations", id.as_str()];
        all.extend_from_slice(parts);
        self.key(&all)
    }

    /// Upload every file of `dir` under `to`, `last` after all the others.
    fn upload_dir(&self, dir: &Path, to: &Key, last: Option<&str>) -> io::Result<()> {
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
    fn upload_files(&self, files: Vec<(PathBuf, Key)>) -> io::Result<()> {
        self.rt.block_on(async {
            futures_util::stream::iter(files.iter().map(|(path, key)| self.put_file(path, key)))
                .buffer_unordered(FILES_IN_FLIGHT)
                .try_collect::<Vec<()>>()
                .await
                .map(|_| ())
        })
    }

    /// Stream one local file to `key`.
    async fn put_file(&self, path: &Path, key: &Key) -> io::Result<()> {
        let mut file = std::fs::File::open(path)?;
        let len = file.metadata()?.len();
        {
            if len <= PART_BYTES as u64 {
                let mut bytes = Vec::with_capacity(len as usize);
                file.read_to_end(&mut bytes)?;
                self.store
                    .put(key, PutPayload::from(bytes))
                    .await
                    .map_err(unavailable)?;
                return Ok(());
            }
            let upload = self.store.put_multipart(key).await.map_err(unavailable)?;
            let mut parts = WriteMultipart::new_with_chunk_size(upload, PART_BYTES);
            let mut buf = vec![0u8; 1 << 20];
            let sent: io::Result<()> = async {
                loop {
                    let n = file.read(&mut buf)?;
                    if n == 0 {
                        return Ok(());
                    }
                    parts
                        .wait_for_capacity(PARTS_IN_FLIGHT)
                        .await
                        .map_err(unavailable)?;
                    parts.write(&buf[..n]);
                }
            }
            .await;
            match sent {
                Ok(()) => parts.finish().await.map(|_| ()).map_err(unavailable),
                Err(e) => {
                    let _ = parts.abort().await;
                    Err(e)
                }
            }
        }
    }

    /// Fetch `key` into the local file `to`.
    async fn download(&self, key: Key, to: PathBuf) -> io::Result<()> {
        let got = self.store.get(&key).await.map_err(unavailable)?;
        let mut chunks = got.into_stream();
        let mut file = std::fs::File::create(&to)?;
        while let Some(chunk) = chunks.next().await {
            file.write_all(&chunk.map_err(unavailable)?)?;
        }
        Ok(())
    }

    /// Delete every object under `prefix`.
    fn delete_under(&self, prefix: &Key) -> io::Result<()> {
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
                .map_err(unavailable)?;
            Ok(())
        })
    }

    /// The ids under `{prefix}/{kind}/` whose newest object is older than `settle`, and
    /// the newest object time of the others.
    fn settled_ids(&self, kind: &str) -> io::Result<Vec<Uuid>> {
        let root = self.key(&[kind]);
        let newest = self.rt.block_on(async {
            let mut newest = std::collections::HashMap::<Uuid, i64>::new();
            let mut listing = self.store.list(Some(&root));
            while let Some(meta) = listing.next().await {
                let meta = meta.map_err(unavailable)?;
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
            Ok::<_, io::Error>(newest)
        })?;
        let cutoff = now_ms() - self.settle.as_millis() as i64;
        Ok(newest
            .into_iter()
            .filter(|(_, at)| *at < cutoff)
            .map(|(id, _)| id)
            .collect())
    }

    fn staged(&self, id: Uuid, what: &str) -> PathBuf {
        self.scratch_root
            .join("jobs")
            .join(id.to_string())
            .join(what)
    }
}

/// Any failure of the object store: the store is down, unreachable, or refused.
fn unavailable(e: object_store::Error) -> io::Error {
    match e {
        object_store::Error::NotFound { path, .. } => {
            io::Error::new(io::ErrorKind::NotFound, format!("no object {path}"))
        }
        other => io::Error::other(Unavailable(other.to_string())),
    }
}

fn union(mut a: Vec<Uuid>, b: Vec<Uuid>) -> Vec<Uuid> {
    a.extend(b);
    a.sort();
    a.dedup();
    a
}

impl BlobStore for S3Store {
    fn stage_inputs(&self, id: Uuid) -> io::Result<PathBuf> {
        self.scratch.stage_inputs(id)
    }

    fn commit_inputs(&self, id: Uuid) -> io::Result<()> {
        let staged = self.staged(id, "input.partial");
        self.upload_dir(&staged, &self.job_key(id, &["input"]), Some(MANIFEST_FILE))?;
        self.scratch.remove_job(id)
    }

    fn has_inputs(&self, id: Uuid) -> io::Result<bool> {
        let key = self.job_key(id, &["input", MANIFEST_FILE]);
        match self.rt.block_on(self.store.head(&key)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(unavailable(e)),
        }
    }

    fn fetch_inputs(&self, id: Uuid, have: &dyn Fn(&str) -> bool) -> io::Result<PathBuf> {
        let dir = self.staged(id, "input");
        match std::fs::remove_dir_all(&dir) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
            _ => {}
        }
        std::fs::create_dir_all(&dir)?;
        let root = self.job_key(id, &["input"]);
        self.rt.block_on(async {
            let keys: Vec<Key> = self
                .store
                .list(Some(&root))
                .map_ok(|meta| meta.location)
                .try_collect()
                .await
                .map_err(unavailable)?;
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

    fn remove_inputs(&self, id: Uuid) -> io::Result<()> {
        self.scratch.remove_inputs(id)?;
        self.delete_under(&self.job_key(id, &["input"]))
    }

    fn stage_outputs(&self, id: Uuid) -> io::Result<PathBuf> {
        self.scratch.stage_outputs(id)
    }

    fn commit_outputs(
        &self,
        id: Uuid,
        attempt: &str,
        artifacts: &mut [ArtifactInfo],
    ) -> io::Result<()> {
        let staged = self.staged(id, "output.partial");
        let mut files = Vec::new();
        for info in artifacts.iter_mut() {
            let key = self.job_key(id, &["outputs", attempt, &info.name]);
            info.key = Some(key.to_string());
            files.push((staged.join(&info.name), key));
        }
        self.upload_files(files)?;
        self.scratch.discard_outputs(id, attempt)
    }

    fn discard_outputs(&self, id: Uuid, attempt: &str) -> io::Result<()> {
        self.scratch.discard_outputs(id, attempt)?;
        self.delete_under(&self.job_key(id, &["outputs", attempt]))
    }

    fn read(
        &self,
        file: Served<'_>,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'static, io::Result<ByteStream>> {
        let key = match file {
            Served::Artifact { info, .. } => info.key.as_deref().map(Key::from),
            Served::Calibration { id, info } => Some(self.calibration_key(id, &[&info.name])),
        };
        let store = self.store.clone();
        Box::pin(async move {
            let key = key.ok_or_else(|| {
                io::Error::new(io::ErrorKind::NotFound, "the artifact has no object key")
            })?;
            let options = GetOptions {
                range: range.map(GetRange::Bounded),
                ..GetOptions::default()
            };
            let got = store.get_opts(&key, options).await.map_err(unavailable)?;
            Ok(got.into_stream().map_err(unavailable).boxed())
        })
    }

    fn local_artifacts(
        &self,
        _id: Uuid,
        artifacts: &[&ArtifactInfo],
    ) -> io::Result<LocalArtifacts> {
        let dir = self
            .scratch_root
            .join(format!("fetched-{}", Uuid::new_v4().simple()));
        std::fs::create_dir_all(&dir)?;
        let local = LocalArtifacts::fetched(dir.clone());
        for info in artifacts {
            let key = info.key.as_deref().map(Key::from).ok_or_else(|| {
                io::Error::new(io::ErrorKind::NotFound, "the artifact has no object key")
            })?;
            self.rt.block_on(self.download(key, dir.join(&info.name)))?;
        }
        Ok(local)
    }

    fn remove_job(&self, id: Uuid) -> io::Result<()> {
        self.scratch.remove_job(id)?;
        self.delete_under(&self.job_key(id, &[]))
    }

    fn job_ids(&self) -> io::Result<Vec<Uuid>> {
        Ok(union(self.scratch.job_ids()?, self.settled_ids("jobs")?))
    }

    fn remove_partials(&self, id: Uuid) -> io::Result<()> {
        self.scratch.remove_partials(id)
    }

    fn free_bytes(&self) -> io::Result<u64> {
        self.scratch.free_bytes()
    }

    fn probe_writable(&self) -> io::Result<()> {
        self.scratch.probe_writable()?;
        let key = self.key(&["probes", &Uuid::new_v4().simple().to_string()]);
        self.rt.block_on(async {
            self.store
                .put(&key, PutPayload::from_static(b"ok"))
                .await
                .map_err(unavailable)?;
            self.store.delete(&key).await.map_err(unavailable)
        })
    }

    fn stage_calibration(&self, id: Uuid) -> io::Result<PathBuf> {
        self.scratch.stage_calibration(id)
    }

    fn commit_calibration(&self, id: Uuid) -> io::Result<()> {
        let staged = self
            .scratch_root
            .join("calibrations")
            .join(id.to_string())
            .join("files.partial");
        self.upload_dir(&staged, &self.calibration_key(id, &[]), None)?;
        self.scratch.remove_calibration(id)
    }

    fn remove_calibration(&self, id: Uuid) -> io::Result<()> {
        self.scratch.remove_calibration(id)?;
        self.delete_under(&self.calibration_key(id, &[]))
    }

    fn calibration_ids(&self) -> io::Result<Vec<Uuid>> {
        Ok(union(
            self.scratch.calibration_ids()?,
            self.settled_ids("calibrations")?,
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
