//! ROS 2 serialized messages: a 4-byte encapsulation header (representation id, options)
//! then plain CDR in the byte order the header names. This is what rosbag2 stores in an
//! MCAP file (`message_encoding = "cdr"`) and what DDS carries.

use byteorder::{BigEndian, LittleEndian};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// A serialized ROS 2 message could not be decoded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CdrError {
    /// Fewer than 4 bytes: no encapsulation header.
    #[error("message of {len} bytes has no CDR encapsulation header")]
    Short {
        /// Bytes seen.
        len: usize,
    },
    /// The header names an encoding other than plain CDR (e.g. XCDR2 or PL_CDR).
    #[error("unsupported CDR representation {id:#06x} (expected 0x0000 CDR_BE or 0x0001 CDR_LE)")]
    Representation {
        /// The representation identifier.
        id: u16,
    },
    /// The body does not decode as the expected type.
    #[error("{0}")]
    Body(#[from] cdr_encoding::Error),
}

/// Decode one serialized message (encapsulation header + CDR body).
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CdrError> {
    if bytes.len() < 4 {
        return Err(CdrError::Short { len: bytes.len() });
    }
    let id = u16::from_be_bytes([bytes[0], bytes[1]]);
    let body = &bytes[4..];
    let (value, _) = match id {
        0x0001 => cdr_encoding::from_bytes::<T, LittleEndian>(body)?,
        0x0000 => cdr_encoding::from_bytes::<T, BigEndian>(body)?,
        other => return Err(CdrError::Representation { id: other }),
    };
    Ok(value)
}

/// Encode one message as little-endian CDR with its encapsulation header.
pub fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, CdrError> {
    let mut out = vec![0x00, 0x01, 0x00, 0x00];
    cdr_encoding::to_writer::<_, LittleEndian, _>(&mut out, value)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{JointTrajectory, JointTrajectoryPoint, StringMsg};

    #[test]
    fn round_trip_and_typed_errors() {
        let t = JointTrajectory {
            joint_names: vec!["j1".into()],
            points: vec![JointTrajectoryPoint {
                positions: vec![0.25],
                ..Default::default()
            }],
            ..Default::default()
        };
        let bytes = encode(&t).unwrap();
        assert_eq!(decode::<JointTrajectory>(&bytes).unwrap(), t);
        assert!(matches!(
            decode::<JointTrajectory>(&bytes[..2]),
            Err(CdrError::Short { len: 2 })
        ));
        let mut xcdr2 = bytes.clone();
        xcdr2[1] = 0x07;
        assert!(matches!(
            decode::<JointTrajectory>(&xcdr2),
            Err(CdrError::Representation { id: 7 })
        ));
        // A std_msgs/String is not a trajectory: the body runs out.
        let s = encode(&StringMsg { data: "x".into() }).unwrap();
        assert!(matches!(
            decode::<JointTrajectory>(&s),
            Err(CdrError::Body(_))
        ));
    }
}
