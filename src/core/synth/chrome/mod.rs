//! Light-calibration captures: chrome (mirror) spheres photographed once per light by an
//! orthographic camera (or a pinhole, [`ChromeSet::camera_distance`]), and a matte white
//! sphere under the same lights.
//!
//! Each pixel integrates what the ball reflects over its footprint (`SUPERSAMPLE`²
//! samples), so a light of finite angular size leaves a highlight with a real, finite
//! shape: round near the ball's centre, squeezed towards the rim. The environment is a dim
//! room, the light (a disc of `light_radius_deg`, or a small sphere at a 3-D position),
//! static room lights, a bright diffuse object beside the ball and a thin streak from
//! another fixture; with several balls each also mirrors the others. Outside the balls, a
//! textured backdrop (stripes and a checkerboard) lit by the same light.
//!
//! Frame: x = column right, y = row down, z towards the camera, in pixels; the image
//! plane z = 0 passes through every ball's centre. A pinhole camera sits on the axis
//! through the image centre at `camera_distance` above that plane, with that focal length
//! in pixels, so the plane is imaged one unit a pixel and the balls' centres where they
//! are; their outlines are then a little larger, and ellipses off the axis.
//!
//! `set` holds the types ([`ChromeSet`], [`RoomLight`]), the usual capture and its
//! variants; `render` draws a capture's images, `write` writes them with their truth.

mod render;
mod set;
#[cfg(test)]
mod tests;
mod write;

pub use set::{ChromeSet, RoomLight, matte_intensities};
