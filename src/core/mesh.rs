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
//!
//! This file is the document and its writers; below it: `triangulate` (the geometry),
//! `texture` (the albedo texture), `document` (the glTF JSON and buffer) and `ply`.

mod document;
mod error;
mod ply;
mod texture;
mod triangulate;

use std::io::Write;

use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;
use gltf_json as json;

pub use error::MeshError;
pub use ply::write_points_ply;
pub use triangulate::{TriMesh, grid_step, triangulate, triangulate_with};

use super::camera::Pinhole;
use super::options::MeshOptions;
use super::reconstruction::Reconstruction;
use document::document;

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

#[cfg(test)]
mod tests {
    use super::*;
    use json::validation::USize64;
    use serde_json::Value;

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
}
