//! glTF 2.0 meshes of a reconstruction's height map.
//!
//! One vertex per sampled mask pixel (every `step`-th row and column) and triangles only
//! where all their corners are vertices: background never becomes geometry, holes stay
//! holes, there are no walls. Positions use glTF's frame (x right, y up, z towards the
//! viewer): pixel (row, col) lands at (col, −row, height·height_scale), all times
//! `pixel_size` when given. The albedo travels as an embedded PNG base-colour texture.
//! The bytes depend only on the input (no hash-map order, no timestamps).
//!
//! Under a pinhole camera ([`Document::with_camera`]) the heights are depths along the
//! optical axis and each vertex is its pixel's camera-frame point (`Pinhole::unproject`)
//! with y flipped into glTF's frame: (X, −Y, Z), camera at the origin looking down −z, in
//! the depth's unit (`height_scale` and `pixel_size` do not apply).
//!
//! [`write_points_ply`] writes the same surface as a point cloud, one point per mask pixel.

use std::io::Write;

use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;
use fast_image_resize as fir;
use gltf_json as json;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};
use json::accessor::{ComponentType, GenericComponentType, Type};
use json::buffer::Target;
use json::validation::{Checked::Valid, USize64};
use ndarray::{Array2, ArrayView2, Axis, s};
use rayon::prelude::*;
use serde_json::Value;

use super::camera::Pinhole;
use super::options::{MeshNormals, MeshOptions};
use super::reconstruction::Reconstruction;

/// Largest texture side; larger albedo maps are downscaled (many GPUs stop at 4096).
const MAX_TEXTURE_SIDE: usize = 4096;
/// Rings of background texels filled with nearby object colours, so texture filtering and
/// mipmaps do not bleed black into the object's edge.
const FILL_RINGS: usize = 4;
/// No vertex at this grid point.
const NONE: u32 = u32::MAX;

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

/// A glTF document and its binary buffer, built once and encoded as `.glb`, `.gltf` or
/// both (the triangulation and the texture are the expensive part).
#[derive(Debug, Clone)]
pub struct Document {
    root: json::Root,
    bin: Vec<u8>,
}

impl Document {
    /// Triangulate the height map and encode the albedo texture (in parallel).
    pub fn new(rec: &Reconstruction, opts: &MeshOptions) -> Result<Self, MeshError> {
        Self::with_camera(rec, opts, None)
    }

    /// [`Document::new`], or with a camera: `rec.heights` are depths and the vertices are
    /// unprojected through it (module docs).
    pub fn with_camera(
        rec: &Reconstruction,
        opts: &MeshOptions,
        camera: Option<&Pinhole>,
    ) -> Result<Self, MeshError> {
        let (root, bin) = document(rec, opts, camera)?;
        Ok(Self { root, bin })
    }

    /// The binary glTF (`.glb`) file.
    pub fn glb(&self) -> Result<Vec<u8>, MeshError> {
        let mut out = Vec::new();
        self.write_glb(&mut out)?;
        Ok(out)
    }

    /// Stream the `.glb` file into `out` (no whole-file copy of the buffer).
    pub fn write_glb(&self, out: &mut dyn Write) -> Result<(), MeshError> {
        let mut json = self
            .root
            .to_vec()
            .map_err(|e| MeshError::Json(e.to_string()))?;
        json.resize(json.len().next_multiple_of(4), b' ');
        let bytes = 12 + 8 + json.len() + 8 + self.bin.len();
        let total = u32::try_from(bytes).map_err(|_| MeshError::TooLarge { bytes })?;
        out.write_all(b"glTF")?;
        out.write_all(&2u32.to_le_bytes())?;
        out.write_all(&total.to_le_bytes())?;
        for (kind, data) in [(b"JSON", json.as_slice()), (b"BIN\0", &self.bin)] {
            out.write_all(&(data.len() as u32).to_le_bytes())?;
            out.write_all(kind)?;
            out.write_all(data)?;
        }
        Ok(())
    }

    /// The self-contained `.gltf` JSON file (buffer embedded as a base64 data URI).
    pub fn gltf(&self) -> Result<String, MeshError> {
        let mut out = Vec::new();
        self.write_gltf(&mut out)?;
        String::from_utf8(out).map_err(|e| MeshError::Json(e.to_string()))
    }

    /// Stream the `.gltf` file into `out`. The JSON is serialised with an empty data URI
    /// and the base64 text is written into it chunk by chunk: the buffer never exists as
    /// one big string, and the serialiser does not scan it for characters to escape.
    pub fn write_gltf(&self, out: &mut dyn Write) -> Result<(), MeshError> {
        let mut root = self.root.clone();
        root.buffers[0].uri = Some(DATA_URI.into());
        let json = root.to_vec().map_err(|e| MeshError::Json(e.to_string()))?;
        let quoted = format!("\"{DATA_URI}\"");
        let at = json
            .windows(quoted.len())
            .position(|w| w == quoted.as_bytes())
            .ok_or_else(|| MeshError::Json("the buffer URI is missing".into()))?
            + quoted.len()
            - 1;
        out.write_all(&json[..at])?;
        // 3 bytes make 4 characters: chunks that are multiples of 3 need no padding
        // except at the end.
        let mut text = vec![0u8; BASE64_CHUNK / 3 * 4];
        for chunk in self.bin.chunks(BASE64_CHUNK) {
            let n = BASE64
                .encode_slice(chunk, &mut text)
                .map_err(|e| MeshError::Json(e.to_string()))?;
            out.write_all(&text[..n])?;
        }
        out.write_all(&json[at..])?;
        Ok(())
    }
}

/// Prefix of the `.gltf` file's embedded buffer.
const DATA_URI: &str = "data:application/octet-stream;base64,";
/// Bytes encoded per base64 step (a multiple of 3).
const BASE64_CHUNK: usize = 3 << 14;

/// The mesh as a binary glTF (`.glb`) file.
pub fn glb(rec: &Reconstruction, opts: &MeshOptions) -> Result<Vec<u8>, MeshError> {
    Document::new(rec, opts)?.glb()
}

/// The mesh as a self-contained `.gltf` JSON file (buffer embedded as a base64 data URI).
pub fn gltf(rec: &Reconstruction, opts: &MeshOptions) -> Result<String, MeshError> {
    Document::new(rec, opts)?.gltf()
}

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

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
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

/// The glTF document and its binary buffer (views 4-byte aligned, length padded to 4).
fn document(
    rec: &Reconstruction,
    opts: &MeshOptions,
    camera: Option<&Pinhole>,
) -> Result<(json::Root, Vec<u8>), MeshError> {
    let (mesh, texture) = rayon::join(|| triangulate_with(rec, opts, camera), || albedo_png(rec));
    let (mesh, texture) = (mesh?, texture?);
    let mut root = json::Root {
        asset: json::Asset {
            generator: Some(format!("photostereo {}", env!("CARGO_PKG_VERSION"))),
            ..Default::default()
        },
        ..Default::default()
    };
    let buffer = root.push(json::Buffer {
        byte_length: USize64(0), // set below, once the buffer is complete
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    // Sized up front (positions, normals, uvs, u32 indices at most, texture, padding): a
    // growing buffer of ~10 MB was copied by each reallocation.
    let (n, t) = (mesh.positions.len(), mesh.triangles.len());
    let mut bin = Vec::with_capacity(n * (12 + 12 + 8) + t * 12 + texture.len() + 5 * 3);
    let mut view = |root: &mut json::Root, bytes: &[u8], target: Option<Target>| {
        bin.resize(bin.len().next_multiple_of(4), 0);
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        root.push(json::buffer::View {
            buffer,
            byte_length: bytes.len().into(),
            byte_offset: Some(offset.into()),
            byte_stride: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    };
    let floats = |v: &[f32]| {
        let mut out = Vec::with_capacity(v.len() * 4);
        v.iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
        out
    };

    let (lo, hi) = bounds(&mesh.positions);
    let v = view(
        &mut root,
        &floats(mesh.positions.as_flattened()),
        Some(Target::ArrayBuffer),
    );
    let positions = accessor(
        &mut root,
        v,
        n,
        ComponentType::F32,
        Type::Vec3,
        Some((lo, hi)),
    );
    let v = view(
        &mut root,
        &floats(mesh.normals.as_flattened()),
        Some(Target::ArrayBuffer),
    );
    let normals = accessor(&mut root, v, n, ComponentType::F32, Type::Vec3, None);
    let v = view(
        &mut root,
        &floats(mesh.uvs.as_flattened()),
        Some(Target::ArrayBuffer),
    );
    let uvs = accessor(&mut root, v, n, ComponentType::F32, Type::Vec2, None);
    // u16 when every index fits below 65535 (that value means primitive restart).
    let flat = mesh.triangles.as_flattened();
    let (bytes, kind): (Vec<u8>, _) = if n < usize::from(u16::MAX) {
        let b = flat.iter().flat_map(|&i| (i as u16).to_le_bytes());
        (b.collect(), ComponentType::U16)
    } else {
        (
            flat.iter().flat_map(|i| i.to_le_bytes()).collect(),
            ComponentType::U32,
        )
    };
    let v = view(&mut root, &bytes, Some(Target::ElementArrayBuffer));
    let indices = accessor(&mut root, v, flat.len(), kind, Type::Scalar, None);
    let image_view = view(&mut root, &texture, None);
    bin.resize(bin.len().next_multiple_of(4), 0);
    root.buffers[0].byte_length = bin.len().into();

    let image = root.push(json::Image {
        buffer_view: Some(image_view),
        mime_type: Some(json::image::MimeType("image/png".into())),
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    let sampler = root.push(json::texture::Sampler {
        mag_filter: Some(Valid(json::texture::MagFilter::Linear)),
        min_filter: Some(Valid(json::texture::MinFilter::LinearMipmapLinear)),
        wrap_s: Valid(json::texture::WrappingMode::ClampToEdge),
        wrap_t: Valid(json::texture::WrappingMode::ClampToEdge),
        ..Default::default()
    });
    let texture = root.push(json::Texture {
        sampler: Some(sampler),
        source: image,
        extensions: None,
        extras: Default::default(),
    });
    // A matte, non-metallic surface: what photometric stereo assumes (Lambertian).
    let material = root.push(json::Material {
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_texture: Some(json::texture::Info {
                index: texture,
                tex_coord: 0,
                extensions: None,
                extras: Default::default(),
            }),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(1.0),
            ..Default::default()
        },
        double_sided: false,
        ..Default::default()
    });
    let attributes = [
        (json::mesh::Semantic::Positions, positions),
        (json::mesh::Semantic::Normals, normals),
        (json::mesh::Semantic::TexCoords(0), uvs),
    ];
    let primitive = json::mesh::Primitive {
        attributes: attributes.into_iter().map(|(k, a)| (Valid(k), a)).collect(),
        extensions: None,
        extras: Default::default(),
        indices: Some(indices),
        material: Some(material),
        mode: Valid(json::mesh::Mode::Triangles),
        targets: None,
    };
    let mesh = root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        primitives: vec![primitive],
        weights: None,
    });
    let node = root.push(json::Node {
        mesh: Some(mesh),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        nodes: vec![node],
    });
    root.scene = Some(scene);
    Ok((root, bin))
}

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

fn accessor(
    root: &mut json::Root,
    view: json::Index<json::buffer::View>,
    count: usize,
    component: ComponentType,
    kind: Type,
    bounds: Option<(Value, Value)>,
) -> json::Index<json::Accessor> {
    let (min, max) = bounds.unzip();
    root.push(json::Accessor {
        buffer_view: Some(view),
        byte_offset: None,
        count: count.into(),
        component_type: Valid(GenericComponentType(component)),
        extensions: None,
        extras: Default::default(),
        type_: Valid(kind),
        min,
        max,
        normalized: false,
        sparse: None,
    })
}

/// Per-axis minimum and maximum as JSON arrays (f32 → f64 is exact, so they match the
/// data bit for bit as the spec requires).
fn bounds(points: &[[f32; 3]]) -> (Value, Value) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (Value::from(lo.to_vec()), Value::from(hi.to_vec()))
}

/// The albedo as an 8-bit PNG: gray, or RGB when colour albedo exists, no side over
/// [`MAX_TEXTURE_SIDE`]. Values are written as stored, like `albedo.png` (intake does not
/// linearise its inputs).
fn albedo_png(rec: &Reconstruction) -> Result<Vec<u8>, MeshError> {
    let planes: Vec<ArrayView2<f32>> = match &rec.albedo_rgb {
        Some(rgb) => rgb.axis_iter(Axis(2)).collect(),
        None => vec![rec.albedo.view()],
    };
    let (pixel, color) = if planes.len() == 1 {
        (fir::PixelType::U8, ExtendedColorType::L8)
    } else {
        (fir::PixelType::U8x3, ExtendedColorType::Rgb8)
    };
    let (h, w) = rec.mask.dim();
    let texels = texels(&planes, &rec.mask);
    let (texels, w, h) = fit_texture(texels, w as u32, h as u32, pixel, MAX_TEXTURE_SIDE)?;
    let mut out = Vec::new();
    // Fast settings, as for every PNG the service writes (see `outputs::png_to`).
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Up)
        .write_image(&texels, w, h, color)
        .map_err(|e| MeshError::Texture(e.to_string()))?;
    Ok(out)
}

/// `texels` (`w`×`h` pixels of type `pixel`) scaled down, when a side exceeds `max_side`,
/// to fit it: a tent filter whose support widens with the factor, in SIMD
/// (`fast_image_resize`). `image`'s generic resize took 2.4 s of a 5120² job's 7.7 s.
fn fit_texture(
    texels: Vec<u8>,
    w: u32,
    h: u32,
    pixel: fir::PixelType,
    max_side: usize,
) -> Result<(Vec<u8>, u32, u32), MeshError> {
    let side = w.max(h) as usize;
    if side <= max_side {
        return Ok((texels, w, h));
    }
    let f = max_side as f64 / side as f64;
    let scaled = |n: u32| ((f64::from(n) * f).round() as u32).clamp(1, max_side as u32);
    let failed = |e: &dyn std::fmt::Display| MeshError::Texture(format!("scaling: {e}"));
    let src = fir::images::Image::from_vec_u8(w, h, texels, pixel).map_err(|e| failed(&e))?;
    let mut dst = fir::images::Image::new(scaled(w), scaled(h), pixel);
    let tent = fir::ResizeOptions::new()
        .resize_alg(fir::ResizeAlg::Convolution(fir::FilterType::Bilinear));
    fir::Resizer::new()
        .resize(&src, &mut dst, &tent)
        .map_err(|e| failed(&e))?;
    let (w, h) = (dst.width(), dst.height());
    Ok((dst.into_vec(), w, h))
}

/// Interleaved 8-bit texels of `planes` (one channel each), the background filled by
/// [`fill_background`]. Rows are converted in parallel; the texture is made on every job
/// with a mesh, and at 2048² a per-pixel sequential pass was most of the mesh's time.
fn texels(planes: &[ArrayView2<f32>], mask: &Array2<bool>) -> Vec<u8> {
    let (h, w) = mask.dim();
    let n = planes.len();
    let mut out = vec![0u8; h * w * n];
    if out.is_empty() {
        return out;
    }
    // Rounds to nearest; NaN saturates to 0.
    let texel = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    out.par_chunks_mut(w * n).enumerate().for_each(|(r, row)| {
        for (k, plane) in planes.iter().enumerate() {
            let src = plane.row(r);
            match src.as_slice() {
                // Gray albedo: contiguous in and out, a loop that vectorises.
                Some(src) if n == 1 => row.iter_mut().zip(src).for_each(|(t, &v)| *t = texel(v)),
                _ => (row.iter_mut().skip(k).step_by(n).zip(src)).for_each(|(t, &v)| *t = texel(v)),
            }
        }
    });
    let mask = super::contiguous(mask.view());
    fill_background(&mut out, n, &mask, w);
    out
}

/// Background pixels with a 4-neighbour on the mask, in index order: row by row in
/// parallel, from whole rows (a per-pixel neighbour search cost 4 % of a 2048² job).
fn outline(mask: &[bool], w: usize) -> Vec<usize> {
    let h = mask.len() / w;
    let row = |r: usize| &mask[r * w..(r + 1) * w];
    let none = vec![false; w];
    (0..h)
        .into_par_iter()
        .flat_map_iter(|r| {
            let (up, cur) = (if r > 0 { row(r - 1) } else { &none }, row(r));
            let down = if r + 1 < h { row(r + 1) } else { &none };
            (0..w).filter_map(move |c| {
                let side = (c > 0 && cur[c - 1]) || (c + 1 < w && cur[c + 1]);
                (!cur[c] && (up[c] || down[c] || side)).then_some(r * w + c)
            })
        })
        .collect()
}

/// Give background texels near the mask the mean of their already-filled 4-neighbours,
/// ring by ring, and the rest the mask's mean colour: filtering and mipmaps then blend
/// the object's edge with its own colours, not black. Each ring is found from the last
/// one's neighbours, so the cost follows the mask's outline, not the frame. `texels` holds
/// `n` interleaved channels per pixel of a `mask.len() / w`-row grid.
fn fill_background(texels: &mut [u8], n: usize, mask: &[bool], w: usize) {
    let h = mask.len() / w;
    let neighbours = |i: usize| {
        let (r, c) = (i / w, i % w);
        [
            (r > 0).then(|| i - w),
            (r + 1 < h).then(|| i + w),
            (c > 0).then(|| i - 1),
            (c + 1 < w).then(|| i + 1),
        ]
        .into_iter()
        .flatten()
    };
    // The mask's mean colour, from exact integer sums (the last entry counts pixels).
    let sums = (texels.par_chunks(w * n).zip(mask.par_chunks(w)))
        .map(|(texels, mask)| {
            let mut sums = vec![0u64; n + 1];
            if n == 1 {
                // Branch-free, so it vectorises (gray textures are the common case).
                for (&v, &m) in texels.iter().zip(mask) {
                    sums[0] += u64::from(v) * u64::from(m);
                    sums[1] += u64::from(m);
                }
                return sums;
            }
            for (px, _) in texels.chunks_exact(n).zip(mask).filter(|(_, m)| **m) {
                sums.iter_mut()
                    .zip(px)
                    .for_each(|(s, &v)| *s += u64::from(v));
                sums[n] += 1;
            }
            sums
        })
        .reduce(
            || vec![0u64; n + 1],
            |a, b| a.iter().zip(&b).map(|(a, b)| a + b).collect(),
        );
    let count = sums[n].max(1);
    let mean: Vec<u8> = (sums[..n].iter())
        .map(|&s| ((s + count / 2) / count) as u8)
        .collect();

    let mut known = mask.to_vec();
    let mut ring = outline(mask, w);
    let mut fills: Vec<u8> = Vec::new();
    for depth in 0..FILL_RINGS {
        if ring.is_empty() {
            break;
        }
        // Values first (from pixels known before this ring), then mark the ring known.
        fills.clear();
        for &i in &ring {
            for k in 0..n {
                let (mut sum, mut m) = (0u32, 0u32);
                for j in neighbours(i).filter(|&j| known[j]) {
                    sum += u32::from(texels[j * n + k]);
                    m += 1;
                }
                fills.push(((sum + m / 2) / m) as u8);
            }
        }
        for (f, &i) in fills.chunks(n).zip(&ring) {
            texels[i * n..(i + 1) * n].copy_from_slice(f);
            known[i] = true;
        }
        if depth + 1 < FILL_RINGS {
            let mut next: Vec<usize> = (ring.iter())
                .flat_map(|&i| neighbours(i))
                .filter(|&j| !known[j])
                .collect();
            next.sort_unstable();
            next.dedup();
            ring = next;
        }
    }
    (texels.par_chunks_mut(w * n).zip(known.par_chunks(w))).for_each(|(texels, known)| {
        if n == 1 {
            for (t, &k) in texels.iter_mut().zip(known) {
                *t = if k { *t } else { mean[0] };
            }
            return;
        }
        for (px, _) in texels.chunks_exact_mut(n).zip(known).filter(|(_, k)| !**k) {
            px.copy_from_slice(&mean);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outline_is_every_background_pixel_next_to_the_mask() {
        let (h, w) = (23, 31);
        let mask: Vec<bool> = (0..h * w).map(|i| (i * 7919 % 13) < 4).collect();
        let on = |r: isize, c: isize| {
            (0..h as isize).contains(&r)
                && (0..w as isize).contains(&c)
                && mask[r as usize * w + c as usize]
        };
        let naive: Vec<usize> = (0..h * w)
            .filter(|&i| {
                let (r, c) = ((i / w) as isize, (i % w) as isize);
                !mask[i] && (on(r - 1, c) || on(r + 1, c) || on(r, c - 1) || on(r, c + 1))
            })
            .collect();
        assert!(!naive.is_empty());
        assert_eq!(outline(&mask, w), naive);
    }

    #[test]
    fn texture_keeps_the_object_and_pads_its_outline_with_its_own_colours() {
        // A 3×3 object in a 16×16 frame: left column 0.2, the rest 1.0 (RGB: the green
        // channel is inverted).
        let (h, w) = (16, 16);
        let mask =
            Array2::from_shape_fn((h, w), |(r, c)| (5..8).contains(&r) && (5..8).contains(&c));
        let value = |c: usize| if c == 5 { 0.2 } else { 1.0 };
        let gray =
            Array2::from_shape_fn((h, w), |(r, c)| if mask[[r, c]] { value(c) } else { 0.0 });
        let inverted = gray.mapv(|v| 1.0 - v);
        let q = |v: f32| (v * 255.0).round() as u8;
        for planes in [
            vec![gray.view()],
            vec![gray.view(), inverted.view(), gray.view()],
        ] {
            let n = planes.len();
            let t = texels(&planes, &mask);
            let at = |r: usize, c: usize, k: usize| t[(r * w + c) * n + k];
            let want = |v: f32, k: usize| if k == 1 { q(1.0 - v) } else { q(v) };
            for k in 0..n {
                for ((r, c), &m) in mask.indexed_iter() {
                    if m {
                        assert_eq!(at(r, c, k), want(value(c), k), "object ({r}, {c})");
                    }
                }
                // Ring 1, left of the object: its one known neighbour.
                assert_eq!(at(6, 4, k), want(0.2, k));
                // Ring 2, diagonal to the corner: the mean of its two ring-1 neighbours.
                let corner = (u32::from(at(4, 5, k)) + u32::from(at(5, 4, k))).div_ceil(2) as u8;
                assert_eq!(at(4, 4, k), corner);
                // Beyond the rings: the object's mean colour.
                let mean = (0.2 + 2.0 * 1.0) / 3.0;
                let mean_q =
                    ((3 * u32::from(want(0.2, k)) + 6 * u32::from(want(1.0, k)) + 4) / 9) as u8;
                assert!(want(mean, k).abs_diff(mean_q) <= 1);
                assert_eq!(at(0, 15, k), mean_q, "far corner");
            }
        }
    }

    #[test]
    fn oversized_textures_are_scaled_to_fit_keeping_their_colours() {
        // 30×12 RGB, left half dark red, right half light blue, one bright column at 15.
        let (w, h) = (30u32, 12u32);
        let colour = |c: u32| match c {
            15 => [255, 255, 255],
            c if c < 15 => [120, 10, 10],
            _ => [20, 40, 200],
        };
        let texels: Vec<u8> = (0..w * h).flat_map(|i| colour(i % w)).collect();
        let fits = fit_texture(texels.clone(), w, h, fir::PixelType::U8x3, 30).unwrap();
        assert_eq!(
            fits,
            (texels.clone(), w, h),
            "a texture that fits is kept as is"
        );

        let (t, sw, sh) = fit_texture(texels, w, h, fir::PixelType::U8x3, 10).unwrap();
        assert_eq!((sw, sh), (10, 4), "longest side at the limit, aspect kept");
        let at = |r: u32, c: u32| &t[((r * sw + c) * 3) as usize..][..3];
        for r in 0..sh {
            // Far from the edges each side keeps its colour exactly (a filter's weights
            // sum to 1); next to the bright column it is brighter than its side.
            assert_eq!(at(r, 0), &[120, 10, 10]);
            assert_eq!(at(r, 9), &[20, 40, 200]);
            assert!(
                at(r, 4)[1] > 10 && at(r, 5)[0] > 20,
                "the bright column leaves a trace"
            );
        }

        let gray = vec![77u8; 5000 * 3];
        let (t, sw, sh) = fit_texture(gray, 5000, 3, fir::PixelType::U8, 4096).unwrap();
        assert_eq!((sw, sh), (4096, 2));
        assert!(t.iter().all(|&v| v == 77));
    }

    #[test]
    fn mesh_gltf_data_uri_spans_several_base64_chunks() {
        // Not a multiple of 3, and long enough for three chunks and padding at the end.
        let bin: Vec<u8> = (0..2 * BASE64_CHUNK + 7)
            .map(|i| (i * 31 % 251) as u8)
            .collect();
        let mut root = json::Root::default();
        root.push(json::Buffer {
            byte_length: USize64(bin.len() as u64),
            uri: None,
            extensions: None,
            extras: Default::default(),
        });
        let doc = Document { root, bin };
        let text = doc.gltf().unwrap();
        let parsed: Value = serde_json::from_str(&text).unwrap();
        let uri = parsed["buffers"][0]["uri"].as_str().unwrap();
        let data = uri.strip_prefix(DATA_URI).unwrap();
        assert!(data.ends_with('='), "padding only at the end");
        assert_eq!(BASE64.decode(data).unwrap(), doc.bin);
    }

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
