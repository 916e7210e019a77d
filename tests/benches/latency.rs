//! Latency and throughput of the go/no-go screen, all figures from one run:
//!
//! - the embedding forward pass, batch 1: candle (the reference) and the fast path
//!   (`guardian_models::sequence::forward`), plus features + forward and preprocessing + embedding;
//! - `guardiand`'s compute per check in this process: its own `Screen` built from the same
//!   configuration (shipped model and default bank, workcell rules on, the same classes
//!   enrolled) answering whole check requests, and each stage alone;
//! - the compute floor: model FLOPs / the GEMM rate measured here on one core;
//! - the round trip planner -> `guardiand` -> verdict over iceoryx2 with a spawned daemon,
//!   in `event` and `busy-poll` serving mode;
//! - a baseline in the same run: the same check served by the same screen code over a Unix
//!   domain socket with JSON (newline-delimited) encoding, in a separate process;
//! - throughput with 1, 4 and 16 concurrent planner clients.
//!
//! Run (see `docs/performance.md`):
//! `RAYON_NUM_THREADS=1 cargo bench -p guardian-tests --bench latency`
//! Options after `--`: `--model FILE` (default `models/embedder.safetensors`, else random
//! weights) and `--bank FILE` (its default bank), `--strokes DIR` (default
//! `../shared/omniglot/strokes`), `--quick`; `--baseline-model FILE [--baseline-bank FILE]`
//! adds a paired before/after figure — the whole check of both models in one process,
//! alternating rounds, and the p50 ratio — and `--paired-only` stops after it.
//! The bench builds `guardiand` with the bench's own profile before spawning it
//! (`GUARDIAND_BIN` overrides the binary).

use guardian_robot::kinematics::PANDA_JOINTS;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use guardian_client::{Client, Trajectory, Verdict};
use guardian_daemon::config::Config;
use guardian_daemon::screen::Screen;
use guardian_daemon::state::{load_bank, load_model};
use guardian_models::embedder::{EMBED_DIM, Embedder};
use guardian_models::sequence::forward::{Scratch, sgemm};
use guardian_omniglot::dataset::convert_strokes;
use guardian_omniglot::path::{Geometry, PathSolver};
use guardian_omniglot::strokes::read_strokes;
use guardian_shared::trajectory::Waypoint;
use guardian_shared::wire::{
    Op, ReasonCode, RequestHeader, VerdictCode, decode_code, decode_text, encode_class_name,
};
use guardian_tests::harness::{Daemon, Setup, latin_drawing, workspace_root};
use serde::{Deserialize, Serialize};

/// Latin characters enrolled as task classes, drawers used to enroll, drawers checked.
const CLASSES: u32 = 8;
const ENROLL_DRAWERS: std::ops::RangeInclusive<u32> = 1..=4;
const CHECK_DRAWERS: std::ops::RangeInclusive<u32> = 11..=14;

struct Opts {
    model: Option<PathBuf>,
    /// The default bank served with `model` (when it is not the shipped model).
    bank: Option<PathBuf>,
    /// A second model (and its default bank) for the paired before/after check.
    baseline_model: Option<PathBuf>,
    baseline_bank: Option<PathBuf>,
    /// Only the paired comparison (and what it needs).
    paired_only: bool,
    strokes: PathBuf,
    quick: bool,
}

fn parse_opts() -> Result<Opts> {
    let mut args = std::env::args().skip(1);
    let mut o = Opts {
        model: None,
        bank: None,
        baseline_model: None,
        baseline_bank: None,
        paired_only: false,
        strokes: workspace_root().join("../shared/omniglot/strokes"),
        quick: false,
    };
    while let Some(a) = args.next() {
        match a.as_str() {
            "--model" => o.model = Some(args.next().context("--model FILE")?.into()),
            "--strokes" => o.strokes = args.next().context("--strokes DIR")?.into(),
            "--quick" => o.quick = true,
            "--bank" => o.bank = Some(args.next().context("--bank FILE")?.into()),
            "--baseline-model" => {
                o.baseline_model = Some(args.next().context("--baseline-model FILE")?.into());
            }
            "--baseline-bank" => {
                o.baseline_bank = Some(args.next().context("--baseline-bank FILE")?.into());
            }
            "--paired-only" => o.paired_only = true,
            // `cargo bench` passes `--bench`; ignore other harness flags too.
            _ => {}
        }
    }
    Ok(o)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--uds-server") {
        let socket = args.get(i + 1).context("--uds-server SOCKET CONFIG")?;
        let config = args.get(i + 2).context("--uds-server SOCKET CONFIG")?;
        return uds_server(Path::new(socket), Path::new(config));
    }
    run(parse_opts()?)
}

// ---------------------------------------------------------------- statistics

#[derive(Clone, Copy)]
struct Stats {
    n: usize,
    p50: f64,
    p99: f64,
    p999: f64,
    max: f64,
}

/// Percentiles (microseconds) of durations.
fn stats(samples: &[Duration]) -> Stats {
    let mut v: Vec<f64> = samples.iter().map(|d| d.as_secs_f64() * 1e6).collect();
    v.sort_by(f64::total_cmp);
    let q = |p: f64| {
        let i = ((p * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
        v[i]
    };
    Stats {
        n: v.len(),
        p50: q(0.5),
        p99: q(0.99),
        p999: q(0.999),
        max: v[v.len() - 1],
    }
}

fn print_header() {
    println!(
        "{:<46} {:>7} {:>9} {:>9} {:>9} {:>9}",
        "path (batch 1)", "n", "p50 us", "p99 us", "p99.9 us", "max us"
    );
}

fn print_row(name: &str, s: &Stats) {
    println!(
        "{:<46} {:>7} {:>9.1} {:>9.1} {:>9.1} {:>9.1}",
        name, s.n, s.p50, s.p99, s.p999, s.max
    );
}

/// Time `f` `n` times after `warm` untimed calls.
fn time_n(warm: usize, n: usize, mut f: impl FnMut() -> Result<()>) -> Result<Vec<Duration>> {
    for _ in 0..warm {
        f()?;
    }
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        f()?;
        out.push(t.elapsed());
    }
    Ok(out)
}

// ---------------------------------------------------------------- data

struct Drawings {
    /// (class, examples) to enroll.
    enroll: Vec<(String, Vec<Trajectory>)>,
    /// (class, trajectory) to check, with its dense waypoints.
    checks: Vec<(String, Vec<Waypoint>)>,
}

fn load_drawings(strokes: &Path) -> Result<Drawings> {
    let solver = PathSolver::new(&Geometry::default())?;
    let conv = |c: u32, d: u32| -> Result<Vec<Waypoint>> {
        let s = read_strokes(&latin_drawing(strokes, c, d)?)?;
        Ok(convert_strokes(&solver, &s)?.dense.waypoints)
    };
    let mut enroll = Vec::new();
    let mut checks = Vec::new();
    for c in 1..=CLASSES {
        let name = format!("latin{c:02}");
        let ex = ENROLL_DRAWERS
            .map(|d| conv(c, d).map(|w| Trajectory::from_waypoints(&w, PANDA_JOINTS)))
            .collect::<Result<Vec<_>>>()?;
        enroll.push((name.clone(), ex));
        for d in CHECK_DRAWERS {
            checks.push((name.clone(), conv(c, d)?));
        }
    }
    Ok(Drawings { enroll, checks })
}

// ---------------------------------------------------------------- guardiand

/// A deployment: the tests' harness set-up (its own directory, service name and iceoryx2
/// prefix; `/metrics` on a free loopback port) with the bench's model and bank, the
/// workcell rules on as shipped, three nearest classes.
fn deployment(model: &Path, default_bank: Option<PathBuf>) -> Setup {
    let mut s = Setup::new(0);
    s.model = model.to_path_buf();
    s.default_bank = default_bank;
    s.workcell_rules = true;
    configure(&mut s, "event", 16);
    s
}

/// Set `s`'s serving mode and batch size (written with its config).
fn configure(s: &mut Setup, mode: &str, max_batch: usize) {
    s.extra = format!("serving-mode = {mode:?}\nmax-batch = {max_batch}\nk-nearest = 3");
}

/// Start guardiand in `mode` with `max_batch` on the harness (warnings only in its log, so
/// no log line per request).
fn start(s: &mut Setup, mode: &str, max_batch: usize) -> Daemon {
    configure(s, mode, max_batch);
    Daemon::start_with_env(s, &[("RUST_LOG", "warn".into())])
}

/// SIGTERM (so shared memory is released) and wait for the exit.
fn stop(mut d: Daemon) {
    d.signal("TERM");
    d.wait_exit();
}

/// The daemon's own p50, p90, p99, max service time (us) of its recent requests.
fn service_times(client: &Client) -> Result<[f32; 4]> {
    let s = client
        .status()
        .map_err(|e| anyhow::anyhow!("status: {e}"))?;
    Ok(s.latency_us.unwrap_or([f32::NAN; 4]))
}

fn check_ok(client: &Client, t: &Trajectory, class: &str) -> Result<Verdict> {
    client
        .check(t, class)
        .map_err(|e| anyhow::anyhow!("check {class}: {e}"))
}

/// Round trips of one client, cycling through the check drawings.
/// Round trips of one client, cycling through the check drawings, each followed by one
/// timed call of `forward` in this process: the two lists are taken under the same
/// conditions, so their ratio does not depend on what the shared machine did in between.
fn round_trips(
    client: &Client,
    checks: &[(String, Trajectory)],
    warm: usize,
    n: usize,
    forward: &mut dyn FnMut() -> Result<()>,
) -> Result<(Vec<Duration>, Vec<Duration>)> {
    let (mut rt, mut fwd) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for i in 0..warm + n {
        let (class, t) = &checks[i % checks.len()];
        let start = Instant::now();
        check_ok(client, t, class)?;
        let round_trip = start.elapsed();
        let start = Instant::now();
        forward()?;
        let forward_time = start.elapsed();
        if i >= warm {
            rt.push(round_trip);
            fwd.push(forward_time);
        }
    }
    Ok((rt, fwd))
}

struct Throughput {
    clients: usize,
    max_batch: usize,
    checks_per_s: f64,
    lat: Stats,
}

/// `clients` threads, each with its own connection, checking for `run_for`.
fn throughput(
    dep: &Setup,
    checks: &Arc<Vec<(String, Trajectory)>>,
    clients: usize,
    max_batch: usize,
    run_for: Duration,
) -> Result<Throughput> {
    let barrier = Arc::new(Barrier::new(clients + 1));
    let mut handles = Vec::new();
    for c in 0..clients {
        let (barrier, checks, cfg) = (barrier.clone(), checks.clone(), dep.client_config());
        handles.push(std::thread::spawn(move || -> Result<Vec<Duration>> {
            let client = Client::connect(cfg).map_err(|e| anyhow::anyhow!("{e}"));
            barrier.wait();
            let client = client?;
            let mut lat = Vec::new();
            let start = Instant::now();
            let mut i = c * 7;
            while start.elapsed() < run_for {
                let (class, t) = &checks[i % checks.len()];
                i += 1;
                let t0 = Instant::now();
                check_ok(&client, t, class)?;
                lat.push(t0.elapsed());
            }
            Ok(lat)
        }));
    }
    barrier.wait();
    let start = Instant::now();
    let mut all = Vec::new();
    for h in handles {
        let lat = h
            .join()
            .map_err(|_| anyhow::anyhow!("client thread panicked"))??;
        all.extend(lat);
    }
    let elapsed = start.elapsed().as_secs_f64();
    Ok(Throughput {
        clients,
        max_batch,
        checks_per_s: all.len() as f64 / elapsed,
        lat: stats(&all),
    })
}

// ---------------------------------------------------------------- guardiand's compute

/// A request header and payload for `op` with the given trajectories.
fn request(op: Op, class: &str, examples: &[&[Waypoint]]) -> Result<(RequestHeader, Vec<f32>)> {
    let mut h = RequestHeader::new(1, op);
    h.channels = 8;
    h.examples = u32::try_from(examples.len())?;
    for (slot, t) in h.waypoints.iter_mut().zip(examples) {
        *slot = u32::try_from(t.len())?;
    }
    h.class_name = encode_class_name(class)?;
    Ok((
        h,
        examples
            .iter()
            .flat_map(|t| guardian_shared::trajectory::to_flat(t, PANDA_JOINTS))
            .collect(),
    ))
}

/// What `guardiand` computes for a check, in this process: its own `Screen` built from the
/// same configuration (model, shipped bank, workcell rules) with the same classes enrolled,
/// answering whole requests, and each stage of a check alone.
/// Check requests as the wire carries them: header and payload.
type Requests = Vec<(RequestHeader, Vec<f32>)>;

/// A `Screen` in this process built from `dep`'s configuration, the Latin classes enrolled
/// through it, and one check request per check drawing.
fn in_process_screen(
    dep: &Setup,
    drawings: &Drawings,
    name: &str,
) -> Result<(Screen, Config, Requests)> {
    let config = Config::from_file(&dep.write_config())?;
    let (embedder, station) = load_model(&config)?;
    let panda = station.robot().clone();
    let (bank, _) = load_bank(&config, &embedder, &station)?;
    let state = dep.dir.path().join(name);
    std::fs::create_dir_all(&state)?;
    let mut screen = Screen::new(
        embedder,
        station,
        bank,
        state.join("bank.gcb"),
        config.k_nearest,
    );
    for (class, ex) in &drawings.enroll {
        let ws: Vec<Vec<Waypoint>> = ex
            .iter()
            .map(|t| guardian_shared::trajectory::from_flat(t.as_flat(), 8, panda.limits()))
            .collect::<Result<_, _>>()?;
        let refs: Vec<&[Waypoint]> = ws.iter().map(Vec::as_slice).collect();
        let (h, p) = request(Op::Enroll, class, &refs)?;
        let r = screen.handle(&h, &p).response;
        if r.status != 0 {
            bail!("in-process enrolment of {class}: status {}", r.status);
        }
    }
    let reqs: Requests = drawings
        .checks
        .iter()
        .map(|(c, w)| request(Op::Check, c, &[w]))
        .collect::<Result<_>>()?;
    Ok((screen, config, reqs))
}

/// The whole check (`Screen::handle`) of two deployments that differ only in their model
/// (and its default bank), timed in alternating rounds over the same requests so both see
/// the same machine: `(baseline, current)` samples.
fn paired_checks(
    baseline: &Setup,
    current: &Setup,
    drawings: &Drawings,
    n: usize,
) -> Result<(Vec<Duration>, Vec<Duration>)> {
    let (mut a, _, reqs) = in_process_screen(baseline, drawings, "paired-baseline")?;
    let (mut b, _, _) = in_process_screen(current, drawings, "paired-current")?;
    let (mut ta, mut tb) = (Vec::new(), Vec::new());
    let rounds = 20;
    let mut i = 0usize;
    for r in 0..rounds + 2 {
        let warm = if r < 2 { 50 } else { 0 };
        for (screen, out) in [(&mut a, &mut ta), (&mut b, &mut tb)] {
            let t = time_n(warm, n / rounds, || {
                i += 1;
                let (h, p) = &reqs[i % reqs.len()];
                std::hint::black_box(screen.handle(h, p));
                Ok(())
            })?;
            if r >= 2 {
                out.extend(t);
            }
        }
    }
    Ok((ta, tb))
}

fn compute_breakdown(
    dep: &Setup,
    drawings: &Drawings,
    n: usize,
) -> Result<Vec<(&'static str, Vec<Duration>)>> {
    use guardian_robot::workcell::inspect_with;
    use guardian_screen::check::{self, Embedded, Prepared};
    let (mut screen, config, reqs) = in_process_screen(dep, drawings, "in-process")?;
    let len = reqs.len();
    let (station, bank, embedder, k) = (
        screen.station().clone(),
        screen.bank().clone(),
        screen.embedder().clone(),
        config.k_nearest,
    );
    let (panda, cell) = (station.robot(), station.workcell());
    // Each stage's input, computed once so each stage is timed alone.
    let waypoints: Vec<Vec<Waypoint>> = reqs
        .iter()
        .map(|(_, p)| guardian_shared::trajectory::from_flat(p, 8, panda.limits()))
        .collect::<Result<_, _>>()?;
    let resampled: Vec<_> = waypoints
        .iter()
        .map(|w| inspect_with(panda, cell, w).map(|i| i.resampled))
        .collect::<Result<_, _>>()?;
    // The check pipeline's plan-only stages: the embedding and the pen path of each check.
    let embedded: Vec<Embedded> = waypoints
        .iter()
        .map(|w| match check::prepare(&embedder, &station, w) {
            Ok(Prepared::Embedded(e)) => Ok(*e),
            Ok(early) => bail!("a bench check stopped before the embedding: {early:?}"),
            Err(e) => Err(anyhow::anyhow!(e)),
        })
        .collect::<Result<_>>()?;
    let geometry: Vec<_> = embedded.iter().map(Embedded::geometry).collect();
    // Each stage timed over the checks in turn.
    let cycling = |f: &mut dyn FnMut(usize) -> Result<()>| {
        let mut i = 0usize;
        time_n(50, n, || {
            i += 1;
            f(i % len)
        })
    };
    let mut out = vec![
        (
            "Screen::handle, a whole check",
            cycling(&mut |j| {
                let (h, p) = &reqs[j];
                std::hint::black_box(screen.handle(h, p));
                Ok(())
            })?,
        ),
        (
            "  validate, FK poses, workcell rules, resample",
            cycling(&mut |j| {
                std::hint::black_box(inspect_with(panda, cell, &waypoints[j])?);
                Ok(())
            })?,
        ),
        (
            "  embed (pen path, features, fast forward)",
            cycling(&mut |j| {
                let e = embedder.embed_with_pen_path(panda, &resampled[j]);
                std::hint::black_box(e.map_err(|e| anyhow::anyhow!(e))?);
                Ok(())
            })?,
        ),
    ];
    if bank.geometry_calibration().is_some() {
        out.push((
            "  plan geometry of that pen path",
            cycling(&mut |j| {
                std::hint::black_box(embedded[j].geometry());
                Ok(())
            })?,
        ));
    }
    out.push((
        "  bank decision (k nearest, geometry score)",
        cycling(&mut |j| {
            let class = &drawings.checks[j].0;
            let e = &embedded[j].embedding;
            let d = bank.decide_with_geometry(e, geometry[j].as_ref(), class, k);
            std::hint::black_box(d);
            Ok(())
        })?,
    ));
    println!(
        "  in-process screen: {} classes in the bank, geometry calibration {}",
        bank.len(),
        if bank.geometry_calibration().is_some() {
            "on"
        } else {
            "off"
        }
    );
    Ok(out)
}

// ---------------------------------------------------------------- UDS + JSON baseline

#[derive(Serialize, Deserialize)]
struct JsonRequest {
    op: String,
    class: String,
    /// One row per waypoint: q1..q7, tool.
    waypoints: Vec<Vec<f32>>,
}

#[derive(Serialize, Deserialize, Debug, PartialEq)]
struct JsonNeighbour {
    class: String,
    distance: f32,
}

#[derive(Serialize, Deserialize, Debug)]
struct JsonResponse {
    status: u32,
    verdict: String,
    reason: String,
    claimed_distance: Option<f32>,
    threshold: Option<f32>,
    nearest: Vec<JsonNeighbour>,
    model_version: String,
}

/// The baseline server: the daemon's screen (same model, same bank, same code path for a
/// check) behind a Unix socket speaking one JSON object per line.
fn uds_server(socket: &Path, config: &Path) -> Result<()> {
    let config = Config::from_file(config)?;
    let (embedder, station) = load_model(&config)?;
    let (bank, _) = load_bank(&config, &embedder, &station)?;
    let mut screen = Screen::new(
        embedder,
        station,
        bank,
        config.bank_path(),
        config.k_nearest,
    );
    let listener = UnixListener::bind(socket)?;
    // One connection at a time, served until it closes; "quit" ends the server.
    for stream in listener.incoming() {
        let stream = stream?;
        let mut reader = BufReader::new(stream.try_clone()?);
        let mut writer = stream;
        let mut line = String::new();
        let mut id = 0u64;
        loop {
            line.clear();
            if reader.read_line(&mut line)? == 0 {
                break;
            }
            if line.trim() == "quit" {
                return Ok(());
            }
            id += 1;
            let req: JsonRequest = serde_json::from_str(&line)?;
            if req.op != "check" {
                bail!("baseline serves only checks");
            }
            let mut h = RequestHeader::new(id, Op::Check);
            h.channels = 8;
            h.examples = 1;
            h.waypoints[0] = u32::try_from(req.waypoints.len())?;
            h.class_name = encode_class_name(&req.class)?;
            let payload: Vec<f32> = req.waypoints.iter().flatten().copied().collect();
            let answer = screen.handle(&h, &payload);
            let (r, entries) = (answer.response, answer.entries);
            let opt = |v: f32| if v.is_nan() { None } else { Some(v) };
            let resp = JsonResponse {
                status: r.status,
                verdict: match decode_code::<VerdictCode>(r.verdict) {
                    Some(VerdictCode::Go) => "go",
                    Some(VerdictCode::NoGo) => "no-go",
                    _ => "none",
                }
                .into(),
                reason: format!("{:?}", decode_code::<ReasonCode>(r.reason)),
                claimed_distance: opt(r.claimed_distance),
                threshold: opt(r.threshold),
                nearest: entries
                    .iter()
                    .map(|e| JsonNeighbour {
                        class: decode_text(&e.name),
                        distance: e.distance,
                    })
                    .collect(),
                model_version: decode_text(&r.model_version),
            };
            let mut out = serde_json::to_vec(&resp)?;
            out.push(b'\n');
            writer.write_all(&out)?;
        }
    }
    Ok(())
}

struct UdsClient {
    reader: BufReader<UnixStream>,
    writer: UnixStream,
    line: String,
}

impl UdsClient {
    fn connect(socket: &Path) -> Result<Self> {
        let start = Instant::now();
        let stream = loop {
            match UnixStream::connect(socket) {
                Ok(s) => break s,
                Err(e) if start.elapsed() > Duration::from_secs(60) => {
                    return Err(e).context("baseline server did not come up");
                }
                Err(_) => std::thread::sleep(Duration::from_millis(20)),
            }
        };
        Ok(Self {
            reader: BufReader::new(stream.try_clone()?),
            writer: stream,
            line: String::new(),
        })
    }

    fn check(&mut self, waypoints: &[Waypoint], class: &str) -> Result<JsonResponse> {
        let req = JsonRequest {
            op: "check".into(),
            class: class.into(),
            waypoints: waypoints
                .iter()
                .map(|w| {
                    guardian_shared::trajectory::to_flat(std::slice::from_ref(w), PANDA_JOINTS)
                })
                .collect(),
        };
        let mut out = serde_json::to_vec(&req)?;
        out.push(b'\n');
        self.writer.write_all(&out)?;
        self.line.clear();
        if self.reader.read_line(&mut self.line)? == 0 {
            bail!("baseline server closed the connection");
        }
        Ok(serde_json::from_str(&self.line)?)
    }
}

// ---------------------------------------------------------------- the run

fn run(o: Opts) -> Result<()> {
    let (n_fwd, n_rt, run_for) = if o.quick {
        (300, 1_000, Duration::from_millis(500))
    } else {
        (3_000, 10_000, Duration::from_secs(3))
    };
    println!("guardian latency benchmark");
    println!("{}", guardian_tests::harness::machine_line());
    let tmp = tempfile::tempdir()?;
    let shipped = workspace_root().join("models/embedder.safetensors");
    let model_path = match &o.model {
        Some(p) => p.clone(),
        None if shipped.exists() => shipped,
        None => {
            let p = tmp.path().join("random.safetensors");
            Embedder::random(1).save(&p)?;
            println!("  NOTE: models/embedder.safetensors not found; using RANDOM weights");
            p
        }
    };
    let embedder = Embedder::load(&model_path)?;
    println!(
        "  model {} ({}), {} network(s): {}",
        model_path.display(),
        embedder.version(),
        embedder.nets().len(),
        embedder.config_json()
    );
    let t = Instant::now();
    let drawings = load_drawings(&o.strokes)?;
    let mean_wp = drawings.checks.iter().map(|c| c.1.len()).sum::<usize>() as f64
        / drawings.checks.len() as f64;
    println!(
        "  data: {} classes (Latin), {} enrolment and {} check drawings, {:.0} waypoints \
         ({:.1} KiB) per check on average, converted in {:.1} s",
        drawings.enroll.len(),
        drawings.enroll.iter().map(|e| e.1.len()).sum::<usize>(),
        drawings.checks.len(),
        mean_wp,
        mean_wp * 32.0 / 1024.0,
        t.elapsed().as_secs_f64()
    );

    // ---- forward passes, batch 1: every network of the model on its view of one plan
    let samples: Vec<_> = drawings
        .checks
        .iter()
        .map(|(_, w)| guardian_robot::preprocess::preprocess(w))
        .collect::<Result<_, _>>()?;
    // Per network: its input for the first check drawing (forward, and reversed when
    // averaging), copies, steps and channels.
    let path = guardian_robot::pen::pen_path(&samples[0]);
    let inputs: Vec<(Vec<f32>, usize, usize, usize)> = embedder
        .nets()
        .iter()
        .map(|net| {
            let cfg = net.config();
            let joints = cfg.features == guardian_models::features::FeatureKind::Joints;
            let copies = if cfg.reverse_average && !joints { 2 } else { 1 };
            let values = cfg.features.values();
            let mut feats = vec![0.0f32; copies * values];
            let (fwd, bwd) = feats.split_at_mut(values);
            if joints {
                guardian_models::features::compute(cfg.features, &samples[0], fwd);
            } else {
                guardian_models::features::path_features(
                    cfg.features,
                    &path,
                    &Default::default(),
                    fwd,
                );
            }
            if copies == 2 {
                let rev = guardian_models::features::Augment {
                    reverse: true,
                    ..Default::default()
                };
                guardian_models::features::path_features(cfg.features, &path, &rev, bwd);
            }
            (feats, copies, cfg.features.steps(), cfg.features.channels())
        })
        .collect();
    let candle_nets = embedder
        .nets()
        .iter()
        .map(|n| n.to_net())
        .collect::<candle_core::Result<Vec<_>>>()?;
    let candle_fwd = time_n(50, n_fwd, || {
        for (net, (feats, copies, steps, c)) in candle_nets.iter().zip(&inputs) {
            let x = candle_core::Tensor::from_slice(
                feats,
                (*copies, *steps, *c),
                &candle_core::Device::Cpu,
            )?;
            let e = net.forward(&x)?.flatten_all()?.to_vec1::<f32>()?;
            std::hint::black_box(e);
        }
        Ok(())
    })?;
    let mut scratch: Vec<Scratch> = embedder.nets().iter().map(|_| Scratch::default()).collect();
    let mut out = vec![0.0f32; 2 * EMBED_DIM];
    let mut forward_once = || -> Result<()> {
        for ((net, (feats, copies, steps, _)), scratch) in
            embedder.nets().iter().zip(&inputs).zip(&mut scratch)
        {
            let d = net.config().embed_dim;
            net.forward(feats, *copies, *steps, scratch, &mut out[..copies * d])?;
            std::hint::black_box(&out);
        }
        Ok(())
    };
    // The compute floor's GEMM rate, timed in rounds alternating with the fast forward so
    // that both see the same machine: one 512^3 GEMM, then n_fwd / rounds forwards.
    let flops = embedder.flops();
    let (m, n, kk) = (512usize, 512usize, 512usize);
    let a = vec![0.5f32; m * kk];
    let b = vec![0.25f32; kk * n];
    let mut d = vec![0.0f32; m * n];
    let rounds = if o.quick { 10 } else { 40 };
    let (mut gemm_t, mut fast_fwd) = (Vec::new(), Vec::new());
    for r in 0..rounds + 3 {
        let start = Instant::now();
        sgemm(m, n, kk, &a, &b, &mut d, false)?;
        std::hint::black_box(&d);
        let g = start.elapsed();
        let f = time_n(
            if r < 3 { 50 } else { 0 },
            n_fwd / rounds,
            &mut forward_once,
        )?;
        // The first three rounds warm up.
        if r >= 3 {
            gemm_t.push(g);
            fast_fwd.extend(f);
        }
    }
    let panda = guardian_robot::kinematics::default_panda();
    let mut k = 0usize;
    let embed = time_n(50, n_fwd, || {
        k += 1;
        std::hint::black_box(embedder.embed(panda, &samples[k % samples.len()])?);
        Ok(())
    })?;
    // Preprocessing and the pen path alone, with the specialised position FK (serving) and
    // through the general chain with full frames (the path before it, kept as reference).
    let mut k = 0usize;
    let prep = time_n(50, n_fwd, || {
        k += 1;
        let w = &drawings.checks[k % samples.len()].1;
        std::hint::black_box(guardian_robot::preprocess::preprocess(w)?);
        Ok(())
    })?;
    let mut k = 0usize;
    let prep_ref = time_n(50, n_fwd, || {
        k += 1;
        let w = &drawings.checks[k % samples.len()].1;
        std::hint::black_box(guardian_robot::preprocess::preprocess_reference(panda, w)?);
        Ok(())
    })?;
    let mut k = 0usize;
    let path_fk = time_n(50, n_fwd, || {
        k += 1;
        std::hint::black_box(guardian_robot::pen::pen_path(&samples[k % samples.len()]));
        Ok(())
    })?;
    let mut k = 0usize;
    let path_ref = time_n(50, n_fwd, || {
        k += 1;
        std::hint::black_box(guardian_robot::pen::pen_path_reference(
            &samples[k % samples.len()],
        ));
        Ok(())
    })?;
    let mut k = 0usize;
    let full = time_n(50, n_fwd, || {
        k += 1;
        let x = guardian_robot::preprocess::preprocess(&drawings.checks[k % samples.len()].1)?;
        std::hint::black_box(embedder.embed(panda, &x)?);
        Ok(())
    })?;

    // ---- compute floor
    let gemm_flops = 2.0 * (m * n * kk) as f64;
    let mut rates: Vec<f64> = gemm_t
        .iter()
        .map(|t| gemm_flops / t.as_secs_f64() / 1e9)
        .collect();
    rates.sort_by(f64::total_cmp);
    let rate_med = rates[rates.len() / 2];
    let rate_best = rates[rates.len() - 1];
    let floor_us = flops as f64 / (rate_med * 1e9) * 1e6;

    // ---- guardiand over iceoryx2
    let default_bank = o.bank.clone().or_else(|| {
        Some(workspace_root().join("models/default-bank.gcb")).filter(|b| {
            b.exists() && o.model.is_none() && model_path.ends_with("models/embedder.safetensors")
        })
    });
    let mut dep = deployment(&model_path, default_bank);
    if let Some(base) = &o.baseline_model {
        let baseline = deployment(base, o.baseline_bank.clone());
        let (a, b) = paired_checks(&baseline, &dep, &drawings, n_fwd)?;
        let (sa, sb) = (stats(&a), stats(&b));
        println!();
        println!(
            "paired whole check (Screen::handle), alternating rounds: baseline {} vs this model {}",
            base.display(),
            model_path.display()
        );
        print_header();
        print_row("baseline model", &sa);
        print_row("this model", &sb);
        println!(
            "whole check p50 ratio this/baseline: {:.2} (p99 {:.2})",
            sb.p50 / sa.p50,
            sb.p99 / sa.p99
        );
        if o.paired_only {
            return Ok(());
        }
    }
    let breakdown = compute_breakdown(&dep, &drawings, n_fwd)?;
    let checks: Arc<Vec<(String, Trajectory)>> = Arc::new(
        drawings
            .checks
            .iter()
            .map(|(c, w)| (c.clone(), Trajectory::from_waypoints(w, PANDA_JOINTS)))
            .collect(),
    );
    let daemon = start(&mut dep, "event", 16);
    let client = Client::connect(dep.client_config()).map_err(|e| anyhow::anyhow!("{e}"))?;
    for (class, ex) in &drawings.enroll {
        client
            .enroll(class, ex)
            .map_err(|e| anyhow::anyhow!("enroll {class}: {e}"))?;
    }
    let mut go = 0;
    let mut verdicts = Vec::new();
    for (class, t) in checks.iter() {
        let v = check_ok(&client, t, class)?;
        go += usize::from(v.is_go());
        verdicts.push(v);
    }
    println!(
        "  checks of unseen drawers against their true class: {go} of {} go",
        checks.len()
    );
    let (rt_event, fwd_event) = round_trips(&client, &checks, 200, n_rt, &mut forward_once)?;
    let served_event = service_times(&client)?;
    let mut tput = Vec::new();
    for clients in [1, 4, 16] {
        tput.push(throughput(&dep, &checks, clients, 16, run_for)?);
    }
    drop(client);
    stop(daemon);
    // The same without micro-batching.
    let daemon = start(&mut dep, "event", 1);
    for clients in [4, 16] {
        tput.push(throughput(&dep, &checks, clients, 1, run_for)?);
    }
    stop(daemon);

    let daemon = start(&mut dep, "busy-poll", 16);
    let mut client = Client::connect(dep.client_config()).map_err(|e| anyhow::anyhow!("{e}"))?;
    let (rt_busy, fwd_busy) = round_trips(&client, &checks, 200, n_rt, &mut forward_once)?;
    // The planner polls for its answer too instead of sleeping on the notification.
    client.set_spin(Duration::from_millis(5));
    let (rt_busy_spin, fwd_busy_spin) =
        round_trips(&client, &checks, 200, n_rt, &mut forward_once)?;
    let served_busy = service_times(&client)?;
    drop(client);
    stop(daemon);

    // ---- UDS + JSON baseline, same screen, same model, same bank
    let socket = dep.dir.path().join("baseline.sock");
    configure(&mut dep, "event", 16);
    let config = dep.write_config();
    let mut server = Command::new(std::env::current_exe()?)
        .arg("--uds-server")
        .arg(&socket)
        .arg(&config)
        .stdout(Stdio::null())
        .spawn()?;
    let mut uds = UdsClient::connect(&socket)?;
    for ((class, w), v) in drawings.checks.iter().zip(&verdicts) {
        let r = uds.check(w, class)?;
        let same = (r.verdict == "go") == v.is_go()
            && r.claimed_distance
                .zip(v.claimed_distance)
                .is_none_or(|(a, b)| (a - b).abs() <= 1e-5 * b.abs().max(1.0));
        if !same {
            bail!("baseline and guardiand disagree on {class}: {r:?} vs {v:?}");
        }
    }
    let mut i = 0usize;
    let rt_uds = time_n(200, n_rt, || {
        let (class, w) = &drawings.checks[i % drawings.checks.len()];
        i += 1;
        std::hint::black_box(uds.check(w, class)?);
        Ok(())
    })?;
    uds.writer.write_all(b"quit\n")?;
    server.wait()?;

    // ---- report
    println!();
    print_header();
    let rows = [
        ("candle forward", stats(&candle_fwd)),
        ("fast forward (overlapping-row gemm)", stats(&fast_fwd)),
        ("embed: features + fast forward", stats(&embed)),
        ("preprocess + embed (daemon's compute)", stats(&full)),
        ("round trip iceoryx2, event mode", stats(&rt_event)),
        ("round trip iceoryx2, busy-poll mode", stats(&rt_busy)),
        ("  ... and the client spinning too", stats(&rt_busy_spin)),
        ("round trip UDS + JSON baseline", stats(&rt_uds)),
    ];
    for (name, s) in &rows {
        print_row(name, s);
    }
    println!(
        "fast forward timed alongside (one after every round trip, same process as the client):"
    );
    for (name, v) in [
        ("  ... with the event-mode round trips", &fwd_event),
        ("  ... with the busy-poll round trips", &fwd_busy),
        ("  ... with the spinning-client round trips", &fwd_busy_spin),
    ] {
        print_row(name, &stats(v));
    }
    println!();
    println!(
        "guardiand's own service time per request (last 4096, from its status): \
         event p50 {:.1} / p99 {:.1} us, busy-poll p50 {:.1} / p99 {:.1} us",
        served_event[0], served_event[2], served_busy[0], served_busy[2]
    );
    println!(
        "compute floor: {:.2} MFLOP per check / {:.1} GFLOP/s (gemm {m}x{n}x{kk}, 1 thread, \
         median; best {:.1}) = {:.1} us",
        flops as f64 / 1e6,
        rate_med,
        rate_best,
        floor_us
    );
    println!();
    println!("throughput, event mode, each client checking back to back:");
    println!(
        "{:<8} {:>9} {:>10} {:>9} {:>9} {:>9} {:>9}",
        "clients", "max-batch", "checks/s", "p50 us", "p99 us", "p99.9 us", "max us"
    );
    for t in &tput {
        println!(
            "{:<8} {:>9} {:>10.0} {:>9.1} {:>9.1} {:>9.1} {:>9.1}",
            t.clients, t.max_batch, t.checks_per_s, t.lat.p50, t.lat.p99, t.lat.p999, t.lat.max
        );
    }
    println!();
    println!("guardiand's compute per check, in process (its Screen and configuration):");
    print_header();
    for (name, v) in &breakdown {
        print_row(name, &stats(v));
    }
    println!();
    println!("forward kinematics, specialised position FK vs the general chain (full frames):");
    print_header();
    for (name, v) in [
        ("preprocess (validate, FK length, resample)", &prep),
        ("  ... general-chain FK (before)", &prep_ref),
        ("pen path of 128 resampled points", &path_fk),
        ("  ... general-chain FK (before)", &path_ref),
    ] {
        print_row(name, &stats(v));
    }
    let [candle, fastf, _, _, ev, busy, spin, json] = rows.map(|r| r.1);
    let (fwd_ev, fwd_busy, fwd_spin) = (stats(&fwd_event), stats(&fwd_busy), stats(&fwd_busy_spin));
    // The faster busy-poll variant, with the forward timed alongside it.
    let (busy, fwd_busy) = if spin.p50 < busy.p50 {
        (spin, fwd_spin)
    } else {
        (busy, fwd_busy)
    };
    let fastest = candle.p50.min(fastf.p50);
    println!();
    println!("{:<52} {:>8} {:>8}  result", "ratio", "measured", "target");
    // (name, measured, target, whether the target is an upper bound)
    let ratios = [
        (
            "candle forward p50 / compute floor",
            candle.p50 / floor_us,
            1.5,
            true,
        ),
        (
            "fastest forward p50 / compute floor",
            fastest / floor_us,
            1.5,
            true,
        ),
        (
            "candle forward p50 / fast forward p50",
            candle.p50 / fastf.p50,
            1.0,
            false,
        ),
        (
            "round trip p50 (event) / fastest forward p50",
            ev.p50 / fastest,
            1.3,
            true,
        ),
        (
            "round trip p50 (busy-poll) / fastest forward p50",
            busy.p50 / fastest,
            1.3,
            true,
        ),
        (
            "round trip p50 (event) / fast forward p50 alongside",
            ev.p50 / fwd_ev.p50,
            1.3,
            true,
        ),
        (
            "round trip p50 (busy-poll) / fast forward alongside",
            busy.p50 / fwd_busy.p50,
            1.3,
            true,
        ),
        (
            "UDS+JSON p50 / round trip p50 (event)",
            json.p50 / ev.p50,
            5.0,
            false,
        ),
        (
            "UDS+JSON p50 / round trip p50 (busy-poll)",
            json.p50 / busy.p50,
            5.0,
            false,
        ),
        (
            "busy-poll p99.9 / p50 (faster client variant)",
            busy.p999 / busy.p50,
            3.0,
            true,
        ),
        (
            "event p99.9 / p50 (no target)",
            ev.p999 / ev.p50,
            f64::INFINITY,
            true,
        ),
    ];
    for (name, v, target, le) in ratios {
        let ok = if le { v <= target } else { v >= target };
        println!(
            "{:<52} {:>8.2} {:>3}{:>5.1}  {}",
            name,
            v,
            if le { "<=" } else { ">=" },
            target,
            if ok { "met" } else { "MISSED" }
        );
    }
    println!();
    println!(
        "load average at end {}",
        guardian_tests::harness::load_average()
    );
    Ok(())
}
