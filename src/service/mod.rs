//! The HTTP service: an axum shell around [`crate::core`], one concern a folder (see
//! `docs/architecture.md`, "The service").
//!
//! - `server`: `photostereo serve` ([`serve`], [`serve_with`]): the listener, signals and
//!   shutdown; `connections` the accept loop, the connection cap and timeouts.
//! - `http`: the [`router`], each resource's routes, the middleware and the OpenAPI
//!   document ([`openapi_json`]).
//! - `intake`: a submission's body read and checked as it streams.
//! - `state`: [`AppState`], what the handlers share.
//! - `tenancy`: API keys and tenants, quotas, `Idempotency-Key` answers.
//! - `worker`: the `Runner` that claims and runs jobs, with no HTTP types.
//! - [`repo`]: job records behind [`repo::JobRepo`] (SQLite, or PostgreSQL).
//! - [`store`]: job inputs and artifacts behind [`store::BlobStore`] (a local directory,
//!   or an S3-compatible object store).
//! - [`error`]: [`ApiError`], every failure as RFC 9457 problem+json.
//! - [`config`]: [`ServeArgs`] (flags + environment) and [`Config`].
//! - [`client`]: the one HTTP/1.1 client (the health check, webhooks, the bench).

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
pub use http::openapi_json;
pub use http::router;
pub use intake::{parse_options, unpack_archive};
pub use problem::Problem;
pub use server::{serve, serve_with};
pub use state::AppState;
