//! Safe retries: `Idempotency-Key` on a creating `POST`. The first request with a key
//! stores its answer (status, body, `Location`) with a hash of what it sent; the same key
//! and the same request from the same tenant within [`WINDOW`] gets that answer again,
//! the same key with a different request is 422. Records live in the repo (they survive a
//! restart), scoped by route (`"jobs"`, and any other creating route that uses this).
//!
//! A route uses it in four steps: [`key_from`] before reading the body, a [`PartHasher`]
//! fed while the body is read,
//! [`Idempotency::idempotent`](crate::service::repo::Idempotency::idempotent) to look for an
//! earlier answer ([`replay`] it), and
//! [`Idempotency::remember`](crate::service::repo::Idempotency::remember) after creating the
//! resource (an earlier answer it returns means a concurrent request with the same key
//! won: undo and replay that one).

use std::time::Duration;

use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

use crate::service::error::ApiError;
use crate::service::repo::Remembered;

/// The request header.
pub const HEADER: &str = "idempotency-key";

/// How long a key's answer is kept and replayed.
pub const WINDOW: Duration = crate::service::config::IDEMPOTENCY_WINDOW;

/// The `Idempotency-Key` of a request, if it sent one: 1 to 255 visible ASCII characters
/// (400 otherwise).
pub fn key_from(headers: &HeaderMap) -> Result<Option<String>, ApiError> {
    let mut values = headers.get_all(HEADER).iter();
    let Some(value) = values.next() else {
        return Ok(None);
    };
    if values.next().is_some() {
        return Err(ApiError::bad_request(
            "send one Idempotency-Key header, not several",
        ));
    }
    let key = value.to_str().unwrap_or_default();
    if !(1..=255).contains(&key.len()) || !key.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(ApiError::bad_request(
            "Idempotency-Key must be 1 to 255 visible ASCII characters (a UUID, say)",
        ));
    }
    Ok(Some(key.to_string()))
}

/// A hash of a multipart request's parts in order: each part's name, file name and
/// bytes. What decides "the same request" for a retry, independent of the multipart
/// boundary a client picks. A no-op when the request has no key.
pub struct PartHasher {
    sha: Option<Sha256>,
    part_bytes: u64,
}

impl PartHasher {
    pub fn new(enabled: bool) -> Self {
        Self {
            sha: enabled.then(Sha256::new),
            part_bytes: 0,
        }
    }

    /// A part starts (the previous one, if any, ends).
    pub fn part(&mut self, name: &str, file_name: Option<&str>) {
        self.end_part();
        if let Some(sha) = &mut self.sha {
            for field in [name, file_name.unwrap_or("")] {
                sha.update((field.len() as u64).to_le_bytes());
                sha.update(field.as_bytes());
            }
            sha.update([u8::from(file_name.is_some())]);
        }
    }

    pub fn update(&mut self, bytes: &[u8]) {
        if let Some(sha) = &mut self.sha {
            sha.update(bytes);
            self.part_bytes += bytes.len() as u64;
        }
    }

    fn end_part(&mut self) {
        if let Some(sha) = &mut self.sha {
            sha.update(self.part_bytes.to_le_bytes());
        }
        self.part_bytes = 0;
    }

    /// The hex digest (None without a key).
    pub fn finish(mut self) -> Option<String> {
        self.end_part();
        self.sha
            .map(|sha| sha.finalize().iter().map(|b| format!("{b:02x}")).collect())
    }
}

/// The earlier answer again, if `body_hash` is the earlier request's; 422 if the key was
/// used for a different request.
pub fn replay(earlier: &Remembered, body_hash: &str) -> Result<Response, ApiError> {
    if earlier.body_hash != body_hash {
        return Err(ApiError::invalid(
            "this Idempotency-Key was used for a different request in the last 24 hours: send a new key for a new request",
        ));
    }
    Ok(answer(earlier))
}

/// A remembered answer as a response (also what the first request sends, so both are
/// byte for byte the same).
pub fn answer(r: &Remembered) -> Response {
    let status = StatusCode::from_u16(r.status).unwrap_or(StatusCode::OK);
    let mut response = (
        status,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        r.body.clone(),
    )
        .into_response();
    if let Some(location) = r
        .location
        .as_deref()
        .and_then(|l| HeaderValue::from_str(l).ok())
    {
        response.headers_mut().insert(header::LOCATION, location);
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (name, file name, chunks)
    type Part<'a> = (&'a str, Option<&'a str>, &'a [&'a [u8]]);

    fn hash(parts: &[Part<'_>]) -> String {
        let mut h = PartHasher::new(true);
        for (name, file, chunks) in parts {
            h.part(name, *file);
            for c in *chunks {
                h.update(c);
            }
        }
        h.finish().unwrap()
    }

    #[test]
    fn the_hash_sees_parts_not_chunks() {
        let a = hash(&[
            ("images", Some("a.png"), &[b"abc", b"def"]),
            ("lights", None, &[b"x"]),
        ]);
        let same = hash(&[
            ("images", Some("a.png"), &[b"abcdef"]),
            ("lights", None, &[b"x"]),
        ]);
        assert_eq!(a, same);
        for other in [
            hash(&[
                ("images", Some("b.png"), &[b"abcdef"]),
                ("lights", None, &[b"x"]),
            ]),
            hash(&[
                ("images", Some("a.png"), &[b"abcde"]),
                ("lights", None, &[b"fx"]),
            ]),
            hash(&[
                ("images", Some("a.png"), &[b"abcdef"]),
                ("lights", Some(""), &[b"x"]),
            ]),
            hash(&[
                ("lights", None, &[b"x"]),
                ("images", Some("a.png"), &[b"abcdef"]),
            ]),
        ] {
            assert_ne!(a, other);
        }
        assert!(PartHasher::new(false).finish().is_none());
    }

    #[test]
    fn keys_are_checked() {
        let mut h = HeaderMap::new();
        assert_eq!(key_from(&h).unwrap(), None);
        h.insert(HEADER, HeaderValue::from_static("retry-1"));
        assert_eq!(key_from(&h).unwrap().as_deref(), Some("retry-1"));
        for bad in ["", "has space"] {
            h.insert(HEADER, HeaderValue::from_static(bad));
            assert_eq!(key_from(&h).unwrap_err().status(), StatusCode::BAD_REQUEST);
        }
        h.insert(HEADER, HeaderValue::from_str(&"k".repeat(256)).unwrap());
        assert!(key_from(&h).is_err());
    }
}
