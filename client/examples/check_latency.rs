//! Round-trip latency of `Client::check` against a running daemon, for comparison with other
//! clients in the same run (`python/bench.py` runs it beside the Python package's checks).
//!
//! `check_latency PLAN.csv CLASS N [SERVICE [ROOT_PATH [PREFIX]]]` checks the plan (one
//! waypoint per line, comma-separated) N times after 50 warm-up checks and prints one JSON
//! line: `{"n":..,"p50_us":..,"p99_us":..,"go":..}`.

use std::time::{Duration, Instant};

use guardian_client::{Client, ClientConfig, Trajectory};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 {
        return Err("usage: check_latency PLAN.csv CLASS N [SERVICE [ROOT_PATH [PREFIX]]]".into());
    }
    let text = std::fs::read_to_string(&args[0])?;
    let mut data = Vec::new();
    let mut channels = 0;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let row: Vec<f32> = line
            .split(',')
            .map(|v| v.trim().parse::<f32>())
            .collect::<Result<_, _>>()?;
        channels = row.len();
        data.extend(row);
    }
    let plan = Trajectory::from_flat(data, channels);
    let n: usize = args[2].parse()?;
    let mut config = ClientConfig::default();
    if let Some(s) = args.get(3) {
        config.service_name = s.clone();
    }
    config.iceoryx2_root_path = args.get(4).map(Into::into);
    config.iceoryx2_prefix = args.get(5).cloned();
    let client = Client::connect(config)?;
    for _ in 0..50 {
        client.check(&plan, &args[1])?;
    }
    let mut times: Vec<Duration> = Vec::with_capacity(n);
    let mut go = 0;
    for _ in 0..n {
        let t0 = Instant::now();
        let v = client.check(&plan, &args[1])?;
        times.push(t0.elapsed());
        go += usize::from(v.is_go());
    }
    times.sort();
    let pct = |p: f64| {
        let i = ((p * times.len() as f64).ceil() as usize).clamp(1, times.len()) - 1;
        times[i].as_secs_f64() * 1e6
    };
    println!(
        "{{\"n\":{n},\"p50_us\":{:.1},\"p99_us\":{:.1},\"go\":{go}}}",
        pct(0.50),
        pct(0.99)
    );
    Ok(())
}
