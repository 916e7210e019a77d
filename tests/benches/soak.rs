//! Soak benchmark: at least a million checks from several planner threads against one real
//! `guardiand` serving the shipped model, every answer compared with the answer the same
//! daemon gave to the same request before the run. Prints the daemon's resident memory
//! (`VmRSS` from `/proc/<pid>/status`) after warm-up and at the end with the growth in %,
//! and the round-trip latency percentiles per window of requests.
//!
//! Run (see `docs/reliability.md`):
//! `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench soak`
//! Options after `--`: `--requests N` (default 1,000,000), `--threads N` (default 4),
//! `--window N` (default 100,000; the first window is the warm-up), `--model FILE`
//! (default `models/embedder.safetensors`), `--strokes DIR` (default
//! `../shared/omniglot/strokes`).

use guardian_robot::kinematics::PANDA_JOINTS;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Barrier, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use guardian_client::{Client, Decision, NoGoReason, Trajectory, Waypoint};
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::read_strokes;
use guardian_tests::harness::{Daemon, Expected, Setup, latin_drawing, workspace_root};

/// Latin characters enrolled as task classes, drawers used to enroll, drawers checked.
const CLASSES: u32 = 8;
const ENROLL_DRAWERS: std::ops::RangeInclusive<u32> = 1..=4;
const CHECK_DRAWERS: std::ops::RangeInclusive<u32> = 11..=14;

struct Opts {
    requests: u64,
    threads: usize,
    window: u64,
    model: PathBuf,
    strokes: PathBuf,
}

fn parse_opts() -> Result<Opts> {
    let mut o = Opts {
        requests: 1_000_000,
        threads: 4,
        window: 100_000,
        model: workspace_root().join("models/embedder.safetensors"),
        strokes: workspace_root().join("../shared/omniglot/strokes"),
    };
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = |what: &str| args.next().with_context(|| format!("{a} {what}"));
        match a.as_str() {
            "--requests" => o.requests = value("N")?.parse()?,
            "--threads" => o.threads = value("N")?.parse()?,
            "--window" => o.window = value("N")?.parse()?,
            "--model" => o.model = value("FILE")?.into(),
            "--strokes" => o.strokes = value("DIR")?.into(),
            // `cargo bench` passes `--bench`.
            _ => {}
        }
    }
    if o.threads == 0 || o.window == 0 || o.requests < 2 * o.window {
        bail!("need --threads >= 1 and --requests >= 2 x --window");
    }
    Ok(o)
}

struct Request {
    claim: String,
    plan: Trajectory,
    expected: Expected,
}

/// `VmRSS`, `RssAnon` (heap and stacks) and `RssShmem` (touched shared memory: the
/// iceoryx2 segments) of a process, KiB.
fn rss_kib(pid: u32) -> Result<[u64; 3]> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let field = |name: &str| -> Result<u64> {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .with_context(|| format!("no {name} in /proc/{pid}/status"))
    };
    Ok([field("VmRSS:")?, field("RssAnon:")?, field("RssShmem:")?])
}

/// p50, p90, p99, p99.9, max of microsecond samples.
fn percentiles(v: &mut [f32]) -> [f32; 5] {
    if v.is_empty() {
        return [f32::NAN; 5];
    }
    v.sort_by(f32::total_cmp);
    let q = |p: f64| {
        let i = ((p * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        v[i]
    };
    [q(0.5), q(0.9), q(0.99), q(0.999), v[v.len() - 1]]
}

/// Requests done, time since the start, daemon memory ([`rss_kib`]).
type Mark = (u64, Duration, [u64; 3]);

#[derive(Default)]
struct Outcome {
    /// (global sequence number, round trip in microseconds).
    latencies: Vec<(u64, f32)>,
    mismatched: u64,
    errors: BTreeMap<String, u64>,
    go: u64,
}

fn main() -> Result<()> {
    let o = parse_opts()?;
    println!("guardian soak benchmark");
    println!("{}", guardian_tests::harness::machine_line());

    // Real Omniglot drawings converted to dense Panda joint paths by the dataset library.
    let solver = PathSolver::new(&Geometry::default())?;
    let conv = |c: u32, d: u32| -> Result<Vec<Waypoint>> {
        let s = read_strokes(&latin_drawing(&o.strokes, c, d)?)?;
        Ok(convert_strokes(&solver, &s)?.dense.waypoints)
    };
    let mut s = Setup::new(0);
    s.model = o.model.clone();
    s.extra = "k-nearest = 3".into();
    let daemon = Daemon::start_with_env(&s, &[("RUST_LOG", "warn".into())]);
    let pid = daemon.pid();
    let client = Client::connect(s.client_config())?;
    let mut checks = Vec::new();
    for c in 1..=CLASSES {
        let name = format!("latin{c:02}");
        let examples = ENROLL_DRAWERS
            .map(|d| conv(c, d).map(|w| Trajectory::from_waypoints(&w, PANDA_JOINTS)))
            .collect::<Result<Vec<_>>>()?;
        client.enroll(&name, &examples)?;
        for d in CHECK_DRAWERS {
            checks.push((c, conv(c, d)?));
        }
    }
    // Every check drawing claims its own class, the next class and an unknown one; some
    // carry a NaN at a varying waypoint. The answers before the run are the reference.
    let mut requests = Vec::new();
    for (i, (c, w)) in checks.iter().enumerate() {
        let next = c % CLASSES + 1;
        for claim in [
            format!("latin{c:02}"),
            format!("latin{next:02}"),
            "not-enrolled".into(),
        ] {
            let plan = Trajectory::from_waypoints(w, PANDA_JOINTS);
            let v = client.check(&plan, &claim)?;
            requests.push(Request {
                claim,
                plan,
                expected: Expected::of(&v),
            });
        }
        let mut bad = w.clone();
        let at = (i * 7) % bad.len();
        bad[at][2] = f32::NAN;
        let plan = Trajectory::from_waypoints(&bad, PANDA_JOINTS);
        let v = client.check(&plan, &format!("latin{c:02}"))?;
        if !matches!(
            &v.decision,
            Decision::NoGo { reason: NoGoReason::InvalidTrajectory { index, .. } } if *index as usize == at
        ) {
            bail!("a NaN at waypoint {at} was answered {:?}", v.decision);
        }
        requests.push(Request {
            claim: format!("latin{c:02}"),
            plan,
            expected: Expected::of(&v),
        });
    }
    let ref_go = requests
        .iter()
        .filter(|r| r.expected.decision == Decision::Go)
        .count();
    let waypoints: usize = checks.iter().map(|(_, w)| w.len()).sum();
    println!(
        "  model {} | {} classes (Latin, drawers 1-4), {} distinct requests ({} go), {} waypoints per drawing on average",
        o.model.display(),
        CLASSES,
        requests.len(),
        ref_go,
        waypoints / checks.len()
    );
    println!(
        "  {} requests from {} client threads, windows of {}",
        o.requests, o.threads, o.window
    );
    drop(client);

    let requests = Arc::new(requests);
    let next = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicU64::new(0));
    let barrier = Arc::new(Barrier::new(o.threads + 1));
    // Clients stay connected until the end figures are taken.
    let end_barrier = Arc::new(Barrier::new(o.threads + 1));
    let mut handles = Vec::new();
    for t in 0..o.threads {
        let (requests, next, done, barrier, end_barrier) = (
            requests.clone(),
            next.clone(),
            done.clone(),
            barrier.clone(),
            end_barrier.clone(),
        );
        let cfg = s.client_config();
        let total = o.requests;
        handles.push(std::thread::spawn(move || -> Result<Outcome> {
            let client = Client::connect(cfg);
            barrier.wait();
            let client = client?;
            let mut out = Outcome::default();
            loop {
                let seq = next.fetch_add(1, Ordering::Relaxed);
                if seq >= total {
                    break;
                }
                let r = &requests[(seq as usize * 7 + t) % requests.len()];
                let t0 = Instant::now();
                let answer = client.check(&r.plan, &r.claim);
                let us = t0.elapsed().as_secs_f32() * 1e6;
                out.latencies.push((seq, us));
                match answer {
                    Ok(v) => {
                        out.go += u64::from(v.is_go());
                        if !r.expected.matches(&v) {
                            out.mismatched += 1;
                        }
                    }
                    Err(e) => *out.errors.entry(format!("{e}")).or_default() += 1,
                }
                done.fetch_add(1, Ordering::Relaxed);
            }
            end_barrier.wait();
            Ok(out)
        }));
    }

    // Progress, RSS and wall time whenever a window of requests completes.
    let finished = Arc::new(AtomicBool::new(false));
    let marks: Arc<Mutex<Vec<Mark>>> = Arc::new(Mutex::new(Vec::new()));
    barrier.wait();
    let start = Instant::now();
    let monitor = {
        let (done, finished, marks) = (done.clone(), finished.clone(), marks.clone());
        let (window, total) = (o.window, o.requests);
        std::thread::spawn(move || -> Result<()> {
            let mut next_mark = window;
            marks
                .lock()
                .map_err(|_| anyhow::anyhow!("poisoned"))?
                .push((0, Duration::ZERO, rss_kib(pid)?));
            while next_mark <= total {
                let n = done.load(Ordering::Relaxed);
                if n >= next_mark {
                    let rss = rss_kib(pid)?;
                    let at = start.elapsed();
                    println!(
                        "  {n:>9} requests  {:>7.1} s  daemon VmRSS {} KiB (anon {}, shmem {})  load {}",
                        at.as_secs_f64(),
                        rss[0],
                        rss[1],
                        rss[2],
                        guardian_tests::harness::load_average()
                    );
                    marks
                        .lock()
                        .map_err(|_| anyhow::anyhow!("poisoned"))?
                        .push((next_mark, at, rss));
                    next_mark += window;
                    continue;
                }
                if finished.load(Ordering::Relaxed) {
                    break;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            Ok(())
        })
    };
    end_barrier.wait();
    let wall = start.elapsed();
    let end_rss = rss_kib(pid)?;
    let mut outcomes = Vec::new();
    for h in handles {
        outcomes.push(
            h.join()
                .map_err(|_| anyhow::anyhow!("client thread panicked"))??,
        );
    }
    finished.store(true, Ordering::Relaxed);
    monitor
        .join()
        .map_err(|_| anyhow::anyhow!("monitor panicked"))??;
    let left_rss = rss_kib(pid)?;

    let status = Client::connect(s.client_config())?.status()?;
    drop(daemon);

    let windows = o.requests.div_ceil(o.window) as usize;
    let mut per_window: Vec<Vec<f32>> = vec![Vec::new(); windows];
    let (mut mismatched, mut go, mut answered) = (0u64, 0u64, 0u64);
    let mut errors: BTreeMap<String, u64> = BTreeMap::new();
    for out in outcomes {
        mismatched += out.mismatched;
        go += out.go;
        answered += out.latencies.len() as u64;
        for (seq, us) in out.latencies {
            per_window[(seq / o.window) as usize].push(us);
        }
        for (e, n) in out.errors {
            *errors.entry(e).or_default() += n;
        }
    }
    let lost: u64 = errors.values().sum();
    let marks = marks
        .lock()
        .map_err(|_| anyhow::anyhow!("poisoned"))?
        .clone();

    println!();
    println!(
        "{:>19} {:>8} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>11} {:>10}",
        "requests",
        "checks/s",
        "p50 us",
        "p90 us",
        "p99 us",
        "p99.9 us",
        "max us",
        "wall s",
        "VmRSS KiB",
        "anon KiB"
    );
    for (w, lat) in per_window.iter_mut().enumerate() {
        let [p50, p90, p99, p999, max] = percentiles(lat);
        let (from, to) = (
            w as u64 * o.window,
            ((w as u64 + 1) * o.window).min(o.requests),
        );
        let mark = |n: u64| marks.iter().find(|m| m.0 == n);
        let (wall_s, rate, rss, anon) = match (mark(from), mark(to)) {
            (Some(a), Some(b)) => (
                format!("{:.1}", b.1.as_secs_f64()),
                format!("{:.0}", (to - from) as f64 / (b.1 - a.1).as_secs_f64()),
                b.2[0].to_string(),
                b.2[1].to_string(),
            ),
            _ => ("-".into(), "-".into(), "-".into(), "-".into()),
        };
        println!(
            "{:>19} {rate:>8} {p50:>9.1} {p90:>9.1} {p99:>9.1} {p999:>9.1} {max:>9.1} {wall_s:>9} {rss:>11} {anon:>10}",
            format!("{from}-{to}")
        );
    }
    let warm = marks
        .iter()
        .find(|m| m.0 == o.window)
        .map(|m| m.2)
        .context("no RSS sample after the warm-up window")?;
    let growth = |i: usize| 100.0 * (end_rss[i] as f64 - warm[i] as f64) / warm[i] as f64;
    println!();
    println!(
        "daemon VmRSS: at start {} KiB, after warm-up ({} requests) {} KiB, at the end {} KiB: growth {:+.2}% (target < 5%)",
        marks.first().map_or(0, |m| m.2[0]),
        o.window,
        warm[0],
        end_rss[0],
        growth(0)
    );
    println!(
        "  of which RssAnon {} -> {} KiB ({:+.2}%), RssShmem {} -> {} KiB; after the clients disconnected VmRSS {} KiB",
        warm[1],
        end_rss[1],
        growth(1),
        warm[2],
        end_rss[2],
        left_rss[0]
    );
    println!(
        "answered {answered} of {} in {:.1} s ({:.0} checks/s): {go} go, {mismatched} mismatched, {lost} lost (errors)",
        o.requests,
        wall.as_secs_f64(),
        answered as f64 / wall.as_secs_f64()
    );
    for (e, n) in &errors {
        println!("  error x{n}: {e}");
    }
    println!(
        "daemon status: {} requests, {} errors, {} go, {} no-go; service time p50 {:.1} / p99 {:.1} us (last 4096)",
        status.requests,
        status.errors,
        status.go,
        status.no_go,
        status.latency_us.map_or(f32::NAN, |l| l[0]),
        status.latency_us.map_or(f32::NAN, |l| l[2]),
    );
    println!(
        "load average at end {}",
        guardian_tests::harness::load_average()
    );
    if mismatched > 0 || lost > 0 || answered != o.requests {
        bail!("{mismatched} mismatched and {lost} lost responses");
    }
    Ok(())
}
