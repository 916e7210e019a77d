//! The screen: model + class bank + counters, and the handling of one decoded request.
//! Transport-free, so every request path is testable without iceoryx2.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use guardian_models::bank::{ClassBank, DEFAULT_THRESHOLD, Outcome};
use guardian_models::workcell::{self, Inspection};
use guardian_shared::trajectory::{CHANNELS, InvalidTrajectory, Waypoint, from_flat, validate};
use guardian_shared::wire::{
    ClassEntry, MAX_EXAMPLES, Op, ReasonCode, RequestHeader, ResponseHeader, Status, VerdictCode,
    decode_class_name, encode_text,
};
use guardian_shared::workcell::Workcell;

use crate::config::Config;
use crate::engine::Engine;

const LATENCY_WINDOW: usize = 4096;

/// Where the bank in use came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BankSource {
    /// The persisted bank in the state directory.
    State(PathBuf),
    /// The shipped or configured default bank.
    Default(PathBuf),
    /// Nothing found; an empty bank.
    Empty,
}

impl std::fmt::Display for BankSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::State(p) => write!(f, "persisted bank {}", p.display()),
            Self::Default(p) => write!(f, "default bank {}", p.display()),
            Self::Empty => write!(f, "empty bank"),
        }
    }
}

/// Loading the model or bank failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadStateError {
    /// The model could not be loaded.
    #[error("cannot load model {path}: {detail}")]
    Model {
        /// The weights file.
        path: PathBuf,
        /// Why.
        detail: String,
    },
    /// The bank could not be loaded.
    #[error("cannot load class bank {path}: {source}")]
    Bank {
        /// The bank file.
        path: PathBuf,
        /// Why.
        source: guardian_models::bank::LoadBankError,
    },
    /// The bank was built with another model.
    #[error(
        "class bank {path} was built with model {bank_model} ({bank_dim}-d) but the loaded model is {model} ({model_dim}-d); \
         re-enroll the classes or remove the file"
    )]
    BankModelMismatch {
        /// The bank file.
        path: PathBuf,
        /// Model version recorded in the bank.
        bank_model: String,
        /// Its embedding dimension.
        bank_dim: usize,
        /// The loaded model's version.
        model: String,
        /// The loaded model's dimension.
        model_dim: usize,
    },
}

/// Load the model named by `config`.
pub fn load_engine(config: &Config) -> Result<Engine, LoadStateError> {
    let path = config.model_path();
    Engine::load(&path).map_err(|e| LoadStateError::Model {
        path,
        detail: e.to_string(),
    })
}

/// Load the bank for `engine`: the persisted one, else the default one, else empty.
pub fn load_bank(
    config: &Config,
    engine: &Engine,
) -> Result<(ClassBank, BankSource), LoadStateError> {
    let state = config.bank_path();
    let load = |path: &PathBuf| {
        ClassBank::load(path).map_err(|source| LoadStateError::Bank {
            path: path.clone(),
            source,
        })
    };
    let (mut bank, source) = if state.exists() {
        (load(&state)?, BankSource::State(state))
    } else if let Some(p) = config.default_bank_path() {
        (load(&p)?, BankSource::Default(p))
    } else {
        let t = config.default_threshold.unwrap_or(DEFAULT_THRESHOLD);
        (
            ClassBank::new(engine.dim(), engine.version(), t),
            BankSource::Empty,
        )
    };
    if bank.dim() != engine.dim() || bank.model_version() != engine.version() {
        let path = match &source {
            BankSource::State(p) | BankSource::Default(p) => p.clone(),
            BankSource::Empty => PathBuf::new(),
        };
        return Err(LoadStateError::BankModelMismatch {
            path,
            bank_model: bank.model_version().to_owned(),
            bank_dim: bank.dim(),
            model: engine.version().to_owned(),
            model_dim: engine.dim(),
        });
    }
    if let Some(t) = config.default_threshold
        && t != bank.default_threshold()
    {
        bank.set_default_threshold(t);
    }
    let without = bank.classes_without_geometry();
    if bank.geometry_calibration().is_none() && !bank.is_empty() {
        tracing::warn!(%source, "class bank has no geometry calibration (format 1 or not calibrated): geometry check off");
    } else if !without.is_empty() {
        tracing::warn!(%source, classes = without.len(), first = without[0], "classes without plan-geometry descriptors (enrolled by format 1): geometry check off for them");
    }
    Ok((bank, source))
}

/// How long the latency percentiles reported with every response may be stale (sorting
/// the window on every request cost more than a check itself).
const LATENCY_REFRESH: Duration = Duration::from_secs(1);

/// Service times of the most recent requests.
#[derive(Debug, Default)]
struct Latencies(VecDeque<f32>);

impl Latencies {
    fn push(&mut self, d: Duration) {
        if self.0.len() == LATENCY_WINDOW {
            self.0.pop_front();
        }
        self.0.push_back(d.as_secs_f32() * 1e6);
    }

    /// p50, p90, p99, max in microseconds (NaN when empty).
    fn percentiles(&self) -> [f32; 4] {
        if self.0.is_empty() {
            return [f32::NAN; 4];
        }
        let mut v: Vec<f32> = self.0.iter().copied().collect();
        v.sort_by(f32::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        [q(0.5), q(0.9), q(0.99), v[v.len() - 1]]
    }
}

/// Counters since start.
#[derive(Debug, Default, Clone, Copy)]
struct Counters {
    requests: u64,
    errors: u64,
    go: u64,
    no_go: u64,
}

/// Model, bank and statistics of a running daemon.
#[derive(Debug)]
pub struct Screen {
    engine: Engine,
    bank: ClassBank,
    bank_path: PathBuf,
    k: usize,
    started: Instant,
    counters: Counters,
    latencies: Latencies,
    /// Percentiles of `latencies` and when they were computed.
    latency_summary: ([f32; 4], Option<Instant>),
    /// Inspection and embedding of the check being handled, computed beforehand in a batch.
    batched: Option<Prepared>,
    /// The workcell rules applied to every check.
    workcell: Workcell,
}

/// A check's trajectory after [`workcell::inspect`], with its embedding if already computed.
#[derive(Debug)]
struct Prepared {
    inspection: Inspection,
    embedding: Option<Vec<f32>>,
}

enum Fail {
    Status(Status, String),
    Invalid(InvalidTrajectory, u32),
}

impl Screen {
    /// A screen serving `bank` with `engine`, persisting the bank to `bank_path`.
    pub fn new(engine: Engine, bank: ClassBank, bank_path: PathBuf, k: usize) -> Self {
        Self {
            engine,
            bank,
            bank_path,
            k,
            started: Instant::now(),
            counters: Counters::default(),
            latencies: Latencies::default(),
            latency_summary: ([f32::NAN; 4], None),
            batched: None,
            workcell: Workcell::default(),
        }
    }

    /// Set the workcell rules (default: [`Workcell::default`], enabled).
    pub fn set_workcell(&mut self, workcell: Workcell) {
        self.workcell = workcell;
    }

    /// The workcell rules in use.
    pub fn workcell(&self) -> &Workcell {
        &self.workcell
    }

    /// The model in use.
    pub fn engine(&self) -> &Engine {
        &self.engine
    }
    /// The bank in use.
    pub fn bank(&self) -> &ClassBank {
        &self.bank
    }
    /// Where the bank is persisted.
    pub fn bank_path(&self) -> &Path {
        &self.bank_path
    }

    /// Replace model and bank (after a successful reload).
    pub fn replace(&mut self, engine: Engine, bank: ClassBank, k: usize) {
        self.engine = engine;
        self.bank = bank;
        self.k = k;
    }

    /// Record the service time of one answered request.
    pub fn record_latency(&mut self, d: Duration) {
        self.latencies.push(d);
    }

    /// One-line status for logs and `STATUS=`.
    pub fn summary(&self) -> String {
        format!(
            "serving {} classes (bank v{}), model {}",
            self.bank.len(),
            self.bank.generation(),
            self.engine.version()
        )
    }

    /// Answer several queued requests. Checks whose trajectory is valid are embedded in one
    /// forward pass first; every request is then answered exactly as by [`Screen::handle`]
    /// (a failed batch falls back to one-by-one embedding, so errors are reported per
    /// request, never turned into a verdict).
    pub fn handle_batch(
        &mut self,
        items: &[(RequestHeader, &[f32])],
    ) -> Vec<(ResponseHeader, Vec<ClassEntry>)> {
        let mut embedded: Vec<Option<Prepared>> = items.iter().map(|_| None).collect();
        let mut which = Vec::new();
        let mut xs = Vec::new();
        for (i, (h, payload)) in items.iter().enumerate() {
            if Op::from_u32(h.op) != Some(Op::Check) {
                continue;
            }
            if let Ok(Ok(mut t)) = Self::trajectories(h, payload, 1, false)
                && let Some(t) = t.pop()
                && let Ok(inspection) = workcell::inspect(&self.workcell, t)
            {
                if inspection.violation.is_none() {
                    which.push(i);
                    xs.push(inspection.resampled);
                }
                embedded[i] = Some(Prepared {
                    inspection,
                    embedding: None,
                });
            }
        }
        if xs.len() >= 2
            && let Ok(es) = self.engine.embed_resampled(&xs)
        {
            for (i, e) in which.into_iter().zip(es) {
                if let Some(p) = embedded[i].as_mut() {
                    p.embedding = Some(e.to_vec());
                }
            }
        }
        items
            .iter()
            .zip(embedded)
            .map(|((h, payload), e)| {
                self.batched = e;
                let answer = self.handle(h, payload);
                self.batched = None;
                answer
            })
            .collect()
    }

    /// Answer one request. Never panics on input; errors become error statuses.
    pub fn handle(
        &mut self,
        h: &RequestHeader,
        payload: &[f32],
    ) -> (ResponseHeader, Vec<ClassEntry>) {
        let mut r = ResponseHeader::new(h.request_id, h.op);
        r.class_name = h.class_name;
        let entries = match Op::from_u32(h.op) {
            None => Err(Fail::Status(
                Status::BadRequest,
                format!("unknown op {}", h.op),
            )),
            Some(Op::Check) => self.check(h, payload, &mut r),
            Some(Op::Identify) => self.identify(h, payload),
            Some(Op::Enroll) => self.enroll(h, payload),
            Some(Op::Forget) => self.forget(h),
            Some(Op::Classes) => Ok(self.class_list()),
            Some(Op::Status) => Ok(Vec::new()),
            Some(_) => Err(Fail::Status(Status::BadRequest, "unsupported op".into())),
        };
        self.counters.requests += 1;
        let entries = match entries {
            Ok(e) => e,
            Err(fail) => {
                self.counters.errors += 1;
                match fail {
                    Fail::Status(s, msg) => {
                        r.status = s as u32;
                        r.message = encode_text(&msg);
                    }
                    Fail::Invalid(inv, example) => {
                        r.status = Status::InvalidTrajectory as u32;
                        r.invalid_kind = inv.kind as u32;
                        r.invalid_index = inv.index;
                        r.invalid_example = example;
                        r.message = encode_text(&inv.to_string());
                    }
                }
                r.verdict = VerdictCode::None as u32;
                Vec::new()
            }
        };
        if r.verdict == VerdictCode::Go as u32 {
            self.counters.go += 1;
        } else if r.verdict == VerdictCode::NoGo as u32 {
            self.counters.no_go += 1;
        }
        // Status answers fresh percentiles; other responses carry ones at most a second old.
        let stale = self
            .latency_summary
            .1
            .is_none_or(|at| at.elapsed() >= LATENCY_REFRESH);
        if stale || Op::from_u32(h.op) == Some(Op::Status) {
            self.latency_summary = (self.latencies.percentiles(), Some(Instant::now()));
        }
        self.fill_common(&mut r);
        (r, entries)
    }

    fn fill_common(&self, r: &mut ResponseHeader) {
        r.bank_version = self.bank.generation();
        r.class_count = u32::try_from(self.bank.len()).unwrap_or(u32::MAX);
        r.model_version = encode_text(self.engine.version());
        r.uptime_ms = u64::try_from(self.started.elapsed().as_millis()).unwrap_or(u64::MAX);
        r.requests = self.counters.requests;
        r.errors = self.counters.errors;
        r.go = self.counters.go;
        r.no_go = self.counters.no_go;
        let [p50, p90, p99, max] = self.latency_summary.0;
        r.latency_p50_us = p50;
        r.latency_p90_us = p90;
        r.latency_p99_us = p99;
        r.latency_max_us = max;
    }

    fn class_name(h: &RequestHeader) -> Result<String, Fail> {
        decode_class_name(&h.class_name)
            .map(str::to_owned)
            .map_err(|e| Fail::Status(Status::InvalidClassName, e.to_string()))
    }

    /// Split the payload into the header's trajectories, borrowed from it (no copy: a
    /// waypoint is 8 consecutive floats), validating each when `check` (a caller passing
    /// `false` must validate them itself before using them).
    fn trajectories<'p>(
        h: &RequestHeader,
        payload: &'p [f32],
        max_examples: usize,
        check: bool,
    ) -> Result<Result<Vec<&'p [Waypoint]>, Fail>, Fail> {
        let n = h.examples as usize;
        if n == 0 || n > max_examples {
            return Err(Fail::Status(
                Status::BadRequest,
                format!("examples is {n}, expected 1..={max_examples}"),
            ));
        }
        // Checked: 16 counts of up to 2^32 - 1 waypoints of up to 2^32 - 1 channels overflow
        // u64, and a wrapped total could match the payload and index past it.
        let channels = u64::from(h.channels);
        let total = h.waypoints[..n].iter().try_fold(0u64, |acc, &w| {
            u64::from(w)
                .checked_mul(channels)
                .and_then(|floats| acc.checked_add(floats))
        });
        if total != Some(payload.len() as u64) {
            return Err(Fail::Status(
                Status::BadRequest,
                match total {
                    Some(total) => {
                        format!(
                            "payload has {} floats, header announces {total}",
                            payload.len()
                        )
                    }
                    None => format!(
                        "payload has {} floats, header announces more than 2^64",
                        payload.len()
                    ),
                },
            ));
        }
        let mut out = Vec::with_capacity(n);
        let mut at = 0usize;
        for (i, &w) in h.waypoints[..n].iter().enumerate() {
            let len = w as usize * h.channels as usize;
            let slice = &payload[at..at + len];
            at += len;
            // An empty trajectory with a wrong channel count is reported as too few
            // waypoints, like any other empty one.
            let parsed = if w == 0 {
                validate(&[]).map(|()| &[][..])
            } else if h.channels as usize != CHANNELS {
                // The shared contract's error for a wrong channel count.
                from_flat(&[], h.channels as usize).map(|_| &[][..])
            } else {
                // `len` is a multiple of 8 here, so nothing is left over.
                let (ws, _) = slice.as_chunks::<CHANNELS>();
                if check {
                    validate(ws).map(|()| ws)
                } else {
                    Ok(ws)
                }
            };
            match parsed {
                Ok(t) => out.push(t),
                Err(e) => return Ok(Err(Fail::Invalid(e, i as u32))),
            }
        }
        Ok(Ok(out))
    }

    fn embed(&self, t: &[Waypoint]) -> Result<Vec<f32>, Fail> {
        self.engine.embed(t).map_err(|e| match e {
            crate::engine::EmbedFailure::Invalid(inv) => Fail::Invalid(inv, 0),
            crate::engine::EmbedFailure::Internal(msg) => {
                tracing::error!(error = %msg, "embedding failed");
                Fail::Status(Status::Internal, format!("embedding failed: {msg}"))
            }
        })
    }

    fn check(
        &mut self,
        h: &RequestHeader,
        payload: &[f32],
        r: &mut ResponseHeader,
    ) -> Result<Vec<ClassEntry>, Fail> {
        let claimed = Self::class_name(h)?;
        // `inspect` validates (before anything else), so the split does not.
        let mut t = match Self::trajectories(h, payload, 1, false)? {
            Ok(t) => t,
            Err(Fail::Invalid(inv, _)) => {
                no_go_invalid(r, inv);
                return Ok(Vec::new());
            }
            Err(other) => return Err(other),
        };
        let t = t.pop().unwrap_or_default();
        let prepared = match self.batched.take() {
            Some(p) => p,
            None => match workcell::inspect(&self.workcell, t) {
                Ok(inspection) => Prepared {
                    inspection,
                    embedding: None,
                },
                Err(inv) => {
                    no_go_invalid(r, inv);
                    return Ok(Vec::new());
                }
            },
        };
        // Workcell rules first: absolute, no model involved.
        if let Some(v) = prepared.inspection.violation {
            r.verdict = VerdictCode::NoGo as u32;
            r.reason = ReasonCode::Workcell as u32;
            r.workcell_kind = v.kind as u32;
            r.workcell_index = v.index;
            r.message = encode_text(&format!(
                "workcell rule broken: {:?} at waypoint {}",
                v.kind, v.index
            ));
            return Ok(Vec::new());
        }
        let x = prepared.inspection.resampled;
        // The pen path comes with a single embedding (a batch computes it again below).
        let (e, path) = match prepared.embedding {
            Some(e) => (e, None),
            None => match self.engine.embed_with_pen_path(&x) {
                Ok((e, path)) => (e.to_vec(), Some(path)),
                Err(msg) => {
                    tracing::error!(error = %msg, "embedding failed");
                    return Err(Fail::Status(
                        Status::Internal,
                        format!("embedding failed: {msg}"),
                    ));
                }
            },
        };
        // Plan geometry only when the bank can use it.
        let geometry = self.bank.geometry_calibration().and_then(|_| match &path {
            Some(path) => workcell::plan_geometry_of_path(path),
            None => workcell::plan_geometry(&x),
        });
        let d = self
            .bank
            .decide_with_geometry(&e, geometry.as_ref(), &claimed, self.k);
        let (verdict, reason) = match &d.outcome {
            Outcome::Go => (VerdictCode::Go, ReasonCode::None),
            Outcome::WrongTask { .. } => (VerdictCode::NoGo, ReasonCode::WrongTask),
            Outcome::Outlier => (VerdictCode::NoGo, ReasonCode::Outlier),
            Outcome::GeometryMismatch { .. } => (VerdictCode::NoGo, ReasonCode::GeometryMismatch),
            Outcome::UnknownClass => (VerdictCode::NoGo, ReasonCode::UnknownClass),
        };
        r.geometry_score = d.geometry_score.unwrap_or(f32::NAN);
        r.geometry_threshold = d.geometry_threshold.unwrap_or(f32::NAN);
        r.geometry_feature = d.geometry_feature.map_or(0, |f| f as u32);
        r.verdict = verdict as u32;
        r.reason = reason as u32;
        r.claimed_distance = d.claimed_distance.unwrap_or(f32::NAN);
        r.threshold = d.threshold.unwrap_or(f32::NAN);
        r.margin = d.margin.unwrap_or(f32::NAN);
        r.gap = d.gap.unwrap_or(f32::NAN);
        // With WrongTask the nearest class is the overall nearest, so it is entries[0].
        Ok(d.nearest
            .iter()
            .map(|n| self.entry(&n.name, n.distance))
            .collect())
    }

    fn identify(&mut self, h: &RequestHeader, payload: &[f32]) -> Result<Vec<ClassEntry>, Fail> {
        let mut t = Self::trajectories(h, payload, 1, true)??;
        let t = t.pop().unwrap_or_default();
        let e = self.embed(t)?;
        if self.bank.is_empty() {
            return Err(Fail::Status(
                Status::EmptyBank,
                "no classes enrolled".into(),
            ));
        }
        Ok(self
            .bank
            .nearest(&e, self.k)
            .iter()
            .map(|n| self.entry(&n.name, n.distance))
            .collect())
    }

    fn enroll(&mut self, h: &RequestHeader, payload: &[f32]) -> Result<Vec<ClassEntry>, Fail> {
        let name = Self::class_name(h)?;
        let ts = Self::trajectories(h, payload, MAX_EXAMPLES, true)??;
        let mut embeddings = Vec::with_capacity(ts.len());
        let mut geometry = Vec::with_capacity(ts.len());
        for (i, t) in ts.iter().enumerate() {
            let x = guardian_models::preprocess::preprocess(t)
                .map_err(|inv| Fail::Invalid(inv, i as u32))?;
            let e = self
                .engine
                .embed_resampled(std::slice::from_ref(&x))
                .map_err(|msg| {
                    Fail::Status(Status::Internal, format!("embedding failed: {msg}"))
                })?;
            embeddings.extend(e.iter().map(|e| e.to_vec()));
            geometry.push(workcell::plan_geometry(&x));
        }
        // Descriptors only if every example draws on the canvas.
        let geometry: Vec<_> = geometry
            .into_iter()
            .collect::<Option<_>>()
            .unwrap_or_default();
        let mut next = self.bank.clone();
        next.enroll_with_geometry(&name, &embeddings, &geometry)
            .map_err(|e| Fail::Status(Status::Internal, e.to_string()))?;
        self.commit(next)?;
        tracing::info!(class = %name, examples = embeddings.len(), bank = self.bank.generation(), "enrolled");
        Ok(vec![self.entry(&name, f32::NAN)])
    }

    fn forget(&mut self, h: &RequestHeader) -> Result<Vec<ClassEntry>, Fail> {
        let name = Self::class_name(h)?;
        let mut next = self.bank.clone();
        let Some(_) = next.forget(&name) else {
            return Err(Fail::Status(
                Status::UnknownClass,
                format!("class {name:?} is not enrolled"),
            ));
        };
        self.commit(next)?;
        tracing::info!(class = %name, bank = self.bank.generation(), "forgot class");
        Ok(Vec::new())
    }

    /// Persist `next` atomically, then serve it. On failure the old bank stays.
    fn commit(&mut self, next: ClassBank) -> Result<(), Fail> {
        if let Err(e) = next.save(&self.bank_path) {
            tracing::error!(error = %e, "cannot persist class bank; change rejected");
            return Err(Fail::Status(
                Status::Internal,
                format!("cannot persist class bank: {e}"),
            ));
        }
        self.bank = next;
        Ok(())
    }

    /// Save the bank now (used at shutdown; every change is already saved).
    pub fn flush(&self) -> Result<(), guardian_models::bank::SaveBankError> {
        if self.bank.generation() == 0 && !self.bank_path.exists() {
            return Ok(());
        }
        self.bank.save(&self.bank_path)
    }

    fn class_list(&self) -> Vec<ClassEntry> {
        self.bank
            .classes()
            .map(|(n, _)| self.entry(n, f32::NAN))
            .collect()
    }

    fn entry(&self, name: &str, distance: f32) -> ClassEntry {
        let class = self.bank.class(name);
        ClassEntry {
            name: encode_text(name),
            distance,
            threshold: self.bank.threshold(name).unwrap_or(f32::NAN),
            examples: class.map_or(0, |c| u32::try_from(c.embeddings.len()).unwrap_or(u32::MAX)),
            calibrated: u32::from(class.is_some_and(|c| c.threshold.is_some())),
        }
    }
}

/// A check whose trajectory failed validation: no-go with the typed reason and its index.
fn no_go_invalid(r: &mut ResponseHeader, inv: InvalidTrajectory) {
    r.verdict = VerdictCode::NoGo as u32;
    r.reason = ReasonCode::InvalidTrajectory as u32;
    r.invalid_kind = inv.kind as u32;
    r.invalid_index = inv.index;
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_client::samples::task;
    use guardian_models::embedder::Embedder;
    use guardian_shared::wire::encode_class_name;

    fn request(op: Op, class: &str, t: &[Waypoint]) -> (RequestHeader, Vec<f32>) {
        let mut h = RequestHeader::new(7, op);
        h.channels = 8;
        h.examples = 1;
        h.waypoints[0] = t.len() as u32;
        h.class_name = encode_class_name(class).unwrap();
        (h, t.iter().flatten().copied().collect())
    }

    /// A batch answers every request exactly as one-by-one handling does: valid checks,
    /// an invalid trajectory, an unknown class and a non-check op mixed together.
    #[test]
    fn batched_checks_answer_like_single_ones() {
        let dir = tempfile::tempdir().unwrap();
        let engine = Engine::from_embedder(Embedder::random(3));
        let mut bank = ClassBank::new(engine.dim(), engine.version(), 0.8);
        for c in 0..3 {
            let es: Vec<Vec<f32>> = (0..4).map(|d| engine.embed(&task(c, d)).unwrap()).collect();
            bank.enroll(&format!("task{c}"), &es).unwrap();
        }
        let mut screen = Screen::new(engine, bank, dir.path().join("bank.gcb"), 3);
        // The synthetic tasks are joint-space patterns, not drawings on the canvas.
        screen.set_workcell(Workcell {
            enabled: false,
            ..Workcell::default()
        });
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
        for ((h, p), (rb, eb)) in reqs.iter().zip(&batched) {
            let (r1, e1) = screen.handle(h, p);
            assert_eq!(
                (rb.status, rb.verdict, rb.reason),
                (r1.status, r1.verdict, r1.reason)
            );
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
        assert_eq!(batched[2].0.reason, ReasonCode::InvalidTrajectory as u32);
        assert_eq!(batched[4].0.reason, ReasonCode::UnknownClass as u32);
    }
}
