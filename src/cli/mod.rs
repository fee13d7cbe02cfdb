//! The subcommands other than `serve`, `openapi`, `healthcheck` and `bench`, one file each,
//! and the flags they share.

pub(crate) mod calibrate;
pub(crate) mod evaluate;
pub(crate) mod flags;
pub(crate) mod integrate;
pub(crate) mod reconstruct;
