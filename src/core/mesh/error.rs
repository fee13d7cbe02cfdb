//! Why no mesh could be made: an empty mask, no triangles at the step, arrays of the
//! wrong size, non-finite heights, options, size, or the texture, JSON or writer failing.

/// Why no mesh could be made.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("the mask is empty: no mesh")]
    EmptyMask,
    #[error(
        "no three neighbouring mask pixels at grid step {step}: no mesh \
         (lower the step or raise max_vertices)"
    )]
    NoTriangles { step: usize },
    #[error("the reconstruction's {array} array does not match its {width}×{height} size")]
    Shape {
        array: &'static str,
        width: usize,
        height: usize,
    },
    #[error("the height at row {row}, column {col} is not finite")]
    NonFinite { row: usize, col: usize },
    #[error("invalid mesh options: {0}")]
    Options(&'static str),
    #[error("the mesh needs {bytes} bytes, more than a GLB file can hold")]
    TooLarge { bytes: usize },
    #[error("encoding the albedo texture: {0}")]
    Texture(String),
    #[error("encoding the glTF JSON: {0}")]
    Json(String),
    #[error("writing the mesh: {0}")]
    Write(#[from] std::io::Error),
}
