//! The bank's append-only journal: one checksummed record per enroll or forget, appended
//! next to the snapshot (`bank.gcb` → `bank.gcb.journal`) and fsynced before the change is
//! acknowledged, so persisting a change costs O(the changed class), not O(the bank).
//! Compaction is [`ClassBank::save`]: it writes the snapshot atomically and then removes the
//! journal, and [`ClassBank::load`] replays the journal, so whoever loads, changes and saves
//! a bank with this API sees and keeps every journalled change.
//!
//! Format: the line `guardian-bank-journal 1\n`, then one line per record,
//! `sha256:<64 hex> <json>\n`, the checksum over the JSON bytes. A record holds the bank
//! generation after the change and the changed class's full state (`put`) or its removal
//! (`remove`), so replaying a record twice changes nothing. Replay applies, in order, the
//! records whose generation is above the snapshot's (a crash between a compaction's rename
//! and the journal's removal leaves records the snapshot already holds; they are skipped).
//! Only an **incomplete last line** (no terminating newline) is a torn tail: an append
//! writes its record and the newline in one `write` and fsyncs it before the change is
//! acknowledged, so a crash can cut the last line short but never leave a complete line
//! that fails its checksum. The torn tail is ignored and reported. A complete line that
//! fails its checksum or does not parse — the last one included — is damage, and the bank
//! does not load (an acknowledged change must never vanish silently).

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::file::hex;
use super::{Class, ClassBank, LoadBankError, SaveBankError};

const MAGIC: &str = "guardian-bank-journal 1\n";

/// The journal file of the snapshot at `bank`: `<bank>.journal`.
pub fn journal_path(bank: &Path) -> PathBuf {
    let mut name = bank.file_name().unwrap_or_default().to_os_string();
    name.push(".journal");
    bank.with_file_name(name)
}

/// One change.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "op", deny_unknown_fields)]
enum Record {
    /// `class` now is `value` (enrolled or extended).
    Put {
        generation: u64,
        class: String,
        value: Box<Class>,
    },
    /// `class` was forgotten.
    Remove { generation: u64, class: String },
}

/// What replaying the journal found.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Replay {
    /// Records applied on top of the snapshot.
    pub applied: usize,
    /// Records skipped because the snapshot already holds them.
    pub skipped: usize,
    /// Bytes of a torn last record that were ignored (0: none).
    pub torn_bytes: u64,
    /// Size of the journal file (0: none).
    pub journal_bytes: u64,
}

impl ClassBank {
    /// Load the snapshot at `path` and replay its journal, if there is one.
    pub fn load_with_journal(path: &Path) -> Result<(Self, Replay), LoadBankError> {
        let mut bank = Self::load_snapshot(path)?;
        let jpath = journal_path(path);
        let bytes = match fs::read(&jpath) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok((bank, Replay::default()));
            }
            Err(source) => {
                return Err(LoadBankError::Io {
                    path: jpath,
                    source,
                });
            }
        };
        let replay = bank
            .replay(&bytes)
            .map_err(|detail| LoadBankError::Journal {
                path: jpath.clone(),
                detail,
            })?;
        bank.check()?;
        Ok((bank, replay))
    }

    fn replay(&mut self, bytes: &[u8]) -> Result<Replay, String> {
        let mut replay = Replay {
            journal_bytes: bytes.len() as u64,
            ..Replay::default()
        };
        if bytes.len() < MAGIC.len() && MAGIC.as_bytes().starts_with(bytes) {
            // Killed while writing the first header: nothing was acknowledged.
            replay.torn_bytes = bytes.len() as u64;
            return Ok(replay);
        }
        let Some(mut rest) = bytes.strip_prefix(MAGIC.as_bytes()) else {
            return Err("not a guardian bank journal (bad header line)".into());
        };
        let mut line_no = 1;
        while !rest.is_empty() {
            line_no += 1;
            let (line, after, complete) = match rest.iter().position(|&b| b == b'\n') {
                Some(nl) => (&rest[..nl], &rest[nl + 1..], true),
                None => (rest, &rest[rest.len()..], false),
            };
            if !complete {
                // Necessarily the last line: an append cut short by a crash, unless it is a
                // whole record whose newline was changed into another byte.
                if line.len() > 1 && parse_record(&line[..line.len() - 1]).is_some() {
                    return Err(format!(
                        "record on line {line_no} (the last one) is whole but its newline is damaged"
                    ));
                }
                replay.torn_bytes = rest.len() as u64;
                break;
            }
            match parse_record(line) {
                Some(record) => self.apply(record, &mut replay),
                None => {
                    let last = if after.is_empty() {
                        " (the last one)"
                    } else {
                        ""
                    };
                    return Err(format!(
                        "record on line {line_no}{last} is complete but fails its checksum or does not parse: \
                         damage, not an interrupted append"
                    ));
                }
            }
            rest = after;
        }
        Ok(replay)
    }

    fn apply(&mut self, record: Record, replay: &mut Replay) {
        let generation = match &record {
            Record::Put { generation, .. } | Record::Remove { generation, .. } => *generation,
        };
        if generation <= self.generation {
            replay.skipped += 1;
            return;
        }
        match record {
            Record::Put { class, value, .. } => {
                self.classes.insert(class, *value);
            }
            Record::Remove { class, .. } => {
                self.classes.remove(&class);
            }
        }
        self.generation = generation;
        replay.applied += 1;
    }

    /// Append the current state of class `name` (present: `put`, absent: `remove`) to the
    /// journal of the snapshot at `path` and fsync it. Returns the journal's size after the
    /// append. On failure the journal is cut back to its previous length (best effort).
    pub fn append_change(&self, path: &Path, name: &str) -> Result<u64, SaveBankError> {
        let record = match self.classes.get(name) {
            Some(c) => Record::Put {
                generation: self.generation,
                class: name.to_owned(),
                value: Box::new(c.clone()),
            },
            None => Record::Remove {
                generation: self.generation,
                class: name.to_owned(),
            },
        };
        let json = serde_json::to_vec(&record)?;
        let jpath = journal_path(path);
        let io = |source| SaveBankError::Io {
            path: jpath.clone(),
            source,
        };
        let mut f = {
            use std::os::unix::fs::OpenOptionsExt;
            fs::OpenOptions::new()
                .create(true)
                .append(true)
                .mode(0o600)
                .open(&jpath)
                .map_err(io)?
        };
        let before = f.metadata().map_err(io)?.len();
        let mut buf = Vec::with_capacity(json.len() + 80);
        if before == 0 {
            buf.extend_from_slice(MAGIC.as_bytes());
        }
        buf.extend_from_slice(format!("sha256:{} ", hex(&Sha256::digest(&json))).as_bytes());
        buf.extend_from_slice(&json);
        buf.push(b'\n');
        let written = f.write_all(&buf).and_then(|()| f.sync_data());
        if let Err(e) = written {
            let _ = f.set_len(before).and_then(|()| f.sync_data());
            return Err(io(e));
        }
        if before == 0 {
            // A new file: make its directory entry durable too.
            let dir = match jpath.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            fs::File::open(dir).and_then(|d| d.sync_all()).map_err(io)?;
        }
        Ok(before + buf.len() as u64)
    }

    /// Put class `name` back as it was before a change (`previous`; `None`: it did not
    /// exist) and the generation with it: undoes a change that could not be persisted or
    /// that broke a limit.
    pub fn undo_change(&mut self, name: &str, previous: Option<Class>, generation: u64) {
        match previous {
            Some(c) => {
                self.classes.insert(name.to_owned(), c);
            }
            None => {
                self.classes.remove(name);
            }
        }
        self.generation = generation;
    }
}

fn parse_record(line: &[u8]) -> Option<Record> {
    let rest = line.strip_prefix(b"sha256:")?;
    if rest.len() < 65 || rest[64] != b' ' {
        return None;
    }
    let (sum, json) = (&rest[..64], &rest[65..]);
    if hex(&Sha256::digest(json)).as_bytes() != sum {
        return None;
    }
    serde_json::from_slice(json).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bank() -> ClassBank {
        let mut b = ClassBank::new(2, "m", 0.5);
        b.enroll("a", &[vec![0.0, 1.0]]).unwrap();
        b
    }

    fn names(b: &ClassBank) -> Vec<String> {
        b.classes().map(|(n, _)| n.to_owned()).collect()
    }

    /// Every prefix of the journal (a crash at any byte of an append) loads the state
    /// before or after that append, never anything else; damage before the last record
    /// is refused.
    #[test]
    fn a_torn_append_at_any_byte_leaves_the_old_or_the_new_state() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bank.gcb");
        let mut b = bank();
        b.save(&path).unwrap();
        b.enroll("b", &[vec![1.0, 0.0]]).unwrap();
        let after_one = b.append_change(&path, "b").unwrap();
        b.enroll("a", &[vec![0.5, 0.5]]).unwrap();
        b.append_change(&path, "a").unwrap();
        b.forget("b");
        let full = b.append_change(&path, "b").unwrap();
        let (loaded, replay) = ClassBank::load_with_journal(&path).unwrap();
        assert_eq!(loaded, b);
        assert_eq!((replay.applied, replay.torn_bytes), (3, 0));

        let journal = fs::read(journal_path(&path)).unwrap();
        assert_eq!(journal.len() as u64, full);
        let states: Vec<Vec<String>> = vec![
            vec!["a".into()],
            vec!["a".into(), "b".into()],
            vec!["a".into()],
        ];
        for cut in 0..journal.len() {
            fs::write(journal_path(&path), &journal[..cut]).unwrap();
            let (l, r) = ClassBank::load_with_journal(&path).unwrap();
            assert!(states.contains(&names(&l)), "cut {cut}: {:?}", names(&l));
            if cut as u64 >= after_one {
                assert!(l.generation() > 1, "cut {cut}: first record lost");
            }
            if cut > MAGIC.len() && r.applied == 0 {
                assert!(r.torn_bytes > 0, "cut {cut}");
            }
        }
        // A damaged record followed by another is damage, not a torn tail.
        let mut bad = journal.clone();
        bad[MAGIC.len() + 80] ^= 1;
        fs::write(journal_path(&path), &bad).unwrap();
        assert!(matches!(
            ClassBank::load_with_journal(&path),
            Err(LoadBankError::Journal { .. })
        ));
        // Compaction folds the journal into the snapshot and removes it; records the
        // snapshot already holds are skipped when a stale journal is left behind.
        fs::write(journal_path(&path), &journal).unwrap();
        b.save(&path).unwrap();
        assert!(!journal_path(&path).exists());
        fs::write(journal_path(&path), &journal).unwrap();
        let (l, r) = ClassBank::load_with_journal(&path).unwrap();
        assert_eq!(l, b);
        assert_eq!((r.applied, r.skipped), (0, 3));
    }

    /// A complete last record that fails its checksum is damage, refused like damage
    /// elsewhere; only a last line without its newline is a torn append.
    #[test]
    fn a_damaged_complete_last_record_is_refused_not_taken_for_a_torn_append() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bank.gcb");
        let mut b = bank();
        b.save(&path).unwrap();
        b.enroll("b", &[vec![1.0, 0.0]]).unwrap();
        let first = b.append_change(&path, "b").unwrap() as usize;
        b.enroll("c", &[vec![0.5, 0.5]]).unwrap();
        b.append_change(&path, "c").unwrap();
        let journal = fs::read(journal_path(&path)).unwrap();
        let last = first..journal.len();
        // A bit flipped at every byte of the last record but its newline (checksum, space,
        // JSON): refused, never loaded without it.
        for i in last.start..last.end - 1 {
            let mut bad = journal.clone();
            bad[i] ^= 0x04;
            fs::write(journal_path(&path), &bad).unwrap();
            match ClassBank::load_with_journal(&path) {
                Err(LoadBankError::Journal { detail, .. }) => {
                    assert!(detail.contains("the last one"), "byte {i}: {detail}")
                }
                other => panic!("byte {i}: {other:?}"),
            }
        }
        // Its newline damaged: the record is whole, so this is damage too.
        let mut bad = journal.clone();
        *bad.last_mut().unwrap() = b'x';
        fs::write(journal_path(&path), &bad).unwrap();
        assert!(matches!(
            ClassBank::load_with_journal(&path),
            Err(LoadBankError::Journal { .. })
        ));
        // Cut before its newline: a torn append, ignored and reported.
        fs::write(journal_path(&path), &journal[..journal.len() - 1]).unwrap();
        let (l, r) = ClassBank::load_with_journal(&path).unwrap();
        assert_eq!(names(&l), ["a", "b"]);
        assert_eq!(r.torn_bytes as usize, last.len() - 1);
    }
}
