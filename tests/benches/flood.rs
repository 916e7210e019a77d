//! Fairness under a flood, all figures from one run: a well-behaved planner's check round
//! trip (p50 / p99) against a real `guardiand`, alone and while one other client floods the
//! daemon back to back with maximum-size requests, keeping the 4 requests in flight that
//! iceoryx2 admits per client:
//!
//! - `check` flood: checks of 4,096 waypoints (the largest trajectory; the most expensive
//!   request a planner can send under admin separation);
//! - `enroll` flood: enrolls of 16 x 4,096 waypoints (the largest request, 2 MiB), which
//!   admin separation refuses from the header.
//!
//! Each is measured with per-client fairness on (`fair-batching = true`, the default) and
//! off, each daemon with admin separation on and micro-batching (`max-batch = 16`).
//!
//! Run: `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench flood`
//! Options after `--`: `--checks N` (well-behaved checks per phase, default 400).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use guardian_client::Trajectory;
use guardian_robot::kinematics::PANDA_JOINTS;
use guardian_shared::trajectory::{MAX_WAYPOINTS, Waypoint, to_flat};
use guardian_shared::wire::{MAX_EXAMPLES, Op, RequestHeader, encode_class_name};
use guardian_tests::harness::{Daemon, Setup, task, traj};

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Flood {
    None,
    Check,
    Enroll,
}

impl Flood {
    fn name(self) -> &'static str {
        match self {
            Self::None => "alone",
            Self::Check => "check flood (1 x 4096 waypoints)",
            Self::Enroll => "enroll flood (16 x 4096 waypoints)",
        }
    }
}

/// A valid trajectory of `n` waypoints: a synthetic task repeated.
fn long_plan(n: usize) -> Vec<Waypoint> {
    let base = task(0, 1);
    (0..n).map(|i| base[i % base.len()]).collect()
}

/// One client flooding the daemon until `stop`: 4 requests in flight, each re-sent as soon
/// as it is answered. Returns the number of answers.
fn flood(s: &Setup, kind: Flood, stop: Arc<AtomicBool>, answered: Arc<AtomicU64>) {
    let planner = s.raw_planner();
    let port = planner.client_port();
    let plan: Vec<f32> = to_flat(&long_plan(MAX_WAYPOINTS), PANDA_JOINTS);
    let (examples, payload) = match kind {
        Flood::Check => (1, plan),
        _ => (MAX_EXAMPLES, plan.repeat(MAX_EXAMPLES)),
    };
    let mut header = RequestHeader::new(
        0,
        if kind == Flood::Check {
            Op::Check
        } else {
            Op::Enroll
        },
    );
    header.channels = (PANDA_JOINTS + 1) as u32;
    header.examples = examples as u32;
    for w in header.waypoints.iter_mut().take(examples) {
        *w = MAX_WAYPOINTS as u32;
    }
    header.class_name = encode_class_name("task0").expect("name");
    let send = |id: u64| {
        let mut h = header;
        h.request_id = id;
        let mut r = port.loan_slice_uninit(payload.len()).expect("loan");
        *r.user_header_mut() = h;
        let pending = r.write_from_slice(&payload).send().expect("send");
        planner.wake.notify().expect("notify");
        pending
    };
    let mut id = 0;
    let mut pending: Vec<_> = (0..4)
        .map(|_| {
            id += 1;
            Some(send(id))
        })
        .collect();
    while !stop.load(Ordering::Relaxed) {
        let mut progressed = false;
        for slot in pending.iter_mut() {
            // The response and its pending request are dropped before the next send, so at
            // most 4 requests are active.
            let answered_now = slot
                .as_ref()
                .is_some_and(|p| matches!(p.receive(), Ok(Some(_))));
            if answered_now {
                *slot = None;
                answered.fetch_add(1, Ordering::Relaxed);
                id += 1;
                *slot = Some(send(id));
                progressed = true;
            }
        }
        if !progressed {
            std::thread::yield_now();
        }
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() -> Result<()> {
    let mut checks = 400usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--checks" => checks = args.next().unwrap_or_default().parse()?,
            "--bench" => {}
            other => bail!("unknown option {other}"),
        }
    }
    println!("guardian flood benchmark");
    println!("{}", guardian_tests::harness::machine_line());
    println!(
        "  well-behaved client: {checks} sequential checks of a {}-waypoint plan per phase",
        traj(1, 9).len()
    );
    println!();
    println!(
        "{:<9} {:<36} {:>9} {:>9} {:>9} {:>9} {:>14}",
        "fairness", "phase", "p50 us", "p99 us", "p50 x", "p99 x", "flood answers/s"
    );
    for fair in [true, false] {
        let mut s = Setup::new(70);
        s.extra = format!(
            "default-threshold = 1e9\nfair-batching = {fair}\nmax-batch = 16\n[admin]\nseparation = true\nsocket = {:?}\n",
            s.dir.path().join("admin.sock")
        );
        let s = Arc::new(s);
        let _d = Daemon::start(&s);
        let admin = guardian_client::AdminClient::new(
            s.dir.path().join("admin.sock"),
            Duration::from_secs(30),
        );
        for c in 0..4 {
            admin
                .enroll(&format!("task{c}"), &[traj(c, 1), traj(c, 2), traj(c, 3)])
                .map_err(|e| anyhow::anyhow!("enroll: {e}"))?;
        }
        let client = s.client();
        let plan: Trajectory = traj(1, 9);
        let mut base = (0.0, 0.0);
        for kind in [Flood::None, Flood::Check, Flood::Enroll] {
            let stop = Arc::new(AtomicBool::new(false));
            let answered = Arc::new(AtomicU64::new(0));
            let flooder = (kind != Flood::None).then(|| {
                let (stop, answered, s2) = (stop.clone(), answered.clone(), s.clone());
                std::thread::spawn(move || flood(&s2, kind, stop, answered))
            });
            // Let the flood reach its steady state.
            std::thread::sleep(Duration::from_millis(if flooder.is_some() {
                500
            } else {
                50
            }));
            let start = Instant::now();
            let first = answered.load(Ordering::Relaxed);
            let mut lat = Vec::with_capacity(checks);
            for _ in 0..checks {
                let t = Instant::now();
                let v = client
                    .check(&plan, "task1")
                    .map_err(|e| anyhow::anyhow!("check: {e}"))?;
                lat.push(t.elapsed().as_secs_f64() * 1e6);
                assert!(v.is_go(), "{:?}", v.decision);
            }
            let rate =
                (answered.load(Ordering::Relaxed) - first) as f64 / start.elapsed().as_secs_f64();
            stop.store(true, Ordering::Relaxed);
            if let Some(f) = flooder {
                f.join().expect("flooder");
            }
            lat.sort_by(f64::total_cmp);
            let (p50, p99) = (percentile(&lat, 0.5), percentile(&lat, 0.99));
            if kind == Flood::None {
                base = (p50, p99);
            }
            println!(
                "{:<9} {:<36} {:>9.0} {:>9.0} {:>9.2} {:>9.2} {:>14.0}",
                if fair { "on" } else { "off" },
                kind.name(),
                p50,
                p99,
                p50 / base.0,
                p99 / base.1,
                rate
            );
        }
    }
    Ok(())
}
