//! Test harness for end-to-end tests: a real `guardiand` process with its own service name, iceoryx2 prefix,
//! state directory, model file and `NOTIFY_SOCKET`, killed on drop.

use guardian_robot::kinematics::PANDA_JOINTS;
use std::io::Read;
use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use guardian_client::{Client, ClientConfig, Decision, Trajectory, Verdict};
use guardian_models::embedder::Embedder;
use guardian_shared::wire::{self, ClassEntry, RequestHeader, ResponseHeader};
use iceoryx2::prelude::{
    AllocationStrategy, FileName, Node, NodeBuilder, SemanticString, ServiceName,
    SignalHandlingMode, ipc,
};

static COUNTER: AtomicU32 = AtomicU32::new(0);

/// Functional bound for start-up and signals (not a performance claim).
pub const PATIENCE: Duration = Duration::from_secs(60);

pub struct Setup {
    pub dir: tempfile::TempDir,
    pub service: String,
    pub prefix: String,
    pub model: PathBuf,
    pub extra: String,
    /// Apply the workcell rules (`[workcell] enabled`). Off by default here: the synthetic
    /// sample tasks are joint-space patterns that do not draw on the canvas.
    pub workcell_rules: bool,
    /// The config's `default-bank` (`None`: none, `default-bank = ""`).
    pub default_bank: Option<PathBuf>,
    /// TOML tables appended to the config. By default `[metrics]` on a free loopback port
    /// (`127.0.0.1:0`, so parallel tests never share one; [`Daemon::metrics_address`]).
    pub tables: String,
}

/// The `[metrics]` table every test daemon gets unless a test replaces [`Setup::tables`].
pub const METRICS_ANY_PORT: &str = "[metrics]\naddress = \"127.0.0.1:0\"\n";

/// Remove what iceoryx2 left in `/dev/shm` under `prefix` (a name ending in `_`, so no
/// other test's prefix starts with it): the daemon and the clients remove their services'
/// segments, but iceoryx2 keeps one small `…global_mgmt` file per prefix, and each test has
/// its own prefix.
pub fn remove_shm(prefix: &str) {
    if let Ok(dir) = std::fs::read_dir("/dev/shm") {
        for entry in dir.flatten() {
            if entry.file_name().to_string_lossy().starts_with(prefix) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
}

impl Drop for Setup {
    /// After the test's daemon and clients (declared after the setup, so dropped first).
    fn drop(&mut self) {
        remove_shm(&self.prefix);
    }
}

impl Setup {
    pub fn new(seed: u64) -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        let n = COUNTER.fetch_add(1, Ordering::SeqCst);
        // The temporary directory's random name keeps the iceoryx2 prefix unique even when a
        // process id repeats and an earlier, killed test left segments in /dev/shm.
        let unique: String = dir
            .path()
            .file_name()
            .map(|f| {
                f.to_string_lossy()
                    .chars()
                    .filter(char::is_ascii_alphanumeric)
                    .collect()
            })
            .unwrap_or_default();
        let tag = format!("{}x{n}{unique}", std::process::id());
        let model = dir.path().join("model.safetensors");
        Embedder::random(seed).save(&model).expect("save model");
        Self {
            service: format!("guardian-test/{tag}/v1/rpc"),
            prefix: format!("gt{tag}_"),
            model,
            dir,
            extra: String::new(),
            workcell_rules: false,
            default_bank: None,
            tables: METRICS_ANY_PORT.to_owned(),
        }
    }

    pub fn state_dir(&self) -> PathBuf {
        self.dir.path().join("state")
    }

    pub fn config_path(&self) -> PathBuf {
        self.dir.path().join("guardiand.toml")
    }

    pub fn write_config(&self) -> PathBuf {
        let text = format!(
            "model = {:?}\ndefault-bank = {:?}\nstate-dir = {:?}\nservice-name = {:?}\ntick-ms = 50\n{}\n[iceoryx2]\nroot-path = {:?}\nprefix = {:?}\n[workcell]\nenabled = {}\n{}",
            self.model,
            self.default_bank.clone().unwrap_or_default(),
            self.state_dir(),
            self.service,
            self.extra,
            self.dir.path().join("iox"),
            self.prefix,
            self.workcell_rules,
            self.tables
        );
        let p = self.config_path();
        std::fs::write(&p, text).expect("write config");
        p
    }

    pub fn client_config(&self) -> ClientConfig {
        ClientConfig {
            service_name: self.service.clone(),
            timeout: Duration::from_secs(10),
            iceoryx2_root_path: Some(self.dir.path().join("iox")),
            iceoryx2_prefix: Some(self.prefix.clone()),
        }
    }

    pub fn client(&self) -> Client {
        Client::connect(self.client_config()).expect("connect")
    }
}

/// A running daemon plus the datagrams it sent to its `NOTIFY_SOCKET`.
pub struct Daemon {
    pub child: Child,
    pub notes: Arc<Mutex<Vec<String>>>,
    pub stderr: Arc<Mutex<String>>,
}

/// The `guardiand` binary under test: `$GUARDIAND_BIN` if set, otherwise built (once per
/// process) with the profile of the running test or bench executable, so it is never stale.
pub fn bin() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| guardiand_bin().unwrap_or_else(|e| panic!("{e:#}")))
}

/// The `guardianctl` binary under test: `$GUARDIANCTL_BIN` if set, otherwise built like
/// [`bin`].
pub fn ctl_bin() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
        built_bin("guardianctl", "GUARDIANCTL_BIN").unwrap_or_else(|e| panic!("{e:#}"))
    })
}

/// The no-go rows of the verdict record at `record` as `guardianctl --json verdicts
/// --no-go` lists them, once there are at least `at_least` (the record is written behind
/// the answers); panics after [`PATIENCE`].
pub fn recorded_no_go(record: &Path, at_least: usize) -> Vec<serde_json::Value> {
    let start = Instant::now();
    loop {
        let out = Command::new(ctl_bin())
            .args(["--json", "verdicts", "--no-go", "--record"])
            .arg(record)
            .output()
            .expect("run guardianctl");
        let rows: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap_or_default();
        if rows.len() >= at_least {
            return rows;
        }
        assert!(
            start.elapsed() < PATIENCE,
            "{} no-go rows recorded, {at_least} expected: {}",
            rows.len(),
            String::from_utf8_lossy(&out.stderr)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Locate or build `guardiand` for the current profile (see [`bin`]).
pub fn guardiand_bin() -> anyhow::Result<PathBuf> {
    built_bin("guardiand", "GUARDIAND_BIN")
}

/// `$env` if set, else binary `name` (`guardiand` or `guardianctl`) built with the running
/// executable's profile, together with the other one.
fn built_bin(name: &str, env: &str) -> anyhow::Result<PathBuf> {
    use anyhow::{Context, bail};
    if let Some(p) = std::env::var_os(env) {
        return Ok(p.into());
    }
    let exe = std::env::current_exe()?;
    // target/<profile-dir>/deps/<name>-<hash>
    let profile_dir = exe
        .parent()
        .and_then(Path::parent)
        .context("test executable has no profile directory")?;
    let profile = match profile_dir.file_name().and_then(|n| n.to_str()) {
        Some("debug") | None => "dev".to_string(),
        Some(other) => other.to_string(),
    };
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    // Both binaries in one build, so their dependencies are built once with one feature set,
    // guardiand with fleet membership (this crate depends on it; the fleet tests need it).
    // For tests (dev profile): the workspace's binaries and tests, which is the feature set
    // of `cargo test --workspace` — guardiand then only needs linking, and Zenoh is never
    // compiled a second time with the two binaries' narrower feature set (measured: a
    // `-p guardian-daemon -p guardian-ctl` build resolves another zenoh unit). Benchmarks
    // (release profiles) build just the two binaries.
    let args: &[&str] = if profile == "dev" {
        &["build", "-q", "--workspace", "--bins", "--tests"]
    } else {
        &[
            "build",
            "-q",
            "-p",
            "guardian-daemon",
            "-p",
            "guardian-ctl",
            "--bins",
            "--features",
            "guardian-daemon/fleet",
        ]
    };
    let status = Command::new(cargo)
        .args(args)
        .args(["--profile", &profile])
        .current_dir(workspace_root())
        .status()
        .with_context(|| format!("running cargo build for {name}"))?;
    if !status.success() {
        bail!("building {name} failed");
    }
    let bin = profile_dir.join(name);
    if !bin.exists() {
        bail!("{} not found after the build", bin.display());
    }
    Ok(bin)
}

impl Daemon {
    /// Start and wait for `READY=1`.
    pub fn start(setup: &Setup) -> Self {
        Self::start_with_env(setup, &[])
    }

    pub fn start_with_env(setup: &Setup, env: &[(&str, String)]) -> Self {
        let d = Self::spawn(setup, env, None);
        d.wait_note("READY=1");
        d
    }

    /// Spawn with an optional pre-bound notify socket path (`@name` = abstract).
    pub fn spawn(
        setup: &Setup,
        env: &[(&str, String)],
        notify: Option<(UnixDatagram, String)>,
    ) -> Self {
        let config = setup.write_config();
        let (sock, addr) = match notify {
            Some(n) => n,
            None => {
                let p = setup.dir.path().join(format!(
                    "notify{}.sock",
                    COUNTER.fetch_add(1, Ordering::SeqCst)
                ));
                let s = UnixDatagram::bind(&p).expect("bind notify socket");
                (s, p.to_string_lossy().into_owned())
            }
        };
        let mut cmd = Command::new(bin());
        cmd.arg("--config")
            .arg(&config)
            .env("NOTIFY_SOCKET", &addr)
            .env("RUST_LOG", "info,guardian_daemon=debug")
            .env_remove("WATCHDOG_USEC")
            .env_remove("STATE_DIRECTORY")
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().expect("spawn guardiand");
        let notes = Arc::new(Mutex::new(Vec::new()));
        let n2 = notes.clone();
        sock.set_read_timeout(Some(Duration::from_millis(100))).ok();
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            loop {
                match sock.recv(&mut buf) {
                    Ok(len) => n2
                        .lock()
                        .unwrap()
                        .push(String::from_utf8_lossy(&buf[..len]).into_owned()),
                    Err(e)
                        if e.kind() == std::io::ErrorKind::WouldBlock
                            || e.kind() == std::io::ErrorKind::TimedOut =>
                    {
                        if Arc::strong_count(&n2) == 1 {
                            return;
                        }
                    }
                    Err(_) => return,
                }
            }
        });
        let stderr = Arc::new(Mutex::new(String::new()));
        let s2 = stderr.clone();
        let mut pipe = child.stderr.take().expect("stderr");
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = pipe.read(&mut buf) {
                if n == 0 {
                    break;
                }
                s2.lock()
                    .unwrap()
                    .push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        });
        Daemon {
            child,
            notes,
            stderr,
        }
    }

    /// The address the daemon serves `/metrics` on (from its log line).
    pub fn metrics_address(&self) -> String {
        self.served_address("metrics served at http://", "/metrics")
    }

    /// The address the daemon serves its page on (from its log line).
    pub fn page_address(&self) -> String {
        self.served_address("page served at http://", "/")
    }

    fn served_address(&self, prefix: &str, suffix: &str) -> String {
        self.wait_log(prefix);
        let log = self.log();
        let rest = &log[log.find(prefix).expect("logged") + prefix.len()..];
        rest[..rest.find(suffix).expect("address end")].to_owned()
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn log(&self) -> String {
        self.stderr.lock().unwrap().clone()
    }

    pub fn notes(&self) -> Vec<String> {
        self.notes.lock().unwrap().clone()
    }

    /// Wait until a notification containing `what` arrived.
    pub fn wait_note(&self, what: &str) {
        let start = Instant::now();
        while start.elapsed() < PATIENCE {
            if self.notes().iter().any(|n| n.contains(what)) {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!(
            "no {what:?} from guardiand; notes {:?}\nlog:\n{}",
            self.notes(),
            self.log()
        );
    }

    /// Wait until the log contains `what`.
    pub fn wait_log(&self, what: &str) {
        let start = Instant::now();
        while start.elapsed() < PATIENCE {
            if self.log().contains(what) {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!("log never showed {what:?}:\n{}", self.log());
    }

    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .arg(format!("-{sig}"))
            .arg(self.pid().to_string())
            .status()
            .expect("run kill")
            .success();
        assert!(ok, "kill -{sig} failed");
    }

    /// Wait for exit; returns the exit status.
    pub fn wait_exit(&mut self) -> std::process::ExitStatus {
        let start = Instant::now();
        while start.elapsed() < PATIENCE {
            if let Some(s) = self.child.try_wait().expect("try_wait") {
                return s;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        panic!("guardiand did not exit; log:\n{}", self.log());
    }
}

impl Drop for Daemon {
    /// Stop gracefully (so iceoryx2 removes its shared memory), kill if that hangs.
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = Command::new("kill")
                .arg("-TERM")
                .arg(self.pid().to_string())
                .status();
            let start = Instant::now();
            while start.elapsed() < Duration::from_secs(10) {
                if let Ok(Some(_)) = self.child.try_wait() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Run `guardiand` to completion (for start-up failures).
pub fn run_to_exit(setup: &Setup) -> std::process::Output {
    let config = setup.write_config();
    let mut child = Command::new(bin())
        .arg("--config")
        .arg(&config)
        .env_remove("NOTIFY_SOCKET")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let start = Instant::now();
    while start.elapsed() < PATIENCE {
        if child.try_wait().expect("try_wait").is_some() {
            return child.wait_with_output().expect("output");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = child.kill();
    let _ = child.wait();
    panic!("guardiand did not exit");
}

pub use guardian_client::samples::task;

/// A bank for `model` with `classes` classes of `examples` pseudo-random embeddings each
/// (xorshift from `seed`): big banks for persistence tests and benchmarks.
pub fn random_bank(
    model: &Path,
    classes: usize,
    examples: usize,
    seed: u64,
) -> guardian_bank::ClassBank {
    let embedder = Embedder::load(model).expect("load model");
    let dim = guardian_models::embedder::EMBED_DIM;
    let mut bank = guardian_bank::ClassBank::new(dim, embedder.version(), 1e9);
    let mut x = seed | 1;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
    };
    for c in 0..classes {
        let e: Vec<Vec<f32>> = (0..examples)
            .map(|_| (0..dim).map(|_| next()).collect())
            .collect();
        bank.enroll(&format!("base{c:04}"), &e).expect("enroll");
    }
    bank
}

/// The uid and gid of the second user the access tests switch to (nobody).
pub const NOBODY: u32 = 65534;

/// Run the `#[ignore]`d test `child` of the running test executable as uid/gid [`NOBODY`]
/// (through `setpriv`; needs root), with `env` set. The executable is copied to a directory
/// that user can read, since the test's own path may not be.
pub fn run_as_nobody(child: &str, env: &[(&str, &std::ffi::OsStr)]) -> std::process::Output {
    use std::os::unix::fs::PermissionsExt;
    let bin_dir = tempfile::tempdir().expect("tempdir");
    std::fs::set_permissions(bin_dir.path(), std::fs::Permissions::from_mode(0o755))
        .expect("chmod");
    let exe = bin_dir.path().join("second-uid-child");
    std::fs::copy(std::env::current_exe().expect("current exe"), &exe).expect("copy exe");
    std::fs::set_permissions(&exe, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    let mut cmd = Command::new("setpriv");
    cmd.args([
        &format!("--reuid={NOBODY}"),
        &format!("--regid={NOBODY}"),
        "--clear-groups",
        "--",
    ])
    .arg(&exe)
    .args(["--exact", child, "--ignored", "--nocapture"]);
    for (k, v) in env {
        cmd.env(k, v);
    }
    cmd.output().expect("run setpriv")
}

/// Enroll `task<c>` for every `c` of `classes` from drawers 0..4 of [`task`], asserting
/// each answer (4 examples, the name).
pub fn enroll_tasks(client: &Client, classes: &[u32]) {
    for &c in classes {
        let examples: Vec<Trajectory> = (0..4).map(|d| traj(c, d)).collect();
        let info = client
            .enroll(&format!("task{c}"), &examples)
            .expect("enroll");
        assert_eq!(info.examples, 4);
        assert_eq!(info.name, format!("task{c}"));
    }
}

pub fn traj(class: u32, drawer: u32) -> Trajectory {
    Trajectory::from_waypoints(&task(class, drawer), PANDA_JOINTS)
}

/// `GET path` from `address` (`host:port`) over plain HTTP/1.0 with a 10 s timeout:
/// the status code and the body.
pub fn http_get(address: &str, path: &str) -> std::io::Result<(u16, String)> {
    http_get_accept(address, path, "*/*")
}

/// [`http_get`] with an `Accept` header.
pub fn http_get_accept(address: &str, path: &str, accept: &str) -> std::io::Result<(u16, String)> {
    use std::io::Write;
    let mut s = std::net::TcpStream::connect(address)?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    s.set_write_timeout(Some(Duration::from_secs(10)))?;
    write!(
        s,
        "GET {path} HTTP/1.0\r\nHost: {address}\r\nAccept: {accept}\r\n\r\n"
    )?;
    let mut text = String::new();
    s.read_to_string(&mut text)?;
    let code = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map_or(String::new(), |(_, b)| b.to_owned());
    Ok((code, body))
}

pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The request-response service of a test daemon, as a planner opens it.
pub type RawRpc = iceoryx2::service::port_factory::request_response::PortFactory<
    ipc::Service,
    [f32],
    RequestHeader,
    [ClassEntry],
    ResponseHeader,
>;

/// A client port on [`RawRpc`].
pub type RawPort = iceoryx2::port::client::Client<
    ipc::Service,
    [f32],
    RequestHeader,
    [ClassEntry],
    ResponseHeader,
>;

/// A planner that bypasses the client library (as a C planner would): its own iceoryx2 node
/// on the test daemon's root path and prefix, the opened request-response service and a
/// notifier on the request event. Fields drop in order, the node last.
pub struct RawPlanner {
    /// The opened request-response service.
    pub rpc: RawRpc,
    /// Notifier on `<service>/requests`.
    pub wake: iceoryx2::port::notifier::Notifier<ipc::Service>,
    /// The planner's node.
    pub node: Node<ipc::Service>,
}

impl RawPlanner {
    /// A new client port (payloads grow by powers of two from 8,192 floats).
    pub fn client_port(&self) -> RawPort {
        self.rpc
            .client_builder()
            .initial_max_slice_len(8192)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .expect("client port")
    }
}

impl Setup {
    /// Open this daemon's services as a raw planner (the daemon must be running).
    pub fn raw_planner(&self) -> RawPlanner {
        let mut ic = iceoryx2::config::Config::default();
        let root = format!("{}/", self.dir.path().join("iox").display());
        ic.global
            .set_root_path(&iceoryx2::prelude::Path::new(root.as_bytes()).expect("root path"));
        ic.global.prefix = FileName::new(self.prefix.as_bytes()).expect("prefix");
        let node = NodeBuilder::new()
            .config(&ic)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .expect("node");
        let rpc = node
            .service_builder(&ServiceName::new(&self.service).expect("service name"))
            .request_response::<[f32], [ClassEntry]>()
            .request_user_header::<RequestHeader>()
            .response_user_header::<ResponseHeader>()
            .open()
            .expect("open the request-response service");
        let wake = node
            .service_builder(
                &ServiceName::new(&wire::request_event_name(&self.service)).expect("event name"),
            )
            .event()
            .open()
            .expect("open the request event")
            .notifier_builder()
            .create()
            .expect("notifier");
        RawPlanner { rpc, wake, node }
    }
}

/// The answer a request must get again: the decision and nearest class the daemon gave the
/// same request before, and the claimed distance (load and soak compare every answer to it).
#[derive(Debug, Clone, PartialEq)]
pub struct Expected {
    /// Go or no-go with the reason.
    pub decision: Decision,
    /// Nearest class.
    pub nearest: Option<String>,
    /// Distance to the claimed class.
    pub distance: Option<f32>,
}

impl Expected {
    /// What `v` answered.
    pub fn of(v: &Verdict) -> Self {
        Self {
            decision: v.decision.clone(),
            nearest: v.nearest.first().map(|n| n.class.clone()),
            distance: v.claimed_distance,
        }
    }

    /// Same decision and nearest class; the distance may differ by float rounding between a
    /// micro-batched and a single forward pass (1e-4 relative), far less than between plans.
    pub fn matches(&self, v: &Verdict) -> bool {
        let got = Self::of(v);
        let close = match (self.distance, got.distance) {
            (Some(a), Some(b)) => (a - b).abs() <= 1e-4 * a.abs().max(1.0),
            (None, None) => true,
            _ => false,
        };
        close && self.decision == got.decision && self.nearest == got.nearest
    }
}

/// The load average (1, 5 and 15 minutes) from `/proc/loadavg`; `?` where unreadable.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// The line every benchmark prints under its title: cores, `RAYON_NUM_THREADS` and the
/// load average at start, so that figures from different runs can be compared.
pub fn machine_line() -> String {
    format!(
        "  cpus {} | RAYON_NUM_THREADS={} | load average at start {}",
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "unset".into()),
        load_average()
    )
}

/// The stroke file of Latin character `character` by its `drawer`-th drawer (1-based, in
/// file-name order) under an Omniglot stroke root: what the benches check and enroll.
pub fn latin_drawing(strokes: &Path, character: u32, drawer: u32) -> anyhow::Result<PathBuf> {
    use anyhow::Context as _;
    let dir = strokes
        .join("Latin")
        .join(format!("character{character:02}"));
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()?;
    files.sort();
    files
        .get((drawer as usize).wrapping_sub(1))
        .cloned()
        .with_context(|| format!("{}: no drawer {drawer}", dir.display()))
}
