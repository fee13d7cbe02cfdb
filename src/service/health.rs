//! `photostereo healthcheck`: a GET through the service's HTTP/1.1 client, for container
//! health checks (the runtime image has no curl).

use std::time::Duration;

use anyhow::{Context, bail};
use tokio::net::TcpStream;

use super::client::Conn;

/// Arguments of `photostereo healthcheck`.
#[derive(Debug, Clone, clap::Args)]
pub struct HealthcheckArgs {
    /// URL to GET; the check passes on a 2xx answer within the timeout.
    #[arg(
        long,
        env = "PHOTOSTEREO_HEALTHCHECK_URL",
        default_value = "http://127.0.0.1:8080/healthz"
    )]
    pub url: String,
}

/// GET `url` (plain `http://host[:port]/path`) and succeed on a 2xx status within 5 s.
pub async fn healthcheck(url: &str) -> anyhow::Result<()> {
    tokio::time::timeout(Duration::from_secs(5), get_status(url))
        .await
        .with_context(|| format!("{url}: no answer within 5 s"))?
        .and_then(|status| {
            if (200..300).contains(&status) {
                Ok(())
            } else {
                bail!("{url}: HTTP status {status}")
            }
        })
}

/// Split `http://host[:port]/path` into (host, port, path).
fn parse_url(url: &str) -> anyhow::Result<(String, u16, String)> {
    let rest = url
        .strip_prefix("http://")
        .with_context(|| format!("{url}: only http:// URLs are supported"))?;
    let (authority, path) = match rest.find('/') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, "/"),
    };
    if authority.is_empty() {
        bail!("{url}: no host");
    }
    let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
        let (h, after) = v6
            .split_once(']')
            .with_context(|| format!("{url}: unclosed [ in host"))?;
        let port = after.strip_prefix(':').unwrap_or("80");
        (h.to_string(), port)
    } else {
        match authority.rsplit_once(':') {
            Some((h, p)) => (h.to_string(), p),
            None => (authority.to_string(), "80"),
        }
    };
    let port: u16 = port
        .parse()
        .with_context(|| format!("{url}: invalid port {port:?}"))?;
    Ok((host, port, path.to_string()))
}

async fn get_status(url: &str) -> anyhow::Result<u16> {
    let (host, port, path) = parse_url(url)?;
    let stream = TcpStream::connect((host.as_str(), port))
        .await
        .with_context(|| format!("{url}: cannot connect"))?;
    let host_header = if host.contains(':') {
        format!("[{host}]:{port}")
    } else {
        format!("{host}:{port}")
    };
    let mut conn = Conn::over(stream, host_header)?;
    let headers = [
        ("User-Agent", "photostereo-healthcheck"),
        ("Connection", "close"),
    ];
    conn.write_request("GET", &path, &headers, None).await?;
    let head = conn.read_status_line().await?;
    let line = String::from_utf8_lossy(&head);
    let status_line = line.lines().next().unwrap_or_default();
    let mut fields = status_line.split_whitespace();
    match (
        fields.next(),
        fields.next().and_then(|s| s.parse::<u16>().ok()),
    ) {
        (Some(v), Some(code)) if v.starts_with("HTTP/") => Ok(code),
        _ => bail!("{url}: not an HTTP answer: {status_line:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls() {
        assert_eq!(
            parse_url("http://127.0.0.1:8080/healthz").unwrap(),
            ("127.0.0.1".into(), 8080, "/healthz".into())
        );
        assert_eq!(
            parse_url("http://localhost").unwrap(),
            ("localhost".into(), 80, "/".into())
        );
        assert_eq!(
            parse_url("http://[::1]:9000/readyz").unwrap(),
            ("::1".into(), 9000, "/readyz".into())
        );
        assert!(parse_url("https://x/").is_err());
        assert!(parse_url("http://x:port/").is_err());
    }
}
