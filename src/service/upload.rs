//! Receiving a job: the multipart body streams to the job's staging directory part by
//! part, and everything cheap is checked before the job is accepted (multipart shape,
//! light table, names, image signatures and dimensions, options), so that bad input gets
//! its problem answer at once rather than as a failed job.
//!
//! Nothing the caller sends becomes a path: images are stored as `000.img`, `001.img`, …
//! and `manifest.json` maps them to the names the light table uses.
//!
//! A normals job sends a `normals` part (a normal map, stored as `normals.img`) instead of
//! images and lights; its header, the mask's size and the camera are checked here, its
//! pixels by the job.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::{Component, Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, BodyDataStream, Bytes};
use futures_util::future::BoxFuture;
use futures_util::{Stream, StreamExt};

use axum::extract::Multipart;
use axum::extract::multipart::{Field, MultipartError};
use image::ImageReader;
use serde::Deserialize;

use crate::core::camera::{self, Pinhole};
use crate::core::layout;
use crate::core::lights::{self, Light};
use crate::core::near;
use crate::core::normalmap::{self, Convention, NormalMapError};
use crate::core::normals_in;
use crate::core::options::MaskMode;
use crate::core::outputs;
use crate::core::{InputError, Options};

use super::config::{Config, MAX_LIGHTS_BYTES, MAX_OPTIONS_BYTES};
use super::error::ApiError;
use super::idempotency::PartHasher;
use super::prefetch::Prefetch;
use super::store::{
    LIGHTS_FILE, MANIFEST_FILE, MASK_FILE, Manifest, ManifestEntry, NORMALS_FILE, NormalsEntry,
    image_file,
};

/// The request body, shared between the multipart parser and the handler: it enforces the
/// body size limit, and lets the handler drain what is left after refusing an upload, so
/// that the client reads the refusal instead of a reset connection (a lingering close).
#[derive(Clone)]
pub struct BodyTap {
    state: Arc<TapState>,
}

struct TapState {
    stream: Mutex<BodyDataStream>,
    seen: AtomicU64,
    limit: u64,
    exceeded: AtomicBool,
}

/// How long a refused upload's remaining body is read and discarded (a lingering close,
/// so that the client gets to read the refusal instead of a broken pipe).
pub const LINGER: std::time::Duration = std::time::Duration::from_secs(5);

impl BodyTap {
    pub fn new(body: Body, limit: u64) -> Self {
        Self {
            state: Arc::new(TapState {
                stream: Mutex::new(body.into_data_stream()),
                seen: AtomicU64::new(0),
                limit,
                exceeded: AtomicBool::new(false),
            }),
        }
    }

    /// A body for the multipart parser that reads through the tap.
    pub fn body(&self) -> Body {
        Body::from_stream(TapReader(self.state.clone()))
    }

    /// Whether the body went over the limit.
    pub fn exceeded(&self) -> bool {
        self.state.exceeded.load(Ordering::SeqCst)
    }

    /// Read and discard the rest of the body, for at most `max`.
    pub async fn drain(&self, max: Duration) {
        let state = self.state.clone();
        let _ = tokio::time::timeout(max, async move {
            loop {
                let next = std::future::poll_fn(|cx| {
                    state
                        .stream
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .poll_next_unpin(cx)
                })
                .await;
                if !matches!(next, Some(Ok(_))) {
                    break;
                }
            }
        })
        .await;
    }
}

struct TapReader(Arc<TapState>);

impl Stream for TapReader {
    type Item = Result<Bytes, std::io::Error>;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let state = &self.0;
        if state.exceeded.load(Ordering::SeqCst) {
            return Poll::Ready(Some(Err(too_large_error())));
        }
        let polled = state
            .stream
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .poll_next_unpin(cx);
        match polled {
            Poll::Ready(Some(Ok(bytes))) => {
                let seen =
                    state.seen.fetch_add(bytes.len() as u64, Ordering::SeqCst) + bytes.len() as u64;
                if seen > state.limit {
                    state.exceeded.store(true, Ordering::SeqCst);
                    Poll::Ready(Some(Err(too_large_error())))
                } else {
                    Poll::Ready(Some(Ok(bytes)))
                }
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(std::io::Error::other(e)))),
            Poll::Ready(None) => Poll::Ready(None),
            Poll::Pending => Poll::Pending,
        }
    }
}

fn too_large_error() -> std::io::Error {
    std::io::Error::other("the request body is over the size limit")
}

/// Bytes kept from the start of each file to recognise its format.
const HEAD_BYTES: usize = 64;
const ARCHIVE_FILE: &str = "archive.zip";
/// Longest `callback_url` accepted (bytes).
const MAX_CALLBACK_BYTES: usize = 2048;
/// Longest `calibration` part accepted (bytes; an id is 36).
const MAX_CALIBRATION_BYTES: usize = 256;
/// Longest camera file accepted (`camera` part, or a camera file in an archive): a K.txt
/// or camera.json is a few dozen bytes.
const MAX_CAMERA_BYTES: usize = 4096;
/// Longest `convention` part accepted (bytes; `benchmark` is 9).
const MAX_CONVENTION_BYTES: usize = 64;

/// The light table of a job's `calibration` part (the id as sent), as the caller may see
/// it; a 422 naming the id when there is none.
pub type CalibrationTables<'a> =
    &'a (dyn Fn(String) -> BoxFuture<'static, Result<Vec<u8>, ApiError>> + Send + Sync);

/// An image (or a mask, a normal map) stored in the staging directory.
#[derive(Debug, Clone)]
struct StoredImage {
    /// The caller's name for it (what the light table says).
    name: String,
    /// The stored file's name.
    file: String,
    width: u32,
    height: u32,
    /// Bits per sample (8, 16 or 32), as the core will decode it.
    depth: u8,
}

impl StoredImage {
    fn entry(&self) -> ManifestEntry {
        ManifestEntry {
            name: self.name.clone(),
            file: self.file.clone(),
        }
    }
}

/// A received, checked job, ready to be queued.
#[derive(Debug)]
pub struct Received {
    pub image_count: usize,
    /// The options, defaults filled in.
    pub options: serde_json::Value,
    /// The `callback_url` part, as sent (the caller checks it).
    pub callback_url: Option<String>,
    /// Whether its light table gives positions (near lights): the job decodes its images
    /// itself, so none scanned during the upload are kept for it.
    pub near: bool,
}

#[derive(Default)]
struct Parts {
    images: Vec<StoredImage>,
    lights: Option<Vec<u8>>,
    /// The `lights` part's file name, when it has one.
    lights_file: Option<String>,
    mask: Option<StoredImage>,
    options: Option<Options>,
    /// The mask mode the options part names, if it names one.
    mask_chosen: Option<MaskMode>,
    archive: Option<PathBuf>,
    callback_url: Option<String>,
    /// The `calibration` part: a calibration id instead of a light table.
    calibration: Option<String>,
    /// The `camera` part: a K.txt's or camera.json's text, or `fx,fy,cx,cy`.
    camera: Option<Pinhole>,
    /// The `normals` part: a normal map to integrate instead of images and lights.
    normals: Option<StoredImage>,
    /// The `convention` part: how the normal map's green channel points.
    convention: Option<Convention>,
    /// The top-level fields the options part names.
    options_fields: Vec<String>,
    count: usize,
    /// Bytes of image and mask files written so far (bounded by `max_input_bytes`).
    stored: u64,
}

/// Read the multipart body into `dir` and check it. The caller removes `dir` on error.
/// Each image is handed to `prefetch` to scan once it is written and probed; every
/// part goes through `hash`; a `calibration` part's table comes from `calibrations`.
pub async fn receive(
    config: &Config,
    dir: &Path,
    multipart: &mut Multipart,
    tap: &BodyTap,
    prefetch: Option<&Prefetch>,
    hash: &mut PartHasher,
    calibrations: CalibrationTables<'_>,
) -> Result<Received, ApiError> {
    let mut parts = Parts::default();
    while let Some(mut field) = multipart
        .next_field()
        .await
        .map_err(|e| multipart_error(e, tap, config))?
    {
        parts.count += 1;
        if parts.count > config.max_parts {
            return Err(ApiError::too_large(format!(
                "the upload has more than {} parts",
                config.max_parts
            )));
        }
        let part = field.name().unwrap_or_default().to_string();
        hash.part(&part, field.file_name());
        if parts.normals.is_some() && IMAGE_JOB_PARTS.contains(&part.as_str()) {
            return Err(normals_with(&part));
        }
        match part.as_str() {
            "images" => {
                if parts.archive.is_some() {
                    return Err(both_forms());
                }
                if parts.images.len() >= config.max_images {
                    return Err(InputError::TooManyImages {
                        count: parts.images.len() + 1,
                        limit: config.max_images,
                    }
                    .into());
                }
                let name = file_name(&field, "images")?;
                let file = image_file(parts.images.len());
                let target = dir.join(&file);
                let stored = Some((&mut parts.stored, name.as_str()));
                let (head, written) =
                    stream_to_file(&mut field, &target, tap, config, hash, stored).await?;
                let (width, height, depth) =
                    probe(dir.join(&file), name.clone(), head, config).await?;
                if let Some(p) = prefetch {
                    // The decoded copy's unlinked scratch file goes beside the staging
                    // directory, not in it: a scan that starts late (the pool busy with
                    // another job) would otherwise find it renamed by the commit.
                    p.start(file.clone(), written, dir.parent().unwrap_or(dir));
                }
                parts.images.push(StoredImage {
                    name,
                    file,
                    width,
                    height,
                    depth,
                });
            }
            "lights" => {
                if parts.archive.is_some() {
                    return Err(both_forms());
                }
                once(&parts.lights, "lights")?;
                parts.lights_file = field.file_name().map(str::to_string);
                parts.lights = Some(
                    read_small(&mut field, MAX_LIGHTS_BYTES, "lights", tap, config, hash).await?,
                );
            }
            "mask" => {
                once(&parts.mask, "mask")?;
                let name = file_name_or(&field, "mask");
                let target = dir.join(MASK_FILE);
                let stored = Some((&mut parts.stored, name.as_str()));
                let (head, _) =
                    stream_to_file(&mut field, &target, tap, config, hash, stored).await?;
                let (width, height, depth) = probe(dir.join(MASK_FILE), name.clone(), head, config)
                    .await
                    .map_err(|e| {
                        if e.status() == axum::http::StatusCode::UNPROCESSABLE_ENTITY {
                            ApiError::invalid(format!("mask: {}", e.detail()))
                        } else {
                            e
                        }
                    })?;
                parts.mask = Some(StoredImage {
                    name,
                    file: MASK_FILE.to_string(),
                    width,
                    height,
                    depth,
                });
            }
            "options" => {
                once(&parts.options, "options")?;
                let bytes =
                    read_small(&mut field, MAX_OPTIONS_BYTES, "options", tap, config, hash).await?;
                let options = parse_options(&bytes)?;
                parts.options_fields = serde_json::from_slice::<serde_json::Value>(&bytes)
                    .ok()
                    .and_then(|v| Some(v.as_object()?.keys().cloned().collect()))
                    .unwrap_or_default();
                let names_mask = parts.options_fields.iter().any(|f| f == "mask");
                parts.mask_chosen = names_mask.then_some(options.mask);
                parts.options = Some(options);
            }
            "callback_url" => {
                once(&parts.callback_url, "callback_url")?;
                let bytes = read_small(
                    &mut field,
                    MAX_CALLBACK_BYTES,
                    "callback_url",
                    tap,
                    config,
                    hash,
                )
                .await?;
                let url = String::from_utf8(bytes)
                    .map_err(|_| ApiError::invalid("callback_url: not UTF-8 text"))?;
                parts.callback_url = Some(url.trim().to_string());
            }
            "calibration" => {
                if parts.archive.is_some() {
                    return Err(calibration_with_archive());
                }
                once(&parts.calibration, "calibration")?;
                let bytes = read_small(
                    &mut field,
                    MAX_CALIBRATION_BYTES,
                    "calibration",
                    tap,
                    config,
                    hash,
                )
                .await?;
                let id = String::from_utf8(bytes)
                    .map_err(|_| ApiError::invalid("calibration: not UTF-8 text"))?;
                parts.calibration = Some(id.trim().to_string());
            }
            "camera" => {
                once(&parts.camera, "camera")?;
                let bytes =
                    read_small(&mut field, MAX_CAMERA_BYTES, "camera", tap, config, hash).await?;
                parts.camera = Some(parse_camera(&bytes, "the camera part")?);
            }
            "archive" => {
                once(&parts.archive, "archive")?;
                if !parts.images.is_empty() || parts.lights.is_some() {
                    return Err(both_forms());
                }
                if parts.calibration.is_some() {
                    return Err(calibration_with_archive());
                }
                let path = dir.join(ARCHIVE_FILE);
                // Not input bytes: it is removed once unpacked, and what it unpacks to is
                // counted as image parts are.
                let (head, _) = stream_to_file(&mut field, &path, tap, config, hash, None).await?;
                if !(head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06")) {
                    return Err(ApiError::unsupported_media(
                        "the archive part is not a zip file (expected a .zip of a folder with the images and light_directions.csv, or in the benchmark layout with light_directions.txt and filenames.txt)",
                    ));
                }
                parts.archive = Some(path);
            }
            "normals" => {
                once(&parts.normals, "normals")?;
                if let Some(other) = parts.image_job_part() {
                    return Err(normals_with(other));
                }
                let name = file_name_or(&field, "normals");
                let target = dir.join(NORMALS_FILE);
                let stored = Some((&mut parts.stored, name.as_str()));
                let (head, _) =
                    stream_to_file(&mut field, &target, tap, config, hash, stored).await?;
                let (width, height, depth) =
                    probe_normals(target, name.clone(), head, config).await?;
                parts.normals = Some(StoredImage {
                    name,
                    file: NORMALS_FILE.to_string(),
                    width,
                    height,
                    depth,
                });
            }
            "convention" => {
                once(&parts.convention, "convention")?;
                let bytes = read_small(
                    &mut field,
                    MAX_CONVENTION_BYTES,
                    "convention",
                    tap,
                    config,
                    hash,
                )
                .await?;
                parts.convention = Some(parse_convention(&bytes)?);
            }
            "" => {
                return Err(ApiError::bad_request(format!(
                    "a multipart part has no name; expected {PART_NAMES}"
                )));
            }
            other => {
                return Err(ApiError::bad_request(format!(
                    "unknown part {other:?}; expected {PART_NAMES}"
                )));
            }
        }
    }

    let mut options = parts.options.take().unwrap_or_default();
    if parts.normals.is_some() {
        return finish_normals(parts, options, dir).await;
    }
    if parts.convention.is_some() {
        return Err(ApiError::invalid(
            "a convention part goes with a normals part: it says how the normal map's green channel points",
        ));
    }
    let mut notes = Vec::new();
    if let Some(archive) = parts.archive.take() {
        let limits = ArchiveLimits::from(config);
        let out = dir.to_path_buf();
        // The archive's own mask.png is the mask unless a mask part came, or the options
        // chose a mode that takes none (auto, none); it then makes the mode `given`.
        let own_mask = match (&parts.mask, parts.mask_chosen) {
            (Some(_), _) => Err("a mask part was sent"),
            (None, None | Some(MaskMode::Given)) => Ok(()),
            (None, Some(_)) => Err("the mask mode asked for takes no mask"),
        };
        let unpacked = tokio::task::spawn_blocking(move || {
            let r = extract_archive(&archive, &out, &limits, own_mask.is_ok());
            let _ = std::fs::remove_file(&archive);
            r
        })
        .await??;
        parts.images = unpacked.images;
        parts.lights = Some(unpacked.table);
        notes = unpacked.notes;
        if let Some((name, camera)) = unpacked.camera {
            notes.push(choose_camera(
                &mut options,
                parts.camera.is_some(),
                &name,
                camera,
            ));
        }
        match (own_mask, unpacked.mask) {
            (Ok(()), Some(mask)) => {
                parts.mask = Some(mask);
                options.mask = MaskMode::Given;
            }
            (Err(why), _) if unpacked.has_mask => {
                notes.push(format!("{} in the archive not used: {why}", layout::MASK));
            }
            _ => {}
        }
    }
    let calibration = parts.calibration.take();
    let table = match (parts.lights.take(), &calibration) {
        (Some(_), Some(_)) => {
            return Err(ApiError::invalid(
                "send either a lights part or a calibration part (whose lights are then used), not both",
            ));
        }
        (Some(table), None) => table,
        (None, Some(id)) => calibrations(id.clone()).await?,
        (None, None) => {
            return Err(ApiError::bad_request(
                "missing the lights part (the light table: CSV `name, x, y, z[, intensity]`, JSON or .lp), a calibration part or an archive part; or send a normals part (a normal map to integrate)",
            ));
        }
    };
    if parts.images.is_empty() {
        return Err(ApiError::bad_request(
            "no images parts: send each image as a file part named images (curl -F images=@im1.png), or an archive part",
        ));
    }
    // A part named `*.lp` is read as one, so that its errors are the .lp table's; the job
    // reads the stored table back with `lights::parse_bytes`, which knows an .lp table
    // by its first line, as `lp::parse_bytes` requires it.
    // A JSON table may give positions (near lights): it is stored as sent, and its rig
    // (camera, distance, unit) completed from the job's options below.
    let parsed = match parts.lights_file.as_deref() {
        Some(file) if lights::lp::is_lp_name(file) => lights::Table {
            lights: lights::lp::parse_bytes(file, &table)?,
            rig: lights::Rig::default(),
        },
        _ => lights::parse_table_bytes(&table)?,
    };
    let near = parsed.is_near();
    if near {
        check_near_options(&parts.options_fields, &options)?;
    }
    let lights = parsed.lights;
    if let Some(id) = &calibration {
        check_calibration_names(id, &lights, &parts.images)?;
    }
    let ordered = check_names(&lights, &parts.images, config)?;
    check_sizes(&ordered)?;
    if let Some(mask) = &parts.mask {
        let first = ordered[0];
        if (mask.width, mask.height) != (first.width, first.height) {
            return Err(InputError::Mask(format!(
                "{:?} is {}×{} but the images are {}×{}",
                mask.name, mask.width, mask.height, first.width, first.height
            ))
            .into());
        }
    } else if options.mask == MaskMode::Given {
        return Err(InputError::Mask(
            "options ask for the given mask (\"mask\": \"given\") but no mask part was sent".into(),
        )
        .into());
    }
    take_camera_part(&mut options, parts.camera)?;
    let first = ordered[0];
    let (width, height) = (first.width as usize, first.height as usize);
    if near {
        near_rig(&options, &parsed.rig, &lights, (width, height))?;
    } else {
        options.check_camera(width, height)?;
    }

    let manifest = Manifest {
        images: ordered.iter().map(|i| i.entry()).collect(),
        mask: parts.mask.as_ref().map(StoredImage::entry),
        normals: None,
        notes,
    };
    write_manifest(dir, &manifest).await?;
    tokio::fs::write(dir.join(LIGHTS_FILE), &table).await?;
    let mut received = received(ordered.len(), &options, parts.callback_url)?;
    received.near = near;
    Ok(received)
}

/// The camera and working distance of a near-light job: the job's (`camera` part or
/// option, `distance` option) or else its light table's; a 422 naming what neither gives,
/// a camera that cannot have taken the `width × height` images, or an LED of `lights`
/// facing away from the object.
pub(super) fn near_rig(
    options: &Options,
    rig: &lights::Rig,
    lights: &[lights::Light],
    (width, height): (usize, usize),
) -> Result<(Pinhole, f64), ApiError> {
    let camera = options.camera.or(rig.camera);
    let distance = options.distance.or(rig.distance);
    let mut missing = Vec::new();
    if camera.is_none() {
        missing.push(
            "the camera (\"camera\": {\"fx\", \"fy\", \"cx\", \"cy\"} in the light table, or the job's camera part or `camera` option)",
        );
    }
    if distance.is_none() {
        missing.push(
            "the working distance to the object along the optical axis (\"distance\" in the light table, or the job's `distance` option)",
        );
    }
    let (Some(camera), Some(distance)) = (camera, distance) else {
        return Err(InputError::Lights(format!(
            "lights given by position (near lights) need {}",
            missing.join(" and ")
        ))
        .into());
    };
    camera.check(width, height).map_err(InputError::from)?;
    crate::core::options::check_distance(Some(distance), Some(&camera))?;
    crate::core::near::check_cones(lights, &camera, distance, (width, height))?;
    Ok((camera, distance))
}

/// A near-light job's options name only the fields it takes ([`near::OPTIONS`]) and its
/// `outputs` only what it writes ([`near::check_outputs`]): a 422 naming the first that
/// does not apply.
fn check_near_options(fields: &[String], options: &Options) -> Result<(), ApiError> {
    if let Some(field) = fields.iter().find(|f| !near::OPTIONS.contains(&f.as_str())) {
        return Err(InputError::Options(format!(
            "field `{field}` does not apply to a near-light job, which takes {}",
            near::OPTIONS.join(", ")
        ))
        .into());
    }
    if let Some(names) = &options.outputs {
        near::check_outputs(names)?;
    }
    Ok(())
}

/// A normals job's parts checked against each other, and its manifest written: its
/// options name only the fields it takes, a mask has the map's size, a camera (part or
/// option) fits the map, the outputs named are ones it writes with or without that
/// camera. The map's pixels are the job's to check (unit length, usable pixels): it fails
/// naming them.
async fn finish_normals(
    mut parts: Parts,
    mut options: Options,
    dir: &Path,
) -> Result<Received, ApiError> {
    let Some(map) = parts.normals.take() else {
        return Err(ApiError::internal("no normals part"));
    };
    let other = (parts.options_fields.iter()).find(|f| !normals_in::OPTIONS.contains(&f.as_str()));
    if let Some(field) = other {
        return Err(InputError::Options(format!(
            "field `{field}` does not apply to a normals job, which takes {}",
            normals_in::OPTIONS.join(", ")
        ))
        .into());
    }
    if let Some(mask) = &parts.mask
        && (mask.width, mask.height) != (map.width, map.height)
    {
        return Err(NormalMapError::MaskSize {
            mask: mask.name.clone(),
            mask_width: mask.width as usize,
            mask_height: mask.height as usize,
            name: map.name.clone(),
            width: map.width as usize,
            height: map.height as usize,
        }
        .into());
    }
    take_camera_part(&mut options, parts.camera)?;
    options.check_camera(map.width as usize, map.height as usize)?;
    if let Some(names) = &options.outputs {
        normals_in::check_outputs(names, options.camera.is_some())?;
    }
    let manifest = Manifest {
        images: Vec::new(),
        mask: parts.mask.as_ref().map(StoredImage::entry),
        normals: Some(NormalsEntry {
            name: map.name,
            file: map.file,
            convention: parts.convention.unwrap_or_default(),
        }),
        notes: Vec::new(),
    };
    write_manifest(dir, &manifest).await?;
    received(0, &options, parts.callback_url)
}

/// The parts of an image job, which a normals job replaces.
const IMAGE_JOB_PARTS: [&str; 4] = ["images", "lights", "calibration", "archive"];

/// Every part name `POST /v1/jobs` takes, for refusals.
const PART_NAMES: &str = "images, lights, calibration, mask, camera, options, callback_url, archive, normals or convention";

impl Parts {
    /// The first of [`IMAGE_JOB_PARTS`] received, if any.
    fn image_job_part(&self) -> Option<&'static str> {
        let sent = [
            !self.images.is_empty(),
            self.lights.is_some(),
            self.calibration.is_some(),
            self.archive.is_some(),
        ];
        IMAGE_JOB_PARTS
            .into_iter()
            .zip(sent)
            .find_map(|(part, sent)| sent.then_some(part))
    }
}

fn normals_with(part: &str) -> ApiError {
    ApiError::invalid(format!(
        "the upload has both a normals part and {part}: a normals job integrates the normal map it is sent (with an optional mask, camera, convention and options) and takes no images, lights, calibration or archive"
    ))
}

/// The `convention` part: `opengl` (aliases `project`, `benchmark`) or `directx`.
fn parse_convention(bytes: &[u8]) -> Result<Convention, ApiError> {
    let text = String::from_utf8_lossy(bytes).trim().to_string();
    serde_json::from_value(serde_json::Value::String(text.clone())).map_err(|_| {
        ApiError::invalid(format!(
            "convention: {text:?} is not a normal map convention; expected opengl (green up; aliases project, benchmark) or directx (green down)"
        ))
    })
}

/// The `camera` part becomes the `camera` option; a 422 when both were sent.
fn take_camera_part(options: &mut Options, part: Option<Pinhole>) -> Result<(), ApiError> {
    if let Some(camera) = part {
        if options.camera.is_some() {
            return Err(ApiError::invalid(
                "send the camera either as the camera part or as the `camera` option, not both",
            ));
        }
        options.camera = Some(camera);
    }
    Ok(())
}

async fn write_manifest(dir: &Path, manifest: &Manifest) -> Result<(), ApiError> {
    let bytes = serde_json::to_vec_pretty(manifest)
        .map_err(|e| ApiError::internal(format!("manifest: {e}")))?;
    tokio::fs::write(dir.join(MANIFEST_FILE), bytes).await?;
    Ok(())
}

fn received(
    image_count: usize,
    options: &Options,
    callback_url: Option<String>,
) -> Result<Received, ApiError> {
    Ok(Received {
        image_count,
        options: serde_json::to_value(options)
            .map_err(|e| ApiError::internal(format!("options: {e}")))?,
        callback_url,
        near: false,
    })
}

fn calibration_with_archive() -> ApiError {
    ApiError::invalid(
        "a calibration part goes with images parts; an archive brings its own light table",
    )
}

/// A camera file's bytes (`what` names it in a refusal): 422 naming the problem.
fn parse_camera(bytes: &[u8], what: &str) -> Result<Pinhole, ApiError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| ApiError::invalid(format!("camera: {what} is not UTF-8 text")))?;
    let named = |camera::CameraError(e)| camera::CameraError(format!("{what}: {e}"));
    let camera = Pinhole::parse(text).and_then(|k| k.check_values().map(|()| k));
    Ok(camera.map_err(|e| InputError::from(named(e)))?)
}

/// An archive's own camera file is the camera unless one was sent (`camera` part or
/// option): the note for `result.json` says which.
fn choose_camera(options: &mut Options, part: bool, name: &str, camera: Pinhole) -> String {
    if part || options.camera.is_some() {
        return format!("{name} in the archive not used: a camera was sent");
    }
    options.camera = Some(camera);
    format!("camera from {name} in the archive")
}

/// Every light of the calibration has its image and every image its light, else a 422
/// listing the names that do not match.
fn check_calibration_names(
    id: &str,
    lights: &[Light],
    images: &[StoredImage],
) -> Result<(), ApiError> {
    let sent: std::collections::HashSet<&str> = images.iter().map(|i| i.name.as_str()).collect();
    let named: std::collections::HashSet<&str> = lights.iter().map(|l| l.name.as_str()).collect();
    let missing: Vec<&str> = (lights.iter().map(|l| l.name.as_str()))
        .filter(|n| !sent.contains(n))
        .collect();
    let unmatched: Vec<&str> = (images.iter().map(|i| i.name.as_str()))
        .filter(|n| !named.contains(n))
        .collect();
    let mut problems = Vec::new();
    if !missing.is_empty() {
        problems.push(format!("no image for its lights {}", missing.join(", ")));
    }
    if !unmatched.is_empty() {
        problems.push(format!(
            "no light in it for the images {}",
            unmatched.join(", ")
        ));
    }
    if problems.is_empty() {
        return Ok(());
    }
    Err(ApiError::invalid(format!(
        "the images do not match the lights of calibration {id} (matched by name): {}",
        problems.join("; ")
    )))
}

fn both_forms() -> ApiError {
    ApiError::bad_request("send either an archive part or images and lights parts, not both")
}

pub(super) fn once<T>(slot: &Option<T>, part: &str) -> Result<(), ApiError> {
    match slot {
        Some(_) => Err(ApiError::bad_request(format!(
            "the {part} part appears more than once"
        ))),
        None => Ok(()),
    }
}

pub(super) fn multipart_error(e: MultipartError, tap: &BodyTap, config: &Config) -> ApiError {
    if tap.exceeded() || e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::too_large(format!(
            "the request body is larger than the limit of {} bytes",
            config.max_body_bytes
        ))
    } else {
        ApiError::bad_request(format!("malformed multipart body: {}", e.body_text()))
    }
}

/// A part's file name, or `default` when it has none.
fn file_name_or(field: &Field<'_>, default: &str) -> String {
    field
        .file_name()
        .filter(|n| !n.is_empty())
        .unwrap_or(default)
        .to_string()
}

/// The file name of an image part: the name the light table uses for it.
pub(super) fn file_name(field: &Field<'_>, part: &str) -> Result<String, ApiError> {
    match field.file_name() {
        Some(n) if !n.is_empty() => Ok(n.to_string()),
        _ => Err(ApiError::bad_request(format!(
            "every {part} part needs a file name (the name the light table uses for it), e.g. curl -F {part}=@im1.png"
        ))),
    }
}

/// Parse the `options` part; errors name the field at fault.
pub fn parse_options(bytes: &[u8]) -> Result<Options, ApiError> {
    // Straight from the bytes, as the worker reads them back: a `Value` would keep only
    // the last of repeated keys, where this refuses them. The `Value` is built only to
    // explain a refusal.
    let options =
        serde_json::from_slice::<Options>(bytes).map_err(|e| {
            match serde_json::from_slice::<serde_json::Value>(bytes) {
                Ok(value) => InputError::Options(explain_options_error(&value, e)),
                Err(e) => InputError::Options(format!("not valid JSON: {e}")),
            }
        })?;
    if let Some(names) = &options.outputs {
        outputs::check_selection(names)?;
    }
    options.check_values()?;
    Ok(options)
}

/// serde's message, prefixed with the top-level field that fails on its own.
fn explain_options_error(value: &serde_json::Value, err: serde_json::Error) -> String {
    let message = err.to_string();
    if let serde_json::Value::Object(fields) = value {
        for (key, v) in fields {
            let single =
                serde_json::Value::Object(std::iter::once((key.clone(), v.clone())).collect());
            if let Err(e) = Options::deserialize(&single) {
                let e = e.to_string();
                return if e.contains(&format!("`{key}`")) {
                    e
                } else {
                    format!("field `{key}`: {e}")
                };
            }
        }
    }
    message
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
pub(super) async fn stream_to_file(
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

/// Read a small text part into memory, refusing more than `limit` bytes.
pub(super) async fn read_small(
    field: &mut Field<'_>,
    limit: usize,
    part: &str,
    tap: &BodyTap,
    config: &Config,
    hash: &mut PartHasher,
) -> Result<Vec<u8>, ApiError> {
    let mut out = Vec::new();
    while let Some(chunk) = field
        .chunk()
        .await
        .map_err(|e| multipart_error(e, tap, config))?
    {
        if out.len() + chunk.len() > limit {
            return Err(ApiError::too_large(format!(
                "the {part} part is larger than {limit} bytes"
            )));
        }
        hash.update(&chunk);
        out.extend_from_slice(&chunk);
    }
    Ok(out)
}

/// Recognise the image format from its signature and read its dimensions and bit depth
/// from the header (no decoding), off the async runtime.
pub(super) async fn probe(
    path: PathBuf,
    name: String,
    head: Vec<u8>,
    config: &Config,
) -> Result<(u32, u32, u8), ApiError> {
    let max_pixels = config.max_pixels;
    Ok(tokio::task::spawn_blocking(move || probe_image(&path, &name, &head, max_pixels)).await??)
}

fn probe_image(
    path: &Path,
    name: &str,
    head: &[u8],
    max_pixels: u64,
) -> Result<(u32, u32, u8), InputError> {
    let (w, h, colour) = read_header(path, name, head, max_pixels)?;
    // Bits per sample of what the decoder will produce (the core's bit depth).
    let depth = 8 * colour.bytes_per_pixel() / colour.channel_count().max(1);
    Ok((w, h, depth))
}

/// A normal map's dimensions and bits per sample (8, 16 or 32) from its header: a 422
/// naming the part's file when it is no normal map (unrecognised, gray), 413 over the
/// pixel limit.
async fn probe_normals(
    path: PathBuf,
    name: String,
    head: Vec<u8>,
    config: &Config,
) -> Result<(u32, u32, u8), ApiError> {
    let max_pixels = config.max_pixels;
    tokio::task::spawn_blocking(move || {
        let (w, h, colour) = read_header(&path, &name, &head, max_pixels).map_err(|e| {
            if e.is_too_large() || matches!(e, InputError::Io { .. }) {
                ApiError::from(e)
            } else {
                NormalMapError::unreadable(&name, e).into()
            }
        })?;
        Ok((w, h, normalmap::bits_of(&name, colour)?))
    })
    .await?
}

/// Recognise a picture from its first bytes `head` and read its dimensions and colour
/// type from the header; refused over `max_pixels`.
fn read_header(
    path: &Path,
    name: &str,
    head: &[u8],
    max_pixels: u64,
) -> Result<(u32, u32, image::ColorType), InputError> {
    use image::ImageDecoder;
    let format = image::guess_format(head).map_err(|_| InputError::UnsupportedFormat {
        name: name.into(),
        reason: "unrecognised file signature".into(),
    })?;
    let file = File::open(path).map_err(|e| InputError::io(path, e))?;
    let decoder = ImageReader::with_format(BufReader::new(file), format)
        .into_decoder()
        .map_err(|e| match e {
            image::ImageError::Unsupported(u) => InputError::UnsupportedFormat {
                name: name.into(),
                reason: u.to_string(),
            },
            other => InputError::Decode {
                name: name.into(),
                reason: other.to_string(),
            },
        })?;
    let (w, h) = decoder.dimensions();
    let colour = decoder.color_type();
    let pixels = u64::from(w) * u64::from(h);
    if pixels > max_pixels {
        return Err(InputError::TooLarge {
            name: name.into(),
            width: w.into(),
            height: h.into(),
            pixels,
            limit: max_pixels,
        });
    }
    Ok((w, h, colour))
}

/// The refusal of the part `name` that takes a job's stored input files past `limit`
/// bytes (checked as it is written, so the rest of the body is not read).
fn too_much_input(name: &str, limit: u64) -> ApiError {
    ApiError::too_large(format!(
        "{name:?} takes the job's stored input files over the limit of {limit} bytes (max-input-bytes)"
    ))
}

/// Pair the table's rows with the uploaded images, in table order.
fn check_names<'a>(
    lights: &[Light],
    images: &'a [StoredImage],
    config: &Config,
) -> Result<Vec<&'a StoredImage>, ApiError> {
    if lights.len() > config.max_images {
        return Err(InputError::TooManyImages {
            count: lights.len(),
            limit: config.max_images,
        }
        .into());
    }
    let mut by_name: HashMap<&str, (usize, &StoredImage)> = HashMap::new();
    for (i, img) in images.iter().enumerate() {
        if let Some((first, _)) = by_name.insert(img.name.as_str(), (i, img)) {
            return Err(ApiError::invalid(format!(
                "image {:?} was sent twice (image parts {} and {})",
                img.name,
                first + 1,
                i + 1
            )));
        }
    }
    let mut ordered = Vec::with_capacity(lights.len());
    for l in lights {
        match by_name.remove(l.name.as_str()) {
            Some((_, img)) => ordered.push(img),
            None => {
                return Err(InputError::MissingImage {
                    name: l.name.clone(),
                }
                .into());
            }
        }
    }
    if let Some(img) = images
        .iter()
        .find(|i| by_name.contains_key(i.name.as_str()))
    {
        return Err(InputError::UnlistedImage {
            name: img.name.clone(),
        }
        .into());
    }
    Ok(ordered)
}

fn check_sizes(ordered: &[&StoredImage]) -> Result<(), ApiError> {
    let first = ordered[0];
    for img in &ordered[1..] {
        if (img.width, img.height) != (first.width, first.height) {
            return Err(InputError::SizeMismatch {
                name: img.name.clone(),
                width: img.width,
                height: img.height,
                first: first.name.clone(),
                expected_width: first.width,
                expected_height: first.height,
            }
            .into());
        }
        if img.depth != first.depth {
            return Err(InputError::BitDepthMismatch {
                name: img.name.clone(),
                depth: img.depth,
                first: first.name.clone(),
                expected: first.depth,
            }
            .into());
        }
    }
    Ok(())
}

/// Bounds on what an archive may unpack to.
#[derive(Debug, Clone, Copy)]
struct ArchiveLimits {
    max_entries: usize,
    max_unpacked: u64,
    max_images: usize,
    max_pixels: u64,
    max_input_bytes: u64,
}

impl From<&Config> for ArchiveLimits {
    fn from(c: &Config) -> Self {
        Self {
            max_entries: c.max_parts,
            max_unpacked: c.max_unpacked_bytes,
            max_images: c.max_images,
            max_pixels: c.max_pixels,
            max_input_bytes: c.max_input_bytes,
        }
    }
}

/// macOS and editor leftovers that are skipped rather than refused.
fn is_junk(components: &[String]) -> bool {
    components
        .iter()
        .any(|c| c == "__MACOSX" || c.starts_with('.'))
}

fn zip_error(entry: &str, e: zip::result::ZipError) -> ApiError {
    match e {
        zip::result::ZipError::UnsupportedArchive(what) => {
            ApiError::unsupported_media(format!("archive entry {entry:?} cannot be read: {what}"))
        }
        zip::result::ZipError::CompressionMethodNotSupported(m) => {
            ApiError::unsupported_media(format!(
                "archive entry {entry:?} uses compression method {m}; only stored and deflate are supported"
            ))
        }
        other => ApiError::invalid(format!("archive entry {entry:?} cannot be read: {other}")),
    }
}

/// What an archive unpacked to.
struct Unpacked {
    /// The images its table names, in archive order.
    images: Vec<StoredImage>,
    /// Its light table, as JSON in the project's frame ([`lights::to_json`]); a table
    /// giving positions, as the archive holds it.
    table: Vec<u8>,
    /// Its `mask.png`, when asked for and present.
    mask: Option<StoredImage>,
    /// Whether it holds a `mask.png` (used or not).
    has_mask: bool,
    /// Its camera file (`camera.json`, else `K.txt`): the name and the camera.
    camera: Option<(String, Pinhole)>,
    notes: Vec<String>,
}

/// Unpack a zip of a folder in one of the layouts [`layout`] reads (at the top of the
/// archive or in one folder) into `dir`: its table files are read, then the images the
/// table names (and its `mask.png` when `want_mask`) streamed out under the size caps;
/// every other entry is skipped.
fn extract_archive(
    path: &Path,
    dir: &Path,
    limits: &ArchiveLimits,
    want_mask: bool,
) -> Result<Unpacked, ApiError> {
    let file = File::open(path)?;
    let mut zip = zip::ZipArchive::new(BufReader::new(file))
        .map_err(|e| ApiError::invalid(format!("the archive is not a readable zip file: {e}")))?;
    if zip.len() > limits.max_entries {
        return Err(ApiError::too_large(format!(
            "the archive has {} entries, over the limit of {}",
            zip.len(),
            limits.max_entries
        )));
    }

    // Pass 1: names only. Refuse unsafe paths and links; find the layout.
    let mut entries: Vec<(usize, Vec<String>)> = Vec::new();
    for i in 0..zip.len() {
        let entry = zip
            .by_index_data(i)
            .map_err(|e| zip_error(&format!("#{i}"), e))?;
        let raw = entry
            .name()
            .map(|n| n.into_owned())
            .unwrap_or_else(|_| format!("#{i}"));
        let unsafe_path = || {
            ApiError::invalid(format!(
                "archive entry {raw:?} has an unsafe path (absolute, or leading out of the archive)"
            ))
        };
        let absolute =
            raw.starts_with('/') || raw.starts_with('\\') || raw.as_bytes().get(1) == Some(&b':');
        if absolute {
            return Err(unsafe_path());
        }
        let enclosed = entry.enclosed_name().ok_or_else(unsafe_path)?;
        let mut components = Vec::new();
        for c in enclosed.components() {
            match c {
                Component::Normal(s) => components.push(s.to_string_lossy().into_owned()),
                Component::CurDir => {}
                _ => return Err(unsafe_path()),
            }
        }
        if entry.is_dir() || components.is_empty() || is_junk(&components) {
            continue;
        }
        if entry.is_symlink() {
            return Err(ApiError::invalid(format!(
                "archive entry {raw:?} is a symbolic link"
            )));
        }
        entries.push((i, components));
    }
    if entries.is_empty() {
        return Err(ApiError::invalid("the archive holds no files"));
    }
    let flat = entries.iter().all(|(_, c)| c.len() == 1);
    if !flat {
        let top = &entries[0].1[0];
        if let Some((_, c)) = entries.iter().find(|(_, c)| c.len() != 2 || &c[0] != top) {
            return Err(ApiError::invalid(format!(
                "archive entry {:?} is out of place: the images and the light table must be at the top of the archive or all inside one folder",
                c.join("/")
            )));
        }
    }
    let mut by_name: HashMap<String, usize> = HashMap::new();
    for (i, components) in &entries {
        let name = components.last().cloned().unwrap_or_default();
        if by_name.insert(name.clone(), *i).is_some() {
            return Err(ApiError::invalid(format!(
                "the archive holds {name:?} more than once"
            )));
        }
    }

    let mut budget = limits.max_unpacked;
    // The images' and the mask's bytes, as stored for the job.
    let mut stored = 0u64;
    let over_budget = || {
        ApiError::too_large(format!(
            "the archive unpacks to more than {} bytes",
            limits.max_unpacked
        ))
    };
    // The table files first: they say which entries are wanted.
    let mut texts: HashMap<&str, Vec<u8>> = HashMap::new();
    let mut tables: Vec<(&str, usize)> = (by_name.iter())
        .filter(|(n, _)| layout::is_table_file(n))
        .map(|(n, &i)| (n.as_str(), i))
        .collect();
    tables.sort();
    for (name, i) in tables {
        let what = format!("the light table file {name:?}");
        let bytes = read_entry(
            &mut zip,
            i,
            (name, &what),
            MAX_LIGHTS_BYTES,
            &mut budget,
            &over_budget,
        )?;
        texts.insert(name, bytes);
    }
    let mut names: Vec<String> = by_name.keys().cloned().collect();
    names.sort();
    let table = layout::read_table("the archive", &names, &mut |n| {
        Ok(texts.get(n).cloned().unwrap_or_default())
    })?;
    let named: std::collections::HashSet<&str> =
        table.lights.iter().map(|l| l.name.as_str()).collect();
    if named.len() > limits.max_images {
        return Err(InputError::TooManyImages {
            count: named.len(),
            limit: limits.max_images,
        }
        .into());
    }
    // A table of directions is stored as JSON in the project's frame; one that gives
    // positions (only light_directions.json can) as it came, rig and all, for the job to
    // read back with `lights::parse_table`.
    let stored_table = if table.lights.iter().any(|l| l.emitter.is_some()) {
        texts.get(layout::SEED_JSON).cloned().unwrap_or_default()
    } else {
        lights::to_json(&table.lights)
    };
    let mask_name = table.mask.as_deref().filter(|_| want_mask);
    let camera = match camera::FILES.iter().find(|n| by_name.contains_key(**n)) {
        Some(name) => {
            let what = format!("{name} in the archive");
            let index = by_name[*name];
            let bytes = read_entry(
                &mut zip,
                index,
                (name, &what),
                MAX_CAMERA_BYTES,
                &mut budget,
                &over_budget,
            )?;
            Some((name.to_string(), parse_camera(&bytes, &what)?))
        }
        None => None,
    };

    // Then the images the table names, and the mask, in archive order.
    let mut images = Vec::new();
    let mut mask = None;
    let mut buf = vec![0u8; 64 * 1024];
    for (i, components) in entries {
        let name = components.last().cloned().unwrap_or_default();
        let is_mask = mask_name == Some(name.as_str());
        if !(named.contains(name.as_str()) || is_mask) {
            continue;
        }
        let mut entry = zip.by_index(i).map_err(|e| zip_error(&name, e))?;
        if entry.size() > budget {
            return Err(over_budget());
        }
        let file = if is_mask {
            MASK_FILE.to_string()
        } else {
            image_file(images.len())
        };
        let target = dir.join(&file);
        let mut out = File::create(&target)?;
        let mut head = Vec::with_capacity(HEAD_BYTES);
        loop {
            let n = match entry.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    return Err(ApiError::invalid(format!(
                        "archive entry {name:?} cannot be read: {e}"
                    )));
                }
            };
            if n as u64 > budget {
                return Err(over_budget());
            }
            budget -= n as u64;
            stored += n as u64;
            if stored > limits.max_input_bytes {
                return Err(too_much_input(&name, limits.max_input_bytes));
            }
            if head.len() < HEAD_BYTES {
                let take = (HEAD_BYTES - head.len()).min(n);
                head.extend_from_slice(&buf[..take]);
            }
            out.write_all(&buf[..n])?;
        }
        out.flush()?;
        drop(out);
        let probed = probe_image(&target, &name, &head, limits.max_pixels);
        if is_mask {
            let (width, height, depth) =
                probed.map_err(|e| ApiError::invalid(format!("mask: {e}")))?;
            mask = Some(StoredImage {
                name,
                file,
                width,
                height,
                depth,
            });
            continue;
        }
        let (width, height, depth) = probed?;
        images.push(StoredImage {
            name,
            file,
            width,
            height,
            depth,
        });
    }
    Ok(Unpacked {
        images,
        table: stored_table,
        mask,
        has_mask: table.mask.is_some(),
        camera,
        notes: table.notes,
    })
}

/// A small entry (a table or camera file: its name, and what it is for a refusal) read
/// whole, within `limit` bytes and the archive's unpacking `budget`.
fn read_entry(
    zip: &mut zip::ZipArchive<BufReader<File>>,
    index: usize,
    (name, what): (&str, &str),
    limit: usize,
    budget: &mut u64,
    over_budget: &dyn Fn() -> ApiError,
) -> Result<Vec<u8>, ApiError> {
    let mut entry = zip.by_index(index).map_err(|e| zip_error(name, e))?;
    if entry.size() > *budget {
        return Err(over_budget());
    }
    let mut bytes = Vec::new();
    (&mut entry)
        .take(limit as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| ApiError::invalid(format!("archive entry {name:?} cannot be read: {e}")))?;
    if bytes.len() > limit {
        return Err(ApiError::too_large(format!(
            "{what} is larger than {limit} bytes"
        )));
    }
    *budget -= bytes.len() as u64;
    Ok(bytes)
}

/// The archive reader on its own, for property tests and fuzzing: unpack the zip file at
/// `zip` into the directory `dir` under `config`'s caps (`max_parts` entries,
/// `max_unpacked_bytes`, `max_images`, `max_pixels`, `max_input_bytes`), exactly as an `archive` part is
/// unpacked. Returns the images' names (in archive order) and the light table's bytes
/// (as stored for the job: JSON in the project's frame).
pub fn unpack_archive(
    zip: &Path,
    dir: &Path,
    config: &Config,
) -> Result<(Vec<String>, Vec<u8>), ApiError> {
    let unpacked = extract_archive(zip, dir, &ArchiveLimits::from(config), true)?;
    let names = unpacked.images.into_iter().map(|i| i.name).collect();
    Ok((names, unpacked.table))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;
    use zip::write::SimpleFileOptions;

    fn png(w: u32, h: u32) -> Vec<u8> {
        let img = image::GrayImage::from_pixel(w, h, image::Luma([128]));
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    }

    fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
        let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
        for (name, data) in entries {
            w.start_file(*name, SimpleFileOptions::default()).unwrap();
            w.write_all(data).unwrap();
        }
        w.finish().unwrap().into_inner()
    }

    fn limits() -> ArchiveLimits {
        ArchiveLimits {
            max_entries: 16,
            max_unpacked: 1 << 20,
            max_images: 8,
            max_pixels: 1 << 20,
            max_input_bytes: 1 << 20,
        }
    }

    fn extract(bytes: &[u8], limits: &ArchiveLimits) -> Result<Vec<String>, ApiError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.zip");
        std::fs::write(&path, bytes).unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        extract_archive(&path, &out, limits, true)
            .map(|u| u.images.into_iter().map(|i| i.name).collect())
    }

    const TABLE: &[u8] = b"a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n";

    #[test]
    fn accepts_flat_and_one_folder_and_skips_junk() {
        let p = png(4, 4);
        let flat = zip_of(&[
            ("a.png", &p),
            ("light_directions.csv", TABLE),
            ("__MACOSX/._a.png", b"x"),
        ]);
        assert_eq!(extract(&flat, &limits()).unwrap(), ["a.png"]);
        let nested = zip_of(&[
            ("set/a.png", &p),
            ("set/b.png", &p),
            ("set/light_directions.csv", TABLE),
            ("set/.DS_Store", b"x"),
            ("set/notes.txt", b"not named: skipped"),
            ("set/other.png", b"not named: skipped"),
        ]);
        assert_eq!(extract(&nested, &limits()).unwrap(), ["a.png", "b.png"]);
    }

    #[test]
    fn an_archive_may_bring_an_lp_table() {
        let p = png(4, 4);
        let lp = b"3\r\n./jpeg-exports/a.png 0 0 1\r\nC:\\rti\\b.png 1 0 1\r\nc.png 0 1 1\r\n";
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.zip");
        let zip = zip_of(&[
            ("set/a.png", &p),
            ("set/b.png", &p),
            ("set/c.png", &p),
            ("set/rti.lp", lp),
        ]);
        std::fs::write(&path, zip).unwrap();
        let u = extract_archive(&path, dir.path(), &limits(), true).unwrap();
        let names: Vec<&str> = u.images.iter().map(|i| i.name.as_str()).collect();
        assert_eq!(names, ["a.png", "b.png", "c.png"]);
        // Stored in the project's frame: y up in the file is −y here.
        let stored = lights::parse_bytes(&u.table).unwrap();
        assert!(
            (stored[2].direction[1] + 0.5f64.sqrt()).abs() < 1e-15,
            "{stored:?}"
        );
        let e = extract(
            &zip_of(&[("a.png", &p), ("x.lp", lp), ("y.lp", lp)]),
            &limits(),
        )
        .unwrap_err();
        assert!(e.detail().contains("2 .lp files"), "{e}");
    }

    #[test]
    fn an_archive_brings_its_camera_file_json_first() {
        let p = png(4, 4);
        let k = b"8 0 1.5\n0 8 1.5\n0 0 1\n";
        let json = br#"{"fx": 9, "fy": 9, "cx": 1.5, "cy": 1.5}"#;
        let camera = |entries: &[(&str, &[u8])]| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("a.zip");
            std::fs::write(&path, zip_of(entries)).unwrap();
            extract_archive(&path, dir.path(), &limits(), true).map(|u| u.camera)
        };
        let base = [("a.png", &p[..]), ("light_directions.csv", TABLE)];
        let (name, k_txt) = camera(&[base[0], base[1], ("K.txt", k)]).unwrap().unwrap();
        assert_eq!((name.as_str(), k_txt.fx, k_txt.cx), ("K.txt", 8.0, 1.5));
        let both = camera(&[base[0], base[1], ("K.txt", k), ("camera.json", json)]);
        assert_eq!(both.unwrap().unwrap().1.fx, 9.0);
        assert!(camera(&base).unwrap().is_none());
        let e = camera(&[base[0], base[1], ("K.txt", b"8 8")]).unwrap_err();
        assert_eq!(e.status().as_u16(), 422);
        assert!(
            e.detail().contains("K.txt in the archive") && e.detail().contains("2 numbers"),
            "{e}"
        );
        let e = camera(&[base[0], base[1], ("K.txt", &[b' '; 5000][..])]).unwrap_err();
        assert_eq!(e.status().as_u16(), 413, "{e}");
    }

    #[test]
    fn refuses_unsafe_layouts_junk_and_bombs() {
        let p = png(4, 4);
        let e = extract(
            &zip_of(&[("../a.png", &p), ("light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert_eq!(e.status().as_u16(), 422);
        assert!(e.detail().contains("unsafe path"), "{e}");
        let e = extract(
            &zip_of(&[("/etc/a.png", &p), ("light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert!(e.detail().contains("unsafe path"), "{e}");
        let e = extract(
            &zip_of(&[("x/a.png", &p), ("y/light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert!(e.detail().contains("out of place"), "{e}");
        let e = extract(
            &zip_of(&[
                ("a.png", b"hello"),
                ("notes.txt", b"hello"),
                ("light_directions.csv", TABLE),
            ]),
            &limits(),
        )
        .unwrap_err();
        assert_eq!(e.status().as_u16(), 415, "{e}");
        assert!(e.detail().contains("a.png"), "{e}");
        let e = extract(&zip_of(&[("a.png", &p)]), &limits()).unwrap_err();
        assert!(e.detail().contains("light_directions.csv"), "{e}");
        // 4 MiB of zeros compresses to a few KiB: the cap stops it while streaming.
        let zeros = vec![0u8; 4 << 20];
        let e = extract(
            &zip_of(&[("a.png", &zeros), ("light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert_eq!(e.status().as_u16(), 413, "{e}");
        let many: Vec<(String, Vec<u8>)> =
            (0..20).map(|i| (format!("{i}.png"), p.clone())).collect();
        let refs: Vec<(&str, &[u8])> = many
            .iter()
            .map(|(n, d)| (n.as_str(), d.as_slice()))
            .collect();
        let e = extract(&zip_of(&refs), &limits()).unwrap_err();
        assert_eq!(e.status().as_u16(), 413, "{e}");
        let e = extract(b"PK\x03\x04 not really a zip", &limits()).unwrap_err();
        assert_eq!(e.status().as_u16(), 422, "{e}");
    }

    #[test]
    fn probe_reads_dimensions_and_refuses_junk() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x");
        let p = png(5, 3);
        std::fs::write(&path, &p).unwrap();
        assert_eq!(
            probe_image(&path, "x.png", &p[..HEAD_BYTES], 100).unwrap(),
            (5, 3, 8)
        );
        let e = probe_image(&path, "x.png", &p[..HEAD_BYTES], 10).unwrap_err();
        assert!(e.is_too_large());
        std::fs::write(&path, b"GIF89a\x01\x00\x01\x00\x00\x00\x00;").unwrap();
        let e =
            probe_image(&path, "x.gif", b"GIF89a\x01\x00\x01\x00\x00\x00\x00;", 100).unwrap_err();
        assert!(e.is_unsupported_media(), "{e}");
        let e = probe_image(&path, "x.txt", b"hello", 100).unwrap_err();
        assert!(e.is_unsupported_media(), "{e}");
    }

    #[test]
    fn options_errors_name_the_field() {
        let e = parse_options(br#"{"solver": "magic"}"#).unwrap_err();
        assert_eq!(e.status().as_u16(), 422);
        assert!(e.detail().contains("magic"), "{e}");
        let e = parse_options(br#"{"outputs": ["albedo.png", "selfie.jpg"]}"#).unwrap_err();
        assert!(e.detail().contains("selfie.jpg"), "{e}");
        let e = parse_options(br#"{"colour": 1}"#).unwrap_err();
        assert!(e.detail().contains("colour"), "{e}");
        assert!(parse_options(br#"{"integration": "path"}"#).is_ok());
        for (bad, needle) in [
            (r#"{"mesh": {"height_scale": 1e39}}"#, "height_scale"),
            (r#"{"mesh": {"pixel_size": 0}}"#, "pixel_size"),
            (r#"{"mesh": {"pixel_size": -1}}"#, "pixel_size"),
            (r#"{"shading_light": [0, 0, 0]}"#, "shading_light"),
            (r#"{"shading_light": [1e300, 1e300, 1]}"#, "shading_light"),
            // Repeated keys are refused, not resolved to the last one (found by fuzzing).
            (
                r#"{"mask": "none", "mask": "given"}"#,
                "duplicate field `mask`",
            ),
            (
                r#"{"mesh": {"step": 2, "step": 3}}"#,
                "duplicate field `step`",
            ),
            (r#"{"camera": "1 2 3"}"#, "field `camera`"),
            (r#"{"camera": [80, 80, 1, 1]}"#, "field `camera`"),
            (
                r#"{"camera": {"fx": 0.5, "fy": 80, "cx": 1, "cy": 1}}"#,
                "field `camera`: fx must be a focal length",
            ),
        ] {
            let e = parse_options(bad.as_bytes()).unwrap_err();
            assert_eq!(e.status().as_u16(), 422, "{bad}");
            assert!(e.detail().contains(needle), "{bad}: {e}");
        }
    }
}
