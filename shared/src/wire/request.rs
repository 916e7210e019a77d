//! A request decoded once: the header and payload a planner sent become one typed value per
//! operation ([`Request`]), or the typed reason the request cannot be answered
//! ([`RequestError`]). The daemon decodes with [`Request::decode`]; the client builds
//! headers with [`RequestHeader::encode`].

use super::decode_code;
use super::{
    ClassNameError, MAX_EXAMPLES, Op, RequestHeader, Status, decode_class_name, encode_class_name,
};
use crate::trajectory::{InvalidKind, InvalidTrajectory, Waypoint, split_flat};

/// One decoded request. Names are borrowed from the header; each trajectory is copied once
/// from the payload (`joints + 1` floats per waypoint) into [`Waypoint`]s.
#[derive(Debug, Clone, PartialEq)]
pub enum Request<'a> {
    /// Is `trajectory` the class `claimed`? The trajectory's shape (waypoint count zero,
    /// channel count) is checked here and a shape problem is carried, not raised: a check
    /// answers it with a no-go. Its values are not validated here; the check pipeline
    /// validates before anything else.
    Check {
        /// The claimed class.
        claimed: &'a str,
        /// The trajectory, or why its shape is invalid.
        trajectory: Result<Vec<Waypoint>, InvalidTrajectory>,
    },
    /// Which classes are nearest to `trajectory` (validated)?
    Identify {
        /// The trajectory.
        trajectory: Vec<Waypoint>,
    },
    /// Add `examples` (validated, 1..=[`MAX_EXAMPLES`]) to `class`.
    Enroll {
        /// The target class.
        class: &'a str,
        /// The examples, in payload order.
        examples: Vec<Vec<Waypoint>>,
    },
    /// Remove `class`.
    Forget {
        /// The target class.
        class: &'a str,
    },
    /// List the enrolled classes, a page of at most
    /// [`MAX_RESPONSE_ENTRIES`](super::MAX_RESPONSE_ENTRIES) from the `first`-th on.
    Classes {
        /// Index of the first class to list.
        first: usize,
    },
    /// Versions, counters and latency percentiles.
    Status,
}

/// A request that cannot be answered as sent.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum RequestError {
    /// The op is not an [`Op`] value.
    #[error("unknown op {op}")]
    UnknownOp {
        /// The value sent.
        op: u32,
    },
    /// The example count is out of range for the op.
    #[error("examples is {got}, expected 1..={max}")]
    ExampleCount {
        /// The count sent.
        got: usize,
        /// The op's maximum.
        max: usize,
    },
    /// The payload length disagrees with the header's waypoint counts and channels.
    #[error("payload has {got} floats, header announces {}", announced_text(.announced))]
    PayloadLength {
        /// Floats in the payload.
        got: usize,
        /// Floats the header announces (`None`: more than 2^64).
        announced: Option<u64>,
    },
    /// The class name field is not a valid class name.
    #[error(transparent)]
    InvalidClassName(#[from] ClassNameError),
    /// A trajectory failed validation (identify, enroll).
    #[error("{source}")]
    InvalidTrajectory {
        /// Which trajectory of the request.
        example: u32,
        /// What is wrong.
        source: InvalidTrajectory,
    },
}

fn announced_text(announced: &Option<u64>) -> String {
    match announced {
        Some(total) => total.to_string(),
        None => "more than 2^64".to_owned(),
    }
}

impl RequestError {
    /// The response status that reports this error.
    pub fn status(&self) -> Status {
        match self {
            Self::UnknownOp { .. } | Self::ExampleCount { .. } | Self::PayloadLength { .. } => {
                Status::BadRequest
            }
            Self::InvalidClassName(_) => Status::InvalidClassName,
            Self::InvalidTrajectory { .. } => Status::InvalidTrajectory,
        }
    }
}

/// A trajectory split from the payload, or the first invalid one (its example index and
/// what is wrong).
type Split = Result<Vec<Vec<Waypoint>>, (u32, InvalidTrajectory)>;

impl<'a> Request<'a> {
    /// Decode `header` and `payload`. Errors come in the order a client can act on them:
    /// the op, then the class name (check, enroll, forget), then the example count and
    /// payload length, then each trajectory's shape in order. Trajectories must have the
    /// served robot's channel count (`joints + 1`); their values are validated once, by the
    /// check pipeline that resamples them (`guardian_screen::check`), for every op.
    pub fn decode(
        header: &'a RequestHeader,
        payload: &[f32],
        joints: usize,
    ) -> Result<Self, RequestError> {
        let Some(op) = decode_code::<Op>(header.op) else {
            return Err(RequestError::UnknownOp { op: header.op });
        };
        let class = || decode_class_name(&header.class_name);
        Ok(match op {
            Op::Check => {
                let claimed = class()?;
                let trajectory = match split(header, payload, joints, 1)? {
                    Ok(mut t) => Ok(t.pop().unwrap_or_default()),
                    Err((_, inv)) => Err(inv),
                };
                Self::Check {
                    claimed,
                    trajectory,
                }
            }
            Op::Identify => {
                let mut t = split(header, payload, joints, 1)?.map_err(invalid)?;
                Self::Identify {
                    trajectory: t.pop().unwrap_or_default(),
                }
            }
            Op::Enroll => {
                let class = class()?;
                let examples = split(header, payload, joints, MAX_EXAMPLES)?.map_err(invalid)?;
                Self::Enroll { class, examples }
            }
            Op::Forget => Self::Forget { class: class()? },
            Op::Classes => Self::Classes {
                first: header.first as usize,
            },
            Op::Status => Self::Status,
        })
    }

    /// The op of this request.
    pub fn op(&self) -> Op {
        match self {
            Self::Check { .. } => Op::Check,
            Self::Identify { .. } => Op::Identify,
            Self::Enroll { .. } => Op::Enroll,
            Self::Forget { .. } => Op::Forget,
            Self::Classes { .. } => Op::Classes,
            Self::Status => Op::Status,
        }
    }
}

fn invalid((example, source): (u32, InvalidTrajectory)) -> RequestError {
    RequestError::InvalidTrajectory { example, source }
}

/// Split the payload into the header's trajectories, checking their shape only (the caller
/// validates the values before using them).
fn split(
    h: &RequestHeader,
    payload: &[f32],
    joints: usize,
    max_examples: usize,
) -> Result<Split, RequestError> {
    let n = h.examples as usize;
    if n == 0 || n > max_examples {
        return Err(RequestError::ExampleCount {
            got: n,
            max: max_examples,
        });
    }
    // Checked: 16 counts of up to 2^32 - 1 waypoints of up to 2^32 - 1 channels overflow
    // u64, and a wrapped total could match the payload and index past it.
    let channels = u64::from(h.channels);
    let total = h.waypoints[..n].iter().try_fold(0u64, |acc, &w| {
        u64::from(w)
            .checked_mul(channels)
            .and_then(|floats| acc.checked_add(floats))
    });
    if total != Some(payload.len() as u64) {
        return Err(RequestError::PayloadLength {
            got: payload.len(),
            announced: total,
        });
    }
    let mut out = Vec::with_capacity(n);
    let mut at = 0usize;
    for (i, &w) in h.waypoints[..n].iter().enumerate() {
        let len = w as usize * h.channels as usize;
        let slice = &payload[at..at + len];
        at += len;
        // An empty trajectory with a wrong channel count is reported as too few
        // waypoints, like any other empty one.
        let parsed = if w == 0 {
            Err(InvalidTrajectory::new(InvalidKind::TooFewWaypoints, 0))
        } else {
            // `len` is a multiple of `channels`, so only the channel count can be wrong.
            split_flat(slice, h.channels as usize, joints)
        };
        match parsed {
            Ok(t) => out.push(t),
            Err(e) => return Ok(Err((i as u32, e))),
        }
    }
    Ok(Ok(out))
}

impl RequestHeader {
    /// A header for `op` about `class` (check: claimed; enroll, forget: target) carrying
    /// trajectories of `channels` floats per waypoint with the given waypoint counts, in
    /// payload order (at most [`MAX_EXAMPLES`]; counts saturate at `u32::MAX`). The request
    /// id is left zero for the sender to set.
    pub fn encode(
        op: Op,
        class: Option<&str>,
        channels: usize,
        waypoints: &[usize],
    ) -> Result<Self, ClassNameError> {
        let mut h = Self::new(0, op);
        if let Some(c) = class {
            h.class_name = encode_class_name(c)?;
        }
        if !waypoints.is_empty() {
            h.channels = u32::try_from(channels).unwrap_or(u32::MAX);
            h.examples = waypoints.len().min(MAX_EXAMPLES) as u32;
            for (slot, &w) in h.waypoints.iter_mut().zip(waypoints) {
                *slot = u32::try_from(w).unwrap_or(u32::MAX);
            }
        }
        Ok(h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CHANNELS: usize = 8;

    fn header(op: Op, class: &str, waypoints: &[usize]) -> RequestHeader {
        RequestHeader::encode(op, Some(class), CHANNELS, waypoints).unwrap()
    }

    /// Seven joints: the shapes matter here, not the values.
    const JOINTS: usize = 7;

    #[test]
    fn requests_decode_into_their_operation() {
        let t = vec![0.0f32; 3 * CHANNELS];
        let h = header(Op::Check, "c1", &[3]);
        match Request::decode(&h, &t, JOINTS).unwrap() {
            Request::Check {
                claimed,
                trajectory,
            } => {
                assert_eq!(claimed, "c1");
                assert_eq!(trajectory.unwrap().len(), 3);
            }
            other => panic!("{other:?}"),
        }
        let h = header(Op::Forget, "c1", &[]);
        assert_eq!(
            Request::decode(&h, &[], JOINTS),
            Ok(Request::Forget { class: "c1" })
        );
        let h = RequestHeader::new(0, Op::Status);
        assert_eq!(
            Request::decode(&h, &[], JOINTS).map(|r| r.op()),
            Ok(Op::Status)
        );
    }

    #[test]
    fn malformed_requests_are_typed_errors_with_the_documented_text() {
        let mut h = RequestHeader::new(0, Op::Status);
        h.op = 9;
        let e = Request::decode(&h, &[], JOINTS).unwrap_err();
        assert_eq!(e, RequestError::UnknownOp { op: 9 });
        assert_eq!(e.to_string(), "unknown op 9");
        assert_eq!(e.status(), Status::BadRequest);

        let h = header(Op::Check, "c1", &[3]);
        let e = Request::decode(&h, &[0.0; 5], JOINTS).unwrap_err();
        assert_eq!(e.to_string(), "payload has 5 floats, header announces 24");
        let mut h = header(Op::Enroll, "c1", &[1; 16]);
        h.channels = u32::MAX;
        h.waypoints = [u32::MAX; MAX_EXAMPLES];
        let e = Request::decode(&h, &[], JOINTS).unwrap_err();
        assert_eq!(
            e.to_string(),
            "payload has 0 floats, header announces more than 2^64"
        );
        let h = header(Op::Identify, "c1", &[3, 3]);
        let e = Request::decode(&h, &[0.0; 48], JOINTS).unwrap_err();
        assert_eq!(e.to_string(), "examples is 2, expected 1..=1");

        // A check carries a shape problem instead of failing; identify fails with it.
        let mut h = header(Op::Check, "c1", &[3]);
        h.channels = 7;
        let Ok(Request::Check { trajectory, .. }) = Request::decode(&h, &[0.0; 21], JOINTS) else {
            panic!("a check with a wrong channel count decodes");
        };
        assert_eq!(
            trajectory,
            Err(InvalidTrajectory::new(InvalidKind::WrongChannelCount, 7))
        );
        let mut h = header(Op::Identify, "c1", &[0]);
        h.channels = 7;
        let e = Request::decode(&h, &[], JOINTS).unwrap_err();
        assert_eq!(
            e,
            RequestError::InvalidTrajectory {
                example: 0,
                source: InvalidTrajectory::new(InvalidKind::TooFewWaypoints, 0)
            }
        );
        assert_eq!(e.status(), Status::InvalidTrajectory);

        let mut h = header(Op::Enroll, "c1", &[3]);
        h.class_name = [0; super::super::NAME_BYTES];
        let e = Request::decode(&h, &[0.0; 24], JOINTS).unwrap_err();
        assert_eq!(e, RequestError::InvalidClassName(ClassNameError::Empty));
        assert_eq!(e.status(), Status::InvalidClassName);
    }
}
