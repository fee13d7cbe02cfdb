//! Who is calling: API keys belong to tenants, and every job belongs to the tenant that
//! created it.
//!
//! Keys come from `--api-key` (`tenant:secret`, or a bare secret that is its own tenant)
//! and from `--api-keys-file` (lines `tenant secret [role]`, re-read on SIGHUP). The
//! middleware in `mod.rs` turns the presented key into a [`Caller`] in the request's
//! extensions; handlers take it as an extractor and check ownership through
//! [`Caller::sees`] (jobs: `http::extract::owned_job`). Only digests of the secrets are kept.

use std::path::Path;

use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use sha2::{Digest, Sha256};
use subtle::{ConditionallySelectable, ConstantTimeEq};

use crate::service::error::ApiError;

/// The tenant of every job when no keys are configured (and of jobs recorded before
/// tenants existed).
pub const OPEN_TENANT: &str = "default";

/// The authenticated caller of a `/v1` request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Caller {
    pub tenant: String,
    /// A key with the `admin` role: sees and manages every tenant's jobs.
    pub admin: bool,
}

impl Caller {
    /// The caller when no keys are configured: the API is open, as one tenant that sees
    /// everything.
    pub fn open() -> Self {
        Self {
            tenant: OPEN_TENANT.to_string(),
            admin: true,
        }
    }

    /// Whether this caller may see (and manage) a record owned by `owner`. Every route
    /// that names a job (or another tenant-owned record) goes through this, and answers
    /// `false` exactly as it answers an id that does not exist.
    pub fn sees(&self, owner: &str) -> bool {
        self.admin || self.tenant == owner
    }

    /// The tenant a listing is limited to; `None` (admin) lists every tenant's.
    pub fn scope(&self) -> Option<String> {
        (!self.admin).then(|| self.tenant.clone())
    }
}

/// Put there by the authentication middleware on every `/v1` request; a route outside
/// it that asks for a caller is a bug, answered with 500 rather than served open.
impl<S: Send + Sync> FromRequestParts<S> for Caller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Self, Self::Rejection> {
        parts
            .extensions
            .get::<Caller>()
            .cloned()
            .ok_or_else(|| ApiError::internal("a /v1 route is not behind the authentication"))
    }
}

struct Key {
    tenant: String,
    digest: [u8; 32],
    admin: bool,
}

/// The configured keys, as digests.
#[derive(Default)]
pub struct Keyring {
    keys: Vec<Key>,
    /// Keys are configured (flags or a keys file, even one left empty): never open.
    closed: bool,
}

impl Keyring {
    /// The keys of `--api-key` values and of the keys file. Errors name the value or line
    /// at fault, never a secret.
    pub fn load(flags: &[String], file: Option<&Path>) -> anyhow::Result<Self> {
        let mut keys = Vec::new();
        for (i, flag) in flags.iter().enumerate() {
            keys.push(parse_flag(flag).map_err(|why| {
                anyhow::anyhow!("--api-key value {} (of {}): {why}", i + 1, flags.len())
            })?);
        }
        if let Some(path) = file {
            let text = std::fs::read_to_string(path).map_err(|e| {
                anyhow::anyhow!("cannot read the keys file {}: {e}", path.display())
            })?;
            for (n, line) in text.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with('#') {
                    continue;
                }
                keys.push(
                    parse_line(line).map_err(|why| {
                        anyhow::anyhow!("{} line {}: {why}", path.display(), n + 1)
                    })?,
                );
            }
        }
        Ok(Self {
            keys,
            closed: !flags.is_empty() || file.is_some(),
        })
    }

    /// No keys configured: the API is open.
    pub fn is_open(&self) -> bool {
        !self.closed
    }

    pub fn count(&self) -> usize {
        self.keys.len()
    }

    /// The caller a presented key authenticates. Every configured key is compared, in
    /// constant time and as SHA-256 digests (equal lengths hide the keys' lengths too), so
    /// the time taken says nothing about which key, if any, matched.
    pub fn find(&self, presented: &str) -> Option<Caller> {
        let presented = Sha256::digest(presented.as_bytes());
        let mut found = subtle::Choice::from(0u8);
        let mut index = 0u32;
        for (i, key) in self.keys.iter().enumerate() {
            let hit = key.digest.ct_eq(presented.as_slice());
            index.conditional_assign(&(i as u32), hit);
            found |= hit;
        }
        bool::from(found).then(|| {
            let key = &self.keys[index as usize];
            Caller {
                tenant: key.tenant.clone(),
                admin: key.admin,
            }
        })
    }
}

fn digest(secret: &str) -> [u8; 32] {
    Sha256::digest(secret.as_bytes()).into()
}

/// `tenant:secret`, or a bare secret, which is its own tenant `key-<12 hex digits of its
/// SHA-256>`: stable across restarts, and not the secret.
fn parse_flag(value: &str) -> Result<Key, String> {
    let value = value.trim();
    match value.split_once(':') {
        Some((tenant, secret)) => {
            check_tenant(tenant)?;
            check_secret(secret)?;
            Ok(Key {
                tenant: tenant.to_string(),
                digest: digest(secret),
                admin: false,
            })
        }
        None => {
            check_secret(value)?;
            let d = digest(value);
            let hex: String = d[..6].iter().map(|b| format!("{b:02x}")).collect();
            Ok(Key {
                tenant: format!("key-{hex}"),
                digest: d,
                admin: false,
            })
        }
    }
}

/// `tenant secret [role]`, role `admin` or `member` (the default).
fn parse_line(line: &str) -> Result<Key, String> {
    let fields: Vec<&str> = line.split_whitespace().collect();
    let (tenant, secret, role) = match fields.as_slice() {
        [t, s] => (*t, *s, "member"),
        [t, s, r] => (*t, *s, *r),
        _ => {
            let n = fields.len();
            let s = if n == 1 { "" } else { "s" };
            return Err(format!("expected `tenant secret [role]`, got {n} field{s}"));
        }
    };
    check_tenant(tenant)?;
    check_secret(secret)?;
    let admin = match role {
        "admin" => true,
        "member" => false,
        other => {
            return Err(format!(
                "unknown role {other:?}; roles are admin and member"
            ));
        }
    };
    Ok(Key {
        tenant: tenant.to_string(),
        digest: digest(secret),
        admin,
    })
}

/// Tenant names appear in records, metrics labels and logs: 1 to 64 of `A-Z a-z 0-9 . _ -`.
pub fn check_tenant(name: &str) -> Result<(), String> {
    let ok = (1..=64).contains(&name.len())
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "tenant name {name:?} must be 1 to 64 letters, digits, '.', '_' or '-'"
        ))
    }
}

fn check_secret(secret: &str) -> Result<(), String> {
    if secret.is_empty() {
        Err("the secret is empty".into())
    } else if secret.chars().any(|c| c.is_whitespace() || c.is_control()) {
        Err("the secret contains white space or control characters".into())
    } else {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Jobs recorded before tenants existed belong to the open API's tenant: the
    /// migrations' default is this tenant's name.
    #[test]
    fn jobs_recorded_before_tenants_belong_to_the_open_tenant() {
        let default = format!("NOT NULL DEFAULT '{OPEN_TENANT}'");
        for migration in [
            include_str!("../repo/sqlite/migrations/002_tenants.sql"),
            include_str!("../repo/postgres/migrations/001_jobs_idempotency_calibrations.sql"),
        ] {
            assert!(migration.contains(&default), "{migration}");
        }
    }

    #[test]
    fn flags_and_file_lines_name_tenants() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("keys");
        std::fs::write(
            &file,
            "# tenants\nalice a-secret\n\nops o-secret admin\nbob b-secret member\n",
        )
        .unwrap();
        let ring = Keyring::load(&["carol:c-secret".into(), "bare".into()], Some(&file)).unwrap();
        assert_eq!(ring.count(), 5);
        assert!(!ring.is_open());
        assert!(Keyring::load(&[], None).unwrap().is_open());
        std::fs::write(&file, "# nobody yet\n").unwrap();
        let emptied = Keyring::load(&[], Some(&file)).unwrap();
        assert!(!emptied.is_open() && emptied.find("a-secret").is_none());
        let who = |k: &str| ring.find(k).map(|c| (c.tenant, c.admin));
        assert_eq!(who("a-secret"), Some(("alice".into(), false)));
        assert_eq!(who("o-secret"), Some(("ops".into(), true)));
        assert_eq!(who("b-secret"), Some(("bob".into(), false)));
        assert_eq!(who("c-secret"), Some(("carol".into(), false)));
        assert_eq!(who("carol:c-secret"), None);
        let (bare, _) = who("bare").unwrap();
        assert!(bare.starts_with("key-") && bare.len() == 16, "{bare}");
        assert!(!bare.contains("bare"));
        assert_eq!(who("nope"), None);
        assert!(ring.find("").is_none());
    }

    #[test]
    fn bad_keys_are_refused_without_showing_the_secret() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("keys");
        for (text, needle) in [
            ("alice\n", "got 1 field"),
            ("al ice top-secret x y\n", "fields"),
            ("alice top-secret root\n", "unknown role"),
            ("al/ice top-secret\n", "tenant name"),
        ] {
            std::fs::write(&file, text).unwrap();
            let e = Keyring::load(&[], Some(&file)).err().unwrap().to_string();
            assert!(e.contains("line 1") && e.contains(needle), "{e}");
            assert!(!e.contains("top-secret"), "{e}");
        }
        let e = Keyring::load(&["a b:top-secret".into()], None)
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("tenant name") && !e.contains("top-secret"),
            "{e}"
        );
        assert!(Keyring::load(&["alice:".into()], None).is_err());
        assert!(Keyring::load(&[], Some(&dir.path().join("missing"))).is_err());
    }

    #[test]
    fn callers_see_their_own_and_admins_all() {
        let alice = Caller {
            tenant: "alice".into(),
            admin: false,
        };
        assert!(alice.sees("alice") && !alice.sees("bob"));
        assert_eq!(alice.scope().as_deref(), Some("alice"));
        let admin = Caller {
            tenant: "ops".into(),
            admin: true,
        };
        assert!(admin.sees("bob") && admin.scope().is_none());
        assert!(Caller::open().sees("anyone"));
    }
}
