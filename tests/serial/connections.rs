//! Connections against the real binary: thousands of idle and trickling sockets while
//! `/healthz`, `/readyz` and an authenticated API call each answer within a second; idle,
//! trickling and kept-alive connections closed after their timeouts (HTTP/1.1 and h2c);
//! the cap, where an idle connection makes room and busy ones get a 503; the server's
//! memory through it all.
//!
//! The tests take turns with the `serial` program's others (`crate::ONE_AT_A_TIME`), and no
//! other program's tests run beside them: each opens thousands of sockets and measures
//! latencies on two cores.

use crate::binserver;
use crate::common::raw_http;

use std::time::{Duration, Instant};

use binserver::BinServer;
use raw_http::{RawAnswer, read_answer};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The server's `--api-key` (tenant:secret) and the bearer key its clients send.
const API_KEY: &str = "tenant-a:s3cret-key";
const KEY: &str = "s3cret-key";
/// What a probe may take, connect to answer.
const PROBE_WITHIN: Duration = Duration::from_secs(1);

/// The test process holds thousands of sockets: its soft open-files limit goes up to the
/// hard one.
fn raise_own_file_limit() -> u64 {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit read and write a struct we own.
    unsafe {
        assert_eq!(libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit), 0);
        limit.rlim_cur = limit.rlim_max;
        libc::setrlimit(libc::RLIMIT_NOFILE, &limit);
    }
    limit.rlim_cur
}

fn get(addr: &str, path: &str, key: Option<&str>, close: bool) -> String {
    let auth = key
        .map(|k| format!("Authorization: Bearer {k}\r\n"))
        .unwrap_or_default();
    let connection = if close { "Connection: close\r\n" } else { "" };
    format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n{auth}{connection}\r\n")
}

/// `GET path` on a new connection: the answer (None: none within 10 s) and the time from
/// connect to answer.
async fn probe(addr: &str, path: &str, key: Option<&str>) -> (Option<RawAnswer>, Duration) {
    let started = Instant::now();
    let answer = tokio::time::timeout(Duration::from_secs(10), async {
        let mut s = TcpStream::connect(addr).await.ok()?;
        s.write_all(get(addr, path, key, true).as_bytes())
            .await
            .ok()?;
        read_answer(&mut s).await
    })
    .await
    .ok()
    .flatten();
    (answer, started.elapsed())
}

/// `/healthz`, `/readyz` and `GET /v1/jobs` with the key each answer 200 within
/// [`PROBE_WITHIN`]; returns the slowest.
async fn probes_answer(s: &BinServer, case: &str) -> Duration {
    let mut slowest = Duration::ZERO;
    for (path, key) in [
        ("/healthz", None),
        ("/readyz", None),
        ("/v1/jobs", Some(KEY)),
    ] {
        let (answer, took) = probe(s.addr(), path, key).await;
        let status = answer.as_ref().map(|a| a.status);
        assert_eq!(
            status,
            Some(200),
            "{case}: GET {path} after {took:?}\n{}",
            s.logs()
        );
        assert!(took < PROBE_WITHIN, "{case}: GET {path} took {took:?}");
        slowest = slowest.max(took);
    }
    slowest
}

/// A value of the server's /metrics (a line starting with `series`).
async fn metric(s: &BinServer, series: &str) -> f64 {
    let (answer, _) = probe(s.addr(), "/metrics", None).await;
    let text = answer.expect("/metrics answers").text();
    text.lines()
        .find_map(|l| l.strip_prefix(series)?.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {series} in /metrics:\n{text}"))
}

/// `n` connections that send nothing.
async fn open_silent(addr: &str, n: usize) -> Vec<TcpStream> {
    let mut conns = Vec::with_capacity(n);
    for _ in 0..n {
        conns.push(TcpStream::connect(addr).await.expect("connect"));
    }
    conns
}

/// `n` connections that send a request head a byte every `every`, never finishing it;
/// each task ends (with the time from connect) when the server closes its connection.
async fn open_trickling(
    addr: &str,
    n: usize,
    every: Duration,
) -> Vec<tokio::task::JoinHandle<Duration>> {
    let head: Vec<u8> = format!("GET /healthz HTTP/1.1\r\nHost: {addr}\r\nX-Slow: ")
        .into_bytes()
        .into_iter()
        .chain(std::iter::repeat(b'a'))
        .take(64 << 10)
        .collect();
    let head = std::sync::Arc::new(head);
    let mut tasks = Vec::with_capacity(n);
    for _ in 0..n {
        let stream = TcpStream::connect(addr).await.expect("connect");
        let head = head.clone();
        tasks.push(tokio::spawn(async move {
            let started = Instant::now();
            let mut stream = stream;
            for byte in head.iter() {
                if stream.write_all(&[*byte]).await.is_err() {
                    break;
                }
                // A closed connection shows as a read of 0 (or a reset) before the next byte.
                let mut probe = [0u8; 1];
                match tokio::time::timeout(every, stream.read(&mut probe)).await {
                    Err(_) => {}
                    Ok(_) => break,
                }
            }
            started.elapsed()
        }));
    }
    tasks
}

/// Each connection's time until the server closes it (read EOF or reset), measured from
/// `since`; `None` when still open after `within`.
async fn closed_after(
    conns: Vec<TcpStream>,
    since: Instant,
    within: Duration,
) -> Vec<Option<Duration>> {
    let tasks: Vec<_> = conns
        .into_iter()
        .map(|mut c| {
            tokio::spawn(async move {
                let mut buf = [0u8; 1024];
                let read = async {
                    loop {
                        match c.read(&mut buf).await {
                            Ok(0) | Err(_) => break,
                            Ok(_) => {}
                        }
                    }
                };
                tokio::time::timeout(within, read)
                    .await
                    .ok()
                    .map(|()| since.elapsed())
            })
        })
        .collect();
    let mut out = Vec::with_capacity(tasks.len());
    for t in tasks {
        out.push(t.await.unwrap());
    }
    out
}

fn summary(times: &[Option<Duration>]) -> (usize, Duration, Duration) {
    let closed: Vec<Duration> = times.iter().flatten().copied().collect();
    let min = closed.iter().min().copied().unwrap_or_default();
    let max = closed.iter().max().copied().unwrap_or_default();
    (closed.len(), min, max)
}

fn peak_mb(s: &BinServer) -> u64 {
    s.memory_kb("VmHWM") / 1024
}

// ---------------------------------------------------------------------------------------

/// A server under `ulimit -n 4096` (the file limit the accept loop used to run out of) with
/// its default cap and timeouts (longer than the test), so only the cap keeps the probes
/// answering: 6,000
/// silent and 1,500 trickling connections, opened in waves with probes between them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thousands_of_idle_and_trickling_connections_leave_probes_answering() {
    let _turn = crate::ONE_AT_A_TIME.lock().await;
    assert!(
        raise_own_file_limit() >= 12_000,
        "the test needs 12,000 descriptors"
    );
    let dir = tempfile::tempdir().unwrap();
    let flags = ["--api-key", API_KEY, "--workers", "1", "--max-images", "16"];
    let s = BinServer::start_with_file_limit(dir.path(), &flags, 4096);
    probes_answer(&s, "at start").await;
    let before = s.memory_kb("VmRSS") / 1024;
    let mut silent = Vec::new();
    let mut trickling = Vec::new();
    let mut slowest = Duration::ZERO;
    for wave in 0..6 {
        silent.extend(open_silent(s.addr(), 1000).await);
        if wave % 2 == 0 {
            let every = Duration::from_millis(500);
            trickling.extend(open_trickling(s.addr(), 500, every).await);
        }
        let case = format!("{} silent, {} trickling", silent.len(), trickling.len());
        slowest = slowest.max(probes_answer(&s, &case).await);
    }
    let open = metric(&s, "photostereo_connections_open").await;
    let max = metric(&s, "photostereo_connections_max").await;
    let evicted = metric(&s, "photostereo_connections_evicted_total").await;
    let peak = peak_mb(&s);
    println!(
        "7,500 idle and trickling connections: probes within {slowest:?}; {open} open of {max}, {evicted} evicted; RSS {before} MB before, peak {peak} MB"
    );
    assert!(
        max < 4096.0,
        "the cap leaves room under the file limit: {max}"
    );
    assert!(open <= max, "{open} open, over the cap {max}");
    assert!(evicted >= 7_500.0 - max, "{evicted} evicted");
    assert!(
        peak < before + 150,
        "peak RSS {peak} MB with {max} connections open (started at {before} MB)"
    );
    drop(silent);
    for t in trickling {
        t.abort();
    }
    probes_answer(&s, "after").await;
}

/// A server with a 2 s header timeout, a 4 s keep-alive timeout, one worker and room for
/// 10,000 connections.
fn start_with_short_timeouts(dir: &std::path::Path) -> BinServer {
    let flags = [
        "--api-key",
        API_KEY,
        "--workers",
        "1",
        "--header-timeout",
        "2s",
        "--keep-alive-timeout",
        "4s",
        "--max-connections",
        "10000",
    ];
    BinServer::start(dir, &flags)
}

/// Short timeouts: silent and trickling connections are closed at the header timeout
/// (trickling does not extend it), kept-alive ones at the keep-alive timeout after their
/// answer, and probes answer throughout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_trickling_and_kept_alive_connections_close_after_their_timeouts() {
    let _turn = crate::ONE_AT_A_TIME.lock().await;
    raise_own_file_limit();
    let dir = tempfile::tempdir().unwrap();
    let s = start_with_short_timeouts(dir.path());
    let before = s.memory_kb("VmRSS") / 1024;

    let mut kept = Vec::new();
    // Every kept-alive connection is answered after this, so each closes at least the
    // keep-alive timeout after it, however long the 200 requests take.
    let first_sent = Instant::now();
    for _ in 0..200 {
        let mut c = TcpStream::connect(s.addr()).await.unwrap();
        c.write_all(get(s.addr(), "/healthz", None, false).as_bytes())
            .await
            .unwrap();
        let answer = read_answer(&mut c).await.expect("an answer");
        assert_eq!(answer.status, 200);
        kept.push(c);
    }
    let kept = tokio::spawn(closed_after(kept, first_sent, Duration::from_secs(15)));

    let opened = Instant::now();
    let silent = open_silent(s.addr(), 2000).await;
    let silent = tokio::spawn(closed_after(silent, opened, Duration::from_secs(15)));
    let trickling = open_trickling(s.addr(), 2000, Duration::from_millis(200)).await;
    let mut slowest = Duration::ZERO;
    while opened.elapsed() < Duration::from_millis(1500) {
        slowest = slowest.max(probes_answer(&s, "2,000 silent, 2,000 trickling").await);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let peak = peak_mb(&s);

    let silent = silent.await.unwrap();
    let mut trickled = Vec::new();
    for t in trickling {
        let took = tokio::time::timeout(Duration::from_secs(15), t).await;
        trickled.push(took.ok().map(|r| r.unwrap()));
    }
    let kept = kept.await.unwrap();
    let (silent_n, silent_min, silent_max) = summary(&silent);
    let (trickled_n, trickled_min, trickled_max) = summary(&trickled);
    let (kept_n, kept_min, kept_max) = summary(&kept);
    println!(
        "header timeout 2s: {silent_n}/2000 silent closed after {silent_min:?}..{silent_max:?}, {trickled_n}/2000 trickling after {trickled_min:?}..{trickled_max:?}; keep-alive 4s: {kept_n}/200 closed {kept_min:?}..{kept_max:?} after the first request; probes within {slowest:?}; RSS {before} MB before, peak {peak} MB"
    );
    assert_eq!(silent_n, 2000, "silent connections still open");
    assert_eq!(trickled_n, 2000, "trickling connections still open");
    assert_eq!(kept_n, 200, "kept-alive connections still open");
    // Silent ones were opened within the first second or so of `opened`.
    assert!(silent_min >= Duration::from_millis(1900), "{silent_min:?}");
    assert!(silent_max < Duration::from_secs(6), "{silent_max:?}");
    assert!(
        trickled_min >= Duration::from_millis(1900),
        "{trickled_min:?}"
    );
    assert!(trickled_max < Duration::from_secs(4), "{trickled_max:?}");
    assert!(kept_min >= Duration::from_millis(3900), "{kept_min:?}");
    assert!(kept_max < Duration::from_secs(7), "{kept_max:?}");
    assert!(
        peak < before + 150,
        "peak RSS {peak} MB (started at {before} MB)"
    );

    let header = metric(
        &s,
        "photostereo_connections_timed_out_total{timeout=\"header\"}",
    )
    .await;
    let keep_alive = metric(
        &s,
        "photostereo_connections_timed_out_total{timeout=\"keep_alive\"}",
    )
    .await;
    assert!(header >= 4000.0, "{header} header timeouts");
    assert!(keep_alive >= 200.0, "{keep_alive} keep-alive timeouts");
    assert_eq!(metric(&s, "photostereo_connections_open").await, 1.0);
}

/// A multipart upload whose body never finishes: a request in flight.
async fn upload_in_flight(addr: &str) -> TcpStream {
    let mut c = TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: 100000\r\n\r\n--b\r\nContent-Disposition: form-data; name=\"lights\"\r\n\r\n"
    );
    c.write_all(head.as_bytes()).await.unwrap();
    c
}

/// `--max-connections 20`: with every connection busy the 21st gets a 503 at once; an idle
/// one makes room for a new one; a closed one frees its place.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn past_the_cap_an_idle_connection_makes_room_and_busy_ones_get_503() {
    let _turn = crate::ONE_AT_A_TIME.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let flags = ["--max-connections", "20", "--upload-timeout", "1m"];
    let s = BinServer::start(dir.path(), &flags);
    let mut uploads = Vec::new();
    for _ in 0..20 {
        uploads.push(upload_in_flight(s.addr()).await);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;

    let (answer, took) = probe(s.addr(), "/healthz", None).await;
    let answer = answer.expect("an answer past the cap");
    println!("past the cap, all busy: {} after {took:?}", answer.status);
    assert_eq!(answer.status, 503, "{}", answer.head);
    assert!(took < PROBE_WITHIN, "{took:?}");
    let head = answer.head.to_ascii_lowercase();
    assert!(head.contains("retry-after: "), "{head}");
    assert!(head.contains("connection: close"), "{head}");
    assert!(answer.is_problem(), "{head}");
    let problem = answer.json();
    assert_eq!(problem["status"], 503);
    assert!(
        problem["detail"].as_str().unwrap().contains("connections"),
        "{problem}"
    );

    // One upload gone: its place serves the next connection.
    drop(uploads.pop());
    let freed = Instant::now();
    loop {
        let (answer, _) = probe(s.addr(), "/healthz", None).await;
        if answer.is_some_and(|a| a.status == 200) {
            break;
        }
        assert!(freed.elapsed() < Duration::from_secs(5), "no place freed");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // 19 busy and one idle: a new connection takes the idle one's place.
    let idle = TcpStream::connect(s.addr()).await.unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let idle_since = Instant::now();
    let (answer, took) = probe(s.addr(), "/healthz", None).await;
    assert_eq!(answer.map(|a| a.status), Some(200), "{took:?}");
    assert!(took < PROBE_WITHIN, "{took:?}");
    let closed = closed_after(vec![idle], idle_since, Duration::from_secs(2)).await;
    assert!(closed[0].is_some(), "the idle connection was not closed");

    drop(uploads);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let refused = metric(&s, "photostereo_connections_refused_total").await;
    let evicted = metric(&s, "photostereo_connections_evicted_total").await;
    println!("refused {refused}, evicted {evicted}");
    assert!(refused >= 1.0 && evicted >= 1.0);
    assert!(
        s.logs().contains("new connections refused (503)"),
        "the refusal is logged"
    );
}

/// A client that reads nothing of a large answer is closed after the send timeout, even
/// though its request is in flight.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_reads_nothing_is_closed_after_the_send_timeout() {
    let _turn = crate::ONE_AT_A_TIME.lock().await;
    let dir = tempfile::tempdir().unwrap();
    let flags = ["--send-timeout", "2s", "--keep-alive-timeout", "1m"];
    let s = BinServer::start(dir.path(), &flags);
    // A small receive buffer, before the connection's window is set: the server's writes
    // wait soon.
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let mut c = socket.connect(s.addr().parse().unwrap()).await.unwrap();
    // Pipelined requests for the OpenAPI document (73 kB each), never read.
    let many = get(s.addr(), "/openapi.json", None, false).repeat(400);
    c.write_all(many.as_bytes()).await.unwrap();
    let sent = Instant::now();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let closed = tokio::time::timeout(Duration::from_secs(10), async {
        let mut buf = vec![0u8; 1 << 16];
        loop {
            match c.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(_) => {}
            }
        }
    })
    .await;
    println!(
        "a client reading nothing: closed {:?} after its requests",
        sent.elapsed()
    );
    assert!(closed.is_ok(), "still open");
    let send = metric(
        &s,
        "photostereo_connections_timed_out_total{timeout=\"send\"}",
    )
    .await;
    assert_eq!(send, 1.0);
}

/// The HTTP/2 client preface and an empty SETTINGS frame: what an h2c client (prior
/// knowledge) sends first.
fn h2_preface() -> Vec<u8> {
    let mut bytes = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    bytes.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
    bytes
}

/// A HEADERS frame (stream 1, END_STREAM | END_HEADERS) for `GET path`: HPACK with
/// literals that are never indexed, so no table state is needed.
fn h2_get(addr: &str, path: &str) -> Vec<u8> {
    let mut block = vec![0x82, 0x86]; // :method GET, :scheme http (static table)
    for (index, value) in [(4u8, path), (1, addr)] {
        // Literal, never indexed, name from the static table (:path 4, :authority 1).
        block.push(0x10 | index);
        block.push(value.len() as u8);
        block.extend_from_slice(value.as_bytes());
    }
    let len = block.len();
    let mut frame = vec![
        (len >> 16) as u8,
        (len >> 8) as u8,
        len as u8,
        1,
        0x05,
        0,
        0,
        0,
        1,
    ];
    frame.extend(block);
    frame
}

/// The frames a server sent until the `:status` of stream 1 (None: none before EOF or
/// 5 s): that status, from the HEADERS frame's first byte (an indexed static-table status).
async fn h2_status(c: &mut TcpStream) -> Option<u16> {
    let read = async {
        loop {
            let mut head = [0u8; 9];
            c.read_exact(&mut head).await.ok()?;
            let len = (head[0] as usize) << 16 | (head[1] as usize) << 8 | head[2] as usize;
            let mut payload = vec![0u8; len];
            c.read_exact(&mut payload).await.ok()?;
            let stream = u32::from_be_bytes([head[5], head[6], head[7], head[8]]) & 0x7fff_ffff;
            if head[3] == 1 && stream == 1 {
                // Static table: 0x88 is :status 200, 0x8d 404, 0x8e 500.
                return Some(match payload.first()? {
                    0x88 => 200,
                    0x8d => 404,
                    0x8e => 500,
                    other => 1000 + *other as u16,
                });
            }
        }
    };
    tokio::time::timeout(Duration::from_secs(5), read)
        .await
        .ok()
        .flatten()
}

/// HTTP/2 with prior knowledge (h2c) is held to the same clocks: a connection that sends
/// its preface and nothing more is closed at the header timeout, one idle after its
/// request at the keep-alive timeout; 1,000 such silent ones leave the probes answering.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn h2c_connections_close_after_their_timeouts() {
    let _turn = crate::ONE_AT_A_TIME.lock().await;
    raise_own_file_limit();
    let dir = tempfile::tempdir().unwrap();
    let s = start_with_short_timeouts(dir.path());

    let mut served = TcpStream::connect(s.addr()).await.unwrap();
    served.write_all(&h2_preface()).await.unwrap();
    served
        .write_all(&h2_get(s.addr(), "/healthz"))
        .await
        .unwrap();
    assert_eq!(h2_status(&mut served).await, Some(200), "{}", s.logs());
    let answered = Instant::now();
    let served = tokio::spawn(closed_after(
        vec![served],
        answered,
        Duration::from_secs(15),
    ));

    let opened = Instant::now();
    let mut silent = Vec::new();
    for _ in 0..1000 {
        let mut c = TcpStream::connect(s.addr()).await.unwrap();
        c.write_all(&h2_preface()).await.unwrap();
        silent.push(c);
    }
    let silent = tokio::spawn(closed_after(silent, opened, Duration::from_secs(15)));
    let mut slowest = Duration::ZERO;
    while opened.elapsed() < Duration::from_millis(1500) {
        slowest = slowest.max(probes_answer(&s, "1,000 silent h2c connections").await);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (silent_n, silent_min, silent_max) = summary(&silent.await.unwrap());
    let (served_n, served_min, _) = summary(&served.await.unwrap());
    println!(
        "h2c: {silent_n}/1000 silent closed after {silent_min:?}..{silent_max:?} (header timeout 2s); the served one {served_min:?} after its answer (keep-alive 4s); probes within {slowest:?}"
    );
    assert_eq!(silent_n, 1000, "silent h2c connections still open");
    assert!(silent_min >= Duration::from_millis(1900), "{silent_min:?}");
    assert!(silent_max < Duration::from_secs(6), "{silent_max:?}");
    assert_eq!(served_n, 1, "the served h2c connection is still open");
    assert!(served_min >= Duration::from_millis(3900), "{served_min:?}");
    assert!(served_min < Duration::from_secs(7), "{served_min:?}");
    assert_eq!(metric(&s, "photostereo_connections_open").await, 1.0);
}
