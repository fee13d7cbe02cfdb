//! What a submission brings, read as it streams and checked before it is accepted: the
//! body behind its tap (`tap`), the one multipart part loop (`form`), the checks that
//! need no decoding (`checks`), archives (`archive`); the two forms, a job's (`job`) and
//! a calibration's (`calibration`).

pub(crate) mod archive;
pub(crate) mod calibration;
pub(crate) mod checks;
pub(crate) mod form;
pub(crate) mod job;
pub(crate) mod tap;

pub use archive::unpack_archive;
pub use checks::parse_options;
