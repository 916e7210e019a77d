//! The signed change record: one enroll or forget of one class, as replicated in a fleet.
//!
//! A record says "in fleet F, for robot R and model M, class C is now V" (enroll: V is the
//! class's full state after the change, opaque bytes to this crate) or "class C is
//! forgotten", with the signer's Lamport counter, the signer's Ed25519 public key and a
//! signature over everything before it. Replaying a record twice changes nothing.
//!
//! Canonical byte encoding (all integers little-endian):
//!
//! | field | bytes |
//! |---|---|
//! | magic `GFR1` | 4 |
//! | op: 1 enroll (put), 2 forget | 1 |
//! | lamport | 8 |
//! | fleet, robot, model, class: each `u16` length + UTF-8 | 2 + n each |
//! | value: `u32` length + bytes (empty for forget) | 4 + n |
//! | signer public key | 32 |
//! | signature | 64 |
//!
//! The signature is Ed25519 over [`SIGNING_DOMAIN`] followed by every byte before the
//! signature, so a signature made for something else (a remote request) never verifies as a
//! record.

use ed25519_dalek::{Signature, Signer, SigningKey, Verifier, VerifyingKey};
use sha2::{Digest, Sha256};

/// Magic bytes opening a record.
pub const MAGIC: &[u8; 4] = b"GFR1";
/// Prefix of the signed message.
pub const SIGNING_DOMAIN: &[u8] = b"guardian-fleet-record-v1\0";
/// Longest text field (fleet, robot, model, class), bytes.
pub const MAX_TEXT: usize = 1024;
/// Longest value (a class's state), bytes.
pub const MAX_VALUE: usize = 64 << 20;

/// What a record does to its class.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Change {
    /// The class is now this value (its full state, encoded by the daemon).
    Put(Vec<u8>),
    /// The class is forgotten.
    Forget,
}

/// The fields a record is made of, before it is signed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Unsigned {
    /// The fleet's name.
    pub fleet: String,
    /// The robot the class's plans belong to (its record, e.g. `panda/7/<urdf sha256>`).
    pub robot: String,
    /// The model version the class was embedded with.
    pub model: String,
    /// The class.
    pub class: String,
    /// The change.
    pub change: Change,
    /// The signer's Lamport counter when it made the change.
    pub lamport: u64,
}

/// A signed record with its canonical encoding.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Record {
    fields: Unsigned,
    signer: [u8; 32],
    bytes: Vec<u8>,
    hash: [u8; 32],
}

/// Bytes that are not a well-formed record.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeError {
    /// The bytes end before the record does.
    #[error("record truncated: {field} needs {needed} more bytes, {left} left")]
    Truncated {
        /// The field being read.
        field: &'static str,
        /// Bytes it needs.
        needed: usize,
        /// Bytes left.
        left: usize,
    },
    /// Not a record (or a record of an unknown version).
    #[error("not a fleet record (magic {got:02x?})")]
    Magic {
        /// The first bytes.
        got: Vec<u8>,
    },
    /// An unknown op code.
    #[error("unknown record op {0}")]
    Op(u8),
    /// A text field is not UTF-8 or too long.
    #[error("record field {field} is not valid: {detail}")]
    Field {
        /// The field.
        field: &'static str,
        /// Why.
        detail: String,
    },
    /// A forget carrying a value.
    #[error("a forget record carries a value of {0} bytes")]
    ForgetWithValue(usize),
    /// Bytes after the signature.
    #[error("{0} bytes after the end of the record")]
    Trailing(usize),
}

/// A well-formed record that must not be applied.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum VerifyError {
    /// The signer's key is not among the trusted admin keys.
    #[error("record signed by an unknown key {signer}")]
    UnknownSigner {
        /// The signer's public key, hex.
        signer: String,
    },
    /// The signature does not verify.
    #[error("record signature does not verify (signer {signer})")]
    BadSignature {
        /// The claimed signer, hex.
        signer: String,
    },
}

struct Reader<'a> {
    buf: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, field: &'static str) -> Result<&'a [u8], DecodeError> {
        if self.buf.len() < n {
            return Err(DecodeError::Truncated {
                field,
                needed: n,
                left: self.buf.len(),
            });
        }
        let (a, b) = self.buf.split_at(n);
        self.buf = b;
        Ok(a)
    }
    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], DecodeError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, field)?);
        Ok(out)
    }
    fn text(&mut self, field: &'static str) -> Result<String, DecodeError> {
        let len = u16::from_le_bytes(self.array(field)?) as usize;
        if len > MAX_TEXT {
            return Err(DecodeError::Field {
                field,
                detail: format!("{len} bytes, at most {MAX_TEXT}"),
            });
        }
        let b = self.take(len, field)?;
        String::from_utf8(b.to_vec()).map_err(|e| DecodeError::Field {
            field,
            detail: e.to_string(),
        })
    }
}

fn put_text(out: &mut Vec<u8>, s: &str) {
    // Lengths are bounded by `Record::sign`'s callers (names are short); cut defensively.
    let b = &s.as_bytes()[..s.len().min(MAX_TEXT)];
    out.extend_from_slice(&(b.len() as u16).to_le_bytes());
    out.extend_from_slice(b);
}

impl Unsigned {
    /// Everything before the signature.
    fn body(&self, signer: &[u8; 32]) -> Vec<u8> {
        let value: &[u8] = match &self.change {
            Change::Put(v) => v,
            Change::Forget => &[],
        };
        let mut out = Vec::with_capacity(64 + value.len() + 4 * 16);
        out.extend_from_slice(MAGIC);
        out.push(match self.change {
            Change::Put(_) => 1,
            Change::Forget => 2,
        });
        out.extend_from_slice(&self.lamport.to_le_bytes());
        put_text(&mut out, &self.fleet);
        put_text(&mut out, &self.robot);
        put_text(&mut out, &self.model);
        put_text(&mut out, &self.class);
        out.extend_from_slice(&(value.len() as u32).to_le_bytes());
        out.extend_from_slice(value);
        out.extend_from_slice(signer);
        out
    }
}

fn signed_message(body: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(SIGNING_DOMAIN.len() + body.len());
    m.extend_from_slice(SIGNING_DOMAIN);
    m.extend_from_slice(body);
    m
}

impl Record {
    /// Sign `fields` with `key`.
    pub fn sign(fields: Unsigned, key: &SigningKey) -> Self {
        let signer = key.verifying_key().to_bytes();
        let mut bytes = fields.body(&signer);
        let signature = key.sign(&signed_message(&bytes));
        bytes.extend_from_slice(&signature.to_bytes());
        let hash = Sha256::digest(&bytes).into();
        Self {
            fields,
            signer,
            bytes,
            hash,
        }
    }

    /// Parse a record (its signature is checked by [`Record::verify`]).
    pub fn decode(bytes: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader { buf: bytes };
        let magic = r.take(4, "magic").map_err(|_| DecodeError::Magic {
            got: bytes.to_vec(),
        })?;
        if magic != MAGIC {
            return Err(DecodeError::Magic {
                got: magic.to_vec(),
            });
        }
        let op = r.array::<1>("op")?[0];
        let lamport = u64::from_le_bytes(r.array("lamport")?);
        let fleet = r.text("fleet")?;
        let robot = r.text("robot")?;
        let model = r.text("model")?;
        let class = r.text("class")?;
        let len = u32::from_le_bytes(r.array("value length")?) as usize;
        if len > MAX_VALUE {
            return Err(DecodeError::Field {
                field: "value",
                detail: format!("{len} bytes, at most {MAX_VALUE}"),
            });
        }
        let value = r.take(len, "value")?.to_vec();
        let change = match op {
            1 => Change::Put(value),
            2 if value.is_empty() => Change::Forget,
            2 => return Err(DecodeError::ForgetWithValue(value.len())),
            other => return Err(DecodeError::Op(other)),
        };
        let signer = r.array::<32>("signer")?;
        r.take(64, "signature")?;
        if !r.buf.is_empty() {
            return Err(DecodeError::Trailing(r.buf.len()));
        }
        Ok(Self {
            fields: Unsigned {
                fleet,
                robot,
                model,
                class,
                change,
                lamport,
            },
            signer,
            bytes: bytes.to_vec(),
            hash: Sha256::digest(bytes).into(),
        })
    }

    /// Check the signature and that the signer is one of `trusted`.
    pub fn verify(&self, trusted: &[VerifyingKey]) -> Result<(), VerifyError> {
        let signer_hex = || crate::keys::hex(&self.signer);
        let Some(key) = trusted.iter().find(|k| k.as_bytes() == &self.signer) else {
            return Err(VerifyError::UnknownSigner {
                signer: signer_hex(),
            });
        };
        let (body, sig) = self.bytes.split_at(self.bytes.len() - 64);
        let sig = Signature::from_slice(sig).map_err(|_| VerifyError::BadSignature {
            signer: signer_hex(),
        })?;
        key.verify(&signed_message(body), &sig)
            .map_err(|_| VerifyError::BadSignature {
                signer: signer_hex(),
            })
    }

    /// The signed fields.
    pub fn fields(&self) -> &Unsigned {
        &self.fields
    }
    /// The class.
    pub fn class(&self) -> &str {
        &self.fields.class
    }
    /// The Lamport counter.
    pub fn lamport(&self) -> u64 {
        self.fields.lamport
    }
    /// The signer's public key.
    pub fn signer(&self) -> &[u8; 32] {
        &self.signer
    }
    /// The canonical encoding (what is published and persisted).
    pub fn bytes(&self) -> &[u8] {
        &self.bytes
    }
    /// SHA-256 of the encoding.
    pub fn hash(&self) -> &[u8; 32] {
        &self.hash
    }
    /// The total order of records of one class: the greatest wins (last writer wins).
    pub fn order_key(&self) -> (u64, [u8; 32], [u8; 32]) {
        (self.fields.lamport, self.signer, self.hash)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(b: u8) -> SigningKey {
        SigningKey::from_bytes(&[b; 32])
    }

    fn unsigned(class: &str, lamport: u64, change: Change) -> Unsigned {
        Unsigned {
            fleet: "cell".into(),
            robot: "panda/7/abc".into(),
            model: "m1".into(),
            class: class.into(),
            change,
            lamport,
        }
    }

    #[test]
    fn round_trip_and_verify() {
        let k = key(1);
        for change in [Change::Put(b"{\"x\":1}".to_vec()), Change::Forget] {
            let r = Record::sign(unsigned("pick", 3, change), &k);
            let d = Record::decode(r.bytes()).unwrap();
            assert_eq!(d, r);
            d.verify(&[key(2).verifying_key(), k.verifying_key()])
                .unwrap();
        }
    }

    #[test]
    fn unknown_signer_and_tampering_are_refused() {
        let r = Record::sign(unsigned("pick", 3, Change::Put(vec![1, 2, 3])), &key(1));
        assert!(matches!(
            r.verify(&[key(2).verifying_key()]),
            Err(VerifyError::UnknownSigner { .. })
        ));
        // Flip one byte of the value: still well-formed, signature fails.
        let mut b = r.bytes().to_vec();
        let at = b.len() - 64 - 32 - 1;
        b[at] ^= 1;
        let t = Record::decode(&b).unwrap();
        assert!(matches!(
            t.verify(&[key(1).verifying_key()]),
            Err(VerifyError::BadSignature { .. })
        ));
        // A record re-signed by another key cannot claim the first signer.
        let mut b = r.bytes().to_vec();
        let other = Record::sign(unsigned("pick", 3, Change::Put(vec![1, 2, 3])), &key(2));
        let n = b.len();
        b[n - 64..].copy_from_slice(&other.bytes()[n - 64..]);
        assert!(
            Record::decode(&b)
                .unwrap()
                .verify(&[key(1).verifying_key()])
                .is_err()
        );
    }

    #[test]
    fn every_truncation_is_a_typed_error() {
        let r = Record::sign(unsigned("pick", 3, Change::Put(vec![9; 40])), &key(1));
        for n in 0..r.bytes().len() {
            let e = Record::decode(&r.bytes()[..n]).unwrap_err();
            assert!(
                matches!(e, DecodeError::Truncated { .. } | DecodeError::Magic { .. }),
                "{n}: {e:?}"
            );
        }
        let mut long = r.bytes().to_vec();
        long.push(0);
        assert_eq!(Record::decode(&long), Err(DecodeError::Trailing(1)));
        let mut bad = r.bytes().to_vec();
        bad[4] = 9;
        assert_eq!(Record::decode(&bad), Err(DecodeError::Op(9)));
    }

    #[test]
    fn order_is_lamport_then_signer_then_hash() {
        let a = Record::sign(unsigned("c", 2, Change::Forget), &key(1));
        let b = Record::sign(unsigned("c", 1, Change::Forget), &key(9));
        assert!(a.order_key() > b.order_key());
        let c = Record::sign(unsigned("c", 2, Change::Forget), &key(9));
        assert_eq!(
            a.order_key() < c.order_key(),
            a.signer() < c.signer(),
            "ties on lamport go to the signer"
        );
    }
}
