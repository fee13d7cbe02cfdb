//! The work done away from requests, with no HTTP types: a [`Runner`] (`runner`) holds
//! the config, the repo, the store and the worker pool (`pool`), and `start` opens it;
//! `run` is a worker thread and the run of one job, `upkeep` the recovery at start and the background loop (heartbeat, reaper,
//! retention sweep), `prefetch` the images decoded during uploads, `webhooks` the
//! deliveries of jobs' ends. A job's [`Failure`] becomes its record's problem through the
//! [`Render`] the runner is given.

mod failure;
mod pool;
mod prefetch;
mod run;
mod runner;
mod start;
mod upkeep;
pub(crate) mod webhooks;

pub use failure::Failure;
pub use pool::Workers;
pub(crate) use prefetch::Prefetch;
pub(crate) use run::near_rig;
pub use runner::{Render, Runner};
