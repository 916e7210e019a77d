//! The admin endpoint: enroll and forget through the daemon's Unix socket, where the daemon
//! checks who is calling (`SO_PEERCRED` against its configured admin uids and gids). Same
//! request and response headers as on iceoryx2, framed for a byte stream
//! (`guardian_shared::wire::admin`, `docs/wire-protocol.md` §8).

use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use guardian_shared::wire::{ClassEntry, Op, RequestHeader, ResponseHeader, admin};

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
    pub fn enroll(&self, class: &str, examples: &[Trajectory]) -> Result<ClassInfo, EnrollError> {
        let (h, payload) = crate::enroll_request(class, examples)?;
        let (r, entries) = self.call(h, &payload)?;
        crate::enrolled(&r, &entries)
    }

    /// Remove `class` from the bank.
    pub fn forget(&self, class: &str) -> Result<(), CheckError> {
        let h = RequestHeader::encode(Op::Forget, Some(class), 0, &[])?;
        let (r, _) = self.call(h, &[])?;
        crate::status_ok(&r)
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
    ) -> Result<(ResponseHeader, Vec<ClassEntry>), CheckError> {
        header.request_id = u64::from(std::process::id());
        let mut s = UnixStream::connect(&self.path).map_err(self.io("connect"))?;
        s.set_read_timeout(Some(self.timeout))
            .and_then(|()| s.set_write_timeout(Some(self.timeout)))
            .map_err(self.io("set timeout"))?;
        s.write_all(&admin::encode_request(&header, payload))
            .map_err(self.io("send request"))?;
        let mut len = [0u8; 4];
        s.read_exact(&mut len).map_err(self.io("read response"))?;
        let len = u32::from_le_bytes(len) as usize;
        admin::check_response_len(len, MAX_ENTRIES).map_err(|e| CheckError::Protocol {
            detail: e.to_string(),
        })?;
        let mut body = vec![0u8; len];
        s.read_exact(&mut body).map_err(self.io("read response"))?;
        let (r, entries) =
            admin::decode_response(&body, MAX_ENTRIES).map_err(|e| CheckError::Protocol {
                detail: e.to_string(),
            })?;
        if r.request_id != header.request_id || r.op != header.op {
            return Err(CheckError::Protocol {
                detail: "admin response does not echo the request's id and op".into(),
            });
        }
        Ok((r, entries))
    }
}
