//! The OpenAPI document: paths come from the handlers' `#[utoipa::path]`, collected by
//! `utoipa_axum`'s router; this adds the info, tags, shared schemas and the bearer scheme.

use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::error::Problem;
use super::repo::JobStatus;
use super::routes::{Health, ImageFile, JobList, JobView, ResultSummary};

#[derive(OpenApi)]
#[openapi(
    info(
        title = "photostereo",
        version = "1",
        description = "Photometric stereo reconstruction as a service: upload images of an object lit from known directions, get back albedo, normals, heights, meshes and pictures.\n\nSubmit a job with `POST /v1/jobs` (multipart), poll `GET /v1/jobs/{id}` until it has `succeeded`, then download the artifacts it links. Every error is an RFC 9457 `application/problem+json` body.\n\nWhen the server has API keys configured, every `/v1` route needs `Authorization: Bearer <key>`."
    ),
    components(schemas(Problem, JobStatus, JobView, JobList, ResultSummary, Health, ImageFile)),
    modifiers(&BearerScheme),
    tags(
        (name = "jobs", description = "Reconstruction jobs and their artifacts"),
        (name = "operations", description = "Health, readiness, metrics and this document"),
    )
)]
pub struct ApiDoc;

struct BearerScheme;

impl Modify for BearerScheme {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        openapi.info.license = None;
        if let Some(components) = openapi.components.as_mut() {
            components.add_security_scheme(
                "bearer",
                SecurityScheme::Http(
                    HttpBuilder::new()
                        .scheme(HttpAuthScheme::Bearer)
                        .description(Some(
                            "An API key from the server's --api-key / PHOTOSTEREO_API_KEYS (only when keys are configured)",
                        ))
                        .build(),
                ),
            );
        }
    }
}
