//! A job's input directory as the upload leaves it: the stored files' names and the
//! manifest (`manifest.json`) that maps the light table's names to them. Written by the
//! upload, read by the worker; the store moves it like any other file.

use serde::{Deserialize, Serialize};

use crate::core::normalmap::Convention;

/// File names inside a job's input directory.
pub const MANIFEST_FILE: &str = "manifest.json";
pub const LIGHTS_FILE: &str = "lights.txt";
pub const MASK_FILE: &str = "mask.img";
pub const NORMALS_FILE: &str = "normals.img";

/// Name of the `i`-th stored input image.
pub fn image_file(i: usize) -> String {
    format!("{i:03}.img")
}

/// What the input directory holds: table names → stored files.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub images: Vec<ManifestEntry>,
    pub mask: Option<ManifestEntry>,
    /// A normals job's normal map (its `images` are then empty and there is no light
    /// table).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normals: Option<NormalsEntry>,
    /// What the upload ignored or chose (an archive's unnamed images, say), for the
    /// job's `result.json`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ManifestEntry {
    /// The name the light table uses (or the mask part's file name).
    pub name: String,
    /// The stored file, relative to the input directory.
    pub file: String,
}

/// A normals job's normal map and how its green channel points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalsEntry {
    /// The `normals` part's file name.
    pub name: String,
    /// The stored file, relative to the input directory.
    pub file: String,
    pub convention: Convention,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manifests_without_normals_still_read_and_a_normals_job_round_trips() {
        let old = br#"{"images": [{"name": "a.png", "file": "000.img"}], "mask": null}"#;
        let manifest: Manifest = serde_json::from_slice(old).unwrap();
        assert_eq!((manifest.images.len(), manifest.normals), (1, None));
        let normals = Manifest {
            images: Vec::new(),
            mask: None,
            normals: Some(NormalsEntry {
                name: "n.png".into(),
                file: NORMALS_FILE.into(),
                convention: Convention::Directx,
            }),
            notes: Vec::new(),
        };
        let json = serde_json::to_vec(&normals).unwrap();
        assert_eq!(serde_json::from_slice::<Manifest>(&json).unwrap(), normals);
    }
}
