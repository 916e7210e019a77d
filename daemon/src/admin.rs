//! The admin endpoint: a Unix stream socket whose callers are identified by the kernel
//! (`SO_PEERCRED`: uid and gid at connect time) and checked against the configured admin
//! uids and gids. Frames are the wire headers as bytes (`guardian_shared::wire::admin`).
//!
//! One thread accepts connections and reads requests, with timeouts and size bounds, so a
//! slow or hostile caller never stalls the serving loop; each request of an admin is handed
//! to the serving loop (which owns the bank) through a channel, and the loop is woken on the
//! request event. A caller that is not an admin is answered `NotPermitted` by this thread;
//! its request never reaches the bank.

use std::io::{Read, Write};
use std::os::unix::fs::{FileTypeExt, PermissionsExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use guardian_shared::wire::{
    ClassEntry, Failure, RequestHeader, ResponseHeader, admin, encode_failure,
};

/// Builds, inside the endpoint's thread, the function that wakes the serving loop (iceoryx2
/// ports are single-threaded, so the thread makes its own).
pub type WakerFactory = Box<dyn FnOnce() -> Box<dyn FnMut()> + Send>;

/// How long the endpoint waits for a caller's bytes, and for the serving loop's answer.
const IO_TIMEOUT: Duration = Duration::from_secs(5);
const ANSWER_TIMEOUT: Duration = Duration::from_secs(60);

/// An admin's request, for the serving loop to answer.
#[derive(Debug)]
pub struct AdminJob {
    /// The request header.
    pub header: RequestHeader,
    /// Its payload.
    pub payload: Vec<f32>,
    /// Where the answer goes.
    reply: mpsc::SyncSender<(ResponseHeader, Vec<ClassEntry>)>,
}

impl AdminJob {
    /// Send the serving loop's answer back to the caller.
    pub fn answer(self, response: (ResponseHeader, Vec<ClassEntry>)) {
        let _ = self.reply.send(response);
    }
}

/// Who may use the endpoint.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AdminPolicy {
    /// Admin uids.
    pub uids: Vec<u32>,
    /// Admin gids (the caller's effective primary gid, as `SO_PEERCRED` reports it).
    pub gids: Vec<u32>,
}

impl AdminPolicy {
    fn allows(&self, uid: u32, gid: u32) -> bool {
        self.uids.contains(&uid) || self.gids.contains(&gid)
    }
}

/// The running endpoint; stops its thread and removes its socket on drop.
#[derive(Debug)]
pub struct AdminEndpoint {
    /// Requests of admins, in arrival order.
    pub jobs: mpsc::Receiver<AdminJob>,
    path: PathBuf,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Starting the endpoint failed.
#[derive(Debug, thiserror::Error)]
#[error("cannot serve the admin socket {path}: {source}")]
pub struct AdminSocketError {
    /// The socket.
    pub path: PathBuf,
    /// The cause.
    pub source: std::io::Error,
}

impl AdminEndpoint {
    /// Bind `path` (a stale socket left by a killed daemon is replaced; any other file is
    /// an error), make it connectable by every local user — the credentials decide, not
    /// the file mode — and serve it. The waker `make_wake` builds is called after each job
    /// is queued.
    pub fn start(
        path: &Path,
        policy: AdminPolicy,
        make_wake: WakerFactory,
    ) -> Result<Self, AdminSocketError> {
        let err = |source| AdminSocketError {
            path: path.to_owned(),
            source,
        };
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            if !meta.file_type().is_socket() {
                return Err(err(std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    "exists and is not a socket",
                )));
            }
            std::fs::remove_file(path).map_err(err)?;
        }
        let listener = UnixListener::bind(path).map_err(err)?;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o666)).map_err(err)?;
        let (tx, jobs) = mpsc::sync_channel(4);
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        let thread = std::thread::Builder::new()
            .name("admin-socket".into())
            .spawn(move || accept_loop(listener, policy, tx, make_wake, stop2))
            .map_err(err)?;
        Ok(Self {
            jobs,
            path: path.to_owned(),
            stop,
            thread: Some(thread),
        })
    }
}

impl Drop for AdminEndpoint {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            // Refuse queued jobs (their callers get no answer and close), unblock accept()
            // with a connection of our own, and give a caller mid-request its I/O timeout.
            let start = std::time::Instant::now();
            while !t.is_finished() && start.elapsed() < IO_TIMEOUT + Duration::from_secs(1) {
                while self.jobs.try_recv().is_ok() {}
                let _ = UnixStream::connect(&self.path);
                std::thread::sleep(Duration::from_millis(5));
            }
            if t.is_finished() {
                let _ = t.join();
            }
        }
        let _ = std::fs::remove_file(&self.path);
    }
}

fn accept_loop(
    listener: UnixListener,
    policy: AdminPolicy,
    jobs: mpsc::SyncSender<AdminJob>,
    make_wake: WakerFactory,
    stop: Arc<AtomicBool>,
) {
    let mut wake = make_wake();
    for stream in listener.incoming() {
        if stop.load(Ordering::SeqCst) {
            return;
        }
        let stream = match stream {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!(error = %e, "admin socket: accept failed");
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
        };
        if let Err(e) = serve_connection(stream, &policy, &jobs, &mut *wake) {
            tracing::debug!(error = %e, "admin socket: connection ended");
        }
    }
}

/// Answer the requests of one connection until it closes, breaks a frame or times out.
fn serve_connection(
    mut s: UnixStream,
    policy: &AdminPolicy,
    jobs: &mpsc::SyncSender<AdminJob>,
    wake: &mut dyn FnMut(),
) -> std::io::Result<()> {
    let cred = rustix::net::sockopt::socket_peercred(&s)?;
    let (uid, gid) = (cred.uid.as_raw(), cred.gid.as_raw());
    let admin = policy.allows(uid, gid);
    s.set_read_timeout(Some(IO_TIMEOUT))?;
    s.set_write_timeout(Some(IO_TIMEOUT))?;
    loop {
        let mut len = [0u8; 4];
        match s.read_exact(&mut len) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(()),
            Err(e) => return Err(e),
        }
        let len = u32::from_le_bytes(len) as usize;
        if let Err(e) = admin::check_request_len(len) {
            // The stream cannot be resynchronised: answer once and close.
            let mut r = ResponseHeader::new(0, 0);
            encode_failure(
                &mut r,
                &Failure::BadRequest {
                    message: e.to_string(),
                },
            );
            return s.write_all(&admin::encode_response(&r, &[]));
        }
        let mut body = vec![0u8; len];
        s.read_exact(&mut body)?;
        let (header, payload) = admin::decode_request(&body)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))?;
        let response = if admin {
            tracing::info!(
                uid,
                gid,
                pid = cred.pid.as_raw_nonzero().get(),
                op = header.op,
                "admin request"
            );
            let (reply, answer) = mpsc::sync_channel(1);
            let job = AdminJob {
                header,
                payload,
                reply,
            };
            if jobs.send(job).is_err() {
                return Ok(()); // the daemon is stopping
            }
            wake();
            match answer.recv_timeout(ANSWER_TIMEOUT) {
                Ok(r) => r,
                Err(_) => return Ok(()),
            }
        } else {
            tracing::warn!(
                uid,
                gid,
                op = header.op,
                "admin socket: caller is not an admin"
            );
            let mut r = ResponseHeader::answering(&header);
            encode_failure(
                &mut r,
                &Failure::NotPermitted {
                    message: format!(
                        "uid {uid} gid {gid} is not in the daemon's admin uids or gids"
                    ),
                },
            );
            (r, Vec::new())
        };
        s.write_all(&admin::encode_response(&response.0, &response.1))?;
    }
}
