//! `points.ply` and `mesh.glb` of a reconstruction's surface.

use std::path::Path;

use crate::core::camera::Pinhole;
use crate::core::commit::Committer;
use crate::core::error::RunError;
use crate::core::mesh::{self, Document, MeshError};
use crate::core::options::MeshOptions;
use crate::core::reconstruction::Reconstruction;

/// `points.ply` and `mesh.glb` of `rec`'s surface (heights, or depth unprojected through
/// `camera`), each when `wanted` takes it; a mask too small to triangulate gives a note in
/// `notes` instead of the mesh. Returns the names written.
pub fn write_geometry(
    rec: &Reconstruction,
    mesh_options: &MeshOptions,
    camera: Option<&Pinhole>,
    wanted: &dyn Fn(&str) -> bool,
    (dir, commits): (&Path, &Committer),
    notes: &mut Vec<String>,
) -> Result<Vec<String>, RunError> {
    let mut written = Vec::new();
    if wanted("points.ply") {
        commits.write(dir, "points.ply", &mut |f| {
            mesh::write_points_ply(f, &rec.heights, &rec.normals, &rec.mask, camera)
        })?;
        written.push("points.ply".to_string());
    }
    if !wanted("mesh.glb") {
        return Ok(written);
    }
    match Document::with_camera(rec, mesh_options, camera) {
        Ok(doc) => {
            commits.write(dir, "mesh.glb", &mut |f| {
                doc.write_glb(f).map_err(|e| match e {
                    MeshError::Write(io) => io,
                    other => std::io::Error::other(other.to_string()),
                })
            })?;
            written.push("mesh.glb".to_string());
        }
        Err(e @ (MeshError::EmptyMask | MeshError::NoTriangles { .. })) => {
            notes.push(format!("no mesh.glb: {e}"))
        }
        Err(e) => {
            return Err(RunError::Output {
                path: dir.join("mesh.glb").display().to_string(),
                reason: e.to_string(),
            });
        }
    }
    Ok(written)
}
