//! The job resource: `POST /v1/jobs` (the upload, checked as it streams, then queued),
//! `GET /v1/jobs`, `GET` and `DELETE /v1/jobs/{id}`.

use axum::Json;
use axum::extract::{Request, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;
use uuid::Uuid;

use crate::core::normalmap::Convention;
use crate::core::options::Options;
use crate::service::config::RETRY_AFTER_SECS;
use crate::service::error::ApiError;
use crate::service::intake::checks::check_url;
use crate::service::intake::job as intake;
use crate::service::intake::tap::BodyTap;
use crate::service::problem::Problem;
use crate::service::repo::{Admission, Callback, CallbackState, JobRecord, JobStatus};
use crate::service::state::AppState;
use crate::service::tenancy::Caller;
use crate::service::tenancy::idempotency::{self, PartHasher};
use crate::service::util::{format_duration, now_ms};
use crate::service::views::JobView;

use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::extract::{
    ApiQuery, JobId, ListQuery, PageQuery, owned_calibration, owned_job, request_id,
};
use super::submission::{
    Submission, answer_of, linger_if_refused, open_submission, remember, tapped,
};

/// `POST` and `GET /v1/jobs`, `GET` and `DELETE /v1/jobs/{id}`.
pub(crate) fn routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::default()
        .routes(routes!(create_job, list_jobs))
        .routes(routes!(get_job, delete_job))
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
    let (parts, tap) = tapped(&state, request);
    let answer = accept_job(&state, &caller, parts, &tap).await;
    linger_if_refused(&answer, tap);
    answer
}

async fn accept_job(
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
        intake::receive(
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
            check_url(url, &config.webhook_allow_hosts)?;
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
    let answer = answer_of(
        body_hash,
        StatusCode::ACCEPTED,
        (&view, &view.url, "job view"),
        record.created_at,
    )?;
    let key = (JOBS_SCOPE, idempotency_key, since);
    // A concurrent request with the same key got there first: this job never was.
    if let Some(first) = remember(state, caller, key, &answer).await? {
        state.remove_prefetch(id);
        state.repo(move |r| r.delete(id)).await?;
        return idempotency::replay(&first, &answer.body_hash);
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
        RETRY_AFTER_SECS,
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
