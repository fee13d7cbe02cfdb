//! Near lights (LED domes, inspection rings): each light's direction and irradiance at a
//! pixel follow from where the light is and where the surface point is, so the per-pixel
//! solve and the depth integration alternate until the normals stop moving.

mod intensities;
mod model;
mod pieces;
mod pixel;
mod run;
mod solve;

pub use intensities::Gram;
pub use model::{irradiance, light_vectors};
pub use pixel::{Fit, fit};
pub use run::{NearReport, run};
pub use solve::{Iteration, NearSettings, NearSurface, solve};
