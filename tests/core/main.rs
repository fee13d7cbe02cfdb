//! The core as a library, one module per subject: accuracy of the solvers and integrators
//! against rendered scenes and the seed's real data, light calibration, `.lp` tables, near
//! lights, meshes, intake errors, cancellation, and property tests of the parsers.
//!
//! `cargo test --release --test core` runs them; `cargo test --release --test core glossy::`
//! one module's.

#[path = "../common/mod.rs"]
mod common;
#[path = "../seed/mod.rs"]
mod seed;

mod accuracy;
mod calibrate;
mod defaults;
mod depth_real;
mod depth_steps;
mod glossy;
mod intake_errors;
mod lp;
mod mesh;
mod near_lights;
mod props;
mod real_chrome;
mod robust;
mod run_control;
