//! `photostereo serve` as a child process of the bench: this binary's own `serve`, on
//! 127.0.0.1 with a port of its own, JSON logs read for its address, its memory read from
//! /proc/<pid>/status. Dropping it kills the process and then removes its data directory.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};

use super::client;
use super::memory::{reset_peak_of, status_bytes_of};
use super::temp_dir::TempDir;

/// Longest the server may take to listen and answer /healthz.
const START_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a graceful stop may take before the process is killed.
const STOP_TIMEOUT: Duration = Duration::from_secs(5);
/// Log lines kept for error messages.
const KEEP_LINES: usize = 50;

/// The two tenants' keys, as `--api-key` values and as bearer secrets.
pub(super) const API_KEYS: [&str; 2] = ["a:secretA", "b:secretB"];
pub(super) const KEY_A: &str = "secretA";
pub(super) const KEY_B: &str = "secretB";

pub(super) struct ServeChild {
    child: Child,
    pub(super) addr: SocketAddr,
    logs: Arc<Mutex<VecDeque<String>>>,
    /// Removed after the process is gone (fields drop after `Drop::drop`).
    _dir: TempDir,
}

impl ServeChild {
    /// Start `serve` with its data directory in `dir` and `extra` arguments; returns once
    /// /healthz answers 200.
    pub(super) fn start(
        dir: TempDir,
        extra: &[String],
        rt: &tokio::runtime::Runtime,
    ) -> anyhow::Result<Self> {
        let exe = std::env::current_exe().context("finding this executable")?;
        let mut command = Command::new(exe);
        command
            .args(["serve", "--listen", "127.0.0.1:0", "--log-format", "json"])
            .arg("--data-dir")
            .arg(dir.0.join("data"));
        for key in API_KEYS {
            command.args(["--api-key", key]);
        }
        // The server must not outlive the bench, even one killed with SIGKILL (the signal
        // comes when the thread that started it ends: this one, which waits for it).
        #[cfg(target_os = "linux")]
        // SAFETY: prctl(2) is async-signal-safe and touches no memory of the parent.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            })
        };
        let mut child = command
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("starting photostereo serve")?;
        let stdout = child.stdout.take().ok_or_else(|| anyhow!("no stdout"))?;
        let logs = Arc::new(Mutex::new(VecDeque::new()));
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        let kept = logs.clone();
        // Drain the log for the whole life of the process (a full pipe would block it).
        std::thread::spawn(move || drain(stdout, tx, kept));
        let mut started = Self {
            child,
            addr: "127.0.0.1:0".parse()?,
            logs,
            _dir: dir,
        };
        let addr = rx
            .recv_timeout(START_TIMEOUT)
            .map_err(|_| anyhow!("the server did not report its address:\n{}", started.logs()))?;
        started.addr = addr.parse().context("the server's address")?;
        rt.block_on(started.wait_healthy())?;
        Ok(started)
    }

    async fn wait_healthy(&self) -> anyhow::Result<()> {
        let start = Instant::now();
        loop {
            let answer = async {
                let mut c = client::connect(self.addr).await?;
                c.send("GET", "/healthz", &[], None, Duration::from_secs(2))
                    .await
            };
            if let Ok(r) = answer.await
                && r.status == 200
            {
                return Ok(());
            }
            if start.elapsed() > START_TIMEOUT {
                bail!("/healthz did not answer 200:\n{}", self.logs());
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    fn pid(&self) -> String {
        self.child.id().to_string()
    }

    /// A `kB` field of the server's /proc status (`VmHWM`, `VmRSS`), in bytes.
    pub(super) fn status_bytes(&self, key: &str) -> Option<f64> {
        status_bytes_of(&self.pid(), key)
    }

    /// Reset the server's VmHWM to its current size.
    pub(super) fn reset_peak(&self) -> bool {
        reset_peak_of(&self.pid())
    }

    /// The server's soft limit on open files.
    pub(super) fn open_files_limit(&self) -> Option<u64> {
        let limits = std::fs::read_to_string(format!("/proc/{}/limits", self.pid())).ok()?;
        let line = limits.lines().find(|l| l.starts_with("Max open files"))?;
        line.split_whitespace().nth(3)?.parse().ok()
    }

    /// How the process ended, when it has.
    pub(super) fn exited(&mut self) -> Option<String> {
        match self.child.try_wait() {
            Ok(Some(status)) => Some(status.to_string()),
            _ => None,
        }
    }

    /// The last log lines.
    pub(super) fn logs(&self) -> String {
        let logs = self.logs.lock().map(|l| l.clone()).unwrap_or_default();
        Vec::from(logs).join("\n")
    }

    /// SIGTERM, then SIGKILL if it has not exited within [`STOP_TIMEOUT`]; reaped either way.
    fn stop(&mut self) {
        if self.exited().is_some() {
            return;
        }
        // SAFETY: kill(2) with our own, not yet reaped, child's pid and a valid signal.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        let start = Instant::now();
        while start.elapsed() < STOP_TIMEOUT {
            if self.exited().is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for ServeChild {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Read the server's log lines: the first one with an address goes to `tx`, the last
/// [`KEEP_LINES`] to `kept`.
fn drain(
    stdout: std::process::ChildStdout,
    tx: std::sync::mpsc::Sender<String>,
    kept: Arc<Mutex<VecDeque<String>>>,
) {
    let mut tx = Some(tx);
    for line in BufReader::new(stdout).lines() {
        let Ok(line) = line else { break };
        if let Some(t) = &tx
            && let Ok(v) = serde_json::from_str::<serde_json::Value>(&line)
            && let Some(addr) = v["fields"]["addr"].as_str()
        {
            let _ = t.send(addr.to_string());
            tx = None;
        }
        if let Ok(mut k) = kept.lock() {
            if k.len() >= KEEP_LINES {
                k.pop_front();
            }
            k.push_back(line);
        }
    }
}
