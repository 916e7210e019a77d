//! Remote checks over Zenoh (feature `fleet`): [`RemoteClient`] asks a fleet member's
//! `guardian/<fleet>/<member>/check` queryable for check, identify and status, with the
//! same API and answers as the local [`crate::Client`]. Each request is the iceoryx2
//! request's bytes in an envelope signed by this caller's key (which the member must list
//! in `caller-keys`), and each answer is signed by the member's key, which this client
//! checks (`docs/fleet.md`, `docs/wire-protocol.md` §10). A remote caller can never enroll
//! or forget.

use std::path::PathBuf;
use std::time::Duration;

use guardian_fleet::keys::{SigningKey, VerifyingKey, parse_public_key, read_signing_key};
use guardian_fleet::node::Caller;
use guardian_fleet::remote::{RemoteError, nonce, now_ms, open_response, seal_request};
use guardian_shared::wire::{ClassEntry, Op, RequestHeader, ResponseHeader, admin};

use crate::{CheckError, ConnectError, DaemonStatus, Ranking, Trajectory, Verdict};

/// Most class entries a remote answer may carry.
const MAX_ENTRIES: usize = 4096;

/// Where and how to reach a fleet member.
#[derive(Debug, Clone)]
pub struct RemoteConfig {
    /// Zenoh endpoints to connect to (the member's `listen`, e.g. `tcp/10.0.0.7:7447`).
    pub connect: Vec<String>,
    /// The fleet's name.
    pub fleet: String,
    /// The member to ask.
    pub member: String,
    /// This caller's secret key file (`guardiand --fleet-keygen`; its public key must be in
    /// the member's `caller-keys`).
    pub caller_key: PathBuf,
    /// The member's public key (64 hex digits; its `signing-key`'s `.pub` file).
    pub member_key: String,
    /// How long a call waits for its answer.
    pub timeout: Duration,
}

/// A client of one fleet member over Zenoh.
#[derive(Debug)]
pub struct RemoteClient {
    caller: Caller,
    key: SigningKey,
    member_key: VerifyingKey,
    fleet: String,
    member: String,
    timeout: Duration,
    next_id: std::sync::atomic::AtomicU64,
}

fn invalid(detail: impl std::fmt::Display) -> ConnectError {
    ConnectError::InvalidConfig {
        detail: detail.to_string(),
    }
}

fn protocol(e: RemoteError) -> CheckError {
    CheckError::Protocol {
        detail: format!("remote answer refused: {e}"),
    }
}

impl RemoteClient {
    /// Open a Zenoh session to `config.connect` (peer mode, no scouting).
    pub fn connect(config: RemoteConfig) -> Result<Self, ConnectError> {
        let key = read_signing_key(&config.caller_key).map_err(invalid)?;
        let member_key = parse_public_key(&config.member_key, "member-key").map_err(invalid)?;
        if config.connect.is_empty() {
            return Err(invalid("no Zenoh endpoint to connect to"));
        }
        let caller = Caller::connect(&config.connect).map_err(invalid)?;
        Ok(Self {
            caller,
            key,
            member_key,
            fleet: config.fleet,
            member: config.member,
            timeout: config.timeout,
            next_id: std::sync::atomic::AtomicU64::new(1),
        })
    }

    fn call(
        &self,
        mut header: RequestHeader,
        payload: &[f32],
    ) -> Result<(ResponseHeader, Vec<ClassEntry>), CheckError> {
        let id = self
            .next_id
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        header.request_id = id;
        let frame = admin::encode_request(&header, payload);
        let n = nonce().map_err(|e| CheckError::Internal {
            message: format!("cannot draw a nonce: {e}"),
        })?;
        let env = seal_request(
            &self.key,
            &self.fleet,
            &self.member,
            &frame[4..],
            now_ms(),
            n,
        );
        let answer = self
            .caller
            .call(&self.fleet, &self.member, env, self.timeout)
            .map_err(|e| match e {
                guardian_fleet::node::NodeError::Zenoh {
                    what: "wait for the remote answer",
                    ..
                } => CheckError::Timeout {
                    after: self.timeout,
                },
                other => CheckError::NotServing {
                    detail: other.to_string(),
                },
            })?
            .map_err(|message| CheckError::NotPermitted { message })?;
        let body = open_response(&self.member_key, &self.fleet, &self.member, n, &answer)
            .map_err(protocol)?;
        let (r, entries) =
            admin::decode_response(&body, MAX_ENTRIES).map_err(|e| CheckError::Protocol {
                detail: e.to_string(),
            })?;
        if r.request_id != id {
            return Err(CheckError::Protocol {
                detail: format!("answer to request {} instead of {id}", r.request_id),
            });
        }
        Ok((r, entries))
    }

    /// Is `trajectory` the task `claimed_class`? As [`crate::Client::check`].
    pub fn check(
        &self,
        trajectory: &Trajectory,
        claimed_class: &str,
    ) -> Result<Verdict, CheckError> {
        let h = RequestHeader::encode(
            Op::Check,
            Some(claimed_class),
            trajectory.channels(),
            &[trajectory.len()],
        )?;
        let (r, entries) = self.call(h, trajectory.as_flat())?;
        crate::verdict_of_response(&r, &entries, claimed_class)
    }

    /// The nearest enrolled classes to `trajectory`. As [`crate::Client::identify`].
    pub fn identify(&self, trajectory: &Trajectory) -> Result<Ranking, CheckError> {
        let h = RequestHeader::encode(
            Op::Identify,
            None,
            trajectory.channels(),
            &[trajectory.len()],
        )?;
        let (r, entries) = self.call(h, trajectory.as_flat())?;
        crate::ranking(&r, &entries)
    }

    /// Versions, counters, latency percentiles and fleet position. As
    /// [`crate::Client::status`].
    pub fn status(&self) -> Result<DaemonStatus, CheckError> {
        let (r, entries) = self.call(RequestHeader::new(0, Op::Status), &[])?;
        crate::daemon_status(&r, &entries)
    }

    /// Send an arbitrary request (tests: a remote enroll must be refused).
    #[doc(hidden)]
    pub fn raw(
        &self,
        header: RequestHeader,
        payload: &[f32],
    ) -> Result<(ResponseHeader, Vec<ClassEntry>), CheckError> {
        self.call(header, payload)
    }
}
