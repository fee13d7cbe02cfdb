//! The artifacts' names: every one a job can write with its Content-Type, the default
//! selections, and which of them a selection and a surface take.

use crate::core::error::InputError;

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
    ("depth.png", "image/png"),
    ("depth.exr", "image/x-exr"),
    ("needle.png", "image/png"),
    ("curl.png", "image/png"),
    ("confidence.png", "image/png"),
    ("unreliable.png", "image/png"),
    ("specular.png", "image/png"),
    ("roughness.png", "image/png"),
    ("shaded.png", "image/png"),
    ("preview.png", "image/png"),
    ("mesh.glb", "model/gltf-binary"),
    ("mesh.gltf", "model/gltf+json"),
    ("points.ply", "application/x-ply"),
    ("lights.json", "application/json"),
    ("result.json", "application/json"),
];

/// What a job writes when its options name no `outputs`: the maps most users fetch, in
/// their most precise lossless form that every viewer opens. The rest (EXRs, the three
/// normal components, needle/curl/unreliable pictures, the preview, `mesh.gltf`) are 95
/// of the 127 MB a 2048² job writes with every artifact, and are written on request.
/// `albedo_rgb.png` is written only for colour inputs, the [`GLOSSY_OUTPUTS`] only by the
/// `glossy` solver; under a camera `height.png` gives way to [`DEFAULT_DEPTH_OUTPUTS`].
pub const DEFAULT_OUTPUTS: &[&str] = &[
    "albedo.png",
    "albedo_rgb.png",
    "mask.png",
    "normal.png",
    "height.png",
    "confidence.png",
    "specular.png",
    "roughness.png",
    "shaded.png",
    "mesh.glb",
    "result.json",
];

/// Added to the default set under a camera: the depth in both forms and the point cloud,
/// what a perspective reconstruction is for.
pub const DEFAULT_DEPTH_OUTPUTS: &[&str] = &["depth.png", "depth.exr", "points.ply"];

/// The `glossy` solver's material maps: specular albedo and GGX roughness (a Beckmann
/// lobe's as the GGX lobe of its width; 0 where the pixel is Lambertian), each 16-bit over
/// [0, 1]; `albedo.png` is then the diffuse albedo.
pub const GLOSSY_OUTPUTS: [&str; 2] = ["specular.png", "roughness.png"];

/// In an `outputs` selection, stands for every artifact.
pub const ALL: &str = "all";

/// Artifacts a run writes when it has them, whatever the selection: `lights.json`, the
/// light table with the intensities a near-light run estimated.
pub const UNSELECTED: [&str; 1] = ["lights.json"];

/// Whether artifact `name` is to be written under the `outputs` selection `selection`
/// (the default set when there is none), for a surface of heights, or of depth when
/// `camera` ([`fits_surface`]); never one of [`UNSELECTED`].
pub fn wanted(selection: Option<&[String]>, name: &str, camera: bool) -> bool {
    let selected = match selection {
        None => DEFAULT_OUTPUTS.contains(&name) || camera && DEFAULT_DEPTH_OUTPUTS.contains(&name),
        Some(names) => names.iter().any(|n| n == name || n == ALL),
    };
    selected && fits_surface(name, camera) && !UNSELECTED.contains(&name)
}

/// Whether artifact `name` exists for a surface of heights (orthographic), or of depth
/// along the optical axis when `camera`: the height pictures for one, the depth pictures
/// for the other.
pub fn fits_surface(name: &str, camera: bool) -> bool {
    match name {
        "height.png" | "height.exr" => !camera,
        "depth.png" | "depth.exr" => camera,
        _ => true,
    }
}

/// Content-Type of an artifact, or None when the name is not one.
pub fn content_type(name: &str) -> Option<&'static str> {
    ARTIFACTS.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// Check an `outputs` selection names only known artifacts.
pub fn check_selection(names: &[String]) -> Result<(), InputError> {
    match names
        .iter()
        .find(|n| *n != ALL && content_type(n).is_none())
    {
        Some(bad) => Err(InputError::Options(format!(
            "unknown output {bad:?}; known: {ALL:?} or {}",
            ARTIFACTS
                .iter()
                .map(|(n, _)| *n)
                .collect::<Vec<_>>()
                .join(", ")
        ))),
        None => Ok(()),
    }
}

/// Whether picture `name` is drawn after the integration: from the heights (or depth), or
/// from the curl, which is formed once the integration's buffers are freed. The others are
/// written while the integration runs.
pub fn after_integration(name: &str) -> bool {
    matches!(
        name,
        "height.png" | "height.exr" | "depth.png" | "depth.exr" | "curl.png"
    )
}
