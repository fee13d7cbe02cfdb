//! Light calibration from a chrome sphere: one image of a mirror ball per light → the light
//! table (`name, x, y, z[, intensity]`) that `reconstruct` reads.
//!
//! `run` is the calibration: `sphere` finds the balls' outlines (or a given circle or
//! mask is taken), `balls` finds every ball in the frame with it and keeps those the
//! images confirm, `highlight` finds each image's highlight on each ball and its direction
//! through `mirror` (orthographic or pinhole camera), `positions` places near lights where
//! several balls' rays meet, `matte` fits relative intensities from a matte sphere.
//! `circle` and `model` hold the types it takes and gives, `error` its errors, `checks` what it asks
//! of its input and result; `output` writes the tables and, through `draw`, the pictures
//! a person checks it by. Pure functions over decoded planes; `folder` ([`load_dir`],
//! [`read_mask`]) is the only file I/O.
//!
//! With several balls, given or found, the first ball is the one the light table's
//! directions are on and the positions' origin (orthographic): the first circle given or,
//! found, the leftmost ball.
//!
//! Pixel coordinates are 0-based with pixel centres at integers: the first pixel's centre
//! is (0, 0). Directions are in the project's frame (x = column right, y = row down,
//! z towards the camera).

mod balls;
mod checks;
mod circle;
mod draw;
mod environment;
mod error;
mod folder;
mod highlight;
mod matte;
mod mirror;
mod model;
mod output;
mod positions;
mod reading;
mod run;
mod source;
mod sphere;

pub use checks::MIN_SPREAD_DEG;
pub use circle::Circle;
pub use error::CalibrationError;
pub use folder::{NAMES_FILE, SphereFolder, is_ambient, load_dir, load_images, read_mask};
pub use highlight::{Highlight, MAX_BEHIND_DEG};
pub use mirror::{Camera, FOCAL_PX};
pub use model::{Budget, CalibratedLight, Calibration, CircleSource, Settings, Skipped};
pub use positions::LightPosition;
pub use reading::{COARSE_BYTES, CROP_BYTES, FIT_PIXELS, READERS, peak_bytes};
pub use run::calibrate;
pub use source::{ImageFiles, Source, SphereImage};
pub use sphere::{OutlineFit, circle_of_mask, fit_outline};
