//! The daemon's statistics: counters since start and the service times of recent requests,
//! with the percentiles sent in every response.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use guardian_shared::wire::VerdictCode;

const LATENCY_WINDOW: usize = 4096;

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
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Counters {
    /// Requests answered.
    pub requests: u64,
    /// Requests answered with an error status.
    pub errors: u64,
    /// Checks answered go.
    pub go: u64,
    /// Checks answered no-go.
    pub no_go: u64,
}

/// Counters, uptime and latency percentiles of a running daemon.
#[derive(Debug)]
pub struct Stats {
    started: Instant,
    counters: Counters,
    latencies: Latencies,
    /// Percentiles of `latencies` and when they were computed.
    summary: ([f32; 4], Option<Instant>),
}

impl Default for Stats {
    fn default() -> Self {
        Self {
            started: Instant::now(),
            counters: Counters::default(),
            latencies: Latencies::default(),
            summary: ([f32::NAN; 4], None),
        }
    }
}

impl Stats {
    /// Record the service time of one answered request.
    pub fn record_latency(&mut self, d: Duration) {
        self.latencies.push(d);
    }

    /// Count one answered request: whether it failed, and its verdict code.
    pub fn count(&mut self, failed: bool, verdict: u32) {
        self.counters.requests += 1;
        self.counters.errors += u64::from(failed);
        if verdict == VerdictCode::Go as u32 {
            self.counters.go += 1;
        } else if verdict == VerdictCode::NoGo as u32 {
            self.counters.no_go += 1;
        }
    }

    /// The counters so far.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// Milliseconds since start.
    pub fn uptime_ms(&self) -> u64 {
        u64::try_from(self.started.elapsed().as_millis()).unwrap_or(u64::MAX)
    }

    /// p50, p90, p99 and max service time in microseconds to report: recomputed when
    /// `fresh` (a status request) or when at least [`LATENCY_REFRESH`] old.
    pub fn latency_us(&mut self, fresh: bool) -> [f32; 4] {
        let stale = self
            .summary
            .1
            .is_none_or(|at| at.elapsed() >= LATENCY_REFRESH);
        if stale || fresh {
            self.summary = (self.latencies.percentiles(), Some(Instant::now()));
        }
        self.summary.0
    }
}
