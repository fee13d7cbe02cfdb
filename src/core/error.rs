//! Errors the core reports about its inputs. Each names the file, row or value at fault,
//! so a caller (CLI or HTTP) can pass the message on verbatim.

use thiserror::Error;

/// Why an image set, light table, mask or option set cannot be reconstructed.
#[derive(Debug, Error)]
pub enum InputError {
    #[error("light table: {0}")]
    Lights(String),
    #[error("{place} matches no layout intake reads; accepted: {accepted}")]
    NoLayout {
        place: String,
        accepted: &'static str,
    },
    #[error("light table row {row}: {reason}")]
    LightRow { row: usize, reason: String },
    #[error("image {name:?} appears twice in the light table (rows {first} and {second})")]
    DuplicateName {
        name: String,
        first: usize,
        second: usize,
    },
    #[error("need at least 3 images with lights, got {count}")]
    TooFewImages { count: usize },
    #[error("image {name:?} is named in the light table but was not provided")]
    MissingImage { name: String },
    #[error("image {name:?} was provided but the light table has no row for it")]
    UnlistedImage { name: String },
    #[error(
        "image {name:?} is {width}×{height} but {first:?} is {expected_width}×{expected_height}: all images must be the same size"
    )]
    SizeMismatch {
        name: String,
        width: u32,
        height: u32,
        first: String,
        expected_width: u32,
        expected_height: u32,
    },
    #[error(
        "image {name:?} is {depth}-bit but {first:?} is {expected}-bit: all images must share one bit depth"
    )]
    BitDepthMismatch {
        name: String,
        depth: u8,
        first: String,
        expected: u8,
    },
    #[error("image {name:?} cannot be decoded: {reason}")]
    Decode { name: String, reason: String },
    #[error(
        "image {name:?} is not a supported image format (PNG, BMP, JPEG, TIFF, OpenEXR): {reason}"
    )]
    UnsupportedFormat { name: String, reason: String },
    #[error(
        "image {name:?} is {width}×{height} = {pixels} pixels, over the limit of {limit} pixels per image"
    )]
    TooLarge {
        name: String,
        width: u64,
        height: u64,
        pixels: u64,
        limit: u64,
    },
    #[error("{count} images is over the limit of {limit} images per job")]
    TooManyImages { count: usize, limit: usize },
    #[error(
        "the light directions span fewer than 3 dimensions (rank {rank}): normals cannot be solved"
    )]
    RankDeficient { rank: usize },
    #[error(
        "the light directions are too ill-conditioned to solve: condition number {condition:.1} exceeds the limit {limit:.1}"
    )]
    IllConditioned { condition: f64, limit: f64 },
    #[error("mask: {0}")]
    Mask(String),
    #[error("options: {0}")]
    Options(String),
    #[error(transparent)]
    Camera(#[from] super::camera::CameraError),
    #[error("{path}: {reason}")]
    Io { path: String, reason: String },
}

impl InputError {
    /// Whether the fault is the size of the input (an HTTP service answers 413).
    pub fn is_too_large(&self) -> bool {
        matches!(self, Self::TooLarge { .. } | Self::TooManyImages { .. })
    }

    /// Whether the fault is an image format the core cannot read (HTTP 415).
    pub fn is_unsupported_media(&self) -> bool {
        matches!(self, Self::UnsupportedFormat { .. })
    }

    pub(crate) fn io(path: impl AsRef<std::path::Path>, err: impl std::fmt::Display) -> Self {
        Self::Io {
            path: path.as_ref().display().to_string(),
            reason: err.to_string(),
        }
    }
}

/// The message a caught panic carried (`panic!` with a literal or with arguments), for
/// the errors and logs that report it.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> &str {
    payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("no message")
}

#[cfg(test)]
mod tests {
    use super::panic_message;
    use std::panic::catch_unwind;

    #[test]
    fn panic_messages_of_every_payload_kind() {
        let literal = catch_unwind(|| panic!("plain")).unwrap_err();
        assert_eq!(panic_message(&*literal), "plain");
        let formatted = catch_unwind(|| panic!("n = {}", 3)).unwrap_err();
        assert_eq!(panic_message(&*formatted), "n = 3");
        let other = catch_unwind(|| std::panic::panic_any(7u8)).unwrap_err();
        assert_eq!(panic_message(&*other), "no message");
    }
}

/// Why a run stopped without a result.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The inputs or options cannot be reconstructed (the caller's fault).
    #[error(transparent)]
    Input(#[from] InputError),
    /// The progress callback asked to stop.
    #[error("cancelled")]
    Cancelled,
    /// Writing an output failed (the machine's fault: disk full, permissions).
    #[error("writing {path}: {reason}")]
    Output { path: String, reason: String },
}
