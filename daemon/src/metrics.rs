//! OpenMetrics for Prometheus (`docs/operating.md`, "What the screen stops"): the metrics
//! are `prometheus-client` atomics updated by the serving loop and the record's writer, and
//! encoded only by the `/metrics` thread ([`serve_metrics`]), which listens on its own
//! address (loopback by default) and answers nothing but `GET /metrics`.

use std::collections::HashSet;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use guardian_shared::verdict::Verdict;
use guardian_shared::wire::{Failure, Status, decode_code};
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::metrics::info::Info;
use prometheus_client::registry::{Registry, Unit};

/// The class label of checks whose claimed class is not enrolled (any name a planner sends
/// would otherwise become a label).
pub const UNKNOWN_CLASS_LABEL: &str = "_unknown";
/// The class label of enrolled classes beyond the label bound (`[metrics] max-class-labels`).
pub const OTHER_CLASS_LABEL: &str = "_other";

/// Labels of `guardian_checks_total`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct CheckLabels {
    /// `go`, `no-go` or `error`.
    pub verdict: &'static str,
    /// The no-go reason (`none` for go), or the error status.
    pub reason: &'static str,
    /// The claimed class, bounded ([`ClassLabels`]).
    pub class: String,
}

/// Labels of `guardian_admin_operations_total`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct AdminLabels {
    /// The operation (`enroll`, `forget`, `classes`, ...).
    pub op: &'static str,
    /// Its outcome: `ok` or the error status.
    pub status: &'static str,
}

/// Labels of `guardian_record_dropped_total`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DropLabels {
    /// `queue-full` (the writer was behind) or `record-off` (the record is off).
    pub cause: &'static str,
}

/// Labels of `guardian_fleet_position`.
#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct SignerLabels {
    /// The signer's public key (hex).
    pub signer: String,
}

/// The model version, encoded as the info metric `guardian_model_info` at each scrape (a
/// reload may change it).
#[derive(Debug, Default)]
struct ModelInfo(Mutex<String>);

impl Collector for ModelInfo {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let version = self.0.lock().map(|v| v.clone()).unwrap_or_default();
        let info = Info::new(vec![("version".to_owned(), version)]);
        let metric = encoder.encode_descriptor(
            "guardian_model",
            "The embedding model in use",
            None,
            info.metric_type(),
        )?;
        info.encode(metric)
    }
}

/// Every metric of a daemon. Cloning shares them.
#[derive(Debug, Clone)]
pub struct Metrics {
    checks: Family<CheckLabels, Counter>,
    check_seconds: Histogram,
    bank_classes: Gauge,
    bank_version: Gauge,
    model: Arc<ModelInfo>,
    admin: Family<AdminLabels, Counter>,
    /// Entries not recorded, by cause.
    pub record_dropped: Family<DropLabels, Counter>,
    /// Entries the record's writer committed.
    pub record_written: Counter,
    /// 1 while the record is on, 0 once it is off (disabled, or turned off by an error).
    pub record_enabled: Gauge,
    fleet_position: Family<SignerLabels, Gauge>,
    fleet_peers: Gauge,
}

/// Every `(verdict, reason)` pair a check can count: pre-set to 0 per class label, so
/// `rate()` sees the first no-go of a reason (a series that starts at 1 has no increase).
const CHECK_OUTCOMES: [(&str, &str); 7] = [
    ("go", "none"),
    ("no-go", "wrong-task"),
    ("no-go", "outlier"),
    ("no-go", "unknown-class"),
    ("no-go", "invalid-trajectory"),
    ("no-go", "workcell"),
    ("no-go", "geometry-mismatch"),
];

impl Default for Metrics {
    fn default() -> Self {
        let record_dropped = Family::<DropLabels, Counter>::default();
        // Pre-set to 0, so the first drop is an increase.
        for cause in ["queue-full", "record-off"] {
            drop(record_dropped.get_or_create(&DropLabels { cause }));
        }
        Self {
            checks: Family::default(),
            // 25 us .. ~105 ms in factors of 2 (a check's service time is ~100-400 us).
            check_seconds: Histogram::new(
                prometheus_client::metrics::histogram::exponential_buckets(25e-6, 2.0, 13),
            ),
            bank_classes: Gauge::default(),
            bank_version: Gauge::default(),
            model: Arc::default(),
            admin: Family::default(),
            record_dropped,
            record_written: Counter::default(),
            record_enabled: Gauge::default(),
            fleet_position: Family::default(),
            fleet_peers: Gauge::default(),
        }
    }
}

impl Metrics {
    /// A registry holding every metric (for the `/metrics` thread).
    pub fn registry(&self) -> Registry {
        let mut r = Registry::default();
        r.register(
            "guardian_checks",
            "Checks answered, by verdict, reason (or error status) and claimed class",
            self.checks.clone(),
        );
        r.register_with_unit(
            "guardian_check_duration",
            "Service time of a check: from taking its batch to sending its answer",
            Unit::Seconds,
            self.check_seconds.clone(),
        );
        r.register(
            "guardian_bank_classes",
            "Classes in the served bank",
            self.bank_classes.clone(),
        );
        r.register(
            "guardian_bank_version",
            "Generation of the served bank (one more per change)",
            self.bank_version.clone(),
        );
        r.register_collector(Box::new(self.model.clone()));
        r.register(
            "guardian_admin_operations",
            "Requests answered on the admin socket, by operation and outcome",
            self.admin.clone(),
        );
        r.register(
            "guardian_record_dropped",
            "Verdicts not recorded: the writer's queue was full, or the record is off",
            self.record_dropped.clone(),
        );
        r.register(
            "guardian_record_written",
            "Verdicts written to the record",
            self.record_written.clone(),
        );
        r.register(
            "guardian_record_enabled",
            "1 while the verdict record is on; 0 when disabled or turned off by a storage error",
            self.record_enabled.clone(),
        );
        r.register(
            "guardian_fleet_position",
            "Fleet members only: per signer, the Lamport time of the last record applied here",
            self.fleet_position.clone(),
        );
        r.register(
            "guardian_fleet_peers",
            "Fleet members only: signers whose records were seen here (this member's own included)",
            self.fleet_peers.clone(),
        );
        r
    }

    /// Count one answered check and its service time; `class` is its bounded label.
    pub fn count_check(&self, check: &Result<Verdict, Failure>, class: String, took: Duration) {
        let (verdict, reason) = verdict_labels(check);
        let labels = CheckLabels {
            verdict,
            reason,
            class,
        };
        // A class label's first check: its other outcomes start at 0 beside it.
        if self.checks.get(&labels).is_none() {
            for (verdict, reason) in CHECK_OUTCOMES {
                drop(self.checks.get_or_create(&CheckLabels {
                    verdict,
                    reason,
                    class: labels.class.clone(),
                }));
            }
        }
        self.checks.get_or_create(&labels).inc();
        self.check_seconds.observe(took.as_secs_f64());
    }

    /// Count one request answered on the admin socket.
    pub fn count_admin(&self, op: u32, status: u32) {
        self.admin
            .get_or_create(&AdminLabels {
                op: op_name(op),
                status: status_name(status),
            })
            .inc();
    }

    /// The served bank's size and generation, and the model version.
    pub fn set_state(&self, classes: usize, generation: u64, model: &str) {
        self.bank_classes
            .set(i64::try_from(classes).unwrap_or(i64::MAX));
        self.bank_version
            .set(i64::try_from(generation).unwrap_or(i64::MAX));
        if let Ok(mut m) = self.model.0.lock()
            && *m != model
        {
            model.clone_into(&mut m);
        }
    }

    /// A fleet member's position (per signer, hex key and Lamport time); `own` is this
    /// member's key, not counted among the peers.
    pub fn set_fleet(&self, position: &[(String, u64)], own: Option<&str>) {
        for (signer, lamport) in position {
            self.fleet_position
                .get_or_create(&SignerLabels {
                    signer: signer.clone(),
                })
                .set(i64::try_from(*lamport).unwrap_or(i64::MAX));
        }
        let peers = position
            .iter()
            .filter(|(s, _)| Some(s.as_str()) != own)
            .count();
        self.fleet_peers.set(peers as i64);
    }

    /// Count one verdict that was not recorded.
    pub fn dropped(&self, cause: &'static str) {
        self.record_dropped
            .get_or_create(&DropLabels { cause })
            .inc();
    }
}

/// The `verdict` and `reason` labels of a check's answer.
pub fn verdict_labels(check: &Result<Verdict, Failure>) -> (&'static str, &'static str) {
    match check {
        Err(f) => ("error", status_name(f.status() as u32)),
        Ok(v) => match v.reason() {
            None => ("go", "none"),
            Some(r) => ("no-go", r.name()),
        },
    }
}

/// A status code's name (`ok` or the error, kebab-case).
pub fn status_name(status: u32) -> &'static str {
    match decode_code::<Status>(status) {
        Some(Status::Ok) => "ok",
        Some(Status::BadRequest) => "bad-request",
        Some(Status::InvalidTrajectory) => "invalid-trajectory",
        Some(Status::InvalidClassName) => "invalid-class-name",
        Some(Status::UnknownClass) => "unknown-class",
        Some(Status::EmptyBank) => "empty-bank",
        Some(Status::Internal) => "internal",
        Some(Status::LimitExceeded) => "limit-exceeded",
        Some(Status::NotPermitted) => "not-permitted",
        Some(Status::Storage) => "storage",
        Some(Status::Unreplicated) => "unreplicated",
        _ => "other",
    }
}

/// An op code's name.
pub fn op_name(op: u32) -> &'static str {
    use guardian_shared::wire::Op;
    match decode_code::<Op>(op) {
        Some(Op::Check) => "check",
        Some(Op::Identify) => "identify",
        Some(Op::Enroll) => "enroll",
        Some(Op::Forget) => "forget",
        Some(Op::Classes) => "classes",
        Some(Op::Status) => "status",
        _ => "other",
    }
}

/// The bound on the `class` label of `guardian_checks_total`: the first `max` enrolled
/// classes checked get their own label, later ones share [`OTHER_CLASS_LABEL`], and a
/// claimed class that is not enrolled is [`UNKNOWN_CLASS_LABEL`]. Owned by the serving loop.
#[derive(Debug)]
pub struct ClassLabels {
    max: usize,
    labelled: HashSet<String>,
}

impl ClassLabels {
    /// At most `max` classes get a label of their own.
    pub fn new(max: usize) -> Self {
        Self {
            max,
            labelled: HashSet::new(),
        }
    }

    /// The label of a check that claimed `class` (`unknown`: answered unknown class).
    pub fn label(&mut self, class: &str, unknown: bool) -> String {
        if unknown {
            return UNKNOWN_CLASS_LABEL.to_owned();
        }
        if self.labelled.contains(class) {
            return class.to_owned();
        }
        if self.labelled.len() < self.max {
            self.labelled.insert(class.to_owned());
            return class.to_owned();
        }
        OTHER_CLASS_LABEL.to_owned()
    }
}

/// The Prometheus text format 0.0.4 of an OpenMetrics exposition, for scrapers that do
/// not ask for OpenMetrics (`promtool check metrics`, curl): counters are described under
/// their `_total` sample name, an info metric is a gauge named `<name>_info`, and the
/// `# UNIT` and `# EOF` lines go.
pub fn to_prometheus_text(openmetrics: &str) -> String {
    let mut out = String::with_capacity(openmetrics.len());
    let mut help: Option<(&str, &str)> = None;
    for line in openmetrics.lines() {
        if let Some(rest) = line.strip_prefix("# HELP ") {
            help = Some(rest.split_once(' ').unwrap_or((rest, "")));
            continue;
        }
        if let Some(rest) = line.strip_prefix("# TYPE ") {
            let (name, kind) = rest.split_once(' ').unwrap_or((rest, "untyped"));
            let (name, kind) = match kind {
                "counter" => (format!("{name}_total"), "counter"),
                "info" => (format!("{name}_info"), "gauge"),
                other => (name.to_owned(), other),
            };
            if let Some((_, text)) = help.take() {
                out.push_str(&format!("# HELP {name} {text}\n"));
            }
            out.push_str(&format!("# TYPE {name} {kind}\n"));
            continue;
        }
        if line.starts_with("# UNIT ") || line == "# EOF" {
            continue;
        }
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// Serve `GET /metrics` on `server` until `stop` is set: OpenMetrics 1.0 to a scraper that
/// asks for it (`Accept: application/openmetrics-text`, as Prometheus does), the
/// Prometheus text format 0.0.4 otherwise ([`to_prometheus_text`]). Every other request is
/// answered 404 (GET/HEAD) or 405.
pub fn serve_metrics(server: crate::http::Listener, registry: Registry, stop: Arc<AtomicBool>) {
    use crate::http::Response;
    crate::http::serve(server, &stop, "metrics", move |request| {
        match (request.method.as_str(), request.path.as_str()) {
            ("GET", "/metrics") => {
                let wants_openmetrics = request
                    .header("accept")
                    .is_some_and(|a| a.contains("application/openmetrics-text"));
                let mut body = String::new();
                match prometheus_client::encoding::text::encode(&mut body, &registry) {
                    Ok(()) => {
                        let (body, content_type) = if wants_openmetrics {
                            (
                                body,
                                "application/openmetrics-text; version=1.0.0; charset=utf-8",
                            )
                        } else {
                            (
                                to_prometheus_text(&body),
                                "text/plain; version=0.0.4; charset=utf-8",
                            )
                        };
                        Response {
                            status: 200,
                            content_type,
                            body: body.into_bytes(),
                        }
                    }
                    Err(_) => Response::text(500, "cannot encode the metrics\n"),
                }
            }
            ("GET" | "HEAD", _) => {
                Response::text(404, "not found: this port serves /metrics only\n")
            }
            _ => Response::text(405, "method not allowed\n"),
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use guardian_shared::verdict::NoGoReason;

    #[test]
    fn class_labels_are_bounded_and_unknown_classes_share_one() {
        let mut l = ClassLabels::new(2);
        assert_eq!(l.label("a", false), "a");
        assert_eq!(l.label("b", false), "b");
        assert_eq!(l.label("c", false), OTHER_CLASS_LABEL);
        assert_eq!(l.label("a", false), "a");
        assert_eq!(l.label("zzz", true), UNKNOWN_CLASS_LABEL);
    }

    #[test]
    fn exposition_names_every_family() {
        let m = Metrics::default();
        let wrong = NoGoReason::WrongTask {
            nearest: "task1".into(),
        };
        let v = Verdict::early("task0", wrong, "abc", 7);
        m.count_check(&Ok(v), "task0".into(), Duration::from_micros(300));
        m.set_state(3, 7, "abc");
        m.count_admin(guardian_shared::wire::Op::Enroll as u32, 0);
        m.dropped("queue-full");
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &m.registry()).unwrap();
        for needle in [
            "guardian_checks_total{verdict=\"no-go\",reason=\"wrong-task\",class=\"task0\"} 1",
            "guardian_check_duration_seconds_count 1",
            "guardian_bank_classes 3",
            "guardian_bank_version 7",
            "guardian_model_info{version=\"abc\"} 1",
            "guardian_admin_operations_total{op=\"enroll\",status=\"ok\"} 1",
            "guardian_record_dropped_total{cause=\"queue-full\"} 1",
            // Pre-set to 0: the first of each is an increase `rate()` sees.
            "guardian_record_dropped_total{cause=\"record-off\"} 0",
            "guardian_checks_total{verdict=\"no-go\",reason=\"geometry-mismatch\",class=\"task0\"} 0",
            "guardian_checks_total{verdict=\"go\",reason=\"none\",class=\"task0\"} 0",
            "# EOF",
        ] {
            assert!(text.contains(needle), "{needle} missing in\n{text}");
        }
        let old = to_prometheus_text(&text);
        for needle in [
            "# TYPE guardian_checks_total counter",
            "# HELP guardian_checks_total Checks answered",
            "# TYPE guardian_model_info gauge",
            "guardian_model_info{version=\"abc\"} 1",
            "# TYPE guardian_check_duration_seconds histogram",
        ] {
            assert!(old.contains(needle), "{needle} missing in\n{old}");
        }
        assert!(!old.contains("# EOF") && !old.contains("# UNIT"), "{old}");
    }
}
