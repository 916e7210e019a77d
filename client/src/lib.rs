//! guardian-client: the thin library a motion planner links to ask `guardiand` whether a
//! candidate trajectory is the task it claims to be. It speaks iceoryx2 shared memory and
//! pulls in no model code.
//!
//! ```no_run
//! use guardian_client::{Client, ClientConfig, Trajectory};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let client = Client::connect(ClientConfig::default())?;
//! // The daemon says which robot it serves; a plan has that robot's joints + the tool.
//! let robot = client.status()?.robot;
//! assert_eq!(robot.joints, 7, "this planner plans for the Panda");
//! let plan: Vec<f32> = [0.0, -0.7, 0.0, -2.3, 0.0, 1.6, 0.8, 0.0].repeat(50);
//! let verdict = client.check(&Trajectory::from_flat(plan, robot.channels()), "character01")?;
//! if verdict.is_go() { /* execute */ } else { println!("no-go: {:?}", verdict.decision); }
//! # Ok(()) }
//! ```
//!
//! # Threads and processes
//! A [`Client`] owns iceoryx2 `ipc::Service` ports, which are single-threaded: `Client` is
//! neither `Send` nor `Sync`. Give every planner thread (or process) its own `Client` — each
//! `connect` creates its own iceoryx2 node and ports, and the daemon serves them all; see
//! `tests/tests/e2e.rs` (`eight_concurrent_clients_get_their_own_answers`). The daemon admits
//! `max-clients` (default 32) client ports at once.
//!
//! # Errors and timeouts
//! Every call waits at most [`ClientConfig::timeout`] and then returns
//! [`CheckError::Timeout`]. A dead daemon, a timeout or any transport problem is an error,
//! never a `Go`. Responses whose `request_id` does not match the request are discarded.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

/// Synthetic sample trajectories for tests (feature `samples`, off by default).
#[cfg(feature = "samples")]
#[doc(hidden)]
pub mod samples;

mod admin;
mod locate;
#[cfg(feature = "fleet")]
pub mod remote;
pub use admin::AdminClient;
pub use locate::{ADMIN_SOCKET_ENV, LocateAdminError, QUICK_START_ADMIN_SOCKET};

use std::cell::Cell;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use iceoryx2::port::listener::ListenerWaitError;
use iceoryx2::prelude::*;
use serde::Serialize;

pub use guardian_shared::trajectory::{
    InvalidKind, MAX_JOINTS, MAX_WAYPOINTS, MIN_WAYPOINTS, Waypoint, waypoint,
};
use guardian_shared::wire::{
    self, ClassEntry, ClassNameError, Failure, MAX_CHANNELS, MAX_EXAMPLES, Op, ProtocolError,
    RequestHeader, ResponseHeader,
};
pub use guardian_shared::wire::{DEFAULT_ADMIN_SOCKET, Limit, LimitKind};
pub use guardian_shared::workcell::{GeometryFeature, WorkcellKind};

/// How to reach the daemon.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClientConfig {
    /// The daemon's request-response service name ([`wire::DEFAULT_SERVICE_NAME`]).
    pub service_name: String,
    /// Longest wait for one response.
    pub timeout: Duration,
    /// iceoryx2 `global.root-path`; must match the daemon's.
    pub iceoryx2_root_path: Option<PathBuf>,
    /// iceoryx2 `global.prefix`; must match the daemon's.
    pub iceoryx2_prefix: Option<String>,
}

impl Default for ClientConfig {
    fn default() -> Self {
        Self {
            service_name: wire::DEFAULT_SERVICE_NAME.to_owned(),
            timeout: Duration::from_secs(2),
            iceoryx2_root_path: None,
            iceoryx2_prefix: None,
        }
    }
}

/// A trajectory as sent: row-major waypoints of `channels` floats each, the served robot's
/// joint positions (rad, or m for a prismatic joint) then the tool (0/1): 8 for the Panda,
/// 7 for the UR5e ([`RobotInfo::channels`] from [`Client::status`]). Build it from a flat
/// buffer ([`Trajectory::from_flat`], any channel count, so a wrong one reaches the daemon
/// and is reported, as for a C planner) or from in-memory [`Waypoint`]s of a robot with
/// `joints` joints ([`Trajectory::from_waypoints`]). Bounds: [`MIN_WAYPOINTS`]..=
/// [`MAX_WAYPOINTS`] waypoints, joints within the served robot's limits, tool exactly 0 or
/// 1 — checked by the daemon, not here.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    data: Vec<f32>,
    channels: usize,
}

impl Trajectory {
    /// From in-memory waypoints of a robot with `joints` joints (slots `0..joints` and the
    /// tool are sent: `joints + 1` channels).
    pub fn from_waypoints(waypoints: &[Waypoint], joints: usize) -> Self {
        let joints = joints.min(MAX_JOINTS);
        Self {
            data: guardian_shared::trajectory::to_flat(waypoints, joints),
            channels: joints + 1,
        }
    }

    /// From a flat buffer of `channels`-wide rows (a trailing partial row is dropped).
    pub fn from_flat(mut data: Vec<f32>, channels: usize) -> Self {
        let keep = data.len().checked_div(channels).unwrap_or(0) * channels;
        data.truncate(keep);
        Self { data, channels }
    }

    /// Number of waypoints.
    pub fn len(&self) -> usize {
        self.data.len().checked_div(self.channels).unwrap_or(0)
    }

    /// No waypoints.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Floats per waypoint.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The flat data.
    pub fn as_flat(&self) -> &[f32] {
        &self.data
    }
}

pub use guardian_shared::verdict::{Decision, Neighbour, NoGoReason, Verdict};

/// The verdict a check response carries (header and entries, as any transport delivers
/// them) for a check that claimed `claimed_class` ([`wire::decode_check`], the one
/// conversion from the wire; the daemon's [`wire::encode_check`] is the one conversion to
/// it). A daemon error status, or a response that does not answer that check, is an error.
pub fn verdict_of_response(
    r: &ResponseHeader,
    entries: &[ClassEntry],
    claimed_class: &str,
) -> Result<Verdict, CheckError> {
    status_ok(r)?;
    if r.op != Op::Check as u32 || wire::decode_text(&r.class_name) != claimed_class {
        return Err(CheckError::Protocol {
            detail: "response does not echo the request's op and class".into(),
        });
    }
    wire::decode_check(r, entries, claimed_class).map_err(protocol)
}

/// The answer to [`Client::identify`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Ranking {
    /// The k nearest classes, nearest first.
    pub nearest: Vec<Neighbour>,
    /// Model version that answered.
    pub model_version: String,
    /// Class bank version that answered.
    pub bank_version: u64,
}

/// An enrolled class.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClassInfo {
    /// Class name.
    pub name: String,
    /// Enrolled examples.
    pub examples: u32,
    /// Decision threshold.
    pub threshold: f32,
    /// Whether the threshold is calibrated for this class (else the global default).
    pub calibrated: bool,
}

/// The answer to [`Client::status`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DaemonStatus {
    /// Model version.
    pub model_version: String,
    /// Class bank version (increments on every change).
    pub bank_version: u64,
    /// Enrolled classes.
    pub classes: u32,
    /// Time since the daemon started.
    pub uptime: Duration,
    /// Requests answered.
    pub requests: u64,
    /// Requests answered with an error.
    pub errors: u64,
    /// Checks answered go.
    pub go: u64,
    /// Checks answered no-go.
    pub no_go: u64,
    /// Service-time percentiles over recent requests in microseconds: p50, p90, p99, max
    /// (`None` before the first request).
    pub latency_us: Option<[f32; 4]>,
    /// The robot the daemon serves (its trajectories have `joints + 1` channels).
    pub robot: RobotInfo,
    /// A fleet member's position (`docs/fleet.md`): per record signer, the greatest Lamport
    /// counter of its records applied here; empty for a daemon outside a fleet.
    pub fleet: Vec<FleetPosition>,
    /// A fleet member's bank digest (`docs/fleet.md`): the first 16 bytes, in hex, of the
    /// SHA-256 over every class it serves. Members with equal digests serve the same
    /// classes; `None` for a daemon outside a fleet.
    pub bank_digest: Option<String>,
}

/// How far a fleet member has applied one signer's records.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct FleetPosition {
    /// The first 16 hex digits of the signer's public key.
    pub signer: String,
    /// The greatest Lamport counter of that signer's records applied.
    pub lamport: u64,
}

/// The robot a daemon serves.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct RobotInfo {
    /// Its name (`panda`, `ur5e`, or the name in a description file).
    pub name: String,
    /// Joints.
    pub joints: u32,
    /// SHA-256 of its URDF, 64 hex digits.
    pub urdf_sha256: String,
}

impl RobotInfo {
    /// Floats per waypoint of this robot's trajectories: its joints and the tool.
    pub fn channels(&self) -> usize {
        self.joints as usize + 1
    }
}

/// [`Client::connect`] failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConnectError {
    /// A config value is unusable.
    #[error("invalid client config: {detail}")]
    InvalidConfig {
        /// What is wrong.
        detail: String,
    },
    /// No daemon serves this service name.
    #[error("guardiand is not running (no server on service {service:?})")]
    DaemonNotRunning {
        /// The service name.
        service: String,
    },
    /// The iceoryx2 root path or prefix is unusable.
    #[error(transparent)]
    Iceoryx2Config(#[from] guardian_shared::ipc::Iceoryx2ConfigError),
    /// An iceoryx2 setup or port operation failed.
    #[error(transparent)]
    Iceoryx(#[from] guardian_shared::ipc::Iceoryx2Error),
}

/// A request (check, identify, forget, classes, status) failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum CheckError {
    /// No response within the configured timeout.
    #[error("no response from guardiand within {after:?}")]
    Timeout {
        /// The timeout.
        after: Duration,
    },
    /// The daemon is gone (no server, or it dropped the request unanswered).
    #[error("guardiand is not serving: {detail}")]
    NotServing {
        /// What was observed.
        detail: String,
    },
    /// The class name was rejected (by this client or the daemon).
    #[error("invalid class name: {0}")]
    InvalidClassName(#[from] ClassNameError),
    /// A trajectory failed validation (identify, enroll).
    #[error("invalid trajectory {example}: {kind:?} at index {index}")]
    InvalidTrajectory {
        /// What is wrong.
        kind: InvalidKind,
        /// Waypoint index or offending count.
        index: u32,
        /// Which trajectory of the request.
        example: u32,
    },
    /// The class is not enrolled.
    #[error("class {class:?} is not enrolled")]
    UnknownClass {
        /// The class.
        class: String,
    },
    /// The bank has no classes.
    #[error("no classes are enrolled")]
    EmptyBank,
    /// The daemon rejected the request as malformed.
    #[error("bad request: {message}")]
    BadRequest {
        /// The daemon's explanation.
        message: String,
    },
    /// The daemon failed internally.
    #[error("guardiand internal error: {message}")]
    Internal {
        /// The daemon's explanation.
        message: String,
    },
    /// The daemon could not persist the change (its state directory is full or read-only,
    /// or an I/O error) and did not apply it: the bank is as before. Retry once the cause
    /// is fixed.
    #[error("guardiand could not persist the change (nothing changed): {message}")]
    Storage {
        /// The daemon's explanation (the file and the system error).
        message: String,
    },
    /// A fleet member made the enroll or forget (it is in effect and durable there), but
    /// fewer peers than its `[fleet] replicas` acknowledged holding it within
    /// `replica-timeout-ms`: they get it when they catch up, and it is lost if that member
    /// is lost first. Retrying makes the change again (a new record).
    #[error("the change is in effect on this member, but not yet on enough peers: {message}")]
    Unreplicated {
        /// How many peers hold it, how many were required, within how long.
        message: String,
    },
    /// An iceoryx2 operation failed.
    #[error(transparent)]
    Transport(TransportError),
    /// The response violates the protocol.
    #[error("protocol violation: {detail}")]
    Protocol {
        /// What was wrong.
        detail: String,
    },
    /// The enroll would take the bank past a configured limit; nothing changed.
    #[error("{} limit of {} reached (the enroll needs {}): {message}", .limit.kind.key(), .limit.max, .limit.requested)]
    LimitExceeded {
        /// Which limit, its value and what the enroll asked for.
        limit: Limit,
        /// The daemon's explanation.
        message: String,
    },
    /// The daemon does not permit this operation here: enroll and forget on the planners'
    /// service under admin separation (use the admin socket, [`AdminClient`]), or a caller
    /// that is not in the admin list.
    #[error("not permitted: {message}")]
    NotPermitted {
        /// The daemon's explanation.
        message: String,
    },
    /// An enroll or forget was sent whole over the admin socket but no answer came (timeout,
    /// or the connection broke): the daemon may or may not have applied it. The daemon
    /// applies a change only while its requester still waits, so once this client has hung
    /// up (it has, when this error is returned) the outcome is settled and the next request
    /// served shows it: ask the admin socket ([`AdminClient::classes`], `guardianctl
    /// classes --admin`) whether the class is there.
    #[error(
        "outcome unknown: the {op} of class {class:?} was sent to the admin socket {} but no answer came ({detail}); \
         the daemon applied it only if it had taken it before this client gave up — list the classes through \
         the admin socket (`guardianctl --admin-socket {} classes --admin`) to see whether it happened",
        .path.display(), .path.display()
    )]
    OutcomeUnknown {
        /// `enroll` or `forget`.
        op: &'static str,
        /// The class.
        class: String,
        /// The socket.
        path: PathBuf,
        /// What happened to the answer.
        detail: String,
    },
    /// The admin socket could not be reached or broke off (nothing was applied: the request
    /// was not sent whole, or it changes nothing).
    #[error("admin socket {}: {detail}", .path.display())]
    AdminSocket {
        /// The socket.
        path: PathBuf,
        /// The I/O error's kind.
        kind: std::io::ErrorKind,
        /// What was being done and the error.
        detail: String,
    },
}

/// [`Client::enroll`] failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum EnrollError {
    /// No trajectories were given.
    #[error("enroll needs at least one example")]
    NoExamples,
    /// More than [`MAX_EXAMPLES`] trajectories.
    #[error("{got} examples, at most {max} per request")]
    TooManyExamples {
        /// Given.
        got: usize,
        /// Allowed.
        max: usize,
    },
    /// The request failed.
    #[error(transparent)]
    Request(#[from] CheckError),
}

/// An iceoryx2 operation of a request failed: what was being done, with iceoryx2's error as
/// the source ([`guardian_shared::ipc::Iceoryx2Error`]). It is shared behind an [`Arc`] so
/// that [`CheckError`] stays `Clone` and `PartialEq` (callers keep and compare errors; the
/// iceoryx2 errors themselves are neither): a value equals itself and its clones, never
/// another failure.
#[derive(Debug, Clone, thiserror::Error)]
#[error(transparent)]
pub struct TransportError(Arc<guardian_shared::ipc::Iceoryx2Error>);

impl TransportError {
    /// What was being done.
    pub fn what(&self) -> &'static str {
        self.0.what
    }
}

impl PartialEq for TransportError {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

fn transport<E: std::error::Error + Send + Sync + 'static>(
    what: &'static str,
) -> impl FnOnce(E) -> CheckError {
    let during = guardian_shared::ipc::Iceoryx2Error::during(what);
    move |e| CheckError::Transport(TransportError(Arc::new(during(e))))
}

fn connect_err<E: std::error::Error + Send + Sync + 'static>(
    what: &'static str,
) -> impl FnOnce(E) -> ConnectError {
    let during = guardian_shared::ipc::Iceoryx2Error::during(what);
    move |e| during(e).into()
}

type RpcClient = iceoryx2::port::client::Client<
    ipc::Service,
    [f32],
    RequestHeader,
    [ClassEntry],
    ResponseHeader,
>;

/// A connection to `guardiand`. Not `Send`: one per thread (see the crate docs).
pub struct Client {
    client: RpcClient,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
    timeout: Duration,
    spin: Duration,
    next_id: Cell<u64>,
    // Declared last: ports must drop before their node.
    _node: Node<ipc::Service>,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client")
            .field("timeout", &self.timeout)
            .finish_non_exhaustive()
    }
}

/// Held while a [`Client`] opens its iceoryx2 ports (see [`Client::connect`]).
static CONNECTING: std::sync::Mutex<()> = std::sync::Mutex::new(());

impl Client {
    /// Open the daemon's services. Fails with [`ConnectError::DaemonNotRunning`] when no
    /// daemon serves `config.service_name`.
    pub fn connect(config: ClientConfig) -> Result<Client, ConnectError> {
        // iceoryx2 sets the process umask to 0177 while it binds a Unix datagram socket
        // (a listener) and restores what it found; two threads connecting at once could
        // leave 0177 behind for the whole process (files it creates later: 0600,
        // directories unusable). Connects in one process take turns.
        let _one_at_a_time = CONNECTING
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let ic = guardian_shared::ipc::iceoryx2_config(
            config.iceoryx2_root_path.as_deref(),
            config.iceoryx2_prefix.as_deref(),
        )?;
        let node = NodeBuilder::new()
            .config(&ic)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(connect_err("create node"))?;
        let name = |s: String| {
            ServiceName::new(&s).map_err(|e| ConnectError::InvalidConfig {
                detail: format!("service name {s:?}: {e:?}"),
            })
        };
        let not_running = || ConnectError::DaemonNotRunning {
            service: config.service_name.clone(),
        };
        let rpc = node
            .service_builder(&name(config.service_name.clone())?)
            .request_response::<[f32], [ClassEntry]>()
            .request_user_header::<RequestHeader>()
            .response_user_header::<ResponseHeader>()
            .open()
            .map_err(|e| match e {
                iceoryx2::service::builder::request_response::RequestResponseOpenError::DoesNotExist => {
                    not_running()
                }
                other => connect_err("open request-response service")(other),
            })?;
        if rpc.dynamic_config().number_of_servers() == 0 {
            return Err(not_running());
        }
        let wake_server = node
            .service_builder(&name(wire::request_event_name(&config.service_name))?)
            .event()
            .open()
            .map_err(connect_err("open request event service"))?;
        let notifier = wake_server
            .notifier_builder()
            .create()
            .map_err(connect_err("create notifier"))?;
        // A static pool sized for the largest request (16 examples of 4096 waypoints of 17
        // channels, 4.25 MiB a chunk, backed only where written) and one request at a time.
        // A growable pool made iceoryx2 set up and tear down bookkeeping for the 255
        // segments it may grow to whenever this client connected or left, on the daemon's
        // serving loop too (issue 39, docs/performance.md "A connecting client").
        let client = rpc
            .client_builder()
            .initial_max_slice_len(wire::MAX_EXAMPLES * MAX_WAYPOINTS * MAX_CHANNELS)
            .max_active_requests(1)
            .allocation_strategy(AllocationStrategy::Static)
            .create()
            .map_err(connect_err("create client port"))?;
        // This client's own response event service (named after its port id, which the
        // daemon sees on every request): an answer wakes only this client. Its listener
        // exists before the first request, so no wake-up is lost.
        let own_events = node
            .service_builder(&name(wire::client_response_event_name(
                &config.service_name,
                client.id().value(),
            ))?)
            .event()
            .max_listeners(1)
            .max_notifiers(4)
            .max_nodes(4)
            .create()
            .map_err(connect_err("create own response event service"))?;
        let listener = own_events
            .listener_builder()
            .create()
            .map_err(connect_err("create listener"))?;
        // Distinct id streams per client keep logs readable; uniqueness per client is all
        // the protocol needs.
        let seed = u64::from(std::process::id()) << 32;
        Ok(Client {
            client,
            notifier,
            listener,
            timeout: config.timeout,
            spin: Duration::ZERO,
            next_id: Cell::new(seed | 1),
            _node: node,
        })
    }

    /// The per-request timeout.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// Poll for the response without sleeping for up to `spin` after each request, before
    /// waiting on the daemon's notification (default: zero, sleep at once). Pairs with a
    /// daemon in `busy-poll` mode when the planner can spare a core: it saves the wake-up
    /// of the planner thread (see `docs/performance.md`).
    pub fn set_spin(&mut self, spin: Duration) {
        self.spin = spin;
    }

    /// Send one request and wait for the response with the same id.
    fn call(
        &self,
        mut header: RequestHeader,
        payload: &[f32],
    ) -> Result<(ResponseHeader, Vec<ClassEntry>), CheckError> {
        let id = self.next_id.get();
        self.next_id.set(id.wrapping_add(1));
        header.request_id = id;
        let deadline = Instant::now() + self.timeout;
        let mut request = self
            .client
            .loan_slice_uninit(payload.len())
            .map_err(transport("loan request"))?;
        *request.user_header_mut() = header;
        let request = request.write_from_slice(payload);
        let pending = request.send().map_err(transport("send request"))?;
        if pending.number_of_server_connections() == 0 {
            return Err(CheckError::NotServing {
                detail: "no server received the request".into(),
            });
        }
        self.notifier
            .notify()
            .map_err(transport("notify guardiand"))?;
        let spin_until = Instant::now() + self.spin;
        loop {
            while let Some(response) = pending.receive().map_err(transport("receive response"))? {
                let h = *response.user_header();
                if h.request_id != id {
                    tracing::warn!(
                        expected = id,
                        got = h.request_id,
                        "discarding response with a foreign id"
                    );
                    continue;
                }
                return Ok((h, response.payload().to_vec()));
            }
            if !pending.is_connected() {
                if let Some(response) = pending.receive().map_err(transport("receive response"))?
                    && response.user_header().request_id == id
                {
                    return Ok((*response.user_header(), response.payload().to_vec()));
                }
                return Err(CheckError::NotServing {
                    detail: "guardiand dropped the request without answering".into(),
                });
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(CheckError::Timeout {
                    after: self.timeout,
                });
            }
            if now < spin_until {
                // Poll, but let other runnable tasks (the daemon, on a shared core) go first.
                std::thread::yield_now();
                continue;
            }
            let wait = (deadline - now).min(Duration::from_millis(5));
            match self.listener.timed_wait(|_| {}, wait) {
                // A signal in the planner process: just look again.
                Ok(_) | Err(ListenerWaitError::InterruptSignal) => {}
                Err(e) => return Err(transport("wait for response")(e)),
            }
        }
    }

    fn single(op: Op, t: &Trajectory, class: Option<&str>) -> Result<RequestHeader, CheckError> {
        Ok(RequestHeader::encode(op, class, t.channels(), &[t.len()])?)
    }

    /// Is `trajectory` the task `claimed_class`? Invalid trajectories and unknown classes
    /// are answered with a `NoGo` verdict; transport problems and daemon errors are `Err`.
    pub fn check(
        &self,
        trajectory: &Trajectory,
        claimed_class: &str,
    ) -> Result<Verdict, CheckError> {
        let h = Self::single(Op::Check, trajectory, Some(claimed_class))?;
        let (r, entries) = self.call(h, trajectory.as_flat())?;
        verdict_of_response(&r, &entries, claimed_class)
    }

    /// The nearest enrolled classes to `trajectory`.
    pub fn identify(&self, trajectory: &Trajectory) -> Result<Ranking, CheckError> {
        let h = Self::single(Op::Identify, trajectory, None)?;
        let (r, entries) = self.call(h, trajectory.as_flat())?;
        ranking(&r, &entries)
    }

    /// Add `examples` (1..=[`MAX_EXAMPLES`]) to `class`, creating it if new. No retraining:
    /// the daemon embeds them, updates the prototype and persists the bank before answering.
    pub fn enroll(&self, class: &str, examples: &[Trajectory]) -> Result<ClassInfo, EnrollError> {
        let (h, payload) = enroll_request(class, examples)?;
        let (r, entries) = self.call(h, &payload)?;
        enrolled(&r, &entries)
    }

    /// Remove `class` from the bank.
    pub fn forget(&self, class: &str) -> Result<(), CheckError> {
        let h = RequestHeader::encode(Op::Forget, Some(class), 0, &[])?;
        let (r, _) = self.call(h, &[])?;
        status_ok(&r)
    }

    /// Every enrolled class, by name.
    pub fn classes(&self) -> Result<Vec<ClassInfo>, CheckError> {
        list_classes(|h| self.call(h, &[]))
    }

    /// Versions, counters and latency percentiles.
    pub fn status(&self) -> Result<DaemonStatus, CheckError> {
        let (r, entries) = self.call(RequestHeader::new(0, Op::Status), &[])?;
        daemon_status(&r, &entries)
    }
}

/// The ranking an identify response carries.
pub(crate) fn ranking(r: &ResponseHeader, entries: &[ClassEntry]) -> Result<Ranking, CheckError> {
    status_ok(r)?;
    let state = wire::decode_state(r);
    Ok(Ranking {
        nearest: wire::neighbours(entries),
        model_version: state.model_version.into_owned(),
        bank_version: state.bank_version,
    })
}

/// The status a status response carries (a fleet member's position in its entries).
pub(crate) fn daemon_status(
    r: &ResponseHeader,
    entries: &[ClassEntry],
) -> Result<DaemonStatus, CheckError> {
    status_ok(r)?;
    let s = wire::decode_state(r);
    let lat = s.latency_us;
    Ok(DaemonStatus {
        model_version: s.model_version.into_owned(),
        bank_version: s.bank_version,
        classes: s.class_count,
        uptime: Duration::from_millis(s.uptime_ms),
        requests: s.requests,
        errors: s.errors,
        go: s.go,
        no_go: s.no_go,
        latency_us: if lat.iter().any(|v| v.is_nan()) {
            None
        } else {
            Some(lat)
        },
        robot: RobotInfo {
            urdf_sha256: s.robot.urdf_sha256_hex(),
            name: s.robot.name.into_owned(),
            joints: s.robot.joints,
        },
        fleet: entries
            .iter()
            .filter_map(|e| {
                let name = wire::decode_text(&e.name);
                let signer = name.strip_prefix("fleet:")?.to_owned();
                Some(FleetPosition {
                    signer,
                    lamport: u64::from(e.examples) | (u64::from(e.calibrated) << 32),
                })
            })
            .collect(),
        bank_digest: entries.iter().find_map(|e| {
            wire::decode_text(&e.name)
                .strip_prefix("bank:")
                .map(str::to_owned)
        }),
    })
}

/// The header and payload of an enroll of `examples` into `class` (checked here as far as
/// the client can).
pub(crate) fn enroll_request(
    class: &str,
    examples: &[Trajectory],
) -> Result<(RequestHeader, Vec<f32>), EnrollError> {
    if examples.is_empty() {
        return Err(EnrollError::NoExamples);
    }
    if examples.len() > MAX_EXAMPLES {
        return Err(EnrollError::TooManyExamples {
            got: examples.len(),
            max: MAX_EXAMPLES,
        });
    }
    let channels = examples[0].channels();
    let lens: Vec<usize> = examples.iter().map(Trajectory::len).collect();
    let h = RequestHeader::encode(Op::Enroll, Some(class), channels, &lens)
        .map_err(CheckError::from)?;
    let mut payload = Vec::new();
    for (i, t) in examples.iter().enumerate() {
        if t.channels() != channels {
            return Err(CheckError::InvalidTrajectory {
                kind: InvalidKind::WrongChannelCount,
                index: u32::try_from(t.channels()).unwrap_or(u32::MAX),
                example: i as u32,
            }
            .into());
        }
        payload.extend_from_slice(t.as_flat());
    }
    Ok((h, payload))
}

/// The class an enroll answer reports.
pub(crate) fn enrolled(
    r: &ResponseHeader,
    entries: &[ClassEntry],
) -> Result<ClassInfo, EnrollError> {
    status_ok(r)?;
    entries
        .first()
        .map(class_info)
        .ok_or_else(|| CheckError::Protocol {
            detail: "enroll answered without the class".into(),
        })?
        .map_err(Into::into)
}

fn protocol(e: ProtocolError) -> CheckError {
    CheckError::Protocol {
        detail: e.to_string(),
    }
}

pub(crate) fn status_ok(r: &ResponseHeader) -> Result<(), CheckError> {
    let Some(failure) = wire::decode_failure(r).map_err(protocol)? else {
        return Ok(());
    };
    Err(match failure {
        Failure::BadRequest { message } => CheckError::BadRequest { message },
        Failure::InvalidTrajectory {
            invalid, example, ..
        } => CheckError::InvalidTrajectory {
            kind: invalid.kind,
            index: invalid.index,
            example,
        },
        // The response echoes the request's name field: decode it for the typed reason.
        Failure::InvalidClassName { message } => match wire::decode_class_name(&r.class_name) {
            Err(e) => CheckError::InvalidClassName(e),
            Ok(_) => CheckError::BadRequest { message },
        },
        Failure::UnknownClass { .. } => CheckError::UnknownClass {
            class: wire::decode_text(&r.class_name),
        },
        Failure::EmptyBank { .. } => CheckError::EmptyBank,
        Failure::Internal { message } => CheckError::Internal { message },
        Failure::LimitExceeded { limit, message } => CheckError::LimitExceeded { limit, message },
        Failure::NotPermitted { message } => CheckError::NotPermitted { message },
        Failure::Storage { message } => CheckError::Storage { message },
        Failure::Unreplicated { message } => CheckError::Unreplicated { message },
        // A status this client does not know yet.
        _ => CheckError::Protocol {
            detail: format!("unknown status {}", r.status),
        },
    })
}

/// The whole class list, read a page of at most [`wire::MAX_RESPONSE_ENTRIES`] at a time
/// with `call`. A bank that changes between pages (its version moves) is read again from
/// the start, at most [`LIST_ATTEMPTS`] times.
pub(crate) fn list_classes(
    mut call: impl FnMut(RequestHeader) -> Result<(ResponseHeader, Vec<ClassEntry>), CheckError>,
) -> Result<Vec<ClassInfo>, CheckError> {
    for _ in 0..LIST_ATTEMPTS {
        let mut classes = Vec::new();
        let mut version = None;
        let consistent = loop {
            let mut h = RequestHeader::new(0, Op::Classes);
            h.first = u32::try_from(classes.len()).map_err(|_| CheckError::Protocol {
                detail: "class list longer than 2^32".into(),
            })?;
            let (r, entries) = call(h)?;
            status_ok(&r)?;
            if *version.get_or_insert(r.bank_version) != r.bank_version {
                break false;
            }
            for e in &entries {
                classes.push(class_info(e)?);
            }
            let total = r.class_count as usize;
            if classes.len() >= total {
                break true;
            }
            if entries.is_empty() {
                return Err(CheckError::Protocol {
                    detail: format!(
                        "classes: an empty page at {} of {total} classes",
                        classes.len()
                    ),
                });
            }
        };
        if consistent {
            return Ok(classes);
        }
    }
    Err(CheckError::Protocol {
        detail: format!("classes: the bank changed while it was listed, {LIST_ATTEMPTS} times"),
    })
}

/// How often [`list_classes`] starts again when the bank changes under it.
const LIST_ATTEMPTS: usize = 8;

pub(crate) fn class_info(e: &ClassEntry) -> Result<ClassInfo, CheckError> {
    Ok(ClassInfo {
        name: wire::decode_class_name(&e.name)?.to_owned(),
        examples: e.examples,
        threshold: e.threshold,
        calibrated: e.calibrated != 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A transport failure keeps iceoryx2's error as a typed source, and a `CheckError`
    /// holding it is still `Clone` and `PartialEq`.
    #[test]
    fn transport_errors_keep_their_source() {
        let cause = iceoryx2::port::client::RequestSendError::ExceedsMaxActiveRequests;
        let e = transport("send request")(cause);
        let CheckError::Transport(t) = &e else {
            panic!("{e:?}");
        };
        assert_eq!(t.what(), "send request");
        let source = std::error::Error::source(&e).expect("a source");
        assert!(
            source.is::<iceoryx2::port::client::RequestSendError>(),
            "{source:?}"
        );
        assert_eq!(e.to_string(), format!("iceoryx2: send request: {source}"));
        assert_eq!(e.clone(), e);
        assert_ne!(transport("send request")(cause), e);
    }

    /// The class list is read a page at a time; a bank that changes between pages is read
    /// again from the start; one that never holds still, or a short page, is an error.
    #[test]
    fn the_class_list_is_read_page_by_page_and_again_when_the_bank_moves() {
        let bank: Vec<String> = (0..600).map(|i| format!("c{i:03}")).collect();
        // Answer a classes request from `bank` at `version`.
        let answer = |h: &RequestHeader, version: u64, bank: &[String], page: usize| {
            let mut r = ResponseHeader::answering(h);
            r.bank_version = version;
            r.class_count = bank.len() as u32;
            let entries = bank
                .iter()
                .skip(h.first as usize)
                .take(page)
                .map(|n| ClassEntry {
                    name: wire::encode_text(n),
                    distance: f32::NAN,
                    threshold: 1.0,
                    examples: 1,
                    calibrated: 0,
                })
                .collect();
            Ok((r, entries))
        };
        let names = |v: Vec<ClassInfo>| v.into_iter().map(|c| c.name).collect::<Vec<_>>();
        let mut firsts = Vec::new();
        let all = list_classes(|h| {
            firsts.push(h.first);
            answer(&h, 1, &bank, wire::MAX_RESPONSE_ENTRIES)
        })
        .expect("list");
        assert_eq!(names(all), bank);
        assert_eq!(firsts, [0, 256, 512]);

        // The bank changes after the first page: the list starts over and is consistent.
        let mut calls = 0;
        let all = list_classes(|h| {
            calls += 1;
            let version = if calls == 1 { 1 } else { 2 };
            answer(&h, version, &bank, wire::MAX_RESPONSE_ENTRIES)
        })
        .expect("list");
        assert_eq!((names(all), calls), (bank.clone(), 5));

        // A bank that changes on every page.
        let mut version = 0;
        let e = list_classes(|h| {
            version += 1;
            answer(&h, version, &bank, wire::MAX_RESPONSE_ENTRIES)
        })
        .expect_err("never consistent");
        assert!(matches!(e, CheckError::Protocol { .. }), "{e:?}");

        // A daemon that stops answering entries before the count is reached.
        let e = list_classes(|h| answer(&h, 1, &bank, if h.first == 0 { 256 } else { 0 }))
            .expect_err("short");
        assert!(matches!(e, CheckError::Protocol { .. }), "{e:?}");
    }
}
