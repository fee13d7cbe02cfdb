//! The reconstruction core: intake → solve → mask → integrate → outputs / mesh.
//!
//! Every stage is a plain function over owned or borrowed arrays; only `intake`,
//! `outputs` and `commit` (and `synth`, which writes the rendered sets, `calibrate`'s
//! folder and mask readers, `normalmap`'s reader and `normals_in`, which writes what it
//! integrated) touch files or bytes.

// First: its macro is used by the modules after it.
#[macro_use]
mod simd;

mod arrays;
pub mod bands;
pub mod calibrate;
pub mod camera;
pub mod commit;
pub mod error;
pub mod heap;
mod histogram;
pub mod holdout;
pub mod intake;
pub mod integrate;
pub mod intensities;
pub mod lambert;
pub mod layout;
pub mod lights;
pub mod mask;
pub mod mesh;
pub mod metrics;
pub mod near;
pub mod normalmap;
pub mod normals_in;
pub mod options;
pub mod outputs;
pub mod pipeline;
pub mod preview;
pub mod progress;
pub mod reconstruction;
pub mod reflectance;
pub mod render;
pub mod robust;
pub mod solve;
pub mod stream;
pub mod synth;
mod vec3;

pub use error::{InputError, RunError};
pub use options::Options;
pub use pipeline::reconstruct;
pub use progress::RunToEnd;
pub use reconstruction::Reconstruction;
