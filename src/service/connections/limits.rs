//! How many connections may be open at once and how long a head may take to arrive: the
//! cap (by default from the open-files limit, less the descriptors jobs, uploads and
//! calibrations may hold), resolved from the config.

use std::time::Duration;

use crate::service::config::Config;

/// `--max-connections` when the open-files limit leaves room for it.
pub const DEFAULT_MAX_CONNECTIONS: usize = 4096;

/// Refused connections that may stay open at once to read the request they sent, so that
/// their client reads the 503 rather than a reset; the others are closed at once.
pub(super) const LINGERING: usize = 64;

/// Descriptors kept for the process besides jobs, uploads and connections (database,
/// store clients, logs, the runtime).
const BASE_FILES: usize = 256;

/// The connection settings in force.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_connections: usize,
    pub header_timeout: Duration,
    pub keep_alive_timeout: Duration,
    pub send_timeout: Duration,
}

impl Limits {
    /// `--max-connections`, or a default the open-files limit has room for beside the files
    /// the jobs, calibrations and uploads may hold.
    pub fn resolve(config: &Config) -> Self {
        let files = open_files_limit();
        let reserved = reserved_files(config);
        let max_connections = match (config.max_connections, files) {
            (Some(n), Some(files)) => {
                if n.saturating_add(reserved) > files {
                    tracing::warn!(
                        max_connections = n,
                        open_files_limit = files,
                        reserved_for_files = reserved,
                        "--max-connections is more than the open-files limit has room for; at the limit, idle connections are closed to make room"
                    );
                }
                n
            }
            (Some(n), None) => n,
            (None, None) => DEFAULT_MAX_CONNECTIONS,
            (None, Some(files)) => {
                let room = files.saturating_sub(reserved);
                if room >= 256 {
                    room.min(DEFAULT_MAX_CONNECTIONS)
                } else {
                    let n = (files / 4).max(16);
                    tracing::warn!(
                        open_files_limit = files,
                        reserved_for_files = reserved,
                        max_connections = n,
                        "the open-files limit is low for this configuration; raise it (ulimit -n) or set --max-connections"
                    );
                    n
                }
            }
        };
        Self {
            max_connections,
            header_timeout: config.header_timeout,
            keep_alive_timeout: config.keep_alive_timeout,
            send_timeout: config.send_timeout,
        }
    }
}

/// Descriptors the rest of the server may hold at once: a spill file per image for each
/// running job, calibration and upload decoded ahead, a file or two per upload, the
/// refused connections lingering, and a base.
fn reserved_files(c: &Config) -> usize {
    let holders = 2 * c.workers.max(1) + c.decode_ahead;
    c.max_images
        .saturating_mul(holders)
        .saturating_add(2 * c.max_uploads + LINGERING + BASE_FILES)
}

/// Raise the soft limit on open files to the hard limit (what a server is allowed; the
/// soft limit is often 1024). Returns the limit in force.
pub fn raise_open_files_limit() -> Option<usize> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes into the struct we own.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
            return None;
        }
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: limit.rlim_max,
                rlim_max: limit.rlim_max,
            };
            // SAFETY: setrlimit reads the struct we own. It fails (EPERM) when the hard
            // limit is above the kernel's nr_open; the soft limit then stays.
            if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
                limit.rlim_cur = limit.rlim_max;
            }
        }
        Some(usize::try_from(limit.rlim_cur).unwrap_or(usize::MAX))
    }
    #[cfg(not(unix))]
    None
}

fn open_files_limit() -> Option<usize> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes into the struct we own.
        (unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0)
            .then(|| usize::try_from(limit.rlim_cur).unwrap_or(usize::MAX))
    }
    #[cfg(not(unix))]
    None
}
