//! Fleet figures, all from one run on loopback (three real `guardiand` processes with
//! fleet membership, Zenoh on `tcp/127.0.0.1:<port>`, scouting off):
//!
//! - replication delay: an enroll through member A's admin socket until member B (and C)
//!   answer a `classes` request listing it, p50 / p99 / max over the rounds, counted from
//!   the admin request (A's own enroll included) and from A's acknowledgment (A publishes
//!   the record before it acknowledges); members polled every 0.2 ms;
//! - a check's round trip from a client process to member B: over iceoryx2 (the local
//!   client) and over Zenoh (`RemoteClient`, signed request and answer), interleaved in
//!   the same run, p50 / p99.
//!
//! Run: `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench fleet`
//! Options after `--`: `--rounds N` (replication rounds, default 200), `--checks N` (checks
//! per transport, default 1000).

use std::time::{Duration, Instant};

use guardian_tests::fleet::{CONVERGE, Fleet, examples, has};
use guardian_tests::harness::traj;

fn pct(v: &mut [Duration], p: f64) -> Duration {
    v.sort();
    let i = ((v.len() as f64 - 1.0) * p).round() as usize;
    v[i.min(v.len() - 1)]
}

fn us(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let rounds = arg("--rounds", 200);
    let checks = arg("--checks", 1000);
    let mut f = Fleet::new(3);
    for i in 0..3 {
        f.start(i);
    }
    let all = [0, 1, 2];
    f.admin(0)
        .enroll("warmup", &examples(5, 0..3))
        .expect("enroll");
    f.converge(&all, |c| has(c, "warmup", 3));

    let (b, c) = (f.client(1), f.client(2));
    let admin = f.admin(0);
    let mut to_b = Vec::new();
    let mut to_all = Vec::new();
    let mut ack_to_all = Vec::new();
    for round in 0..rounds {
        let class = format!("r{round}");
        let t0 = Instant::now();
        admin
            .enroll(&class, &examples(round as u32 % 3, 0..2))
            .expect("enroll");
        let ack = t0.elapsed();
        let mut seen = [None, None];
        while seen.iter().any(Option::is_none) {
            for (k, client) in [&b, &c].into_iter().enumerate() {
                if seen[k].is_none()
                    && client
                        .classes()
                        .expect("classes")
                        .iter()
                        .any(|x| x.name == class)
                {
                    seen[k] = Some(t0.elapsed());
                }
            }
            assert!(t0.elapsed() < CONVERGE, "round {round} did not replicate");
            std::thread::sleep(Duration::from_micros(200));
        }
        let (sb, sc) = (seen[0].unwrap_or_default(), seen[1].unwrap_or_default());
        to_b.push(sb);
        to_all.push(sb.max(sc));
        ack_to_all.push(sb.max(sc).saturating_sub(ack));
        // Keep the bank small: forget it again (replicated too) before the next round.
        admin.forget(&class).expect("forget");
    }
    println!(
        "fleet bench: 3 members on loopback, {rounds} enroll rounds, {checks} checks per transport"
    );
    println!(
        "replication delay A -> B:        p50 {:>8.0} us  p99 {:>8.0} us  max {:>8.0} us",
        us(pct(&mut to_b, 0.5)),
        us(pct(&mut to_b, 0.99)),
        us(pct(&mut to_b, 1.0))
    );
    println!(
        "replication delay A -> B and C:  p50 {:>8.0} us  p99 {:>8.0} us  max {:>8.0} us",
        us(pct(&mut to_all, 0.5)),
        us(pct(&mut to_all, 0.99)),
        us(pct(&mut to_all, 1.0))
    );
    println!(
        "  the same after A's ack:        p50 {:>8.0} us  p99 {:>8.0} us  max {:>8.0} us",
        us(pct(&mut ack_to_all, 0.5)),
        us(pct(&mut ack_to_all, 0.99)),
        us(pct(&mut ack_to_all, 1.0))
    );

    // Check round trips on B: iceoryx2 and Zenoh interleaved.
    for c in 0..3u32 {
        f.admin(0)
            .enroll(&format!("task{c}"), &examples(c, 0..3))
            .expect("enroll");
    }
    f.converge(&all, |c| has(c, "task2", 3));
    let remote = f.remote(1, f.caller_key.clone());
    let local = f.client(1);
    let probe = traj(1, 9);
    for _ in 0..50 {
        remote.check(&probe, "task1").expect("warm-up");
        local.check(&probe, "task1").expect("warm-up");
    }
    let (mut iox, mut zen) = (Vec::with_capacity(checks), Vec::with_capacity(checks));
    for _ in 0..checks {
        let t = Instant::now();
        let l = local.check(&probe, "task1").expect("check");
        iox.push(t.elapsed());
        let t = Instant::now();
        let r = remote.check(&probe, "task1").expect("check");
        zen.push(t.elapsed());
        assert_eq!(l.decision, r.decision);
    }
    println!(
        "check round trip, iceoryx2:      p50 {:>8.0} us  p99 {:>8.0} us",
        us(pct(&mut iox, 0.5)),
        us(pct(&mut iox, 0.99))
    );
    println!(
        "check round trip, Zenoh remote:  p50 {:>8.0} us  p99 {:>8.0} us",
        us(pct(&mut zen, 0.5)),
        us(pct(&mut zen, 0.99))
    );
    // How long items from Zenoh waited for the serving loop (each member logs it at DEBUG):
    // a missed wake-up would show as a wait of a whole tick (tick-ms, 50 here).
    let mut waits: Vec<u64> = (0..3)
        .flat_map(|i| {
            f.log(i)
                .lines()
                .filter(|l| l.contains("fleet item taken by the serving loop"))
                .filter_map(|l| {
                    l.split("waited_us=")
                        .nth(1)?
                        .split_whitespace()
                        .next()?
                        .parse()
                        .ok()
                })
                .collect::<Vec<u64>>()
        })
        .collect();
    waits.sort_unstable();
    if !waits.is_empty() {
        let p = |q: f64| waits[((waits.len() - 1) as f64 * q).round() as usize];
        println!(
            "Zenoh -> serving loop hand-over: n {} p50 {:>8} us  p99 {:>8} us  max {:>8} us  over 40 ms {}",
            waits.len(),
            p(0.5),
            p(0.99),
            waits[waits.len() - 1],
            waits.iter().filter(|&&w| w > 40_000).count()
        );
    }
}
