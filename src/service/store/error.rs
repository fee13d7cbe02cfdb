//! The store's one error, whichever store answers: the local file system's (staging,
//! scratch, the data directory), or an object store that does not answer for now
//! ([`Error::is_unavailable`]), which callers wait out.

use std::io;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read, written or found (an object that is not there is one).
    #[error(transparent)]
    Io(#[from] io::Error),
    /// The object store did not answer (or refused): the request may succeed later, so
    /// the service answers 503 and a job waits rather than fails.
    #[error("the object store is unavailable: {0}")]
    Unavailable(String),
}

impl Error {
    /// Whether the store does not answer for now.
    pub fn is_unavailable(&self) -> bool {
        matches!(self, Error::Unavailable(_))
    }

    /// Whether the file or object asked for is not there.
    pub fn is_not_found(&self) -> bool {
        matches!(self, Error::Io(e) if e.kind() == io::ErrorKind::NotFound)
    }
}

/// Any failure of the object store: an object that is not there, or a store that is
/// down, unreachable, or refused.
impl From<object_store::Error> for Error {
    fn from(e: object_store::Error) -> Self {
        match e {
            object_store::Error::NotFound { path, .. } => Error::Io(io::Error::new(
                io::ErrorKind::NotFound,
                format!("no object {path}"),
            )),
            other => Error::Unavailable(other.to_string()),
        }
    }
}

pub type Result<T> = std::result::Result<T, Error>;
