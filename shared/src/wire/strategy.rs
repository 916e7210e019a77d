//! proptest strategies for hostile and half-valid requests (feature `proptest`), one set for
//! every fuzz test of the workspace: the wire decoder's, the screen's in process and the
//! daemon's across processes.

use proptest::prelude::*;

use super::{NAME_BYTES, RequestHeader, encode_class_name};
use crate::trajectory::MAX_WAYPOINTS;

/// Any `f32`: arbitrary bits, small values, NaN and both infinities.
pub fn f32_any() -> impl Strategy<Value = f32> {
    prop_oneof![
        any::<u32>().prop_map(f32::from_bits),
        -4.0f32..4.0,
        Just(f32::NAN),
        Just(f32::INFINITY),
        Just(f32::NEG_INFINITY),
        Just(0.5f32),
    ]
}

/// A count field: arbitrary, small, at and past the limits.
pub fn count() -> impl Strategy<Value = u32> {
    prop_oneof![
        any::<u32>(),
        0u32..8,
        Just(u32::MAX),
        Just(MAX_WAYPOINTS as u32 + 1),
        Just(1 << 31)
    ]
}

/// A class-name field: one of `names`, arbitrary bytes, control and non-ASCII text, all
/// zeros, all `x`.
pub fn name_field(names: Vec<&'static str>) -> impl Strategy<Value = [u8; NAME_BYTES]> {
    prop_oneof![
        prop::sample::select(names).prop_map(|n| encode_class_name(n).unwrap_or([0; NAME_BYTES])),
        prop::collection::vec(any::<u8>(), NAME_BYTES)
            .prop_map(|v| v.try_into().unwrap_or([0; NAME_BYTES])),
        "[\\x00-\\x1f\\x7f a-z\\u{80}-\\u{ff}]{0,64}".prop_map(|s| {
            let mut f = [0u8; NAME_BYTES];
            let n = s.len().min(NAME_BYTES);
            f[..n].copy_from_slice(&s.as_bytes()[..n]);
            f
        }),
        Just([0u8; NAME_BYTES]),
        Just([b'x'; NAME_BYTES]),
    ]
}

/// Payloads: a `genuine` plan (flat), often with one value replaced by [`f32_any`];
/// up to `random_len` random floats; empty.
pub fn payload(
    genuine: impl Strategy<Value = Vec<f32>>,
    random_len: usize,
) -> impl Strategy<Value = Vec<f32>> {
    prop_oneof![
        (
            genuine,
            prop::option::of((any::<prop::sample::Index>(), f32_any()))
        )
            .prop_map(|(mut p, m)| {
                if let Some((i, v)) = m
                    && !p.is_empty()
                {
                    let i = i.index(p.len());
                    p[i] = v;
                }
                p
            }),
        prop::collection::vec(f32_any(), 0..random_len),
        Just(Vec::new()),
    ]
}

/// A request header and its payload: often consistent (the served robot's `channels`, one
/// example whose waypoint count matches the payload) so that requests reach validation and
/// the model, otherwise arbitrary in every field.
pub fn request(
    channels: u32,
    names: impl Strategy<Value = [u8; NAME_BYTES]>,
    first: impl Strategy<Value = u32>,
    payload: impl Strategy<Value = Vec<f32>>,
) -> impl Strategy<Value = (RequestHeader, Vec<f32>)> {
    (
        any::<u64>(),
        prop_oneof![4 => 1u32..=6, 1 => any::<u32>()],
        prop_oneof![4 => Just(channels), 1 => count()],
        prop_oneof![4 => Just(1u32), 1 => 0u32..=17, 1 => count()],
        prop::array::uniform16(count()),
        prop::bool::weighted(0.7),
        names,
        first,
        payload,
    )
        .prop_map(
            |(
                request_id,
                op,
                channels,
                examples,
                mut waypoints,
                consistent,
                class_name,
                first,
                payload,
            )| {
                if consistent && channels != 0 {
                    waypoints[0] = (payload.len() / channels as usize) as u32;
                }
                let h = RequestHeader {
                    request_id,
                    op,
                    channels,
                    examples,
                    first,
                    waypoints,
                    class_name,
                };
                (h, payload)
            },
        )
}
