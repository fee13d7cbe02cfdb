//! The RFC 9457 problem document, as the API answers it and as a failed job keeps it.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// The media type of every error body.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// An RFC 9457 problem: what went wrong, as a machine-readable `type` and a human `detail`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(example = json!({
    "type": "urn:photostereo:problem:invalid-input",
    "title": "Invalid input",
    "status": 422,
    "detail": "image \"im4.png\" is named in the light table but was not provided"
}))]
pub struct Problem {
    /// A URI naming the kind of problem (`urn:photostereo:problem:<kind>`).
    #[serde(rename = "type")]
    pub kind: String,
    /// A short summary of the kind of problem.
    pub title: String,
    /// The HTTP status code of this kind of problem.
    pub status: u16,
    /// What exactly went wrong, naming the part, file, row or value at fault.
    pub detail: String,
    /// The resource the problem is about, when there is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
}
