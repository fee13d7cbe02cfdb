//! The work done away from requests: the upkeep of the queue and the stored files.

pub(crate) mod upkeep;
