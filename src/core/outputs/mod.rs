//! Encoders: the PNG/EXR pictures of a reconstruction and `result.json`, written in
//! parallel, each under a temporary name and renamed once complete.

mod encoding;
mod geometry;
mod names;
mod pictures;
mod reshade;
#[cfg(test)]
mod tests;

pub use encoding::{decode_height_exr, decode_png16, png_bytes, png_bytes_filtered, png_to};
pub use geometry::write_geometry;
pub use names::{
    ALL, ARTIFACTS, DEFAULT_DEPTH_OUTPUTS, DEFAULT_OUTPUTS, GLOSSY_OUTPUTS, UNSELECTED,
    after_integration, check_selection, content_type, fits_surface, wanted,
};
pub use pictures::{Heights, Maps, applies, encode, encode_to, write_pictures};
pub use reshade::{shaded_png_capacity, shaded_png_from_dir};
