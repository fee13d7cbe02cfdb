//! The router: each resource's routes merged, the middleware layered over them, and the
//! OpenAPI document they make (served at `/openapi.json`).

use std::sync::OnceLock;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request};
use axum::http::{HeaderValue, header};
use axum::middleware as layer;
use axum::response::{IntoResponse, Response};
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;
use utoipa_swagger_ui::SwaggerUi;

use crate::service::state::AppState;

use super::{app, artifacts, calibrations, events, jobs, middleware, openapi, ops};

/// The `/v1` routes (behind the API key when one is configured).
fn api_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        .merge(jobs::routes())
        .merge(artifacts::routes())
        .merge(events::routes())
        .merge(calibrations::routes())
}

/// Health, readiness, metrics, the OpenAPI document (always open).
fn operations_routes() -> OpenApiRouter<AppState> {
    ops::routes().routes(routes!(openapi_doc))
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

/// The OpenAPI document served at `/openapi.json` (pretty JSON, trailing newline), also
/// what `photostereo openapi` prints and `openapi/openapi.json` holds.
pub fn openapi_json() -> String {
    static DOC: OnceLock<String> = OnceLock::new();
    DOC.get_or_init(|| {
        let mut doc = api_routes().merge(operations_routes()).into_openapi();
        openapi::name_artifacts(&mut doc);
        let mut text = doc
            .to_pretty_json()
            .expect("the OpenAPI document serialises");
        text.push('\n');
        text
    })
    .clone()
}

/// This API's OpenAPI document.
#[utoipa::path(
    get,
    path = "/openapi.json",
    tag = "operations",
    responses((status = 200, description = "OpenAPI 3.1 document", content_type = "application/json"))
)]
pub async fn openapi_doc() -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        openapi_json(),
    )
        .into_response()
}
