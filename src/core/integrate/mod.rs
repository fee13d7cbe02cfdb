//! Heights from normals: gradients `p = −nx/nz`, `q = −ny/nz`, then one of several
//! integrators.
//!
//! Frame: arrays are `[row, col]`; x = column (right), y = row (down), z towards the camera.
//! `p = dz/dx` (along columns), `q = dz/dy` (along rows); heights are in pixel units.
//!
//! Discretisation of `poisson` (and of [`curl`]): the height difference across the edge
//! between two 4-adjacent pixels is the slope of the mean of their two normals — the two
//! gradient samples averaged with weights `n_z` (`poisson::edge_slope`). On gentle slopes
//! that is the trapezoidal rule (`z[r][c+1] − z[r][c] = (p[r][c] + p[r][c+1]) / 2`, which
//! `frankot-chellappa` uses in its spectral form); near a silhouette, where `p ~ 1/n_z`
//! grows without bound, the plain mean overshoots by pixels per edge while the mean normal
//! gives the chord of the local circle. Both are second-order accurate where the one-sided
//! `path` rule is first-order.
//!
//! | method | domain | solver | cost |
//! |---|---|---|---|
//! | `path` | mask, one path per pixel | running sums (the seed's) | O(N), poor |
//! | `frankot-chellappa` | full periodic frame, 0 off mask | FFT projection | O(N log N) |
//! | `poisson` | mask only (Neumann) | DCT on a full mask, else multigrid-PCG | ≈ O(N) |
//!
//! `gradients` forms the slopes and their curl; `methods` holds the entry points that run
//! each method: `path`, `fourier` (Frankot–Chellappa), `poisson` over `multigrid`, the
//! Cauchy re-weighting of `robust_poisson`, and `bilateral` (on the mask's bounding box,
//! `crop`); `components` are the mask's connected pieces, and `perspective` the
//! log-depth gradients under a pinhole camera.

mod bilateral;
mod components;
mod crop;
mod fourier;
mod gradients;
mod methods;
mod multigrid;
mod path;
pub mod perspective;
mod poisson;
mod robust_poisson;

pub use bilateral::Cuts;
pub use gradients::{MIN_NZ, curl, gradients};
pub use methods::{
    Given, LogDepth, integrate, integrate_log_depth, integrate_until, integrate_weighted,
    integrate_with_confidence,
};
pub use multigrid::MIN_EDGE_WEIGHT;

#[cfg(test)]
mod tests;
