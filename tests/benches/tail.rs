//! Where a planner's tail latency under a flood comes from: a planner checking every 10 ms
//! against a real `guardiand`, alone and while 8 other clients check back to back, with the
//! daemon at normal priority and reniced (`nice -10`). For each phase it prints the
//! planner's round trip (p50 / p99 / max), the daemon's own service time (its status
//! percentiles: batch start to response sent), and how long the daemon's serving thread and
//! the planner's thread waited on the kernel's run queue (`/proc/.../schedstat`, run delay
//! per scheduling slice): waiting for a core is the OS scheduler's part, not the daemon's.
//!
//! Run: `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench tail` (needs root for the
//! reniced phase; without it that phase is skipped). Options after `--`: `--checks N` (500),
//! `--flooders N` (8).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use guardian_tests::harness::{Daemon, Setup, traj};

/// (run time ns, run-queue wait ns, slices) of a thread, from its `schedstat`.
fn schedstat(path: &str) -> (u64, u64, u64) {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let v: Vec<u64> = text
        .split_whitespace()
        .filter_map(|x| x.parse().ok())
        .collect();
    (
        v.first().copied().unwrap_or(0),
        v.get(1).copied().unwrap_or(0),
        v.get(2).copied().unwrap_or(0),
    )
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() -> Result<()> {
    let (mut checks, mut flooders) = (500usize, 8usize);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--checks" => checks = args.next().unwrap_or_default().parse()?,
            "--flooders" => flooders = args.next().unwrap_or_default().parse()?,
            "--bench" => {}
            other => bail!("unknown option {other}"),
        }
    }
    let root = std::fs::metadata("/proc/self")
        .map(|m| std::os::unix::fs::MetadataExt::uid(&m) == 0)
        .unwrap_or(false);
    println!("guardian tail-latency benchmark");
    println!("{}", guardian_tests::harness::machine_line());
    println!(
        "  planner: {checks} checks of a {}-waypoint plan, one every 10 ms; flood: {flooders} clients checking back to back",
        traj(1, 9).len()
    );
    println!();
    println!(
        "{:<28} {:>8} {:>8} {:>8} {:>10} {:>10} {:>12} {:>12} {:>10}",
        "phase",
        "p50 us",
        "p99 us",
        "max us",
        "svc p99",
        "svc max",
        "daemon wait",
        "planner wait",
        "flood/s"
    );
    let mut s = Setup::new(71);
    s.extra = "default-threshold = 1e9\n".into();
    let s = Arc::new(s);
    let d = Daemon::start(&s);
    let client = s.client();
    for c in 0..4 {
        client
            .enroll(&format!("task{c}"), &[traj(c, 1), traj(c, 2), traj(c, 3)])
            .map_err(|e| anyhow::anyhow!("enroll: {e}"))?;
    }
    let daemon_stat = format!("/proc/{}/task/{}/schedstat", d.pid(), d.pid());
    let plan = traj(1, 9);
    let phases: &[(&str, usize, bool)] = &[
        ("alone", 0, false),
        ("flood", flooders, false),
        ("flood, daemon at nice -10", flooders, true),
    ];
    for &(name, n, renice) in phases {
        if renice && !root {
            println!("{name:<28} skipped (renice needs root)");
            continue;
        }
        let nice = if renice { "-10" } else { "0" };
        std::process::Command::new("renice")
            .args(["-n", nice, "-p", &d.pid().to_string()])
            .output()?;
        let stop = Arc::new(AtomicBool::new(false));
        let answered = Arc::new(AtomicU64::new(0));
        let threads: Vec<_> = (0..n)
            .map(|i| {
                let (stop, answered, s2) = (stop.clone(), answered.clone(), s.clone());
                std::thread::spawn(move || {
                    let c = s2.client();
                    let t = traj((i % 4) as u32, 10 + (i / 4) as u32);
                    while !stop.load(Ordering::Relaxed) {
                        if c.check(&t, "task0").is_ok() {
                            answered.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                })
            })
            .collect();
        std::thread::sleep(Duration::from_millis(if n > 0 { 1000 } else { 50 }));
        let (d0, p0) = (
            schedstat(&daemon_stat),
            schedstat("/proc/thread-self/schedstat"),
        );
        let first = answered.load(Ordering::Relaxed);
        let start = Instant::now();
        let mut lat = Vec::with_capacity(checks);
        let mut next = Instant::now();
        for _ in 0..checks {
            next += Duration::from_millis(10);
            let t = Instant::now();
            let v = client
                .check(&plan, "task1")
                .map_err(|e| anyhow::anyhow!("check: {e}"))?;
            lat.push(t.elapsed().as_secs_f64() * 1e6);
            assert!(v.is_go(), "{:?}", v.decision);
            if let Some(wait) = next.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        let (d1, p1) = (
            schedstat(&daemon_stat),
            schedstat("/proc/thread-self/schedstat"),
        );
        let rate =
            (answered.load(Ordering::Relaxed) - first) as f64 / start.elapsed().as_secs_f64();
        let status = client
            .status()
            .map_err(|e| anyhow::anyhow!("status: {e}"))?;
        stop.store(true, Ordering::Relaxed);
        for t in threads {
            t.join().expect("flooder");
        }
        lat.sort_by(f64::total_cmp);
        // Mean run-queue wait per scheduling slice, microseconds.
        let wait = |a: (u64, u64, u64), b: (u64, u64, u64)| {
            (b.1 - a.1) as f64 / 1e3 / (b.2 - a.2).max(1) as f64
        };
        let (svc_p99, svc_max) = status
            .latency_us
            .map_or((f32::NAN, f32::NAN), |[_, _, p99, max]| (p99, max));
        println!(
            "{:<28} {:>8.0} {:>8.0} {:>8.0} {:>10.0} {:>10.0} {:>12.0} {:>12.0} {:>10.0}",
            name,
            percentile(&lat, 0.5),
            percentile(&lat, 0.99),
            lat[lat.len() - 1],
            svc_p99,
            svc_max,
            wait(d0, d1),
            wait(p0, p1),
            rate
        );
    }
    println!();
    println!(
        "svc: the daemon's service time (status, last 4096 requests); wait: mean run-queue wait per scheduling slice (schedstat), us"
    );
    Ok(())
}
