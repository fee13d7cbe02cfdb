//! The real `photostereo serve` binary as a child process, for tests that need to kill it
//! (crash recovery) or measure its memory (hostile input): started on 127.0.0.1:0 with
//! JSON logs, its address read from the "serving" log line.

#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Log lines kept for failure messages.
const KEEP_LINES: usize = 200;

pub struct BinServer {
    child: Child,
    pub base: String,
    pub client: reqwest::Client,
    pub data_dir: PathBuf,
    logs: Arc<Mutex<Vec<String>>>,
}

impl BinServer {
    /// Start `photostereo serve` on `data_dir` with `extra` flags; waits until it listens.
    pub fn start(data_dir: &Path, extra: &[&str]) -> Self {
        Self::start_with_env(data_dir, extra, &[])
    }

    /// [`start`](Self::start) with environment variables set for the server.
    pub fn start_with_env(data_dir: &Path, extra: &[&str], env: &[(&str, String)]) -> Self {
        Self::launch(data_dir, extra, env, None)
    }

    /// [`start`](Self::start) with the server's open-files limit (soft and hard) at
    /// `files`, as under `ulimit -n files`.
    pub fn start_with_file_limit(data_dir: &Path, extra: &[&str], files: u64) -> Self {
        Self::launch(data_dir, extra, &[], Some(files))
    }

    fn launch(
        data_dir: &Path,
        extra: &[&str],
        env: &[(&str, String)],
        file_limit: Option<u64>,
    ) -> Self {
        // PHOTOSTEREO_TEST_BINARY runs the tests against another build (an older one, to
        // see a test fail without the change it covers).
        let binary = std::env::var_os("PHOTOSTEREO_TEST_BINARY")
            .unwrap_or_else(|| env!("CARGO_BIN_EXE_photostereo").into());
        let mut command = Command::new(binary);
        command
            .args(["serve", "--listen", "127.0.0.1:0", "--log-format", "json"])
            .arg("--data-dir")
            .arg(data_dir)
            .args(["--min-free-disk", "0"])
            .args(extra)
            .envs(env.iter().map(|(k, v)| (k, v)))
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        if let Some(files) = file_limit {
            use std::os::unix::process::CommandExt;
            let limit = libc::rlimit {
                rlim_cur: files,
                rlim_max: files,
            };
            // SAFETY: setrlimit is async-signal-safe and reads a struct the closure owns.
            unsafe {
                command.pre_exec(move || {
                    if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) == 0 {
                        Ok(())
                    } else {
                        Err(std::io::Error::last_os_error())
                    }
                });
            }
        }
        let mut child = command.spawn().expect("start photostereo serve");
        let stdout = child.stdout.take().unwrap();
        let logs = Arc::new(Mutex::new(Vec::new()));
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        let kept = logs.clone();
        // Drain the log for the whole life of the process (a full pipe would block it).
        std::thread::spawn(move || {
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
                let mut k = kept.lock().unwrap();
                if k.len() >= KEEP_LINES {
                    k.remove(0);
                }
                k.push(line);
            }
        });
        let addr = match rx.recv_timeout(Duration::from_secs(30)) {
            Ok(addr) => addr,
            Err(_) => {
                let _ = child.kill();
                panic!(
                    "the server did not report its address: {:?}",
                    logs.lock().unwrap()
                );
            }
        };
        let client = reqwest::Client::builder()
            .timeout(Duration::from_secs(60))
            .build()
            .unwrap();
        Self {
            child,
            base: format!("http://{addr}"),
            client,
            data_dir: data_dir.to_path_buf(),
            logs,
        }
    }

    /// Submit `form`; the id of its 202 (anything else fails the test).
    pub async fn submit(&self, form: reqwest::multipart::Form) -> String {
        let r = self
            .client
            .post(self.url("/v1/jobs"))
            .multipart(form)
            .send()
            .await
            .expect("submit");
        let status = r.status();
        let body: serde_json::Value = r.json().await.unwrap();
        assert_eq!(status, 202, "submit: {body}");
        body["id"].as_str().unwrap().to_string()
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub fn addr(&self) -> &str {
        self.base.trim_start_matches("http://")
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGKILL, and reap the process.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM: the graceful stop.
    pub fn terminate(&self) {
        // SAFETY: kill(2) with our own child's pid and a valid signal number.
        let rc = unsafe { libc::kill(self.pid() as libc::pid_t, libc::SIGTERM) };
        assert_eq!(rc, 0, "kill -TERM {}", self.pid());
    }

    /// Wait up to `timeout` for the process to exit.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let start = Instant::now();
        while start.elapsed() < timeout {
            if let Ok(Some(status)) = self.child.try_wait() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }

    /// Whether the process is still running.
    pub fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// The last log lines (for failure messages).
    pub fn logs(&self) -> String {
        self.logs.lock().unwrap().join("\n")
    }

    /// The logs once a line holds `needle`: they reach the test through a thread draining
    /// the server's stdout, which may lag its answers. Fails the test after `timeout`.
    pub async fn logs_with(&self, needle: &str, timeout: Duration) -> String {
        let start = std::time::Instant::now();
        loop {
            let logs = self.logs();
            if logs.contains(needle) {
                return logs;
            }
            assert!(
                start.elapsed() < timeout,
                "no {needle:?} in the logs: {logs}"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// A field of /proc/<pid>/status in kB (`VmRSS`, `VmHWM`).
    pub fn memory_kb(&self, field: &str) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.pid()))
            .expect("read the server's /proc status");
        status
            .lines()
            .find_map(|l| {
                l.strip_prefix(field)?
                    .trim_start_matches(':')
                    .trim()
                    .trim_end_matches("kB")
                    .trim()
                    .parse()
                    .ok()
            })
            .unwrap_or_else(|| panic!("no {field} in /proc status"))
    }

    /// Poll `GET path` until `done(json)`; panics after `timeout`.
    pub async fn wait_json(
        &self,
        path: &str,
        timeout: Duration,
        done: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let start = Instant::now();
        loop {
            if let Ok(r) = self.client.get(self.url(path)).send().await
                && r.status() == 200
                && let Ok(v) = r.json::<serde_json::Value>().await
                && done(&v)
            {
                return v;
            }
            assert!(
                start.elapsed() < timeout,
                "GET {path} not done after {timeout:?}; server log:\n{}",
                self.logs()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for BinServer {
    fn drop(&mut self) {
        self.kill();
    }
}
