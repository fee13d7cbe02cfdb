//! Memory figures from Linux: the process's own peak and current resident size
//! (/proc/self/status, reset through /proc/self/clear_refs) and a child's peak (`wait4`).

/// The unit the bench prints memory in (10⁶ bytes).
pub(super) const MB: f64 = 1e6;

/// Wait for `child` and read its peak resident size (bytes) from `wait4`'s resource usage.
#[cfg(target_os = "linux")]
pub(super) fn wait_with_peak(
    child: std::process::Child,
) -> std::io::Result<(std::process::ExitStatus, Option<f64>)> {
    use std::os::unix::process::ExitStatusExt;
    let pid = child.id() as libc::pid_t;
    let mut raw = 0;
    // SAFETY: `rusage` is plain integers, for which all zeros is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: both pointers are to live locals; `pid` is our own child, not yet waited
        // for (`Child` waits only when asked to, and it is not asked).
        let got = unsafe { libc::wait4(pid, &mut raw, 0, &mut usage) };
        if got == pid {
            // Linux reports ru_maxrss in KiB.
            let peak = usage.ru_maxrss as f64 * 1024.0;
            return Ok((std::process::ExitStatus::from_raw(raw), Some(peak)));
        }
        let e = std::io::Error::last_os_error();
        if e.kind() != std::io::ErrorKind::Interrupted {
            return Err(e);
        }
    }
}

#[cfg(not(target_os = "linux"))]
pub(super) fn wait_with_peak(
    mut child: std::process::Child,
) -> std::io::Result<(std::process::ExitStatus, Option<f64>)> {
    Ok((child.wait()?, None))
}

/// Reset the process's peak resident size (VmHWM) to its current size (Linux only).
pub(super) fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// A `kB` field of /proc/self/status, in bytes.
pub(super) fn status_bytes(key: &str) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status.lines().find_map(|line| {
        let rest = line.strip_prefix(key)?.strip_prefix(':')?;
        let kb: f64 = rest.split_whitespace().next()?.parse().ok()?;
        Some(kb * 1024.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_own_status() {
        if cfg!(target_os = "linux") {
            assert!(status_bytes("VmRSS").is_some_and(|b| b > 0.0));
            assert!(status_bytes("VmNothing").is_none());
        }
    }
}
