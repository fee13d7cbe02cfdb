//! The one error type of the HTTP API: every failure becomes an RFC 9457
//! `application/problem+json` body.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use crate::core::calibrate::CalibrationError;
use crate::core::error::InputError;
use crate::core::error::RunError;
use crate::core::normalmap::NormalMapError;

use super::problem::{PROBLEM_JSON, Problem};
use super::worker::Failure;

/// An error answer of the API.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    kind: &'static str,
    title: &'static str,
    detail: String,
    instance: Option<String>,
    retry_after: Option<u64>,
}

impl ApiError {
    fn new(status: StatusCode, kind: &'static str, title: &'static str, detail: String) -> Self {
        Self {
            status,
            kind,
            title,
            detail,
            instance: None,
            retry_after: None,
        }
    }

    /// 400: the request is not shaped as the API expects (multipart, parts, parameters).
    pub fn bad_request(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::BAD_REQUEST,
            "bad-request",
            "Malformed request",
            detail.into(),
        )
    }

    /// 401: a key is configured and the request did not present a valid one.
    pub fn unauthorized(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "Missing or invalid API key",
            detail.into(),
        )
    }

    /// 404: no such job, artifact or route.
    pub fn not_found(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::NOT_FOUND,
            "not-found",
            "Not found",
            detail.into(),
        )
    }

    /// 405: the path exists but not with this method.
    pub fn method_not_allowed(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::METHOD_NOT_ALLOWED,
            "method-not-allowed",
            "Method not allowed",
            detail.into(),
        )
    }

    /// 408: the upload did not complete in time.
    pub fn upload_timeout(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::REQUEST_TIMEOUT,
            "upload-timeout",
            "Upload took too long",
            detail.into(),
        )
    }

    /// 409: the job is not in a state that allows this (e.g. its artifacts are not ready).
    pub fn conflict(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::CONFLICT,
            "not-ready",
            "Job not finished",
            detail.into(),
        )
    }

    /// 413: the body, an image, or the number of parts or images is over a limit.
    pub fn too_large(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too-large",
            "Request too large",
            detail.into(),
        )
    }

    /// 415: an image (or archive) in a format the service cannot read.
    pub fn unsupported_media(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            "Unsupported media type",
            detail.into(),
        )
    }

    /// 422: the inputs are well-formed but cannot be reconstructed (lights, names, sizes,
    /// options).
    pub fn invalid(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid-input",
            "Invalid input",
            detail.into(),
        )
    }

    /// 503: the job queue is full; try again after `retry_after` seconds.
    pub fn queue_full(retry_after: u64, detail: impl Into<String>) -> Self {
        let mut e = Self::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "queue-full",
            "Job queue full",
            detail.into(),
        );
        e.retry_after = Some(retry_after);
        e
    }

    /// 429: a tenant's quota (the detail names the limit); retry after `retry_after`
    /// seconds.
    pub fn quota_exceeded(retry_after: u64, detail: impl Into<String>) -> Self {
        let mut e = Self::new(
            StatusCode::TOO_MANY_REQUESTS,
            "quota-exceeded",
            "Quota exceeded",
            detail.into(),
        );
        e.retry_after = Some(retry_after);
        e
    }

    /// 503: the service is stopping or not ready.
    pub fn unavailable(retry_after: u64, detail: impl Into<String>) -> Self {
        let mut e = Self::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "unavailable",
            "Service unavailable",
            detail.into(),
        );
        e.retry_after = Some(retry_after);
        e
    }

    /// 416: a `Range` that no byte of the file satisfies.
    pub fn range_not_satisfiable(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::RANGE_NOT_SATISFIABLE,
            "range-not-satisfiable",
            "Range not satisfiable",
            detail.into(),
        )
    }

    /// 507: not enough free disk space to accept a job.
    pub fn insufficient_storage(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::INSUFFICIENT_STORAGE,
            "insufficient-storage",
            "Insufficient storage",
            detail.into(),
        )
    }

    /// 500: the server's fault. The detail is logged; the caller gets a generic one.
    pub fn internal(detail: impl std::fmt::Display) -> Self {
        tracing::error!(error = %detail, "internal error");
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "Internal server error",
            "the server failed to handle the request; see its logs".into(),
        )
    }

    /// A timed-out reconstruction (stored as a failed job's error).
    pub fn job_timeout(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "job-timeout",
            "Job time limit exceeded",
            detail.into(),
        )
    }

    /// A reconstruction that could not write its outputs or crashed (stored as a failed
    /// job's error).
    pub fn job_failed(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "job-failed",
            "Reconstruction failed",
            detail.into(),
        )
    }

    /// Name the resource the problem is about.
    pub fn with_instance(mut self, instance: impl Into<String>) -> Self {
        self.instance = Some(instance.into());
        self
    }

    pub fn status(&self) -> StatusCode {
        self.status
    }

    pub fn detail(&self) -> &str {
        &self.detail
    }

    /// The body this error answers with.
    pub fn problem(&self) -> Problem {
        Problem {
            kind: format!("urn:photostereo:problem:{}", self.kind),
            title: self.title.to_string(),
            status: self.status.as_u16(),
            detail: self.detail.clone(),
            instance: self.instance.clone(),
        }
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {}: {}",
            self.status.as_u16(),
            self.title,
            self.detail
        )
    }
}

impl std::error::Error for ApiError {}

/// Answer with a problem body as it is (used for stored job errors too).
pub fn problem_response(status: StatusCode, problem: &Problem) -> Response {
    let body = serde_json::to_vec(problem).unwrap_or_default();
    (
        status,
        [(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON))],
        body,
    )
        .into_response()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut response = problem_response(self.status, &self.problem());
        let headers = response.headers_mut();
        if let Some(secs) = self.retry_after {
            headers.insert(header::RETRY_AFTER, HeaderValue::from(secs));
        }
        if self.status == StatusCode::UNAUTHORIZED {
            headers.insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"photostereo\""),
            );
        }
        response
    }
}

/// The core's input errors: the message goes out verbatim; size → 413, format → 415,
/// anything else → 422. An I/O error reading the service's own files is the server's fault.
impl From<InputError> for ApiError {
    fn from(e: InputError) -> Self {
        if e.is_too_large() {
            Self::too_large(e.to_string())
        } else if e.is_unsupported_media() {
            Self::unsupported_media(e.to_string())
        } else if matches!(e, InputError::Io { .. }) {
            Self::internal(e)
        } else {
            Self::invalid(e.to_string())
        }
    }
}

/// A normal map that cannot be used: 422 naming the file and the problem; over the pixel
/// limit 413, as an image.
impl From<NormalMapError> for ApiError {
    fn from(e: NormalMapError) -> Self {
        match e {
            NormalMapError::TooLarge(e) => e.into(),
            other => Self::invalid(other.to_string()),
        }
    }
}

/// The calibration's errors name the image, circle or mask at fault: 422, except for the
/// input errors, mapped as above.
impl From<CalibrationError> for ApiError {
    fn from(e: CalibrationError) -> Self {
        match e {
            CalibrationError::Input(e) => e.into(),
            other => Self::invalid(other.to_string()),
        }
    }
}

impl From<RunError> for ApiError {
    fn from(e: RunError) -> Self {
        match e {
            RunError::Input(e) => e.into(),
            RunError::Cancelled => Self::conflict("the job was cancelled"),
            RunError::Output { path, reason } => {
                let file = std::path::Path::new(&path)
                    .file_name()
                    .map(|f| f.to_string_lossy().into_owned())
                    .unwrap_or_default();
                tracing::error!(%path, %reason, "writing an artifact failed");
                Self::job_failed(format!("writing {file} failed: {reason}"))
            }
        }
    }
}

impl From<super::repo::RepoError> for ApiError {
    fn from(e: super::repo::RepoError) -> Self {
        if e.is_unavailable() {
            tracing::warn!(error = %e, "the job database does not answer");
            return Self::unavailable(
                DATABASE_RETRY_SECONDS,
                "the job database does not answer for now; nothing accepted is lost, try again",
            );
        }
        Self::internal(e)
    }
}

/// Retry-After while the job database does not answer.
const DATABASE_RETRY_SECONDS: u64 = 5;

impl From<tokio::task::JoinError> for ApiError {
    fn from(e: tokio::task::JoinError) -> Self {
        Self::internal(format!("background task failed: {e}"))
    }
}

/// A store error is the server's fault, except an object store that does not answer for
/// now: 503, to be retried.
impl From<super::store::Error> for ApiError {
    fn from(e: super::store::Error) -> Self {
        if e.is_unavailable() {
            tracing::warn!(error = %e, "the object store does not answer");
            Self::unavailable(
                super::config::RETRY_AFTER_SECS,
                "the storage for job files does not answer; retry shortly",
            )
        } else {
            Self::internal(format!("i/o: {e}"))
        }
    }
}

/// A job's failure, as its record keeps it: each kind as the request it stands for would
/// have been answered.
impl From<Failure> for ApiError {
    fn from(e: Failure) -> Self {
        match e {
            Failure::Input(e) => e.into(),
            Failure::NormalMap(e) => e.into(),
            Failure::Run(e) => e.into(),
            Failure::Repo(e) => e.into(),
            Failure::Store(e) => e.into(),
            Failure::Io(e) => e.into(),
            Failure::Invalid(detail) => Self::invalid(detail),
            Failure::Internal(detail) => Self::internal(detail),
            Failure::Failed(detail) => Self::job_failed(detail),
            Failure::TimedOut(detail) => Self::job_timeout(detail),
        }
    }
}

/// An I/O error of the service's own files is the server's fault.
impl From<std::io::Error> for ApiError {
    fn from(e: std::io::Error) -> Self {
        Self::internal(format!("i/o: {e}"))
    }
}
