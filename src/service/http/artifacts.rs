//! A succeeded job's artifacts: `GET /v1/jobs/{id}/artifacts/{name}`, stored files with
//! their ETags and ranges, and `shaded.png` re-shaded under another light on request.

use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::HeaderMap;
use axum::response::Response;
use serde::Deserialize;
use utoipa::IntoParams;

use crate::core::outputs::{self, ARTIFACTS};
use crate::service::budget::Reservation;
use crate::service::error::ApiError;
use crate::service::problem::Problem;
use crate::service::repo::{JobRecord, JobStatus};
use crate::service::state::AppState;
use crate::service::store::Served;
use crate::service::tenancy::Caller;
use crate::service::util::strong_etag;
use crate::service::views::job_url;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::extract::{ApiQuery, JobId, owned_job};
use super::responses::{self, IMMUTABLE, artifact_response, not_modified, not_modified_response};

/// `GET /v1/jobs/{id}/artifacts/{name}`.
pub(crate) fn routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::default().routes(routes!(get_artifact))
}

/// Cache lifetime of re-shaded pictures.
const RESHADED: &str = "private, max-age=86400";

#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ArtifactQuery {
    /// For `shaded.png` only: re-shade under this light, `x,y,z` (three finite numbers,
    /// not all zero; need not be unit length).
    #[param(example = "1,2,3")]
    pub light: Option<String>,
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
    responses::stored(&state, file, &headers, content_type, IMMUTABLE).await
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
    let store = state.store_handle();
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
    _memory: Option<Reservation>,
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

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::StatusCode;

    #[test]
    fn light_parameter() {
        assert_eq!(parse_light("1,2,3").unwrap(), [1.0, 2.0, 3.0]);
        assert_eq!(parse_light(" -0.5, 0 ,1e0").unwrap(), [-0.5, 0.0, 1.0]);
        for bad in ["1,2", "1,2,3,4", "a,b,c", "0,0,0", "inf,0,1", "NaN,1,1", ""] {
            let e = parse_light(bad).unwrap_err();
            assert_eq!(e.status(), StatusCode::UNPROCESSABLE_ENTITY, "{bad}");
        }
    }
}
