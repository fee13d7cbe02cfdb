//! A job's form: the multipart body streams to the job's staging directory part by
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

use std::path::{Path, PathBuf};

use axum::extract::Multipart;
use futures_util::future::BoxFuture;

use crate::core::camera::Pinhole;
use crate::core::holdout;
use crate::core::layout;
use crate::core::lights;
use crate::core::normalmap::{Convention, NormalMapError};
use crate::core::normals_in;
use crate::core::options::MaskMode;
use crate::core::{InputError, Options};
use crate::service::config::{Config, MAX_LIGHTS_BYTES, MAX_OPTIONS_BYTES};
use crate::service::error::ApiError;
use crate::service::store::{
    LIGHTS_FILE, MANIFEST_FILE, MASK_FILE, Manifest, NORMALS_FILE, NormalsEntry, image_file,
};
use crate::service::tenancy::idempotency::PartHasher;
use crate::service::worker::Prefetch;

use super::archive::{ArchiveLimits, extract_archive};
use super::checks::{
    MAX_CAMERA_BYTES, StoredImage, check_calibration_names, check_names, check_near_options,
    check_sizes, choose_camera, parse_camera, parse_convention, parse_options, probe,
    probe_normals, take_camera_part,
};
use super::form::PartReader;
use super::tap::BodyTap;
use crate::service::worker::near_rig;

const ARCHIVE_FILE: &str = "archive.zip";
/// Longest `callback_url` accepted (bytes).
const MAX_CALLBACK_BYTES: usize = 2048;
/// Longest `calibration` part accepted (bytes; an id is 36).
const MAX_CALIBRATION_BYTES: usize = 256;
/// Longest `convention` part accepted (bytes; `benchmark` is 9).
const MAX_CONVENTION_BYTES: usize = 64;

/// The light table of a job's `calibration` part (the id as sent), as the caller may see
/// it; a 422 naming the id when there is none.
pub type CalibrationTables<'a> =
    &'a (dyn Fn(String) -> BoxFuture<'static, Result<Vec<u8>, ApiError>> + Send + Sync);

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
    let mut form = PartReader::new(multipart, config, tap, hash, dir, PART_NAMES);
    while let Some(mut part) = form.next().await? {
        let name = part.name().to_string();
        if parts.normals.is_some() && IMAGE_JOB_PARTS.contains(&name.as_str()) {
            return Err(normals_with(&name));
        }
        match name.as_str() {
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
                let name = part.image_name()?;
                let file = image_file(parts.images.len());
                let (head, written) = part.store(&file, Some(&name)).await?;
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
                part.once(&parts.lights)?;
                parts.lights_file = part.file_name().map(str::to_string);
                parts.lights = Some(part.bytes(MAX_LIGHTS_BYTES).await?);
            }
            "mask" => {
                part.once(&parts.mask)?;
                let name = part.file_name_or_part();
                let (head, _) = part.store(MASK_FILE, Some(&name)).await?;
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
                part.once(&parts.options)?;
                let bytes = part.bytes(MAX_OPTIONS_BYTES).await?;
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
                part.once(&parts.callback_url)?;
                let url = part.text(MAX_CALLBACK_BYTES).await?;
                parts.callback_url = Some(url.trim().to_string());
            }
            "calibration" => {
                if parts.archive.is_some() {
                    return Err(calibration_with_archive());
                }
                part.once(&parts.calibration)?;
                let id = part.text(MAX_CALIBRATION_BYTES).await?;
                parts.calibration = Some(id.trim().to_string());
            }
            "camera" => {
                part.once(&parts.camera)?;
                let bytes = part.bytes(MAX_CAMERA_BYTES).await?;
                parts.camera = Some(parse_camera(&bytes, "the camera part")?);
            }
            "archive" => {
                part.once(&parts.archive)?;
                if !parts.images.is_empty() || parts.lights.is_some() {
                    return Err(both_forms());
                }
                if parts.calibration.is_some() {
                    return Err(calibration_with_archive());
                }
                // Not input bytes: it is removed once unpacked, and what it unpacks to is
                // counted as image parts are.
                let (head, _) = part.store(ARCHIVE_FILE, None).await?;
                if !(head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06")) {
                    return Err(ApiError::unsupported_media(
                        "the archive part is not a zip file (expected a .zip of a folder with the images and light_directions.csv, or in the benchmark layout with light_directions.txt and filenames.txt)",
                    ));
                }
                parts.archive = Some(part.path(ARCHIVE_FILE));
            }
            "normals" => {
                part.once(&parts.normals)?;
                if let Some(other) = parts.image_job_part() {
                    return Err(normals_with(other));
                }
                let name = part.file_name_or_part();
                let (head, _) = part.store(NORMALS_FILE, Some(&name)).await?;
                let target = part.path(NORMALS_FILE);
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
                part.once(&parts.convention)?;
                let bytes = part.bytes(MAX_CONVENTION_BYTES).await?;
                parts.convention = Some(parse_convention(&bytes)?);
            }
            _ => return Err(part.unknown()),
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
        if options.holdout_lights {
            holdout::check_count(lights.len())?;
        }
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

fn both_forms() -> ApiError {
    ApiError::bad_request("send either an archive part or images and lights parts, not both")
}
