//! Job records, the queue, calibrations and remembered answers, behind [`JobRepo`]: the
//! capabilities ([`Jobs`], [`Queue`], [`Calibrations`], [`Idempotency`]) in `traits`, the
//! records in `model`, the one error in `error`, the rows both databases share in
//! `rows`; [`SqliteRepo`] (one file, the default) and [`PostgresRepo`] (shared by any
//! number of instances), each with its migrations as files. `contract` is the behaviour
//! every backend owes, run against both by the tests.

#[doc(hidden)]
pub mod contract;
mod error;
mod model;
mod postgres;
mod rows;
mod sqlite;
mod traits;

pub use error::{RepoError, RepoResult};
pub use model::{
    Admission, ArtifactInfo, CalibrationRecord, Callback, CallbackAttempt, CallbackState, Finish,
    JobRecord, JobStatus, Lease, Problem, Reaped, Remembered,
};
pub use postgres::PostgresRepo;
pub use rows::{readable, unreadable_records};
pub use sqlite::SqliteRepo;
pub use traits::{Calibrations, Idempotency, JobRepo, Jobs, Queue};
