//! The HTTP server's accept loop and connections: a cap on how many are open and the
//! timeouts that close the ones a client leaves hanging (`axum::serve` has neither).
//!
//! A connection is always in one of three states ([`Conn`]):
//! - **reading a request head**: `--header-timeout` from the head's first byte (for the
//!   first request, from the accept, so a client that sends nothing is closed too);
//!   trickling bytes does not extend it;
//! - **a request in flight**, from its head until its response body is dropped: no
//!   timeout (uploads have their own), but `--send-timeout` while the client reads nothing
//!   of the response;
//! - **idle between requests**: closed after `--keep-alive-timeout`.
//!
//! At `--max-connections`, a new connection takes the place of the one idle longest
//! (reading a head or between requests: neither has work under way), so idle and
//! trickling sockets arriving faster than the timeouts expire cannot keep probes and
//! clients out. Only when every open connection has a request in flight is a new one
//! refused: a canned 503 written without reading the request, then closed. Running out
//! of descriptors anyway (other files) closes the longest-idle connection too.

mod limits;

use limits::LINGERING;
pub use limits::{Limits, raise_open_files_limit};

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::Router;
use axum::body::{Body, Bytes};
use http_body::{Frame, SizeHint};
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, Semaphore, watch};

use super::config::RETRY_AFTER_SECS;
use super::error::ApiError;
use super::metrics::ConnectionCounters;

/// Largest HTTP/1 request head (431 past it), and what a connection buffers of a body:
/// the bound on a trickling head's memory.
const MAX_HEAD_BYTES: usize = 32 << 10;
/// HTTP/2 (h2c): streams per connection, bytes queued to send per stream, receive
/// windows. Together they bound what one HTTP/2 connection holds.
const H2_STREAMS: u32 = 16;
const H2_SEND_BUFFER: usize = 64 << 10;
const H2_WINDOW: u32 = 256 << 10;
const LINGER: Duration = Duration::from_secs(1);
/// At most one log line per kind of trouble in this interval.
const LOG_EVERY: Duration = Duration::from_secs(10);
/// A time that has not happened, in [`Registry::now`] units.
const NEVER: u64 = u64::MAX;

/// What the open connections are told when the server stops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stop {
    Serving,
    /// Finish the request in flight, then close; idle connections close at once.
    Finishing,
    /// The shutdown grace is over: close now.
    Abandon,
}

/// Serve `app` on `listener` until `shutdown` completes; then `on_shutdown`, no new
/// connections, idle ones closed, requests in flight finished for up to `grace`.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: Limits,
    counters: Arc<ConnectionCounters>,
    shutdown: impl Future<Output = ()>,
    on_shutdown: impl FnOnce(),
    grace: Duration,
) {
    counters.limit.store(limits.max_connections as u64, Relaxed);
    tracing::info!(
        max_connections = limits.max_connections,
        header_timeout = ?limits.header_timeout,
        keep_alive_timeout = ?limits.keep_alive_timeout,
        send_timeout = ?limits.send_timeout,
        "connection limits"
    );
    let registry = Arc::new(Registry::new(limits, counters));
    let builder = Arc::new(builder());
    let refusal = Refusal::new(limits.max_connections);
    let (stop, stopped) = watch::channel(Stop::Serving);
    let mut out_of_files = Every::default();
    let mut accept_failed = Every::default();
    tokio::pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            biased;
            () = &mut shutdown => break,
            accepted = listener.accept() => accepted,
        };
        let stream = match accepted {
            Ok((stream, _)) => stream,
            Err(e) if out_of_descriptors(&e) => {
                if !registry.evict_longest_idle() {
                    out_of_files.note(|n| {
                        tracing::warn!(error = %e, times = n, "cannot accept connections: out of descriptors, and none is idle")
                    });
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
                continue;
            }
            Err(e) if is_connection_error(&e) => continue,
            Err(e) => {
                accept_failed.note(|n| tracing::warn!(error = %e, times = n, "accept failed"));
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Some(conn) = registry.admit() else {
            refusal.refuse(stream, &registry.counters);
            continue;
        };
        let _ = stream.set_nodelay(true);
        let task = Task {
            registry: registry.clone(),
            conn,
            app: app.clone(),
            builder: builder.clone(),
            stop: stopped.clone(),
        };
        tokio::spawn(task.run(stream));
    }
    on_shutdown();
    drop(listener);
    let _ = stop.send(Stop::Finishing);
    let drained = async {
        while registry.open() > 0 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    };
    if tokio::time::timeout(grace, drained).await.is_err() {
        tracing::warn!(
            connections = registry.open(),
            "connections still open after the shutdown grace are dropped"
        );
        let _ = stop.send(Stop::Abandon);
    }
}

/// HTTP/1.1 and HTTP/2 with prior knowledge (h2c), with the buffers bounded. Hyper's own
/// header timeout is off: it would also close connections idle between requests at the
/// head's deadline, and [`Task`] keeps both clocks.
fn builder() -> auto::Builder<TokioExecutor> {
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .max_buf_size(MAX_HEAD_BYTES)
        .header_read_timeout(None);
    builder
        .http2()
        .max_concurrent_streams(H2_STREAMS)
        .max_send_buf_size(H2_SEND_BUFFER)
        .initial_stream_window_size(H2_WINDOW)
        .initial_connection_window_size(H2_WINDOW)
        .max_header_list_size(MAX_HEAD_BYTES as u32);
    builder
}

fn out_of_descriptors(e: &io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM)
    )
}

/// Errors of one connection that accept(2) reports; the next accept is unaffected.
fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
    )
}

/// Why a timeout closed a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Timeout {
    Header,
    KeepAlive,
    Send,
}

/// One connection's state, shared by its task, its IO, its requests and the registry.
struct Conn {
    id: u64,
    accepted: u64,
    /// Requests whose response body is not yet dropped (HTTP/2: several).
    in_flight: AtomicU32,
    /// A request head has arrived on it.
    served: AtomicBool,
    /// When its last request ended (or when it was accepted).
    idle_since: AtomicU64,
    /// When the first byte after its last request arrived; [`NEVER`]: none yet.
    head_started: AtomicU64,
    /// Since when a write has waited for the client to read; [`NEVER`]: none waits.
    write_blocked: AtomicU64,
    /// Its key in the registry's idle set, when listed (changed under the registry lock).
    idle_key: AtomicU64,
    listed: AtomicBool,
    /// Left the registry (evicted or closed); changed under the registry lock.
    gone: AtomicBool,
    evicted: AtomicBool,
    /// Rung when its deadline may have moved earlier, or it was evicted.
    wake: Notify,
}

#[derive(Default)]
struct Slots {
    open: usize,
    /// Connections with no request in flight, by (idle since, id): the first is the one
    /// idle longest.
    idle: BTreeMap<(u64, u64), Arc<Conn>>,
}

/// The open connections: their count, the idle ones in order, the clocks.
struct Registry {
    epoch: Instant,
    limits: Limits,
    counters: Arc<ConnectionCounters>,
    slots: Mutex<Slots>,
    next_id: AtomicU64,
    evictions: Mutex<Every>,
}

impl Registry {
    fn new(limits: Limits, counters: Arc<ConnectionCounters>) -> Self {
        Self {
            epoch: Instant::now(),
            limits,
            counters,
            slots: Mutex::default(),
            next_id: AtomicU64::new(0),
            evictions: Mutex::default(),
        }
    }

    /// Milliseconds since the registry was made.
    fn now(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    fn lock(&self) -> MutexGuard<'_, Slots> {
        self.slots.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn open(&self) -> usize {
        self.lock().open
    }

    /// A place for a new connection: a free one, or the longest-idle connection's.
    fn admit(&self) -> Option<Arc<Conn>> {
        let now = self.now();
        let conn = Arc::new(Conn {
            id: self.next_id.fetch_add(1, Relaxed),
            accepted: now,
            in_flight: AtomicU32::new(0),
            served: AtomicBool::new(false),
            idle_since: AtomicU64::new(now),
            head_started: AtomicU64::new(NEVER),
            write_blocked: AtomicU64::new(NEVER),
            idle_key: AtomicU64::new(now),
            listed: AtomicBool::new(true),
            gone: AtomicBool::new(false),
            evicted: AtomicBool::new(false),
            wake: Notify::new(),
        });
        let mut slots = self.lock();
        if slots.open >= self.limits.max_connections {
            if !self.evict_first(&mut slots) {
                return None;
            }
        } else {
            slots.open += 1;
        }
        slots.idle.insert((now, conn.id), conn.clone());
        self.counters.open.store(slots.open as u64, Relaxed);
        self.counters.accepted.fetch_add(1, Relaxed);
        Some(conn)
    }

    /// Close the longest-idle connection to free its descriptor.
    fn evict_longest_idle(&self) -> bool {
        let mut slots = self.lock();
        if !self.evict_first(&mut slots) {
            return false;
        }
        slots.open -= 1;
        self.counters.open.store(slots.open as u64, Relaxed);
        true
    }

    /// Take the longest-idle connection out (its place stays counted, for the caller to
    /// reuse or free) and tell its task to close it.
    fn evict_first(&self, slots: &mut Slots) -> bool {
        let Some((_, victim)) = slots.idle.pop_first() else {
            return false;
        };
        victim.listed.store(false, Relaxed);
        victim.gone.store(true, Relaxed);
        victim.evicted.store(true, Relaxed);
        victim.wake.notify_one();
        self.counters.evicted.fetch_add(1, Relaxed);
        self.evictions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .note(|n| {
                tracing::warn!(
                    evicted = n,
                    max_connections = self.limits.max_connections,
                    "at the connection cap: idle connections closed to make room"
                )
            });
        true
    }

    /// The connection is closed: free its place (unless eviction did).
    fn leave(&self, conn: &Conn) {
        let mut slots = self.lock();
        if conn.gone.swap(true, Relaxed) {
            return;
        }
        if conn.listed.swap(false, Relaxed) {
            slots.idle.remove(&(conn.idle_key.load(Relaxed), conn.id));
        }
        slots.open -= 1;
        self.counters.open.store(slots.open as u64, Relaxed);
    }

    fn begin_request(&self, conn: &Conn) {
        let mut slots = self.lock();
        conn.served.store(true, Relaxed);
        if conn.in_flight.fetch_add(1, Relaxed) == 0 && conn.listed.swap(false, Relaxed) {
            slots.idle.remove(&(conn.idle_key.load(Relaxed), conn.id));
        }
    }

    fn end_request(&self, conn: &Arc<Conn>) {
        let now = self.now();
        let mut slots = self.lock();
        if conn.in_flight.fetch_sub(1, Relaxed) != 1 {
            return;
        }
        conn.idle_since.store(now, Relaxed);
        conn.head_started.store(NEVER, Relaxed);
        if !conn.gone.load(Relaxed) {
            conn.idle_key.store(now, Relaxed);
            conn.listed.store(true, Relaxed);
            slots.idle.insert((now, conn.id), conn.clone());
        }
        drop(slots);
        conn.wake.notify_one();
    }
}

impl Registry {
    /// The first bytes of a request head after an idle spell start its clock.
    fn read_some(&self, conn: &Conn) {
        if conn.in_flight.load(Relaxed) == 0
            && conn.served.load(Relaxed)
            && conn.head_started.load(Relaxed) == NEVER
        {
            conn.head_started.store(self.now(), Relaxed);
            conn.wake.notify_one();
        }
    }

    fn write_waits(&self, conn: &Conn, waits: bool) {
        let blocked = conn.write_blocked.load(Relaxed) != NEVER;
        if waits && !blocked {
            conn.write_blocked.store(self.now(), Relaxed);
            conn.wake.notify_one();
        } else if !waits && blocked {
            conn.write_blocked.store(NEVER, Relaxed);
        }
    }

    /// When the connection's current state runs out, and which timeout that is.
    fn due(&self, conn: &Conn) -> Option<(u64, Timeout)> {
        let ms = |d: Duration| d.as_millis() as u64;
        let blocked = conn.write_blocked.load(Relaxed);
        let send = (blocked != NEVER).then(|| {
            (
                blocked.saturating_add(ms(self.limits.send_timeout)),
                Timeout::Send,
            )
        });
        if conn.in_flight.load(Relaxed) > 0 {
            return send;
        }
        let head = ms(self.limits.header_timeout);
        let head_started = conn.head_started.load(Relaxed);
        let idle = if !conn.served.load(Relaxed) {
            (conn.accepted + head, Timeout::Header)
        } else if head_started != NEVER {
            (head_started + head, Timeout::Header)
        } else {
            let since = conn.idle_since.load(Relaxed);
            (
                since + ms(self.limits.keep_alive_timeout),
                Timeout::KeepAlive,
            )
        };
        Some(match send {
            Some(send) if send.0 < idle.0 => send,
            _ => idle,
        })
    }

    fn count_timeout(&self, timeout: Timeout) {
        let c = &self.counters;
        match timeout {
            Timeout::Header => &c.header_timeouts,
            Timeout::KeepAlive => &c.keep_alive_timeouts,
            Timeout::Send => &c.send_timeouts,
        }
        .fetch_add(1, Relaxed);
    }
}

/// One connection's task: hyper serving it, and the clocks and signals that close it.
struct Task {
    registry: Arc<Registry>,
    conn: Arc<Conn>,
    app: Router,
    builder: Arc<auto::Builder<TokioExecutor>>,
    stop: watch::Receiver<Stop>,
}

impl Task {
    async fn run(mut self, stream: TcpStream) {
        let registry = self.registry.clone();
        let conn = self.conn.clone();
        let io = TokioIo::new(Watched {
            io: stream,
            registry: registry.clone(),
            conn: conn.clone(),
        });
        let service = Requests {
            app: self.app.clone(),
            registry: registry.clone(),
            conn: conn.clone(),
        };
        let served = self.builder.serve_connection(io, service);
        tokio::pin!(served);
        let mut finishing = false;
        loop {
            if conn.evicted.load(Relaxed) {
                break;
            }
            let due = registry.due(&conn);
            let deadline = match due {
                Some((at, _)) => registry.epoch + Duration::from_millis(at),
                None => Instant::now() + Duration::from_secs(86_400),
            };
            tokio::select! {
                _ = served.as_mut() => break,
                () = conn.wake.notified() => {}
                () = tokio::time::sleep_until(deadline.into()) => {
                    if let Some((at, timeout)) = registry.due(&conn)
                        && at <= registry.now()
                    {
                        registry.count_timeout(timeout);
                        tracing::debug!(connection = conn.id, ?timeout, "connection timed out");
                        break;
                    }
                }
                changed = self.stop.changed() => {
                    let stop = if changed.is_ok() { *self.stop.borrow_and_update() } else { Stop::Abandon };
                    match stop {
                        Stop::Serving => {}
                        // Idle (or still sending its first head): close now. Otherwise
                        // hyper closes it once the answer in flight is written.
                        Stop::Finishing if !finishing => {
                            finishing = true;
                            if conn.in_flight.load(Relaxed) == 0 {
                                break;
                            }
                            served.as_mut().graceful_shutdown();
                        }
                        Stop::Finishing => {}
                        Stop::Abandon => break,
                    }
                }
            }
        }
        registry.leave(&conn);
    }
}

/// The socket, noting what the clocks need: bytes read, writes waiting for the client.
struct Watched {
    io: TcpStream,
    registry: Arc<Registry>,
    conn: Arc<Conn>,
}

impl Watched {
    fn note_write<T>(&self, polled: &Poll<T>) {
        self.registry.write_waits(&self.conn, polled.is_pending());
    }
}

impl AsyncRead for Watched {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        let polled = Pin::new(&mut self.io).poll_read(cx, buf);
        if matches!(polled, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.registry.read_some(&self.conn);
        }
        polled
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.io).poll_write(cx, buf);
        self.note_write(&polled);
        polled
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        self.note_write(&polled);
        polled
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }
}

/// The app as hyper calls it, each request counted in flight until its response body is
/// dropped (sent, or the connection gone).
#[derive(Clone)]
struct Requests {
    app: Router,
    registry: Arc<Registry>,
    conn: Arc<Conn>,
}

type Answer = Pin<Box<dyn Future<Output = Result<hyper::Response<Tracked>, Infallible>> + Send>>;

impl hyper::service::Service<hyper::Request<Incoming>> for Requests {
    type Response = hyper::Response<Tracked>;
    type Error = Infallible;
    type Future = Answer;

    fn call(&self, request: hyper::Request<Incoming>) -> Answer {
        let busy = InFlight::begin(self.registry.clone(), self.conn.clone());
        let answer = tower::ServiceExt::oneshot(self.app.clone(), request.map(Body::new));
        Box::pin(async move {
            let response = answer.await?;
            Ok(response.map(|body| Tracked { body, _busy: busy }))
        })
    }
}

/// A request in flight on its connection, until dropped.
struct InFlight {
    registry: Arc<Registry>,
    conn: Arc<Conn>,
}

impl InFlight {
    fn begin(registry: Arc<Registry>, conn: Arc<Conn>) -> Self {
        registry.begin_request(&conn);
        Self { registry, conn }
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.registry.end_request(&self.conn);
    }
}

/// A response body that keeps its request in flight.
struct Tracked {
    body: Body,
    _busy: InFlight,
}

impl http_body::Body for Tracked {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

/// The answer to a connection past the cap: a 503 written without reading the request.
struct Refusal {
    answer: Arc<[u8]>,
    lingering: Arc<Semaphore>,
    log: Mutex<Every>,
}

impl Refusal {
    fn new(max_connections: usize) -> Self {
        let problem = ApiError::unavailable(
            RETRY_AFTER_SECS,
            format!(
                "the server has its {max_connections} connections open, each with a request in flight; try again later"
            ),
        )
        .problem();
        let body = serde_json::to_string(&problem).unwrap_or_default();
        let answer = format!(
            "HTTP/1.1 503 Service Unavailable\r\ncontent-type: {}\r\nretry-after: {RETRY_AFTER_SECS}\r\nconnection: close\r\ncontent-length: {}\r\n\r\n{body}",
            super::problem::PROBLEM_JSON,
            body.len()
        );
        Self {
            answer: answer.into_bytes().into(),
            lingering: Arc::new(Semaphore::new(LINGERING)),
            log: Mutex::default(),
        }
    }

    fn refuse(&self, stream: TcpStream, counters: &ConnectionCounters) {
        counters.refused.fetch_add(1, Relaxed);
        self.log.lock().unwrap_or_else(|p| p.into_inner()).note(|n| {
            tracing::warn!(
                refused = n,
                "at the connection cap with every connection busy: new connections refused (503)"
            )
        });
        let Ok(permit) = self.lingering.clone().try_acquire_owned() else {
            let _ = stream.try_write(&self.answer);
            return;
        };
        let answer = self.answer.clone();
        tokio::spawn(async move {
            let _permit = permit;
            let mut stream = stream;
            let _ = tokio::time::timeout(LINGER, async {
                stream.write_all(&answer).await?;
                stream.shutdown().await?;
                let mut sink = [0u8; 2048];
                while stream.read(&mut sink).await? > 0 {}
                Ok::<_, io::Error>(())
            })
            .await;
        });
    }
}

/// Counts an event and lets it be logged at most once per [`LOG_EVERY`], with the count
/// since the last line.
#[derive(Default)]
struct Every {
    last: Option<Instant>,
    count: u64,
}

impl Every {
    fn note(&mut self, log: impl FnOnce(u64)) {
        self.count += 1;
        if self.last.is_none_or(|t| t.elapsed() >= LOG_EVERY) {
            self.last = Some(Instant::now());
            log(std::mem::take(&mut self.count));
        }
    }
}
