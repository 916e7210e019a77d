//! Bounds on the bank's growth, checked before an enroll changes or writes anything: the
//! number of classes, the examples of one class and the bank's size in bytes (counted as the
//! classes' JSON in the snapshot, so the persisted files stay bounded too).

use guardian_shared::wire::{Limit, LimitKind};

use super::ClassBank;

/// The configured limits (`max-classes`, `max-examples-per-class`, `max-bank-bytes`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BankLimits {
    /// Most classes in the bank.
    pub max_classes: usize,
    /// Most examples of one class.
    pub max_examples_per_class: usize,
    /// Most bytes of class data ([`ClassBank::class_bytes`] summed over the classes).
    pub max_bytes: u64,
}

impl BankLimits {
    /// Would adding `examples` examples to class `name` keep the class and example counts
    /// within the limits? Cheap: call it before embedding anything.
    pub fn check_counts(&self, bank: &ClassBank, name: &str, examples: usize) -> Result<(), Limit> {
        let existing = bank.class(name).map_or(0, |c| c.embeddings.len());
        self.check_class(bank, name, existing + examples)
    }

    /// Would class `name` holding `examples` examples in all (new, or replacing what the bank
    /// holds) keep the class and example counts within the limits?
    pub fn check_class(&self, bank: &ClassBank, name: &str, examples: usize) -> Result<(), Limit> {
        let classes = bank.len() + usize::from(bank.class(name).is_none());
        if classes > self.max_classes {
            return Err(Limit {
                kind: LimitKind::Classes,
                max: self.max_classes as u64,
                requested: classes as u64,
            });
        }
        if examples > self.max_examples_per_class {
            return Err(Limit {
                kind: LimitKind::ExamplesPerClass,
                max: self.max_examples_per_class as u64,
                requested: examples as u64,
            });
        }
        Ok(())
    }

    /// Is a bank of `bytes` bytes of class data within the limit?
    pub fn check_bytes(&self, bytes: u64) -> Result<(), Limit> {
        if bytes > self.max_bytes {
            return Err(Limit {
                kind: LimitKind::BankBytes,
                max: self.max_bytes,
                requested: bytes,
            });
        }
        Ok(())
    }
}

impl ClassBank {
    /// Bytes class `name` takes in the snapshot (its JSON entry), 0 if not enrolled.
    /// O(the class).
    pub fn class_bytes(&self, name: &str) -> u64 {
        self.classes.get(name).map_or(0, |c| {
            let body = serde_json::to_vec(c).map_or(0, |v| v.len());
            // "name": {...},
            (body + name.len() + 4) as u64
        })
    }

    /// [`ClassBank::class_bytes`] of every class. O(the bank): call it at load.
    pub fn classes_bytes(&self) -> u64 {
        self.classes.keys().map(|n| self.class_bytes(n)).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_bytes_are_checked_against_the_limits() {
        let mut b = ClassBank::new(2, "m", 0.5);
        b.enroll("a", &[vec![0.0, 1.0], vec![1.0, 0.0]]).unwrap();
        let l = BankLimits {
            max_classes: 1,
            max_examples_per_class: 3,
            max_bytes: 10_000,
        };
        assert_eq!(l.check_counts(&b, "a", 1), Ok(()));
        let e = l.check_counts(&b, "a", 2).unwrap_err();
        assert_eq!(
            (e.kind, e.max, e.requested),
            (LimitKind::ExamplesPerClass, 3, 4)
        );
        let e = l.check_counts(&b, "b", 1).unwrap_err();
        assert_eq!((e.kind, e.max, e.requested), (LimitKind::Classes, 1, 2));
        let bytes = b.classes_bytes();
        assert!(bytes > 20 && bytes == b.class_bytes("a"), "{bytes}");
        assert!(b.to_bytes().unwrap().len() as u64 > bytes);
        assert_eq!(l.check_bytes(10_000), Ok(()));
        assert_eq!(
            l.check_bytes(10_001).unwrap_err().kind,
            LimitKind::BankBytes
        );
    }
}
