//! photostereo: photometric stereo reconstruction.
//!
//! [`core`] is the numeric heart (no HTTP, no async): decoded images and options in,
//! albedo, normals, heights, meshes and pictures out. [`service`] is the axum shell
//! around it.

pub mod core;
pub mod service;
