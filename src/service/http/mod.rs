//! The HTTP side: `router` merges each resource's routes (`jobs`, `artifacts`, `events`,
//! `calibrations`, `ops`) under the `middleware` and assembles the OpenAPI document
//! (`openapi`); `extract`, `submission` and `responses` are what the resources share, `app`
//! the browser app.

mod app;
mod artifacts;
pub(crate) mod calibrations;
mod events;
mod extract;
pub(crate) mod jobs;
mod middleware;
mod openapi;
mod ops;
mod responses;
mod router;
mod submission;

pub use router::{openapi_json, router};
