//! The gate's one guardiand connection, on a thread of its own (the client is not `Send`):
//! a check with the claimed task, or in identify mode the nearest class then a check
//! against it. Every failure is an [`Outcome`] with `go = false`: nothing here turns an
//! error into go.

use std::sync::mpsc;
use std::time::Duration;

use futures::channel::oneshot;
use guardian_client::{CheckError, Client, ClientConfig, DaemonStatus, Decision, Trajectory};

use crate::config::GuardiandConfig;
use crate::plan::Plan;

/// What the screen decided about one plan.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// Forward it.
    pub go: bool,
    /// `go`, `no-go` or `error`.
    pub verdict: &'static str,
    /// Short reason code (see `msgs::Verdict::reason`).
    pub reason: &'static str,
    /// The sentence for `error_string` and the log.
    pub detail: String,
    /// Nearest class (empty if none).
    pub nearest: String,
    /// Distance to the claimed (or identified) class, NaN if none.
    pub distance: f32,
    /// Its threshold, NaN if none.
    pub threshold: f32,
    /// Model version ("" if guardiand did not answer).
    pub model_version: String,
    /// Bank version.
    pub bank_version: u64,
}

impl Outcome {
    /// A fail-closed outcome: guardiand did not give a verdict.
    pub fn failed(reason: &'static str, detail: impl Into<String>) -> Self {
        Self {
            go: false,
            verdict: "error",
            reason,
            detail: detail.into(),
            nearest: String::new(),
            distance: f32::NAN,
            threshold: f32::NAN,
            model_version: String::new(),
            bank_version: 0,
        }
    }
}

enum Job {
    Screen {
        plan: Plan,
        claim: Option<String>,
        reply: oneshot::Sender<Outcome>,
    },
    Status {
        reply: oneshot::Sender<Result<DaemonStatus, String>>,
    },
}

/// Handle to the screen thread. Dropping it ends the thread.
#[derive(Debug, Clone)]
pub struct Screen {
    jobs: mpsc::Sender<Job>,
    /// Longest wait for an answer before the goal is refused (fail closed).
    deadline: Duration,
}

impl std::fmt::Debug for Job {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Job")
    }
}

impl Screen {
    /// Start the thread; it connects lazily and again after every transport failure.
    pub fn start(config: &GuardiandConfig) -> std::io::Result<Self> {
        let timeout = Duration::from_millis(config.timeout_ms);
        let client_config = ClientConfig {
            service_name: config.service_name.clone(),
            timeout,
            iceoryx2_root_path: config.iceoryx2_root_path.clone(),
            iceoryx2_prefix: config.iceoryx2_prefix.clone(),
        };
        let (jobs, rx) = mpsc::channel::<Job>();
        std::thread::Builder::new()
            .name("guardiand-client".into())
            .spawn(move || worker(client_config, rx))?;
        // Identify mode makes two calls; a connect may precede them.
        Ok(Self {
            jobs,
            deadline: timeout * 3 + Duration::from_millis(200),
        })
    }

    /// Screen `plan` against `claim` (None: identify mode). Never fails: a lost thread, a
    /// timeout or any error is a refusing [`Outcome`].
    pub async fn screen(&self, plan: Plan, claim: Option<String>) -> Outcome {
        let (reply, answer) = oneshot::channel();
        if self.jobs.send(Job::Screen { plan, claim, reply }).is_err() {
            return Outcome::failed("internal", "the guardiand client thread is gone");
        }
        let timer = async {
            smol::Timer::after(self.deadline).await;
            None
        };
        let answer = async { Some(answer.await) };
        match futures::future::FutureExt::boxed(smol::future::or(answer, timer)).await {
            Some(Ok(outcome)) => outcome,
            Some(Err(_)) => Outcome::failed(
                "internal",
                "the guardiand client thread dropped the request",
            ),
            None => Outcome::failed(
                "timeout",
                format!("no verdict from guardiand within {:?}", self.deadline),
            ),
        }
    }

    /// guardiand's status (for /diagnostics).
    pub async fn status(&self) -> Result<DaemonStatus, String> {
        let (reply, answer) = oneshot::channel();
        self.jobs
            .send(Job::Status { reply })
            .map_err(|_| "the guardiand client thread is gone".to_string())?;
        let timer = async {
            smol::Timer::after(self.deadline).await;
            Err("no status from guardiand in time".to_string())
        };
        let answer = async {
            answer
                .await
                .unwrap_or_else(|_| Err("the guardiand client thread dropped the request".into()))
        };
        smol::future::or(answer, timer).await
    }
}

fn worker(config: ClientConfig, jobs: mpsc::Receiver<Job>) {
    let mut client: Option<Client> = None;
    while let Ok(job) = jobs.recv() {
        if client.is_none() {
            match Client::connect(config.clone()) {
                Ok(c) => client = Some(c),
                Err(e) => {
                    let detail =
                        format!("guardian error (fail closed): guardiand unreachable: {e}");
                    match job {
                        Job::Screen { reply, .. } => {
                            let _ = reply.send(Outcome::failed("guardiand-unreachable", detail));
                        }
                        Job::Status { reply } => {
                            let _ = reply.send(Err(detail));
                        }
                    }
                    continue;
                }
            }
        }
        let Some(c) = client.as_ref() else { continue };
        let keep = match job {
            Job::Screen { plan, claim, reply } => {
                let outcome = screen_one(c, &plan, claim.as_deref());
                let keep = outcome.verdict != "error";
                let _ = reply.send(outcome);
                keep
            }
            Job::Status { reply } => {
                let r = c.status();
                let keep = r.is_ok();
                let _ = reply.send(r.map_err(|e| e.to_string()));
                keep
            }
        };
        if !keep {
            // Reconnect next time: the daemon may have restarted.
            client = None;
        }
    }
}

fn screen_one(c: &Client, plan: &Plan, claim: Option<&str>) -> Outcome {
    let t = Trajectory::from_flat(plan.data.clone(), plan.channels);
    let class = match claim {
        Some(class) => class.to_string(),
        None => match c.identify(&t) {
            Ok(r) => match r.nearest.first() {
                Some(n) if n.distance <= n.threshold => n.class.clone(),
                Some(n) => {
                    return Outcome {
                        go: false,
                        verdict: "no-go",
                        reason: "outlier",
                        detail: format!(
                            "guardian no-go: outlier (identify mode: nearest class {:?} at distance {:.3} > threshold {:.3})",
                            n.class, n.distance, n.threshold
                        ),
                        nearest: n.class.clone(),
                        distance: n.distance,
                        threshold: n.threshold,
                        model_version: r.model_version,
                        bank_version: r.bank_version,
                    };
                }
                None => {
                    return no_verdict(
                        "outlier",
                        "guardian no-go: outlier (identify mode: no class enrolled)",
                    );
                }
            },
            Err(e) => return check_error(e),
        },
    };
    match c.check(&t, &class) {
        Ok(v) => {
            let nearest = v
                .nearest
                .first()
                .map(|n| n.class.clone())
                .unwrap_or_default();
            let distance = v.claimed_distance.unwrap_or(f32::NAN);
            let threshold = v.threshold.unwrap_or(f32::NAN);
            let mode = if claim.is_some() {
                "claimed"
            } else {
                "identified"
            };
            let (go, verdict, reason, detail) = match &v.decision {
                Decision::Go => (
                    true,
                    "go",
                    "genuine",
                    format!(
                        "guardian go: {mode} task {class:?}, distance {distance:.3} <= threshold {threshold:.3}"
                    ),
                ),
                Decision::NoGo { reason } => {
                    (
                        false,
                        "no-go",
                        // The reason's name as the record and the metrics write it.
                        reason.name(),
                        format!(
                            "guardian no-go: {reason}; {mode} task {class:?}, nearest class {:?}, distance {distance:.3}, threshold {threshold:.3}",
                            nearest
                        ),
                    )
                }
            };
            Outcome {
                go,
                verdict,
                reason,
                detail,
                nearest,
                distance,
                threshold,
                model_version: v.model_version,
                bank_version: v.bank_version,
            }
        }
        Err(e) => check_error(e),
    }
}

fn no_verdict(reason: &'static str, detail: &str) -> Outcome {
    Outcome {
        verdict: "no-go",
        ..Outcome::failed(reason, detail)
    }
}

fn check_error(e: CheckError) -> Outcome {
    match e {
        CheckError::Timeout { .. } => {
            Outcome::failed("timeout", format!("guardian error (fail closed): {e}"))
        }
        CheckError::NotServing { .. } | CheckError::Transport(_) => Outcome::failed(
            "guardiand-unreachable",
            format!("guardian error (fail closed): {e}"),
        ),
        CheckError::InvalidTrajectory { .. } => {
            no_verdict("invalid-trajectory", &format!("guardian no-go: {e}"))
        }
        CheckError::EmptyBank => no_verdict(
            "outlier",
            "guardian no-go: outlier (identify mode: no class enrolled)",
        ),
        CheckError::InvalidClassName(_) | CheckError::UnknownClass { .. } => {
            no_verdict("unknown-class", &format!("guardian no-go: {e}"))
        }
        other => Outcome::failed("internal", format!("guardian error (fail closed): {other}")),
    }
}
