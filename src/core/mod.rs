//! The reconstruction core: intake → solve → mask → integrate → outputs / mesh.
//!
//! Every stage is a plain function over owned or borrowed arrays; only `intake` and
//! `outputs` touch files or bytes.

// First: its macro is used by the modules after it.
#[macro_use]
mod simd;

pub mod commit;
pub mod error;
pub mod intake;
pub mod integrate;
pub mod lights;
pub mod mask;
pub mod mesh;
pub mod metrics;
pub mod options;
pub mod outputs;
pub mod pipeline;
pub mod preview;
pub mod render;
pub mod robust;
pub mod solve;
pub mod synth;

pub use error::InputError;
pub use options::Options;
pub use pipeline::{Reconstruction, RunToEnd, reconstruct};
