//! The admin endpoint: enroll and forget through the daemon's Unix socket, where the daemon
//! checks who is calling (`SO_PEERCRED` against its configured admin uids and gids). Same
//! request and response headers as on iceoryx2, framed for a byte stream
//! (`guardian_shared::wire::admin`, `docs/wire-protocol.md` §8).

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use guardian_shared::wire::{
    self, ClassEntry, Op, RequestHeader, ResponseHeader, admin, decode_code,
};

use crate::{CheckError, ClassInfo, EnrollError, Trajectory};

/// Most class entries an admin response may carry (an enroll answers one).
const MAX_ENTRIES: usize = 1;

/// A client of the daemon's admin socket. Each call opens its own connection, so the value
/// is cheap, `Send` and usable from any thread.
#[derive(Debug, Clone)]
pub struct AdminClient {
    path: PathBuf,
    timeout: Duration,
}

impl AdminClient {
    /// A client of the socket at `path` (the daemon's `[admin] socket`; installed:
    /// [`crate::DEFAULT_ADMIN_SOCKET`]); each call waits at most `timeout`.
    pub fn new(path: impl Into<PathBuf>, timeout: Duration) -> Self {
        Self {
            path: path.into(),
            timeout,
        }
    }

    /// The socket path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Add `examples` to `class`, as [`crate::Client::enroll`] does over iceoryx2.
    ///
    /// A failure means the enroll was not applied, except
    /// [`CheckError::OutcomeUnknown`]: the request was sent whole and no answer came.
    pub fn enroll(&self, class: &str, examples: &[Trajectory]) -> Result<ClassInfo, EnrollError> {
        let (h, payload) = crate::enroll_request(class, examples)?;
        let (r, entries) = self.call(h, &payload, MAX_ENTRIES)?;
        crate::enrolled(&r, &entries)
    }

    /// Remove `class` from the bank (failures as for [`AdminClient::enroll`]).
    pub fn forget(&self, class: &str) -> Result<(), CheckError> {
        let h = RequestHeader::encode(Op::Forget, Some(class), 0, &[])?;
        let (r, _) = self.call(h, &[], MAX_ENTRIES)?;
        crate::status_ok(&r)
    }

    /// The enrolled classes, as the daemon holds them after every admin request that was
    /// sent before this one (the serving loop answers admin requests in arrival order).
    pub fn classes(&self) -> Result<Vec<ClassInfo>, CheckError> {
        crate::list_classes(|h| self.call(h, &[], wire::MAX_RESPONSE_ENTRIES))
    }

    fn io(&self, what: &str) -> impl FnOnce(std::io::Error) -> CheckError + '_ {
        let what = what.to_owned();
        move |e| CheckError::AdminSocket {
            path: self.path.clone(),
            kind: e.kind(),
            detail: format!("{what}: {e}"),
        }
    }

    fn call(
        &self,
        mut header: RequestHeader,
        payload: &[f32],
        max_entries: usize,
    ) -> Result<(ResponseHeader, Vec<ClassEntry>), CheckError> {
        header.request_id = u64::from(std::process::id());
        let mut s = UnixStream::connect(&self.path).map_err(self.io("connect"))?;
        s.set_read_timeout(Some(self.timeout))
            .and_then(|()| s.set_write_timeout(Some(self.timeout)))
            .map_err(self.io("set timeout"))?;
        if let Err(e) = s.write_all(&admin::encode_request(&header, payload)) {
            // Not sent whole, so not applied. A caller the daemon refuses at connect (not an
            // admin, or too many admin connections) finds the refusal waiting.
            return match read_frame(&mut s, max_entries) {
                Ok(Ok((r, _))) if r.request_id == 0 => Err(refused(&r)),
                _ => Err(self.io("send request")(e)),
            };
        }
        let (r, entries) = match read_frame(&mut s, max_entries) {
            Ok(frame) => frame?,
            Err(e) => {
                let op = match decode_code::<Op>(header.op) {
                    Some(Op::Enroll) => "enroll",
                    Some(Op::Forget) => "forget",
                    _ => return Err(self.io("read response")(e)),
                };
                // Hang up first: from now on the daemon will not apply the change if it has
                // not taken it yet.
                drop(s);
                return Err(CheckError::OutcomeUnknown {
                    op,
                    class: guardian_shared::wire::decode_text(&header.class_name),
                    path: self.path.clone(),
                    detail: match e.kind() {
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => {
                            format!("timed out after {:?}", self.timeout)
                        }
                        std::io::ErrorKind::UnexpectedEof => {
                            "the daemon closed the connection".into()
                        }
                        _ => e.to_string(),
                    },
                });
            }
        };
        if r.request_id == 0 && r.op == 0 {
            // Answered as a connection (refused before the request was read).
            return Err(refused(&r));
        }
        if r.request_id != header.request_id || r.op != header.op {
            return Err(CheckError::Protocol {
                detail: "admin response does not echo the request's id and op".into(),
            });
        }
        Ok((r, entries))
    }
}

/// The error a connection-level answer (request id 0) carries.
fn refused(r: &ResponseHeader) -> CheckError {
    match crate::status_ok(r) {
        Err(e) => e,
        Ok(()) => CheckError::Protocol {
            detail: "a connection-level admin answer without a failure".into(),
        },
    }
}

/// Read one response frame: `Err` if the bytes did not arrive, `Ok(Err)` if they do not
/// make a valid frame.
fn read_frame(
    s: &mut UnixStream,
    max_entries: usize,
) -> std::io::Result<Result<(ResponseHeader, Vec<ClassEntry>), CheckError>> {
    let mut len = [0u8; 4];
    s.read_exact(&mut len)?;
    let len = u32::from_le_bytes(len) as usize;
    if let Err(e) = admin::check_response_len(len, max_entries) {
        return Ok(Err(CheckError::Protocol {
            detail: e.to_string(),
        }));
    }
    let mut body = vec![0u8; len];
    s.read_exact(&mut body)?;
    Ok(
        admin::decode_response(&body, max_entries).map_err(|e| CheckError::Protocol {
            detail: e.to_string(),
        }),
    )
}
