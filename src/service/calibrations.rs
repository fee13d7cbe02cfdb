//! Light calibrations as a resource: `POST /v1/calibrations` takes one chrome-sphere image
//! per light, runs the core's calibration within the request (on the blocking pool, at
//! most `workers` at once) and answers 201 with the result. The calibration keeps its
//! light table, per-light quality and pictures until it is deleted; a job names it in a
//! `calibration` part instead of sending a light table (see `upload`).
//!
//! The upload streams to `calibrations/{id}/files.partial/` (images as `000.img`, …, never
//! the caller's names), which is replaced by the calibration's files and committed before
//! the record is written; ownership follows the jobs' rule (`routes::owned_calibration`).

use std::collections::BTreeMap;
use std::path::Path;

use axum::Json;
use axum::extract::{FromRequestParts, Multipart, Path as UrlPath, Request, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use uuid::Uuid;

use crate::core::InputError;
use crate::core::calibrate::{
    self, Budget, CalibratedLight, Calibration, Camera, Circle, CircleSource, Highlight,
    ImageFiles, Settings, Source,
};
use crate::core::intake::{Limits, NamedFile};
use crate::core::lights;

use super::config::{Config, MAX_LIGHTS_BYTES};
use super::download::{self, not_modified, not_modified_response};
use super::error::ApiError;
use super::idempotency::{self, PartHasher};
use super::problem::Problem;
use super::repo::{ArtifactInfo, CalibrationRecord, Remembered, RepoError, readable};
use super::routes::{
    ApiQuery, IMMUTABLE, ListQuery, PageQuery, Submission, open_submission, owned_calibration,
    request_id,
};
use super::state::AppState;
use super::store::Served;
use super::tenants::Caller;
use super::upload::{self, BodyTap};
use super::util::{format_duration, now_ms, rfc3339, strong_etag};

/// The `Idempotency-Key` scope of `POST /v1/calibrations`.
const SCOPE: &str = "calibrations";
/// Longest `circle`, `ball_diameter`, `focal_length` or `skip_bad` part accepted (bytes).
const MAX_VALUE_BYTES: usize = 256;
/// Most `circle` parts (balls in the frame): every ball is a window of every image read,
/// so the count is bounded like the images are.
pub const MAX_CIRCLES: usize = 16;

/// The files a calibration keeps, and their content types (`positions.csv` only with
/// several balls).
pub const FILES: [(&str, &str); 4] = [
    ("lights.csv", "text/csv; charset=utf-8"),
    ("overlay.png", "image/png"),
    ("lights.png", "image/png"),
    ("positions.csv", "text/csv; charset=utf-8"),
];

/// A calibration: the circle used, the lights with their quality figures, the images left
/// out, and links to its files.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationView {
    /// The calibration's id (a random UUID); a job's `calibration` part names it.
    pub id: Uuid,
    /// The tenant that created it.
    #[schema(example = "alice")]
    pub tenant: String,
    /// RFC 3339.
    #[schema(example = "2025-11-25T19:34:00.123Z")]
    pub created_at: String,
    #[serde(flatten)]
    pub measured: Measured,
    /// File name → download URL: `lights.csv` (the light table), `overlay.png` (circles
    /// and numbered highlights over the maximum image), `lights.png` (the directions on
    /// the unit hemisphere) and, with several balls, `positions.csv` (the lights'
    /// positions).
    #[schema(example = json!({"lights.csv": "/v1/calibrations/0b6f2a43-3c1e-4c51-9d1e-6c9f3a7d2e10/lights.csv"}))]
    pub files: BTreeMap<String, String>,
    /// This resource's URL.
    pub url: String,
}

/// What a calibration measured (stored as the record's detail).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Measured {
    /// The sphere images' size, pixels.
    pub width: u32,
    pub height: u32,
    /// Sphere images sent (lights found plus images skipped).
    pub image_count: u32,
    /// The pinhole camera's focal length in pixels; null for an orthographic camera.
    pub focal_length: Option<f64>,
    /// The (first) ball's circle: the lights' `direction` and `highlight` are on it.
    pub circle: CircleView,
    /// With several balls (`circle` given more than once, or found when no circle is
    /// given): the other balls' circles, in the order given or, when found, left to right
    /// (the first ball, `circle`, is then the leftmost); empty with one ball.
    #[serde(default)]
    pub more_circles: Vec<CircleView>,
    /// The `ball_diameter` part, when given.
    #[serde(default)]
    pub ball_diameter: Option<f64>,
    /// With several balls, the unit of the lights' `position`: `ball_radii`, or
    /// `ball_diameter` (the unit `ball_diameter` was given in); null with one ball.
    #[serde(default)]
    #[schema(example = "ball_radii")]
    pub position_unit: Option<String>,
    /// With several balls, the origin of the lights' `position` (x = column right, y =
    /// row down, z towards the camera): `first_ball` (its centre; orthographic) or
    /// `camera` (with `focal_length`); null with one ball.
    #[serde(default)]
    #[schema(example = "first_ball")]
    pub position_origin: Option<String>,
    /// One per sphere image with a usable highlight, in upload order.
    pub lights: Vec<LightView>,
    /// Images left out (`skip_bad`), and why.
    pub skipped: Vec<SkippedView>,
}

/// The sphere's circle in pixels (0-based, pixel centres at integers).
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct CircleView {
    pub cx: f64,
    pub cy: f64,
    pub r: f64,
    /// `fitted` (to the images' outline), `given` (a `circle` part) or `mask`.
    #[schema(example = "fitted")]
    pub source: String,
    /// For a fitted circle: the fraction of the outline the fit found, and the RMS
    /// distance of its edge points from the circle (pixels).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms: Option<f64>,
}

/// One calibrated light.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct LightView {
    /// The light table's name for it (what the object image must be called).
    #[schema(example = "im1.png")]
    pub name: String,
    /// Its sphere image's file name, and its number (1-based, upload order) in
    /// `overlay.png` and `lights.png`.
    pub image: String,
    pub number: u32,
    /// Unit direction towards the light: x = column right, y = row down, z towards the
    /// camera.
    pub direction: [f64; 3],
    /// Relative intensity (mean 1) from the matte sphere, when `matte` images were sent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intensity: Option<f64>,
    /// Degrees above the image plane, and around it from the x axis (towards y).
    pub elevation_deg: f64,
    pub azimuth_deg: f64,
    pub highlight: HighlightView,
    /// With several balls: its highlight on each of the other balls, in the order of
    /// `more_circles`; empty with one ball.
    #[serde(default)]
    pub more_highlights: Vec<MoreHighlightView>,
    /// With several balls: where the balls' rays towards the light meet, in
    /// `position_unit` from `position_origin`; null with one ball, or when the rays are
    /// (near) parallel (a light far away).
    #[serde(default)]
    pub position: Option<PositionView>,
}

/// A light's highlight on another ball, and the direction it gives from there.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct MoreHighlightView {
    /// Unit direction towards the light from that ball's highlight (as `direction`).
    pub direction: [f64; 3],
    pub highlight: HighlightView,
}

/// A light's position from several balls.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PositionView {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    /// RMS distance of the position from the balls' rays, in `position_unit`: large
    /// against the distance means the highlights disagree.
    pub residual: f64,
    /// Largest angle between two of the rays, degrees: near 0 the distance is poorly
    /// known.
    pub spread_deg: f64,
}

/// The highlight the direction comes from, and how trustworthy it looks.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct HighlightView {
    /// Brightness-weighted centre, pixels (0-based, pixel centres at integers).
    pub x: f64,
    pub y: f64,
    /// Pixels in the blob.
    pub pixels: u64,
    /// Brightest value (fraction of full scale) and whether it is clipped.
    pub peak: f64,
    pub clipped: bool,
    /// Distance of the centre from the sphere's outline, pixels.
    pub rim_distance: f64,
    /// Ratio of the blob's principal axes in direction space (1 = round).
    pub elongation: f64,
    /// The blob's equivalent angular radius, degrees.
    pub radius_deg: f64,
    /// How sure the finder is that this is the light's own highlight, 0..1: it beats
    /// any other candidate clearly, the environment explains little of it, and it has a
    /// few pixels at least. Absent in calibrations stored before it was measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<f64>,
}

/// A sphere image left out.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct SkippedView {
    pub image: String,
    pub reason: String,
}

/// A page of calibrations, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationList {
    pub calibrations: Vec<CalibrationView>,
    /// Pass as `cursor` to get the next page; null on the last page.
    pub next_cursor: Option<String>,
}

/// The `POST /v1/calibrations` form.
#[derive(ToSchema)]
#[allow(dead_code)] // documents the multipart body; the handler streams it
pub struct CalibrationUpload {
    /// One chrome-sphere image per light, in light order (repeat the part; each needs a
    /// file name, which the errors and the overlay use).
    #[schema(value_type = Vec<super::routes::ImageFile>)]
    images: Vec<Vec<u8>>,
    /// The light table's names, one per line, one per image in the same order (what the
    /// object images will be called); without it each light is named by its image.
    #[schema(value_type = String, required = false)]
    names: Option<String>,
    /// The sphere's circle `cx,cy,r` in pixels (0-based, pixel centres at integers),
    /// instead of fitting its outline. Repeat the part once per ball when the frame holds
    /// several (at most 16, of one size, the first one first): each ball is calibrated
    /// (the light table holds the first ball's directions) and each light is placed where
    /// the balls' rays meet (`position`, `positions.csv`). Without it every ball in the
    /// frame is found, the first being the leftmost.
    #[schema(value_type = Vec<String>, required = false, example = json!(["120.4,119.6,70.3", "359.7,120.3,69.6"]))]
    circle: Option<Vec<String>>,
    /// With two balls or more (two `circle` parts or more, or none and the balls found):
    /// the balls' diameter, in the unit the positions should be in (a positive number);
    /// without it, positions are in ball radii. Refused with one `circle` part or a
    /// `mask`, or when only one ball is found.
    #[schema(value_type = String, required = false, example = "25.4")]
    ball_diameter: Option<String>,
    /// A mask of the sphere (non-zero = sphere), the images' size, instead of fitting its
    /// outline.
    #[schema(value_type = super::routes::ImageFile, required = false)]
    mask: Option<Vec<u8>>,
    /// Images of a matte white sphere under the same lights, same order: fits each
    /// light's relative intensity.
    #[schema(value_type = Vec<super::routes::ImageFile>, required = false)]
    matte: Option<Vec<Vec<u8>>>,
    /// A pinhole camera's focal length in pixels (principal point at the image centre);
    /// orthographic without it.
    #[schema(value_type = String, required = false, example = "2400")]
    focal_length: Option<String>,
    /// `true`: leave out images without a usable highlight (listed in `skipped`) instead
    /// of refusing the upload.
    #[schema(value_type = String, required = false, example = "true")]
    skip_bad: Option<String>,
    /// The ball with the rig's lights off (room lights on as in the other images): what
    /// it shows is environment, never a light.
    #[schema(value_type = super::routes::ImageFile, required = false)]
    ambient: Option<Vec<u8>>,
}

/// The `{id}` of a calibration URL; anything that is not a UUID names none (404).
pub struct CalibrationId(pub Uuid);

impl<S: Send + Sync> FromRequestParts<S> for CalibrationId {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let UrlPath(params) = UrlPath::<BTreeMap<String, String>>::from_request_parts(parts, state)
            .await
            .map_err(|e| ApiError::bad_request(e.body_text()))?;
        let raw = params.get("id").cloned().unwrap_or_default();
        Uuid::parse_str(&raw)
            .map(CalibrationId)
            .map_err(|_| ApiError::not_found(format!("there is no calibration {raw:?}")))
    }
}

fn calibration_url(id: Uuid) -> String {
    format!("/v1/calibrations/{id}")
}

impl CalibrationView {
    pub fn from_record(r: CalibrationRecord) -> Result<Self, ApiError> {
        let url = calibration_url(r.id);
        let measured: Measured = serde_json::from_value(r.detail)
            .map_err(|e| ApiError::internal(format!("stored calibration {}: {e}", r.id)))?;
        Ok(Self {
            id: r.id,
            tenant: r.tenant,
            created_at: rfc3339(r.created_at),
            measured,
            files: r
                .artifacts
                .iter()
                .map(|a| (a.name.clone(), format!("{url}/{}", a.name)))
                .collect(),
            url,
        })
    }
}

/// Calibrate the lights from a chrome sphere.
///
/// One image of a mirror ball per light; the sphere's outline is fitted to the images
/// unless a `circle` or `mask` is given. With several balls in the frame (a `circle` part
/// per ball, or none and the balls found), each light is also placed where the balls'
/// rays meet. The calibration
/// runs within the request and the answer is 201 with the result: at most `--workers` are
/// computed at once (one tenant at most `--tenant-max-calibrations`), each within the
/// memory budget; the others wait. Give its id as a job's `calibration` part to
/// reconstruct with its lights.
#[utoipa::path(
    post,
    path = "/v1/calibrations",
    tag = "calibrations",
    request_body(content = inline(CalibrationUpload), content_type = "multipart/form-data"),
    params(
        ("Idempotency-Key" = Option<String>, Header, description = "1 to 255 visible ASCII characters. The same key and the same parts from the same tenant within 24 hours get the first answer again instead of a new calibration; the same key with different parts is 422."),
    ),
    responses(
        (status = 201, description = "Calibrated (or, for a repeated Idempotency-Key, the first request's answer)", body = CalibrationView,
            headers(("Location" = String, description = "The calibration's URL"))),
        (status = 400, description = "Not multipart, or parts missing, repeated or unknown", body = Problem, content_type = "application/problem+json"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 408, description = "The upload took longer than the upload time limit", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Body, image, part count, image count or the stored input bytes over a limit", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "An image in an unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "No sphere found, an image without a usable highlight, a circle outside the image or not cx,cy,r, more than 16 circles, a ball_diameter that is not a positive number, with one circle or a mask, or with one ball found, images of different sizes, fewer than 3 images, names or matte images not one per image; an Idempotency-Key already used for a different request. The detail names the image", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "The tenant's submissions per minute (shared with jobs) are used up; retry after Retry-After seconds", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = u64, description = "Seconds to wait"))),
        (status = 503, description = "The most uploads at once are under way, or the tenant's share of them, or the service is stopping", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = u64, description = "Seconds to wait"))),
        (status = 507, description = "Not enough free disk space", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn create_calibration(
    State(state): State<AppState>,
    caller: Caller,
    request: Request,
) -> Result<Response, ApiError> {
    let (parts, body) = request.into_parts();
    let tap = BodyTap::new(body, state.config().max_body_bytes);
    let answer = accept(&state, &caller, parts, &tap).await;
    if answer.is_err() {
        tokio::spawn(async move { tap.drain(upload::LINGER).await });
    }
    answer
}

async fn accept(
    state: &AppState,
    caller: &Caller,
    parts: Parts,
    tap: &BodyTap,
) -> Result<Response, ApiError> {
    let config = state.config();
    let Submission {
        request_id,
        idempotency_key,
        mut multipart,
        earlier,
        since,
        _receiving,
    } = open_submission(state, caller, parts, tap, SCOPE).await?;
    if earlier.is_none() {
        state.admit_submission(&caller.tenant)?;
    }

    let id = Uuid::new_v4();
    let staging = state.stage_calibration(id).await?;
    let mut hash = PartHasher::new(idempotency_key.is_some());
    let form = tokio::time::timeout(
        config.upload_timeout,
        receive(config, staging.path(), &mut multipart, tap, &mut hash),
    )
    .await
    .map_err(|_| {
        ApiError::upload_timeout(format!(
            "the upload did not complete within {}",
            format_duration(config.upload_timeout)
        ))
    })??;
    let body_hash = hash.finish().unwrap_or_default();
    if let Some(earlier) = &earlier {
        return idempotency::replay(earlier, &body_hash);
    }

    // The slot, the memory and the uploaded files move into the blocking task: a client
    // that goes away frees none of them while the work goes on (its files are removed
    // when the work ends).
    let computing = state.calibration_slot(&caller.tenant).await;
    let limits = config.limits();
    let (mut staging, made) = tokio::task::spawn_blocking(move || {
        let made = computing.run(|| compute(staging.path(), form, &limits));
        (staging, made)
    })
    .await?;
    let made = made?;
    staging.commit().await?;

    let record = CalibrationRecord {
        id,
        tenant: caller.tenant.clone(),
        created_at: now_ms(),
        detail: serde_json::to_value(&made.measured)
            .map_err(|e| ApiError::internal(format!("calibration detail: {e}")))?,
        table: made.table,
        artifacts: made.files,
    };
    // Read back through the code that serves it before it is stored: a record that could
    // not be listed or used by a job is never committed.
    let view = CalibrationView::from_record(record.clone())?;
    lights::parse(&record.table)
        .map_err(|e| ApiError::internal(format!("calibration light table: {e}")))?;
    let stored = record.clone();
    state.repo(move |r| r.insert_calibration(&stored)).await?;
    staging.keep();
    let answer = Remembered {
        body_hash,
        status: StatusCode::CREATED.as_u16(),
        body: serde_json::to_string(&view)
            .map_err(|e| ApiError::internal(format!("calibration view: {e}")))?,
        location: Some(view.url.clone()),
        created_at: record.created_at,
    };
    if let Some(key) = idempotency_key {
        let (tenant, remembered) = (caller.tenant.clone(), answer.clone());
        let raced = state
            .repo(move |r| r.remember(&tenant, SCOPE, &key, &remembered, since))
            .await?;
        // A concurrent request with the same key got there first: this calibration never was.
        if let Some(first) = raced {
            state.repo(move |r| r.delete_calibration(id)).await?;
            remove_files(state, id).await;
            return idempotency::replay(&first, &answer.body_hash);
        }
    }
    tracing::info!(
        target: "audit",
        action = "create",
        tenant = %caller.tenant,
        calibration = %id,
        request_id = %request_id,
        lights = view.measured.lights.len(),
        "calibration created"
    );
    Ok(idempotency::answer(&answer))
}

async fn remove_files(state: &AppState, id: Uuid) {
    let store = state.inner.store.clone();
    match tokio::task::spawn_blocking(move || store.remove_calibration(id)).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => {
            tracing::warn!(calibration = %id, error = %e, "cannot remove calibration files")
        }
        Err(e) => tracing::warn!(calibration = %id, error = %e, "cannot remove calibration files"),
    }
}

/// A stored upload image: the caller's file name, the stored file, its size.
struct Stored {
    name: String,
    file: String,
    width: u32,
    height: u32,
}

/// A received calibration form, its images on disk.
#[derive(Default)]
struct Form {
    images: Vec<Stored>,
    matte: Vec<Stored>,
    mask: Option<Stored>,
    ambient: Option<Stored>,
    /// One per ball, the first one first.
    circles: Vec<Circle>,
    ball_diameter: Option<f64>,
    names: Option<Vec<String>>,
    focal_length: Option<f64>,
    skip_bad: Option<bool>,
}

const PARTS: &str =
    "images, names, circle, ball_diameter, mask, ambient, matte, focal_length or skip_bad";

/// Read the multipart body into `dir`, checking what is cheap: the parts, each image's
/// format and dimensions (from its header) against the limits and the first image.
async fn receive(
    config: &Config,
    dir: &Path,
    multipart: &mut Multipart,
    tap: &BodyTap,
    hash: &mut PartHasher,
) -> Result<Form, ApiError> {
    let mut form = Form::default();
    let mut count = 0;
    // Image and mask bytes stored so far (413 past `max_input_bytes`, as for jobs).
    let mut stored = 0u64;
    while let Some(mut field) = multipart
        .next_field()
        .await
        .map_err(|e| upload::multipart_error(e, tap, config))?
    {
        count += 1;
        if count > config.max_parts {
            return Err(ApiError::too_large(format!(
                "the upload has more than {} parts",
                config.max_parts
            )));
        }
        let part = field.name().unwrap_or_default().to_string();
        hash.part(&part, field.file_name());
        match part.as_str() {
            "images" | "matte" => {
                let list = if part == "images" {
                    &form.images
                } else {
                    &form.matte
                };
                if list.len() >= config.max_images {
                    return Err(InputError::TooManyImages {
                        count: list.len() + 1,
                        limit: config.max_images,
                    }
                    .into());
                }
                let name = upload::file_name(&field, &part)?;
                let file = format!("{part}{:03}.img", list.len());
                let into = Some((&mut stored, name.as_str()));
                let (head, _) =
                    upload::stream_to_file(&mut field, &dir.join(&file), tap, config, hash, into)
                        .await?;
                let (width, height, _) =
                    upload::probe(dir.join(&file), name.clone(), head, config).await?;
                let stored = Stored {
                    name,
                    file,
                    width,
                    height,
                };
                if part == "images" {
                    check_size(form.images.first(), &stored)?;
                    form.images.push(stored);
                } else {
                    form.matte.push(stored);
                }
            }
            "mask" | "ambient" => {
                let slot = if part == "mask" {
                    &mut form.mask
                } else {
                    &mut form.ambient
                };
                upload::once(slot, &part)?;
                let name = field
                    .file_name()
                    .filter(|n| !n.is_empty())
                    .unwrap_or(&part)
                    .to_string();
                let file = format!("{part}.img");
                let into = Some((&mut stored, name.as_str()));
                let (head, _) =
                    upload::stream_to_file(&mut field, &dir.join(&file), tap, config, hash, into)
                        .await?;
                let (width, height, _) =
                    upload::probe(dir.join(&file), name.clone(), head, config).await?;
                *slot = Some(Stored {
                    name,
                    file,
                    width,
                    height,
                });
            }
            "names" => {
                upload::once(&form.names, "names")?;
                let text =
                    text_part(&mut field, MAX_LIGHTS_BYTES, "names", tap, config, hash).await?;
                form.names = Some(parse_names(&text)?);
            }
            "circle" => {
                if form.circles.len() >= MAX_CIRCLES {
                    return Err(ApiError::invalid(format!(
                        "circle: at most {MAX_CIRCLES} circle parts (one per ball) are accepted"
                    )));
                }
                let text =
                    text_part(&mut field, MAX_VALUE_BYTES, "circle", tap, config, hash).await?;
                form.circles.push(parse_circle(&text)?);
            }
            "ball_diameter" => {
                upload::once(&form.ball_diameter, "ball_diameter")?;
                let text = text_part(
                    &mut field,
                    MAX_VALUE_BYTES,
                    "ball_diameter",
                    tap,
                    config,
                    hash,
                )
                .await?;
                form.ball_diameter = Some(parse_ball_diameter(&text)?);
            }
            "focal_length" => {
                upload::once(&form.focal_length, "focal_length")?;
                let text = text_part(
                    &mut field,
                    MAX_VALUE_BYTES,
                    "focal_length",
                    tap,
                    config,
                    hash,
                )
                .await?;
                form.focal_length = Some(parse_focal_length(&text)?);
            }
            "skip_bad" => {
                upload::once(&form.skip_bad, "skip_bad")?;
                let text =
                    text_part(&mut field, MAX_VALUE_BYTES, "skip_bad", tap, config, hash).await?;
                form.skip_bad = Some(parse_flag(&text)?);
            }
            "" => {
                return Err(ApiError::bad_request(format!(
                    "a multipart part has no name; expected {PARTS}"
                )));
            }
            other => {
                return Err(ApiError::bad_request(format!(
                    "unknown part {other:?}; expected {PARTS}"
                )));
            }
        }
    }
    if form.images.is_empty() {
        return Err(ApiError::bad_request(
            "no images parts: send each chrome-sphere image as a file part named images (curl -F images=@ball01.png)",
        ));
    }
    if !form.circles.is_empty() && form.mask.is_some() {
        return Err(ApiError::invalid(
            "give the sphere either as a circle or as a mask, not both",
        ));
    }
    // As the CLI's --positions: positions need the rays of two balls at least, given or
    // found (then checked once the calibration has found them).
    if form.ball_diameter.is_some() && (form.circles.len() == 1 || form.mask.is_some()) {
        return Err(ApiError::invalid(
            "ball_diameter needs two balls or more in the frame: send a circle part cx,cy,r for each, or none to have them found",
        ));
    }
    Ok(form)
}

/// Images of a calibration have one size (the core checks it too, after decoding: this
/// answers before the rest of the body is read).
fn check_size(first: Option<&Stored>, img: &Stored) -> Result<(), ApiError> {
    match first {
        Some(f) if (f.width, f.height) != (img.width, img.height) => {
            Err(InputError::SizeMismatch {
                name: img.name.clone(),
                width: img.width,
                height: img.height,
                first: f.name.clone(),
                expected_width: f.width,
                expected_height: f.height,
            }
            .into())
        }
        _ => Ok(()),
    }
}

async fn text_part(
    field: &mut axum::extract::multipart::Field<'_>,
    limit: usize,
    part: &str,
    tap: &BodyTap,
    config: &Config,
    hash: &mut PartHasher,
) -> Result<String, ApiError> {
    let bytes = upload::read_small(field, limit, part, tap, config, hash).await?;
    String::from_utf8(bytes).map_err(|_| ApiError::invalid(format!("{part}: not UTF-8 text")))
}

/// One light name per line (blank lines skipped), each one a light table can hold.
fn parse_names(text: &str) -> Result<Vec<String>, ApiError> {
    text.lines()
        .map(str::trim)
        .enumerate()
        .filter(|(_, l)| !l.is_empty())
        .map(|(i, l)| {
            lights::check_name(l)
                .map(|()| l.to_string())
                .map_err(|why| ApiError::invalid(format!("names, line {}: {why}", i + 1)))
        })
        .collect()
}

/// `cx,cy,r`: three finite numbers, pixels.
fn parse_circle(text: &str) -> Result<Circle, ApiError> {
    let bad = || {
        ApiError::invalid(format!(
            "circle: expected cx,cy,r (three finite numbers, pixels), got {:?}",
            text.trim()
        ))
    };
    let v: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad())?;
    match v[..] {
        [cx, cy, r] if v.iter().all(|x| x.is_finite()) => Ok(Circle { cx, cy, r }),
        _ => Err(bad()),
    }
}

/// The balls' diameter: a positive finite number, in the unit the positions should be in.
fn parse_ball_diameter(text: &str) -> Result<f64, ApiError> {
    match text.trim().parse::<f64>() {
        Ok(d) if d.is_finite() && d > 0.0 => Ok(d),
        _ => Err(ApiError::invalid(format!(
            "ball_diameter must be a positive number (the balls' diameter, in the unit the positions should be in), got {:?}",
            text.trim()
        ))),
    }
}

fn parse_focal_length(text: &str) -> Result<f64, ApiError> {
    match text.trim().parse::<f64>() {
        Ok(f) if calibrate::FOCAL_PX.contains(&f) => Ok(f),
        _ => Err(ApiError::invalid(format!(
            "focal_length must be a number of pixels from {} to {:e} (leave it out for a long lens far away), got {:?}",
            calibrate::FOCAL_PX.start(),
            calibrate::FOCAL_PX.end(),
            text.trim()
        ))),
    }
}

fn parse_flag(text: &str) -> Result<bool, ApiError> {
    match text.trim() {
        "true" | "1" | "yes" => Ok(true),
        "false" | "0" | "no" => Ok(false),
        other => Err(ApiError::invalid(format!(
            "skip_bad must be true or false, got {other:?}"
        ))),
    }
}

/// What [`compute`] made: the measured detail, the light table and the stored files.
struct Made {
    measured: Measured,
    table: String,
    files: Vec<ArtifactInfo>,
}

/// Calibrate from the stored images (read from their files a few at a time, within
/// `calibrate::peak_bytes(max_pixels)`, spilling to `dir` when needed), and replace the
/// uploads in `dir` with the calibration's files. Blocking.
fn compute(dir: &Path, form: Form, limits: &Limits) -> Result<Made, ApiError> {
    let files = |images: &[Stored]| {
        ImageFiles::new(
            images
                .iter()
                .map(|s| NamedFile {
                    name: s.name.clone(),
                    path: dir.join(&s.file),
                })
                .collect(),
            *limits,
        )
    };
    let images = files(&form.images);
    let (circle, source) = match (&form.circles[..], &form.mask) {
        ([c], _) => (CircleSource::Given(*c), "given"),
        ([_, _, ..], _) => (CircleSource::Balls(form.circles.clone()), "given"),
        ([], Some(m)) => {
            let mask = files(std::slice::from_ref(m)).decode_all()?.remove(0);
            (
                CircleSource::Mask {
                    name: mask.name,
                    mask: mask.plane.mapv(|v| v > 0),
                },
                "mask",
            )
        }
        ([], None) => (CircleSource::Fit, "fitted"),
    };
    let (w, h) = (
        form.images[0].width as usize,
        form.images[0].height as usize,
    );
    let camera = match form.focal_length {
        Some(f) => Camera::Perspective {
            focal_px: f,
            principal: [(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0],
        },
        None => Camera::Orthographic,
    };
    let settings = Settings {
        circle,
        camera,
        skip_bad: form.skip_bad.unwrap_or(false),
        budget: Budget::default(),
        scratch: Some(dir.to_path_buf()),
    };
    let ambient = form
        .ambient
        .as_ref()
        .map(|a| files(std::slice::from_ref(a)));
    let mut cal = calibrate::calibrate(
        &images,
        form.names.as_deref(),
        ambient.as_ref().map(|a| a as &dyn Source),
        &settings,
    )?;
    if form.ball_diameter.is_some() && cal.more_circles.is_empty() {
        let c = cal.circle;
        return Err(ApiError::invalid(format!(
            "ball_diameter needs two balls or more in the frame, but one ball was found (centre ({:.1}, {:.1}), radius {:.1} px): send a circle part cx,cy,r for each ball",
            c.cx, c.cy, c.r
        )));
    }
    if !form.matte.is_empty() {
        cal.fit_intensities(&files(&form.matte), &settings)?;
    }
    let uploads = (form.images.iter())
        .chain(&form.matte)
        .chain(&form.mask)
        .chain(&form.ambient);
    for s in uploads {
        std::fs::remove_file(dir.join(&s.file))?;
    }
    let table = cal.table();
    let positions = cal.positions_table(form.ball_diameter);
    let mut files = Vec::new();
    let made = [
        ("lights.csv", table.clone().into_bytes()),
        ("overlay.png", cal.overlay_png()),
        ("lights.png", cal.lights_png()),
    ];
    let with_positions = positions.map(|p| ("positions.csv", p.into_bytes()));
    for (name, bytes) in made.into_iter().chain(with_positions) {
        std::fs::write(dir.join(name), &bytes)?;
        files.push(ArtifactInfo {
            name: name.to_string(),
            bytes: bytes.len() as u64,
            etag: strong_etag(crc32fast::hash(&bytes), bytes.len() as u64),
            key: None,
        });
    }
    let measured = measured(&cal, &form, w, h, source);
    Ok(Made {
        measured,
        table,
        files,
    })
}

fn measured(cal: &Calibration, form: &Form, w: usize, h: usize, source: &str) -> Measured {
    let c = cal.circle;
    let several = !cal.more_circles.is_empty();
    // Positions are computed in ball radii; a diameter in some unit scales them to it.
    let scale = form.ball_diameter.map_or(1.0, |d| d / 2.0);
    Measured {
        width: w as u32,
        height: h as u32,
        image_count: form.images.len() as u32,
        focal_length: form.focal_length,
        circle: CircleView {
            cx: c.cx,
            cy: c.cy,
            r: c.r,
            source: source.to_string(),
            coverage: cal.outline.as_ref().map(|o| o.coverage),
            rms: cal.outline.as_ref().map(|o| o.rms),
        },
        more_circles: cal
            .more_circles
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let fit = cal.more_outlines.get(k);
                CircleView {
                    cx: c.cx,
                    cy: c.cy,
                    r: c.r,
                    source: source.to_string(),
                    coverage: fit.map(|o| o.coverage),
                    rms: fit.map(|o| o.rms),
                }
            })
            .collect(),
        ball_diameter: form.ball_diameter,
        position_unit: several.then(|| {
            match form.ball_diameter {
                Some(_) => "ball_diameter",
                None => "ball_radii",
            }
            .to_string()
        }),
        position_origin: several.then(|| {
            match cal.camera_is_pinhole {
                true => "camera",
                false => "first_ball",
            }
            .to_string()
        }),
        lights: cal.lights.iter().map(|l| light_view(l, scale)).collect(),
        skipped: cal
            .skipped
            .iter()
            .map(|s| SkippedView {
                image: s.image.clone(),
                reason: s.reason.clone(),
            })
            .collect(),
    }
}

/// A light as the resource shows it, its position (if any) multiplied by `scale`.
fn light_view(l: &CalibratedLight, scale: f64) -> LightView {
    let d = l.highlight.direction;
    LightView {
        name: l.name.clone(),
        image: l.image.clone(),
        number: l.index as u32 + 1,
        direction: d,
        intensity: l.intensity,
        elevation_deg: d[2].clamp(-1.0, 1.0).asin().to_degrees(),
        azimuth_deg: d[1].atan2(d[0]).to_degrees(),
        highlight: highlight_view(&l.highlight),
        more_highlights: l
            .more
            .iter()
            .map(|hl| MoreHighlightView {
                direction: hl.direction,
                highlight: highlight_view(hl),
            })
            .collect(),
        position: l.position.map(|p| PositionView {
            x: scale * p.position[0],
            y: scale * p.position[1],
            z: scale * p.position[2],
            residual: scale * p.residual,
            spread_deg: p.spread_deg,
        }),
    }
}

fn highlight_view(hl: &Highlight) -> HighlightView {
    HighlightView {
        x: hl.x,
        y: hl.y,
        pixels: hl.pixels as u64,
        peak: hl.peak,
        clipped: hl.clipped,
        rim_distance: hl.rim_distance,
        elongation: hl.elongation,
        radius_deg: hl.radius_deg,
        confidence: Some(hl.confidence),
    }
}

/// A calibration: its circle, lights, per-light quality, skipped images and file links.
#[utoipa::path(
    get,
    path = "/v1/calibrations/{id}",
    tag = "calibrations",
    params(("id" = Uuid, Path, description = "Calibration id")),
    responses(
        (status = 200, description = "The calibration", body = CalibrationView),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_calibration(
    State(state): State<AppState>,
    caller: Caller,
    CalibrationId(id): CalibrationId,
) -> Result<Json<CalibrationView>, ApiError> {
    Ok(Json(CalibrationView::from_record(
        owned_calibration(&state, &caller, id).await?,
    )?))
}

/// The caller's calibrations (an admin's: every tenant's), newest first, a page at a time.
#[utoipa::path(
    get,
    path = "/v1/calibrations",
    tag = "calibrations",
    params(ListQuery),
    responses(
        (status = 200, description = "A page of calibrations", body = CalibrationList,
            headers(("Link" = String, description = "`<next page URL>; rel=\"next\"` when there is one"))),
        (status = 400, description = "Invalid limit or cursor", body = Problem, content_type = "application/problem+json"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn list_calibrations(
    State(state): State<AppState>,
    caller: Caller,
    ApiQuery(q): ApiQuery<ListQuery>,
) -> Result<Response, ApiError> {
    let page_query = PageQuery::parse(&q)?;
    let (limit, before) = (page_query.limit, page_query.before);
    let scope = caller.scope();
    let mut page = state
        .repo(move |r| r.list_calibrations(scope.as_deref(), limit + 1, before))
        .await?;
    let next_cursor = page_query.cut(&mut page, |r| (r.created_at, r.id));
    let calibrations = readable(
        page.into_iter()
            .map(|r| CalibrationView::from_record(r).map_err(|e| RepoError::new(e.to_string()))),
        "calibration",
    );
    let mut response = Json(CalibrationList {
        calibrations,
        next_cursor: next_cursor.clone(),
    })
    .into_response();
    page_query.link_next(&mut response, "/v1/calibrations", next_cursor.as_deref());
    Ok(response)
}

/// Delete a calibration and its files. Jobs submitted with it keep its lights.
#[utoipa::path(
    delete,
    path = "/v1/calibrations/{id}",
    tag = "calibrations",
    params(("id" = Uuid, Path, description = "Calibration id")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn delete_calibration(
    State(state): State<AppState>,
    caller: Caller,
    CalibrationId(id): CalibrationId,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let cal = owned_calibration(&state, &caller, id).await?;
    if !state.repo(move |r| r.delete_calibration(id)).await? {
        return Err(ApiError::not_found(format!("there is no calibration {id}")));
    }
    remove_files(&state, id).await;
    tracing::info!(
        target: "audit",
        action = "delete",
        tenant = %caller.tenant,
        owner = %cal.tenant,
        calibration = %id,
        request_id = %request_id(&headers),
        "calibration deleted"
    );
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// Serve one of a calibration's files (strong ETag, cacheable for good: they never change).
async fn file(
    state: &AppState,
    caller: &Caller,
    id: Uuid,
    name: &str,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let cal = owned_calibration(state, caller, id).await?;
    let content_type = FILES
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, t)| *t)
        .unwrap_or("application/octet-stream");
    let Some(info) = cal.artifacts.iter().find(|a| a.name == name) else {
        return Err(ApiError::not_found(format!(
            "calibration {id} has no {name}"
        )));
    };
    if not_modified(headers, &info.etag) {
        return Ok(not_modified_response(&info.etag, IMMUTABLE));
    }
    let file = Served::Calibration { id, info };
    download::stored(state, file, headers, content_type, IMMUTABLE).await
}

/// The calibration's light table, `name, x, y, z[, intensity]` (the seed's format, as
/// `reconstruct` and a job's `lights` part read it).
#[utoipa::path(
    get,
    path = "/v1/calibrations/{id}/lights.csv",
    tag = "calibrations",
    params(
        ("id" = Uuid, Path, description = "Calibration id"),
        ("If-None-Match" = Option<String>, Header, description = "ETag(s) of a cached copy"),
    ),
    responses(
        (status = 200, description = "The light table", content_type = "text/csv", body = String,
            headers(("ETag" = String, description = "Strong entity tag"))),
        (status = 304, description = "Not modified (If-None-Match matched)"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_lights_csv(
    State(state): State<AppState>,
    caller: Caller,
    CalibrationId(id): CalibrationId,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    file(&state, &caller, id, "lights.csv", &headers).await
}

/// With several balls: the lights' positions, `name, x, y, z` after a `#` line naming the
/// unit and origin (those of the resource's `position_unit` and `position_origin`); a
/// light whose rays are parallel has no row.
#[utoipa::path(
    get,
    path = "/v1/calibrations/{id}/positions.csv",
    tag = "calibrations",
    params(
        ("id" = Uuid, Path, description = "Calibration id"),
        ("If-None-Match" = Option<String>, Header, description = "ETag(s) of a cached copy"),
    ),
    responses(
        (status = 200, description = "The positions table", content_type = "text/csv", body = String,
            headers(("ETag" = String, description = "Strong entity tag"))),
        (status = 304, description = "Not modified (If-None-Match matched)"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration, or one of a single ball (no positions)", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_positions_csv(
    State(state): State<AppState>,
    caller: Caller,
    CalibrationId(id): CalibrationId,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    file(&state, &caller, id, "positions.csv", &headers).await
}

/// The overlay: the fitted circle (every ball's, with several) and each highlight on the
/// first ball, numbered, over the per-pixel maximum of the sphere images (the images'
/// size).
#[utoipa::path(
    get,
    path = "/v1/calibrations/{id}/overlay.png",
    tag = "calibrations",
    params(
        ("id" = Uuid, Path, description = "Calibration id"),
        ("If-None-Match" = Option<String>, Header, description = "ETag(s) of a cached copy"),
    ),
    responses(
        (status = 200, description = "The overlay picture", content_type = "image/png",
            headers(("ETag" = String, description = "Strong entity tag"))),
        (status = 304, description = "Not modified (If-None-Match matched)"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_overlay(
    State(state): State<AppState>,
    caller: Caller,
    CalibrationId(id): CalibrationId,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    file(&state, &caller, id, "overlay.png", &headers).await
}

/// The recovered light directions on the unit hemisphere (rings at 30° and 60°).
#[utoipa::path(
    get,
    path = "/v1/calibrations/{id}/lights.png",
    tag = "calibrations",
    params(
        ("id" = Uuid, Path, description = "Calibration id"),
        ("If-None-Match" = Option<String>, Header, description = "ETag(s) of a cached copy"),
    ),
    responses(
        (status = 200, description = "The light diagram", content_type = "image/png",
            headers(("ETag" = String, description = "Strong entity tag"))),
        (status = 304, description = "Not modified (If-None-Match matched)"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_lights_png(
    State(state): State<AppState>,
    caller: Caller,
    CalibrationId(id): CalibrationId,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    file(&state, &caller, id, "lights.png", &headers).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_values_are_checked() {
        let c = parse_circle(" 1.5, 2 ,30 ").unwrap();
        assert_eq!((c.cx, c.cy, c.r), (1.5, 2.0, 30.0));
        for bad in ["1,2", "1,2,3,4", "a,b,c", "1,2,inf", ""] {
            assert_eq!(parse_circle(bad).unwrap_err().status(), 422, "{bad}");
        }
        assert_eq!(parse_focal_length("2400").unwrap(), 2400.0);
        for bad in ["0", "-1", "NaN", "x", "inf", "1e10", "0.5"] {
            assert!(parse_focal_length(bad).is_err(), "{bad}");
        }
        assert!(parse_flag("true").unwrap());
        assert!(!parse_flag(" 0 ").unwrap());
        assert!(parse_flag("maybe").is_err());
        assert_eq!(parse_ball_diameter(" 25.4 ").unwrap(), 25.4);
        for bad in ["0", "-1", "NaN", "inf", "1e400", "x", ""] {
            let e = parse_ball_diameter(bad).unwrap_err();
            assert_eq!(e.status(), 422, "{bad}");
        }
    }

    /// A record stored before several balls were served reads back with none of their
    /// fields, and the view says so.
    #[test]
    fn a_record_stored_before_several_balls_reads_back() {
        let detail = serde_json::json!({
            "width": 320, "height": 240, "image_count": 3, "focal_length": null,
            "circle": {"cx": 1.0, "cy": 2.0, "r": 3.0, "source": "given"},
            "lights": [{"name": "a.png", "image": "a.png", "number": 1,
                "direction": [0.0, 0.0, 1.0], "elevation_deg": 90.0, "azimuth_deg": 0.0,
                "highlight": {"x": 1.0, "y": 2.0, "pixels": 4, "peak": 0.9, "clipped": false,
                    "rim_distance": 3.0, "elongation": 1.0, "radius_deg": 1.0}}],
            "skipped": []
        });
        let m: Measured = serde_json::from_value(detail).unwrap();
        assert!(m.more_circles.is_empty() && m.position_unit.is_none());
        assert!(m.lights[0].more_highlights.is_empty() && m.lights[0].position.is_none());
        let shown = serde_json::to_value(&m).unwrap();
        assert_eq!(shown["more_circles"], serde_json::json!([]));
        assert!(shown["lights"][0]["position"].is_null());
        // And what is stored now round-trips.
        let again: Measured = serde_json::from_value(shown.clone()).unwrap();
        assert_eq!(serde_json::to_value(&again).unwrap(), shown);
    }
}
