//! Memory and CPU figures from Linux: the peak and current resident size of this process or
//! a child (/proc/<pid>/status, reset through /proc/<pid>/clear_refs), a child's peak
//! (`wait4`), and CPU time, of this process (`getrusage`) and of other process trees
//! (/proc).

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
    reset_peak_of("self")
}

/// [`reset_peak`] of process `pid` (`"self"` or a number; a child of this one, say).
pub(super) fn reset_peak_of(pid: &str) -> bool {
    std::fs::write(format!("/proc/{pid}/clear_refs"), "5").is_ok()
}

/// A `kB` field of /proc/self/status, in bytes.
pub(super) fn status_bytes(key: &str) -> Option<f64> {
    status_bytes_of("self", key)
}

/// A `kB` field of /proc/<pid>/status, in bytes.
pub(super) fn status_bytes_of(pid: &str, key: &str) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status.lines().find_map(|line| {
        let rest = line.strip_prefix(key)?.strip_prefix(':')?;
        let kb: f64 = rest.split_whitespace().next()?.parse().ok()?;
        Some(kb * 1024.0)
    })
}

/// CPU time (user + system) this process has used, all threads, ms.
pub(super) fn own_cpu_ms() -> f64 {
    // SAFETY: `rusage` is plain integers, for which all zeros is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: a live local to write into; RUSAGE_SELF is always valid.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
        return 0.0;
    }
    let ms = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 / 1e3;
    ms(usage.ru_utime) + ms(usage.ru_stime)
}

/// The machine's online cores (whatever this process's affinity).
pub(super) fn online_cores() -> usize {
    // SAFETY: sysconf has no preconditions.
    unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) }.max(1) as usize
}

/// CPU time (user + system) the live processes `pids` and their live descendants have
/// used, ms (from /proc/<pid>/stat; a process that has gone counts no more).
pub(super) fn tree_cpu_ms(pids: &[u32]) -> f64 {
    // SAFETY: sysconf has no preconditions.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    let mut todo: Vec<u32> = pids.to_vec();
    let mut seen = std::collections::HashSet::new();
    let mut total = 0.0;
    while let Some(pid) = todo.pop() {
        if !seen.insert(pid) {
            continue;
        }
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        // Fields after the command (which may hold spaces), from the state, field 3:
        // utime and stime are fields 14 and 15.
        let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
        let fields: Vec<&str> = rest.split_whitespace().collect();
        let field = |n: usize| fields.get(n - 3).and_then(|f| f.parse::<f64>().ok());
        total += field(14).unwrap_or(0.0) + field(15).unwrap_or(0.0);
        let tasks = std::fs::read_dir(format!("/proc/{pid}/task"))
            .into_iter()
            .flatten();
        for task in tasks.flatten() {
            let children = std::fs::read_to_string(task.path().join("children"));
            todo.extend(
                children
                    .iter()
                    .flat_map(|c| c.split_whitespace().filter_map(|p| p.parse::<u32>().ok())),
            );
        }
    }
    total * 1e3 / ticks
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

    #[test]
    fn counts_cpu_time_of_self_and_of_a_process_tree() {
        if !cfg!(target_os = "linux") {
            return;
        }
        let (own, tree) = (own_cpu_ms(), tree_cpu_ms(&[std::process::id()]));
        // Busy until this process has used 100 ms more CPU (however loaded the machine).
        let start = std::time::Instant::now();
        let mut x = 0u64;
        while own_cpu_ms() - own < 100.0 && start.elapsed().as_secs() < 20 {
            for _ in 0..10_000 {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
        }
        assert!(own_cpu_ms() - own >= 100.0, "own CPU time advances");
        // /proc counts in clock ticks (10 ms).
        let grew = tree_cpu_ms(&[std::process::id()]) - tree;
        assert!(grew >= 80.0, "the tree counts it too: {grew} ms");
        assert_eq!(tree_cpu_ms(&[u32::MAX]), 0.0, "no such process");
    }
}
