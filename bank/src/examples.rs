//! The enrolled examples a class keeps: each example's resampled plan ([`STEPS`] waypoints of
//! the robot's joints and the tool channel, as the model saw it), so that a bank survives a
//! new model: [`ClassBank::reembedded`](super::ClassBank::reembedded) embeds them again.
//!
//! On disk an example is one string: the base64 (standard alphabet, padded) of its
//! `STEPS × (joints + 1)` values as little-endian `f32`, waypoint by waypoint (`q1..qn,
//! tool`). Exact (a re-embedding sees the very plan the enrollment saw) and about a third
//! of the size of the same numbers as JSON text: 5,464 bytes for a Panda plan.

use guardian_shared::trajectory::{MAX_JOINTS, Resampled, STEPS, TOOL};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// One enrolled example: a resampled plan of a robot with [`Example::joints`] joints.
#[derive(Clone, PartialEq)]
pub struct Example {
    joints: usize,
    /// `STEPS × (joints + 1)` values, waypoint by waypoint.
    values: Vec<f32>,
}

impl std::fmt::Debug for Example {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Example({} joints x {STEPS})", self.joints)
    }
}

impl Example {
    /// The resampled plan `x` of a robot with `joints` joints (1..=[`MAX_JOINTS`]; slots
    /// past `joints` are not kept).
    pub fn from_resampled(x: &Resampled, joints: usize) -> Self {
        let joints = joints.clamp(1, MAX_JOINTS);
        let mut values = Vec::with_capacity(STEPS * (joints + 1));
        for w in x {
            values.extend_from_slice(&w[..joints]);
            values.push(w[TOOL]);
        }
        Self { joints, values }
    }

    /// The plan as the model's input (unused joint slots 0).
    pub fn to_resampled(&self) -> Resampled {
        let mut x = [[0.0f32; guardian_shared::trajectory::SLOTS]; STEPS];
        for (w, row) in x.iter_mut().zip(self.values.chunks_exact(self.joints + 1)) {
            w[..self.joints].copy_from_slice(&row[..self.joints]);
            w[TOOL] = row[self.joints];
        }
        x
    }

    /// Joints of the robot the plan is for.
    pub fn joints(&self) -> usize {
        self.joints
    }

    /// Every value is finite.
    pub fn is_finite(&self) -> bool {
        self.values.iter().all(|v| v.is_finite())
    }

    fn encode(&self) -> String {
        let bytes: Vec<u8> = self.values.iter().flat_map(|v| v.to_le_bytes()).collect();
        base64_encode(&bytes)
    }

    fn decode(s: &str) -> Result<Self, String> {
        let bytes = base64_decode(s)?;
        let per_step = STEPS * 4;
        let channels = bytes.len() / per_step;
        if !bytes.len().is_multiple_of(per_step) || !(2..=MAX_JOINTS + 1).contains(&channels) {
            return Err(format!(
                "an enrolled example holds {} bytes, not {STEPS} waypoints of 2..={} f32 channels",
                bytes.len(),
                MAX_JOINTS + 1
            ));
        }
        let values = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        Ok(Self {
            joints: channels - 1,
            values,
        })
    }
}

impl Serialize for Example {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.encode())
    }
}

impl<'de> Deserialize<'de> for Example {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = <std::borrow::Cow<'de, str>>::deserialize(d)?;
        Self::decode(&s).map_err(serde::de::Error::custom)
    }
}

const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

fn base64_encode(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            chunk.get(1).copied().unwrap_or(0),
            chunk.get(2).copied().unwrap_or(0),
        ];
        let n = u32::from(b[0]) << 16 | u32::from(b[1]) << 8 | u32::from(b[2]);
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

fn base64_decode(s: &str) -> Result<Vec<u8>, String> {
    let s = s.as_bytes();
    if !s.len().is_multiple_of(4) {
        return Err("an enrolled example is not base64 (length)".into());
    }
    let value = |c: u8| -> Result<u32, String> {
        match c {
            b'A'..=b'Z' => Ok(u32::from(c - b'A')),
            b'a'..=b'z' => Ok(u32::from(c - b'a') + 26),
            b'0'..=b'9' => Ok(u32::from(c - b'0') + 52),
            b'+' => Ok(62),
            b'/' => Ok(63),
            _ => Err(format!("an enrolled example is not base64 (byte {c:#04x})")),
        }
    };
    let mut out = Vec::with_capacity(s.len() / 4 * 3);
    let quads = s.len() / 4;
    for (q, chunk) in s.chunks_exact(4).enumerate() {
        let pad = chunk.iter().rev().take_while(|&&c| c == b'=').count();
        if pad > 2 || (pad > 0 && q + 1 != quads) {
            return Err("an enrolled example is not base64 (padding)".into());
        }
        let mut n = 0u32;
        for &c in &chunk[..4 - pad] {
            n = n << 6 | value(c)?;
        }
        n <<= 6 * pad as u32;
        let bytes = [(n >> 16) as u8, (n >> 8) as u8, n as u8];
        out.extend_from_slice(&bytes[..3 - pad]);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_the_standard_alphabet_and_round_trips() {
        // RFC 4648 test vectors.
        for (plain, coded) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64_encode(plain.as_bytes()), coded);
            assert_eq!(base64_decode(coded).unwrap(), plain.as_bytes());
        }
        let all: Vec<u8> = (0..=255).collect();
        assert_eq!(base64_decode(&base64_encode(&all)).unwrap(), all);
        for bad in ["Zg=", "Z===", "Zg==Zg==", "Zm9*", "Zm9v\n"] {
            assert!(base64_decode(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn an_example_round_trips_exactly_through_json() {
        let mut x = [[0.0f32; guardian_shared::trajectory::SLOTS]; STEPS];
        for (k, w) in x.iter_mut().enumerate() {
            for (j, v) in w[..6].iter_mut().enumerate() {
                *v = (k as f32 * 0.37 + j as f32).sin() * 3.1 + 1e-7 * k as f32;
            }
            w[TOOL] = f32::from(u8::from(k % 3 != 0));
        }
        let e = Example::from_resampled(&x, 6);
        assert_eq!(e.joints(), 6);
        assert_eq!(e.to_resampled(), x);
        let json = serde_json::to_string(&e).unwrap();
        assert_eq!(json.len(), 2 + (STEPS * 7 * 4).div_ceil(3) * 4);
        let back: Example = serde_json::from_str(&json).unwrap();
        assert_eq!(back, e);
        // Not a whole number of waypoints, or too many channels: refused.
        assert!(serde_json::from_str::<Example>("\"Zm9v\"").is_err());
        let wide = base64_encode(&vec![0u8; STEPS * 4 * (MAX_JOINTS + 2)]);
        assert!(serde_json::from_str::<Example>(&format!("\"{wide}\"")).is_err());
    }
}
