//! The request body behind a tap: it enforces the body size limit, and lets a handler
//! drain what is left after refusing an upload, so that the client reads the refusal
//! instead of a reset connection (a lingering close).

use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, BodyDataStream, Bytes};
use futures_util::{Stream, StreamExt};

/// The request body, shared between the multipart parser and the handler: it enforces the
/// body size limit, and lets the handler drain what is left after refusing an upload, so
/// that the client reads the refusal instead of a reset connection (a lingering close).
#[derive(Clone)]
pub struct BodyTap {
    state: Arc<TapState>,
}

struct TapState {
    stream: Mutex<BodyDataStream>,
    seen: AtomicU64,
    limit: u64,
    exceeded: AtomicBool,
}

/// How long a refused upload's remaining body is read and discarded (a lingering close,
/// so that the client gets to read the refusal instead of a broken pipe).
pub const LINGER: std::time::Duration = std::time::Duration::from_secs(5);

impl BodyTap {
    pub fn new(body: Body, limit: u64) -> Self {
        Self {
            state: Arc::new(TapState {
                stream: Mutex::new(body.into_data_stream()),
                seen: AtomicU64::new(0),
                limit,
                exceeded: AtomicBool::new(false),
            }),
        }
    }

    /// A body for the multipart parser that reads through the tap.
    pub fn body(&self) -> Body {
        Body::from_stream(TapReader(self.state.clone()))
    }

    /// Whether the body went over the limit.
    pub fn exceeded(&self) -> bool {
        self.state.exceeded.load(Ordering::SeqCst)
    }

    /// Read and discard the rest of the body, for at most `max`.
    pub async fn drain(&self, max: Duration) {
        let state = self.state.clone();
        let _ = tokio::time::timeout(max, async move {
            loop {
                let next = std::future::poll_fn(|cx| {
                    state
                        .stream
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .poll_next_unpin(cx)
                })
                .await;
                if !matches!(next, Some(Ok(_))) {
                    break;
                }
            }
        })
        .await;
    }
}

struct TapReader(Arc<TapState>);

impl Stream for TapReader {
    type Item = Result<Bytes, std::io::Error>;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let state = &self.0;
        if state.exceeded.load(Ordering::SeqCst) {
            return Poll::Ready(Some(Err(too_large_error())));
        }
        let polled = state
            .stream
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .poll_next_unpin(cx);
        match polled {
            Poll::Ready(Some(Ok(bytes))) => {
                let seen =
                    state.seen.fetch_add(bytes.len() as u64, Ordering::SeqCst) + bytes.len() as u64;
                if seen > state.limit {
                    state.exceeded.store(true, Ordering::SeqCst);
                    Poll::Ready(Some(Err(too_large_error())))
                } else {
                    Poll::Ready(Some(Ok(bytes)))
                }
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(std::io::Error::other(e)))),
            Poll::Ready(None) => Poll::Ready(None),
            Poll::Pending => Poll::Pending,
        }
    }
}

fn too_large_error() -> std::io::Error {
    std::io::Error::other("the request body is over the size limit")
}
