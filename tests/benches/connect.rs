//! A connecting client must not stall the others (issue 39): one persistent planner checks
//! a plan every millisecond against a real `guardiand`, alone and while a second *process*
//! connects, checks once and exits every 100 ms (a script, a monitor, `guardianctl`
//! coming and going). A control kind, other, runs the same processes against a second
//! `guardiand` on the same machine: what a client starting, connecting and leaving costs
//! the planner through the shared cores alone, without the planner's daemon doing anything
//! for it. Phases rotate (alone, other, churn, alone, …) so that all see the same machine; for each kind the planner's round trip p50 / p99 / max over all
//! its rounds is printed, with the p99 ratios and the targets (churn p99 <= 1.5 x alone
//! p99, churn max below 5 ms).
//!
//! Run: `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench connect`. Options after
//! `--`: `--rounds N` (3 of each kind), `--seconds S` (5 per round), `--period-ms P` (100),
//! `--max-clients N` (the daemon's `max-clients`, default its own 32).

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use guardian_client::{Client, ClientConfig};
use guardian_tests::harness::{Daemon, Setup, traj};

/// Set in a child process: connect with this service name, check once, exit.
const CHILD: &str = "GUARDIAN_CONNECT_BENCH_CHILD";
/// The kinds of round, in the order they rotate.
#[derive(Clone, Copy, PartialEq)]
enum Kind {
    Alone,
    Other,
    Churn,
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn child() -> Result<()> {
    let env = |k: &str| std::env::var(k).with_context(|| format!("{k} not set"));
    let client = Client::connect(ClientConfig {
        service_name: env(CHILD)?,
        timeout: Duration::from_secs(10),
        iceoryx2_root_path: Some(env("GUARDIAN_CONNECT_BENCH_ROOT")?.into()),
        iceoryx2_prefix: Some(env("GUARDIAN_CONNECT_BENCH_PREFIX")?),
    })?;
    client.check(&traj(2, 9), "task2")?;
    Ok(())
}

fn main() -> Result<()> {
    if std::env::var_os(CHILD).is_some() {
        return child();
    }
    let (mut rounds, mut seconds, mut period_ms) = (3usize, 5u64, 100u64);
    let mut max_clients: Option<usize> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--rounds" => rounds = args.next().unwrap_or_default().parse()?,
            "--seconds" => seconds = args.next().unwrap_or_default().parse()?,
            "--period-ms" => period_ms = args.next().unwrap_or_default().parse()?,
            "--max-clients" => max_clients = Some(args.next().unwrap_or_default().parse()?),
            "--bench" => {}
            other => bail!("unknown option {other}"),
        }
    }
    println!("guardian connect-churn benchmark");
    println!("{}", guardian_tests::harness::machine_line());
    let mut s = Setup::new(71);
    s.extra = "default-threshold = 1e9\n".into();
    if let Some(n) = max_clients {
        s.extra.push_str(&format!("max-clients = {n}\n"));
    }
    let daemon = Daemon::start(&s);
    // The control's daemon: same configuration, its own service, prefix and directory.
    let mut other = Setup::new(72);
    other.extra = s.extra.clone();
    let _other_daemon = Daemon::start(&other);
    other
        .client()
        .enroll("task2", &[traj(2, 1), traj(2, 2), traj(2, 3)])
        .map_err(|e| anyhow::anyhow!("enroll (other daemon): {e}"))?;
    let planner = s.client();
    for c in 0..4 {
        planner
            .enroll(&format!("task{c}"), &[traj(c, 1), traj(c, 2), traj(c, 3)])
            .map_err(|e| anyhow::anyhow!("enroll: {e}"))?;
    }
    let plan = traj(1, 9);
    println!(
        "  planner: one check of a {}-waypoint plan every 1 ms, {rounds} rounds of {seconds} s per kind, rotating; churn: a new process connects, checks once and exits every {period_ms} ms; other (control): the same processes against a second guardiand; max-clients {}",
        plan.len(),
        max_clients.map_or_else(|| "default".to_owned(), |n| n.to_string())
    );
    println!();
    let exe = std::env::current_exe()?;
    let (mut alone, mut others, mut churn) = (Vec::new(), Vec::new(), Vec::new());
    let (mut spawned, mut failed) = (0usize, 0usize);
    let kinds = [Kind::Alone, Kind::Other, Kind::Churn];
    for round in 0..kinds.len() * rounds {
        let kind = kinds[round % kinds.len()];
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let spawner = (kind != Kind::Alone).then(|| {
            let (stop, exe) = (stop.clone(), exe.clone());
            let s = if kind == Kind::Other { &other } else { &s };
            let cfg = (
                s.service.clone(),
                s.dir.path().join("iox"),
                s.prefix.clone(),
            );
            std::thread::spawn(move || {
                let (mut n, mut bad) = (0usize, 0usize);
                let mut running: Vec<std::process::Child> = Vec::new();
                let mut next = Instant::now();
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    next += Duration::from_millis(period_ms);
                    match std::process::Command::new(&exe)
                        .env(CHILD, &cfg.0)
                        .env("GUARDIAN_CONNECT_BENCH_ROOT", &cfg.1)
                        .env("GUARDIAN_CONNECT_BENCH_PREFIX", &cfg.2)
                        .stdout(std::process::Stdio::null())
                        .spawn()
                    {
                        Ok(c) => running.push(c),
                        Err(_) => bad += 1,
                    }
                    n += 1;
                    running.retain_mut(|c| match c.try_wait() {
                        Ok(Some(st)) => {
                            bad += usize::from(!st.success());
                            false
                        }
                        Ok(None) => true,
                        Err(_) => false,
                    });
                    if let Some(w) = next.checked_duration_since(Instant::now()) {
                        std::thread::sleep(w);
                    }
                }
                for mut c in running {
                    bad += usize::from(!c.wait().map(|s| s.success()).unwrap_or(false));
                }
                (n, bad)
            })
        });
        let lat = match kind {
            Kind::Alone => &mut alone,
            Kind::Other => &mut others,
            Kind::Churn => &mut churn,
        };
        let end = Instant::now() + Duration::from_secs(seconds);
        let mut next = Instant::now();
        while Instant::now() < end {
            next += Duration::from_millis(1);
            let t = Instant::now();
            let v = planner
                .check(&plan, "task1")
                .map_err(|e| anyhow::anyhow!("check: {e}"))?;
            lat.push(t.elapsed().as_secs_f64() * 1e6);
            assert!(v.is_go(), "{:?}", v.decision);
            match next.checked_duration_since(Instant::now()) {
                Some(w) => std::thread::sleep(w),
                None => next = Instant::now(),
            }
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(h) = spawner {
            let (n, bad) = h.join().expect("spawner");
            if kind == Kind::Churn {
                spawned += n;
            }
            failed += bad;
        }
    }
    let row = |name: &str, v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let over = v.iter().filter(|&&x| x > 5000.0).count();
        println!(
            "{name:<8} {:>8} {:>8.0} {:>8.0} {:>8.0} {:>12}",
            v.len(),
            percentile(v, 0.5),
            percentile(v, 0.99),
            v[v.len() - 1],
            over
        );
        (percentile(v, 0.99), v[v.len() - 1])
    };
    println!(
        "{:<8} {:>8} {:>8} {:>8} {:>8} {:>12}",
        "phase", "checks", "p50 us", "p99 us", "max us", "over 5 ms"
    );
    let (a99, _) = row("alone", &mut alone);
    let (o99, _) = row("other", &mut others);
    let (c99, cmax) = row("churn", &mut churn);
    println!();
    println!("connecting processes: {spawned} started; child processes failed: {failed}");
    let verdict = |ok: bool| if ok { "met" } else { "MISSED" };
    println!(
        "other p99 / alone p99   {:>6.2}  (control: the same clients, another guardiand)",
        o99 / a99
    );
    println!(
        "churn p99 / other p99   {:>6.2}  (what serving them adds on the planner's guardiand)",
        c99 / o99
    );
    println!(
        "churn p99 / alone p99   {:>6.2}  <= 1.5   {}",
        c99 / a99,
        verdict(c99 <= 1.5 * a99)
    );
    println!(
        "churn max               {:>6.0} us < 5000 us {}",
        cmax,
        verdict(cmax < 5000.0)
    );
    // What setting up a new client's wake-up costs (the daemon's opener thread logs it at
    // DEBUG): the time the serving loop spent blocked per new client before it moved there.
    let mut opens: Vec<f64> = daemon
        .log()
        .lines()
        .filter(|l| l.contains("client notifier opened"))
        .filter_map(|l| {
            l.split("micros=")
                .nth(1)?
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
        .collect();
    if !opens.is_empty() {
        opens.sort_by(f64::total_cmp);
        println!(
            "opening a new client's event service + notifier (off the serving loop): n {} p50 {:.0} us p99 {:.0} us max {:.0} us",
            opens.len(),
            percentile(&opens, 0.5),
            percentile(&opens, 0.99),
            opens[opens.len() - 1]
        );
    }
    // The daemon's warnings, by message (a refused connection, a failed receive).
    let mut warnings = std::collections::BTreeMap::<String, usize>::new();
    for l in daemon.log().lines().filter(|l| l.contains(" WARN ")) {
        let msg = l.split(": ").skip(1).collect::<Vec<_>>().join(": ");
        let msg: String = msg.chars().take(160).collect();
        *warnings.entry(msg).or_default() += 1;
    }
    for (msg, n) in &warnings {
        println!("daemon WARN x{n}: {msg}");
    }
    println!(
        "load average at end {}",
        guardian_tests::harness::load_average()
    );
    Ok(())
}
