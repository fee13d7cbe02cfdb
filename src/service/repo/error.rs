//! The repo's one error, whichever database answers: the server's fault, or a database
//! that does not answer for now ([`RepoError::is_unavailable`]), which callers wait out.

/// A storage failure: the server's fault, or a database that does not answer for now
/// ([`is_unavailable`](Self::is_unavailable)), which callers wait out.
#[derive(Debug, thiserror::Error)]
#[error("job repository: {message}")]
pub struct RepoError {
    message: String,
    unavailable: bool,
}

impl RepoError {
    pub(crate) fn new(message: String) -> Self {
        Self {
            message,
            unavailable: false,
        }
    }

    /// The database cannot be reached (down, restarting, out of connections).
    pub(crate) fn unavailable(message: String) -> Self {
        Self {
            message,
            unavailable: true,
        }
    }

    pub fn is_unavailable(&self) -> bool {
        self.unavailable
    }
}

impl From<rusqlite::Error> for RepoError {
    fn from(e: rusqlite::Error) -> Self {
        Self::new(e.to_string())
    }
}

impl From<serde_json::Error> for RepoError {
    fn from(e: serde_json::Error) -> Self {
        Self::new(format!("stored JSON: {e}"))
    }
}

/// PostgreSQL's answer: connection exceptions (SQLSTATE 08…), a server shutting down or
/// starting (57P0…) and no answer at all pass; anything else is the server's fault.
impl From<tokio_postgres::Error> for RepoError {
    fn from(e: tokio_postgres::Error) -> Self {
        match e.as_db_error() {
            Some(db) if is_transient(db.code().code()) => {
                Self::unavailable(format!("PostgreSQL: {}", db.message()))
            }
            Some(db) => Self::new(format!("PostgreSQL: {}", db.message())),
            // No answer from the server at all: a closed connection, a refused one.
            None => Self::unavailable(format!("PostgreSQL does not answer: {e}")),
        }
    }
}

fn is_transient(sqlstate: &str) -> bool {
    sqlstate.starts_with("08") || sqlstate.starts_with("57P0")
}

/// No connection from the pool in time is the database not answering.
impl From<deadpool_postgres::PoolError> for RepoError {
    fn from(e: deadpool_postgres::PoolError) -> Self {
        match e {
            deadpool_postgres::PoolError::Backend(e) => e.into(),
            deadpool_postgres::PoolError::Timeout(_) => {
                Self::unavailable(format!("PostgreSQL does not answer: {e}"))
            }
            e => Self::new(format!("PostgreSQL connection pool: {e}")),
        }
    }
}

pub type RepoResult<T> = Result<T, RepoError>;
