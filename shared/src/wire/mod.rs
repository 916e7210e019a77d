//! The iceoryx2 wire contract between `guardiand` and planners.
//!
//! One request-response service (default name [`DEFAULT_SERVICE_NAME`]) carries every
//! operation, plus two event services used only to wake the other side:
//!
//! - request: user header [`RequestHeader`], payload a slice of `f32` — the trajectories,
//!   row-major, `channels` floats per waypoint, the examples one after the other;
//! - response: user header [`ResponseHeader`], payload a slice of [`ClassEntry`] — the k
//!   nearest classes (check, identify), the class list (classes), the enrolled class (enroll).
//!
//! After sending a request a client notifies the `<service>/requests` event service; after
//! sending a response the daemon notifies the client's own event service
//! `<service>/responses/<client id>` ([`client_response_event_name`]), or `<service>/responses`
//! for a client that has none. The exact byte layout is in
//! `docs/wire-protocol.md`; changing any type here bumps [`PROTOCOL_VERSION`] and with it the
//! service name.
//!
//! The headers are decoded and encoded in one place each: a request becomes a typed
//! [`Request`] with [`Request::decode`] (the daemon) and its header is built by
//! [`RequestHeader::encode`] (the client); a response is written by [`encode_failure`],
//! [`encode_check`] and [`encode_state`] (the daemon) and read by their `decode_*`
//! counterparts (the client).

use iceoryx2::prelude::ZeroCopySend;

pub mod admin;
mod request;
mod response;
#[cfg(feature = "proptest")]
pub mod strategy;

pub use request::{Request, RequestError};
pub use response::{
    DaemonState, Failure, Limit, ProtocolError, RobotInfo, decode_check, decode_failure,
    decode_state, encode_check, encode_failure, encode_state, neighbours,
};

use crate::trajectory::{InvalidKind, MAX_JOINTS, MAX_WAYPOINTS};
use crate::workcell::{GeometryFeature, WorkcellKind};

/// Version of this wire contract; part of the service name.
pub const PROTOCOL_VERSION: u32 = 4;
/// Default name of the request-response service.
pub const DEFAULT_SERVICE_NAME: &str = "guardian/v4/rpc";
/// Where an installed daemon listens for administrative requests (enroll, forget) from
/// other users: its Unix socket in the runtime directory (`docs/wire-protocol.md` §8).
pub const DEFAULT_ADMIN_SOCKET: &str = "/run/guardian/admin.sock";
/// Size of every fixed name field (class names, model version), NUL-padded.
pub const NAME_BYTES: usize = 64;
/// Most entries in one response. A `classes` answer lists the bank a page at a time: the
/// classes from the request's `first` on, at most this many; `class_count` in the response
/// is the whole bank's. The daemon preallocates every response chunk at this size, so no
/// answer is ever larger (`docs/wire-protocol.md`).
pub const MAX_RESPONSE_ENTRIES: usize = 256;
/// Longest class name in bytes (UTF-8); one byte of [`NAME_BYTES`] stays NUL.
pub const MAX_CLASS_NAME: usize = NAME_BYTES - 1;
/// Most examples in one enroll request.
pub const MAX_EXAMPLES: usize = 16;
/// Size of the human-readable message in a response, NUL-padded.
pub const MESSAGE_BYTES: usize = 128;
/// Most floats per waypoint a robot can have: [`MAX_JOINTS`] joints and the tool.
pub const MAX_CHANNELS: usize = MAX_JOINTS + 1;
/// Largest request payload in `f32` values: [`MAX_EXAMPLES`] trajectories of
/// [`MAX_WAYPOINTS`] waypoints of [`MAX_CHANNELS`] channels (4.25 MiB); a daemon sizes its
/// port for its own robot's channels.
pub const MAX_REQUEST_FLOATS: usize = MAX_EXAMPLES * MAX_WAYPOINTS * MAX_CHANNELS;

/// Decode a wire code into its enum (`Op`, `Status`, `WorkcellKind`, ...; each derives
/// [`num_enum::TryFromPrimitive`]): `None` for a value the enum does not have, including one
/// too wide for its representation.
pub fn decode_code<T>(v: u32) -> Option<T>
where
    T: num_enum::TryFromPrimitive,
    T::Primitive: TryFrom<u32>,
{
    T::try_from_primitive(T::Primitive::try_from(v).ok()?).ok()
}

/// Name of the event service clients notify after sending a request.
pub fn request_event_name(service: &str) -> String {
    format!("{service}/requests")
}

/// Name of the event service the daemon notifies after sending a response to a client
/// that has no event service of its own ([`client_response_event_name`]).
pub fn response_event_name(service: &str) -> String {
    format!("{service}/responses")
}

/// Name of one client's own response event service: the client creates it (with its one
/// listener) before its first request, and the daemon notifies it after answering that
/// client's requests, so an answer wakes only the client it is for. `client_id` is the
/// value of the client port's iceoryx2 `UniqueClientId` (`Client::id().value()`), which
/// the daemon reads from every request (`ActiveRequest::origin().value()`); written as 32
/// lower-case hex digits.
pub fn client_response_event_name(service: &str, client_id: u128) -> String {
    format!("{service}/responses/{client_id:032x}")
}

/// Operation codes ([`RequestHeader::op`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, num_enum::TryFromPrimitive)]
#[repr(u32)]
#[non_exhaustive]
pub enum Op {
    /// Is this trajectory the class it claims to be?
    Check = 1,
    /// Which enrolled classes are nearest to this trajectory?
    Identify = 2,
    /// Add or extend a class from 1..=[`MAX_EXAMPLES`] trajectories.
    Enroll = 3,
    /// Remove a class.
    Forget = 4,
    /// List the enrolled classes.
    Classes = 5,
    /// Daemon status: versions, counters, latency percentiles.
    Status = 6,
}

/// Outcome of a request ([`ResponseHeader::status`]). A check answered with a verdict, `Go`
/// or `NoGo`, has status [`Status::Ok`]; every other status is an error and carries no
/// verdict.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, num_enum::TryFromPrimitive)]
#[repr(u32)]
#[non_exhaustive]
pub enum Status {
    /// The operation succeeded.
    Ok = 0,
    /// The request is malformed: unknown op, payload length disagrees with the header,
    /// example count out of range.
    BadRequest = 1,
    /// A trajectory failed validation (identify, enroll); see `invalid_*`.
    InvalidTrajectory = 2,
    /// The class name is empty, too long, not UTF-8 or has control characters.
    InvalidClassName = 3,
    /// The class is not enrolled (forget).
    UnknownClass = 4,
    /// The bank has no classes (identify).
    EmptyBank = 5,
    /// The daemon failed internally (embedding, persistence); see `message`.
    Internal = 6,
    /// An enroll would take the bank past one of the daemon's configured limits; see
    /// `limit_kind`, `limit_max`, `limit_requested`. Nothing changed.
    LimitExceeded = 7,
    /// The operation is not permitted on this endpoint (enroll and forget on the planners'
    /// service under admin separation, or a caller not in the admin list on the admin
    /// socket). Nothing changed.
    NotPermitted = 8,
    /// A change (enroll, forget) could not be persisted — the state directory's file
    /// system is full or read-only, or an I/O error — and was not applied: the bank, its
    /// journal and a fleet member's records are as before, and the daemon keeps serving
    /// the old bank. See `message`; retry once the cause is fixed.
    Storage = 9,
    /// A fleet member's enroll or forget is in effect and durable on this member, but
    /// fewer peers than its `[fleet] replicas` acknowledged holding it within
    /// `replica-timeout-ms` (`message` says how many): the others get it when they catch
    /// up, and it is lost if this member is lost before they do. Not an error of the
    /// change; retrying it makes a new record.
    Unreplicated = 10,
}

/// Verdict codes ([`ResponseHeader::verdict`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, num_enum::TryFromPrimitive)]
#[repr(u32)]
#[non_exhaustive]
pub enum VerdictCode {
    /// Not a check, or the check failed with an error status.
    None = 0,
    /// The trajectory is the task it claims to be.
    Go = 1,
    /// It is not; see [`ReasonCode`].
    NoGo = 2,
}

/// Why a check answered no-go ([`ResponseHeader::reason`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, num_enum::TryFromPrimitive)]
#[repr(u32)]
#[non_exhaustive]
pub enum ReasonCode {
    /// No reason (go, or not a check).
    None = 0,
    /// Another class is nearer than the claimed one (by more than the bank's wrong-task
    /// tolerance); it is `entries[0]`.
    WrongTask = 1,
    /// The claimed class is the nearest but farther than its threshold.
    Outlier = 2,
    /// The claimed class is not enrolled.
    UnknownClass = 3,
    /// The trajectory failed validation; see `invalid_kind`, `invalid_index`.
    InvalidTrajectory = 4,
    /// The plan breaks a workcell rule (tool orientation, pen height, canvas, hover
    /// height); see `workcell_kind`, `workcell_index`. Decided before any model runs.
    Workcell = 5,
    /// The embedding fits the claimed class, but the plan's geometry (position, size,
    /// strokes, direction) is farther from every enrolled example than the calibrated
    /// threshold; see `geometry_score`, `geometry_threshold`, `geometry_feature`.
    GeometryMismatch = 6,
}

/// Which configured bank limit refused an enroll ([`ResponseHeader::limit_kind`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, num_enum::TryFromPrimitive)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
#[non_exhaustive]
pub enum LimitKind {
    /// `max-classes`: classes in the bank.
    Classes = 1,
    /// `max-examples-per-class`: examples of one class.
    ExamplesPerClass = 2,
    /// `max-bank-bytes`: the bank's size in bytes (its snapshot form).
    BankBytes = 3,
}

impl LimitKind {
    /// The config key of the limit.
    pub fn key(self) -> &'static str {
        match self {
            Self::Classes => "max-classes",
            Self::ExamplesPerClass => "max-examples-per-class",
            Self::BankBytes => "max-bank-bytes",
        }
    }
}

/// The request user header. 152 bytes, alignment 8; see `docs/wire-protocol.md`.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("guardian_v4_RequestHeader")]
#[repr(C)]
pub struct RequestHeader {
    /// Chosen by the client, echoed in the response.
    pub request_id: u64,
    /// An [`Op`] value.
    pub op: u32,
    /// Floats per waypoint in the payload: the served robot's joints + 1 (the Panda: 8,
    /// the UR5e: 7); the `status` response says which robot is served.
    pub channels: u32,
    /// Number of trajectories in the payload: 1 for check and identify, 1..=16 for
    /// enroll, 0 otherwise.
    pub examples: u32,
    /// Classes: the index of the first class to list (the bank's name order); a response
    /// lists at most [`MAX_RESPONSE_ENTRIES`] classes. Zero for every other op.
    pub first: u32,
    /// Waypoints of each trajectory, in payload order; entries past `examples` are zero.
    pub waypoints: [u32; MAX_EXAMPLES],
    /// The class (check: claimed; enroll, forget: target), UTF-8, NUL-padded.
    pub class_name: [u8; NAME_BYTES],
}

impl Default for RequestHeader {
    fn default() -> Self {
        Self::new(0, Op::Status)
    }
}

impl RequestHeader {
    /// A header for `op` with everything else zero.
    pub fn new(request_id: u64, op: Op) -> Self {
        Self {
            request_id,
            op: op as u32,
            channels: 0,
            examples: 0,
            first: 0,
            waypoints: [0; MAX_EXAMPLES],
            class_name: [0; NAME_BYTES],
        }
    }
}

/// The response user header. 536 bytes, alignment 8; see `docs/wire-protocol.md`.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("guardian_v4_ResponseHeader")]
#[repr(C)]
pub struct ResponseHeader {
    /// The request's `request_id`.
    pub request_id: u64,
    /// Generation of the class bank that answered (increments on every enroll/forget).
    pub bank_version: u64,
    /// Milliseconds since the daemon started.
    pub uptime_ms: u64,
    /// Requests answered since start.
    pub requests: u64,
    /// Requests answered with an error status since start.
    pub errors: u64,
    /// Checks answered `Go` since start.
    pub go: u64,
    /// Checks answered `NoGo` since start.
    pub no_go: u64,
    /// The request's op.
    pub op: u32,
    /// A [`Status`] value.
    pub status: u32,
    /// A [`VerdictCode`] value (check only).
    pub verdict: u32,
    /// A [`ReasonCode`] value (check only).
    pub reason: u32,
    /// An [`InvalidKind`] value when a trajectory was invalid, else 0.
    pub invalid_kind: u32,
    /// Waypoint index (or offending count) of the invalid value.
    pub invalid_index: u32,
    /// Which example of an enroll request was invalid.
    pub invalid_example: u32,
    /// Number of enrolled classes.
    pub class_count: u32,
    /// Distance of the trajectory's embedding to the claimed class prototype (check), NaN
    /// when there is none.
    pub claimed_distance: f32,
    /// Threshold of the claimed class used by the decision (check), NaN when none.
    pub threshold: f32,
    /// `threshold - claimed_distance`: positive means inside the claimed class (check).
    pub margin: f32,
    /// Distance to the nearest *other* class minus `claimed_distance`: positive means the
    /// claimed class is the nearest (check); NaN with a single class.
    pub gap: f32,
    /// Median request service time in microseconds over the recent window (status).
    pub latency_p50_us: f32,
    /// 90th percentile service time, microseconds (status).
    pub latency_p90_us: f32,
    /// 99th percentile service time, microseconds (status).
    pub latency_p99_us: f32,
    /// Longest service time in the window, microseconds (status).
    pub latency_max_us: f32,
    /// Version of the embedding model, UTF-8, NUL-padded.
    pub model_version: [u8; NAME_BYTES],
    /// Human-readable detail for errors, UTF-8, NUL-padded.
    pub message: [u8; MESSAGE_BYTES],
    /// The class a request was about (check: claimed; enroll/forget: target).
    pub class_name: [u8; NAME_BYTES],
    /// A [`WorkcellKind`] value when a workcell rule was broken (reason `Workcell`), else 0.
    pub workcell_kind: u32,
    /// Index of the first waypoint that broke it.
    pub workcell_index: u32,
    /// Geometry score of the plan against the claimed class (check), NaN when the geometry
    /// check does not apply.
    pub geometry_score: f32,
    /// Geometry threshold (check), NaN when the check does not apply.
    pub geometry_threshold: f32,
    /// The [`GeometryFeature`] behind `geometry_score` (value 1..=13; 13 is the place), 0 when none.
    pub geometry_feature: u32,
    /// A [`LimitKind`] value when an enroll was refused with [`Status::LimitExceeded`],
    /// else 0.
    pub limit_kind: u32,
    /// The configured limit that was hit (status `LimitExceeded`).
    pub limit_max: u64,
    /// What the bank would have held after the enroll (status `LimitExceeded`).
    pub limit_requested: u64,
    /// Joints of the served robot (every response); a request's `channels` must be this + 1.
    pub robot_joints: u32,
    /// Name of the served robot (every response), UTF-8, NUL-padded.
    pub robot_name: [u8; NAME_BYTES],
    /// SHA-256 of the served robot's URDF file (every response).
    pub robot_urdf_sha256: [u8; 32],
    /// Reserved, zero.
    pub reserved: [u8; 20],
}

impl Default for ResponseHeader {
    fn default() -> Self {
        Self::new(0, 0)
    }
}

impl ResponseHeader {
    /// An all-zero header answering `request_id`.
    pub fn new(request_id: u64, op: u32) -> Self {
        Self {
            request_id,
            bank_version: 0,
            uptime_ms: 0,
            requests: 0,
            errors: 0,
            go: 0,
            no_go: 0,
            op,
            status: Status::Ok as u32,
            verdict: VerdictCode::None as u32,
            reason: ReasonCode::None as u32,
            invalid_kind: 0,
            invalid_index: 0,
            invalid_example: 0,
            class_count: 0,
            claimed_distance: f32::NAN,
            threshold: f32::NAN,
            margin: f32::NAN,
            gap: f32::NAN,
            latency_p50_us: f32::NAN,
            latency_p90_us: f32::NAN,
            latency_p99_us: f32::NAN,
            latency_max_us: f32::NAN,
            model_version: [0; NAME_BYTES],
            message: [0; MESSAGE_BYTES],
            class_name: [0; NAME_BYTES],
            workcell_kind: 0,
            workcell_index: 0,
            geometry_score: f32::NAN,
            geometry_threshold: f32::NAN,
            geometry_feature: 0,
            limit_kind: 0,
            limit_max: 0,
            limit_requested: 0,
            robot_joints: 0,
            robot_name: [0; NAME_BYTES],
            robot_urdf_sha256: [0; 32],
            reserved: [0; 20],
        }
    }

    /// The workcell rule broken, if any.
    pub fn workcell(&self) -> Option<WorkcellKind> {
        decode_code::<WorkcellKind>(self.workcell_kind)
    }

    /// The geometry feature behind `geometry_score`, if any.
    pub fn geometry(&self) -> Option<GeometryFeature> {
        decode_code::<GeometryFeature>(self.geometry_feature)
    }

    /// The invalid-trajectory kind, if any.
    pub fn invalid(&self) -> Option<InvalidKind> {
        decode_code(self.invalid_kind)
    }
}

/// One class in a response payload. 80 bytes, alignment 4.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("guardian_v4_ClassEntry")]
#[repr(C)]
pub struct ClassEntry {
    /// Class name, UTF-8, NUL-padded.
    pub name: [u8; NAME_BYTES],
    /// Distance from the request's embedding to the class prototype; NaN in class lists.
    pub distance: f32,
    /// The class's decision threshold.
    pub threshold: f32,
    /// Number of enrolled examples.
    pub examples: u32,
    /// 1 if the threshold is calibrated for this class, 0 if it is the global default.
    pub calibrated: u32,
}

/// A class name was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ClassNameError {
    /// The name is empty.
    #[error("class name is empty")]
    Empty,
    /// The name is longer than [`MAX_CLASS_NAME`] bytes.
    #[error("class name is {len} bytes, at most {max} allowed")]
    TooLong {
        /// Its length in bytes.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// The bytes are not UTF-8.
    #[error("class name is not valid UTF-8")]
    NotUtf8,
    /// The name holds a control character (including NUL inside the name).
    #[error("class name has a control character at byte {index}")]
    ControlCharacter {
        /// Byte offset of the character.
        index: usize,
    },
}

/// Check a class name: 1..=[`MAX_CLASS_NAME`] bytes of UTF-8 without control characters.
pub fn validate_class_name(name: &str) -> Result<(), ClassNameError> {
    if name.is_empty() {
        return Err(ClassNameError::Empty);
    }
    if name.len() > MAX_CLASS_NAME {
        return Err(ClassNameError::TooLong {
            len: name.len(),
            max: MAX_CLASS_NAME,
        });
    }
    if let Some((index, _)) = name.char_indices().find(|(_, c)| c.is_control()) {
        return Err(ClassNameError::ControlCharacter { index });
    }
    Ok(())
}

/// Validate `name` and write it NUL-padded into a name field.
pub fn encode_class_name(name: &str) -> Result<[u8; NAME_BYTES], ClassNameError> {
    validate_class_name(name)?;
    let mut out = [0u8; NAME_BYTES];
    out[..name.len()].copy_from_slice(name.as_bytes());
    Ok(out)
}

/// Read a class name from a NUL-padded field and validate it. Bytes after the first NUL
/// must be NUL too.
pub fn decode_class_name(field: &[u8; NAME_BYTES]) -> Result<&str, ClassNameError> {
    let len = field.iter().position(|&b| b == 0).unwrap_or(NAME_BYTES);
    if let Some(i) = field[len..].iter().position(|&b| b != 0) {
        return Err(ClassNameError::ControlCharacter { index: len + i });
    }
    if len > MAX_CLASS_NAME {
        return Err(ClassNameError::TooLong {
            len,
            max: MAX_CLASS_NAME,
        });
    }
    let name = core::str::from_utf8(&field[..len]).map_err(|_| ClassNameError::NotUtf8)?;
    validate_class_name(name)?;
    Ok(name)
}

/// Write free text NUL-padded into a fixed field, cut at a character boundary so that at
/// least one NUL remains.
pub fn encode_text<const N: usize>(text: &str) -> [u8; N] {
    let mut out = [0u8; N];
    let mut end = text.len().min(N.saturating_sub(1));
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    out[..end].copy_from_slice(&text.as_bytes()[..end]);
    out
}

/// Read free text from a NUL-padded field (lossy on invalid UTF-8).
pub fn decode_text(field: &[u8]) -> String {
    let len = field.iter().position(|&b| b == 0).unwrap_or(field.len());
    String::from_utf8_lossy(&field[..len]).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::mem::{align_of, offset_of, size_of};

    #[test]
    fn layout_matches_the_documented_offsets() {
        assert_eq!(size_of::<RequestHeader>(), 152);
        assert_eq!(align_of::<RequestHeader>(), 8);
        assert_eq!(offset_of!(RequestHeader, request_id), 0);
        assert_eq!(offset_of!(RequestHeader, op), 8);
        assert_eq!(offset_of!(RequestHeader, channels), 12);
        assert_eq!(offset_of!(RequestHeader, examples), 16);
        assert_eq!(offset_of!(RequestHeader, first), 20);
        assert_eq!(offset_of!(RequestHeader, waypoints), 24);
        assert_eq!(offset_of!(RequestHeader, class_name), 88);

        assert_eq!(size_of::<ResponseHeader>(), 536);
        assert_eq!(align_of::<ResponseHeader>(), 8);
        assert_eq!(offset_of!(ResponseHeader, request_id), 0);
        assert_eq!(offset_of!(ResponseHeader, bank_version), 8);
        assert_eq!(offset_of!(ResponseHeader, uptime_ms), 16);
        assert_eq!(offset_of!(ResponseHeader, requests), 24);
        assert_eq!(offset_of!(ResponseHeader, errors), 32);
        assert_eq!(offset_of!(ResponseHeader, go), 40);
        assert_eq!(offset_of!(ResponseHeader, no_go), 48);
        assert_eq!(offset_of!(ResponseHeader, op), 56);
        assert_eq!(offset_of!(ResponseHeader, status), 60);
        assert_eq!(offset_of!(ResponseHeader, verdict), 64);
        assert_eq!(offset_of!(ResponseHeader, reason), 68);
        assert_eq!(offset_of!(ResponseHeader, invalid_kind), 72);
        assert_eq!(offset_of!(ResponseHeader, invalid_index), 76);
        assert_eq!(offset_of!(ResponseHeader, invalid_example), 80);
        assert_eq!(offset_of!(ResponseHeader, class_count), 84);
        assert_eq!(offset_of!(ResponseHeader, claimed_distance), 88);
        assert_eq!(offset_of!(ResponseHeader, threshold), 92);
        assert_eq!(offset_of!(ResponseHeader, margin), 96);
        assert_eq!(offset_of!(ResponseHeader, gap), 100);
        assert_eq!(offset_of!(ResponseHeader, latency_p50_us), 104);
        assert_eq!(offset_of!(ResponseHeader, latency_p90_us), 108);
        assert_eq!(offset_of!(ResponseHeader, latency_p99_us), 112);
        assert_eq!(offset_of!(ResponseHeader, latency_max_us), 116);
        assert_eq!(offset_of!(ResponseHeader, model_version), 120);
        assert_eq!(offset_of!(ResponseHeader, message), 184);
        assert_eq!(offset_of!(ResponseHeader, class_name), 312);
        assert_eq!(offset_of!(ResponseHeader, workcell_kind), 376);
        assert_eq!(offset_of!(ResponseHeader, workcell_index), 380);
        assert_eq!(offset_of!(ResponseHeader, geometry_score), 384);
        assert_eq!(offset_of!(ResponseHeader, geometry_threshold), 388);
        assert_eq!(offset_of!(ResponseHeader, geometry_feature), 392);
        assert_eq!(offset_of!(ResponseHeader, limit_kind), 396);
        assert_eq!(offset_of!(ResponseHeader, limit_max), 400);
        assert_eq!(offset_of!(ResponseHeader, limit_requested), 408);
        assert_eq!(offset_of!(ResponseHeader, robot_joints), 416);
        assert_eq!(offset_of!(ResponseHeader, robot_name), 420);
        assert_eq!(offset_of!(ResponseHeader, robot_urdf_sha256), 484);
        assert_eq!(offset_of!(ResponseHeader, reserved), 516);

        assert_eq!(size_of::<ClassEntry>(), 80);
        assert_eq!(align_of::<ClassEntry>(), 4);
        assert_eq!(offset_of!(ClassEntry, distance), 64);
        assert_eq!(offset_of!(ClassEntry, threshold), 68);
        assert_eq!(offset_of!(ClassEntry, examples), 72);
        assert_eq!(offset_of!(ClassEntry, calibrated), 76);
    }

    #[test]
    fn class_names_are_bounded_utf8_without_controls() {
        let f = encode_class_name("character01").unwrap();
        assert_eq!(decode_class_name(&f), Ok("character01"));
        let max = "é".repeat(31) + "x"; // 63 bytes
        assert_eq!(
            decode_class_name(&encode_class_name(&max).unwrap()),
            Ok(&*max)
        );
        assert_eq!(encode_class_name(""), Err(ClassNameError::Empty));
        assert_eq!(
            encode_class_name(&"x".repeat(64)),
            Err(ClassNameError::TooLong { len: 64, max: 63 })
        );
        assert_eq!(
            encode_class_name("a\nb"),
            Err(ClassNameError::ControlCharacter { index: 1 })
        );
        let mut bad = [0u8; NAME_BYTES];
        bad[0] = 0xff;
        assert_eq!(decode_class_name(&bad), Err(ClassNameError::NotUtf8));
        let mut gap = encode_class_name("ab").unwrap();
        gap[5] = b'x';
        assert!(decode_class_name(&gap).is_err());
        assert!(decode_class_name(&[b'x'; NAME_BYTES]).is_err());
        assert_eq!(
            decode_class_name(&[0; NAME_BYTES]),
            Err(ClassNameError::Empty)
        );
    }

    #[test]
    fn codes_round_trip_and_text_is_cut_on_char_boundaries() {
        for v in 1..=6 {
            assert_eq!(decode_code::<Op>(v).map(|o| o as u32), Some(v));
        }
        assert_eq!(decode_code::<Op>(7), None);
        for v in 0..=10 {
            assert_eq!(decode_code::<Status>(v).map(|s| s as u32), Some(v));
        }
        assert_eq!(decode_code::<Status>(11), None);
        for v in 1..=3 {
            assert_eq!(decode_code::<LimitKind>(v).map(|s| s as u32), Some(v));
        }
        assert_eq!(decode_code::<LimitKind>(0), None);
        for v in 0..=6 {
            assert_eq!(decode_code::<ReasonCode>(v).map(|s| s as u32), Some(v));
        }
        let t: [u8; 4] = encode_text("aéé");
        assert_eq!(decode_text(&t), "aé");
        assert_eq!(request_event_name("g/v1/rpc"), "g/v1/rpc/requests");
        assert_eq!(
            client_response_event_name("g/v1/rpc", 0xab),
            "g/v1/rpc/responses/000000000000000000000000000000ab"
        );
    }
}
