//! The scenes the project renders for `res/` and its tests: analytic surfaces with exact
//! normals, depth and albedo (gray or RGB), lit by distant point or area lights of given
//! colours, with cast shadows, one bounce of interreflection, Lambertian or Oren–Nayar
//! diffuse, specular lobes (Blinn–Phong, GGX Cook–Torrance, Ward; tinted for metals) and
//! a camera with exposure, black level, shot and read noise, clipping and quantisation;
//! the glossy catalogue ([`glossy_catalogue`]); and perspective scenes with depth steps
//! ([`depth_scenes`]).
//!
//! `capture` says how a capture departs from the ideal, `lights` lays out the lights, and
//! `catalogue` is the sets written into `res/`.

mod brdf;
mod capture;
mod catalogue;
mod chrome;
mod depth_scenes;
mod glossy_scenes;
mod lights;
mod near_rigs;
mod render;
mod scene;
mod sensor;
#[cfg(test)]
mod tests;
mod transport;
mod write;

pub use brdf::{Diffuse, Specular};
pub use capture::Capture;
pub use catalogue::{catalogue, chrome_catalogue, glossy_coat};
pub use chrome::{ChromeSet, RoomLight, matte_intensities};
pub use depth_scenes::{DepthScene, depth_scenes, ortho_step_plate, sphere_in_front, step_plate};
pub use glossy_scenes::{Gloss, GlossyScene, glossy_catalogue};
pub use lights::{light_colours, light_grid, light_rings};
pub use near_rigs::{
    NOISE_SIGMA, NearRig, close_ring, dome_sphere, far_ring, ring_relief, ring_relief_of,
};
pub use render::{Rendered, render, render_rgb};
pub use scene::Scene;
pub use sensor::Exposure;
pub use transport::AreaLight;
pub use write::{Truth, read_truth, write_set};
