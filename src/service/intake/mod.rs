//! What a submission brings, read as it streams and checked before it is accepted.

pub(crate) mod calibration;
