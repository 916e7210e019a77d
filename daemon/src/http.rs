//! The daemon's two HTTP listeners (`/metrics` and the page): a small HTTP/1.1 server that
//! holds its ground against hostile clients, on loopback or a robot PC's network.
//!
//! - **Bounded request size**: a request's line and headers are read up to
//!   [`MAX_REQUEST_BYTES`]; a longer one is answered 431 and closed, so one request cannot
//!   grow the daemon's memory (a body is never read: both listeners are GET-only).
//! - **Bounded connections and threads**: one accept thread and [`WORKERS`] workers per
//!   listener, whatever the number of clients. Accepted connections wait in a queue of
//!   [`QUEUE`]; beyond it a connection is answered 503 and closed at once. Each request has
//!   [`DEADLINE`] to arrive whole (a slow client is cut off, 408) and its answer to leave.
//! - **Host checked**: the `Host` header must name the listener by IP literal or as
//!   `localhost`, with its port. A page reached through another name (DNS rebinding: a web
//!   page's script on `evil.example.com` resolving to this address) is answered 421.
//!
//! Every answer closes the connection (`Connection: close`).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, TrySendError, sync_channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Largest request line plus headers read (bytes).
pub const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// Worker threads per listener.
pub const WORKERS: usize = 2;
/// Accepted connections waiting for a worker, per listener.
pub const QUEUE: usize = 4;
/// Time for a request to arrive whole, and for its answer to be written.
pub const DEADLINE: Duration = Duration::from_secs(2);

/// A request's method, path (without the query) and headers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    /// `GET`, `HEAD`, ...
    pub method: String,
    /// The path, without `?query`.
    pub path: String,
    /// The query, without `?` (empty for none).
    pub query: String,
    /// Header names (lower case) and values.
    pub headers: Vec<(String, String)>,
}

impl Request {
    /// The first header `name` (lower case).
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }

    /// The value of `key` in the query (`a=1&b=2`), as sent.
    pub fn param(&self, key: &str) -> Option<&str> {
        self.query
            .split('&')
            .filter_map(|kv| kv.split_once('=').or(Some((kv, ""))))
            .find(|(k, _)| *k == key)
            .map(|(_, v)| v)
    }

    /// `GET` or `HEAD`.
    pub fn is_get(&self) -> bool {
        self.method == "GET" || self.method == "HEAD"
    }
}

/// An answer: status, content type and body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Response {
    /// HTTP status code.
    pub status: u16,
    /// `Content-Type`.
    pub content_type: &'static str,
    /// The body (not sent for `HEAD`).
    pub body: Vec<u8>,
}

impl Response {
    /// A plain-text answer.
    pub fn text(status: u16, body: impl Into<String>) -> Self {
        Self {
            status,
            content_type: "text/plain; charset=utf-8",
            body: body.into().into_bytes(),
        }
    }
}

/// A listener bound to its address.
#[derive(Debug)]
pub struct Listener {
    listener: TcpListener,
    address: SocketAddr,
}

impl Listener {
    /// Bind `address` (`host:port`).
    pub fn bind(address: &str) -> std::io::Result<Self> {
        let listener = TcpListener::bind(address)?;
        let address = listener.local_addr()?;
        listener.set_nonblocking(true)?;
        Ok(Self { listener, address })
    }

    /// The address bound (the port chosen for port 0).
    pub fn address(&self) -> SocketAddr {
        self.address
    }
}

/// Answer every request on `listener` with `answer` until `stop` is set (checked every
/// 50 ms), on one accept thread (this one) and [`WORKERS`] workers. `what` names the
/// listener in log lines.
pub fn serve(
    listener: Listener,
    stop: &AtomicBool,
    what: &'static str,
    answer: impl Fn(&Request) -> Response + Send + Sync + 'static,
) {
    let (tx, rx) = sync_channel::<TcpStream>(QUEUE);
    let rx = Arc::new(Mutex::new(rx));
    let answer = Arc::new(answer);
    let done = Arc::new(AtomicBool::new(false));
    let port = listener.address.port();
    let workers: Vec<_> = (0..WORKERS)
        .filter_map(|i| {
            let (rx, answer, done) = (rx.clone(), answer.clone(), done.clone());
            std::thread::Builder::new()
                .name(format!("{what}-http-{i}"))
                .spawn(move || work(&rx, &done, port, what, answer.as_ref()))
                .map_err(|e| tracing::error!(what, error = %e, "cannot start an HTTP worker"))
                .ok()
        })
        .collect();
    while !stop.load(Ordering::Relaxed) {
        match listener.listener.accept() {
            Ok((stream, _)) => match tx.try_send(stream) {
                Ok(()) => {}
                Err(TrySendError::Full(stream) | TrySendError::Disconnected(stream)) => {
                    tracing::debug!(what, "HTTP queue full: connection refused with 503");
                    let _ = stream.set_nonblocking(false);
                    let _ = stream.set_write_timeout(Some(Duration::from_millis(100)));
                    respond(&stream, &Response::text(503, "busy\n"), false);
                }
            },
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(e) => {
                tracing::warn!(what, error = %e, "accepting a connection failed");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
    done.store(true, Ordering::Relaxed);
    drop(tx);
    for w in workers {
        let _ = w.join();
    }
}

/// A worker: answer queued connections until the accept loop is done.
fn work(
    rx: &Mutex<Receiver<TcpStream>>,
    done: &AtomicBool,
    port: u16,
    what: &str,
    answer: &(dyn Fn(&Request) -> Response + Send + Sync),
) {
    while !done.load(Ordering::Relaxed) {
        let next = match rx.lock() {
            Ok(rx) => rx.recv_timeout(Duration::from_millis(100)),
            Err(_) => return,
        };
        let Ok(stream) = next else { continue };
        let _ = stream.set_nonblocking(false);
        let _ = stream.set_write_timeout(Some(DEADLINE));
        let (response, head_only) = match read_request(&stream) {
            Ok(request) if !host_allowed(request.header("host"), port) => (
                Response::text(421, "unknown Host: name this listener by its address\n"),
                false,
            ),
            Ok(request) => (answer(&request), request.method == "HEAD"),
            Err(status) => (Response::text(status, "bad request\n"), false),
        };
        if !respond(&stream, &response, head_only) {
            tracing::debug!(what, "cannot answer (client gone?)");
        }
    }
}

/// Read a request's line and headers within [`DEADLINE`] and [`MAX_REQUEST_BYTES`]; the
/// status to answer with otherwise.
fn read_request(mut stream: &TcpStream) -> Result<Request, u16> {
    let start = Instant::now();
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    let end = loop {
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break i;
        }
        if buf.len() > MAX_REQUEST_BYTES {
            return Err(431);
        }
        let left = DEADLINE.saturating_sub(start.elapsed());
        if left.is_zero() {
            return Err(408);
        }
        let _ = stream.set_read_timeout(Some(left));
        match stream.read(&mut chunk) {
            Ok(0) => return Err(400),
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return Err(408);
            }
            Err(_) => return Err(400),
        }
    };
    if end > MAX_REQUEST_BYTES {
        return Err(431);
    }
    let head = std::str::from_utf8(&buf[..end]).map_err(|_| 400u16)?;
    let mut lines = head.split("\r\n");
    let mut first = lines.next().unwrap_or("").split(' ');
    let (Some(method), Some(target), Some(version)) = (first.next(), first.next(), first.next())
    else {
        return Err(400);
    };
    if !version.starts_with("HTTP/1.") {
        return Err(400);
    }
    let headers = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(n, v)| (n.trim().to_ascii_lowercase(), v.trim().to_owned()))
        .collect();
    let (path, query) = target.split_once('?').unwrap_or((target, ""));
    Ok(Request {
        method: method.to_owned(),
        path: path.to_owned(),
        query: query.to_owned(),
        headers,
    })
}

/// The `Host` header names this listener: an IP literal or `localhost`, with its `port`.
fn host_allowed(host: Option<&str>, port: u16) -> bool {
    let Some(host) = host else { return false };
    let (name, p) = match host.rsplit_once(':') {
        // `[::1]:port` or `a.b.c.d:port`; a bare IPv6 literal has more colons.
        Some((name, p)) if !name.contains(':') || name.ends_with(']') => (name, p),
        _ => return false,
    };
    if p.parse::<u16>().ok() != Some(port) {
        return false;
    }
    let name = name.trim_start_matches('[').trim_end_matches(']');
    name.eq_ignore_ascii_case("localhost") || name.parse::<std::net::IpAddr>().is_ok()
}

/// Write `response` and close; false if the client was gone.
fn respond(mut stream: &TcpStream, response: &Response, head_only: bool) -> bool {
    let reason = match response.status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "",
    };
    let head = format!(
        "HTTP/1.1 {} {reason}\r\nContent-Type: {}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        response.status,
        response.content_type,
        response.body.len()
    );
    let ok = stream.write_all(head.as_bytes()).is_ok()
        && (head_only || stream.write_all(&response.body).is_ok())
        && stream.flush().is_ok();
    let _ = stream.shutdown(std::net::Shutdown::Write);
    ok
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_parameters_are_found_by_key() {
        let r = Request {
            method: "GET".into(),
            path: "/".into(),
            query: "no-go&before=142&x=".into(),
            headers: Vec::new(),
        };
        assert_eq!(r.param("no-go"), Some(""));
        assert_eq!(r.param("before"), Some("142"));
        assert_eq!(r.param("x"), Some(""));
        assert_eq!(r.param("y"), None);
    }

    #[test]
    fn hosts_name_the_listener_by_address() {
        assert!(host_allowed(Some("127.0.0.1:9720"), 9720));
        assert!(host_allowed(Some("localhost:9720"), 9720));
        assert!(host_allowed(Some("[::1]:9720"), 9720));
        assert!(host_allowed(Some("10.0.0.7:9720"), 9720));
        assert!(!host_allowed(Some("evil.example.com:9720"), 9720));
        assert!(!host_allowed(Some("127.0.0.1:80"), 9720));
        assert!(!host_allowed(Some("127.0.0.1"), 9720));
        assert!(!host_allowed(Some("::1"), 9720));
        assert!(!host_allowed(None, 9720));
    }
}
