//! The verdict record (`docs/operating.md`, "What the screen stops"): every check's outcome
//! in a bounded SQLite database (WAL) in the state directory, and the plans of no-go
//! verdicts with a bound of their own.
//!
//! The check path never waits on it: the serving loop hands each entry to a bounded queue
//! ([`Record::submit`], `try_send`) and a writer thread commits them in batches. A full
//! queue drops the entry (counted in `guardian_record_dropped_total{cause="queue-full"}`).
//! A storage error (a full or read-only disk, a damaged file) turns the record off with an
//! error line and `guardian_record_enabled 0`; checks go on unrecorded until the next start.
//!
//! Readers (`guardianctl verdicts`, the page) open the file read-only; WAL lets them read
//! while the writer writes. The schema is [`SCHEMA`].

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError, sync_channel};
use std::time::{Duration, Instant, SystemTime};

use guardian_shared::verdict::Verdict;
use guardian_shared::wire::{Failure, RequestHeader, ResponseHeader, decode_text};
use rusqlite::{Connection, OpenFlags, params};

use crate::metrics::{Metrics, status_name};

/// File name of the record in the state directory (config `[record] path` unset).
pub const RECORD_FILE: &str = "verdicts.sqlite";

/// The tables. `verdicts`: one row per check. `plans`: the plan of a no-go verdict as the
/// planner sent it (`values`: `waypoints × channels` little-endian `f32`, waypoint by
/// waypoint), keyed by its verdict's id.
pub const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS verdicts (
    id INTEGER PRIMARY KEY,
    time_ms INTEGER NOT NULL,
    service TEXT NOT NULL,
    client TEXT NOT NULL,
    claimed TEXT NOT NULL,
    status TEXT NOT NULL,
    verdict TEXT NOT NULL,
    reason TEXT NOT NULL,
    message TEXT NOT NULL,
    distance REAL,
    threshold REAL,
    margin REAL,
    gap REAL,
    nearest TEXT NOT NULL,
    model TEXT NOT NULL,
    bank_version INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS verdicts_time ON verdicts (time_ms);
CREATE TABLE IF NOT EXISTS plans (
    verdict_id INTEGER PRIMARY KEY,
    channels INTEGER NOT NULL,
    waypoints INTEGER NOT NULL,
    vals BLOB NOT NULL
);
";

/// Bounds and place of the record (`[record]` in the config).
#[derive(Debug, Clone)]
pub struct RecordSettings {
    /// The database file.
    pub path: PathBuf,
    /// The daemon's service name, stored with every verdict.
    pub service: String,
    /// Most verdicts kept (the oldest go first).
    pub max_verdicts: u64,
    /// Most no-go plans kept.
    pub max_plans: u64,
    /// Verdicts older than this are removed (`None`: no age bound).
    pub max_age: Option<Duration>,
    /// Entries the queue to the writer holds.
    pub queue: usize,
}

/// One check's outcome, as the serving loop hands it over.
#[derive(Debug)]
pub struct Entry {
    /// Unix time, milliseconds.
    pub time_ms: i64,
    /// Who asked: the iceoryx2 client id in hex, or `remote:` and the first 8 bytes of a
    /// fleet caller's public key in hex.
    pub client: String,
    /// The request's header (claimed class, plan shape).
    pub request: RequestHeader,
    /// The answer's header (the daemon's model and bank version when the check failed).
    pub response: ResponseHeader,
    /// The verdict, or the failure the check was answered with.
    pub check: Result<Verdict, Failure>,
    /// The plan of a no-go verdict, as sent.
    pub plan: Option<Vec<f32>>,
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// The sending side of the record, owned by the serving loop.
#[derive(Debug)]
pub struct Record {
    tx: Option<SyncSender<Entry>>,
    on: Arc<AtomicBool>,
    /// Turned off by the config: nothing is lost, so nothing is counted as dropped.
    disabled: bool,
    metrics: Metrics,
    writer: Option<std::thread::JoinHandle<()>>,
}

impl Record {
    /// No record because it failed: every verdict submitted counts as dropped
    /// (`record-off`).
    pub fn off(metrics: Metrics) -> Self {
        metrics.record_enabled.set(0);
        Self {
            tx: None,
            on: Arc::new(AtomicBool::new(false)),
            disabled: false,
            metrics,
            writer: None,
        }
    }

    /// No record because the config says so (`[record] enabled = false`): nothing is
    /// counted as dropped.
    pub fn disabled(metrics: Metrics) -> Self {
        let mut record = Self::off(metrics);
        record.disabled = true;
        record
    }

    /// Open (or create) the record and start its writer. A record that cannot be opened
    /// is off, with an error line; the daemon serves anyway.
    pub fn open(settings: RecordSettings, metrics: Metrics) -> Self {
        let conn = match open_for_writing(&settings.path) {
            Ok(c) => c,
            Err(e) => {
                tracing::error!(path = %settings.path.display(), error = %e, "cannot open the verdict record; it is off, checks go on unrecorded");
                return Self::off(metrics);
            }
        };
        let (tx, rx) = sync_channel(settings.queue.max(1));
        let on = Arc::new(AtomicBool::new(true));
        metrics.record_enabled.set(1);
        let writer = {
            let on = on.clone();
            let metrics = metrics.clone();
            std::thread::Builder::new()
                .name("verdict-record".into())
                .spawn(move || Writer::new(conn, settings, on, metrics).run(rx))
        };
        match writer {
            Ok(handle) => Self {
                tx: Some(tx),
                on,
                disabled: false,
                metrics,
                writer: Some(handle),
            },
            Err(e) => {
                tracing::error!(error = %e, "cannot start the verdict record's writer; it is off");
                Self::off(metrics)
            }
        }
    }

    /// The record is on (a no-go's plan is worth copying).
    pub fn is_on(&self) -> bool {
        self.on.load(Ordering::Relaxed)
    }

    /// Hand an entry to the writer; never blocks. A full queue or an off record drops it
    /// (counted).
    pub fn submit(&self, entry: Entry) {
        let Some(tx) = self.tx.as_ref().filter(|_| self.is_on()) else {
            if !self.disabled {
                self.metrics.dropped("record-off");
            }
            return;
        };
        match tx.try_send(entry) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => self.metrics.dropped("queue-full"),
            Err(TrySendError::Disconnected(_)) => self.metrics.dropped("record-off"),
        }
    }
}

impl Drop for Record {
    /// Close the queue and let the writer commit what it holds.
    fn drop(&mut self) {
        self.tx = None;
        if let Some(w) = self.writer.take() {
            let _ = w.join();
        }
    }
}

/// Open the record for the writer: WAL, the schema created if missing.
fn open_for_writing(path: &Path) -> rusqlite::Result<Connection> {
    let conn = Connection::open(path)?;
    conn.busy_timeout(Duration::from_secs(1))?;
    // WAL: readers never block the writer. NORMAL: a crash of the daemon loses nothing
    // committed; a power cut may lose the last commits, never the file.
    conn.pragma_update(None, "journal_mode", "WAL")?;
    conn.pragma_update(None, "synchronous", "NORMAL")?;
    conn.execute_batch(SCHEMA)?;
    Ok(conn)
}

/// Open the record read-only (a reader beside the running daemon).
pub fn open_read_only(path: &Path) -> rusqlite::Result<Connection> {
    let conn = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )?;
    conn.busy_timeout(Duration::from_secs(1))?;
    Ok(conn)
}

/// Commits at most this many entries per transaction.
const BATCH: usize = 4096;
/// At most one commit per this period: the writer wakes, sleeps the rest of the period and
/// commits everything queued meanwhile in one transaction (fewer wake-ups and commits
/// competing with the serving loop for the cores).
const COMMIT_PERIOD: Duration = Duration::from_millis(100);
/// Trim to the bounds after this many entries, or this long.
const TRIM_EVERY: u64 = 512;
const TRIM_PERIOD: Duration = Duration::from_secs(10);

struct Writer {
    conn: Connection,
    settings: RecordSettings,
    on: Arc<AtomicBool>,
    metrics: Metrics,
    since_trim: u64,
    last_trim: Instant,
}

impl Writer {
    fn new(
        conn: Connection,
        settings: RecordSettings,
        on: Arc<AtomicBool>,
        metrics: Metrics,
    ) -> Self {
        Self {
            conn,
            settings,
            on,
            metrics,
            since_trim: 0,
            last_trim: Instant::now(),
        }
    }

    fn run(mut self, rx: Receiver<Entry>) {
        // Bounds changed in the config apply at start.
        if let Err(e) = self.trim() {
            self.turn_off(&e, 0);
            return;
        }
        let mut batch = Vec::with_capacity(BATCH);
        let mut last_commit = Instant::now();
        let mut open = true;
        while open {
            match rx.recv_timeout(TRIM_PERIOD) {
                Ok(e) => {
                    batch.push(e);
                    // Let the period fill (a shutdown ends the wait at once).
                    let rest = COMMIT_PERIOD.saturating_sub(last_commit.elapsed());
                    if !rest.is_zero() {
                        match rx.recv_timeout(rest) {
                            Ok(e) => batch.push(e),
                            Err(RecvTimeoutError::Timeout) => {}
                            Err(RecvTimeoutError::Disconnected) => open = false,
                        }
                        if open {
                            std::thread::sleep(COMMIT_PERIOD.saturating_sub(last_commit.elapsed()));
                        }
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
            while batch.len() < BATCH {
                match rx.try_recv() {
                    Ok(e) => batch.push(e),
                    Err(_) => break,
                }
            }
            if !batch.is_empty() {
                let n = batch.len() as u64;
                if let Err(e) = self.write(&batch) {
                    self.turn_off(&e, n);
                    return;
                }
                self.metrics.record_written.inc_by(n);
                self.since_trim += n;
                batch.clear();
                last_commit = Instant::now();
            }
            if (self.since_trim >= TRIM_EVERY
                || (self.since_trim > 0 && self.last_trim.elapsed() >= TRIM_PERIOD))
                && let Err(e) = self.trim()
            {
                self.turn_off(&e, 0);
                return;
            }
        }
        if let Err(e) = self.trim() {
            tracing::warn!(error = %e, "verdict record: trimming at shutdown failed");
        }
    }

    /// A storage error: the record is off from now on.
    fn turn_off(&self, e: &rusqlite::Error, lost: u64) {
        self.on.store(false, Ordering::Relaxed);
        self.metrics.record_enabled.set(0);
        for _ in 0..lost {
            self.metrics.dropped("record-off");
        }
        tracing::error!(path = %self.settings.path.display(), error = %e, lost, "cannot write the verdict record (disk full or read-only?); the record is off until the next start, checks go on unrecorded");
    }

    fn write(&mut self, batch: &[Entry]) -> rusqlite::Result<()> {
        let tx = self.conn.transaction()?;
        {
            let mut verdict = tx.prepare_cached(
                "INSERT INTO verdicts (time_ms, service, client, claimed, status, verdict, reason, message, distance, threshold, margin, gap, nearest, model, bank_version)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15)",
            )?;
            let mut plan = tx.prepare_cached(
                "INSERT INTO plans (verdict_id, channels, waypoints, vals) VALUES (?1, ?2, ?3, ?4)",
            )?;
            for e in batch {
                // A verdict's decision, reason, why, numbers and nearest classes; a failure's
                // status and message (the daemon's state from its answer's header).
                let (status, name, reason, message, numbers, nearest, model, bank) = match &e.check
                {
                    Ok(v) => (
                        "ok",
                        if v.is_go() { "go" } else { "no-go" },
                        v.reason().map_or("none", |r| r.name()),
                        v.why(),
                        [v.claimed_distance, v.threshold, v.margin, v.gap]
                            .map(|x| x.and_then(finite)),
                        serde_json::Value::Array(
                            v.nearest
                                .iter()
                                .map(|n| {
                                    serde_json::json!({
                                        "class": n.class,
                                        "distance": finite(n.distance),
                                    })
                                })
                                .collect(),
                        )
                        .to_string(),
                        v.model_version.clone(),
                        v.bank_version,
                    ),
                    Err(f) => (
                        status_name(f.status() as u32),
                        "error",
                        "none",
                        f.message().to_owned(),
                        [None; 4],
                        "[]".to_owned(),
                        decode_text(&e.response.model_version),
                        e.response.bank_version,
                    ),
                };
                verdict.execute(params![
                    e.time_ms,
                    self.settings.service,
                    e.client,
                    decode_text(&e.request.class_name),
                    status,
                    name,
                    reason,
                    message,
                    numbers[0],
                    numbers[1],
                    numbers[2],
                    numbers[3],
                    nearest,
                    model,
                    i64::try_from(bank).unwrap_or(i64::MAX),
                ])?;
                if let Some(values) = &e.plan {
                    let id = tx.last_insert_rowid();
                    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
                    let channels = e.request.channels.max(1);
                    plan.execute(params![
                        id,
                        channels,
                        i64::try_from(values.len()).unwrap_or(i64::MAX) / i64::from(channels),
                        bytes
                    ])?;
                }
            }
        }
        tx.commit()
    }

    /// Apply the bounds: verdict count, age, plan count.
    fn trim(&mut self) -> rusqlite::Result<()> {
        let s = &self.settings;
        let tx = self.conn.transaction()?;
        tx.execute(
            "DELETE FROM verdicts WHERE id <= (SELECT MAX(id) FROM verdicts) - ?1",
            params![i64::try_from(s.max_verdicts).unwrap_or(i64::MAX)],
        )?;
        if let Some(age) = s.max_age {
            let cutoff =
                now_ms().saturating_sub(i64::try_from(age.as_millis()).unwrap_or(i64::MAX));
            tx.execute("DELETE FROM verdicts WHERE time_ms < ?1", params![cutoff])?;
        }
        tx.execute(
            "DELETE FROM plans WHERE verdict_id < (SELECT MIN(id) FROM verdicts) OR NOT EXISTS (SELECT 1 FROM verdicts)",
            [],
        )?;
        tx.execute(
            "DELETE FROM plans WHERE verdict_id <= (SELECT verdict_id FROM plans ORDER BY verdict_id DESC LIMIT 1 OFFSET ?1)",
            params![i64::try_from(s.max_plans).unwrap_or(i64::MAX)],
        )?;
        tx.commit()?;
        self.since_trim = 0;
        self.last_trim = Instant::now();
        Ok(())
    }
}

/// A finite value, else NULL.
fn finite(v: f32) -> Option<f64> {
    v.is_finite().then_some(f64::from(v))
}

/// A remote check as answered, for the verdict record and the metrics.
pub struct RemoteCheck {
    /// The request's header.
    pub request: guardian_shared::wire::RequestHeader,
    /// The answer's header.
    pub response: guardian_shared::wire::ResponseHeader,
    /// The verdict, or the failure the check was answered with.
    pub check: Result<Verdict, Failure>,
    /// The plan of a no-go.
    pub plan: Option<Vec<f32>>,
    /// `remote:` and the first 8 bytes of the caller's public key in hex.
    pub client: String,
    /// From the request taken to the answer sent.
    pub took: std::time::Duration,
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_shared::verdict::{Decision, Neighbour, NoGoReason};
    use guardian_shared::wire::{Op, encode_class_name};

    fn entry(claimed: &str, no_go: bool) -> Entry {
        let mut request = RequestHeader::new(1, Op::Check);
        request.class_name = encode_class_name(claimed).unwrap();
        request.channels = 8;
        let response = ResponseHeader::answering(&request);
        let decision = if no_go {
            Decision::NoGo {
                reason: NoGoReason::WrongTask {
                    nearest: "other".into(),
                },
            }
        } else {
            Decision::Go
        };
        let verdict = Verdict {
            decision,
            claimed_class: claimed.into(),
            claimed_distance: Some(1.25),
            threshold: Some(0.9),
            margin: Some(-0.35),
            gap: Some(-0.75),
            nearest: vec![Neighbour {
                class: "other".into(),
                distance: 0.5,
                threshold: 0.9,
            }],
            geometry_score: None,
            geometry_threshold: None,
            geometry_feature: None,
            model_version: "m".into(),
            bank_version: 4,
        };
        Entry {
            time_ms: now_ms(),
            client: format!("{:032x}", 42u128),
            request,
            response,
            check: Ok(verdict),
            plan: no_go.then(|| vec![0.5; 8 * 3]),
        }
    }

    fn settings(dir: &Path, max_verdicts: u64, max_plans: u64) -> RecordSettings {
        RecordSettings {
            path: dir.join(RECORD_FILE),
            service: "svc".into(),
            max_verdicts,
            max_plans,
            max_age: None,
            queue: 64,
        }
    }

    /// Entries are written, the bounds hold, and a reader sees them while the writer has
    /// the file open (WAL).
    #[test]
    fn writes_and_trims_to_the_bounds() {
        let dir = tempfile::tempdir().unwrap();
        let metrics = Metrics::default();
        let record = Record::open(settings(dir.path(), 10, 3), metrics.clone());
        assert!(record.is_on());
        for i in 0..(TRIM_EVERY as usize + 40) {
            // Spread the submissions so that the small queue never fills.
            while record
                .tx
                .as_ref()
                .unwrap()
                .try_send(entry("task", i % 2 == 0))
                .is_err()
            {
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        drop(record);
        let conn = open_read_only(&dir.path().join(RECORD_FILE)).unwrap();
        let count = |sql: &str| conn.query_row(sql, [], |r| r.get::<_, i64>(0)).unwrap();
        assert_eq!(count("SELECT COUNT(*) FROM verdicts"), 10);
        assert_eq!(count("SELECT COUNT(*) FROM plans"), 3);
        assert_eq!(
            count(
                "SELECT COUNT(*) FROM plans p JOIN verdicts v ON v.id = p.verdict_id WHERE v.verdict = 'no-go'"
            ),
            3
        );
        let (reason, nearest, client): (String, String, String) = conn
            .query_row(
                "SELECT reason, nearest, client FROM verdicts WHERE verdict = 'no-go' LIMIT 1",
                [],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
            )
            .unwrap();
        assert_eq!(reason, "wrong-task");
        assert!(nearest.contains("\"other\""), "{nearest}");
        assert!(client.ends_with("2a"));
        assert_eq!(metrics.record_written.get(), TRIM_EVERY + 40);
    }

    /// A record turned off by the config loses nothing, so it counts no drop.
    #[test]
    fn a_record_disabled_by_config_counts_no_drop() {
        let metrics = Metrics::default();
        let record = Record::disabled(metrics.clone());
        assert!(!record.is_on());
        record.submit(entry("task", true));
        assert_eq!(metrics.record_enabled.get(), 0);
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &metrics.registry()).unwrap();
        assert!(!text.contains("cause=\"record-off\"} 1"), "{text}");
    }

    /// A record that cannot be opened is off; submitting to it counts a drop.
    #[test]
    fn an_unopenable_record_is_off_and_counts_drops() {
        let dir = tempfile::tempdir().unwrap();
        let metrics = Metrics::default();
        let mut s = settings(dir.path(), 10, 3);
        s.path = dir.path().join("missing-dir").join(RECORD_FILE);
        let record = Record::open(s, metrics.clone());
        assert!(!record.is_on());
        record.submit(entry("task", true));
        assert_eq!(metrics.record_enabled.get(), 0);
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &metrics.registry()).unwrap();
        assert!(
            text.contains("guardian_record_dropped_total{cause=\"record-off\"} 1"),
            "{text}"
        );
    }
}
