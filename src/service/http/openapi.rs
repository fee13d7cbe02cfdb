//! The OpenAPI document: paths come from the handlers' `#[utoipa::path]`, collected by
//! `utoipa_axum`'s router; this adds the info, tags, shared schemas, the bearer scheme and
//! the artifact names.

use utoipa::openapi::schema::{ArrayItems, Object, Schema, Type};
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::openapi::{ObjectBuilder, RefOr};

use utoipa::{Modify, OpenApi};

use crate::core::camera::Pinhole;
use crate::core::normalmap::{Convention, Counts};
use crate::core::outputs::{ALL, ARTIFACTS};

use super::calibrations::{
    CalibrationList, CalibrationView, CircleView, HighlightView, LightView, Measured,
    MoreHighlightView, PositionView, SkippedView,
};
use super::jobs::{ImageFile, JobList};
use super::ops::Health;
use crate::service::problem::Problem;
use crate::service::repo::JobStatus;
use crate::service::views::{JobView, ResultSummary};

#[derive(OpenApi)]
#[openapi(
    info(
        title = "photostereo",
        version = "1",
        description = "Photometric stereo reconstruction as a service: upload images of an object lit from known directions, get back albedo, normals, heights, meshes and pictures.\n\nSubmit a job with `POST /v1/jobs` (multipart), poll `GET /v1/jobs/{id}` until it has `succeeded`, then download the artifacts it links. A normal map made elsewhere is integrated the same way: send it as the job's `normals` part instead of images and lights. Lights can be measured first: `POST /v1/calibrations` with one chrome-sphere image per light, then give the calibration's id as the job's `calibration` part. Every error is an RFC 9457 `application/problem+json` body.\n\nWhen the server has API keys configured, every `/v1` route needs `Authorization: Bearer <key>`. Each key belongs to a tenant: a tenant sees and manages only its own jobs (another tenant's job is answered exactly like one that does not exist, 404), and a key with the admin role sees all. Each tenant has quotas (jobs queued or running, submissions per minute, stored bytes), answered with 429 and Retry-After; the queue serves tenants in turn."
    ),
    components(schemas(
        Problem,
        Pinhole,
        Convention,
        Counts,
        JobStatus,
        JobView,
        JobList,
        ResultSummary,
        Health,
        ImageFile,
        CalibrationView,
        CalibrationList,
        Measured,
        CircleView,
        LightView,
        HighlightView,
        MoreHighlightView,
        PositionView,
        SkippedView
    )),
    modifiers(&BearerScheme),
    tags(
        (name = "jobs", description = "Reconstruction jobs and their artifacts"),
        (name = "calibrations", description = "Light calibrations from a chrome sphere, for jobs to use instead of a light table"),
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
                            "An API key from the server's --api-key (tenant:secret) or --api-keys-file (tenant secret [role]); only when keys are configured. The key decides the tenant whose jobs the request sees; the admin role sees all.",
                        ))
                        .build(),
                ),
            );
        }
    }
}

/// Artifact names as enums, from [`ARTIFACTS`] (one list for the code and the spec): the
/// download route's `name` and the items of `Options.outputs` (which also take `"all"`).
/// Applied to the whole document, after the routes' paths are merged into it.
pub(super) fn name_artifacts(doc: &mut utoipa::openapi::OpenApi) {
    let names = || ARTIFACTS.iter().map(|(n, _)| *n);
    let strings = |names: Vec<&str>| -> RefOr<Schema> {
        ObjectBuilder::new()
            .schema_type(Type::String)
            .enum_values(Some(names))
            .into()
    };
    let download = doc
        .paths
        .paths
        .get_mut("/v1/jobs/{id}/artifacts/{name}")
        .and_then(|p| p.get.as_mut())
        .and_then(|op| op.parameters.as_mut());
    for p in download.into_iter().flatten() {
        if let RefOr::T(p) = p
            && p.name == "name"
        {
            p.schema = Some(strings(names().collect()));
        }
    }
    let options = doc
        .components
        .as_mut()
        .and_then(|c| c.schemas.get_mut("Options"));
    if let Some(RefOr::T(Schema::Object(Object { properties, .. }))) = options
        && let Some(RefOr::T(Schema::Array(outputs))) = properties.get_mut("outputs")
    {
        outputs.items = ArrayItems::RefOrSchema(Box::new(strings(names().chain([ALL]).collect())));
    }
}
