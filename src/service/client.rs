//! The project's one HTTP/1.1 client, on `tokio::net::TcpStream`: requests (with a body
//! held in memory, or none) over keep-alive connections, Content-Length and chunked
//! responses, or only the status line. `photostereo healthcheck`, webhook deliveries and
//! the bench use it; plain `http://` only, and callers bound every wait with a timeout.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, anyhow, bail, ensure};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

/// Longest a connection or one request (or one upload) may take, unless told otherwise.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);
/// Largest response body read (status JSON is a few kB).
const MAX_BODY: usize = 16 << 20;

/// One HTTP/1.1 connection.
pub struct Conn {
    pub stream: BufReader<TcpStream>,
    host: String,
    /// The server said `Connection: close` (or the stream failed).
    pub closed: bool,
}

pub struct Response {
    pub status: u16,
    pub body: Vec<u8>,
}

impl Response {
    pub fn describe(&self) -> String {
        let body = String::from_utf8_lossy(&self.body);
        let body: String = body.chars().take(300).collect();
        format!("HTTP {} {body}", self.status)
    }
}

impl Conn {
    /// Connect to `addr` (within [`REQUEST_TIMEOUT`]); requests name it as their `Host`.
    pub async fn connect(addr: SocketAddr) -> anyhow::Result<Self> {
        let stream = tokio::time::timeout(REQUEST_TIMEOUT, TcpStream::connect(addr))
            .await
            .map_err(|_| anyhow!("connecting to {addr} timed out"))?
            .with_context(|| format!("connecting to {addr}"))?;
        Self::over(stream, addr.to_string())
    }

    /// A connection over `stream`, whose requests name `host` as their `Host`.
    pub fn over(stream: TcpStream, host: String) -> anyhow::Result<Self> {
        stream.set_nodelay(true)?;
        Ok(Self {
            stream: BufReader::new(stream),
            host,
            closed: false,
        })
    }

    /// A request without a body, and its response.
    pub async fn request(&mut self, method: &str, path: &str) -> anyhow::Result<Response> {
        self.send(method, path, &[], None, REQUEST_TIMEOUT).await
    }

    /// A request with extra headers and a body (sent with its Content-Length), and its
    /// response, within `timeout`.
    pub async fn send(
        &mut self,
        method: &str,
        path: &str,
        headers: &[(&str, &str)],
        body: Option<&[u8]>,
        timeout: Duration,
    ) -> anyhow::Result<Response> {
        let exchange = async {
            self.write_request(method, path, headers, body).await?;
            self.read_response().await
        };
        let r = tokio::time::timeout(timeout, exchange).await;
        match r {
            Ok(Ok(r)) => Ok(r),
            Ok(Err(e)) => {
                self.closed = true;
                Err(e.context(format!("{method} {path}")))
            }
            Err(_) => {
                self.closed = true;
                bail!("{method} {path}: no answer within {timeout:?}")
            }
        }
    }

    /// Send a request: the request line, `Host`, `headers`, and with a body its
    /// Content-Length and the body.
    pub async fn write_request(
        &mut self,
        method: &str,
        path: &str,
        headers: &[(&str, &str)],
        body: Option<&[u8]>,
    ) -> std::io::Result<()> {
        let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {}\r\n", self.host);
        for (name, value) in headers {
            head.push_str(&format!("{name}: {value}\r\n"));
        }
        if let Some(body) = body {
            head.push_str(&format!("Content-Length: {}\r\n", body.len()));
        }
        head.push_str("\r\n");
        let w = self.stream.get_mut();
        w.write_all(head.as_bytes()).await?;
        if let Some(body) = body {
            w.write_all(body).await?;
        }
        w.flush().await
    }

    /// The answer's first bytes up to and including its first line end (at most 8 KiB;
    /// less when the server closes first), for callers that need only the status.
    pub async fn read_status_line(&mut self) -> std::io::Result<Vec<u8>> {
        let mut line = Vec::new();
        (&mut self.stream)
            .take(8192)
            .read_until(b'\n', &mut line)
            .await?;
        Ok(line)
    }

    /// Read one response: status line, headers, then a Content-Length or chunked body.
    pub async fn read_response(&mut self) -> anyhow::Result<Response> {
        let head = self.read_until_blank_line().await?;
        let head = String::from_utf8(head).context("response head is not UTF-8")?;
        let mut lines = head.split("\r\n");
        let status_line = lines.next().unwrap_or_default();
        let status: u16 = status_line
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| anyhow!("bad status line {status_line:?}"))?;
        let mut length = None;
        let mut chunked = false;
        for line in lines.filter(|l| !l.is_empty()) {
            let Some((name, value)) = line.split_once(':') else {
                bail!("bad header line {line:?}");
            };
            let value = value.trim();
            if name.eq_ignore_ascii_case("content-length") {
                length = Some(value.parse::<usize>().context("Content-Length")?);
            } else if name.eq_ignore_ascii_case("transfer-encoding") {
                chunked = value.to_ascii_lowercase().contains("chunked");
            } else if name.eq_ignore_ascii_case("connection") && value.eq_ignore_ascii_case("close")
            {
                self.closed = true;
            }
        }
        let mut body = Vec::new();
        if status == 204 || status == 304 || (100..200).contains(&status) {
            // No body.
        } else if chunked {
            loop {
                let line = self.read_line().await?;
                let size_text = line.split(';').next().unwrap_or_default().trim();
                let size = usize::from_str_radix(size_text, 16)
                    .with_context(|| format!("bad chunk size {size_text:?}"))?;
                if size == 0 {
                    // Trailers, then the blank line.
                    self.skip_trailers().await?;
                    break;
                }
                ensure!(body.len() + size <= MAX_BODY, "response body too large");
                let at = body.len();
                body.resize(at + size, 0);
                self.stream.read_exact(&mut body[at..]).await?;
                let mut crlf = [0u8; 2];
                self.stream.read_exact(&mut crlf).await?;
                ensure!(&crlf == b"\r\n", "chunk not followed by CRLF");
            }
        } else if let Some(n) = length {
            ensure!(n <= MAX_BODY, "response body too large ({n} bytes)");
            body.resize(n, 0);
            self.stream.read_exact(&mut body).await?;
        } else {
            // Delimited by the end of the connection.
            self.closed = true;
            (&mut self.stream)
                .take(MAX_BODY as u64)
                .read_to_end(&mut body)
                .await?;
        }
        Ok(Response { status, body })
    }

    /// Bytes up to and including the first empty line (`\r\n\r\n`), at most 64 KiB.
    async fn read_until_blank_line(&mut self) -> anyhow::Result<Vec<u8>> {
        let mut head: Vec<u8> = Vec::new();
        loop {
            let (used, found) = {
                let buf = self.stream.fill_buf().await?;
                if buf.is_empty() {
                    self.closed = true;
                    bail!("the server closed the connection");
                }
                let from = head.len().saturating_sub(3);
                let before = head.len();
                head.extend_from_slice(buf);
                match head[from..].windows(4).position(|w| w == b"\r\n\r\n") {
                    Some(pos) => {
                        let end = from + pos + 4;
                        head.truncate(end);
                        (end - before, true)
                    }
                    None => (buf.len(), false),
                }
            };
            self.stream.consume(used);
            if found {
                return Ok(head);
            }
            ensure!(head.len() <= 64 << 10, "response head over 64 KiB");
        }
    }

    /// One CRLF-terminated line (without the CRLF), at most 4 KiB.
    async fn read_line(&mut self) -> anyhow::Result<String> {
        let mut line = Vec::new();
        let n = (&mut self.stream)
            .take(4096)
            .read_until(b'\n', &mut line)
            .await?;
        ensure!(
            n > 0 && line.ends_with(b"\n"),
            "truncated line in the response"
        );
        line.pop();
        if line.ends_with(b"\r") {
            line.pop();
        }
        String::from_utf8(line).context("line is not UTF-8")
    }

    /// After the last chunk: trailer lines up to the empty line.
    async fn skip_trailers(&mut self) -> anyhow::Result<()> {
        for _ in 0..100 {
            if self.read_line().await?.is_empty() {
                return Ok(());
            }
        }
        bail!("too many trailer lines")
    }
}
