//! Serving a stored file (a job's artifact, a calibration's file) from the store: the
//! whole file, or one byte range of it (`Range: bytes=…`, 206; 416 when no byte of the
//! file is in it), streamed as the store sends it. `If-None-Match` is the caller's to
//! check ([`not_modified`], before the store is asked); the headers of a file's answer
//! are [`artifact_response`]'s, for files made on request too.

use std::ops::Range;

use axum::body::Body;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use crate::service::error::ApiError;
use crate::service::state::AppState;
use crate::service::store::Served;

/// Cache lifetime of stored artifacts (they never change once a job has succeeded).
pub(crate) const IMMUTABLE: &str = "private, max-age=31536000, immutable";

/// What a request's `Range` asks of a file of `len` bytes.
#[derive(Debug, PartialEq, Eq)]
enum Wanted {
    Whole,
    Part(Range<u64>),
    Unsatisfiable,
}

/// One `bytes=` range, honoured only while `If-Range` (when sent) names the current
/// ETag. Anything else (other units, several ranges, a malformed header) is answered with
/// the whole file, as RFC 9110 allows.
fn wanted(headers: &HeaderMap, etag: &str, len: u64) -> Wanted {
    let Some(raw) = headers.get(header::RANGE).and_then(|v| v.to_str().ok()) else {
        return Wanted::Whole;
    };
    if let Some(tag) = headers.get(header::IF_RANGE)
        && tag.to_str().map(str::trim).ok() != Some(etag)
    {
        return Wanted::Whole;
    }
    let Some(spec) = raw.trim().strip_prefix("bytes=") else {
        return Wanted::Whole;
    };
    let Some((first, last)) = spec.split_once('-') else {
        return Wanted::Whole;
    };
    if spec.contains(',') {
        return Wanted::Whole;
    }
    let (first, last) = (first.trim(), last.trim());
    let number = |s: &str| s.parse::<u64>().ok();
    match (first.is_empty(), last.is_empty()) {
        (true, true) => Wanted::Whole,
        (true, false) => match number(last) {
            None => Wanted::Whole,
            Some(0) => Wanted::Unsatisfiable,
            Some(_) if len == 0 => Wanted::Unsatisfiable,
            Some(n) => Wanted::Part(len.saturating_sub(n)..len),
        },
        (false, _) => {
            let Some(start) = number(first) else {
                return Wanted::Whole;
            };
            let end = if last.is_empty() {
                len
            } else {
                match number(last) {
                    Some(l) if l >= start => l.saturating_add(1).min(len),
                    _ => return Wanted::Whole,
                }
            };
            if start >= len {
                Wanted::Unsatisfiable
            } else {
                Wanted::Part(start..end)
            }
        }
    }
}

/// The answer for a stored file, whole or the range asked for, with its ETag and `cache`.
pub(super) async fn stored(
    state: &AppState,
    file: Served<'_>,
    headers: &HeaderMap,
    content_type: &'static str,
    cache: &'static str,
) -> Result<Response, ApiError> {
    let info = file.info();
    let (name, etag, len) = (info.name.as_str(), info.etag.as_str(), info.bytes);
    let range = match wanted(headers, etag, len) {
        Wanted::Unsatisfiable => {
            let mut r = ApiError::range_not_satisfiable(format!(
                "{name} has {len} bytes; the Range asks for none of them"
            ))
            .into_response();
            if let Ok(v) = HeaderValue::from_str(&format!("bytes */{len}")) {
                r.headers_mut().insert(header::CONTENT_RANGE, v);
            }
            return Ok(r);
        }
        Wanted::Part(r) if r != (0..len) => Some(r),
        _ => None,
    };
    let gone = |e: crate::service::store::Error| {
        if e.is_not_found() {
            ApiError::not_found(format!("{name} is gone from the store"))
        } else {
            ApiError::from(e)
        }
    };
    let stream = state
        .store()
        .read(file, range.clone())
        .await
        .map_err(gone)?;
    let body = Body::from_stream(stream);
    let mut r = match &range {
        None => artifact_response(content_type, etag, cache, name, len, body),
        Some(part) => {
            let mut r =
                artifact_response(content_type, etag, cache, name, part.end - part.start, body);
            *r.status_mut() = StatusCode::PARTIAL_CONTENT;
            let value = format!("bytes {}-{}/{len}", part.start, part.end - 1);
            if let Ok(v) = HeaderValue::from_str(&value) {
                r.headers_mut().insert(header::CONTENT_RANGE, v);
            }
            r
        }
    };
    r.headers_mut()
        .insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    Ok(r)
}

/// Whether `If-None-Match` names `etag` (or `*`).
pub(super) fn not_modified(headers: &HeaderMap, etag: &str) -> bool {
    let bare = |t: &str| t.trim().trim_start_matches("W/").to_string();
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == "*" || bare(t) == etag)
}

/// 304 Not Modified, with the ETag and caching a full answer would carry.
pub(super) fn not_modified_response(etag: &str, cache: &'static str) -> Response {
    let mut r = StatusCode::NOT_MODIFIED.into_response();
    if let Ok(v) = HeaderValue::from_str(etag) {
        r.headers_mut().insert(header::ETAG, v);
    }
    r.headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    r
}

/// A file's answer: its type, length, caching, ETag and file name.
pub(super) fn artifact_response(
    content_type: &'static str,
    etag: &str,
    cache: &'static str,
    name: &str,
    len: u64,
    body: Body,
) -> Response {
    let mut r = Response::new(body);
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    if let Ok(v) = HeaderValue::from_str(etag) {
        h.insert(header::ETAG, v);
    }
    if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"{name}\"")) {
        h.insert(header::CONTENT_DISPOSITION, v);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ask(range: &str, if_range: Option<&str>, len: u64) -> Wanted {
        let mut h = HeaderMap::new();
        h.insert(header::RANGE, HeaderValue::from_str(range).unwrap());
        if let Some(t) = if_range {
            h.insert(header::IF_RANGE, HeaderValue::from_str(t).unwrap());
        }
        wanted(&h, "\"e\"", len)
    }

    #[test]
    fn ranges() {
        assert_eq!(ask("bytes=0-9", None, 100), Wanted::Part(0..10));
        assert_eq!(ask("bytes=90-", None, 100), Wanted::Part(90..100));
        assert_eq!(ask("bytes=90-500", None, 100), Wanted::Part(90..100));
        assert_eq!(ask("bytes=-10", None, 100), Wanted::Part(90..100));
        assert_eq!(ask("bytes=-500", None, 100), Wanted::Part(0..100));
        assert_eq!(ask("bytes=100-", None, 100), Wanted::Unsatisfiable);
        assert_eq!(ask("bytes=-0", None, 100), Wanted::Unsatisfiable);
        assert_eq!(ask("bytes=5-1", None, 100), Wanted::Whole);
        assert_eq!(ask("bytes=0-1,5-6", None, 100), Wanted::Whole);
        assert_eq!(ask("items=0-1", None, 100), Wanted::Whole);
        assert_eq!(ask("bytes=x-1", None, 100), Wanted::Whole);
        assert_eq!(ask("bytes=0-9", Some("\"e\""), 100), Wanted::Part(0..10));
        assert_eq!(ask("bytes=0-9", Some("\"old\""), 100), Wanted::Whole);
        assert_eq!(wanted(&HeaderMap::new(), "\"e\"", 100), Wanted::Whole);
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
}
