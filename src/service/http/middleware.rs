//! The middleware: the API key check on the `/v1` routes, and the request metrics.

use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::service::error::ApiError;
use crate::service::intake::tap::{BodyTap, LINGER};
use crate::service::state::AppState;
use crate::service::tenancy::Caller;

/// `Authorization: Bearer <key>` on the /v1 routes when keys are configured: the key's
/// [`Caller`] goes into the request's extensions. With no keys, every caller is
/// [`Caller::open`].
pub(crate) async fn authenticate(
    State(state): State<AppState>,
    mut req: Request,
    next: Next,
) -> Response {
    // Which of two keys would count is ambiguous between proxies and servers: refuse both.
    if req
        .headers()
        .get_all(header::AUTHORIZATION)
        .iter()
        .nth(1)
        .is_some()
    {
        let tap = BodyTap::new(req.into_body(), state.config().max_body_bytes);
        tokio::spawn(async move { tap.drain(LINGER).await });
        return ApiError::bad_request("send one Authorization header, not several").into_response();
    }
    let keys = state.keys();
    if keys.is_open() {
        req.extensions_mut().insert(Caller::open());
        return next.run(req).await;
    }
    let presented = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            let (scheme, key) = v.trim().split_once(' ')?;
            scheme
                .eq_ignore_ascii_case("bearer")
                .then(|| key.trim().to_string())
        });
    let Some(presented) = presented else {
        return refuse_unauthorized(
            &state,
            req,
            "this server needs an API key: send Authorization: Bearer <key>",
        );
    };
    match keys.find(&presented) {
        Some(caller) => {
            req.extensions_mut().insert(caller);
            next.run(req).await
        }
        None => refuse_unauthorized(&state, req, "the API key is not valid"),
    }
}

/// 401, reading what the client is still uploading in the background (bounded by the body
/// limit and [`LINGER`]) so that it sees the answer rather than a broken pipe.
fn refuse_unauthorized(state: &AppState, req: Request, detail: &str) -> Response {
    let tap = BodyTap::new(req.into_body(), state.config().max_body_bytes);
    tokio::spawn(async move { tap.drain(LINGER).await });
    ApiError::unauthorized(detail).into_response()
}

/// Count requests by method, route template and status.
pub(crate) async fn track_http(
    State(state): State<AppState>,
    req: Request,
    next: Next,
) -> Response {
    const METHODS: [&str; 7] = ["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"];
    let method = req.method().as_str();
    let method = METHODS
        .iter()
        .find(|m| **m == method)
        .copied()
        .unwrap_or("other");
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_string())
        .unwrap_or_else(|| "unmatched".to_string());
    let started = Instant::now();
    let response = next.run(req).await;
    state.metrics().observe_http(
        method,
        &route,
        response.status().as_u16(),
        started.elapsed(),
    );
    response
}
