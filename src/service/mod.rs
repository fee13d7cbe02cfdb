//! The HTTP service: an axum shell around [`crate::core`].
//!
//! - [`server`]: `photostereo serve`, the listener, signals and shutdown.
//! - [`state`]: [`AppState`], what the handlers share.
//! - `http`: the router, middleware and the OpenAPI document; [`routes`] and `calibrations`
//!   the handlers (typed extractors in, `Result<impl IntoResponse, ApiError>` out),
//!   documented with `#[utoipa::path]`; `events` a job's server-sent event stream.
//! - [`jobs`]: the worker pool that claims and runs reconstructions; `worker` the upkeep.
//! - [`repo`]: job records behind [`repo::JobRepo`] (SQLite, or PostgreSQL).
//! - [`store`]: job inputs and artifacts behind [`store::BlobStore`] (a local directory,
//!   or an S3-compatible object store).
//! - [`error`]: [`ApiError`], every failure as RFC 9457 problem+json.
//! - [`config`]: [`ServeArgs`] (flags + environment) and [`Config`].
//! - [`client`]: the one HTTP/1.1 client (the health check, webhooks, the bench).
//! - `connections`: the accept loop, the connection cap and timeouts.
//!
//! [`router`] is what tests call; [`serve`] is `photostereo serve`.

mod budget;
pub mod client;
pub mod config;
mod connections;
pub mod error;
mod health;
mod http;
mod intake;
mod metrics;
pub mod problem;
pub mod repo;
mod server;
mod slots;
mod state;
pub mod store;
mod tenancy;
mod util;
mod views;
mod worker;

pub use config::{Config, LogFormat, ServeArgs};
pub use error::ApiError;
pub use health::{HealthcheckArgs, healthcheck};
pub use http::openapi::openapi_json;
pub use http::router;
pub use intake::{parse_options, unpack_archive};
pub use problem::Problem;
pub use server::{serve, serve_with};
pub use state::AppState;
