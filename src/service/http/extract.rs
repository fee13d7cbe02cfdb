//! What a request names, read and checked: query strings (as problems), the ids in URLs,
//! the records they name as the caller may see them, pages of lists, the request id.

use std::collections::BTreeMap;

use axum::extract::{FromRequestParts, Path, Query};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::Response;
use serde::Deserialize;
use utoipa::IntoParams;
use uuid::Uuid;

use crate::service::error::ApiError;
use crate::service::repo::{CalibrationRecord, JobRecord};
use crate::service::state::AppState;
use crate::service::tenancy::Caller;

#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    /// Jobs per page, 1 to 100 (default 20).
    #[param(minimum = 1, maximum = 100)]
    pub limit: Option<u32>,
    /// `next_cursor` of the previous page.
    pub cursor: Option<String>,
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
        id_in_path(parts, state, "job").await.map(JobId)
    }
}

/// The `{id}` of a calibration URL; anything that is not a UUID names none (404).
pub struct CalibrationId(pub Uuid);

impl<S: Send + Sync> FromRequestParts<S> for CalibrationId {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        id_in_path(parts, state, "calibration")
            .await
            .map(CalibrationId)
    }
}

/// The `{id}` of a URL naming a `what` (a job, a calibration): a path that cannot be read
/// is 400, an id that is not a UUID names none (404, "there is no `what` …").
async fn id_in_path<S: Send + Sync>(
    parts: &mut Parts,
    state: &S,
    what: &str,
) -> Result<Uuid, ApiError> {
    let Path(params) = Path::<BTreeMap<String, String>>::from_request_parts(parts, state)
        .await
        .map_err(|e| ApiError::bad_request(e.body_text()))?;
    let raw = params.get("id").cloned().unwrap_or_default();
    Uuid::parse_str(&raw).map_err(|_| ApiError::not_found(format!("there is no {what} {raw:?}")))
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

/// The request id (set by the request-id layer) for the audit log.
pub(crate) fn request_id(headers: &HeaderMap) -> &str {
    headers
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("-")
}

/// One page of a list: `limit` rows (1 to 100, 20 unless asked) after the `cursor` row.
pub(crate) struct PageQuery {
    pub limit: usize,
    /// (created_at, id) of the last row of the previous page.
    pub before: Option<(i64, Uuid)>,
}

impl PageQuery {
    pub(crate) fn parse(q: &ListQuery) -> Result<Self, ApiError> {
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
    pub(crate) fn cut<T>(
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
    pub(crate) fn link_next(&self, response: &mut Response, path: &str, next: Option<&str>) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cursors_round_trip() {
        let id = Uuid::new_v4();
        let c = format!("{}_{}", 1234, id.simple());
        assert_eq!(parse_cursor(&c).unwrap(), (1234, id));
        assert!(parse_cursor("nope").is_err());
        assert!(parse_cursor("12_zz").is_err());
    }
}
