//! The surface as a PLY point cloud, one point per mask pixel.

use std::io::Write;

use ndarray::Array2;

use crate::core::camera::Pinhole;

/// A binary little-endian PLY point cloud: one vertex per mask pixel, in row-major order,
/// with `x, y, z, nx, ny, nz` as floats, all in the project's frame (x right, y down, z
/// towards the camera). Without a camera the point is `(col, row, z)` with `z` the height
/// in pixels; with one, `z` is the depth along the optical axis and the point is
/// `camera.unproject(col, row, z)` (so its z is −depth). Normals are written as given.
pub fn write_points_ply(
    out: &mut dyn Write,
    z: &Array2<f32>,
    normals: &ndarray::Array3<f32>,
    mask: &Array2<bool>,
    camera: Option<&Pinhole>,
) -> std::io::Result<()> {
    let count = mask.iter().filter(|&&m| m).count();
    let frame = match camera {
        None => {
            "orthographic: x = column, y = row (down), z = height in pixels (towards the camera)"
        }
        Some(_) => "camera frame: x right, y down, z towards the camera (z = -depth)",
    };
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment photostereo {}\ncomment {frame}\n\
         element vertex {count}\nproperty float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\nend_header\n",
        env!("CARGO_PKG_VERSION")
    )?;
    let mut row = Vec::with_capacity(mask.ncols() * 24);
    for (r, line) in mask.outer_iter().enumerate() {
        row.clear();
        for (c, _) in line.indexed_iter().filter(|(_, m)| **m) {
            let depth = f64::from(z[[r, c]]);
            let p = match camera {
                None => [c as f64, r as f64, depth],
                Some(k) => k.unproject(c as f64, r as f64, depth),
            };
            let n = [0, 1, 2].map(|k| f64::from(normals[[r, c, k]]));
            for v in p.into_iter().chain(n) {
                row.extend_from_slice(&(v as f32).to_le_bytes());
            }
        }
        out.write_all(&row)?;
    }
    Ok(())
}
