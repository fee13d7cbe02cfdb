//! The HTTP side: the router, assembled from each resource's routes, its middleware and
//! the OpenAPI document.

mod app;
mod artifacts;
pub(crate) mod calibrations;
mod events;
mod extract;
pub(crate) mod jobs;
pub(crate) mod middleware;
pub(crate) mod openapi;
pub(crate) mod ops;
mod responses;
mod submission;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request};
use axum::middleware as layer;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_swagger_ui::SwaggerUi;

use super::state::AppState;

/// The `/v1` routes (behind the API key when one is configured).
pub(crate) fn api_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        .merge(jobs::routes())
        .merge(artifacts::routes())
        .merge(events::routes())
        .merge(calibrations::routes())
}

/// Health, readiness, metrics, the OpenAPI document (always open).
pub(crate) fn operations_routes() -> OpenApiRouter<AppState> {
    ops::routes()
}

/// The whole HTTP app over `state`.
pub fn router(state: AppState) -> Router {
    let max_body = usize::try_from(state.config().max_body_bytes).unwrap_or(usize::MAX);
    let api = api_routes().route_layer(layer::from_fn_with_state(
        state.clone(),
        middleware::authenticate,
    ));
    let (app, _) = api.merge(operations_routes()).split_for_parts();
    app.merge(SwaggerUi::new("/docs").config(utoipa_swagger_ui::Config::new(["/openapi.json"])))
        .route("/", axum::routing::get(app::page))
        .route("/app/auth.json", axum::routing::get(app::auth))
        .route("/app/{name}", axum::routing::get(app::asset))
        .fallback(ops::not_found)
        .method_not_allowed_fallback(ops::method_not_allowed)
        .layer(layer::from_fn_with_state(
            state.clone(),
            middleware::track_http,
        ))
        .layer(DefaultBodyLimit::max(max_body))
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(|req: &Request| {
                    let id = req
                        .headers()
                        .get("x-request-id")
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or("-");
                    tracing::info_span!(
                        "request",
                        method = %req.method(),
                        path = %req.uri().path(),
                        request_id = %id
                    )
                })
                .on_response(DefaultOnResponse::new().level(tracing::Level::INFO)),
        )
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        .layer(CatchPanicLayer::custom(ops::panic_response))
        .with_state(state)
}
