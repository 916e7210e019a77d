//! The screen: model, class bank and statistics, and the dispatch of one decoded request to
//! its operation. Transport-free, so every request path is testable without iceoryx2. A
//! check runs the models' one check pipeline (`guardian_screen::check`); state loading is
//! in `state.rs`, the statistics in `stats.rs`.

use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::time::Duration;

use guardian_bank::{BankLimits, Class, ClassBank, journal_path};
use guardian_models::embedder::{EmbedError, Embedder};
use guardian_screen::check::{self, EnrollmentError, Prepared, Station};
use guardian_shared::trajectory::{InvalidTrajectory, Waypoint};
use guardian_shared::verdict::Verdict;
use guardian_shared::wire::{
    ClassEntry, DaemonState, Failure, Limit, MAX_RESPONSE_ENTRIES, Op, Request, RequestHeader,
    ResponseHeader, RobotInfo, decode_code, encode_check, encode_failure, encode_state,
    encode_text,
};

use crate::stats::Stats;

/// Model, robot, bank and statistics of a running daemon.
#[derive(Debug)]
pub struct Screen {
    /// The embedding network.
    embedder: Embedder,
    /// The robot served and its workcell rules, resolved once (at start and on reload).
    station: Station,
    bank: ClassBank,
    bank_path: PathBuf,
    k: usize,
    stats: Stats,
    /// Bounds checked before an enroll changes anything.
    limits: BankLimits,
    /// Enroll and forget only through the admin endpoint ([`Screen::handle_admin`]).
    admin_separation: bool,
    /// Bytes of class data in the bank ([`ClassBank::classes_bytes`]), kept up to date.
    bank_bytes: u64,
    /// Size of the journal next to the snapshot.
    journal_bytes: u64,
    /// The journal is known to be intact (after a failed append it may hold a torn tail;
    /// the next change then writes a snapshot instead).
    journal_ok: bool,
    /// The journal outgrew its bound; compact at the next [`Screen::maintain`].
    compact_pending: bool,
    /// Entries a status answer carries: the fleet position of a fleet member (one entry
    /// per signer, `docs/wire-protocol.md` §10), empty otherwise.
    status_entries: Vec<ClassEntry>,
    /// Status answers end with the bank digest entry ([`BANK_DIGEST_PREFIX`]).
    report_bank_digest: bool,
    /// SHA-256 of each class's name and state, computed when first needed and dropped when
    /// the class changes ([`Screen::bank_digest`]).
    class_digests: std::collections::HashMap<String, [u8; 32]>,
}

/// Name prefix of the status entry carrying the bank digest (`docs/wire-protocol.md` §10):
/// `bank:` and the first 16 bytes of [`Screen::bank_digest`] in hex.
pub const BANK_DIGEST_PREFIX: &str = "bank:";

/// The journal is compacted into the snapshot once it is larger than the bank's class data
/// and at least this large (so amortised persistence stays O(the change)).
pub const MIN_JOURNAL_COMPACT_BYTES: u64 = 1 << 20;

/// Limits used until [`Screen::set_limits`] (the config's defaults).
pub const DEFAULT_LIMITS: BankLimits = BankLimits {
    max_classes: 4096,
    max_examples_per_class: 64,
    max_bytes: 256 << 20,
};

/// One answered request: the response and its entries as sent, and for a check the verdict
/// or the failure it was answered with, typed (what the record and the metrics observe).
#[derive(Debug, Clone)]
pub struct Answer {
    /// The response header.
    pub response: ResponseHeader,
    /// The response's entries.
    pub entries: Vec<ClassEntry>,
    /// A check's verdict, or why it has none (`None` for every other op).
    pub check: Option<Result<Verdict, Failure>>,
}

/// A prepared check plan handed from a batch to its answer.
type PreparedPlan = Result<Prepared, EmbedError>;

/// Where a change accepted on the admin path is made durable *before* the bank journals
/// it: a fleet member's record store (`docs/fleet.md`, "Persistence and crashes"). The bank
/// change is made in memory first (nothing is served meanwhile: the serving loop is busy
/// with this request), then [`ChangeLog::record`], then the bank's journal, then
/// [`ChangeLog::committed`]; so every change the bank holds on disk has its record, and a
/// crash between the steps leaves a record the next start applies (never a bank change
/// without a record, which no peer would ever receive).
pub trait ChangeLog {
    /// Make the change durable: class `class` is now `state` (`None`: forgotten). An error
    /// refuses the change (the bank is left as it was).
    fn record(&mut self, class: &str, state: Option<&Class>) -> Result<(), String>;
    /// The bank could not persist the change just recorded: take the record back.
    fn retract(&mut self, class: &str);
    /// The bank persisted the change: publish it.
    fn committed(&mut self, class: &str);
}

impl Screen {
    /// A screen serving `bank` with `embedder` for `station`'s robot and workcell,
    /// persisting the bank to `bank_path`.
    pub fn new(
        embedder: Embedder,
        station: Station,
        bank: ClassBank,
        bank_path: PathBuf,
        k: usize,
    ) -> Self {
        let mut s = Self {
            embedder,
            station,
            bank_bytes: bank.classes_bytes(),
            bank,
            journal_bytes: 0,
            bank_path,
            k,
            stats: Stats::default(),
            limits: DEFAULT_LIMITS,
            admin_separation: false,
            journal_ok: true,
            compact_pending: false,
            status_entries: Vec::new(),
            report_bank_digest: false,
            class_digests: std::collections::HashMap::new(),
        };
        s.journal_bytes = s.journal_len();
        s
    }

    /// Set the bank limits (default [`DEFAULT_LIMITS`]).
    pub fn set_limits(&mut self, limits: BankLimits) {
        self.limits = limits;
    }

    /// Refuse enroll and forget from planners ([`Screen::handle`], [`Screen::handle_batch`])
    /// with `NotPermitted`; the admin endpoint ([`Screen::handle_admin`]) still serves them.
    pub fn set_admin_separation(&mut self, on: bool) {
        self.admin_separation = on;
    }

    fn journal_len(&self) -> u64 {
        std::fs::metadata(journal_path(&self.bank_path)).map_or(0, |m| m.len())
    }

    /// The robot and workcell rules in use.
    pub fn station(&self) -> &Station {
        &self.station
    }

    /// The model in use.
    pub fn embedder(&self) -> &Embedder {
        &self.embedder
    }
    /// The bank in use.
    pub fn bank(&self) -> &ClassBank {
        &self.bank
    }
    /// Where the bank is persisted.
    pub fn bank_path(&self) -> &Path {
        &self.bank_path
    }

    /// Replace model, robot and bank (after a successful reload).
    pub fn replace(&mut self, embedder: Embedder, station: Station, bank: ClassBank, k: usize) {
        self.embedder = embedder;
        self.station = station;
        self.bank_bytes = bank.classes_bytes();
        self.bank = bank;
        self.k = k;
        self.journal_bytes = self.journal_len();
        self.journal_ok = true;
        self.class_digests.clear();
    }

    /// Record the service time of one answered request.
    pub fn record_latency(&mut self, d: Duration) {
        self.stats.record_latency(d);
    }

    /// One-line status for logs and `STATUS=`.
    pub fn summary(&self) -> String {
        format!(
            "serving {} classes (bank v{}), model {}",
            self.bank.len(),
            self.bank.generation(),
            self.embedder.version()
        )
    }

    /// Answer several queued requests. Each is decoded once; the checks among them are
    /// prepared together (one forward pass, see [`check::prepare_batch`]); every request is
    /// then answered in order exactly as by [`Screen::handle`], each check decided against
    /// the bank as it stands at its turn (errors are reported per request, never turned
    /// into a verdict).
    pub fn handle_batch(&mut self, items: &[(RequestHeader, &[f32])]) -> Vec<Answer> {
        let requests: Vec<_> = items
            .iter()
            .map(|(h, p)| self.decode(h, p, false))
            .collect();
        let plans: Vec<&[Waypoint]> = requests.iter().filter_map(plan_of).collect();
        let mut prepared = check::prepare_batch(&self.embedder, &self.station, &plans).into_iter();
        items
            .iter()
            .zip(requests)
            .map(|((h, _), request)| {
                let p = plan_of(&request).and_then(|_| prepared.next());
                self.answer(h, request, p)
            })
            .collect()
    }

    /// Answer one planner request. Never panics on input; errors become error statuses.
    pub fn handle(&mut self, h: &RequestHeader, payload: &[f32]) -> Answer {
        let request = self.decode(h, payload, false);
        self.answer(h, request, None)
    }

    /// Answer one request from the admin endpoint (a caller whose credentials were
    /// checked): every op, enroll and forget included, whatever the admin separation.
    pub fn handle_admin(&mut self, h: &RequestHeader, payload: &[f32]) -> Answer {
        self.handle_admin_logged(h, payload, None)
    }

    /// [`Screen::handle_admin`], with an enroll's or forget's change made durable in `log`
    /// before the bank journals it ([`ChangeLog`]).
    pub fn handle_admin_logged(
        &mut self,
        h: &RequestHeader,
        payload: &[f32],
        log: Option<&mut dyn ChangeLog>,
    ) -> Answer {
        let request = self.decode(h, payload, true);
        self.answer_logged(h, request, None, log)
    }

    /// Answer one request from a remote caller (authenticated by the fleet transport): check,
    /// identify and status only; every other op is refused with `NotPermitted` from its
    /// header alone, whatever the admin separation.
    pub fn handle_remote(&mut self, h: &RequestHeader, payload: &[f32]) -> Answer {
        let request = if matches!(
            decode_code::<Op>(h.op),
            Some(Op::Check | Op::Identify | Op::Status)
        ) {
            self.decode(h, payload, false)
        } else {
            Err(Failure::NotPermitted {
                message: "remote callers may check, identify and ask status only".into(),
            })
        };
        self.answer(h, request, None)
    }

    /// The entries a status answer carries (a fleet member's position).
    pub fn status_entries(&self) -> &[ClassEntry] {
        &self.status_entries
    }

    /// Set the entries a status answer carries (a fleet member's position).
    pub fn set_status_entries(&mut self, entries: Vec<ClassEntry>) {
        self.status_entries = entries;
    }

    /// End every status answer with the bank digest entry (a fleet member's, so that two
    /// members whose banks differ never report the same position).
    pub fn set_report_bank_digest(&mut self, on: bool) {
        self.report_bank_digest = on;
    }

    /// SHA-256 over what decides a check besides the model: the bank's global default
    /// threshold (`f32` bits, little-endian), its calibration and geometry calibration (as
    /// JSON, `null` if none), then every class in name order, each as the SHA-256 of its
    /// name's length (`u64` little-endian), its name and its state as JSON (as a fleet
    /// record carries it). Equal banks, equal digests; after a change only the changed
    /// class is encoded again.
    pub fn bank_digest(&mut self) -> [u8; 32] {
        use sha2::{Digest, Sha256};
        let mut all = Sha256::new();
        all.update(self.bank.default_threshold().to_bits().to_le_bytes());
        all.update(serde_json::to_vec(&self.bank.calibration()).unwrap_or_default());
        all.update(serde_json::to_vec(&self.bank.geometry_calibration()).unwrap_or_default());
        for (name, class) in self.bank.classes() {
            let d = self
                .class_digests
                .entry(name.to_owned())
                .or_insert_with(|| {
                    let mut h = Sha256::new();
                    h.update((name.len() as u64).to_le_bytes());
                    h.update(name.as_bytes());
                    // Serialising plain numbers and strings cannot fail; an error would
                    // leave the class's part empty, which still differs from a served state.
                    h.update(serde_json::to_vec(class).unwrap_or_default());
                    h.finalize().into()
                });
            all.update(*d);
        }
        all.finalize().into()
    }

    fn status_answer(&mut self) -> Vec<ClassEntry> {
        let mut entries = self.status_entries.clone();
        if self.report_bank_digest {
            let d = self.bank_digest();
            let hex: String = d[..16].iter().map(|b| format!("{b:02x}")).collect();
            entries.push(ClassEntry {
                name: encode_text(&format!("{BANK_DIGEST_PREFIX}{hex}")),
                distance: f32::NAN,
                threshold: f32::NAN,
                examples: u32::try_from(self.bank.len()).unwrap_or(u32::MAX),
                calibrated: 0,
            });
        }
        entries
    }

    /// Apply a change replicated from another member: class `name` becomes `class`
    /// (`None`: forgotten), checked like an enroll and within the bank limits, persisted
    /// before it is served. On any failure nothing changes and the error says why.
    pub fn apply_replicated(&mut self, name: &str, class: Option<Class>) -> Result<(), Failure> {
        let generation = self.bank.generation();
        let before = self.bank.class_bytes(name);
        let previous = match class {
            Some(class) => {
                self.limits
                    .check_class(&self.bank, name, class.embeddings.len())
                    .map_err(limit_exceeded)?;
                self.bank
                    .put_class(name, class)
                    .map_err(|e| Failure::BadRequest {
                        message: format!("replicated class {name:?} refused: {e}"),
                    })?
            }
            None => match self.bank.forget(name) {
                Some(c) => Some(c),
                // Already absent: nothing to do.
                None => return Ok(()),
            },
        };
        let after = self.bank_bytes.saturating_sub(before) + self.bank.class_bytes(name);
        if let Err(limit) = self.limits.check_bytes(after) {
            self.bank.undo_change(name, previous, generation);
            return Err(limit_exceeded(limit));
        }
        self.persist(name, previous, generation, after, None)?;
        tracing::info!(class = %name, bank = self.bank.generation(), "applied a replicated change");
        Ok(())
    }

    /// Decode a request; under admin separation a planner's enroll or forget is refused
    /// from its header alone, before its payload is looked at.
    fn decode<'a>(
        &self,
        h: &'a RequestHeader,
        payload: &'a [f32],
        admin: bool,
    ) -> Result<Request<'a>, Failure> {
        if !admin
            && self.admin_separation
            && matches!(decode_code::<Op>(h.op), Some(Op::Enroll | Op::Forget))
        {
            return Err(Failure::NotPermitted {
                message: "enroll and forget are admin operations here: use the admin socket".into(),
            });
        }
        Request::decode(h, payload, self.station.robot().joints()).map_err(|e| Failure::from(&e))
    }

    /// Dispatch a decoded request to its operation and write the response.
    fn answer(
        &mut self,
        h: &RequestHeader,
        request: Result<Request<'_>, Failure>,
        prepared: Option<PreparedPlan>,
    ) -> Answer {
        self.answer_logged(h, request, prepared, None)
    }

    /// [`Screen::answer`], with changes made durable in `log` first.
    fn answer_logged(
        &mut self,
        h: &RequestHeader,
        request: Result<Request<'_>, Failure>,
        prepared: Option<PreparedPlan>,
        log: Option<&mut dyn ChangeLog>,
    ) -> Answer {
        let mut r = ResponseHeader::answering(h);
        let mut verdict = None;
        let result = match request {
            Err(f) => Err(f),
            Ok(Request::Check {
                claimed,
                trajectory,
            }) => self.check(claimed, trajectory, prepared).map(|v| {
                encode_check(&mut r, &v);
                // With WrongTask the nearest class is the overall nearest, so it is entries[0].
                let entries = v
                    .nearest
                    .iter()
                    .map(|n| self.entry(&n.class, n.distance))
                    .collect();
                verdict = Some(v);
                entries
            }),
            Ok(Request::Identify { trajectory }) => self.identify(&trajectory),
            Ok(Request::Enroll { class, examples }) => self.enroll(class, &examples, log),
            Ok(Request::Forget { class }) => self.forget(class, log),
            Ok(Request::Classes { first }) => Ok(self.class_list(first)),
            Ok(Request::Status) => Ok(self.status_answer()),
        };
        // Every response chunk holds at most MAX_RESPONSE_ENTRIES entries (the class list is
        // paged, k-nearest is bounded); a longer answer (a fleet of more signers) is refused
        // whole rather than cut.
        let result = result.and_then(|e| {
            if e.len() > MAX_RESPONSE_ENTRIES {
                Err(Failure::Internal {
                    message: format!(
                        "answer of {} entries, more than a response holds ({MAX_RESPONSE_ENTRIES})",
                        e.len()
                    ),
                })
            } else {
                Ok(e)
            }
        });
        let (entries, check) = match result {
            Ok(e) => (e, verdict.map(Ok)),
            Err(failure) => {
                encode_failure(&mut r, &failure);
                let check = (decode_code::<Op>(h.op) == Some(Op::Check)).then_some(Err(failure));
                (Vec::new(), check)
            }
        };
        self.stats.count(r.status != 0, r.verdict);
        // Status answers fresh percentiles; other responses carry ones at most a second old.
        let latency_us = self
            .stats
            .latency_us(decode_code::<Op>(h.op) == Some(Op::Status));
        let counters = self.stats.counters();
        encode_state(
            &mut r,
            &DaemonState {
                model_version: Cow::Borrowed(self.embedder.version()),
                bank_version: self.bank.generation(),
                class_count: u32::try_from(self.bank.len()).unwrap_or(u32::MAX),
                uptime_ms: self.stats.uptime_ms(),
                requests: counters.requests,
                errors: counters.errors,
                go: counters.go,
                no_go: counters.no_go,
                latency_us,
                robot: RobotInfo {
                    name: Cow::Borrowed(self.station.robot().name()),
                    joints: self.station.robot().joints() as u32,
                    urdf_sha256: *self.station.robot().urdf_sha256(),
                },
            },
        );
        Answer {
            response: r,
            entries,
            check,
        }
    }

    fn check(
        &self,
        claimed: &str,
        trajectory: Result<Vec<Waypoint>, InvalidTrajectory>,
        prepared: Option<PreparedPlan>,
    ) -> Result<Verdict, Failure> {
        // A trajectory whose shape the request already refused is decided as invalid.
        let prepared = match trajectory {
            Err(inv) => Prepared::Invalid(inv),
            Ok(t) => prepared
                .unwrap_or_else(|| check::prepare(&self.embedder, &self.station, &t))
                .map_err(|e| {
                    tracing::error!(error = %e, "embedding failed");
                    embedding_failed(&e)
                })?,
        };
        Ok(check::decide(
            &self.bank,
            &self.station,
            &prepared,
            claimed,
            self.k,
        ))
    }

    fn identify(&self, t: &[Waypoint]) -> Result<Vec<ClassEntry>, Failure> {
        let e = check::embed_plan(&self.embedder, &self.station, t)
            .map_err(|e| {
                tracing::error!(error = %e, "embedding failed");
                embedding_failed(&e)
            })?
            .map_err(|inv| invalid(inv, 0))?;
        if self.bank.is_empty() {
            return Err(Failure::EmptyBank {
                message: "no classes enrolled".into(),
            });
        }
        // An anchored cell names the nearest task among those where the plan happens.
        let ranked = match &e.place {
            Some(place) => {
                let mut r =
                    self.bank
                        .ranked_in_place(&e.embedding, place, &self.station.cell().place);
                r.truncate(self.k);
                r
            }
            None => self.bank.nearest(&e.embedding, self.k),
        };
        Ok(ranked
            .iter()
            .map(|n| self.entry(&n.name, n.distance))
            .collect())
    }

    fn enroll(
        &mut self,
        name: &str,
        ts: &[Vec<Waypoint>],
        log: Option<&mut dyn ChangeLog>,
    ) -> Result<Vec<ClassEntry>, Failure> {
        // Counts first: a refused enroll costs no embedding and changes nothing.
        self.limits
            .check_counts(&self.bank, name, ts.len())
            .map_err(limit_exceeded)?;
        // Validated, resampled and embedded by the models' pipeline (rules off); the
        // resampled plans are kept so that the class survives a new model.
        let enrollment =
            check::enrollment(&self.embedder, &self.station, ts).map_err(|e| match e {
                EnrollmentError::Invalid { index, source } => invalid(source, index),
                EnrollmentError::Embed(e) => {
                    tracing::error!(error = %e, "embedding failed");
                    embedding_failed(&e)
                }
                other => Failure::Internal {
                    message: other.to_string(),
                },
            })?;
        // The change is made in place (no copy of the bank) and undone if it breaks the
        // size limit or cannot be persisted.
        let previous = self.bank.class(name).cloned();
        let generation = self.bank.generation();
        let before = self.bank.class_bytes(name);
        self.bank
            .enroll_placed(
                name,
                &enrollment.embeddings,
                &enrollment.geometry,
                &enrollment.examples,
                &enrollment.place,
            )
            .map_err(|e| Failure::Internal {
                message: e.to_string(),
            })?;
        let after = self.bank_bytes.saturating_sub(before) + self.bank.class_bytes(name);
        if let Err(limit) = self.limits.check_bytes(after) {
            self.bank.undo_change(name, previous, generation);
            return Err(limit_exceeded(limit));
        }
        self.persist(name, previous, generation, after, log)?;
        tracing::info!(class = %name, examples = enrollment.embeddings.len(), bank = self.bank.generation(), "enrolled");
        Ok(vec![self.entry(name, f32::NAN)])
    }

    fn forget(
        &mut self,
        name: &str,
        log: Option<&mut dyn ChangeLog>,
    ) -> Result<Vec<ClassEntry>, Failure> {
        let generation = self.bank.generation();
        let before = self.bank.class_bytes(name);
        let Some(previous) = self.bank.forget(name) else {
            return Err(Failure::UnknownClass {
                message: format!("class {name:?} is not enrolled"),
            });
        };
        let after = self.bank_bytes.saturating_sub(before);
        self.persist(name, Some(previous), generation, after, log)?;
        tracing::info!(class = %name, bank = self.bank.generation(), "forgot class");
        Ok(Vec::new())
    }

    /// Persist the change just made to class `name` (append it to the journal; write a
    /// snapshot if there is none yet or the journal may be damaged), before it is
    /// acknowledged; with a `log`, the change is recorded there first and committed after
    /// ([`ChangeLog`]). On failure the change is undone (and its record retracted): the old
    /// bank stays served.
    fn persist(
        &mut self,
        name: &str,
        previous: Option<Class>,
        generation: u64,
        bank_bytes: u64,
        mut log: Option<&mut dyn ChangeLog>,
    ) -> Result<(), Failure> {
        if let Some(log) = log.as_deref_mut()
            && let Err(e) = log.record(name, self.bank.class(name))
        {
            tracing::error!(class = %name, error = %e, "cannot record the change for the fleet; change rejected, bank unchanged");
            self.bank.undo_change(name, previous, generation);
            return Err(Failure::Storage {
                message: format!("cannot persist the fleet record: {e}"),
            });
        }
        let result = if self.journal_ok && self.bank_path.exists() {
            self.bank
                .append_change(&self.bank_path, name)
                .map(|len| self.journal_bytes = len)
        } else {
            self.snapshot()
        };
        if let Err(e) = result {
            tracing::error!(class = %name, error = %e, "cannot persist class bank; change rejected, bank unchanged");
            self.journal_ok = false;
            self.bank.undo_change(name, previous, generation);
            if let Some(log) = log.as_deref_mut() {
                log.retract(name);
            }
            return Err(Failure::Storage {
                message: format!("cannot persist class bank: {e}"),
            });
        }
        crate::faults::hit(crate::faults::AFTER_JOURNAL);
        self.class_digests.remove(name);
        self.bank_bytes = bank_bytes;
        if self.journal_bytes > MIN_JOURNAL_COMPACT_BYTES.max(self.bank_bytes) {
            self.compact_pending = true;
        }
        if let Some(log) = log {
            log.committed(name);
        }
        Ok(())
    }

    /// Work the serving loop does between requests: compact the journal into the snapshot
    /// once it outgrew its bound. A failed compaction is logged and retried after the next
    /// change; the journal stays valid meanwhile.
    pub fn maintain(&mut self) {
        if !self.compact_pending {
            return;
        }
        self.compact_pending = false;
        let start = std::time::Instant::now();
        let journal_bytes = self.journal_bytes;
        match self.snapshot() {
            Ok(()) => {
                tracing::info!(
                    journal_bytes,
                    millis = start.elapsed().as_millis() as u64,
                    "compacted the bank journal into the snapshot"
                );
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot compact the bank journal; it stays in use")
            }
        }
    }

    /// Bytes of the journal next to the snapshot.
    pub fn journal_bytes(&self) -> u64 {
        self.journal_bytes
    }

    /// Whether a journal file lies next to the snapshot, even an empty one (a daemon killed
    /// after creating it and before its first record was written).
    pub fn has_journal(&self) -> bool {
        journal_path(&self.bank_path).exists()
    }

    /// Save the bank now as a snapshot and remove its journal (at start and shutdown; every
    /// change is already persisted).
    pub fn flush(&mut self) -> Result<(), guardian_bank::SaveBankError> {
        if self.bank.generation() == 0 && !self.bank_path.exists() {
            return Ok(());
        }
        self.snapshot()
    }

    /// Write the bank as a snapshot, which removes its journal.
    fn snapshot(&mut self) -> Result<(), guardian_bank::SaveBankError> {
        self.bank.save(&self.bank_path)?;
        self.journal_bytes = 0;
        self.journal_ok = true;
        Ok(())
    }

    /// One page of the class list: at most [`MAX_RESPONSE_ENTRIES`] classes from the
    /// `first`-th on (empty past the end).
    fn class_list(&self, first: usize) -> Vec<ClassEntry> {
        self.bank
            .classes()
            .skip(first)
            .take(MAX_RESPONSE_ENTRIES)
            .map(|(n, _)| self.entry(n, f32::NAN))
            .collect()
    }

    fn entry(&self, name: &str, distance: f32) -> ClassEntry {
        let class = self.bank.class(name);
        ClassEntry {
            name: encode_text(name),
            distance,
            // The threshold the decision uses (`ClassBank::threshold`), from the one lookup.
            threshold: class.map_or(f32::NAN, |c| {
                c.threshold.unwrap_or(self.bank.default_threshold())
            }),
            examples: class.map_or(0, |c| u32::try_from(c.embeddings.len()).unwrap_or(u32::MAX)),
            calibrated: u32::from(class.is_some_and(|c| c.threshold.is_some())),
        }
    }
}

/// The plan of a check request whose trajectory has a valid shape (the ones a batch
/// prepares).
fn plan_of<'b>(request: &'b Result<Request<'_>, Failure>) -> Option<&'b [Waypoint]> {
    match request {
        Ok(Request::Check {
            trajectory: Ok(t), ..
        }) => Some(t.as_slice()),
        _ => None,
    }
}

/// An enroll refused by a limit.
fn limit_exceeded(limit: Limit) -> Failure {
    Failure::LimitExceeded {
        message: format!(
            "{} = {} reached: the bank would hold {}; nothing changed",
            limit.kind.key(),
            limit.max,
            limit.requested
        ),
        limit,
    }
}

/// Example `example` of the request failed validation.
fn invalid(inv: InvalidTrajectory, example: u32) -> Failure {
    Failure::InvalidTrajectory {
        invalid: inv,
        example,
        message: inv.to_string(),
    }
}

fn embedding_failed(e: &EmbedError) -> Failure {
    Failure::Internal {
        message: format!("embedding failed: {e}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_client::samples::task;
    use guardian_shared::wire::{ReasonCode, VerdictCode, encode_class_name};
    use guardian_shared::workcell::Workcell;

    fn request(op: Op, class: &str, t: &[Waypoint]) -> (RequestHeader, Vec<f32>) {
        let mut h = RequestHeader::new(7, op);
        h.channels = 8;
        h.examples = 1;
        h.waypoints[0] = t.len() as u32;
        h.class_name = encode_class_name(class).unwrap();
        (h, guardian_shared::trajectory::to_flat(t, 7))
    }

    /// A batch answers every request exactly as one-by-one handling does: valid checks,
    /// an invalid trajectory, an unknown class and a non-check op mixed together.
    #[test]
    fn batched_checks_answer_like_single_ones() {
        let dir = tempfile::tempdir().unwrap();
        let embedder = Embedder::random(3);
        // The synthetic tasks are joint-space patterns, not drawings on the canvas.
        let station = Station::panda().with_workcell(Workcell::OFF);
        let mut bank = ClassBank::new(
            guardian_models::embedder::EMBED_DIM,
            embedder.version(),
            0.8,
        );
        for c in 0..3 {
            let es: Vec<Vec<f32>> = (0..4)
                .map(|d| {
                    let e = check::embed_plan(&embedder, &station, &task(c, d));
                    e.unwrap().unwrap().embedding.to_vec()
                })
                .collect();
            bank.enroll(&format!("task{c}"), &es).unwrap();
        }
        let mut screen = Screen::new(embedder, station, bank, dir.path().join("bank.gcb"), 3);
        let mut bad = task(1, 9);
        bad[5][0] = 99.0;
        let reqs = [
            request(Op::Check, "task0", &task(0, 9)),
            request(Op::Check, "task1", &task(2, 9)),
            request(Op::Check, "task1", &bad),
            request(Op::Identify, "any", &task(1, 8)),
            request(Op::Check, "nope", &task(2, 8)),
            request(Op::Check, "task2", &task(2, 10)),
        ];
        let items: Vec<(RequestHeader, &[f32])> =
            reqs.iter().map(|(h, p)| (*h, p.as_slice())).collect();
        let batched = screen.handle_batch(&items);
        assert_eq!(batched.len(), reqs.len());
        let mut go = 0;
        for ((h, p), b) in reqs.iter().zip(&batched) {
            let (rb, eb) = (&b.response, &b.entries);
            let single = screen.handle(h, p);
            let (r1, e1) = (single.response, single.entries);
            assert_eq!(
                (rb.status, rb.verdict, rb.reason),
                (r1.status, r1.verdict, r1.reason)
            );
            let decision = |c: &Option<Result<Verdict, Failure>>| {
                c.as_ref()
                    .and_then(|c| c.as_ref().ok())
                    .map(|v| v.decision.clone())
            };
            assert_eq!(decision(&b.check), decision(&single.check));
            go += usize::from(rb.verdict == VerdictCode::Go as u32);
            let close = |a: f32, b: f32| (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-5;
            assert!(close(rb.claimed_distance, r1.claimed_distance));
            assert_eq!(eb.len(), e1.len());
            for (a, b) in eb.iter().zip(&e1) {
                assert_eq!(a.name, b.name);
                assert!(close(a.distance, b.distance));
            }
        }
        assert!(go >= 1, "some checks should pass");
        assert_eq!(
            batched[2].response.reason,
            ReasonCode::InvalidTrajectory as u32
        );
        assert_eq!(batched[4].response.reason, ReasonCode::UnknownClass as u32);
    }

    /// A remote caller may check, identify and ask status, never enroll or forget; a
    /// replicated class is applied whole, persisted, and a malformed one changes nothing.
    #[test]
    fn remote_requests_and_replicated_changes() {
        let dir = tempfile::tempdir().unwrap();
        let embedder = Embedder::random(3);
        let station = Station::panda().with_workcell(Workcell::OFF);
        let bank = ClassBank::new(
            guardian_models::embedder::EMBED_DIM,
            embedder.version(),
            0.8,
        );
        let path = dir.path().join("bank.gcb");
        let mut screen = Screen::new(embedder, station, bank, path.clone(), 3);
        let (mut h, p) = request(Op::Enroll, "task0", &task(0, 1));
        let r = screen.handle_remote(&h, &p).response;
        assert_eq!(r.status, guardian_shared::wire::Status::NotPermitted as u32);
        h.op = Op::Forget as u32;
        let r = screen.handle_remote(&h, &[]).response;
        assert_eq!(r.status, guardian_shared::wire::Status::NotPermitted as u32);
        assert!(screen.bank().is_empty());
        // Enrolled by the admin path, the class is what a record would carry.
        let (h, p) = request(Op::Enroll, "task0", &task(0, 1));
        assert_eq!(screen.handle_admin(&h, &p).response.status, 0);
        let class = screen.bank().class("task0").cloned().unwrap();
        // Applied elsewhere under another name: served and persisted.
        screen
            .apply_replicated("copy", Some(class.clone()))
            .unwrap();
        let (h, p) = request(Op::Check, "copy", &task(0, 1));
        let a = screen.handle_remote(&h, &p);
        assert_eq!(a.response.status, 0);
        assert!(matches!(a.check, Some(Ok(_))));
        let (loaded, _) = ClassBank::load_with_journal(&path).unwrap();
        assert_eq!(loaded.class("copy"), Some(&class));
        // A class of the wrong dimension is refused; nothing changes.
        let mut bad = class.clone();
        bad.prototype.pop();
        let generation = screen.bank().generation();
        assert!(screen.apply_replicated("bad", Some(bad)).is_err());
        assert_eq!(screen.bank().generation(), generation);
        assert!(screen.bank().class("bad").is_none());
        // A replicated forget removes it; forgetting an absent class is a no-op.
        screen.apply_replicated("copy", None).unwrap();
        assert!(screen.bank().class("copy").is_none());
        screen.apply_replicated("never", None).unwrap();
        // Status carries the entries set by the fleet member.
        screen.set_status_entries(vec![screen.entry("task0", f32::NAN)]);
        let h = RequestHeader::new(8, Op::Status);
        let a = screen.handle_remote(&h, &[]);
        assert_eq!((a.response.status, a.entries.len()), (0, 1));
        assert!(a.check.is_none());
    }
}
