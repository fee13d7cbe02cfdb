//! Light calibrations as a resource: `POST /v1/calibrations` takes one chrome-sphere image
//! per light, runs the core's calibration within the request (on the blocking pool, at
//! most `workers` at once) and answers 201 with the result. The calibration keeps its
//! light table, per-light quality and pictures until it is deleted; a job names it in a
//! `calibration` part instead of sending a light table (see `jobs`).
//!
//! The upload streams to `calibrations/{id}/files.partial/` (images as `000.img`, …, never
//! the caller's names), which is replaced by the calibration's files and committed before
//! the record is written; ownership follows the jobs' rule
//! (`extract::owned_calibration`). The form is read by `intake::calibration`, computed by
//! `compute` and shown as `view` says.

mod compute;
mod view;

pub(crate) use view::{
    CalibrationList, CalibrationView, CircleView, HighlightView, LightView, Measured,
    MoreHighlightView, PositionView, SkippedView,
};

use axum::Json;
use axum::extract::{Request, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use utoipa::ToSchema;
use uuid::Uuid;

use crate::core::lights;
use crate::service::error::ApiError;
use crate::service::intake::calibration::receive;
use crate::service::intake::tap::BodyTap;
use crate::service::problem::Problem;
use crate::service::repo::{CalibrationRecord, RepoError, readable};
use crate::service::state::AppState;
use crate::service::store::Served;
use crate::service::tenancy::Caller;
use crate::service::tenancy::idempotency::{self, PartHasher};
use crate::service::util::{format_duration, now_ms};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::extract::{
    ApiQuery, CalibrationId, ListQuery, PageQuery, owned_calibration, request_id,
};
use super::responses::{self, IMMUTABLE, not_modified, not_modified_response};
use super::submission::{
    Submission, answer_of, linger_if_refused, open_submission, remember, tapped,
};
use compute::compute;

/// `POST` and `GET /v1/calibrations`, `GET` and `DELETE /v1/calibrations/{id}`, and its
/// files.
pub(crate) fn routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::default()
        .routes(routes!(create_calibration, list_calibrations))
        .routes(routes!(get_calibration, delete_calibration))
        .routes(routes!(get_lights_csv))
        .routes(routes!(get_overlay))
        .routes(routes!(get_lights_png))
        .routes(routes!(get_positions_csv))
}

/// The `Idempotency-Key` scope of `POST /v1/calibrations`.
const SCOPE: &str = "calibrations";

/// The files a calibration keeps, and their content types (`positions.csv` only with
/// several balls).
pub const FILES: [(&str, &str); 4] = [
    ("lights.csv", "text/csv; charset=utf-8"),
    ("overlay.png", "image/png"),
    ("lights.png", "image/png"),
    ("positions.csv", "text/csv; charset=utf-8"),
];

/// The `POST /v1/calibrations` form.
#[derive(ToSchema)]
#[allow(dead_code)] // documents the multipart body; the handler streams it
pub struct CalibrationUpload {
    /// One chrome-sphere image per light, in light order (repeat the part; each needs a
    /// file name, which the errors and the overlay use).
    #[schema(value_type = Vec<super::jobs::ImageFile>)]
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
    #[schema(value_type = super::jobs::ImageFile, required = false)]
    mask: Option<Vec<u8>>,
    /// Images of a matte white sphere under the same lights, same order: fits each
    /// light's relative intensity.
    #[schema(value_type = Vec<super::jobs::ImageFile>, required = false)]
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
    #[schema(value_type = super::jobs::ImageFile, required = false)]
    ambient: Option<Vec<u8>>,
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
    let (parts, tap) = tapped(&state, request);
    let answer = accept(&state, &caller, parts, &tap).await;
    linger_if_refused(&answer, tap);
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
    let answer = answer_of(
        body_hash,
        StatusCode::CREATED,
        (&view, &view.url, "calibration view"),
        record.created_at,
    )?;
    let key = (SCOPE, idempotency_key, since);
    // A concurrent request with the same key got there first: this calibration never was.
    if let Some(first) = remember(state, caller, key, &answer).await? {
        state.repo(move |r| r.delete_calibration(id)).await?;
        remove_files(state, id).await;
        return idempotency::replay(&first, &answer.body_hash);
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
    let store = state.store_handle();
    match tokio::task::spawn_blocking(move || store.remove_calibration(id)).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => {
            tracing::warn!(calibration = %id, error = %e, "cannot remove calibration files")
        }
        Err(e) => tracing::warn!(calibration = %id, error = %e, "cannot remove calibration files"),
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
    responses::stored(state, file, headers, content_type, IMMUTABLE).await
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
