//! The holding acknowledgement: "member K holds the record of signer S with Lamport
//! counter L (or a later record of its class)". A member publishes one for every record it
//! takes live, and for every record a catch-up brings it; the record's signer counts them
//! before it answers its admin (`[fleet] replicas`, `docs/fleet.md`).
//!
//! Canonical byte encoding (integers little-endian):
//!
//! | field | bytes |
//! |---|---|
//! | magic `GFA1` | 4 |
//! | fleet: `u16` length + UTF-8 | 2 + n |
//! | the record's signer | 32 |
//! | the record's Lamport counter | 8 |
//! | the acknowledging member's public key | 32 |
//! | signature | 64 |
//!
//! The signature is Ed25519 over [`SIGNING_DOMAIN`] followed by every byte before it, by
//! the acknowledging member's key, which its peers trust (`admin-keys`): an
//! acknowledgement cannot be made up by something on the network that is not a member.

use ed25519_dalek::{Signature, Signer, SigningKey, Verifier, VerifyingKey};

/// Magic bytes opening an acknowledgement.
pub const MAGIC: &[u8; 4] = b"GFA1";
/// Prefix of the signed message.
pub const SIGNING_DOMAIN: &[u8] = b"guardian-fleet-ack-v1\0";

/// A verified acknowledgement.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ack {
    /// The acknowledged record's signer.
    pub signer: [u8; 32],
    /// The acknowledged record's Lamport counter.
    pub lamport: u64,
    /// The member that holds it.
    pub holder: [u8; 32],
}

/// Bytes that are not an acknowledgement this member accepts.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum AckError {
    /// Not the encoding above (length, magic, text).
    #[error("malformed acknowledgement")]
    Malformed,
    /// For another fleet.
    #[error("acknowledgement for fleet {0:?}")]
    OtherFleet(String),
    /// Signed by a key this member does not trust, or the signature is wrong.
    #[error("acknowledgement not signed by a trusted member")]
    Untrusted,
}

/// Sign an acknowledgement of the record (`signer`, `lamport`) by `key`'s member.
pub fn sign(fleet: &str, signer: &[u8; 32], lamport: u64, key: &SigningKey) -> Vec<u8> {
    let mut b = Vec::with_capacity(4 + 2 + fleet.len() + 32 + 8 + 32 + 64);
    b.extend_from_slice(MAGIC);
    b.extend_from_slice(&(fleet.len() as u16).to_le_bytes());
    b.extend_from_slice(fleet.as_bytes());
    b.extend_from_slice(signer);
    b.extend_from_slice(&lamport.to_le_bytes());
    b.extend_from_slice(key.verifying_key().as_bytes());
    let sig = key.sign(&signed_message(&b));
    b.extend_from_slice(&sig.to_bytes());
    b
}

fn signed_message(body: &[u8]) -> Vec<u8> {
    [SIGNING_DOMAIN, body].concat()
}

/// Decode and verify an acknowledgement for `fleet` against the `trusted` member keys.
pub fn open(bytes: &[u8], fleet: &str, trusted: &[VerifyingKey]) -> Result<Ack, AckError> {
    let rest = bytes.strip_prefix(MAGIC).ok_or(AckError::Malformed)?;
    let (len, rest) = rest.split_first_chunk::<2>().ok_or(AckError::Malformed)?;
    let len = u16::from_le_bytes(*len) as usize;
    if rest.len() != len + 32 + 8 + 32 + 64 {
        return Err(AckError::Malformed);
    }
    let (name, rest) = rest.split_at(len);
    let name = std::str::from_utf8(name).map_err(|_| AckError::Malformed)?;
    if name != fleet {
        return Err(AckError::OtherFleet(name.to_owned()));
    }
    let (signer, rest) = rest.split_first_chunk::<32>().ok_or(AckError::Malformed)?;
    let (lamport, rest) = rest.split_first_chunk::<8>().ok_or(AckError::Malformed)?;
    let (holder, sig) = rest.split_first_chunk::<32>().ok_or(AckError::Malformed)?;
    let key = trusted
        .iter()
        .find(|k| k.as_bytes() == holder)
        .ok_or(AckError::Untrusted)?;
    let sig = Signature::from_slice(sig).map_err(|_| AckError::Malformed)?;
    key.verify(&signed_message(&bytes[..bytes.len() - 64]), &sig)
        .map_err(|_| AckError::Untrusted)?;
    Ok(Ack {
        signer: *signer,
        lamport: u64::from_le_bytes(*lamport),
        holder: *holder,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(seed: u8) -> SigningKey {
        SigningKey::from_bytes(&[seed; 32])
    }

    #[test]
    fn round_trips_and_refuses_forgeries() {
        let (a, b, stranger) = (key(1), key(2), key(3));
        let trusted = [a.verifying_key(), b.verifying_key()];
        let signer = *a.verifying_key().as_bytes();
        let bytes = sign("cell", &signer, 42, &b);
        assert_eq!(
            open(&bytes, "cell", &trusted),
            Ok(Ack {
                signer,
                lamport: 42,
                holder: *b.verifying_key().as_bytes()
            })
        );
        assert_eq!(
            open(&bytes, "other", &trusted),
            Err(AckError::OtherFleet("cell".into()))
        );
        // A key the member does not trust.
        let forged = sign("cell", &signer, 42, &stranger);
        assert_eq!(open(&forged, "cell", &trusted), Err(AckError::Untrusted));
        // A changed counter breaks the signature.
        let mut changed = bytes.clone();
        let at = 4 + 2 + 4 + 32;
        changed[at] ^= 1;
        assert_eq!(open(&changed, "cell", &trusted), Err(AckError::Untrusted));
        // A trusted key's bytes in place of the signer's: the signature does not verify.
        let mut swapped = forged.clone();
        let holder_at = 4 + 2 + 4 + 32 + 8;
        swapped[holder_at..holder_at + 32].copy_from_slice(b.verifying_key().as_bytes());
        assert_eq!(open(&swapped, "cell", &trusted), Err(AckError::Untrusted));
        for cut in [0, 3, 10, bytes.len() - 1] {
            assert_eq!(
                open(&bytes[..cut], "cell", &trusted),
                Err(AckError::Malformed)
            );
        }
    }
}
