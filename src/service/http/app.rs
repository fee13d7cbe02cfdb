//! The browser app at `/`: static files compiled into the binary (no build step, nothing
//! fetched from elsewhere), served with their content types, an ETag (revalidated on every
//! load, so a new binary's files are never mixed with cached old ones) and a strict
//! Content-Security-Policy the app satisfies: no inline script or style, same-origin
//! requests only, images only from the server or the app's own blob URLs.

use axum::Json;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::responses::not_modified;
use crate::service::error::ApiError;
use crate::service::state::AppState;
use crate::service::util::strong_etag;

/// name, content type, bytes.
const FILES: &[(&str, &str, &str)] = &[
    (
        "index.html",
        "text/html; charset=utf-8",
        include_str!("app/index.html"),
    ),
    (
        "app.js",
        "text/javascript; charset=utf-8",
        include_str!("app/app.js"),
    ),
    (
        "app.css",
        "text/css; charset=utf-8",
        include_str!("app/app.css"),
    ),
    (
        "api.js",
        "text/javascript; charset=utf-8",
        include_str!("app/api.js"),
    ),
    (
        "form.js",
        "text/javascript; charset=utf-8",
        include_str!("app/form.js"),
    ),
    (
        "maps.js",
        "text/javascript; charset=utf-8",
        include_str!("app/maps.js"),
    ),
    (
        "gl.js",
        "text/javascript; charset=utf-8",
        include_str!("app/gl.js"),
    ),
    (
        "relight.js",
        "text/javascript; charset=utf-8",
        include_str!("app/relight.js"),
    ),
    (
        "mesh.js",
        "text/javascript; charset=utf-8",
        include_str!("app/mesh.js"),
    ),
];

const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
    img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; form-action 'none'; \
    frame-ancestors 'none'";

/// `GET /`: the app's page.
pub async fn page(headers: HeaderMap) -> Response {
    serve("index.html", &headers).unwrap_or_else(IntoResponse::into_response)
}

/// `GET /app/auth.json`: `{"api_key_required": bool}`, so that the page asks for a key
/// before its first API call instead of provoking a 401 (which browsers log as an error).
/// It tells no more than any 401 does.
pub async fn auth(State(state): State<AppState>) -> Response {
    let mut r =
        Json(serde_json::json!({ "api_key_required": !state.keys().is_open() })).into_response();
    r.headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

/// `GET /app/{name}`: the page's script and style sheet.
pub async fn asset(Path(name): Path<String>, headers: HeaderMap) -> Response {
    serve(&name, &headers).unwrap_or_else(IntoResponse::into_response)
}

fn serve(name: &str, headers: &HeaderMap) -> Result<Response, ApiError> {
    let Some((_, content_type, text)) = FILES.iter().find(|(n, _, _)| *n == name) else {
        return Err(ApiError::not_found(format!(
            "there is no app file {name:?}"
        )));
    };
    let etag = strong_etag(crc32fast::hash(text.as_bytes()), text.len() as u64);
    let mut r = if not_modified(headers, &etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, *content_type)], *text).into_response()
    };
    let h = r.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    Ok(r)
}
