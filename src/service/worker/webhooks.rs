//! Webhooks: when a job with a `callback_url` ends, the job resource is POSTed there,
//! signed, and retried with exponential backoff for a bounded time.
//!
//! - Only hosts on `--webhook-allow-host` may be called (none by default), checked when
//!   the job is submitted and again at each delivery, where a name must also resolve to
//!   public addresses only unless the address itself is listed (so DNS cannot point a
//!   listed name at an internal network). Redirects are answers like any other non-2xx:
//!   not followed.
//! - `Webhook-Timestamp: <unix seconds>` and `Webhook-Signature: v1=<hex>`, the
//!   HMAC-SHA256 of `<timestamp>.<body>` under the tenant's webhook secret.
//! - Plain `http://` over the service's HTTP/1.1 client (`client`, one request per
//!   connection); put a TLS-terminating proxy on the allow-list for `https` receivers.

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::Duration;

use hyper::Uri;
use sha2::{Digest, Sha256};
use uuid::Uuid;

use crate::service::repo::{CallbackAttempt, CallbackState, JobRecord};
use crate::service::util::{now_ms, rfc3339};

use crate::service::client::Conn;

use super::runner::Runner;

/// Longest one delivery attempt may take (connect, send, read the status line).
const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(10);

/// A callback URL that passed the submission checks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Target {
    pub host: String,
    pub port: u16,
    /// Path and query.
    pub path: String,
}

/// Check a `callback_url` against the allow-list: why not, prefixed `callback_url: `.
pub fn parse_target(url: &str, allow: &[String]) -> Result<Target, String> {
    let bad = |why: String| format!("callback_url: {why}");
    let uri: Uri = url
        .parse()
        .map_err(|_| bad(format!("{url:?} is not a URL")))?;
    match uri.scheme_str() {
        Some("http") => {}
        Some(other) => {
            return Err(bad(format!(
                "the scheme {other:?} is not supported; use http:// (through a TLS-terminating proxy for https receivers)"
            )));
        }
        None => return Err(bad(format!("{url:?} is not an absolute http:// URL"))),
    }
    let authority = uri
        .authority()
        .ok_or_else(|| bad(format!("{url:?} names no host")))?;
    if authority.as_str().contains('@') {
        return Err(bad("user information in the URL is not allowed".into()));
    }
    let host = authority
        .host()
        .trim_start_matches('[')
        .trim_end_matches(']')
        .to_ascii_lowercase();
    if !allow.iter().any(|a| a.eq_ignore_ascii_case(&host)) {
        return Err(bad(format!(
            "the host {host:?} is not on this server's webhook allow-list (--webhook-allow-host)"
        )));
    }
    // The authority's own text: `http` drops a port it cannot read as u16 (99999 would
    // become the default port).
    let after_host = authority
        .as_str()
        .rsplit_once(']')
        .map_or(authority.as_str(), |(_, rest)| rest);
    let port = match after_host.rsplit_once(':') {
        None => 80,
        Some((_, p)) => match p.parse::<u16>() {
            Ok(n) if n >= 1 && p.bytes().all(|b| b.is_ascii_digit()) => n,
            _ => {
                return Err(bad(format!(
                    "the port {p:?} is not a port number (1 to 65535)"
                )));
            }
        },
    };
    Ok(Target {
        host,
        port,
        path: uri
            .path_and_query()
            .map(|p| p.as_str().to_string())
            .unwrap_or_else(|| "/".into()),
    })
}

/// Addresses a webhook may reach only when they are listed themselves.
fn is_internal(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => {
            v4.is_loopback()
                || v4.is_private()
                || v4.is_link_local()
                || v4.is_unspecified()
                || v4.is_broadcast()
                || v4.is_multicast()
                || v4.octets()[0] == 100 && (v4.octets()[1] & 0xc0) == 64 // shared 100.64/10
        }
        IpAddr::V6(v6) => {
            if let Some(v4) = v6.to_ipv4_mapped() {
                return is_internal(IpAddr::V4(v4));
            }
            v6.is_loopback()
                || v6.is_unspecified()
                || v6.is_multicast()
                || (v6.segments()[0] & 0xfe00) == 0xfc00 // unique local
                || (v6.segments()[0] & 0xffc0) == 0xfe80 // link local
        }
    }
}

/// The signature header's value: `v1=` and the hex HMAC-SHA256 of `timestamp.body`.
pub fn signature(secret: &[u8], timestamp: u64, body: &[u8]) -> String {
    let mut message = format!("{timestamp}.").into_bytes();
    message.extend_from_slice(body);
    let mac = hmac_sha256(secret, &message);
    format!(
        "v1={}",
        mac.iter().map(|b| format!("{b:02x}")).collect::<String>()
    )
}

/// HMAC (RFC 2104) over SHA-256.
fn hmac_sha256(key: &[u8], message: &[u8]) -> [u8; 32] {
    const BLOCK: usize = 64;
    let mut k = [0u8; BLOCK];
    if key.len() > BLOCK {
        k[..32].copy_from_slice(&Sha256::digest(key));
    } else {
        k[..key.len()].copy_from_slice(key);
    }
    let pad = |byte: u8| k.map(|b| b ^ byte);
    let inner = Sha256::new()
        .chain_update(pad(0x36))
        .chain_update(message)
        .finalize();
    Sha256::new()
        .chain_update(pad(0x5c))
        .chain_update(inner)
        .finalize()
        .into()
}

/// One delivery: check the target again, POST `body`, return the status code (or why
/// there is none).
pub async fn post(
    target: &Target,
    allow: &[String],
    headers: &[(&str, String)],
    body: &[u8],
) -> Result<u16, String> {
    if !allow.iter().any(|a| a.eq_ignore_ascii_case(&target.host)) {
        return Err(format!(
            "the host {} is no longer allow-listed",
            target.host
        ));
    }
    let attempt = async {
        let addrs: Vec<_> = tokio::net::lookup_host((target.host.as_str(), target.port))
            .await
            .map_err(|e| format!("cannot resolve {}: {e}", target.host))?
            .collect();
        let listed = |ip: IpAddr| allow.iter().any(|a| a.parse::<IpAddr>().ok() == Some(ip));
        let addr = addrs
            .iter()
            .find(|a| !is_internal(a.ip()) || listed(a.ip()))
            .ok_or_else(|| {
                format!(
                    "{} resolves only to internal addresses that are not allow-listed",
                    target.host
                )
            })?;
        let stream = tokio::net::TcpStream::connect(addr)
            .await
            .map_err(|e| format!("cannot connect to {addr}: {e}"))?;
        let host = format!("{}:{}", target.host, target.port);
        let mut conn =
            Conn::over(stream, host).map_err(|e| format!("cannot connect to {addr}: {e}"))?;
        let mut fields = vec![
            ("Content-Type", "application/json"),
            ("Connection", "close"),
            ("User-Agent", "photostereo-webhook"),
        ];
        fields.extend(headers.iter().map(|(name, value)| (*name, value.as_str())));
        conn.write_request("POST", &target.path, &fields, Some(body))
            .await
            .map_err(|e| format!("sending: {e}"))?;
        let answer = conn
            .read_status_line()
            .await
            .map_err(|e| format!("reading the answer: {e}"))?;
        status_code(&answer).ok_or_else(|| {
            let end = answer
                .iter()
                .position(|&b| b == b'\r')
                .unwrap_or(answer.len());
            format!(
                "the receiver did not answer with an HTTP/1.x status line: {:?}",
                String::from_utf8_lossy(&answer[..end.min(80)])
            )
        })
    };
    tokio::time::timeout(ATTEMPT_TIMEOUT, attempt)
        .await
        .unwrap_or_else(|_| Err(format!("no answer within {} s", ATTEMPT_TIMEOUT.as_secs())))
}

/// The status of an HTTP/1.x answer: `HTTP/1.<digit> <3 digits>` followed by a space or
/// the line's end (RFC 9112 §4), nothing looser: `HTTP/1.1 2000 OK` is no 200.
fn status_code(answer: &[u8]) -> Option<u16> {
    let rest = answer.strip_prefix(b"HTTP/1.")?;
    let (minor, code, after) = (rest.first()?, rest.get(2..5)?, rest.get(5));
    let well_formed = minor.is_ascii_digit()
        && rest.get(1) == Some(&b' ')
        && code.iter().all(u8::is_ascii_digit)
        && matches!(after, Some(b' ' | b'\r'));
    let status = std::str::from_utf8(code).ok()?.parse::<u16>().ok()?;
    (well_formed && (100..=599).contains(&status)).then_some(status)
}

/// `--webhook-secret` values (`tenant:secret`) by tenant.
pub fn parse_secrets(values: &[String]) -> anyhow::Result<HashMap<String, Vec<u8>>> {
    let mut out = HashMap::new();
    for (i, v) in values.iter().enumerate() {
        let (tenant, secret) = v
            .trim()
            .split_once(':')
            .filter(|(t, s)| !t.is_empty() && !s.is_empty())
            .ok_or_else(|| {
                anyhow::anyhow!("--webhook-secret value {} is not tenant:secret", i + 1)
            })?;
        out.insert(tenant.to_string(), secret.as_bytes().to_vec());
    }
    Ok(out)
}

/// Deliver the end of job `id`, if it has a callback, on the runtime: attempts with
/// exponential backoff until one is answered with 2xx or `--webhook-retry-for` has passed
/// since the job ended, each recorded on the job. A callback that already has attempts
/// (resumed after a restart) goes on from the delay its attempts have reached.
pub(crate) fn job_ended(runner: &Runner, id: Uuid) {
    let repo = runner.repo.clone();
    let Ok(Some(job)) = repo.get(id) else { return };
    let Some(mut callback) = job.callback.clone() else {
        return;
    };
    let Some(secret) = runner.webhook_secrets.get(&job.tenant).cloned() else {
        return; // checked at submission; the secret was removed since
    };
    let allow = runner.config.webhook_allow_hosts.clone();
    let deadline = give_up_at(&job, runner.config.webhook_retry_for);
    let tried = u32::try_from(callback.attempts.len()).unwrap_or(u32::MAX);
    let mut delay = runner.config.webhook_first_retry * 2u32.saturating_pow(tried.min(20));
    let render = runner.render.job;
    let mut stop = runner.stop.subscribe();
    runner.runtime.spawn(async move {
        let target = parse_target(&callback.url, &allow);
        loop {
            let r = repo.clone();
            let Ok(Ok(Some(job))) = tokio::task::spawn_blocking(move || r.get(id)).await else {
                return; // deleted meanwhile
            };
            let body = render(job);
            let now = now_ms();
            let ts = (now / 1000) as u64;
            let outcome = match &target {
                Ok(t) => {
                    let headers = [
                        ("Webhook-Id", id.to_string()),
                        ("Webhook-Timestamp", ts.to_string()),
                        ("Webhook-Signature", signature(&secret, ts, body.as_bytes())),
                    ];
                    post(t, &allow, &headers, body.as_bytes()).await
                }
                Err(e) => Err(e.clone()),
            };
            let delivered = matches!(outcome, Ok(200..=299));
            let (status, error) = match outcome {
                Ok(code) => (Some(code), None),
                Err(why) => (None, Some(why)),
            };
            callback.attempts.push(CallbackAttempt {
                at: rfc3339(now),
                status,
                error,
            });
            let out_of_time = now_ms().saturating_add(millis(delay)) > deadline;
            callback.state = match (delivered, out_of_time) {
                (true, _) => CallbackState::Delivered,
                (false, true) => CallbackState::Failed,
                (false, false) => CallbackState::Pending,
            };
            let (r, c) = (repo.clone(), callback.clone());
            let _ = tokio::task::spawn_blocking(move || r.set_callback(id, &c)).await;
            if callback.state != CallbackState::Pending {
                tracing::info!(job = %id, state = ?callback.state, attempts = callback.attempts.len(), "webhook done");
                return;
            }
            tokio::select! {
                _ = tokio::time::sleep(delay) => {}
                _ = stop.changed() => return,
            }
            delay *= 2;
        }
    });
}

/// Startup: go on delivering the callbacks of jobs that ended before the last stop but
/// were not delivered yet (a stop, or a crash, between a job's end and its delivery, or
/// during the retries). Those whose retry window closed meanwhile are given up as failed
/// without another attempt. Returns how many deliveries were resumed.
pub(crate) fn resume(runner: &Runner) -> anyhow::Result<usize> {
    // Every record is read once (there is no index on the callback's state); a startup
    // already reads every job's record to tidy the data directory.
    const PAGE: usize = 500;
    let mut before = None;
    let mut resumed = 0;
    loop {
        let page = runner.repo.list(None, PAGE, before)?;
        for job in &page {
            let Some(callback) = &job.callback else {
                continue;
            };
            if !job.status.is_terminal() || callback.state != CallbackState::Pending {
                continue;
            }
            if now_ms() < give_up_at(job, runner.config.webhook_retry_for) {
                job_ended(runner, job.id);
                resumed += 1;
            } else {
                let mut given_up = callback.clone();
                given_up.state = CallbackState::Failed;
                runner.repo.set_callback(job.id, &given_up)?;
                tracing::info!(job = %job.id, attempts = given_up.attempts.len(), "webhook given up: its retry window closed while the service was stopped");
            }
        }
        match page.last() {
            Some(last) if page.len() == PAGE => before = Some((last.created_at, last.id)),
            _ => return Ok(resumed),
        }
    }
}

/// When the retries of a job's callback stop: `retry_for` after the job ended.
fn give_up_at(job: &JobRecord, retry_for: Duration) -> i64 {
    job.finished_at
        .unwrap_or_else(now_ms)
        .saturating_add(millis(retry_for))
}

fn millis(d: Duration) -> i64 {
    i64::try_from(d.as_millis()).unwrap_or(i64::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hmac_matches_rfc_4231() {
        // Test case 2 of RFC 4231.
        let mac = hmac_sha256(b"Jefe", b"what do ya want for nothing?");
        let hex: String = mac.iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(
            hex,
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        // Test case 6: a key longer than the block.
        let mac = hmac_sha256(
            &[0xaa; 131],
            b"Test Using Larger Than Block-Size Key - Hash Key First",
        );
        assert_eq!(mac[..4], [0x60, 0xe4, 0x31, 0x59]);
        assert!(signature(b"k", 5, b"{}").starts_with("v1="));
    }

    #[test]
    fn status_lines_are_read_strictly() {
        for (line, want) in [
            (&b"HTTP/1.1 200 OK\r\n"[..], Some(200)),
            (b"HTTP/1.0 204\r\n", Some(204)),
            (b"HTTP/1.1 503 Busy\r\n", Some(503)),
            (b"HTTP/1.1 2000 OK\r\n", None),
            (b"HTTP/1.1 20 OK\r\n", None),
            (b"HTTP/1.1 +20 OK\r\n", None),
            (b"HTTP/1.1 099 Low\r\n", None),
            (b"HTTP/1.1  200 OK\r\n", None),
            (b"HTTP/2 200 OK\r\n", None),
            (b"HTTP/1.1 200", None),
            (b"SIP/1.1 200 OK\r\n", None),
        ] {
            assert_eq!(
                status_code(line),
                want,
                "{:?}",
                String::from_utf8_lossy(line)
            );
        }
    }

    #[test]
    fn internal_addresses_are_known() {
        for ip in [
            "127.0.0.1",
            "10.1.2.3",
            "192.168.0.1",
            "169.254.169.254",
            "::1",
            "fd00::1",
            "::ffff:127.0.0.1",
            "100.64.0.1",
        ] {
            assert!(is_internal(ip.parse().unwrap()), "{ip}");
        }
        for ip in ["93.184.216.34", "2606:4700::1"] {
            assert!(!is_internal(ip.parse().unwrap()), "{ip}");
        }
    }
}
