//! One HTTP/1.1 answer read off a raw socket, for tests that speak to the server below
//! what a client library allows (trickled heads, dropped connections, canned refusals).

use serde_json::Value;
use tokio::io::AsyncReadExt;

/// A status, the head as text, and the body.
pub struct RawAnswer {
    pub status: u16,
    pub head: String,
    pub body: Vec<u8>,
}

impl RawAnswer {
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }

    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("{e}: {}", self.text()))
    }

    pub fn is_problem(&self) -> bool {
        self.head
            .to_ascii_lowercase()
            .contains("content-type: application/problem+json")
    }
}

/// Read one answer: its head, then Content-Length bytes or up to EOF. None when the
/// connection ends before a whole head, or the status line is not one.
pub async fn read_answer(stream: &mut (impl AsyncReadExt + Unpin)) -> Option<RawAnswer> {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    let end = loop {
        if let Some(p) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break p;
        }
        let n = stream.read(&mut chunk).await.ok()?;
        if n == 0 {
            return None;
        }
        buf.extend_from_slice(&chunk[..n]);
    };
    let head = String::from_utf8_lossy(&buf[..end]).into_owned();
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    let length: Option<usize> = head.lines().find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.eq_ignore_ascii_case("content-length")
            .then(|| v.trim().parse().ok())?
    });
    let mut body = buf[end + 4..].to_vec();
    while length.is_none_or(|n| body.len() < n) {
        match stream.read(&mut chunk).await {
            Ok(0) | Err(_) => break,
            Ok(n) => body.extend_from_slice(&chunk[..n]),
        }
    }
    Some(RawAnswer { status, head, body })
}
