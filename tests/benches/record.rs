//! The verdict record must not slow checks (issue 43): two real `guardiand`s with the same
//! model and classes, one with the record on (`[record] enabled = true`, the default) and
//! one with it off, checked alternately by one planner (on, off, on, off, … one check every
//! millisecond), half the checks genuine (go) and half the same plan claimed as another
//! task (no-go, whose plan the record keeps). For each daemon: the planner's round trip
//! p50 / p99 / max, the daemon's own service time percentiles (its status), the p50 and p99
//! ratios on/off, and the record's written and dropped counts from `/metrics`.
//!
//! Which daemon goes first in a pair alternates every two pairs, so neither always follows
//! the other's record commit. `--control` runs the same with the record off in both
//! daemons (an A/A run: the ratios the host's noise alone gives).
//!
//! Run: `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench record`. Options after
//! `--`: `--checks N` per daemon (20000), `--control`.

use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use guardian_client::Client;
use guardian_tests::harness::{self, Daemon, Setup, traj};

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn start(record: bool) -> Result<(Setup, Daemon, Client)> {
    let mut s = Setup::new(7);
    s.extra = "default-threshold = 1e9\n".into();
    s.tables = format!(
        "{}[record]\nenabled = {record}\n",
        harness::METRICS_ANY_PORT
    );
    let d = Daemon::start(&s);
    let client = s.client();
    harness::enroll_tasks(&client, &[0, 1, 2, 3]);
    Ok((s, d, client))
}

/// The value of a metric line starting with `prefix` (summed over its label sets).
fn metric(text: &str, prefix: &str) -> f64 {
    text.lines()
        .filter(|l| l.starts_with(prefix))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .fold(0.0, |a, b| a + b)
}

fn main() -> Result<()> {
    let mut checks = 20_000usize;
    let mut control = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--checks" => checks = args.next().unwrap_or_default().parse()?,
            "--control" => control = true,
            "--bench" => {}
            other => bail!("unknown option {other}"),
        }
    }
    println!("guardian verdict-record benchmark (paired: record on / off, alternating checks)");
    println!("{}", harness::machine_line());
    if control {
        println!("  control (A/A): the record is off in both daemons");
    }
    let on = start(!control)?;
    let off = start(false)?;
    let plan = traj(1, 11);
    println!(
        "  {checks} checks per daemon of a {}-waypoint plan, one every 1 ms, alternating daemons; half go (claimed task1), half wrong task (claimed task2, plan recorded)",
        plan.len()
    );
    println!();
    let mut lat = [Vec::with_capacity(checks), Vec::with_capacity(checks)];
    let mut next = Instant::now();
    for i in 0..2 * checks {
        // Order within a pair: on first, then off first, every two pairs.
        let which = (i % 2) ^ ((i / 4) % 2);
        let client = if which == 0 { &on.2 } else { &off.2 };
        let claim = if (i / 2) % 2 == 0 { "task1" } else { "task2" };
        next += Duration::from_millis(1) / 2;
        let t = Instant::now();
        let v = client
            .check(&plan, claim)
            .map_err(|e| anyhow::anyhow!("check: {e}"))?;
        lat[which].push(t.elapsed().as_secs_f64() * 1e6);
        assert_eq!(v.is_go(), claim == "task1", "{:?}", v.decision);
        match next.checked_duration_since(Instant::now()) {
            Some(w) => std::thread::sleep(w),
            None => next = Instant::now(),
        }
    }
    println!(
        "{:<11} {:>8} {:>8} {:>8} {:>8}   {:>22}",
        "record", "checks", "p50 us", "p99 us", "max us", "daemon p50/p99 us"
    );
    let mut p = [[0.0; 2]; 2];
    for (k, name) in [(0, "on"), (1, "off")] {
        let v = &mut lat[k];
        v.sort_by(f64::total_cmp);
        let client = if k == 0 { &on.2 } else { &off.2 };
        let st = client
            .status()
            .map_err(|e| anyhow::anyhow!("status: {e}"))?;
        let [d50, _, d99, _] = st.latency_us.unwrap_or([f32::NAN; 4]);
        p[k] = [percentile(v, 0.5), percentile(v, 0.99)];
        println!(
            "{name:<11} {:>8} {:>8.0} {:>8.0} {:>8.0}   {:>10.0} / {:<10.0}",
            v.len(),
            p[k][0],
            p[k][1],
            v[v.len() - 1],
            d50,
            d99
        );
    }
    println!();
    println!(
        "on / off    p50 {:.3}   p99 {:.3}",
        p[0][0] / p[1][0],
        p[0][1] / p[1][1]
    );
    // The record's own account (the writer commits within moments; give it one second).
    std::thread::sleep(Duration::from_secs(1));
    let (code, text) = harness::http_get(&on.1.metrics_address(), "/metrics")?;
    if code != 200 {
        bail!("metrics answered {code}");
    }
    println!(
        "record on: written {}, dropped {} (queue full or off), enabled {}",
        metric(&text, "guardian_record_written_total"),
        metric(&text, "guardian_record_dropped_total"),
        metric(&text, "guardian_record_enabled")
    );
    let db = on.0.state_dir().join("verdicts.sqlite");
    let bytes: u64 = ["", "-wal", "-shm"]
        .iter()
        .filter_map(|s| std::fs::metadata(format!("{}{s}", db.display())).ok())
        .map(|m| m.len())
        .sum();
    println!("record files: {bytes} bytes");
    println!("load average at end {}", harness::load_average());
    Ok(())
}
