//! The one multipart part loop: every form (a job's, a calibration's) reads its body
//! through a [`PartReader`], which counts the parts against `max_parts`, feeds each one
//! to the idempotency hash, refuses an unnamed one, and hands the form a [`Part`] to
//! store as a file (its bytes counted against `max_input_bytes`) or read as a small value.
//! What each part means is the form's: it matches on [`Part::name`].

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use axum::body::Bytes;
use axum::extract::Multipart;
use axum::extract::multipart::{Field, MultipartError};

use crate::service::config::Config;
use crate::service::error::ApiError;
use crate::service::tenancy::idempotency::PartHasher;

use super::tap::BodyTap;

/// Bytes kept from the start of each file to recognise its format.
pub(crate) const HEAD_BYTES: usize = 64;

/// A multipart body being read into a staging directory, part by part.
pub(crate) struct PartReader<'a> {
    multipart: &'a mut Multipart,
    config: &'a Config,
    tap: &'a BodyTap,
    hash: &'a mut PartHasher,
    dir: &'a Path,
    /// Every part name the form takes, for refusals.
    expected: &'static str,
    count: usize,
    /// Bytes of input files stored so far (bounded by `max_input_bytes`).
    stored: u64,
}

impl<'a> PartReader<'a> {
    /// A reader of `multipart` into `dir`; `expected` lists the part names the form takes.
    pub(crate) fn new(
        multipart: &'a mut Multipart,
        config: &'a Config,
        tap: &'a BodyTap,
        hash: &'a mut PartHasher,
        dir: &'a Path,
        expected: &'static str,
    ) -> Self {
        Self {
            multipart,
            config,
            tap,
            hash,
            dir,
            expected,
            count: 0,
            stored: 0,
        }
    }

    /// The next part, or `None` at the end of the body: 413 past `max_parts`, 400 for a
    /// part without a name or a malformed body.
    pub(crate) async fn next(&mut self) -> Result<Option<Part<'_>>, ApiError> {
        let (config, tap) = (self.config, self.tap);
        let Some(field) = self
            .multipart
            .next_field()
            .await
            .map_err(|e| multipart_error(e, tap, config))?
        else {
            return Ok(None);
        };
        self.count += 1;
        if self.count > config.max_parts {
            return Err(ApiError::too_large(format!(
                "the upload has more than {} parts",
                config.max_parts
            )));
        }
        let name = field.name().unwrap_or_default().to_string();
        self.hash.part(&name, field.file_name());
        if name.is_empty() {
            return Err(ApiError::bad_request(format!(
                "a multipart part has no name; expected {}",
                self.expected
            )));
        }
        Ok(Some(Part {
            field,
            name,
            config,
            tap,
            hash: self.hash,
            dir: self.dir,
            expected: self.expected,
            stored: &mut self.stored,
        }))
    }
}

/// One part of a form, to be stored or read.
pub(crate) struct Part<'r> {
    field: Field<'r>,
    name: String,
    config: &'r Config,
    tap: &'r BodyTap,
    hash: &'r mut PartHasher,
    dir: &'r Path,
    expected: &'static str,
    stored: &'r mut u64,
}

impl Part<'_> {
    /// The part's name (never empty).
    pub(crate) fn name(&self) -> &str {
        &self.name
    }

    /// The part's file name, as sent.
    pub(crate) fn file_name(&self) -> Option<&str> {
        self.field.file_name()
    }

    /// The part's file name, or its part name when it has none.
    pub(crate) fn file_name_or_part(&self) -> String {
        self.field
            .file_name()
            .filter(|n| !n.is_empty())
            .unwrap_or(&self.name)
            .to_string()
    }

    /// The file name of an image part: the name the light table uses for it; 400 without.
    pub(crate) fn image_name(&self) -> Result<String, ApiError> {
        match self.field.file_name() {
            Some(n) if !n.is_empty() => Ok(n.to_string()),
            _ => Err(ApiError::bad_request(format!(
                "every {0} part needs a file name (the name the light table uses for it), e.g. curl -F {0}=@im1.png",
                self.name
            ))),
        }
    }

    /// Where a file of the staging directory goes.
    pub(crate) fn path(&self, file: &str) -> PathBuf {
        self.dir.join(file)
    }

    /// 400 when `slot` already holds this part.
    pub(crate) fn once<T>(&self, slot: &Option<T>) -> Result<(), ApiError> {
        once(slot, &self.name)
    }

    /// 400 for a part the form does not take.
    pub(crate) fn unknown(&self) -> ApiError {
        ApiError::bad_request(format!(
            "unknown part {:?}; expected {}",
            self.name, self.expected
        ))
    }

    /// Store the part as `file` in the staging directory: an input file (`counted`, the
    /// name its refusal gives) adds to the stored bytes, 413 past `max_input_bytes`. Its
    /// first bytes and the file, open for reading.
    pub(crate) async fn store(
        &mut self,
        file: &str,
        counted: Option<&str>,
    ) -> Result<(Vec<u8>, File), ApiError> {
        let path = self.dir.join(file);
        let stored = counted.map(|name| (&mut *self.stored, name));
        stream_to_file(
            &mut self.field,
            &path,
            self.tap,
            self.config,
            self.hash,
            stored,
        )
        .await
    }

    /// Read a small value into memory, refusing more than `limit` bytes.
    pub(crate) async fn bytes(&mut self, limit: usize) -> Result<Vec<u8>, ApiError> {
        let (config, tap) = (self.config, self.tap);
        let mut out = Vec::new();
        while let Some(chunk) = self
            .field
            .chunk()
            .await
            .map_err(|e| multipart_error(e, tap, config))?
        {
            if out.len() + chunk.len() > limit {
                return Err(ApiError::too_large(format!(
                    "the {} part is larger than {limit} bytes",
                    self.name
                )));
            }
            self.hash.update(&chunk);
            out.extend_from_slice(&chunk);
        }
        Ok(out)
    }

    /// Read a small text value (UTF-8), refusing more than `limit` bytes.
    pub(crate) async fn text(&mut self, limit: usize) -> Result<String, ApiError> {
        let bytes = self.bytes(limit).await?;
        String::from_utf8(bytes)
            .map_err(|_| ApiError::invalid(format!("{}: not UTF-8 text", self.name)))
    }
}

/// 400 when `slot` already holds the part `part`.
pub(crate) fn once<T>(slot: &Option<T>, part: &str) -> Result<(), ApiError> {
    match slot {
        Some(_) => Err(ApiError::bad_request(format!(
            "the {part} part appears more than once"
        ))),
        None => Ok(()),
    }
}

fn multipart_error(e: MultipartError, tap: &BodyTap, config: &Config) -> ApiError {
    if tap.exceeded() || e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::too_large(format!(
            "the request body is larger than the limit of {} bytes",
            config.max_body_bytes
        ))
    } else {
        ApiError::bad_request(format!("malformed multipart body: {}", e.body_text()))
    }
}

/// 413: the file `name` takes the job's stored input over `limit`.
pub(crate) fn too_much_input(name: &str, limit: u64) -> ApiError {
    ApiError::too_large(format!(
        "{name:?} takes the job's stored input files over the limit of {limit} bytes (max-input-bytes)"
    ))
}

/// Chunks queued between the multipart reader and a part's file writer.
const WRITE_QUEUE: usize = 64;
/// The writer's buffer: large writes, few system calls.
const WRITE_BUFFER: usize = 1 << 20;

/// Write a part to `path`; returns its first bytes and the file, open for reading too (a
/// handle stays valid when the staging directory is renamed). `stored`, for input files, is
/// the job's input bytes so far, which the part adds to (413 past `max_input_bytes`), and
/// the part's name for that refusal. The chunks go through a
/// bounded channel to one blocking task that owns a std file, so a part costs one
/// blocking-pool hand-off rather than one per chunk, and the async side copies nothing.
async fn stream_to_file(
    field: &mut Field<'_>,
    path: &Path,
    tap: &BodyTap,
    config: &Config,
    hash: &mut PartHasher,
    mut stored: Option<(&mut u64, &str)>,
) -> Result<(Vec<u8>, File), ApiError> {
    let target = path.to_path_buf();
    let file = tokio::task::spawn_blocking(move || {
        File::options()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(target)
    })
    .await??;
    let (tx, rx) = tokio::sync::mpsc::channel::<Bytes>(WRITE_QUEUE);
    let writer = tokio::task::spawn_blocking(move || write_chunks(file, rx));
    let mut head = Vec::with_capacity(HEAD_BYTES);
    let read = async {
        while let Some(chunk) = field
            .chunk()
            .await
            .map_err(|e| multipart_error(e, tap, config))?
        {
            if head.len() < HEAD_BYTES {
                let take = (HEAD_BYTES - head.len()).min(chunk.len());
                head.extend_from_slice(&chunk[..take]);
            }
            if let Some((stored, name)) = &mut stored {
                **stored += chunk.len() as u64;
                if **stored > config.max_input_bytes {
                    return Err(too_much_input(name, config.max_input_bytes));
                }
            }
            hash.update(&chunk);
            if tx.send(chunk).await.is_err() {
                break; // the writer failed: its error is reported below
            }
        }
        Ok::<_, ApiError>(())
    }
    .await;
    drop(tx);
    let written = writer.await?;
    read?;
    Ok((head, written?))
}

/// The writer side of [`stream_to_file`]: until the channel closes.
fn write_chunks(
    file: File,
    mut chunks: tokio::sync::mpsc::Receiver<Bytes>,
) -> std::io::Result<File> {
    let mut out = std::io::BufWriter::with_capacity(WRITE_BUFFER, file);
    while let Some(chunk) = chunks.blocking_recv() {
        out.write_all(&chunk)?;
    }
    let file = out.into_inner().map_err(|e| e.into_error())?;
    start_writeback(&file);
    Ok(file)
}

/// Start writing a finished part to disk now, so that the fsync before the 202 has little
/// left to wait for (durability still rests on that fsync).
#[cfg(target_os = "linux")]
fn start_writeback(file: &File) {
    use std::os::fd::AsRawFd;
    // SAFETY: an open descriptor; the call only schedules writeback of its pages, and a
    // failure just leaves the work to the fsync.
    unsafe {
        libc::sync_file_range(file.as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE);
    }
}

#[cfg(not(target_os = "linux"))]
fn start_writeback(_file: &File) {}
