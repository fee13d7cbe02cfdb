//! The HTTP side: the router, assembled from each resource's routes, its middleware and
//! the OpenAPI document.

pub(crate) mod middleware;
pub(crate) mod openapi;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request};
use axum::middleware as layer;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;
use utoipa_swagger_ui::SwaggerUi;

use super::state::AppState;
use super::{app, calibrations, events, routes};

/// The `/v1` routes (behind the API key when one is configured).
pub(crate) fn api_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        .routes(routes!(routes::create_job, routes::list_jobs))
        .routes(routes!(routes::get_job, routes::delete_job))
        .routes(routes!(routes::get_artifact))
        .routes(routes!(events::job_events))
        .routes(routes!(
            calibrations::create_calibration,
            calibrations::list_calibrations
        ))
        .routes(routes!(
            calibrations::get_calibration,
            calibrations::delete_calibration
        ))
        .routes(routes!(calibrations::get_lights_csv))
        .routes(routes!(calibrations::get_overlay))
        .routes(routes!(calibrations::get_lights_png))
        .routes(routes!(calibrations::get_positions_csv))
}

/// Health, readiness, metrics, the OpenAPI document (always open).
pub(crate) fn operations_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::default()
        .routes(routes!(routes::healthz))
        .routes(routes!(routes::readyz))
        .routes(routes!(routes::metrics))
        .routes(routes!(routes::openapi_doc))
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
        .fallback(routes::not_found)
        .method_not_allowed_fallback(routes::method_not_allowed)
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
        .layer(CatchPanicLayer::custom(routes::panic_response))
        .with_state(state)
}
