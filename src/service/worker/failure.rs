//! Why a job failed, as the worker knows it: what the job's record keeps as its problem,
//! once the runner's `problem` function (given by the HTTP side) has said which kind of
//! problem each failure is.

use crate::core::normalmap::NormalMapError;
use crate::core::{InputError, RunError};
use crate::service::repo::RepoError;
use crate::service::store;

/// A job's failure.
#[derive(Debug)]
pub enum Failure {
    /// Its inputs are wrong (the light table, the images, the options).
    Input(InputError),
    /// Its normal map holds no usable normals.
    NormalMap(NormalMapError),
    /// The run failed.
    Run(RunError),
    /// The job database did not answer or failed.
    Repo(RepoError),
    /// The store did not answer or failed.
    Store(store::Error),
    /// A file of the job could not be read or written.
    Io(std::io::Error),
    /// What was stored for the job does not read back as valid (its options).
    Invalid(String),
    /// What was stored for the job does not read back at all (its manifest, its outputs).
    Internal(String),
    /// The service gave up on the job (its worker crashed or stopped answering, its
    /// inputs are gone).
    Failed(String),
    /// The job ran past the job time limit.
    TimedOut(String),
}

impl From<InputError> for Failure {
    fn from(e: InputError) -> Self {
        Self::Input(e)
    }
}

impl From<NormalMapError> for Failure {
    fn from(e: NormalMapError) -> Self {
        Self::NormalMap(e)
    }
}

impl From<RunError> for Failure {
    fn from(e: RunError) -> Self {
        Self::Run(e)
    }
}

impl From<RepoError> for Failure {
    fn from(e: RepoError) -> Self {
        Self::Repo(e)
    }
}

impl From<store::Error> for Failure {
    fn from(e: store::Error) -> Self {
        Self::Store(e)
    }
}

impl From<std::io::Error> for Failure {
    fn from(e: std::io::Error) -> Self {
        Self::Io(e)
    }
}
