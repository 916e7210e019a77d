//! The accept loop shared by the daemon's two HTTP listeners (`/metrics` and the page),
//! each on its own thread: answer requests until `stop` is set, checking it every 200 ms.

use std::io::Cursor;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Answer every request on `server` with `answer` until `stop` is set. `what` names the
/// listener in log lines.
pub fn serve(
    server: tiny_http::Server,
    stop: &AtomicBool,
    what: &str,
    mut answer: impl FnMut(&tiny_http::Request) -> tiny_http::Response<Cursor<Vec<u8>>>,
) {
    while !stop.load(Ordering::Relaxed) {
        let request = match server.recv_timeout(Duration::from_millis(200)) {
            Ok(Some(r)) => r,
            Ok(None) => continue,
            Err(e) => {
                tracing::warn!(what, error = %e, "accepting a request failed");
                continue;
            }
        };
        let response = answer(&request);
        if let Err(e) = request.respond(response) {
            tracing::debug!(what, error = %e, "cannot answer (client gone?)");
        }
    }
}
