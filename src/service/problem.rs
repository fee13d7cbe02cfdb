//! The RFC 9457 problem document, as the API answers it and as a failed job keeps it
//! (the type is a record of the repo's, [`super::repo::Problem`]).

pub use super::repo::Problem;

/// The media type of every error body.
pub const PROBLEM_JSON: &str = "application/problem+json";
