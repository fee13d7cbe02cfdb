//! Encoders: PNG/EXR pictures of a reconstruction and `result.json`.

/// Every artifact a job can produce: file name and Content-Type.
pub const ARTIFACTS: &[(&str, &str)] = &[
    ("albedo.png", "image/png"),
    ("albedo_rgb.png", "image/png"),
    ("mask.png", "image/png"),
    ("normal.png", "image/png"),
    ("normal_x.png", "image/png"),
    ("normal_y.png", "image/png"),
    ("normal_z.png", "image/png"),
    ("height.png", "image/png"),
    ("normal.exr", "image/x-exr"),
    ("height.exr", "image/x-exr"),
    ("needle.png", "image/png"),
    ("curl.png", "image/png"),
    ("shaded.png", "image/png"),
    ("preview.png", "image/png"),
    ("mesh.glb", "model/gltf-binary"),
    ("mesh.gltf", "model/gltf+json"),
    ("result.json", "application/json"),
];

/// Content-Type of an artifact, or None when the name is not one.
pub fn content_type(name: &str) -> Option<&'static str> {
    ARTIFACTS.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// Re-shade a finished job's outputs (`albedo.png`, `normal.exr` in `dir`) under `light`
/// and encode the picture as an 8-bit PNG.
pub fn shaded_png_from_dir(
    dir: &std::path::Path,
    light: [f64; 3],
) -> Result<Vec<u8>, super::InputError> {
    let _ = (dir, light);
    todo!("outputs under construction")
}
