//! The bench's HTTP/1.1 connections: the service's client ([`photostereo::service::client`]),
//! to the bench's own servers on loopback only.

use std::net::SocketAddr;

use anyhow::ensure;

pub(super) use photostereo::service::client::{Conn, REQUEST_TIMEOUT, Response};

/// A connection to `addr`, which must be a loopback address.
pub(super) async fn connect(addr: SocketAddr) -> anyhow::Result<Conn> {
    ensure!(addr.ip().is_loopback(), "the bench only talks to loopback");
    Conn::connect(addr).await
}
