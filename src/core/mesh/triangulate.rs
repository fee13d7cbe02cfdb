//! The mesh's geometry: the grid step that keeps the vertex count under its cap, one
//! vertex per sampled mask pixel (a height, or a depth unprojected through the camera),
//! triangles where all their corners are vertices, and the vertex normals.

use ndarray::{Array2, s};

use super::error::MeshError;
use crate::core::camera::Pinhole;
use crate::core::options::{MeshNormals, MeshOptions};
use crate::core::reconstruction::Reconstruction;
use crate::core::vec3::sub;

/// A triangulated, decimated height map in glTF's frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TriMesh {
    /// Grid step in pixels: vertices sit on every `step`-th row and column.
    pub step: usize,
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals.
    pub normals: Vec<[f32; 3]>,
    /// Texture coordinates of the vertices' pixel centres (glTF's origin is top-left).
    pub uvs: Vec<[f32; 2]>,
    /// Source pixel `[row, col]` of each vertex.
    pub pixels: Vec<[u32; 2]>,
    /// Counter-clockwise seen from +z, so front faces look at the viewer.
    pub triangles: Vec<[u32; 3]>,
}

/// No vertex at this grid point.
const NONE: u32 = u32::MAX;

/// The grid step: the smallest step ≥ `min_step` (and ≥ 1) at which at most
/// `max_vertices` mask pixels are sampled. Counts only the sampled pixels at each
/// candidate step, never building anything at full resolution.
pub fn grid_step(mask: &Array2<bool>, max_vertices: usize, min_step: usize) -> usize {
    let (h, w) = mask.dim();
    let limit = max_vertices.min(NONE as usize - 1);
    let mut step = min_step.max(1);
    // From max(h, w) on only pixel (0, 0) is sampled: stepping further changes nothing.
    while step < h.max(w) && sampled(mask, step) > limit {
        step += 1;
    }
    step
}

fn sampled(mask: &Array2<bool>, step: usize) -> usize {
    let st = step as isize;
    mask.slice(s![..;st, ..;st]).iter().filter(|&&m| m).count()
}

/// Sample, triangulate and shade the height map (see the module docs for the frame).
pub fn triangulate(rec: &Reconstruction, opts: &MeshOptions) -> Result<TriMesh, MeshError> {
    triangulate_with(rec, opts, None)
}

/// [`triangulate`], or with a camera: `rec.heights` are depths and each vertex is its
/// pixel's camera-frame point, y flipped (module docs).
pub fn triangulate_with(
    rec: &Reconstruction,
    opts: &MeshOptions,
    camera: Option<&Pinhole>,
) -> Result<TriMesh, MeshError> {
    check_shapes(rec)?;
    let unit = opts.pixel_size.unwrap_or(1.0);
    if !(unit.is_finite() && unit > 0.0) {
        return Err(MeshError::Options("pixel_size must be positive and finite"));
    }
    if !opts.height_scale.is_finite() {
        return Err(MeshError::Options("height_scale must be finite"));
    }
    if !rec.mask.iter().any(|&m| m) {
        return Err(MeshError::EmptyMask);
    }
    let (h, w) = rec.mask.dim();
    let step = grid_step(&rec.mask, opts.max_vertices, opts.step.unwrap_or(1));
    let (gh, gw) = (h.div_ceil(step), w.div_ceil(step));
    let zunit = f64::from(opts.height_scale) * unit;
    let mut m = TriMesh {
        step,
        positions: Vec::new(),
        normals: Vec::new(),
        uvs: Vec::new(),
        pixels: Vec::new(),
        triangles: Vec::new(),
    };
    // Vertex index per grid point: decimated size, nothing is built at full resolution.
    let mut index = vec![NONE; gh * gw];
    for (gi, r) in (0..h).step_by(step).enumerate() {
        for (gj, c) in (0..w).step_by(step).enumerate() {
            if !rec.mask[[r, c]] {
                continue;
            }
            let z = rec.heights[[r, c]];
            if !z.is_finite() {
                return Err(MeshError::NonFinite { row: r, col: c });
            }
            index[gi * gw + gj] = m.positions.len() as u32;
            let (x, y) = (c as f64, r as f64);
            m.positions.push(match camera {
                None => [
                    (x * unit) as f32,
                    (-y * unit) as f32,
                    (f64::from(z) * zunit) as f32,
                ],
                Some(k) => {
                    let [px, py, pz] = k.unproject(x, y, f64::from(z));
                    [px as f32, -py as f32, pz as f32]
                }
            });
            m.uvs
                .push([((x + 0.5) / w as f64) as f32, ((y + 0.5) / h as f64) as f32]);
            m.pixels.push([r as u32, c as u32]);
        }
    }
    for gi in 1..gh {
        for gj in 1..gw {
            let at = |i: usize, j: usize| index[i * gw + j];
            let cell = cell_triangles(
                at(gi - 1, gj - 1),
                at(gi - 1, gj),
                at(gi, gj - 1),
                at(gi, gj),
            );
            m.triangles.extend(cell.into_iter().flatten());
        }
    }
    if m.triangles.is_empty() {
        return Err(MeshError::NoTriangles { step });
    }
    let normals = match opts.normals {
        MeshNormals::Geometric => geometric_normals(&m.positions, &m.triangles),
        MeshNormals::Photometric => {
            // A normal relief scaled by s in z has normal ∝ (s·nx, s·ny, nz); rows run
            // down, so y flips. Unusable normals fall back to the geometric ones.
            let stretch = match camera {
                None => f64::from(opts.height_scale),
                Some(_) => 1.0,
            };
            let mut fallback: Option<Vec<[f32; 3]>> = None;
            (m.pixels.iter().enumerate())
                .map(|(i, &[r, c])| {
                    let n = rec.normals.slice(s![r as usize, c as usize, ..]);
                    let [nx, ny, nz] = [n[0], n[1], n[2]].map(f64::from);
                    normalize([stretch * nx, -stretch * ny, nz]).unwrap_or_else(|| {
                        fallback
                            .get_or_insert_with(|| geometric_normals(&m.positions, &m.triangles))[i]
                    })
                })
                .collect()
        }
    };
    m.normals = normals;
    Ok(m)
}

/// A grid cell's triangles (corners top-left, top-right, bottom-left, bottom-right),
/// counter-clockwise seen from +z once rows run along −y: both halves of the TR–BL
/// diagonal when all four corners exist, else the one triangle that three corners span.
fn cell_triangles(tl: u32, tr: u32, bl: u32, br: u32) -> [Option<[u32; 3]>; 2] {
    match [tl, tr, bl, br].map(|v| v != NONE) {
        [true, true, true, true] => [Some([tl, bl, tr]), Some([tr, bl, br])],
        [false, true, true, true] => [Some([tr, bl, br]), None],
        [true, false, true, true] => [Some([tl, bl, br]), None],
        [true, true, false, true] => [Some([tl, br, tr]), None],
        [true, true, true, false] => [Some([tl, bl, tr]), None],
        _ => [None, None],
    }
}

/// Area-weighted normals of the triangulated surface; +z for a vertex in no triangle.
fn geometric_normals(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> Vec<[f32; 3]> {
    let mut acc = vec![[0.0f64; 3]; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| positions[i as usize].map(f64::from));
        let (u, v) = (sub(b, a), sub(c, a));
        // |u × v| is twice the area: summing it weights by area.
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        for &i in t {
            for k in 0..3 {
                acc[i as usize][k] += n[k];
            }
        }
    }
    acc.into_iter()
        .map(|n| normalize(n).unwrap_or([0.0, 0.0, 1.0]))
        .collect()
}

fn normalize(v: [f64; 3]) -> Option<[f32; 3]> {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (len.is_finite() && len > 1e-12).then(|| v.map(|x| (x / len) as f32))
}

fn check_shapes(rec: &Reconstruction) -> Result<(), MeshError> {
    let (width, height) = (rec.width, rec.height);
    let bad = |array| {
        Err(MeshError::Shape {
            array,
            width,
            height,
        })
    };
    if rec.mask.dim() != (height, width) {
        return bad("mask");
    }
    if rec.heights.dim() != (height, width) {
        return bad("heights");
    }
    if rec.albedo.dim() != (height, width) {
        return bad("albedo");
    }
    if rec.normals.dim() != (height, width, 3) {
        return bad("normals");
    }
    if rec
        .albedo_rgb
        .as_ref()
        .is_some_and(|a| a.dim() != (height, width, 3))
    {
        return bad("albedo_rgb");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_cells_are_counter_clockwise_after_the_y_flip() {
        // Corners at glTF (x, y): TL (0, 0), TR (1, 0), BL (0, −1), BR (1, −1).
        let xy = [[0.0, 0.0], [1.0, 0.0], [0.0, -1.0], [1.0, -1.0]];
        for missing in [None, Some(0), Some(1), Some(2), Some(3)] {
            let id = |k: u32| if Some(k) == missing { NONE } else { k };
            let tris = cell_triangles(id(0), id(1), id(2), id(3));
            let tris: Vec<_> = tris.into_iter().flatten().collect();
            assert_eq!(tris.len(), if missing.is_some() { 1 } else { 2 });
            for t in tris {
                assert!(!t.contains(&NONE));
                let [a, b, c] = t.map(|i| xy[i as usize]);
                let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
                assert!(cross > 0.0, "{t:?} is clockwise");
            }
        }
        assert_eq!(cell_triangles(0, NONE, NONE, 3), [None, None]);
    }

    #[test]
    fn mesh_grid_step_is_the_smallest_that_fits() {
        let mask = Array2::from_elem((100, 100), true);
        assert_eq!(grid_step(&mask, 10_000, 1), 1);
        assert_eq!(grid_step(&mask, 9_999, 1), 2);
        assert_eq!(grid_step(&mask, 2_500, 1), 2);
        assert_eq!(grid_step(&mask, 2_499, 1), 3);
        assert_eq!(grid_step(&mask, 10_000, 5), 5);
        assert_eq!(grid_step(&mask, 0, 1), 100);
    }
}
