//! Job inputs, artifacts and calibration files behind [`BlobStore`] (the trait and what
//! its methods take and give, in `traits`): [`LocalStore`] in the data directory, or
//! [`S3Store`] in an S3-compatible object store, laid out as `layout` says, with one
//! error ([`Error`]). `manifest` is the input directory's map of names to files.
//! `contract` is the behaviour every store owes, run against both by the tests.

#[doc(hidden)]
pub mod contract;
mod error;
mod layout;
mod local;
mod manifest;
mod s3;
mod traits;

pub use error::{Error, Result};
pub use local::LocalStore;
pub use manifest::{
    LIGHTS_FILE, MANIFEST_FILE, MASK_FILE, Manifest, ManifestEntry, NORMALS_FILE, NormalsEntry,
    image_file,
};
pub use s3::{PART_BYTES, PARTS_IN_FLIGHT, S3Store, parse_url};
pub use traits::{BlobStore, ByteStream, LocalArtifacts, Served};
