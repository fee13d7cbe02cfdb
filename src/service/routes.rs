//! Handlers: typed extractors in, `Result<impl IntoResponse, ApiError>` out.

use std::collections::BTreeMap;

use axum::Json;
use axum::body::{Body, Bytes};
use axum::extract::{FromRequest, FromRequestParts, Multipart, Path, Query, Request, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use uuid::Uuid;

use crate::core::Options;
use crate::core::error::panic_message;
use crate::core::intensities::Estimated;
use crate::core::normalmap::{Convention, Counts};
use crate::core::outputs::{self, ARTIFACTS};

use super::download::{self, artifact_response, not_modified, not_modified_response};
use super::error::ApiError;
use super::idempotency::{self, PartHasher};
use super::problem::{PROBLEM_JSON, Problem};
use super::repo::{
    Admission, CalibrationRecord, Callback, CallbackState, JobRecord, JobStatus, Remembered,
};
use super::state::AppState;
use super::store::Served;
use super::tenants::Caller;
use super::upload;
use super::util::{format_duration, now_ms, rfc3339, strong_etag};
use super::webhooks;

/// Cache lifetime of stored artifacts (they never change once a job has succeeded).
pub(super) const IMMUTABLE: &str = "private, max-age=31536000, immutable";
/// Cache lifetime of re-shaded pictures.
const RESHADED: &str = "private, max-age=86400";

/// A job: where it is, and once it has succeeded, what it produced.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobView {
    /// The job's id (a random UUID).
    pub id: Uuid,
    pub status: JobStatus,
    /// The tenant that submitted it (`default` when the server has no API keys).
    #[schema(example = "alice")]
    pub tenant: String,
    /// The stage reached: decode, solve, mask, integrate, outputs or mesh (null before a
    /// worker starts it).
    #[schema(example = "solve")]
    pub stage: Option<String>,
    /// Fraction of the stages done, 0 to 1.
    #[schema(example = 0.5)]
    pub progress: f64,
    /// RFC 3339.
    #[schema(example = "2025-11-25T19:34:00.123Z")]
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    /// How many times a worker has started the job (more than 1 when a restart
    /// interrupted it).
    pub attempts: u32,
    /// The images uploaded (0 for a normals job).
    pub image_count: u32,
    /// The options in force, defaults filled in.
    #[schema(value_type = Options)]
    pub options: serde_json::Value,
    /// Why the job failed (only when `status` is `failed`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<Problem>,
    /// Headline numbers of the reconstruction (only when `status` is `succeeded`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub result: Option<ResultSummary>,
    /// Artifact name → download URL, for every artifact the job produced (only when
    /// `status` is `succeeded`).
    #[serde(skip_serializing_if = "Option::is_none")]
    #[schema(example = json!({"albedo.png": "/v1/jobs/0b6f2a43-3c1e-4c51-9d1e-6c9f3a7d2e10/artifacts/albedo.png"}))]
    pub artifacts: Option<BTreeMap<String, String>>,
    /// The webhook, when the job was submitted with a `callback_url`: its state and
    /// every delivery attempt.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub callback: Option<Callback>,
    /// This resource's URL.
    pub url: String,
}

/// The reconstruction's headline numbers (a subset of `result.json`).
#[derive(Debug, Default, Serialize, Deserialize, ToSchema)]
#[serde(default)]
pub struct ResultSummary {
    pub width: Option<u64>,
    pub height: Option<u64>,
    pub light_count: Option<u64>,
    /// Condition number of the light matrix (1 is ideal).
    pub light_condition_number: Option<f64>,
    /// Lowest height on the object, in pixel units (orthographic).
    pub height_min: Option<f64>,
    /// Highest height on the object, in pixel units (orthographic).
    pub height_max: Option<f64>,
    /// Nearest depth on the object, along the optical axis (under a camera; relative with
    /// median 1, or in the unit of the `distance` option; for a near-light job in the
    /// light table's unit).
    pub depth_min: Option<f64>,
    /// Farthest depth on the object (under a camera).
    pub depth_max: Option<f64>,
    /// RMS of the integrability residual (curl) over the object.
    pub integrability_rms: Option<f64>,
    /// RMS difference between the images and the reconstruction re-rendered under the
    /// same lights.
    pub reprojection_rms: Option<f64>,
    pub object_pixels: Option<u64>,
    pub background_pixels: Option<u64>,
    /// Pixels whose albedo was above 1 and clamped.
    pub clamped_albedo_pixels: Option<u64>,
    /// Mean solve confidence over the object (0 to 1).
    pub confidence_mean: Option<f64>,
    /// Mean number of observations kept per object pixel.
    pub inliers_mean: Option<f64>,
    /// Object pixels with fewer than 3 usable observations.
    pub unreliable_pixels: Option<u64>,
    /// Camera black level the robust solver estimated and removed.
    pub black_level: Option<f64>,
    /// Image noise σ the robust solver estimated.
    pub noise_sigma: Option<f64>,
    /// Normals jobs: what the reader did with each pixel of the normal map (used,
    /// back-facing, renormalised, and why the others are off the mask), as `result.json`.
    pub counts: Option<Counts>,
    /// `near` for a near-light job (its light table gives positions); absent otherwise.
    #[schema(example = "near")]
    pub lights: Option<String>,
    /// Near-light jobs: the alternations of per-pixel solve and depth integration run.
    pub iterations: Option<u64>,
    /// Near-light jobs: whether the normals settled (when false, `result.json`'s notes say
    /// how much they still moved).
    pub converged: Option<bool>,
    /// Near-light jobs: median depth over the mask of the surface recovered, along the
    /// optical axis, in `unit`.
    pub median_depth: Option<f64>,
    /// Near-light jobs: the unit of depth (and of the table's positions and distance), as
    /// the light table gives it; null when it gives none.
    pub unit: Option<String>,
    /// The lights' relative intensities (mean 1) estimated from the object (with the
    /// `intensities: estimate` option, or for LEDs whose table gives none); the
    /// `lights.json` artifact is the light table with them.
    pub estimated_intensities: Option<Vec<Estimated>>,
}

/// A page of jobs, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobList {
    pub jobs: Vec<JobView>,
    /// Pass as `cursor` to get the next page; null on the last page.
    pub next_cursor: Option<String>,
}

/// The `POST /v1/jobs` form. Send either `images` + `lights` (or `calibration`) (+ `mask`,
/// `camera`, `options`), `archive` (+ `mask`, `camera`, `options`), or `normals` (+ `mask`,
/// `camera`, `convention`, `options`).
#[derive(ToSchema)]
#[allow(dead_code)] // documents the multipart body; the handler streams it
pub struct JobUpload {
    /// One file part per image (repeat the part); each part's file name is the name the
    /// light table uses for it.
    #[schema(value_type = Vec<ImageFile>, required = false)]
    images: Option<Vec<Vec<u8>>>,
    /// The light table: CSV rows `name, x, y, z[, intensity]`, JSON
    /// `[{"name", "direction": [x, y, z], "intensity"?}]`, or an `.lp` file (the count,
    /// then `name x y z` rows, y up) (text or file part). Near lights: JSON
    /// `{"lights": [{"name", "position": [x, y, z], "axis"?, "anisotropy"?, "intensity"?}],
    /// "camera"?, "distance"?, "unit"?}` (camera frame: x right, y down, z towards the
    /// camera, the scene at negative z) makes a near-light job; it needs a camera (the
    /// `camera` part or option, else the table's) and the working `distance` (the
    /// `distance` option, else the table's): 422 naming what is missing.
    #[schema(value_type = String, required = false)]
    lights: Option<String>,
    /// Instead of `lights`: the id of a calibration (`POST /v1/calibrations`) whose lights
    /// are used, matched to the images by name.
    #[schema(value_type = String, format = Uuid, required = false)]
    calibration: Option<String>,
    /// Optional mask image, same size as the images or the normal map (non-zero = object).
    #[schema(value_type = ImageFile, required = false)]
    mask: Option<Vec<u8>>,
    /// Optional pinhole camera of the images (text or file part): a K.txt (3 × 3), a
    /// camera.json `{fx, fy, cx, cy}` or `fx,fy,cx,cy`, in pixels; or give it as the
    /// `camera` option (not both). An archive's own `camera.json` or `K.txt` is used when
    /// neither is sent.
    #[schema(value_type = String, required = false)]
    camera: Option<String>,
    /// Optional reconstruction options as JSON (unknown fields are refused; a normals job
    /// takes only `integration`, `mesh`, `camera`, `distance` and `outputs`).
    #[schema(value_type = Options, required = false)]
    options: Option<String>,
    /// Instead of images + lights: a .zip of a folder with the images and
    /// `light_directions.csv`, at its top or inside one folder.
    #[schema(value_type = String, content_media_type = "application/zip", required = false)]
    archive: Option<Vec<u8>>,
    /// Instead of images + lights: a normal map to integrate into heights (orthographic) or,
    /// with a camera, depth; an RGB(A) 8/16-bit PNG (`n = 2·v/max − 1`) or 32-bit float
    /// OpenEXR, within the server's pixel limit (413). Black, transparent and zero-length
    /// pixels are background; the job fails (422) when the map does not decode to unit
    /// normals or has no usable pixel.
    #[schema(value_type = ImageFile, required = false)]
    normals: Option<Vec<u8>>,
    /// With `normals`: how its green channel points, `opengl` (y up, the default; aliases
    /// `project`, `benchmark`) or `directx` (y down).
    #[schema(value_type = Convention, required = false)]
    convention: Option<String>,
    /// Optional webhook: an `http://` URL on the server's allow-list that the job resource
    /// is POSTed to when the job ends, signed with the tenant's webhook secret
    /// (`Webhook-Timestamp`, `Webhook-Signature: v1=<hex HMAC-SHA256 of "timestamp.body">`).
    #[schema(value_type = String, required = false)]
    callback_url: Option<String>,
}

/// An image file: PNG, BMP, JPEG or TIFF (8 or 16 bits) or OpenEXR (32-bit float), gray or colour.
#[derive(ToSchema)]
#[schema(value_type = String, content_media_type = "application/octet-stream")]
#[allow(dead_code)]
pub struct ImageFile(Vec<u8>);

/// Liveness / readiness answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct Health {
    #[schema(example = "ok")]
    pub status: String,
}

#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    /// Jobs per page, 1 to 100 (default 20).
    #[param(minimum = 1, maximum = 100)]
    pub limit: Option<u32>,
    /// `next_cursor` of the previous page.
    pub cursor: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ArtifactQuery {
    /// For `shaded.png` only: re-shade under this light, `x,y,z` (three finite numbers,
    /// not all zero; need not be unit length).
    #[param(example = "1,2,3")]
    pub light: Option<String>,
}

/// `Query` whose rejection is a problem (400).
pub struct ApiQuery<T>(pub T);

impl<S, T> FromRequestParts<S> for ApiQuery<T>
where
    S: Send + Sync,
    T: serde::de::DeserializeOwned,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        Query::<T>::from_request_parts(parts, state)
            .await
            .map(|Query(q)| ApiQuery(q))
            .map_err(|e| ApiError::bad_request(format!("invalid query string: {}", e.body_text())))
    }
}

/// The `{id}` of a job URL; anything that is not a UUID names no job (404).
pub struct JobId(pub Uuid);

impl<S: Send + Sync> FromRequestParts<S> for JobId {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let Path(params) = Path::<BTreeMap<String, String>>::from_request_parts(parts, state)
            .await
            .map_err(|e| ApiError::bad_request(e.body_text()))?;
        let raw = params.get("id").cloned().unwrap_or_default();
        Uuid::parse_str(&raw)
            .map(JobId)
            .map_err(|_| ApiError::not_found(format!("there is no job {raw:?}")))
    }
}

fn job_url(id: Uuid) -> String {
    format!("/v1/jobs/{id}")
}

impl JobView {
    pub fn from_record(r: JobRecord) -> Self {
        let url = job_url(r.id);
        let succeeded = r.status == JobStatus::Succeeded;
        Self {
            id: r.id,
            status: r.status,
            tenant: r.tenant,
            stage: r.stage,
            progress: if succeeded { 1.0 } else { r.progress },
            created_at: rfc3339(r.created_at),
            started_at: r.started_at.map(rfc3339),
            finished_at: r.finished_at.map(rfc3339),
            attempts: r.attempts,
            image_count: r.image_count,
            options: r.options,
            error: if r.status == JobStatus::Failed {
                r.error
            } else {
                None
            },
            result: succeeded
                .then(|| r.result.and_then(|v| serde_json::from_value(v).ok()))
                .flatten(),
            artifacts: succeeded.then(|| {
                r.artifacts
                    .iter()
                    .map(|a| (a.name.clone(), format!("{url}/artifacts/{}", a.name)))
                    .collect()
            }),
            callback: r.callback,
            url,
        }
    }
}

/// The job resource as JSON, as `GET /v1/jobs/{id}` answers it (what webhooks deliver).
pub(crate) fn job_json(r: JobRecord) -> String {
    serde_json::to_string(&JobView::from_record(r)).unwrap_or_default()
}

/// The job `id` if the caller may see it. Every route that names a job goes through here:
/// another tenant's job gets exactly the answer of an id that never existed.
pub(crate) async fn owned_job(
    state: &AppState,
    caller: &Caller,
    id: Uuid,
) -> Result<JobRecord, ApiError> {
    state
        .repo(move |r| r.get(id))
        .await?
        .filter(|job| caller.sees(&job.tenant))
        .ok_or_else(|| ApiError::not_found(format!("there is no job {id}")))
}

/// The calibration `id` if the caller may see it: the same rule and answer as
/// [`owned_job`], for every route that names a calibration.
pub(crate) async fn owned_calibration(
    state: &AppState,
    caller: &Caller,
    id: Uuid,
) -> Result<CalibrationRecord, ApiError> {
    state
        .repo(move |r| r.get_calibration(id))
        .await?
        .filter(|c| caller.sees(&c.tenant))
        .ok_or_else(|| ApiError::not_found(format!("there is no calibration {id}")))
}

/// The light table of a job's `calibration` part: an id that is no calibration the caller
/// may see is a 422 (a field of the body), the same for one that never existed and
/// another tenant's.
async fn calibration_table(
    state: &AppState,
    caller: &Caller,
    raw: &str,
) -> Result<Vec<u8>, ApiError> {
    let unknown = || {
        ApiError::invalid(format!(
            "calibration: there is no calibration {raw:?} (send the id of one of your calibrations, as POST /v1/calibrations answered it)"
        ))
    };
    let id = Uuid::parse_str(raw).map_err(|_| unknown())?;
    match owned_calibration(state, caller, id).await {
        Ok(c) => Ok(c.table.into_bytes()),
        Err(e) if e.status() == StatusCode::NOT_FOUND => Err(unknown()),
        Err(e) => Err(e),
    }
}

/// The request id (set by the request-id layer) for the audit log.
pub(super) fn request_id(headers: &HeaderMap) -> &str {
    headers
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("-")
}

/// Submit a reconstruction job.
///
/// The upload streams to disk; the light table, names, image formats and dimensions and the
/// options are checked before the job is accepted, so most mistakes are answered at once.
/// The answer is 202 with the job and its `Location`; poll it until `status` is
/// `succeeded` or `failed`.
#[utoipa::path(
    post,
    path = "/v1/jobs",
    tag = "jobs",
    request_body(content = inline(JobUpload), content_type = "multipart/form-data"),
    params(
        ("Idempotency-Key" = Option<String>, Header, description = "1 to 255 visible ASCII characters. The same key and the same parts from the same tenant within 24 hours get the first answer again (same status and body) instead of a new job; the same key with different parts is 422. Kept across restarts."),
    ),
    responses(
        (status = 202, description = "Accepted and queued (or, for a repeated Idempotency-Key, the first request's answer)", body = JobView,
            headers(("Location" = String, description = "The job's URL"))),
        (status = 400, description = "Not multipart, or parts missing, repeated or unknown", body = Problem, content_type = "application/problem+json"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 408, description = "The upload took longer than the upload time limit", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Body, image, part count, image count, the set's pixels or archive over a limit", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "An image (or archive) in an unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid light table, options, names, sizes or archive layout; a callback_url off the allow-list or not http://, or for a tenant without a webhook secret; an Idempotency-Key already used for a different request", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "A quota of the caller's tenant is reached (the detail names it): jobs queued or running at once, submissions per minute, or stored bytes; retry after Retry-After seconds", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = u64, description = "Seconds to wait"))),
        (status = 503, description = "The queue is full, the most uploads at once (or the tenant's share of them) are under way, or the service is stopping: retry after Retry-After seconds", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = u64, description = "Seconds to wait"))),
        (status = 507, description = "Not enough free disk space", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn create_job(
    State(state): State<AppState>,
    caller: Caller,
    request: Request,
) -> Result<Response, ApiError> {
    let (parts, body) = request.into_parts();
    let tap = upload::BodyTap::new(body, state.config().max_body_bytes);
    let answer = accept_job(&state, &caller, parts, &tap).await;
    if answer.is_err() {
        // Answer now, and read what the client is still sending in the background (a
        // lingering close), so that it gets to read the refusal.
        tokio::spawn(async move { tap.drain(upload::LINGER).await });
    }
    answer
}

/// What every multipart submission (a job, a calibration) starts with, checked before its
/// body is read; `_receiving` holds one of the `max_uploads` upload slots (of the
/// tenant's share) until dropped.
pub(super) struct Submission {
    pub request_id: String,
    pub idempotency_key: Option<String>,
    pub multipart: Multipart,
    /// The answer to an earlier request with the same `Idempotency-Key` (of `scope`), if
    /// any: a retry is answered as the first request was, whatever the queue and quotas say
    /// now.
    pub earlier: Option<Remembered>,
    /// The start of the idempotency window, for remembering this request's answer.
    pub since: i64,
    pub _receiving: super::slots::Slot,
}

/// Refuse a submission the service cannot take now (shutting down, a declared body over
/// the limit, not a multipart body, too little disk, every upload slot or the tenant's
/// share of them taken), and look up
/// an earlier answer to its `Idempotency-Key` in `scope`.
pub(super) async fn open_submission(
    state: &AppState,
    caller: &Caller,
    parts: Parts,
    tap: &upload::BodyTap,
    scope: &'static str,
) -> Result<Submission, ApiError> {
    let config = state.config();
    let request_id = request_id(&parts.headers).to_string();
    let idempotency_key = idempotency::key_from(&parts.headers)?;
    if state.is_shutting_down() {
        return Err(ApiError::unavailable(
            super::config::RETRY_AFTER_SECS,
            "the service is shutting down",
        ));
    }
    let declared = parts
        .headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > config.max_body_bytes) {
        return Err(ApiError::too_large(format!(
            "the request body is larger than the limit of {} bytes",
            config.max_body_bytes
        )));
    }
    let multipart = Multipart::from_request(Request::from_parts(parts, tap.body()), &())
        .await
        .map_err(|e| {
            ApiError::bad_request(format!(
                "expected a multipart/form-data body: {}",
                e.body_text()
            ))
        })?;
    state.check_free_disk().await?;
    let receiving = state.upload_slot(&caller.tenant)?;
    let mut since = now_ms() - idempotency::WINDOW.as_millis() as i64;
    let mut earlier = match idempotency_key.clone() {
        Some(key) => {
            let tenant = caller.tenant.clone();
            state
                .repo(move |r| r.idempotent(&tenant, scope, &key, since))
                .await?
        }
        None => None,
    };
    // An answer is replayed only while what it created exists: once that is deleted (or
    // expired) the key starts afresh, and this request's answer replaces the old one.
    if let Some(e) = &earlier
        && !still_exists(state, e).await?
    {
        since = e.created_at + 1;
        earlier = None;
    }
    Ok(Submission {
        request_id,
        idempotency_key,
        multipart,
        earlier,
        since,
        _receiving: receiving,
    })
}

/// Whether the job or calibration an earlier answer created (its `Location`) is still
/// stored. An answer without one created nothing that could go.
async fn still_exists(state: &AppState, earlier: &Remembered) -> Result<bool, ApiError> {
    let Some(location) = earlier.location.as_deref() else {
        return Ok(true);
    };
    let id = location
        .rsplit('/')
        .next()
        .and_then(|s| Uuid::parse_str(s).ok());
    let Some(id) = id else {
        return Ok(true);
    };
    if location.starts_with("/v1/calibrations/") {
        Ok(state.repo(move |r| r.get_calibration(id)).await?.is_some())
    } else {
        Ok(state.repo(move |r| r.get(id)).await?.is_some())
    }
}

async fn accept_job(
    state: &AppState,
    caller: &Caller,
    parts: Parts,
    tap: &upload::BodyTap,
) -> Result<Response, ApiError> {
    let config = state.config();
    let Submission {
        request_id,
        idempotency_key,
        mut multipart,
        earlier,
        since,
        _receiving,
    } = open_submission(state, caller, parts, tap, JOBS_SCOPE).await?;
    if earlier.is_none() {
        if state.repo(|r| r.queued()).await? >= config.queue_length as u64 {
            state.count_queue_full();
            return Err(queue_full(state));
        }
        state.check_quotas(&caller.tenant).await?;
    }

    let id = Uuid::new_v4();
    let mut staging = state.stage_upload(id).await?;
    // Dropped with its decoded images on any refusal below.
    let prefetch = earlier.is_none().then(|| state.begin_prefetch()).flatten();
    let mut hash = PartHasher::new(idempotency_key.is_some());
    let tables =
        |raw: String| -> futures_util::future::BoxFuture<'static, Result<Vec<u8>, ApiError>> {
            let (state, caller) = (state.clone(), caller.clone());
            Box::pin(async move { calibration_table(&state, &caller, &raw).await })
        };
    let received = tokio::time::timeout(
        config.upload_timeout,
        upload::receive(
            config,
            staging.path(),
            &mut multipart,
            tap,
            prefetch.as_ref(),
            &mut hash,
            &tables,
        ),
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
    let callback = match &received.callback_url {
        Some(url) => {
            webhooks::check_url(url, &config.webhook_allow_hosts)?;
            if !state.has_webhook_secret(&caller.tenant) {
                return Err(ApiError::invalid(format!(
                    "callback_url: tenant {} has no webhook secret on this server (--webhook-secret), so its callbacks could not be signed",
                    caller.tenant
                )));
            }
            Some(Callback {
                url: url.clone(),
                state: CallbackState::Pending,
                attempts: Vec::new(),
            })
        }
        None => None,
    };
    staging.commit().await?;

    let mut record = JobRecord::new_queued(
        id,
        &caller.tenant,
        now_ms(),
        received.image_count as u32,
        received.options,
    );
    record.callback = callback;
    let stored = record.clone();
    let (max_active, max_queued) = (config.tenant_max_jobs, config.queue_length);
    // Parked before the job is recorded, so that a worker that claims it at once finds it.
    // A near-light job decodes its images whole: what was scanned is dropped.
    if let Some(set) = prefetch.filter(|_| !received.near) {
        state.park_prefetch(id, set);
    }
    match state
        .repo(move |r| r.insert(&stored, max_active, max_queued))
        .await
    {
        Ok(Admission::Accepted) => {}
        refused => {
            state.remove_prefetch(id);
            match refused? {
                Admission::TenantFull => return Err(state.over_active_jobs(&caller.tenant)),
                _ => {
                    state.count_queue_full();
                    return Err(queue_full(state));
                }
            }
        }
    }
    let view = JobView::from_record(record.clone());
    let answer = Remembered {
        body_hash,
        status: StatusCode::ACCEPTED.as_u16(),
        body: serde_json::to_string(&view)
            .map_err(|e| ApiError::internal(format!("job view: {e}")))?,
        location: Some(view.url.clone()),
        created_at: record.created_at,
    };
    if let Some(key) = idempotency_key {
        let (tenant, remembered) = (caller.tenant.clone(), answer.clone());
        let raced = state
            .repo(move |r| r.remember(&tenant, JOBS_SCOPE, &key, &remembered, since))
            .await?;
        // A concurrent request with the same key got there first: this job never was.
        if let Some(first) = raced {
            state.remove_prefetch(id);
            state.repo(move |r| r.delete(id)).await?;
            return idempotency::replay(&first, &answer.body_hash);
        }
    }
    state.workers().ring();
    staging.keep();
    state.count_submitted();
    tracing::info!(
        target: "audit",
        action = "create",
        tenant = %caller.tenant,
        job = %id,
        request_id = %request_id,
        images = record.image_count,
        "job accepted"
    );
    Ok(idempotency::answer(&answer))
}

/// The `Idempotency-Key` scope of `POST /v1/jobs`.
const JOBS_SCOPE: &str = "jobs";

fn queue_full(state: &AppState) -> ApiError {
    ApiError::queue_full(
        super::config::RETRY_AFTER_SECS,
        format!(
            "the job queue is full ({} jobs waiting); retry later",
            state.config().queue_length
        ),
    )
}

/// A job's status, progress, result summary and artifact links.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}",
    tag = "jobs",
    params(("id" = Uuid, Path, description = "Job id")),
    responses(
        (status = 200, description = "The job", body = JobView),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_job(
    State(state): State<AppState>,
    caller: Caller,
    JobId(id): JobId,
) -> Result<Json<JobView>, ApiError> {
    Ok(Json(JobView::from_record(
        owned_job(&state, &caller, id).await?,
    )))
}

/// The caller's jobs (an admin's: every tenant's), newest first, a page at a time.
#[utoipa::path(
    get,
    path = "/v1/jobs",
    tag = "jobs",
    params(ListQuery),
    responses(
        (status = 200, description = "A page of jobs", body = JobList,
            headers(("Link" = String, description = "`<next page URL>; rel=\"next\"` when there is one"))),
        (status = 400, description = "Invalid limit or cursor", body = Problem, content_type = "application/problem+json"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn list_jobs(
    State(state): State<AppState>,
    caller: Caller,
    ApiQuery(q): ApiQuery<ListQuery>,
) -> Result<Response, ApiError> {
    let page_query = PageQuery::parse(&q)?;
    let (limit, before) = (page_query.limit, page_query.before);
    let scope = caller.scope();
    let mut page = state
        .repo(move |r| r.list(scope.as_deref(), limit + 1, before))
        .await?;
    let next_cursor = page_query.cut(&mut page, |r| (r.created_at, r.id));
    let mut response = Json(JobList {
        jobs: page.into_iter().map(JobView::from_record).collect(),
        next_cursor: next_cursor.clone(),
    })
    .into_response();
    page_query.link_next(&mut response, "/v1/jobs", next_cursor.as_deref());
    Ok(response)
}

/// One page of a list: `limit` rows (1 to 100, 20 unless asked) after the `cursor` row.
pub(super) struct PageQuery {
    pub limit: usize,
    /// (created_at, id) of the last row of the previous page.
    pub before: Option<(i64, Uuid)>,
}

impl PageQuery {
    pub(super) fn parse(q: &ListQuery) -> Result<Self, ApiError> {
        let limit = q.limit.unwrap_or(20);
        if !(1..=100).contains(&limit) {
            return Err(ApiError::bad_request(format!(
                "limit must be between 1 and 100, got {limit}"
            )));
        }
        Ok(Self {
            limit: limit as usize,
            before: q.cursor.as_deref().map(parse_cursor).transpose()?,
        })
    }

    /// Cut `rows`, fetched as `limit + 1`, to the page; the next page's cursor (from the
    /// last row's `key`) when there is more.
    pub(super) fn cut<T>(
        &self,
        rows: &mut Vec<T>,
        key: impl Fn(&T) -> (i64, Uuid),
    ) -> Option<String> {
        if rows.len() <= self.limit {
            return None;
        }
        rows.truncate(self.limit);
        rows.last().map(|r| {
            let (at, id) = key(r);
            format!("{at}_{}", id.simple())
        })
    }

    /// `Link: <path?limit=…&cursor=…>; rel="next"` when there is a next page.
    pub(super) fn link_next(&self, response: &mut Response, path: &str, next: Option<&str>) {
        if let Some(c) = next
            && let Ok(v) = HeaderValue::from_str(&format!(
                "<{path}?limit={}&cursor={c}>; rel=\"next\"",
                self.limit
            ))
        {
            response.headers_mut().insert(header::LINK, v);
        }
    }
}

fn parse_cursor(c: &str) -> Result<(i64, Uuid), ApiError> {
    let bad = || {
        ApiError::bad_request(format!(
            "invalid cursor {c:?}: pass a next_cursor as it was given"
        ))
    };
    let (at, id) = c.split_once('_').ok_or_else(bad)?;
    Ok((
        at.parse().map_err(|_| bad())?,
        Uuid::parse_str(id).map_err(|_| bad())?,
    ))
}

/// Cancel a queued or running job, or delete a finished one and its files.
///
/// A queued job is cancelled at once; a running one stops within one step of work (its
/// status is `cancelled` from now on). Either way the answer is 200 with the job. A finished job
/// (succeeded, failed or cancelled) is deleted with its files: 204.
#[utoipa::path(
    delete,
    path = "/v1/jobs/{id}",
    tag = "jobs",
    params(("id" = Uuid, Path, description = "Job id")),
    responses(
        (status = 200, description = "Cancelled", body = JobView),
        (status = 204, description = "Deleted"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json"),
    ),
    security((), ("bearer" = []))
)]
pub async fn delete_job(
    State(state): State<AppState>,
    caller: Caller,
    JobId(id): JobId,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let job = owned_job(&state, &caller, id).await?;
    tracing::info!(
        target: "audit",
        action = "delete",
        tenant = %caller.tenant,
        owner = %job.tenant,
        job = %id,
        request_id = %request_id(&headers),
        "job deleted or cancelled"
    );
    let now = now_ms();
    match state.repo(move |r| r.cancel(id, now)).await? {
        Some(JobStatus::Queued) => {
            state.remove_files(id).await;
            state.job_ended(id);
            tracing::info!(job = %id, "queued job cancelled");
        }
        Some(_) => {
            // Held here, it stops within one step of work; held by another instance, once
            // that instance's next heartbeat hears of it.
            state.workers().cancel_running(id);
            tracing::info!(job = %id, "running job cancelled");
        }
        None => {
            if !state.repo(move |r| r.delete(id)).await? {
                return Err(ApiError::not_found(format!("there is no job {id}")));
            }
            // A worker still finishing a cancelled run removes the files itself.
            if !state.workers().is_held(id) {
                state.remove_files(id).await;
            }
            tracing::info!(job = %id, "job deleted");
            return Ok(StatusCode::NO_CONTENT.into_response());
        }
    }
    Ok(Json(JobView::from_record(owned_job(&state, &caller, id).await?)).into_response())
}

/// Download an artifact of a succeeded job.
///
/// Stored artifacts carry a strong ETag and may be cached for good (`immutable`);
/// `If-None-Match` gets 304. `shaded.png?light=x,y,z` re-shades the object under another
/// light on request: at most `--max-reshades` at once, each within the memory budget,
/// else 503 with Retry-After.
#[utoipa::path(
    get,
    path = "/v1/jobs/{id}/artifacts/{name}",
    tag = "jobs",
    params(
        ("id" = Uuid, Path, description = "Job id"),
        ("name" = String, Path, description = "Artifact name (the job's `artifacts` list those it produced)"),
        ArtifactQuery,
        ("If-None-Match" = Option<String>, Header, description = "ETag(s) of a cached copy"),
        ("Range" = Option<String>, Header, description = "One byte range, `bytes=first-last`, `bytes=first-` or `bytes=-suffix` (stored artifacts; several ranges get the whole file)"),
        ("If-Range" = Option<String>, Header, description = "The ETag the Range applies to; another ETag gets the whole file"),
    ),
    responses(
        (status = 200, description = "The artifact (Content-Type by name: image/png, image/x-exr, model/gltf-binary, model/gltf+json, application/json)",
            content(
                ("image/png"),
                ("image/x-exr"),
                ("model/gltf-binary"),
                ("model/gltf+json"),
                ("application/json"),
            ),
            headers(
                ("ETag" = String, description = "Strong entity tag"),
                ("Cache-Control" = String, description = "private, max-age=31536000, immutable"),
            )),
        (status = 206, description = "The byte range asked for (Content-Range says which)",
            headers(
                ("Content-Range" = String, description = "bytes first-last/length"),
                ("ETag" = String, description = "Strong entity tag"),
            )),
        (status = 304, description = "Not modified (If-None-Match matched)"),
        (status = 400, description = "`light` given for an artifact other than shaded.png", body = Problem, content_type = "application/problem+json"),
        (status = 401, description = "Missing or invalid API key", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job, or no such artifact (unknown name, or not produced by this job)", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "The job has not succeeded (queued, running, failed or cancelled)", body = Problem, content_type = "application/problem+json"),
        (status = 416, description = "No byte of the artifact is in the Range (Content-Range: bytes */length)", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid `light`", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "The storage for job files does not answer; or, re-shading, `--max-reshades` re-shades are being computed or the memory budget has no room for this one (Retry-After)", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = u64, description = "Seconds to wait"))),
    ),
    security((), ("bearer" = []))
)]
pub async fn get_artifact(
    State(state): State<AppState>,
    caller: Caller,
    JobId(id): JobId,
    Path(segments): Path<(String, String)>,
    ApiQuery(q): ApiQuery<ArtifactQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let name = segments.1;
    let Some(content_type) = outputs::content_type(&name) else {
        let known: Vec<&str> = ARTIFACTS.iter().map(|(n, _)| *n).collect();
        return Err(ApiError::not_found(format!(
            "there is no artifact {name:?}; artifacts are {}",
            known.join(", ")
        )));
    };
    let job = owned_job(&state, &caller, id).await?;
    if job.status != JobStatus::Succeeded {
        return Err(ApiError::conflict(format!(
            "job {id} is {}: artifacts are served once it has succeeded",
            job.status.as_str()
        ))
        .with_instance(job_url(id)));
    }
    if let Some(light) = q.light {
        if name != "shaded.png" {
            return Err(ApiError::bad_request(format!(
                "the light parameter applies to shaded.png only, not {name:?}"
            )));
        }
        let light = parse_light(&light)?;
        let missing: Vec<&str> = ["albedo.png", "normal.png"]
            .into_iter()
            .filter(|n| !job.artifacts.iter().any(|a| a.name == *n))
            .collect();
        if !missing.is_empty() {
            return Err(ApiError::not_found(format!(
                "re-shading needs albedo.png and normal.png, and job {id} did not produce {}",
                missing.join(" or ")
            )));
        }
        let png = reshade(&state, &caller, &job, light).await?;
        let etag = strong_etag(crc32fast::hash(&png), png.len() as u64);
        if not_modified(&headers, &etag) {
            return Ok(not_modified_response(&etag, RESHADED));
        }
        return Ok(artifact_response(
            content_type,
            &etag,
            RESHADED,
            &name,
            png.len() as u64,
            Body::from(png),
        ));
    }
    let Some(info) = job.artifacts.iter().find(|a| a.name == name) else {
        return Err(ApiError::not_found(format!(
            "job {id} did not produce {name} (see the job's artifacts)"
        )));
    };
    if not_modified(&headers, &info.etag) {
        return Ok(not_modified_response(&info.etag, IMMUTABLE));
    }
    let file = Served::Artifact { job: id, info };
    download::stored(&state, file, &headers, content_type, IMMUTABLE).await
}

/// A succeeded job's `shaded.png` under `light`, within a re-shade slot and the memory
/// budget (503 + Retry-After when either is used up). The picture's bytes keep the
/// reservation until they are freed (the response sent), and then the allocator's free
/// memory goes back to the kernel.
async fn reshade(
    state: &AppState,
    caller: &Caller,
    job: &JobRecord,
    light: [f64; 3],
) -> Result<Bytes, ApiError> {
    let side = |key: &str| job.result.as_ref().and_then(|r| r[key].as_u64());
    let (width, height) = match (side("width"), side("height")) {
        (Some(w), Some(h)) => (w, h),
        // Not recorded: the largest picture a job may have.
        _ => (state.config().max_pixels, 1),
    };
    let (slot, memory) = state.reshade_slot(&caller.tenant, width, height)?;
    let store = state.inner.store.clone();
    let id = job.id;
    let needed: Vec<_> = job
        .artifacts
        .iter()
        .filter(|a| a.name == "albedo.png" || a.name == "normal.png")
        .cloned()
        .collect();
    let png = tokio::task::spawn_blocking(move || {
        let _computing = slot;
        let local = store.local_artifacts(id, &needed.iter().collect::<Vec<_>>())?;
        let png = outputs::shaded_png_from_dir(local.dir(), light);
        if png.is_err() {
            crate::core::heap::release_free_heap();
        }
        Ok::<_, ApiError>(png?)
    })
    .await??;
    Ok(Bytes::from_owner(Reshaded {
        png,
        _memory: Some(memory),
    }))
}

/// A re-shaded picture and its reservation: when the bytes are freed, the allocator's
/// free memory is handed back (off the async threads) and then the reservation.
struct Reshaded {
    png: Vec<u8>,
    _memory: Option<super::budget::Reservation>,
}

impl AsRef<[u8]> for Reshaded {
    fn as_ref(&self) -> &[u8] {
        &self.png
    }
}

impl Drop for Reshaded {
    fn drop(&mut self) {
        drop(std::mem::take(&mut self.png));
        let memory = self._memory.take();
        let release = move || {
            crate::core::heap::release_free_heap();
            drop(memory);
        };
        match tokio::runtime::Handle::try_current() {
            Ok(rt) => drop(rt.spawn_blocking(release)),
            Err(_) => release(),
        }
    }
}

/// `x,y,z`: three finite numbers, not all zero.
fn parse_light(raw: &str) -> Result<[f64; 3], ApiError> {
    let bad = |why: &str| {
        ApiError::invalid(format!(
            "light must be three finite numbers x,y,z, not all zero ({why}); got {raw:?}"
        ))
    };
    let parts: Vec<&str> = raw.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(bad(&format!("{} values", parts.len())));
    }
    let mut v = [0.0; 3];
    for (slot, p) in v.iter_mut().zip(&parts) {
        *slot = p
            .parse::<f64>()
            .map_err(|_| bad(&format!("{p:?} is not a number")))?;
        if !slot.is_finite() {
            return Err(bad(&format!("{p:?} is not finite")));
        }
    }
    if v.iter().all(|c| *c == 0.0) {
        return Err(bad("zero vector"));
    }
    Ok(v)
}

/// Liveness: the process answers.
#[utoipa::path(
    get,
    path = "/healthz",
    tag = "operations",
    responses((status = 200, description = "Alive", body = Health))
)]
pub async fn healthz() -> Json<Health> {
    Json(Health {
        status: "ok".into(),
    })
}

/// Readiness: the job database answers, the data directory is writable, the service is
/// not shutting down, and it is not saturated: an upload slot is free and the memory
/// budget has room for another job.
#[utoipa::path(
    get,
    path = "/readyz",
    tag = "operations",
    responses(
        (status = 200, description = "Ready", body = Health),
        (status = 503, description = "Not ready, or saturated (the detail says why)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn readyz(State(state): State<AppState>) -> Result<Json<Health>, ApiError> {
    let problems = state.readiness_problems().await;
    if problems.is_empty() {
        Ok(Json(Health {
            status: "ready".into(),
        }))
    } else {
        Err(ApiError::unavailable(1, problems.join("; ")))
    }
}

/// Prometheus metrics: jobs by status, queue depth, running workers (and the most ever
/// running at once), stage durations, HTTP requests.
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "operations",
    responses((status = 200, description = "Prometheus text format 0.0.4", body = String, content_type = "text/plain"))
)]
pub async fn metrics(State(state): State<AppState>) -> Result<Response, ApiError> {
    let text = state.render_metrics().await?;
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
        )],
        text,
    )
        .into_response())
}

/// This API's OpenAPI document.
#[utoipa::path(
    get,
    path = "/openapi.json",
    tag = "operations",
    responses((status = 200, description = "OpenAPI 3.1 document", content_type = "application/json"))
)]
pub async fn openapi_doc() -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        super::http::openapi::openapi_json(),
    )
        .into_response()
}

/// Unknown routes.
pub async fn not_found(uri: axum::http::Uri) -> ApiError {
    ApiError::not_found(format!("there is no route {}", uri.path()))
}

/// Known routes, wrong method.
pub async fn method_not_allowed(method: axum::http::Method, uri: axum::http::Uri) -> ApiError {
    ApiError::method_not_allowed(format!("{} does not accept {method}", uri.path()))
}

/// What the catch-panic layer answers (the panic itself is logged).
pub fn panic_response(err: Box<dyn std::any::Any + Send + 'static>) -> Response {
    let what = panic_message(&*err);
    let mut r = ApiError::internal(format!("handler panicked: {what}")).into_response();
    r.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn light_parameter() {
        assert_eq!(parse_light("1,2,3").unwrap(), [1.0, 2.0, 3.0]);
        assert_eq!(parse_light(" -0.5, 0 ,1e0").unwrap(), [-0.5, 0.0, 1.0]);
        for bad in ["1,2", "1,2,3,4", "a,b,c", "0,0,0", "inf,0,1", "NaN,1,1", ""] {
            let e = parse_light(bad).unwrap_err();
            assert_eq!(e.status(), StatusCode::UNPROCESSABLE_ENTITY, "{bad}");
        }
    }

    #[test]
    fn if_none_match() {
        let mut h = HeaderMap::new();
        h.insert(
            header::IF_NONE_MATCH,
            HeaderValue::from_static("\"a\", W/\"b\""),
        );
        assert!(not_modified(&h, "\"b\""));
        assert!(not_modified(&h, "\"a\""));
        assert!(!not_modified(&h, "\"c\""));
        h.insert(header::IF_NONE_MATCH, HeaderValue::from_static("*"));
        assert!(not_modified(&h, "\"c\""));
    }

    #[test]
    fn cursors_round_trip() {
        let id = Uuid::new_v4();
        let c = format!("{}_{}", 1234, id.simple());
        assert_eq!(parse_cursor(&c).unwrap(), (1234, id));
        assert!(parse_cursor("nope").is_err());
        assert!(parse_cursor("12_zz").is_err());
    }
}
