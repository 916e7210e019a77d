//! The admin socket's framing: the same [`RequestHeader`] + `f32` payload and
//! [`ResponseHeader`] + [`ClassEntry`] entries as on iceoryx2, written as little-endian bytes
//! with a length prefix, so that a Unix stream socket carries them (iceoryx2's shared memory
//! needs no framing; a byte stream does). Byte layout: `docs/wire-protocol.md` §8.
//!
//! One frame is `u32 length` (bytes that follow) + the header's fields in declaration order
//! at their documented offsets + the payload. A request frame is at most
//! [`MAX_ADMIN_REQUEST_BYTES`] long.

use super::{
    ClassEntry, MAX_REQUEST_FLOATS, MESSAGE_BYTES, NAME_BYTES, RequestHeader, ResponseHeader,
};

/// Size of an encoded [`RequestHeader`].
pub const REQUEST_HEADER_BYTES: usize = 152;
/// Size of an encoded [`ResponseHeader`].
pub const RESPONSE_HEADER_BYTES: usize = 536;
/// Size of an encoded [`ClassEntry`].
pub const CLASS_ENTRY_BYTES: usize = 80;
/// Longest request frame body: header + the largest legal payload (4.25 MiB + 152 bytes).
pub const MAX_ADMIN_REQUEST_BYTES: usize = REQUEST_HEADER_BYTES + MAX_REQUEST_FLOATS * 4;

/// A frame that is not a valid admin frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// The length prefix is out of range for this frame type.
    #[error("frame of {got} bytes; expected {min}..={max} bytes with whole elements")]
    Length {
        /// Length announced.
        got: usize,
        /// Shortest legal frame.
        min: usize,
        /// Longest legal frame.
        max: usize,
    },
}

struct Out(Vec<u8>);

impl Out {
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn bytes(&mut self, v: &[u8]) {
        self.0.extend_from_slice(v);
    }
}

/// Reads fixed-size fields from a buffer whose length was checked beforehand.
struct In<'a>(&'a [u8]);

impl In<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        let n = N.min(self.0.len());
        out[..n].copy_from_slice(&self.0[..n]);
        self.0 = &self.0[n..];
        out
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.take())
    }
}

/// Check a frame length announced by a peer before reading the frame.
pub fn check_request_len(len: usize) -> Result<(), FrameError> {
    if (REQUEST_HEADER_BYTES..=MAX_ADMIN_REQUEST_BYTES).contains(&len)
        && (len - REQUEST_HEADER_BYTES).is_multiple_of(4)
    {
        Ok(())
    } else {
        Err(FrameError::Length {
            got: len,
            min: REQUEST_HEADER_BYTES,
            max: MAX_ADMIN_REQUEST_BYTES,
        })
    }
}

/// Check a response frame length (entries are bounded by what a daemon can list).
pub fn check_response_len(len: usize, max_entries: usize) -> Result<(), FrameError> {
    let max = RESPONSE_HEADER_BYTES + max_entries * CLASS_ENTRY_BYTES;
    if (RESPONSE_HEADER_BYTES..=max).contains(&len)
        && (len - RESPONSE_HEADER_BYTES).is_multiple_of(CLASS_ENTRY_BYTES)
    {
        Ok(())
    } else {
        Err(FrameError::Length {
            got: len,
            min: RESPONSE_HEADER_BYTES,
            max,
        })
    }
}

/// A request frame: length prefix, header, payload.
pub fn encode_request(h: &RequestHeader, payload: &[f32]) -> Vec<u8> {
    let mut o = Out(Vec::with_capacity(
        4 + REQUEST_HEADER_BYTES + payload.len() * 4,
    ));
    o.u32((REQUEST_HEADER_BYTES + payload.len() * 4) as u32);
    o.u64(h.request_id);
    o.u32(h.op);
    o.u32(h.channels);
    o.u32(h.examples);
    o.u32(h.first);
    for w in h.waypoints {
        o.u32(w);
    }
    o.bytes(&h.class_name);
    for &v in payload {
        o.f32(v);
    }
    o.0
}

/// Decode a request frame body (without its length prefix; its length checked with
/// [`check_request_len`]).
pub fn decode_request(body: &[u8]) -> Result<(RequestHeader, Vec<f32>), FrameError> {
    check_request_len(body.len())?;
    let mut i = In(body);
    // Fields are read in declaration order (struct expressions evaluate in source order).
    let h = RequestHeader {
        request_id: i.u64(),
        op: i.u32(),
        channels: i.u32(),
        examples: i.u32(),
        first: i.u32(),
        waypoints: std::array::from_fn(|_| i.u32()),
        class_name: i.take::<NAME_BYTES>(),
    };
    let payload = body[REQUEST_HEADER_BYTES..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Ok((h, payload))
}

/// A response frame: length prefix, header, entries.
pub fn encode_response(r: &ResponseHeader, entries: &[ClassEntry]) -> Vec<u8> {
    let len = RESPONSE_HEADER_BYTES + entries.len() * CLASS_ENTRY_BYTES;
    let mut o = Out(Vec::with_capacity(4 + len));
    o.u32(len as u32);
    for v in [
        r.request_id,
        r.bank_version,
        r.uptime_ms,
        r.requests,
        r.errors,
        r.go,
        r.no_go,
    ] {
        o.u64(v);
    }
    for v in [
        r.op,
        r.status,
        r.verdict,
        r.reason,
        r.invalid_kind,
        r.invalid_index,
        r.invalid_example,
        r.class_count,
    ] {
        o.u32(v);
    }
    for v in [
        r.claimed_distance,
        r.threshold,
        r.margin,
        r.gap,
        r.latency_p50_us,
        r.latency_p90_us,
        r.latency_p99_us,
        r.latency_max_us,
    ] {
        o.f32(v);
    }
    o.bytes(&r.model_version);
    o.bytes(&r.message);
    o.bytes(&r.class_name);
    o.u32(r.workcell_kind);
    o.u32(r.workcell_index);
    o.f32(r.geometry_score);
    o.f32(r.geometry_threshold);
    o.u32(r.geometry_feature);
    o.u32(r.limit_kind);
    o.u64(r.limit_max);
    o.u64(r.limit_requested);
    o.u32(r.robot_joints);
    o.bytes(&r.robot_name);
    o.bytes(&r.robot_urdf_sha256);
    o.bytes(&r.reserved);
    for e in entries {
        o.bytes(&e.name);
        o.f32(e.distance);
        o.f32(e.threshold);
        o.u32(e.examples);
        o.u32(e.calibrated);
    }
    o.0
}

/// Decode a response frame body (without its length prefix).
pub fn decode_response(
    body: &[u8],
    max_entries: usize,
) -> Result<(ResponseHeader, Vec<ClassEntry>), FrameError> {
    check_response_len(body.len(), max_entries)?;
    let mut i = In(body);
    let r = ResponseHeader {
        request_id: i.u64(),
        bank_version: i.u64(),
        uptime_ms: i.u64(),
        requests: i.u64(),
        errors: i.u64(),
        go: i.u64(),
        no_go: i.u64(),
        op: i.u32(),
        status: i.u32(),
        verdict: i.u32(),
        reason: i.u32(),
        invalid_kind: i.u32(),
        invalid_index: i.u32(),
        invalid_example: i.u32(),
        class_count: i.u32(),
        claimed_distance: i.f32(),
        threshold: i.f32(),
        margin: i.f32(),
        gap: i.f32(),
        latency_p50_us: i.f32(),
        latency_p90_us: i.f32(),
        latency_p99_us: i.f32(),
        latency_max_us: i.f32(),
        model_version: i.take::<NAME_BYTES>(),
        message: i.take::<MESSAGE_BYTES>(),
        class_name: i.take::<NAME_BYTES>(),
        workcell_kind: i.u32(),
        workcell_index: i.u32(),
        geometry_score: i.f32(),
        geometry_threshold: i.f32(),
        geometry_feature: i.u32(),
        limit_kind: i.u32(),
        limit_max: i.u64(),
        limit_requested: i.u64(),
        robot_joints: i.u32(),
        robot_name: i.take::<NAME_BYTES>(),
        robot_urdf_sha256: i.take::<32>(),
        reserved: i.take::<20>(),
    };
    let mut entries = Vec::with_capacity((body.len() - RESPONSE_HEADER_BYTES) / CLASS_ENTRY_BYTES);
    while !i.0.is_empty() {
        entries.push(ClassEntry {
            name: i.take::<NAME_BYTES>(),
            distance: i.f32(),
            threshold: i.f32(),
            examples: i.u32(),
            calibrated: i.u32(),
        });
    }
    Ok((r, entries))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::{Op, encode_class_name, encode_text};

    #[test]
    fn frames_round_trip_and_match_the_in_memory_sizes() {
        assert_eq!(REQUEST_HEADER_BYTES, size_of::<RequestHeader>());
        assert_eq!(RESPONSE_HEADER_BYTES, size_of::<ResponseHeader>());
        assert_eq!(CLASS_ENTRY_BYTES, size_of::<ClassEntry>());
        let mut h = RequestHeader::new(42, Op::Enroll);
        h.examples = 2;
        h.waypoints[0] = 1;
        h.waypoints[1] = 1;
        h.class_name = encode_class_name("task").unwrap();
        let payload: Vec<f32> = (0..16).map(|v| v as f32 * 0.5).collect();
        let f = encode_request(&h, &payload);
        assert_eq!(f.len(), 4 + 152 + 64);
        assert_eq!(
            u32::from_le_bytes(f[..4].try_into().unwrap()) as usize,
            f.len() - 4
        );
        assert_eq!(decode_request(&f[4..]), Ok((h, payload)));

        let mut r = ResponseHeader::new(42, Op::Enroll as u32);
        r.status = 7;
        r.limit_kind = 2;
        r.limit_max = u64::MAX - 1;
        r.limit_requested = 9;
        r.robot_joints = 6;
        r.robot_name[..5].copy_from_slice(b"ur5e\0");
        r.robot_urdf_sha256[31] = 7;
        r.message = encode_text("limit");
        r.latency_p99_us = 12.5;
        let e = ClassEntry {
            name: encode_text("task"),
            distance: f32::NAN,
            threshold: 0.5,
            examples: 3,
            calibrated: 1,
        };
        let f = encode_response(&r, &[e]);
        assert_eq!(f.len(), 4 + 536 + 80);
        let (r2, e2) = decode_response(&f[4..], 1).unwrap();
        // Bitwise equal (NaN fields included): encoding the decoded header gives the frame.
        assert_eq!(encode_response(&r2, &e2), f);
        assert_eq!((e2[0].name, e2[0].examples), (e.name, e.examples));
        assert!(decode_response(&f[4..], 0).is_err());
        assert!(check_request_len(151).is_err());
        assert!(check_request_len(153).is_err());
        assert!(check_request_len(MAX_ADMIN_REQUEST_BYTES + 4).is_err());
        assert!(check_request_len(MAX_ADMIN_REQUEST_BYTES).is_ok());
    }
}
