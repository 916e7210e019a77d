//! Remote requests over Zenoh: the envelope a remote caller signs, and the member's signed
//! answer.
//!
//! The body inside is exactly the admin socket's frame body (`guardian_shared::wire::admin`):
//! the iceoryx2 request header and `f32` payload as little-endian bytes, and the response
//! header and class entries the same way; so a remote check is decoded and answered by the
//! same code as a local one.
//!
//! Request envelope: `GRQ1`, `u64` Unix time in milliseconds, a 16-byte nonce, the caller's
//! public key (32), `u32` body length, the body, an Ed25519 signature (64) over
//! [`REQUEST_DOMAIN`], the target fleet and member (each `u16` length + UTF-8) and every
//! byte before the signature. A member accepts it only from a configured caller key, within
//! ±[`WINDOW_MS`] of its own clock, and only once (a nonce cache covers the window), so a
//! captured request cannot be replayed, nor sent to another member.
//!
//! Response envelope: `GRS1`, the request's nonce (16), `u32` body length, the body, a
//! signature by the member's key over [`RESPONSE_DOMAIN`], fleet, member and every byte
//! before it: a caller holding the member's public key knows the verdict is the member's
//! answer to its request.

use std::collections::HashMap;
use std::io::Read;

use ed25519_dalek::{Signature, Signer, SigningKey, Verifier, VerifyingKey};
use guardian_shared::wire::{Op, decode_code};

/// Prefix of a signed request.
pub const REQUEST_DOMAIN: &[u8] = b"guardian-fleet-request-v1\0";
/// Prefix of a signed response.
pub const RESPONSE_DOMAIN: &[u8] = b"guardian-fleet-response-v1\0";
/// Largest difference between a request's time and the member's clock.
pub const WINDOW_MS: u64 = 30_000;
/// Most nonces remembered; beyond it new requests are refused until old ones expire.
pub const MAX_NONCES: usize = 1 << 20;
/// Longest body (the largest legal request frame).
pub const MAX_BODY: usize = guardian_shared::wire::admin::MAX_ADMIN_REQUEST_BYTES;

/// A remote request or response that is refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum RemoteError {
    /// Not an envelope of this version, or cut short.
    #[error("malformed envelope: {0}")]
    Malformed(&'static str),
    /// The caller's key is not configured.
    #[error("caller key {0} is not a configured caller")]
    UnknownCaller(String),
    /// The signature does not verify.
    #[error("signature does not verify")]
    BadSignature,
    /// The request's time is outside the window.
    #[error("request time is {skew_ms} ms from this member's clock (window {WINDOW_MS} ms)")]
    Stale {
        /// Signed difference, request minus member, milliseconds.
        skew_ms: i64,
    },
    /// This nonce was seen already.
    #[error("replayed request (nonce already seen)")]
    Replay,
    /// The nonce cache is full.
    #[error("too many recent requests; try again")]
    Busy,
    /// The response does not answer this request.
    #[error("response answers another request")]
    WrongNonce,
}

/// A request that passed the gate.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Opened {
    /// The request's nonce (echoed in the response).
    pub nonce: [u8; 16],
    /// The caller's public key.
    pub caller: [u8; 32],
    /// The body: request header and payload bytes.
    pub body: Vec<u8>,
}

/// Whether a remote caller may run `op` (a request header's `op` field): check, identify
/// and status only; enroll, forget and the rest are admin operations.
pub fn permitted(op: u32) -> bool {
    matches!(
        decode_code::<Op>(op),
        Some(Op::Check | Op::Identify | Op::Status)
    )
}

/// Milliseconds since the Unix epoch (0 if the clock is before it).
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// 16 bytes from `/dev/urandom`.
pub fn nonce() -> std::io::Result<[u8; 16]> {
    let mut n = [0u8; 16];
    std::fs::File::open("/dev/urandom")?.read_exact(&mut n)?;
    Ok(n)
}

fn put_text(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u16).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

fn message(domain: &[u8], fleet: &str, member: &str, signed: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(domain.len() + fleet.len() + member.len() + 4 + signed.len());
    m.extend_from_slice(domain);
    put_text(&mut m, fleet);
    put_text(&mut m, member);
    m.extend_from_slice(signed);
    m
}

/// Seal `body` for `member` of `fleet`, signed by the caller's `key`.
pub fn seal_request(
    key: &SigningKey,
    fleet: &str,
    member: &str,
    body: &[u8],
    now_ms: u64,
    nonce: [u8; 16],
) -> Vec<u8> {
    let mut out = Vec::with_capacity(body.len() + 132);
    out.extend_from_slice(b"GRQ1");
    out.extend_from_slice(&now_ms.to_le_bytes());
    out.extend_from_slice(&nonce);
    out.extend_from_slice(key.verifying_key().as_bytes());
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    out.extend_from_slice(body);
    let sig = key.sign(&message(REQUEST_DOMAIN, fleet, member, &out));
    out.extend_from_slice(&sig.to_bytes());
    out
}

/// An envelope's parts: the signed bytes, the body inside them, the signature.
type Parts<'a> = (&'a [u8], &'a [u8], &'a [u8]);

/// Split `env` into its [`Parts`], checking magic and length.
fn split<'a>(env: &'a [u8], magic: &[u8; 4], head: usize) -> Result<Parts<'a>, RemoteError> {
    if env.len() < head + 4 + 64 || &env[..4] != magic {
        return Err(RemoteError::Malformed("too short or wrong magic"));
    }
    let len_at = head;
    let len = u32::from_le_bytes([
        env[len_at],
        env[len_at + 1],
        env[len_at + 2],
        env[len_at + 3],
    ]) as usize;
    if len > MAX_BODY || env.len() != head + 4 + len + 64 {
        return Err(RemoteError::Malformed("body length does not match"));
    }
    let (signed, sig) = env.split_at(env.len() - 64);
    Ok((signed, &signed[head + 4..], sig))
}

fn verify(key: &VerifyingKey, msg: &[u8], sig: &[u8]) -> Result<(), RemoteError> {
    let sig = Signature::from_slice(sig).map_err(|_| RemoteError::BadSignature)?;
    key.verify(msg, &sig).map_err(|_| RemoteError::BadSignature)
}

/// The member side: checks callers, signatures, time and replays.
#[derive(Debug)]
pub struct Gate {
    fleet: String,
    member: String,
    callers: Vec<VerifyingKey>,
    seen: HashMap<([u8; 32], [u8; 16]), u64>,
}

impl Gate {
    /// A gate of `member` in `fleet` admitting `callers`.
    pub fn new(fleet: &str, member: &str, callers: Vec<VerifyingKey>) -> Self {
        Self {
            fleet: fleet.to_owned(),
            member: member.to_owned(),
            callers,
            seen: HashMap::new(),
        }
    }

    /// Open a request envelope received at `now_ms`.
    pub fn open(&mut self, env: &[u8], now_ms: u64) -> Result<Opened, RemoteError> {
        let head = 4 + 8 + 16 + 32;
        let (signed, body, sig) = split(env, b"GRQ1", head)?;
        let ts = u64::from_le_bytes(
            env[4..12]
                .try_into()
                .map_err(|_| RemoteError::Malformed("time"))?,
        );
        let mut nonce = [0u8; 16];
        nonce.copy_from_slice(&env[12..28]);
        let mut caller = [0u8; 32];
        caller.copy_from_slice(&env[28..60]);
        let Some(key) = self.callers.iter().find(|k| k.as_bytes() == &caller) else {
            return Err(RemoteError::UnknownCaller(crate::keys::hex(&caller)));
        };
        verify(
            key,
            &message(REQUEST_DOMAIN, &self.fleet, &self.member, signed),
            sig,
        )?;
        let skew = ts as i128 - now_ms as i128;
        if skew.unsigned_abs() > WINDOW_MS as u128 {
            return Err(RemoteError::Stale {
                skew_ms: skew.clamp(i64::MIN as i128, i64::MAX as i128) as i64,
            });
        }
        // Forget nonces whose requests are outside the window anyway.
        if self.seen.len() >= MAX_NONCES / 2 {
            self.seen.retain(|_, t| t.abs_diff(now_ms) <= WINDOW_MS);
        }
        if self.seen.contains_key(&(caller, nonce)) {
            return Err(RemoteError::Replay);
        }
        if self.seen.len() >= MAX_NONCES {
            return Err(RemoteError::Busy);
        }
        self.seen.insert((caller, nonce), ts);
        Ok(Opened {
            nonce,
            caller,
            body: body.to_vec(),
        })
    }

    /// Nonces remembered.
    pub fn remembered(&self) -> usize {
        self.seen.len()
    }
}

/// Seal a response `body` to the request with `nonce`, signed by the member's `key`.
pub fn seal_response(
    key: &SigningKey,
    fleet: &str,
    member: &str,
    nonce: [u8; 16],
    body: &[u8],
) -> Vec<u8> {
    let mut out = Vec::with_capacity(body.len() + 88);
    out.extend_from_slice(b"GRS1");
    out.extend_from_slice(&nonce);
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    out.extend_from_slice(body);
    let sig = key.sign(&message(RESPONSE_DOMAIN, fleet, member, &out));
    out.extend_from_slice(&sig.to_bytes());
    out
}

/// Open a response to the request with `nonce` from `member` (public key `member_key`).
pub fn open_response(
    member_key: &VerifyingKey,
    fleet: &str,
    member: &str,
    nonce: [u8; 16],
    env: &[u8],
) -> Result<Vec<u8>, RemoteError> {
    let (signed, body, sig) = split(env, b"GRS1", 4 + 16)?;
    verify(
        member_key,
        &message(RESPONSE_DOMAIN, fleet, member, signed),
        sig,
    )?;
    if env[4..20] != nonce {
        return Err(RemoteError::WrongNonce);
    }
    Ok(body.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(b: u8) -> SigningKey {
        SigningKey::from_bytes(&[b; 32])
    }

    #[test]
    fn a_request_opens_once_within_the_window() {
        let caller = key(1);
        let mut gate = Gate::new("cell", "a", vec![caller.verifying_key()]);
        let now = 1_000_000;
        let env = seal_request(&caller, "cell", "a", b"body", now, [7; 16]);
        let o = gate.open(&env, now + 5).unwrap();
        assert_eq!((o.body.as_slice(), o.nonce), (&b"body"[..], [7; 16]));
        assert_eq!(gate.open(&env, now + 6), Err(RemoteError::Replay));
        let late = seal_request(&caller, "cell", "a", b"body", now, [8; 16]);
        assert!(matches!(
            gate.open(&late, now + WINDOW_MS + 1),
            Err(RemoteError::Stale { .. })
        ));
        // For another member, or from another key, or tampered: refused.
        let other = seal_request(&caller, "cell", "b", b"body", now, [9; 16]);
        assert_eq!(gate.open(&other, now), Err(RemoteError::BadSignature));
        let stranger = seal_request(&key(2), "cell", "a", b"body", now, [9; 16]);
        assert!(matches!(
            gate.open(&stranger, now),
            Err(RemoteError::UnknownCaller(_))
        ));
        let mut t = seal_request(&caller, "cell", "a", b"body", now, [10; 16]);
        t[64] ^= 1;
        assert_eq!(gate.open(&t, now), Err(RemoteError::BadSignature));
        for n in 0..env.len() {
            assert!(gate.open(&env[..n], now).is_err());
        }
    }

    #[test]
    fn responses_are_bound_to_member_and_request() {
        let member = key(3);
        let env = seal_response(&member, "cell", "a", [1; 16], b"answer");
        let pk = member.verifying_key();
        assert_eq!(
            open_response(&pk, "cell", "a", [1; 16], &env).unwrap(),
            b"answer"
        );
        assert_eq!(
            open_response(&pk, "cell", "a", [2; 16], &env),
            Err(RemoteError::WrongNonce)
        );
        assert_eq!(
            open_response(&pk, "cell", "b", [1; 16], &env),
            Err(RemoteError::BadSignature)
        );
        assert_eq!(
            open_response(&key(4).verifying_key(), "cell", "a", [1; 16], &env),
            Err(RemoteError::BadSignature)
        );
    }

    #[test]
    fn only_check_identify_status_are_permitted() {
        for (op, ok) in [
            (Op::Check, true),
            (Op::Identify, true),
            (Op::Status, true),
            (Op::Enroll, false),
            (Op::Forget, false),
            (Op::Classes, false),
        ] {
            assert_eq!(permitted(op as u32), ok, "{op:?}");
        }
        assert!(!permitted(0) && !permitted(99));
    }
}
