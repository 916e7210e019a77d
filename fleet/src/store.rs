//! The fleet's replicated state: for each class, the winning record (last writer wins),
//! persisted append-only in `fleet.records` next to the bank.
//!
//! **Order.** Records of one class are totally ordered by `(lamport, signer, record hash)`
//! and the greatest wins. Each member keeps one Lamport clock: it moves past every record
//! it accepts, and a member's own change takes the clock + 1, so a change made after seeing
//! another one always wins over it (causality is kept for sequential edits), while two
//! concurrent changes of the same class are decided by the signer's key and then the
//! record's hash — the same way on every member. The winner of a class is therefore a pure
//! function of the *set* of records a member has received: merging is commutative,
//! associative and idempotent, so members converge whatever the order and the number of
//! times records are delivered. A vector clock would only *detect* concurrent edits; they
//! would still need a deterministic rule to pick one bank, it grows with the fleet, and it
//! gives an operator nothing a per-signer position does not (see [`Store::position`]).
//!
//! **File.** The line `guardian-fleet-records 1\n`, then per record a frame: `u32` length
//! (little-endian), the record's SHA-256 (32 bytes), the record. Appends are written in one
//! `write` and fsynced before the record is applied. Only an incomplete last frame is a
//! torn tail (a crash mid-append): it is reported ([`OpenReport::torn_bytes`]) and cut off,
//! never silently dropped. A complete frame whose checksum fails is damage: the store does
//! not open ([`StoreError::Damaged`]). On open the file is compacted (rewritten atomically
//! with only the winners) when it holds superseded records.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

use ed25519_dalek::VerifyingKey;
use sha2::{Digest, Sha256};

use crate::record::{DecodeError, Record};

/// File name of the store in the state directory.
pub const STORE_FILE: &str = "fleet.records";
const MAGIC: &[u8] = b"guardian-fleet-records 1\n";

/// Opening or writing the store failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// I/O on the store file.
    #[error("fleet record store {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file does not start with the store's magic line.
    #[error("{path} is not a fleet record store")]
    NotAStore {
        /// The file.
        path: PathBuf,
    },
    /// A complete frame fails its checksum or does not decode.
    #[error("fleet record store {path} is damaged at byte {offset}: {detail}")]
    Damaged {
        /// The file.
        path: PathBuf,
        /// Offset of the bad frame.
        offset: u64,
        /// What is wrong.
        detail: String,
    },
}

/// What opening the store found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct OpenReport {
    /// Records read.
    pub records: usize,
    /// Records skipped because their signer is no longer trusted (key rotation).
    pub untrusted: usize,
    /// Bytes of an incomplete last frame, cut off.
    pub torn_bytes: u64,
    /// Whether the file was rewritten with the winners only.
    pub compacted: bool,
}

/// What [`Store::offer`] did with a record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offer {
    /// The record wins for its class: persisted, it is the class's state now.
    Applied,
    /// The very record is already the winner (a duplicate delivery).
    Duplicate,
    /// An older (or replayed) record: the class's current winner is greater.
    Stale {
        /// Lamport counter of the current winner.
        winner_lamport: u64,
    },
}

/// What [`Store::retract`] needs to take an own record back: the state before it.
#[derive(Debug, Clone)]
pub struct Undo {
    class: String,
    previous: Option<Record>,
    clock: u64,
    file_len: u64,
}

/// The winners per class, the Lamport clock and the per-signer position.
#[derive(Debug)]
pub struct Store {
    path: PathBuf,
    winners: BTreeMap<String, Record>,
    clock: u64,
}

fn frame(record: &Record) -> Vec<u8> {
    let b = record.bytes();
    let mut out = Vec::with_capacity(b.len() + 36);
    out.extend_from_slice(&(b.len() as u32).to_le_bytes());
    out.extend_from_slice(record.hash());
    out.extend_from_slice(b);
    out
}

impl Store {
    /// Open (or create) the store at `path`, keeping records signed by `trusted` keys.
    pub fn open(path: &Path, trusted: &[VerifyingKey]) -> Result<(Self, OpenReport), StoreError> {
        let io = |source| StoreError::Io {
            path: path.to_owned(),
            source,
        };
        let mut store = Self {
            path: path.to_owned(),
            winners: BTreeMap::new(),
            clock: 0,
        };
        let mut report = OpenReport::default();
        let data = match fs::read(path) {
            Ok(d) => d,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
            Err(e) => return Err(io(e)),
        };
        if data.is_empty() {
            return Ok((store, report));
        }
        if !data.starts_with(MAGIC) {
            // A file cut inside its magic line was created by a crash before any record.
            if MAGIC.starts_with(&data) {
                report.torn_bytes = data.len() as u64;
                fs::remove_file(path).map_err(io)?;
                return Ok((store, report));
            }
            return Err(StoreError::NotAStore {
                path: path.to_owned(),
            });
        }
        let mut at = MAGIC.len();
        let mut seen = 0usize;
        while at < data.len() {
            let rest = &data[at..];
            let damaged = |detail: String| StoreError::Damaged {
                path: path.to_owned(),
                offset: at as u64,
                detail,
            };
            if rest.len() < 36 {
                report.torn_bytes = rest.len() as u64;
                break;
            }
            let len = u32::from_le_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
            if rest.len() < 36 + len {
                report.torn_bytes = rest.len() as u64;
                break;
            }
            let body = &rest[36..36 + len];
            if Sha256::digest(body).as_slice() != &rest[4..36] {
                return Err(damaged("checksum mismatch".into()));
            }
            let record = Record::decode(body).map_err(|e: DecodeError| damaged(e.to_string()))?;
            seen += 1;
            at += 36 + len;
            if record.verify(trusted).is_err() {
                report.untrusted += 1;
                continue;
            }
            store.merge(record);
        }
        report.records = seen;
        if report.torn_bytes > 0 || seen > store.winners.len() {
            store.rewrite()?;
            report.compacted = seen > store.winners.len();
        }
        Ok((store, report))
    }

    /// Take `record` into memory if it wins its class; returns what it did.
    fn merge(&mut self, record: Record) -> Offer {
        self.clock = self.clock.max(record.lamport());
        match self.winners.get(record.class()) {
            Some(w) if w.hash() == record.hash() => return Offer::Duplicate,
            Some(w) if w.order_key() > record.order_key() => {
                return Offer::Stale {
                    winner_lamport: w.lamport(),
                };
            }
            _ => {}
        }
        self.winners.insert(record.class().to_owned(), record);
        Offer::Applied
    }

    /// Offer a verified record: if it wins its class it is appended to the file (fsynced)
    /// and becomes the class's state. A record that loses changes nothing on disk.
    pub fn offer(&mut self, record: Record) -> Result<Offer, StoreError> {
        let wins = match self.winners.get(record.class()) {
            Some(w) if w.hash() == record.hash() => false,
            Some(w) => w.order_key() < record.order_key(),
            None => true,
        };
        if wins {
            self.append(&record)?;
        }
        Ok(self.merge(record))
    }

    /// Offer this member's own new record (signed with [`Store::next_lamport`], so it wins
    /// its class): appended, fsynced and taken as the class's state, with what
    /// [`Store::retract`] needs to take it back if the change cannot be completed.
    pub fn offer_own(&mut self, record: Record) -> Result<(Offer, Undo), StoreError> {
        let undo = Undo {
            class: record.class().to_owned(),
            previous: self.winners.get(record.class()).cloned(),
            clock: self.clock,
            file_len: fs::metadata(&self.path).map_or(0, |m| m.len()),
        };
        Ok((self.offer(record)?, undo))
    }

    /// Take back the record of [`Store::offer_own`] (the bank could not persist its
    /// change): the file is cut back to its length before the append (fsynced) and the
    /// class's previous winner and the clock are restored. Must come before any other
    /// change of the store. On an error the record stays in memory and on disk.
    pub fn retract(&mut self, undo: Undo) -> Result<(), StoreError> {
        let io = |source| StoreError::Io {
            path: self.path.clone(),
            source,
        };
        let f = fs::OpenOptions::new()
            .write(true)
            .open(&self.path)
            .map_err(io)?;
        f.set_len(undo.file_len)
            .and_then(|()| f.sync_data())
            .map_err(io)?;
        match undo.previous {
            Some(p) => self.winners.insert(undo.class, p),
            None => self.winners.remove(&undo.class),
        };
        self.clock = undo.clock;
        Ok(())
    }

    fn append(&self, record: &Record) -> Result<(), StoreError> {
        let io = |source| StoreError::Io {
            path: self.path.clone(),
            source,
        };
        let mut f = fs::OpenOptions::new()
            .create(true)
            .append(true)
            .mode(0o600)
            .open(&self.path)
            .map_err(io)?;
        let before = f.metadata().map_err(io)?.len();
        let mut buf = Vec::new();
        if before == 0 {
            buf.extend_from_slice(MAGIC);
        }
        buf.extend_from_slice(&frame(record));
        if let Err(e) = f.write_all(&buf).and_then(|()| f.sync_data()) {
            // Cut a partial append back (best effort); a crash leaves a torn tail instead.
            let _ = f.set_len(before).and_then(|()| f.sync_data());
            return Err(io(e));
        }
        if before == 0 {
            sync_dir(&self.path).map_err(io)?;
        }
        Ok(())
    }

    /// Write the winners to a temporary file, fsync, rename over the store.
    fn rewrite(&self) -> Result<(), StoreError> {
        let io = |source| StoreError::Io {
            path: self.path.clone(),
            source,
        };
        let mut tmp = self.path.as_os_str().to_os_string();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        let mut buf = MAGIC.to_vec();
        for r in self.winners.values() {
            buf.extend_from_slice(&frame(r));
        }
        let mut f = fs::OpenOptions::new()
            .create(true)
            .write(true)
            .truncate(true)
            .mode(0o600)
            .open(&tmp)
            .map_err(io)?;
        f.write_all(&buf).and_then(|()| f.sync_all()).map_err(io)?;
        fs::rename(&tmp, &self.path).map_err(io)?;
        sync_dir(&self.path).map_err(io)
    }

    /// The Lamport counter for this member's next own record: past every record seen.
    pub fn next_lamport(&self) -> u64 {
        self.clock + 1
    }

    /// The Lamport clock (the greatest counter seen).
    pub fn clock(&self) -> u64 {
        self.clock
    }

    /// The winning record of `class`.
    pub fn winner(&self, class: &str) -> Option<&Record> {
        self.winners.get(class)
    }

    /// Every class's winning record, by class name.
    pub fn winners(&self) -> impl Iterator<Item = &Record> {
        self.winners.values()
    }

    /// The fleet position: per signer, the greatest Lamport counter among the records of
    /// that signer the bank holds here (the winners). Like the winners, it depends only on
    /// the set of records received, not on their order, so members that converged report
    /// the same position, and a member that missed a signer's latest change reports a
    /// smaller counter for it (or none).
    pub fn position(&self) -> BTreeMap<[u8; 32], u64> {
        let mut p = BTreeMap::new();
        for r in self.winners.values() {
            let e = p.entry(*r.signer()).or_insert(0);
            *e = (*e).max(r.lamport());
        }
        p
    }

    /// SHA-256 over the winners' hashes in class order: equal digests, equal state.
    pub fn digest(&self) -> [u8; 32] {
        let mut h = Sha256::new();
        for r in self.winners.values() {
            h.update(r.hash());
        }
        h.finalize().into()
    }
}

fn sync_dir(path: &Path) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    fs::File::open(dir)?.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::{Change, Unsigned};
    use ed25519_dalek::SigningKey;

    fn key(b: u8) -> SigningKey {
        SigningKey::from_bytes(&[b; 32])
    }

    fn rec(class: &str, lamport: u64, k: u8, v: &[u8]) -> Record {
        Record::sign(
            Unsigned {
                fleet: "cell".into(),
                robot: "panda".into(),
                model: "m".into(),
                class: class.into(),
                change: if v.is_empty() {
                    Change::Forget
                } else {
                    Change::Put(v.to_vec())
                },
                lamport,
            },
            &key(k),
        )
    }

    fn trusted() -> Vec<VerifyingKey> {
        (1..=3).map(|b| key(b).verifying_key()).collect()
    }

    /// Every delivery order of the same records gives the same winners.
    #[test]
    fn converges_whatever_the_order() {
        let records = [
            rec("a", 1, 1, b"a1"),
            rec("a", 2, 2, b"a2"),
            rec("a", 2, 3, b"a2'"),
            rec("b", 1, 2, b"b1"),
            rec("b", 3, 1, b""),
            rec("c", 5, 3, b"c5"),
        ];
        let mut digests = std::collections::BTreeSet::new();
        let n = records.len();
        // A handful of permutations, duplicates included.
        for seed in 0..24u64 {
            let dir = tempfile::tempdir().unwrap();
            let (mut s, _) = Store::open(&dir.path().join(STORE_FILE), &trusted()).unwrap();
            let mut order: Vec<usize> = (0..n).collect();
            let mut x = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            for i in (1..n).rev() {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                order.swap(i, (x >> 33) as usize % (i + 1));
            }
            for &i in order.iter().chain(order.iter().take(2)) {
                s.offer(records[i].clone()).unwrap();
            }
            digests.insert(s.digest());
            assert_eq!(s.clock(), 5);
            assert_eq!(s.winner("b").unwrap().lamport(), 3);
        }
        assert_eq!(digests.len(), 1);
    }

    #[test]
    fn stale_and_duplicate_records_change_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(STORE_FILE);
        let (mut s, _) = Store::open(&path, &trusted()).unwrap();
        let old = rec("a", 1, 1, b"old");
        assert_eq!(s.offer(old.clone()).unwrap(), Offer::Applied);
        let new = rec("a", 2, 2, b"new");
        assert_eq!(s.offer(new.clone()).unwrap(), Offer::Applied);
        let len = fs::metadata(&path).unwrap().len();
        assert_eq!(s.offer(old).unwrap(), Offer::Stale { winner_lamport: 2 });
        assert_eq!(s.offer(new).unwrap(), Offer::Duplicate);
        assert_eq!(fs::metadata(&path).unwrap().len(), len);
        assert_eq!(s.next_lamport(), 3);
        assert_eq!(s.position()[&key(2).verifying_key().to_bytes()], 2);
        // The superseded record's signer holds no winner any more.
        assert!(
            !s.position()
                .contains_key(&key(1).verifying_key().to_bytes())
        );
    }

    /// An own record taken back leaves the file and the state as before it.
    #[test]
    fn an_own_record_is_retracted_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(STORE_FILE);
        let (mut s, _) = Store::open(&path, &trusted()).unwrap();
        // On an empty store (the file is created by the append) and on a written one.
        for round in 0..2u64 {
            let before = (fs::read(&path).unwrap_or_default(), s.digest(), s.clock());
            let r = rec("a", s.next_lamport(), 1, b"new");
            let (offer, undo) = s.offer_own(r).unwrap();
            assert_eq!(offer, Offer::Applied);
            assert_ne!(s.digest(), before.1);
            s.retract(undo).unwrap();
            assert_eq!(
                fs::read(&path).unwrap_or_default(),
                before.0,
                "round {round}"
            );
            assert_eq!((s.digest(), s.clock()), (before.1, before.2));
            let (s2, report) = Store::open(&path, &trusted()).unwrap();
            assert_eq!((s2.digest(), report.torn_bytes), (before.1, 0));
            s.offer(rec("a", s.next_lamport(), 2, b"kept")).unwrap();
        }
    }

    #[test]
    fn reopens_compacts_and_reports_a_torn_tail() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(STORE_FILE);
        let (mut s, _) = Store::open(&path, &trusted()).unwrap();
        for (i, c) in ["a", "b", "a"].iter().enumerate() {
            s.offer(rec(c, i as u64 + 1, 1, b"v")).unwrap();
        }
        let digest = s.digest();
        let full = fs::read(&path).unwrap();
        // Every cut inside the last frame: torn, reported, the rest kept.
        let last = frame(&rec("a", 3, 1, b"v")).len();
        for cut in [1, 20, last - 1] {
            fs::write(&path, &full[..full.len() - cut]).unwrap();
            let (s2, r) = Store::open(&path, &trusted()).unwrap();
            assert_eq!(r.torn_bytes, (last - cut) as u64);
            assert_eq!(s2.winner("a").unwrap().lamport(), 1);
            // The torn tail was cut off: reopening finds nothing torn.
            let (_, r2) = Store::open(&path, &trusted()).unwrap();
            assert_eq!(r2.torn_bytes, 0);
        }
        fs::write(&path, &full).unwrap();
        let (s3, r) = Store::open(&path, &trusted()).unwrap();
        assert_eq!((r.records, r.compacted), (3, true));
        assert_eq!(s3.digest(), digest);
        let (_, r) = Store::open(&path, &trusted()).unwrap();
        assert_eq!((r.records, r.compacted), (2, false));
        // A complete frame with a bad checksum is damage, not a torn tail.
        let mut bad = fs::read(&path).unwrap();
        let n = bad.len();
        bad[n - 70] ^= 1;
        fs::write(&path, &bad).unwrap();
        assert!(matches!(
            Store::open(&path, &trusted()),
            Err(StoreError::Damaged { .. })
        ));
        // A key no longer trusted: its records are skipped.
        fs::write(&path, &full).unwrap();
        let (s4, r) = Store::open(&path, &[key(2).verifying_key()]).unwrap();
        assert_eq!((r.untrusted, s4.winners().count()), (3, 0));
    }
}
