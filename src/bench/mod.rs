//! `photostereo bench`: render synthetic sets, time the core and (optionally) the HTTP
//! service on them in this one process, and print the figures as Markdown tables next to
//! the project's performance targets.
//!
//! Everything lives in a temporary directory that is removed at the end (also on errors).
//! The HTTP side is a small HTTP/1.1 client written here on `tokio::net::TcpStream`
//! (multipart uploads streamed from disk, keep-alive status requests); it only ever talks
//! to its own server on 127.0.0.1 (in this process, or a child process for `--hostile`),
//! and every network wait has a timeout.
//!
//! The module reads downward: [`run`] picks the mode and runs it in a [`temp_dir`],
//! [`args`] holds the flags, [`sets`] renders the image sets,
//! [`timing`] times the core jobs on them (and measures their memory through [`memory`]),
//! [`http`] drives the in-process server with the small client in [`client`], [`sweep`]
//! runs the light-count sweep in child processes, [`integrators`] times the integrators
//! alone on normal maps, [`calibration`] times a chrome-ball calibration of camera-sized
//! images, [`near`] times a near-light job against the distant one on the same images,
//! [`hostile`] probes a `serve` child process
//! ([`child`]) with [`probe`] under hostile loads, and [`tables`] prints what was measured;
//! [`stats`] holds the medians and percentiles they share, [`machine`] says what they
//! were measured on.

mod args;
mod calibration;
mod child;
mod client;
mod hostile;
mod http;
mod integrators;
mod machine;
mod memory;
mod near;
mod probe;
mod run;
mod sets;
mod stats;
mod sweep;
mod tables;
mod temp_dir;
mod timing;

pub use args::BenchArgs;
pub use run::run;
