//! The admin endpoint: a Unix stream socket whose callers are identified by the kernel
//! (`SO_PEERCRED`: uid and gid at connect time) and checked against the configured admin
//! uids and gids. Frames are the wire headers as bytes (`guardian_shared::wire::admin`).
//!
//! One thread accepts connections and checks each caller's credentials **before reading a
//! byte**: a caller that is not an admin is answered `NotPermitted` at once (request id 0)
//! and disconnected, so it can neither hold the socket nor make the daemon read its frame.
//! Each admin connection gets a thread of its own (at most [`MAX_ADMIN_CONNECTIONS`] at a
//! time; more are answered `Internal` "busy" and closed), and each of its requests must
//! arrive whole within [`REQUEST_DEADLINE`] — a deadline for the whole frame, not per read —
//! so one slow connection never delays another. A request is handed to the serving loop
//! (which owns the bank) through a channel, and the loop is woken on the request event.
//!
//! **A change is applied only while its requester waits for the answer.** Before the loop
//! answers a job it takes it ([`AdminJob::take`]): a job whose caller has hung up (the
//! client timed out or was killed) or whose connection thread gave up waiting is dropped
//! unapplied and logged. Once taken, the job is answered; a client that gives up after that
//! point cannot know the outcome and says so (`CheckError::OutcomeUnknown`).

use std::io::{Read, Write};
use std::os::unix::fs::{FileTypeExt, PermissionsExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use guardian_shared::wire::{
    ClassEntry, Failure, Op, RequestHeader, ResponseHeader, admin, decode_code, encode_failure,
};

/// Builds, inside the endpoint's dispatch thread, the function that wakes the serving loop
/// (iceoryx2 ports are single-threaded, so that thread makes its own).
pub type WakerFactory = Box<dyn FnOnce() -> Box<dyn FnMut()> + Send>;

/// How long an admin has to send one whole request frame (counted from the connection, or
/// from the previous answer); a caller slower than that is disconnected and logged.
pub const REQUEST_DEADLINE: Duration = Duration::from_secs(10);
/// How long a connection thread waits for the serving loop to take its request.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest wait to write an answer or a refusal.
const WRITE_TIMEOUT: Duration = Duration::from_secs(5);
/// Admin connections served at once.
pub const MAX_ADMIN_CONNECTIONS: usize = 8;

const QUEUED: u8 = 0;
const TAKEN: u8 = 1;
const ABANDONED: u8 = 2;

/// An admin's request, for the serving loop to answer.
#[derive(Debug)]
pub struct AdminJob {
    /// The request header.
    pub header: RequestHeader,
    /// Its payload.
    pub payload: Vec<f32>,
    /// Where the answer goes.
    reply: mpsc::SyncSender<(ResponseHeader, Vec<ClassEntry>)>,
    /// The caller's connection, to see whether it is still there.
    peer: Arc<UnixStream>,
    /// [`QUEUED`], [`TAKEN`] by the loop or [`ABANDONED`] by the connection thread.
    state: Arc<AtomicU8>,
    /// The caller, for the log.
    uid: u32,
    pid: i32,
}

impl AdminJob {
    /// Take the job to answer it, unless its requester has gone: the caller hung up, or
    /// the connection thread stopped waiting. An untaken job is dropped unanswered and,
    /// being a change nobody waits for, is never applied.
    pub fn take(&self) -> bool {
        let gone = peer_hung_up(&self.peer);
        if !gone
            && self
                .state
                .compare_exchange(QUEUED, TAKEN, Ordering::SeqCst, Ordering::SeqCst)
                .is_ok()
        {
            return true;
        }
        tracing::warn!(
            uid = self.uid,
            pid = self.pid,
            op = self.header.op,
            class = %guardian_shared::wire::decode_text(&self.header.class_name),
            "admin request not applied: its requester has gone (timed out or exited) before it was served"
        );
        false
    }

    /// Send the serving loop's answer back to the caller.
    pub fn answer(self, response: (ResponseHeader, Vec<ClassEntry>)) {
        let _ = self.reply.send(response);
    }
}

/// Whether the other end of `s` has closed the connection (`POLLHUP`: closed for both
/// directions; a caller that only shut down its writing side still waits for the answer).
fn peer_hung_up(s: &UnixStream) -> bool {
    use rustix::event::{PollFd, PollFlags, Timespec};
    let mut fds = [PollFd::new(s, PollFlags::empty())];
    let zero = Timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    match rustix::event::poll(&mut fds, Some(&zero)) {
        Ok(_) => fds[0]
            .revents()
            .intersects(PollFlags::HUP | PollFlags::ERR | PollFlags::NVAL),
        Err(_) => false,
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
    /// The accepting and the dispatching thread.
    threads: Vec<std::thread::JoinHandle<()>>,
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
        let (tx, jobs) = mpsc::sync_channel(MAX_ADMIN_CONNECTIONS);
        // Connection threads hand their jobs to one dispatch thread, which owns the waker.
        let (to_dispatch, dispatch) = mpsc::channel::<AdminJob>();
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        let dispatcher = std::thread::Builder::new()
            .name("admin-dispatch".into())
            .spawn(move || {
                // The waker (an iceoryx2 node and notifier) lives and dies in this thread,
                // which the endpoint joins on drop, so the node is removed cleanly.
                let mut wake = make_wake();
                loop {
                    match dispatch.recv_timeout(Duration::from_millis(50)) {
                        Ok(job) => {
                            if tx.send(job).is_err() {
                                return; // the daemon is stopping
                            }
                            wake();
                        }
                        Err(mpsc::RecvTimeoutError::Timeout) if !stop2.load(Ordering::SeqCst) => {}
                        Err(_) => return,
                    }
                }
            })
            .map_err(err)?;
        let stop3 = stop.clone();
        let acceptor = std::thread::Builder::new()
            .name("admin-socket".into())
            .spawn(move || accept_loop(listener, policy, to_dispatch, stop3))
            .map_err(err)?;
        Ok(Self {
            jobs,
            path: path.to_owned(),
            stop,
            threads: vec![acceptor, dispatcher],
        })
    }
}

impl Drop for AdminEndpoint {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Refuse queued jobs (their callers get no answer and close) and unblock accept()
        // with a connection of our own. The accept thread never reads from a caller, so
        // it ends at once; the dispatch thread within its poll interval; connection
        // threads (not joined) end by their deadlines.
        let start = Instant::now();
        while self.threads.iter().any(|t| !t.is_finished())
            && start.elapsed() < Duration::from_secs(2)
        {
            while self.jobs.try_recv().is_ok() {}
            if !self.threads[0].is_finished() {
                let _ = UnixStream::connect(&self.path);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        for t in self.threads.drain(..) {
            if t.is_finished() {
                let _ = t.join();
            }
        }
        while self.jobs.try_recv().is_ok() {}
        let _ = std::fs::remove_file(&self.path);
    }
}

/// A frame answering a connection as a whole (request id 0, op 0), before any request of
/// it is read.
fn refusal(failure: &Failure) -> Vec<u8> {
    let mut r = ResponseHeader::new(0, 0);
    encode_failure(&mut r, failure);
    admin::encode_response(&r, &[])
}

fn accept_loop(
    listener: UnixListener,
    policy: AdminPolicy,
    jobs: mpsc::Sender<AdminJob>,
    stop: Arc<AtomicBool>,
) {
    let active = Arc::new(AtomicUsize::new(0));
    for stream in listener.incoming() {
        if stop.load(Ordering::SeqCst) {
            return;
        }
        let s = match stream {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!(error = %e, "admin socket: accept failed");
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
        };
        let cred = match rustix::net::sockopt::socket_peercred(&s) {
            Ok(c) => c,
            Err(e) => {
                tracing::warn!(error = %e, "admin socket: cannot read the caller's credentials; refused");
                continue;
            }
        };
        let (uid, gid, pid) = (
            cred.uid.as_raw(),
            cred.gid.as_raw(),
            cred.pid.as_raw_nonzero().get(),
        );
        // Nothing of a refused caller is read; the refusal (540 bytes) fits the socket's
        // buffer, so the write does not wait on the caller either.
        let refuse = |mut s: UnixStream, failure: Failure| {
            let _ = s.set_write_timeout(Some(Duration::from_millis(100)));
            let _ = s.write_all(&refusal(&failure));
            let _ = s.shutdown(std::net::Shutdown::Write);
        };
        if !policy.allows(uid, gid) {
            tracing::warn!(
                uid,
                gid,
                pid,
                "admin socket: caller is not an admin; refused before reading its request"
            );
            refuse(
                s,
                Failure::NotPermitted {
                    message: format!(
                        "uid {uid} gid {gid} is not in the daemon's admin uids or gids"
                    ),
                },
            );
            continue;
        }
        if active.fetch_add(1, Ordering::SeqCst) >= MAX_ADMIN_CONNECTIONS {
            active.fetch_sub(1, Ordering::SeqCst);
            tracing::warn!(
                uid,
                pid,
                max = MAX_ADMIN_CONNECTIONS,
                "admin socket: too many admin connections at once; refused"
            );
            refuse(
                s,
                Failure::Internal {
                    message: format!(
                        "{MAX_ADMIN_CONNECTIONS} admin connections are being served; try again"
                    ),
                },
            );
            continue;
        }
        let (jobs, active2) = (jobs.clone(), active.clone());
        let spawned = std::thread::Builder::new()
            .name("admin-conn".into())
            .spawn(move || {
                if let Err(e) = serve_connection(s, uid, gid, pid, &jobs) {
                    tracing::debug!(error = %e, "admin socket: connection ended");
                }
                active2.fetch_sub(1, Ordering::SeqCst);
            });
        if let Err(e) = spawned {
            active.fetch_sub(1, Ordering::SeqCst);
            tracing::warn!(error = %e, "admin socket: cannot start a connection thread");
        }
    }
}

/// Fill `buf` from `s` before `deadline` (a bound on the whole read, however the caller
/// spreads its bytes). `Ok(false)`: the caller closed before the first byte.
fn read_by(s: &mut UnixStream, buf: &mut [u8], deadline: Instant) -> std::io::Result<bool> {
    let mut got = 0;
    while got < buf.len() {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!("deadline passed with {got} of {} bytes", buf.len()),
            ));
        }
        s.set_read_timeout(Some(left))?;
        match s.read(&mut buf[got..]) {
            Ok(0) if got == 0 => return Ok(false),
            Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(e) => return Err(e),
        }
    }
    Ok(true)
}

/// Answer the requests of one admin connection until it closes, breaks a frame or misses
/// its deadline.
fn serve_connection(
    s: UnixStream,
    uid: u32,
    gid: u32,
    pid: i32,
    jobs: &mpsc::Sender<AdminJob>,
) -> std::io::Result<()> {
    let peer = Arc::new(s);
    let mut s = peer.try_clone()?;
    s.set_write_timeout(Some(WRITE_TIMEOUT))?;
    loop {
        let start = Instant::now();
        let deadline = start + REQUEST_DEADLINE;
        let slow = |e: &std::io::Error, what: &str| {
            if e.kind() == std::io::ErrorKind::TimedOut {
                tracing::warn!(
                    uid,
                    pid,
                    millis = start.elapsed().as_millis() as u64,
                    "admin socket: {what} not received within {REQUEST_DEADLINE:?}; connection closed"
                );
            }
        };
        let mut len = [0u8; 4];
        match read_by(&mut s, &mut len, deadline) {
            Ok(true) => {}
            Ok(false) => return Ok(()),
            Err(e) => {
                slow(&e, "request");
                return Err(e);
            }
        }
        let len = u32::from_le_bytes(len) as usize;
        if let Err(e) = admin::check_request_len(len) {
            // The stream cannot be resynchronised: answer once and close.
            return s.write_all(&refusal(&Failure::BadRequest {
                message: e.to_string(),
            }));
        }
        let mut body = vec![0u8; len];
        if let Err(e) = read_by(&mut s, &mut body, deadline).and_then(|whole| {
            if whole {
                Ok(())
            } else {
                Err(std::io::ErrorKind::UnexpectedEof.into())
            }
        }) {
            slow(&e, &format!("request frame of {len} bytes"));
            return Err(e);
        }
        let (header, payload) = admin::decode_request(&body)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))?;
        drop(body);
        tracing::info!(uid, gid, pid, op = header.op, "admin request");
        let (reply, answer) = mpsc::sync_channel(1);
        let state = Arc::new(AtomicU8::new(QUEUED));
        let job = AdminJob {
            header,
            payload,
            reply,
            peer: peer.clone(),
            state: state.clone(),
            uid,
            pid,
        };
        if jobs.send(job).is_err() {
            return Ok(()); // the daemon is stopping
        }
        let response = match answer.recv_timeout(ANSWER_TIMEOUT) {
            Ok(r) => r,
            Err(mpsc::RecvTimeoutError::Disconnected) => return Ok(()),
            Err(mpsc::RecvTimeoutError::Timeout) => {
                // Give the job up unless the loop has taken it; a taken job is answered.
                if state
                    .compare_exchange(QUEUED, ABANDONED, Ordering::SeqCst, Ordering::SeqCst)
                    .is_ok()
                {
                    tracing::warn!(
                        uid,
                        pid,
                        op = header.op,
                        "admin socket: the serving loop did not take the request within {ANSWER_TIMEOUT:?}; not applied, connection closed"
                    );
                    return Ok(());
                }
                match answer.recv() {
                    Ok(r) => r,
                    Err(_) => return Ok(()),
                }
            }
        };
        s.write_all(&admin::encode_response(&response.0, &response.1))?;
        if matches!(decode_code::<Op>(header.op), Some(Op::Enroll | Op::Forget)) {
            tracing::debug!(uid, pid, op = header.op, "admin change answered");
        }
    }
}
