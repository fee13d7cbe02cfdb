//! Who calls and what they may do: API keys and tenants (`keys`: the [`Caller`] every `/v1`
//! request carries, and the one ownership rule), the per-tenant submission rate
//! (`quota`), and `Idempotency-Key` answers (`idempotency`).

pub(crate) mod idempotency;
pub(crate) mod keys;
pub(crate) mod quota;

pub use keys::{Caller, Keyring};
