//! The service on its other backends, each a real server started by the tests (skipped,
//! saying so, when its binaries are absent, except under `CI=true`): the job repo on
//! PostgreSQL, the files in S3 (SeaweedFS), and several instances sharing both.
//!
//! The S3 modules set the object store's variables in this process's environment; they
//! hold `common::weed::ENV` while they do, and no other program's tests run here.

#[path = "../binserver/mod.rs"]
mod binserver;
#[path = "../common/mod.rs"]
mod common;

mod cluster;
mod postgres;
mod s3;
