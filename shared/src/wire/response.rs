//! A response's meaning, typed, and the one pair of functions per part of the header that
//! write it (the daemon) and read it (the client): the error status ([`Failure`]), the
//! check verdict ([`Verdict`]) and the daemon's state sent with every answer
//! ([`DaemonState`]).

use super::decode_code;
use std::borrow::Cow;

use super::{
    ClassEntry, LimitKind, MESSAGE_BYTES, NAME_BYTES, ReasonCode, RequestError, RequestHeader,
    ResponseHeader, Status, VerdictCode, decode_text, encode_text,
};
use crate::trajectory::{InvalidKind, InvalidTrajectory};
use crate::verdict::{Decision, Neighbour, NoGoReason, Verdict};

/// A response that breaks the protocol (a value no version of it defines).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProtocolError {
    /// `status` is not a [`Status`] value.
    #[error("unknown status {0}")]
    UnknownStatus(u32),
    /// `invalid_kind` is not an [`InvalidKind`] value.
    #[error("unknown invalid kind {0}")]
    UnknownInvalidKind(u32),
    /// `workcell_kind` is not a workcell rule.
    #[error("unknown workcell kind {0}")]
    UnknownWorkcellKind(u32),
    /// `limit_kind` is not a [`LimitKind`] value.
    #[error("unknown limit kind {0}")]
    UnknownLimitKind(u32),
    /// `geometry_feature` is not a [`crate::workcell::GeometryFeature`] value.
    #[error("unknown geometry feature {0}")]
    UnknownGeometryFeature(u32),
    /// A no-go with a `reason` that is not a [`ReasonCode`] no-go value.
    #[error("no-go with unknown reason {0}")]
    UnknownReason(u32),
    /// A check answered with status ok but neither go nor no-go.
    #[error("check answered without a verdict ({0})")]
    NoVerdict(u32),
    /// A wrong-task no-go without the nearest class (the response's first entry).
    #[error("wrong-task verdict without a nearest class")]
    WrongTaskWithoutNearest,
}

/// A request answered with an error status: the status, with the message the daemon wrote.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Failure {
    /// [`Status::BadRequest`].
    BadRequest {
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::InvalidTrajectory`].
    InvalidTrajectory {
        /// What is wrong and where.
        invalid: InvalidTrajectory,
        /// Which trajectory of the request.
        example: u32,
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::InvalidClassName`] (the response echoes the request's name field).
    InvalidClassName {
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::UnknownClass`] (the response echoes the request's name field).
    UnknownClass {
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::EmptyBank`].
    EmptyBank {
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::Internal`].
    Internal {
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::LimitExceeded`]: an enroll was refused before anything changed.
    LimitExceeded {
        /// Which limit, its value and what the enroll asked for.
        limit: Limit,
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::NotPermitted`]: the op is not allowed on this endpoint or for this caller.
    NotPermitted {
        /// The daemon's explanation.
        message: String,
    },
    /// [`Status::Storage`]: the change could not be persisted and was not applied.
    Storage {
        /// The daemon's explanation (the file and the system error).
        message: String,
    },
    /// [`Status::Unreplicated`]: the change is in effect here, fewer peers than required
    /// acknowledged it in time.
    Unreplicated {
        /// How many peers hold it, how many were required, within how long.
        message: String,
    },
}

/// A configured bank limit an enroll would have exceeded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Limit {
    /// Which limit.
    pub kind: LimitKind,
    /// Its configured value.
    pub max: u64,
    /// What the bank would have held after the enroll.
    pub requested: u64,
}

impl From<&RequestError> for Failure {
    fn from(e: &RequestError) -> Self {
        let message = e.to_string();
        match e {
            RequestError::InvalidTrajectory { example, source } => Self::InvalidTrajectory {
                invalid: *source,
                example: *example,
                message,
            },
            RequestError::InvalidClassName(_) => Self::InvalidClassName { message },
            _ => Self::BadRequest { message },
        }
    }
}

impl Failure {
    /// The status this failure is sent with.
    pub fn status(&self) -> Status {
        match self {
            Self::BadRequest { .. } => Status::BadRequest,
            Self::InvalidTrajectory { .. } => Status::InvalidTrajectory,
            Self::InvalidClassName { .. } => Status::InvalidClassName,
            Self::UnknownClass { .. } => Status::UnknownClass,
            Self::EmptyBank { .. } => Status::EmptyBank,
            Self::Internal { .. } => Status::Internal,
            Self::LimitExceeded { .. } => Status::LimitExceeded,
            Self::NotPermitted { .. } => Status::NotPermitted,
            Self::Storage { .. } => Status::Storage,
            Self::Unreplicated { .. } => Status::Unreplicated,
        }
    }

    /// The daemon's explanation.
    pub fn message(&self) -> &str {
        match self {
            Self::BadRequest { message }
            | Self::InvalidTrajectory { message, .. }
            | Self::InvalidClassName { message }
            | Self::UnknownClass { message }
            | Self::EmptyBank { message }
            | Self::Internal { message }
            | Self::LimitExceeded { message, .. }
            | Self::NotPermitted { message }
            | Self::Storage { message }
            | Self::Unreplicated { message } => message,
        }
    }
}

/// Write `failure` into `r`: status, message and, for an invalid trajectory, its kind,
/// index and example; no verdict.
pub fn encode_failure(r: &mut ResponseHeader, failure: &Failure) {
    r.status = failure.status() as u32;
    r.message = encode_text::<MESSAGE_BYTES>(failure.message());
    if let Failure::InvalidTrajectory {
        invalid, example, ..
    } = failure
    {
        r.invalid_kind = invalid.kind as u32;
        r.invalid_index = invalid.index;
        r.invalid_example = *example;
    }
    if let Failure::LimitExceeded { limit, .. } = failure {
        r.limit_kind = limit.kind as u32;
        r.limit_max = limit.max;
        r.limit_requested = limit.requested;
    }
    r.verdict = VerdictCode::None as u32;
}

/// Read `r`'s status: `Ok(None)` when the request succeeded, else the failure.
pub fn decode_failure(r: &ResponseHeader) -> Result<Option<Failure>, ProtocolError> {
    let message = decode_text(&r.message);
    Ok(Some(match decode_code::<Status>(r.status) {
        Some(Status::Ok) => return Ok(None),
        Some(Status::BadRequest) => Failure::BadRequest { message },
        Some(Status::InvalidTrajectory) => Failure::InvalidTrajectory {
            invalid: InvalidTrajectory {
                kind: invalid_kind(r)?,
                index: r.invalid_index,
            },
            example: r.invalid_example,
            message,
        },
        Some(Status::InvalidClassName) => Failure::InvalidClassName { message },
        Some(Status::UnknownClass) => Failure::UnknownClass { message },
        Some(Status::EmptyBank) => Failure::EmptyBank { message },
        Some(Status::Internal) => Failure::Internal { message },
        Some(Status::LimitExceeded) => Failure::LimitExceeded {
            limit: Limit {
                kind: decode_code::<LimitKind>(r.limit_kind)
                    .ok_or(ProtocolError::UnknownLimitKind(r.limit_kind))?,
                max: r.limit_max,
                requested: r.limit_requested,
            },
            message,
        },
        Some(Status::NotPermitted) => Failure::NotPermitted { message },
        Some(Status::Storage) => Failure::Storage { message },
        Some(Status::Unreplicated) => Failure::Unreplicated { message },
        None => return Err(ProtocolError::UnknownStatus(r.status)),
    }))
}

fn invalid_kind(r: &ResponseHeader) -> Result<InvalidKind, ProtocolError> {
    r.invalid()
        .ok_or(ProtocolError::UnknownInvalidKind(r.invalid_kind))
}

/// Write a check's verdict into `r` (status stays ok): its decision, reason and numbers.
/// The nearest classes travel as the response's entries (the daemon adds each class's
/// example count and calibration), the versions as the daemon's state
/// ([`encode_state`]). A workcell no-go also gets its human-readable message.
pub fn encode_check(r: &mut ResponseHeader, v: &Verdict) {
    let nan = |v: Option<f32>| v.unwrap_or(f32::NAN);
    let (verdict, reason) = match &v.decision {
        Decision::Go => (VerdictCode::Go, ReasonCode::None),
        Decision::NoGo { reason } => (
            VerdictCode::NoGo,
            match reason {
                NoGoReason::WrongTask { .. } => ReasonCode::WrongTask,
                NoGoReason::Outlier => ReasonCode::Outlier,
                NoGoReason::UnknownClass => ReasonCode::UnknownClass,
                NoGoReason::InvalidTrajectory { kind, index } => {
                    r.invalid_kind = *kind as u32;
                    r.invalid_index = *index;
                    ReasonCode::InvalidTrajectory
                }
                NoGoReason::Workcell { kind, index } => {
                    r.workcell_kind = *kind as u32;
                    r.workcell_index = *index;
                    r.message = encode_text(&format!(
                        "workcell rule broken: {kind:?} at waypoint {index}"
                    ));
                    ReasonCode::Workcell
                }
                NoGoReason::GeometryMismatch { .. } => ReasonCode::GeometryMismatch,
            },
        ),
    };
    r.geometry_score = nan(v.geometry_score);
    r.geometry_threshold = nan(v.geometry_threshold);
    r.geometry_feature = v.geometry_feature.map_or(0, |f| f as u32);
    r.verdict = verdict as u32;
    r.reason = reason as u32;
    r.claimed_distance = nan(v.claimed_distance);
    r.threshold = nan(v.threshold);
    r.margin = nan(v.margin);
    r.gap = nan(v.gap);
}

/// The nearest classes a response's entries carry.
pub fn neighbours(entries: &[ClassEntry]) -> Vec<Neighbour> {
    entries
        .iter()
        .map(|e| Neighbour {
            class: decode_text(&e.name),
            distance: e.distance,
            threshold: e.threshold,
        })
        .collect()
}

/// Read a check's verdict from `r` (whose status is ok) and its `entries`, for a check that
/// claimed `claimed_class`: the one conversion from the wire back to a [`Verdict`].
pub fn decode_check(
    r: &ResponseHeader,
    entries: &[ClassEntry],
    claimed_class: &str,
) -> Result<Verdict, ProtocolError> {
    let opt = |v: f32| if v.is_nan() { None } else { Some(v) };
    let nearest = neighbours(entries);
    let decision = match decode_code::<VerdictCode>(r.verdict) {
        Some(VerdictCode::Go) => Decision::Go,
        Some(VerdictCode::NoGo) => Decision::NoGo {
            reason: match decode_code::<ReasonCode>(r.reason) {
                Some(ReasonCode::WrongTask) => NoGoReason::WrongTask {
                    nearest: nearest
                        .first()
                        .map(|n| n.class.clone())
                        .ok_or(ProtocolError::WrongTaskWithoutNearest)?,
                },
                Some(ReasonCode::Outlier) => NoGoReason::Outlier,
                Some(ReasonCode::UnknownClass) => NoGoReason::UnknownClass,
                Some(ReasonCode::InvalidTrajectory) => NoGoReason::InvalidTrajectory {
                    kind: invalid_kind(r)?,
                    index: r.invalid_index,
                },
                Some(ReasonCode::Workcell) => NoGoReason::Workcell {
                    kind: r
                        .workcell()
                        .ok_or(ProtocolError::UnknownWorkcellKind(r.workcell_kind))?,
                    index: r.workcell_index,
                },
                Some(ReasonCode::GeometryMismatch) => NoGoReason::GeometryMismatch {
                    feature: r
                        .geometry()
                        .ok_or(ProtocolError::UnknownGeometryFeature(r.geometry_feature))?,
                    score: r.geometry_score,
                    threshold: r.geometry_threshold,
                },
                _ => return Err(ProtocolError::UnknownReason(r.reason)),
            },
        },
        _ => return Err(ProtocolError::NoVerdict(r.verdict)),
    };
    Ok(Verdict {
        decision,
        claimed_class: claimed_class.to_owned(),
        claimed_distance: opt(r.claimed_distance),
        threshold: opt(r.threshold),
        margin: opt(r.margin),
        gap: opt(r.gap),
        nearest,
        geometry_score: opt(r.geometry_score),
        geometry_threshold: opt(r.geometry_threshold),
        geometry_feature: r.geometry(),
        model_version: decode_text(&r.model_version),
        bank_version: r.bank_version,
    })
}

/// What every response says about the daemon that answered.
#[derive(Debug, Clone, PartialEq)]
pub struct DaemonState<'a> {
    /// Version of the embedding model.
    pub model_version: Cow<'a, str>,
    /// Generation of the class bank.
    pub bank_version: u64,
    /// Enrolled classes.
    pub class_count: u32,
    /// Milliseconds since the daemon started.
    pub uptime_ms: u64,
    /// Requests answered.
    pub requests: u64,
    /// Requests answered with an error status.
    pub errors: u64,
    /// Checks answered go.
    pub go: u64,
    /// Checks answered no-go.
    pub no_go: u64,
    /// Service-time p50, p90, p99 and max in microseconds (NaN before the first request).
    pub latency_us: [f32; 4],
    /// The served robot: name, joints and the SHA-256 of its URDF.
    pub robot: RobotInfo<'a>,
}

/// Which robot a daemon serves (every response carries it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RobotInfo<'a> {
    /// The robot's name (its description's `name`).
    pub name: Cow<'a, str>,
    /// Joints; a trajectory has `joints + 1` channels.
    pub joints: u32,
    /// SHA-256 of the robot's URDF file.
    pub urdf_sha256: [u8; 32],
}

impl RobotInfo<'_> {
    /// Floats per waypoint this robot's trajectories have.
    pub fn channels(&self) -> usize {
        self.joints as usize + 1
    }

    /// The URDF checksum as 64 lower-case hex digits.
    pub fn urdf_sha256_hex(&self) -> String {
        self.urdf_sha256
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }
}

/// Write the daemon's state into `r`.
pub fn encode_state(r: &mut ResponseHeader, s: &DaemonState<'_>) {
    r.bank_version = s.bank_version;
    r.class_count = s.class_count;
    r.model_version = encode_text::<NAME_BYTES>(&s.model_version);
    r.uptime_ms = s.uptime_ms;
    r.requests = s.requests;
    r.errors = s.errors;
    r.go = s.go;
    r.no_go = s.no_go;
    let [p50, p90, p99, max] = s.latency_us;
    r.latency_p50_us = p50;
    r.latency_p90_us = p90;
    r.latency_p99_us = p99;
    r.latency_max_us = max;
    r.robot_joints = s.robot.joints;
    r.robot_name = encode_text::<NAME_BYTES>(&s.robot.name);
    r.robot_urdf_sha256 = s.robot.urdf_sha256;
}

/// Read the daemon's state from `r`.
pub fn decode_state(r: &ResponseHeader) -> DaemonState<'static> {
    DaemonState {
        model_version: Cow::Owned(decode_text(&r.model_version)),
        bank_version: r.bank_version,
        class_count: r.class_count,
        uptime_ms: r.uptime_ms,
        requests: r.requests,
        errors: r.errors,
        go: r.go,
        no_go: r.no_go,
        latency_us: [
            r.latency_p50_us,
            r.latency_p90_us,
            r.latency_p99_us,
            r.latency_max_us,
        ],
        robot: RobotInfo {
            name: Cow::Owned(decode_text(&r.robot_name)),
            joints: r.robot_joints,
            urdf_sha256: r.robot_urdf_sha256,
        },
    }
}

impl ResponseHeader {
    /// A header answering `request`: its id, op and class name field echoed, status ok,
    /// everything else empty.
    pub fn answering(request: &RequestHeader) -> Self {
        let mut r = Self::new(request.request_id, request.op);
        r.class_name = request.class_name;
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::workcell::WorkcellKind;

    #[test]
    fn failures_and_answers_round_trip() {
        let failures = [
            Failure::BadRequest {
                message: "unknown op 9".into(),
            },
            Failure::InvalidTrajectory {
                invalid: InvalidTrajectory::new(InvalidKind::JointOutOfLimits, 5),
                example: 2,
                message: "x".into(),
            },
            Failure::Internal {
                message: "embedding failed".into(),
            },
            Failure::LimitExceeded {
                limit: Limit {
                    kind: LimitKind::BankBytes,
                    max: 1 << 26,
                    requested: (1 << 26) + 5,
                },
                message: "bank full".into(),
            },
            Failure::NotPermitted {
                message: "admin only".into(),
            },
        ];
        for f in failures {
            let mut r = ResponseHeader::default();
            encode_failure(&mut r, &f);
            assert_eq!(decode_failure(&r), Ok(Some(f)));
        }
        assert_eq!(decode_failure(&ResponseHeader::default()), Ok(None));
        let r = ResponseHeader {
            status: 99,
            ..ResponseHeader::default()
        };
        assert_eq!(decode_failure(&r), Err(ProtocolError::UnknownStatus(99)));

        let go = Verdict {
            decision: Decision::Go,
            claimed_distance: Some(0.2),
            threshold: Some(0.5),
            margin: Some(0.3),
            geometry_score: Some(1.0),
            geometry_threshold: Some(2.0),
            geometry_feature: Some(crate::workcell::GeometryFeature::CentreX),
            ..Verdict::early("c", NoGoReason::Outlier, "", 0)
        };
        let verdicts = [
            go,
            Verdict::early(
                "c",
                crate::workcell::WorkcellViolation {
                    kind: decode_code::<WorkcellKind>(1).unwrap(),
                    index: 4,
                },
                "",
                0,
            ),
            Verdict::early(
                "c",
                InvalidTrajectory::new(InvalidKind::NonFinite, 3),
                "",
                0,
            ),
        ];
        for v in verdicts {
            let mut r = ResponseHeader::default();
            encode_check(&mut r, &v);
            assert_eq!(decode_check(&r, &[], "c"), Ok(v));
        }
        // A wrong task names its nearest class in the first entry: none is an error.
        let mut r = ResponseHeader::default();
        let wrong = NoGoReason::WrongTask {
            nearest: "d".into(),
        };
        encode_check(&mut r, &Verdict::early("c", wrong, "", 0));
        assert_eq!(
            decode_check(&r, &[], "c"),
            Err(ProtocolError::WrongTaskWithoutNearest)
        );
        let r = ResponseHeader {
            verdict: VerdictCode::NoGo as u32,
            reason: ReasonCode::GeometryMismatch as u32,
            ..ResponseHeader::default()
        };
        assert_eq!(
            decode_check(&r, &[], "c"),
            Err(ProtocolError::UnknownGeometryFeature(0))
        );
        assert_eq!(
            decode_check(&ResponseHeader::default(), &[], "c"),
            Err(ProtocolError::NoVerdict(0))
        );
    }
}
