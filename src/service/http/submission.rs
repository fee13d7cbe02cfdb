//! The submission gate: what every multipart submission (a job, a calibration) passes
//! before its body is read.

use axum::extract::{FromRequest, Multipart, Request};
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use axum::response::Response;
use serde::Serialize;
use uuid::Uuid;

use crate::service::config::RETRY_AFTER_SECS;
use crate::service::error::ApiError;
use crate::service::intake::tap::{BodyTap, LINGER};
use crate::service::repo::Remembered;
use crate::service::slots::Slot;
use crate::service::state::AppState;
use crate::service::tenancy::Caller;
use crate::service::tenancy::idempotency;
use crate::service::util::now_ms;

use super::extract::request_id;

/// What every multipart submission (a job, a calibration) starts with, checked before its
/// body is read; `_receiving` holds one of the `max_uploads` upload slots (of the
/// tenant's share) until dropped.
pub(crate) struct Submission {
    pub request_id: String,
    pub idempotency_key: Option<String>,
    pub multipart: Multipart,
    /// The answer to an earlier request with the same `Idempotency-Key` (of `scope`), if
    /// any: a retry is answered as the first request was, whatever the queue and quotas say
    /// now.
    pub earlier: Option<Remembered>,
    /// The start of the idempotency window, for remembering this request's answer.
    pub since: i64,
    pub _receiving: Slot,
}

/// Refuse a submission the service cannot take now (shutting down, a declared body over
/// the limit, not a multipart body, too little disk, every upload slot or the tenant's
/// share of them taken), and look up
/// an earlier answer to its `Idempotency-Key` in `scope`.
pub(crate) async fn open_submission(
    state: &AppState,
    caller: &Caller,
    parts: Parts,
    tap: &BodyTap,
    scope: &'static str,
) -> Result<Submission, ApiError> {
    let config = state.config();
    let request_id = request_id(&parts.headers).to_string();
    let idempotency_key = idempotency::key_from(&parts.headers)?;
    if state.is_shutting_down() {
        return Err(ApiError::unavailable(
            RETRY_AFTER_SECS,
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

/// A submission's answer as it is remembered and sent: `status` with `view` as its JSON
/// body (`what` names the view in an error) and `url` as its `Location`.
pub(crate) fn answer_of(
    body_hash: String,
    status: StatusCode,
    (view, url, what): (&impl Serialize, &str, &str),
    created_at: i64,
) -> Result<Remembered, ApiError> {
    Ok(Remembered {
        body_hash,
        status: status.as_u16(),
        body: serde_json::to_string(view)
            .map_err(|e| ApiError::internal(format!("{what}: {e}")))?,
        location: Some(url.to_string()),
        created_at,
    })
}

/// Remember `answer` under the submission's `Idempotency-Key` in `scope`, when it has
/// one. `Some(first)` when a concurrent request with the same key got there first: what
/// this one made must then be undone, and `first` replayed.
pub(crate) async fn remember(
    state: &AppState,
    caller: &Caller,
    (scope, key, since): (&'static str, Option<String>, i64),
    answer: &Remembered,
) -> Result<Option<Remembered>, ApiError> {
    let Some(key) = key else {
        return Ok(None);
    };
    let (tenant, remembered) = (caller.tenant.clone(), answer.clone());
    state
        .repo(move |r| r.remember(&tenant, scope, &key, &remembered, since))
        .await
}

/// A submission request's head, and its body behind a [`BodyTap`] that counts it against
/// `max_body_bytes`.
pub(crate) fn tapped(state: &AppState, request: Request) -> (Parts, BodyTap) {
    let (parts, body) = request.into_parts();
    (parts, BodyTap::new(body, state.config().max_body_bytes))
}

/// After a refusal, read what the client is still sending in the background (a lingering
/// close), so that it gets to read the refusal; the answer itself goes out at once.
pub(crate) fn linger_if_refused(answer: &Result<Response, ApiError>, tap: BodyTap) {
    if answer.is_err() {
        tokio::spawn(async move { tap.drain(LINGER).await });
    }
}
