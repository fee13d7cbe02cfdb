//! Near lights (LED domes, inspection rings): each light's direction and irradiance at a
//! pixel follow from where the light is and where the surface point is, so the per-pixel
//! solve and the depth integration alternate until the normals stop moving.

mod alternate;
mod enlarge;
mod maps;
mod model;
mod pieces;
mod pixel;
mod point;
mod refine;
mod run;
mod scale;
mod selection;
mod shrink;
mod solve;
mod surface;

pub use model::{check_cones, irradiance, light_vectors};
pub use pixel::{Fit, fit};
pub use run::{NearReport, peak_bytes, run};
pub use selection::{ARTIFACTS, OPTIONS, check_outputs};
pub use solve::solve;
pub use surface::{COARSE_PIXELS, Iteration, NearSettings, NearSurface};
