//! `guardianctl`: command-line client for a running `guardiand` (crate guardian-ctl, so the
//! planner-facing client library stays free of CLI dependencies).
#![forbid(unsafe_code)]

mod bag;
mod robot;

use std::path::{Path, PathBuf};
use std::time::Duration;

/// The wait for an admin's answer unless `--timeout-ms` says otherwise: longer than the
/// longest `[fleet] replica-timeout-ms` (30 s).
const ADMIN_TIMEOUT: Duration = Duration::from_secs(35);

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
mod verdicts;

use guardian_client::{
    AdminClient, CheckError, ClassInfo, Client, ClientConfig, Trajectory, Verdict,
};

/// Talk to guardiand: check, identify, enroll, forget, list classes, status.
///
/// check, identify, classes and status use the planners' iceoryx2 service; enroll and
/// forget use the daemon's admin socket, which only admin uids/gids may use.
/// The go/no-go demo on real drawings is `cargo run --release --example demo`.
///
/// Exit status: 0 done (check: go), 1 failed or not applied (check: no-go), 3 the outcome
/// of an enroll or forget is unknown (sent, no answer, and the daemon could not be asked
/// afterwards).
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Request-response service name of the daemon.
    #[arg(long, default_value = guardian_shared::wire::DEFAULT_SERVICE_NAME)]
    service: String,
    /// Per-request timeout in milliseconds. Unset: 2000, and 35000 for an enroll or forget
    /// (a fleet member answers it once its peers hold the change, `[fleet]
    /// replica-timeout-ms`, at most 30 s).
    #[arg(long)]
    timeout_ms: Option<u64>,
    /// iceoryx2 root path (must match the daemon's config).
    #[arg(long)]
    iceoryx2_root_path: Option<PathBuf>,
    /// iceoryx2 prefix (must match the daemon's config).
    #[arg(long)]
    iceoryx2_prefix: Option<String>,
    /// The daemon's admin socket (enroll, forget; config `[admin] socket`). Unset:
    /// $GUARDIAN_ADMIN_SOCKET, else the socket the daemon reached with the iceoryx2
    /// options above names in its locator file, else /run/guardian/admin.sock, else
    /// ./guardiand-state/admin.sock.
    #[arg(long)]
    admin_socket: Option<PathBuf>,
    /// Print JSON instead of tables (before or after the subcommand).
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Is the trajectory in FILE the task NAME?
    Check {
        /// CSV (one waypoint per line: q1..qn,tool for the served robot's n joints) or
        /// dataset safetensors (not with --bag).
        #[arg(required_unless_present = "bag")]
        file: Option<PathBuf>,
        /// The claimed class.
        #[arg(long)]
        class: String,
        /// Row of a dataset safetensors file.
        #[arg(long)]
        index: Option<usize>,
        #[command(flatten)]
        bag: bag::BagArgs,
    },
    /// The nearest enrolled classes to the trajectory in FILE.
    Identify {
        /// CSV or dataset safetensors.
        file: PathBuf,
        /// Row of a dataset safetensors file.
        #[arg(long)]
        index: Option<usize>,
    },
    /// Enroll class NAME from one or more trajectory files.
    Enroll {
        /// Class name.
        name: String,
        /// CSV or dataset safetensors files (and/or --bag: each plan one example).
        #[arg(required_unless_present = "bag")]
        files: Vec<PathBuf>,
        /// Rows of a dataset safetensors file (repeatable; one example each).
        #[arg(long)]
        index: Vec<usize>,
        #[command(flatten)]
        bag: bag::BagArgs,
    },
    /// Remove class NAME.
    Forget {
        /// Class name.
        name: String,
    },
    /// List enrolled classes.
    Classes {
        /// Ask the admin socket instead of the planners' iceoryx2 service (an admin of
        /// another uid cannot open the latter).
        #[arg(long)]
        admin: bool,
    },
    /// Versions, counters and latency percentiles.
    Status,
    /// Print a robot description (built-in name or file) and check its kinematics before a
    /// daemon serves it: FK fast path, Jacobian, IK round trips, home pose and canvas reach
    /// (exit status 1 on a failure). Needs no daemon.
    Robot {
        /// A built-in robot (panda, ur5e) or the path of a robot description file.
        robot: String,
    },
    /// The daemon's verdict record: recent checks, oldest first (read from its file).
    Verdicts {
        /// No-go verdicts only.
        #[arg(long)]
        no_go: bool,
        /// Checks that claimed class C only.
        #[arg(long, value_name = "C")]
        class: Option<String>,
        /// Since a time (2026-12-05T10:00:00Z) or for a duration back from now (2h).
        #[arg(long, value_name = "T")]
        since: Option<String>,
        /// At most the newest N.
        #[arg(long, default_value_t = 100)]
        limit: usize,
        /// The record file (config `[record] path`). Unset: /var/lib/guardian/verdicts.sqlite
        /// if present, else ./guardiand-state/verdicts.sqlite.
        #[arg(long)]
        record: Option<PathBuf>,
    },
}

fn main() -> anyhow::Result<()> {
    // A closed pipe (`guardianctl verdicts | head -1`) ends the program quietly, as it does
    // any Unix tool, instead of a panic in `println!`.
    sigpipe::reset();
    let args = Args::parse();
    let timeout = Duration::from_millis(args.timeout_ms.unwrap_or(2000));
    // Enroll and forget go through the admin socket only: an admin of another uid cannot
    // (and need not) open the planners' iceoryx2 service.
    let config = ClientConfig {
        service_name: args.service.clone(),
        timeout,
        iceoryx2_root_path: args.iceoryx2_root_path.clone(),
        iceoryx2_prefix: args.iceoryx2_prefix.clone(),
    };
    // An admin's enroll or forget may wait for the fleet's peers (`[fleet]
    // replica-timeout-ms`, at most 30 s): its answer is awaited longer than a check's.
    let admin_timeout = args.timeout_ms.map_or(ADMIN_TIMEOUT, Duration::from_millis);
    let admin = || match &args.admin_socket {
        Some(p) => Ok(AdminClient::new(p, admin_timeout)),
        None => AdminClient::locate(&ClientConfig {
            timeout: admin_timeout,
            ..config.clone()
        }),
    };
    let connect = || Client::connect(config.clone()).context("cannot connect to guardiand");
    let json = args.json;
    match args.cmd {
        Cmd::Robot { robot } => robot::run(&robot)?,
        Cmd::Check {
            file,
            class,
            index,
            bag,
        } => {
            if let Some(plans) = bag.plans()? {
                return check_bag(&connect()?, &plans, &class, json);
            }
            let Some(file) = file else {
                bail!("check needs FILE or --bag");
            };
            let t = read_trajectory(&file, index)?;
            let v = connect()?.check(&t, &class)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                print_verdict(&v);
            }
            if !v.is_go() {
                std::process::exit(1);
            }
        }
        Cmd::Identify { file, index } => {
            let t = read_trajectory(&file, index)?;
            let r = connect()?.identify(&t)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!(
                    "{:<4} {:<32} {:>10} {:>10}",
                    "rank", "class", "distance", "threshold"
                );
                for (i, n) in r.nearest.iter().enumerate() {
                    println!(
                        "{:<4} {:<32} {:>10.4} {:>10.4}",
                        i + 1,
                        n.class,
                        n.distance,
                        n.threshold
                    );
                }
            }
        }
        Cmd::Enroll {
            name,
            files,
            index,
            bag,
        } => {
            let mut examples = bag.plans()?.unwrap_or_default();
            for f in &files {
                if is_safetensors(f) && !index.is_empty() {
                    for &i in &index {
                        examples.push(read_trajectory(f, Some(i))?);
                    }
                } else {
                    examples.push(read_trajectory(f, None)?);
                }
            }
            let info = match admin()?.enroll(&name, &examples) {
                Err(guardian_client::EnrollError::Request(
                    e @ CheckError::OutcomeUnknown { .. },
                )) => settle(&admin()?, timeout, &e, &name, true),
                Err(guardian_client::EnrollError::Request(e @ CheckError::Unreplicated { .. })) => {
                    unreplicated(&e)
                }
                other => other?,
            };
            if json {
                println!("{}", serde_json::to_string_pretty(&info)?);
            } else {
                println!(
                    "enrolled {}: {} examples, threshold {:.4}",
                    info.name, info.examples, info.threshold
                );
            }
        }
        Cmd::Forget { name } => {
            match admin()?.forget(&name) {
                Err(e @ CheckError::OutcomeUnknown { .. }) => {
                    settle(&admin()?, timeout, &e, &name, false);
                }
                Err(e @ CheckError::Unreplicated { .. }) => unreplicated(&e),
                other => other?,
            }
            if json {
                println!("{}", serde_json::json!({ "forgotten": name }));
            } else {
                println!("forgot {name}");
            }
        }
        Cmd::Classes { admin: via_admin } => {
            let classes = if via_admin {
                admin()?.classes()?
            } else {
                connect()?.classes()?
            };
            if json {
                println!("{}", serde_json::to_string_pretty(&classes)?);
            } else {
                println!(
                    "{:<32} {:>8} {:>10} {:>10}",
                    "class", "examples", "threshold", "calibrated"
                );
                for c in &classes {
                    println!(
                        "{:<32} {:>8} {:>10.4} {:>10}",
                        c.name, c.examples, c.threshold, c.calibrated
                    );
                }
            }
        }
        Cmd::Verdicts {
            no_go,
            class,
            since,
            limit,
            record,
        } => {
            let filter = verdicts::Filter {
                no_go,
                class,
                since_ms: since.as_deref().map(verdicts::parse_since).transpose()?,
                limit,
            };
            verdicts::list(
                &record.unwrap_or_else(verdicts::default_path),
                &filter,
                json,
            )?;
        }
        Cmd::Status => {
            let s = connect()?.status()?;
            if json {
                println!("{}", serde_json::to_string_pretty(&s)?);
            } else {
                println!(
                    "robot           {} ({} joints, {} channels, URDF sha256 {})",
                    s.robot.name,
                    s.robot.joints,
                    s.robot.channels(),
                    s.robot.urdf_sha256
                );
                println!("model version   {}", s.model_version);
                println!("bank version    {}", s.bank_version);
                println!("classes         {}", s.classes);
                println!("uptime          {:.1} s", s.uptime.as_secs_f64());
                println!(
                    "requests        {} ({} errors, {} go, {} no-go)",
                    s.requests, s.errors, s.go, s.no_go
                );
                match s.latency_us {
                    Some([p50, p90, p99, max]) => println!(
                        "service time    p50 {p50:.0} us, p90 {p90:.0} us, p99 {p99:.0} us, max {max:.0} us"
                    ),
                    None => println!("service time    (no requests yet)"),
                }
                // A fleet member's position: per signer, the last record applied here.
                for p in &s.fleet {
                    println!(
                        "fleet           signer {} at lamport {}",
                        p.signer, p.lamport
                    );
                }
                // Equal on members that serve the same classes, different otherwise.
                if let Some(d) = &s.bank_digest {
                    println!("fleet           bank digest {d}");
                }
            }
        }
    }
    Ok(())
}

/// An enroll or forget of `class` was sent but not answered (`unknown`). This client has
/// hung up, so the daemon will not apply it any more if it has not yet; the admin socket
/// answers requests in arrival order, so its class list now shows the outcome. Returns the
/// class if an enroll was applied; exits 1 if the change was not applied, 3 if the daemon
/// cannot be asked either.
/// A fleet member made the change but fewer peers than its `replicas` hold it: said, exit
/// status 4 (not 1: the change is in effect; doing it again makes another record).
fn unreplicated(e: &CheckError) -> ! {
    eprintln!("guardianctl: {e}");
    std::process::exit(4);
}

fn settle(
    admin: &AdminClient,
    timeout: Duration,
    unknown: &CheckError,
    class: &str,
    enroll: bool,
) -> ClassInfo {
    eprintln!("guardianctl: {unknown}");
    let asked = AdminClient::new(admin.path(), timeout.max(Duration::from_secs(10))).classes();
    let classes = match asked {
        Ok(c) => c,
        Err(e) => {
            eprintln!("guardianctl: cannot list the classes to settle it either: {e}");
            std::process::exit(3);
        }
    };
    let now = classes.into_iter().find(|c| c.name == class);
    match (enroll, now) {
        (true, Some(info)) => {
            eprintln!(
                "guardianctl: class {class} is enrolled now with {} examples: the enroll was applied, \
                 unless the class already existed (then compare its example count)",
                info.examples
            );
            info
        }
        (true, None) => {
            eprintln!("guardianctl: class {class} is not enrolled: the enroll was not applied");
            std::process::exit(1);
        }
        (false, None) => {
            eprintln!("guardianctl: class {class} is not enrolled (any more): forgotten");
            ClassInfo {
                name: class.to_owned(),
                examples: 0,
                threshold: f32::NAN,
                calibrated: false,
            }
        }
        (false, Some(_)) => {
            eprintln!("guardianctl: class {class} is still enrolled: the forget was not applied");
            std::process::exit(1);
        }
    }
}

fn print_verdict(v: &Verdict) {
    let opt = |x: Option<f32>| x.map_or("-".to_string(), |v| format!("{v:.4}"));
    println!("verdict   {}", v.decision);
    println!(
        "claimed   {} (distance {}, threshold {})",
        v.claimed_class,
        opt(v.claimed_distance),
        opt(v.threshold)
    );
    println!("margin    {}   gap {}", opt(v.margin), opt(v.gap));
    if v.geometry_score.is_some() {
        println!(
            "geometry  {} (threshold {})",
            opt(v.geometry_score),
            opt(v.geometry_threshold)
        );
    }
    for (i, n) in v.nearest.iter().enumerate() {
        println!("  #{} {:<32} {:.4}", i + 1, n.class, n.distance);
    }
    println!("model {}  bank v{}", v.model_version, v.bank_version);
}

/// `check --bag`: every plan of the recording against `class`; exit status 1 if any is
/// no-go.
fn check_bag(client: &Client, plans: &[Trajectory], class: &str, json: bool) -> anyhow::Result<()> {
    let mut verdicts = Vec::with_capacity(plans.len());
    for t in plans {
        verdicts.push(client.check(t, class)?);
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&verdicts)?);
    } else {
        let opt = |x: Option<f32>| x.map_or("-".to_string(), |v| format!("{v:.4}"));
        println!(
            "{:<6} {:<56} {:>10} {:>10}",
            "msg", "verdict", "distance", "threshold"
        );
        for (i, v) in verdicts.iter().enumerate() {
            println!(
                "{:<6} {:<56} {:>10} {:>10}",
                i,
                v.decision.to_string(),
                opt(v.claimed_distance),
                opt(v.threshold)
            );
        }
        let go = verdicts.iter().filter(|v| v.is_go()).count();
        println!("{go}/{} go", verdicts.len());
    }
    if verdicts.iter().any(|v| !v.is_go()) {
        std::process::exit(1);
    }
    Ok(())
}

fn is_safetensors(p: &Path) -> bool {
    p.extension().is_some_and(|e| e == "safetensors")
}

/// Read a CSV trajectory, or row `index` of a dataset safetensors file.
fn read_trajectory(path: &Path, index: Option<usize>) -> anyhow::Result<Trajectory> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if is_safetensors(path) {
        let Some(i) = index else {
            bail!("{}: a dataset file needs --index", path.display());
        };
        let st = safetensors::SafeTensors::deserialize(&bytes)
            .with_context(|| format!("{}: not a safetensors file", path.display()))?;
        let t = st
            .tensor("trajectories")
            .with_context(|| format!("{}: no `trajectories` tensor", path.display()))?;
        let shape = t.shape();
        if t.dtype() != safetensors::Dtype::F32 || shape.len() != 3 || shape[2] == 0 {
            bail!(
                "{}: trajectories must be f32 [N, steps, joints + 1], got {:?} {:?}",
                path.display(),
                t.dtype(),
                shape
            );
        }
        let channels = shape[2];
        if i >= shape[0] {
            bail!(
                "{}: index {i} out of range (N = {})",
                path.display(),
                shape[0]
            );
        }
        let row = shape[1] * channels * 4;
        let data: Vec<f32> = t.data()[i * row..(i + 1) * row]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        return Ok(Trajectory::from_flat(data, channels));
    }
    let text =
        String::from_utf8(bytes).with_context(|| format!("{}: not UTF-8", path.display()))?;
    let mut data = Vec::new();
    let mut channels = None;
    // The first line with content may be a header of column names; any other line must be
    // numbers (an all-text file is an error, not an empty trajectory).
    let mut first = true;
    let mut header = false;
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let vals: Result<Vec<f32>, _> = line.split(',').map(|v| v.trim().parse::<f32>()).collect();
        let is_first = std::mem::replace(&mut first, false);
        let Ok(vals) = vals else {
            if is_first {
                header = true;
                continue;
            }
            bail!("{}:{}: not a list of numbers", path.display(), n + 1);
        };
        match channels {
            None => channels = Some(vals.len()),
            Some(c) if c != vals.len() => {
                bail!(
                    "{}:{}: {} values, earlier lines have {c}",
                    path.display(),
                    n + 1,
                    vals.len()
                )
            }
            _ => {}
        }
        data.extend(vals);
    }
    if header && channels.is_none() {
        bail!(
            "{}: no line of numbers (only a header line)",
            path.display()
        );
    }
    // An empty file sends no waypoints; the daemon answers TooFewWaypoints.
    Ok(Trajectory::from_flat(data, channels.unwrap_or(0)))
}
