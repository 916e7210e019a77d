//! `guardiand` configuration: TOML, kebab-case keys, unknown keys rejected.
//!
//! Lookup: `--config FILE` > `$GUARDIAN_CONFIG` > `/etc/guardian/guardiand.toml`; a missing
//! default file means built-in defaults, a missing explicitly named file is an error.
//!
//! Paths left unset resolve at start-up:
//! - `model`: `models/embedder.safetensors` relative to the working directory, else the same
//!   file in the source checkout the binary was built from;
//! - `default-bank`: `models/default-bank.gcb`, resolved the same way; none found = start
//!   with an empty bank;
//! - `state-dir`: `$STATE_DIRECTORY` (set by systemd's `StateDirectory=`), else
//!   `./guardiand-state`.

use std::path::{Path, PathBuf};
use std::time::Duration;

use guardian_robot::cell::{Cell, InvalidCell, Region};
use guardian_robot::kinematics::{
    DEFAULT_ROBOT, RobotDescription, RobotLoadError, WorkcellOverrideError,
    apply_workcell_overrides,
};
use guardian_robot::place::PlaceRule;
use guardian_screen::check::Station;
use guardian_shared::workcell::Workcell;
use serde::{Deserialize, Serialize};

/// The system-wide config file consulted when nothing else is given.
pub const SYSTEM_CONFIG: &str = "/etc/guardian/guardiand.toml";
/// File name of the persisted class bank inside the state directory.
pub const BANK_FILE: &str = "bank.gcb";
/// The id the kernel reports for a uid or gid outside the daemon's user namespace.
const OVERFLOW_ID: u32 = 65534;
/// File name of the admin socket in the runtime (else state) directory.
pub const ADMIN_SOCKET_FILE: &str = "admin.sock";
const MODEL_REL: &str = "models/embedder.safetensors";
const BANK_REL: &str = "models/default-bank.gcb";

/// How the serving loop waits for requests.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ServingMode {
    /// Sleep on the request event service; wake on a client's notification (no busy spin).
    #[default]
    Event,
    /// Poll for requests continuously; lowest latency, burns a core.
    BusyPoll,
    /// Poll for `spin-us` after each request, then sleep as in `event`.
    SpinThenSleep,
}

/// iceoryx2 settings that isolate deployments (and tests) from each other.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct Iceoryx2Config {
    /// `global.root-path` of iceoryx2 (where its service and node files live).
    pub root_path: Option<PathBuf>,
    /// `global.prefix` of iceoryx2 (prefix of every shared-memory and file name).
    pub prefix: Option<String>,
}

/// The admin endpoint: a Unix socket for enroll and forget whose callers are identified by
/// their credentials (`SO_PEERCRED`), and whether planners may still enroll and forget over
/// iceoryx2.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct AdminConfig {
    /// Admin separation: the planners' iceoryx2 service answers enroll and forget with
    /// `NotPermitted`; only the admin socket serves them.
    pub separation: bool,
    /// The socket. Unset: `$RUNTIME_DIRECTORY/admin.sock` (systemd `RuntimeDirectory=`),
    /// else `admin.sock` in the state directory.
    pub socket: Option<PathBuf>,
    /// Callers with one of these uids are admins.
    pub uids: Vec<u32>,
    /// Callers whose (effective, primary) gid is one of these are admins.
    pub gids: Vec<u32>,
}

impl Default for AdminConfig {
    fn default() -> Self {
        Self {
            separation: false,
            socket: None,
            uids: vec![0],
            gids: Vec::new(),
        }
    }
}

/// The verdict record (`[record]`; `docs/operating.md`, "What the screen stops").
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct RecordConfig {
    /// Record every check's outcome.
    pub enabled: bool,
    /// The SQLite file. Unset: `verdicts.sqlite` in the state directory.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub path: Option<PathBuf>,
    /// Most verdicts kept; the oldest are removed first.
    pub max_verdicts: u64,
    /// Most plans of no-go verdicts kept.
    pub max_no_go_plans: u64,
    /// Verdicts older than this many days are removed (0: no age bound).
    pub max_age_days: u64,
    /// Entries waiting for the writer; when full, a verdict is dropped (counted), never
    /// waited for.
    pub queue: usize,
}

impl Default for RecordConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            path: None,
            max_verdicts: 100_000,
            max_no_go_plans: 1_000,
            max_age_days: 30,
            queue: 4096,
        }
    }
}

/// `/metrics` (`[metrics]`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct MetricsConfig {
    /// Address (`host:port`) serving `GET /metrics`; an empty string turns it off. Port 0
    /// picks a free port (logged).
    pub address: String,
    /// Most claimed classes with a `class` label of their own; later ones share `_other`.
    pub max_class_labels: usize,
}

impl Default for MetricsConfig {
    fn default() -> Self {
        Self {
            address: "127.0.0.1:9720".to_owned(),
            max_class_labels: 256,
        }
    }
}

/// The read-only page (`[web]`): off unless an address is set.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct WebConfig {
    /// Address (`host:port`) serving the page, e.g. `127.0.0.1:9721`. Unset: no page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,
}

/// The daemon's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct Config {
    /// The robot served: a built-in name (`panda`, `ur5e`) or the path of a robot
    /// description file (`docs/robots.md`). Trajectories have its joints + 1 channels.
    pub robot: String,
    /// Embedding model weights (safetensors). Unset: see the module docs.
    pub model: Option<PathBuf>,
    /// Class bank used when the state directory holds none. Unset: see the module docs;
    /// an empty string disables it (start with an empty bank).
    pub default_bank: Option<PathBuf>,
    /// Where the enrolled class bank is persisted. Unset: see the module docs.
    pub state_dir: Option<PathBuf>,
    /// Name of the request-response service; the event services append `/requests`,
    /// `/responses` and `/responses/<client id>` (see `docs/wire-protocol.md`).
    pub service_name: String,
    /// Global default decision threshold (Euclidean embedding distance) for classes without
    /// a calibrated one. Unset: the bank's own default.
    pub default_threshold: Option<f32>,
    /// Number of nearest classes reported with a verdict or ranking.
    pub k_nearest: usize,
    /// How the serving loop waits.
    pub serving_mode: ServingMode,
    /// Spin time after a request in `spin-then-sleep` mode, microseconds.
    pub spin_us: u64,
    /// Longest sleep between two checks of the request queue, milliseconds (bounds how late
    /// a lost wake-up, a signal or a watchdog ping is handled).
    pub tick_ms: u64,
    /// Send `WATCHDOG=1` to systemd when `$WATCHDOG_USEC` asks for it.
    pub watchdog: bool,
    /// Largest number of concurrent client ports the service admits.
    pub max_clients: usize,
    /// Micro-batching: when several checks are queued, up to this many are embedded in one
    /// forward pass (1 = one at a time). Never waits for a batch to fill.
    pub max_batch: usize,
    /// Per-client fairness: a micro-batch takes at most one request of each client; a
    /// client's further queued requests wait for the next batch (`docs/guardiand.md`).
    pub fair_batching: bool,
    /// Most classes in the bank; an enroll of a new class beyond it is refused.
    pub max_classes: usize,
    /// Most enrolled examples of one class.
    pub max_examples_per_class: usize,
    /// Most bytes of class data in the bank (as in the snapshot file).
    pub max_bank_bytes: u64,
    /// iceoryx2 isolation settings.
    pub iceoryx2: Iceoryx2Config,
    /// Workcell geometry and tolerances of the workcell rules (`docs/guardiand.md`): keys
    /// set here override the robot description's `[workcell]` defaults one by one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub workcell: Option<toml::Table>,
    /// A cell that is not a canvas (`docs/cells.md`): anchoring tasks to their place, the
    /// tool tip's allowed and keep-out boxes. While it is set, the canvas rules are off
    /// unless `[workcell]` sets `enabled` itself.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cell: Option<CellConfig>,
    /// The admin endpoint and admin separation.
    pub admin: AdminConfig,
    /// The verdict record.
    pub record: RecordConfig,
    /// OpenMetrics on `/metrics`.
    pub metrics: MetricsConfig,
    /// The read-only page (opt-in).
    pub web: WebConfig,
    /// Fleet membership (`docs/fleet.md`): bank replication and remote checks over Zenoh.
    /// Needs a daemon built with the `fleet` feature (the Debian package's is).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fleet: Option<FleetTable>,
}

/// The `[cell]` table (`docs/cells.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct CellConfig {
    /// Tasks are where they happen: a plan must be its claimed class in shape and in place
    /// (its tool path in the base frame against the enrolled examples').
    #[serde(default)]
    pub anchored: bool,
    /// The place rule's spread factor (see `guardian_robot::place`).
    #[serde(default = "default_place_spread")]
    pub place_spread: f32,
    /// The place rule's factor for route points (see `guardian_robot::place`).
    #[serde(default = "default_place_route")]
    pub place_route: f32,
    /// Factor on the class thresholds of the shape rule (see `guardian_robot::place`).
    #[serde(default = "default_shape_scale")]
    pub shape_scale: f32,
    /// The place rule's tolerance (m).
    #[serde(default = "default_place_tolerance")]
    pub place_tolerance: f32,
    /// The tool tip stays inside this box (base frame, m).
    #[serde(default)]
    pub allowed: Option<Region>,
    /// The tool tip never enters these boxes (base frame, m).
    #[serde(default)]
    pub keep_out: Vec<Region>,
}

fn default_place_spread() -> f32 {
    PlaceRule::DEFAULT.spread
}

fn default_place_route() -> f32 {
    PlaceRule::DEFAULT.route
}

fn default_shape_scale() -> f32 {
    PlaceRule::DEFAULT.shape
}

fn default_place_tolerance() -> f32 {
    PlaceRule::DEFAULT.tolerance
}

impl CellConfig {
    /// The cell's rules.
    pub fn cell(&self) -> Cell {
        Cell {
            anchored: self.anchored,
            place: PlaceRule {
                spread: self.place_spread,
                route: self.place_route,
                shape: self.shape_scale,
                tolerance: self.place_tolerance,
            },
            allowed: self.allowed,
            keep_out: self.keep_out.clone(),
        }
    }
}

/// The `[cell]` table, commented out, as `--print-default-config` ends (`docs/cells.md`).
pub const CELL_TEMPLATE: &str = "\
# [cell]: a cell that is not a canvas (docs/cells.md). While set, the canvas rules\n\
# are off unless [workcell] sets `enabled` itself.\n\
# [cell]\n\
# anchored = true                          # tasks are where they happen (base frame)\n\
# place-spread = 1.5                       # times the demonstrated spread granted\n\
# place-route = 2.0                        # route points: times the tolerance\n\
# place-tolerance = 0.015                  # m beyond it\n\
# shape-scale = 1.2                        # times the class thresholds (shape)\n\
# allowed = { min = [0.2, -0.6, 0.0], max = [0.9, 0.6, 0.7] }\n\
# keep-out = [{ min = [0.45, -0.05, 0.0], max = [0.55, 0.05, 0.3] }]\n";

/// The `[fleet]` table, commented out, as `--print-default-config` ends: every key with
/// an example value (`docs/fleet.md`, The config). Uncommented, it is a valid table.
pub const FLEET_TEMPLATE: &str = "\
# [fleet]: fleet membership (docs/fleet.md); needs a daemon built with the cargo\n\
# feature `fleet` (the Debian package's is). Off while the table is absent.\n\
# [fleet]\n\
# name = \"cell-1\"                          # the fleet (one key-expression chunk)\n\
# member = \"robot-01\"                      # this member's name in it\n\
# listen = [\"tcp/10.0.0.1:7447\"]           # Zenoh endpoints to listen on\n\
# connect = [\"tcp/10.0.0.2:7447\"]          # every other member (a full mesh)\n\
# signing-key = \"/etc/guardian/fleet.key\"  # guardiand --fleet-keygen\n\
# admin-keys = []                          # the other members' public keys (64 hex)\n\
# caller-keys = []                         # remote callers' public keys (64 hex)\n\
# resync-ms = 10000                        # catch-up period\n\
# replicas = 1                             # peers that hold a change before it is answered\n\
# replica-timeout-ms = 2000                # how long the answer waits for them\n";

/// The `[fleet]` table: parsed and checked by `guardian-fleet` when the daemon is built with
/// the `fleet` feature.
#[cfg(feature = "fleet")]
pub type FleetTable = guardian_fleet::config::FleetConfig;
/// The `[fleet]` table: without the `fleet` feature any such table is refused at load
/// ([`ConfigError::FleetNotBuilt`]).
#[cfg(not(feature = "fleet"))]
pub type FleetTable = toml::Table;

impl Default for Config {
    fn default() -> Self {
        Self {
            robot: DEFAULT_ROBOT.to_owned(),
            model: None,
            default_bank: None,
            state_dir: None,
            service_name: guardian_shared::wire::DEFAULT_SERVICE_NAME.to_owned(),
            default_threshold: None,
            k_nearest: 5,
            serving_mode: ServingMode::Event,
            spin_us: 200,
            tick_ms: 100,
            watchdog: true,
            max_clients: 32,
            max_batch: 16,
            fair_batching: true,
            max_classes: 4096,
            max_examples_per_class: 64,
            max_bank_bytes: 256 << 20,
            iceoryx2: Iceoryx2Config::default(),
            workcell: None,
            cell: None,
            admin: AdminConfig::default(),
            record: RecordConfig::default(),
            metrics: MetricsConfig::default(),
            web: WebConfig::default(),
            fleet: None,
        }
    }
}

/// Loading the configuration failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LoadConfigError {
    /// The file could not be read.
    #[error("cannot read config {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not valid TOML for [`Config`].
    #[error("invalid config {path}: {source}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: Box<toml::de::Error>,
    },
    /// A value is out of range.
    #[error("invalid config {path}: {source}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        source: ConfigError,
    },
}

/// What is wrong with a configuration's values (or with the robot it names).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// A count that must be at least 1 is 0.
    #[error("{key} must be at least 1")]
    Zero {
        /// The key.
        key: &'static str,
    },
    /// `k-nearest` asks for more classes than a response holds.
    #[error("k-nearest must be at most {max}, got {0}", max = guardian_shared::wire::MAX_RESPONSE_ENTRIES)]
    KNearest(usize),
    /// An admin uid or gid is the overflow id.
    #[error("[admin] uids and gids must not contain {OVERFLOW_ID}: unmapped callers appear as it")]
    OverflowId,
    /// `default-threshold` is negative or not finite.
    #[error("default-threshold must be finite and >= 0, got {0}")]
    DefaultThreshold(f32),
    /// The robot cannot be loaded.
    #[error("robot: {0}")]
    Robot(#[from] RobotLoadError),
    /// The `[workcell]` overrides do not fit.
    #[error("[workcell]: {0}")]
    Workcell(#[from] WorkcellOverrideError),
    /// The `[cell]` table's values are unusable.
    #[error("[cell]: {0}")]
    Cell(#[from] InvalidCell),
    /// The config has a `[fleet]` table but this guardiand was built without fleet support.
    #[error(
        "[fleet]: this guardiand was built without the `fleet` feature; \
         build it with `--features fleet` (the Debian package is) or remove the table"
    )]
    FleetNotBuilt,
    /// The `[fleet]` table is invalid.
    #[cfg(feature = "fleet")]
    #[error(transparent)]
    Fleet(#[from] guardian_fleet::config::FleetConfigError),
}

impl Config {
    /// Parse TOML text.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, LoadConfigError> {
        let c: Config = toml::from_str(text).map_err(|e| LoadConfigError::Parse {
            path: path.to_owned(),
            source: Box::new(e),
        })?;
        c.check().map_err(|source| LoadConfigError::Invalid {
            path: path.to_owned(),
            source,
        })?;
        Ok(c)
    }

    /// Read one file.
    pub fn from_file(path: &Path) -> Result<Self, LoadConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| LoadConfigError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml(&text, path)
    }

    /// Apply the lookup order: `explicit` > `$GUARDIAN_CONFIG` > [`SYSTEM_CONFIG`] (if it
    /// exists) > defaults. Returns the config and the file it came from.
    pub fn locate(explicit: Option<&Path>) -> Result<(Self, Option<PathBuf>), LoadConfigError> {
        if let Some(p) = explicit {
            return Ok((Self::from_file(p)?, Some(p.to_owned())));
        }
        if let Some(p) = std::env::var_os("GUARDIAN_CONFIG").filter(|v| !v.is_empty()) {
            let p = PathBuf::from(p);
            return Ok((Self::from_file(&p)?, Some(p)));
        }
        let sys = Path::new(SYSTEM_CONFIG);
        if sys.exists() {
            return Ok((Self::from_file(sys)?, Some(sys.to_owned())));
        }
        Ok((Self::default(), None))
    }

    /// The default config as commented TOML (`--print-default-config`), ending with the
    /// `[fleet]` table commented out ([`FLEET_TEMPLATE`]).
    pub fn default_toml() -> String {
        let body = toml::to_string(&Self::default()).unwrap_or_default();
        format!(
            "# guardiand configuration (all keys optional).\n\
             # Unset paths: model = models/embedder.safetensors and default-bank =\n\
             # models/default-bank.gcb (working directory, then the source checkout);\n\
             # state-dir = $STATE_DIRECTORY, else ./guardiand-state.\n\
             # model = \"/usr/share/guardian/embedder.safetensors\"\n\
             # default-bank = \"/usr/share/guardian/default-bank.gcb\"\n\
             # state-dir = \"/var/lib/guardian\"\n\
             # default-threshold = {}\n\
             # serving-mode: \"event\" | \"busy-poll\" | \"spin-then-sleep\"\n\
             # [iceoryx2] keys (unset: iceoryx2's defaults):\n\
             #   root-path = \"/tmp/iceoryx2/\", prefix = \"iox2_\"\n\
             # robot: \"panda\" | \"ur5e\" | the path of a robot description (docs/robots.md)\n\
             # [workcell]: canvas geometry and tolerances of the workcell rules (m, rad);\n\
             #   defaults from the robot description, each key set here overrides one;\n\
             #   enabled = false turns them off (docs/guardiand.md).\n\
             {body}\n{CELL_TEMPLATE}{FLEET_TEMPLATE}",
            guardian_bank::DEFAULT_THRESHOLD
        )
    }

    /// Check the values. The robot is not resolved here (that reads files; it is done once,
    /// by [`Config::station`], when the daemon loads its state); the `[workcell]` overrides
    /// are checked against the built-in defaults, so an unknown key or a bad value fails
    /// when the file is read.
    fn check(&self) -> Result<(), ConfigError> {
        let counts = [
            ("k-nearest", self.k_nearest as u64),
            ("tick-ms", self.tick_ms),
            ("max-clients", self.max_clients as u64),
            ("max-batch", self.max_batch as u64),
            ("max-classes", self.max_classes as u64),
            ("max-examples-per-class", self.max_examples_per_class as u64),
            ("max-bank-bytes", self.max_bank_bytes),
            ("[record] max-verdicts", self.record.max_verdicts),
            ("[record] queue", self.record.queue as u64),
        ];
        if let Some((key, _)) = counts.iter().find(|(_, v)| *v == 0) {
            return Err(ConfigError::Zero { key });
        }
        if self.k_nearest > guardian_shared::wire::MAX_RESPONSE_ENTRIES {
            return Err(ConfigError::KNearest(self.k_nearest));
        }
        apply_workcell_overrides(Workcell::DEFAULT, self.workcell.as_ref())?;
        if let Some(c) = &self.cell {
            c.cell().validate()?;
        }
        // A caller whose uid or gid the daemon's user namespace does not map (systemd
        // PrivateUsers=) is reported as the overflow id 65534: never an admin.
        if self.admin.uids.contains(&OVERFLOW_ID) || self.admin.gids.contains(&OVERFLOW_ID) {
            return Err(ConfigError::OverflowId);
        }
        if let Some(t) = self.default_threshold
            && !(t.is_finite() && t >= 0.0)
        {
            return Err(ConfigError::DefaultThreshold(t));
        }
        #[cfg(not(feature = "fleet"))]
        if self.fleet.is_some() {
            return Err(ConfigError::FleetNotBuilt);
        }
        #[cfg(feature = "fleet")]
        if let Some(f) = &self.fleet {
            f.check()?;
        }
        Ok(())
    }

    /// The robot served ([`Config::robot`]) and its workcell rules (its description's
    /// defaults with this config's `[workcell]` keys applied), resolved once: the daemon
    /// calls this at start and on reload, and the screen owns the result.
    pub fn station(&self) -> Result<Station, ConfigError> {
        let description = RobotDescription::resolve(&self.robot)?;
        let mut workcell = description.workcell_with(self.workcell.as_ref())?;
        let Some(cell) = &self.cell else {
            return Ok(Station::new(description.robot, workcell));
        };
        if !self
            .workcell
            .as_ref()
            .is_some_and(|t| t.contains_key("enabled"))
        {
            workcell.enabled = false;
        }
        Ok(Station::new(description.robot, workcell).with_cell(cell.cell()))
    }

    /// The serving loop's longest sleep.
    pub fn tick(&self) -> Duration {
        Duration::from_millis(self.tick_ms)
    }

    /// The model file to load.
    pub fn model_path(&self) -> PathBuf {
        self.model.clone().unwrap_or_else(|| shipped(MODEL_REL))
    }

    /// The default bank file, if one is configured or shipped.
    pub fn default_bank_path(&self) -> Option<PathBuf> {
        match &self.default_bank {
            Some(p) if p.as_os_str().is_empty() => None,
            Some(p) => Some(p.clone()),
            None => Some(shipped(BANK_REL)).filter(|p| p.exists()),
        }
    }

    /// The state directory.
    pub fn state_dir(&self) -> PathBuf {
        if let Some(d) = &self.state_dir {
            return d.clone();
        }
        systemd_dir("STATE_DIRECTORY").unwrap_or_else(|| PathBuf::from("guardiand-state"))
    }

    /// The persisted bank file.
    pub fn bank_path(&self) -> PathBuf {
        self.state_dir().join(BANK_FILE)
    }

    /// The verdict record's file.
    pub fn record_path(&self) -> PathBuf {
        self.record
            .path
            .clone()
            .unwrap_or_else(|| self.state_dir().join(crate::record::RECORD_FILE))
    }

    /// The verdict record's bounds and place.
    pub fn record_settings(&self) -> crate::record::RecordSettings {
        crate::record::RecordSettings {
            path: self.record_path(),
            service: self.service_name.clone(),
            max_verdicts: self.record.max_verdicts,
            max_plans: self.record.max_no_go_plans,
            max_age: (self.record.max_age_days > 0)
                .then(|| Duration::from_secs(self.record.max_age_days.saturating_mul(86_400))),
            queue: self.record.queue,
        }
    }

    /// The bank limits.
    pub fn limits(&self) -> guardian_bank::BankLimits {
        guardian_bank::BankLimits {
            max_classes: self.max_classes,
            max_examples_per_class: self.max_examples_per_class,
            max_bytes: self.max_bank_bytes,
        }
    }

    /// The admin socket (see [`AdminConfig::socket`]).
    pub fn admin_socket(&self) -> PathBuf {
        if let Some(p) = &self.admin.socket {
            return p.clone();
        }
        systemd_dir("RUNTIME_DIRECTORY")
            .unwrap_or_else(|| self.state_dir())
            .join(ADMIN_SOCKET_FILE)
    }
}

impl AdminConfig {
    /// The admin uids in force for a daemon running as `own_uid`: the configured ones, and,
    /// with separation off, the daemon's own uid too — its planners may enroll and forget
    /// over iceoryx2 then anyway, so its user gains nothing new, and the quick-start daemon's
    /// user can use `guardianctl enroll`. With separation on the daemon's uid is the
    /// planners' and stays out unless listed.
    pub fn effective_uids(&self, own_uid: u32) -> Vec<u32> {
        let mut uids = self.uids.clone();
        if !self.separation && !uids.contains(&own_uid) && own_uid != OVERFLOW_ID {
            uids.push(own_uid);
        }
        uids
    }
}

/// The directory systemd passes in `$var` (`StateDirectory=` etc.); it may pass several,
/// colon-separated, and the first is ours.
fn systemd_dir(var: &str) -> Option<PathBuf> {
    let v = std::env::var_os(var).filter(|v| !v.is_empty())?;
    Some(PathBuf::from(
        v.to_string_lossy().split(':').next().unwrap_or_default(),
    ))
}

/// `rel` in the working directory if it exists there, else in the source checkout.
fn shipped(rel: &str) -> PathBuf {
    let local = PathBuf::from(rel);
    if local.exists() {
        return local;
    }
    let checkout = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(rel);
    if checkout.exists() { checkout } else { local }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--print-default-config` ends with every `[fleet]` key, commented out; the block
    /// uncommented is a table the daemon accepts (with the feature) or refuses as not
    /// built (without).
    #[test]
    fn default_config_shows_the_fleet_table_commented_out() {
        let text = Config::default_toml();
        let block: Vec<&str> = text.lines().skip_while(|l| *l != "# [fleet]").collect();
        assert!(!block.is_empty(), "{text}");
        for key in [
            "name",
            "member",
            "listen",
            "connect",
            "signing-key",
            "admin-keys",
            "caller-keys",
            "resync-ms",
            "replicas",
            "replica-timeout-ms",
        ] {
            assert!(
                block.iter().any(|l| l.starts_with(&format!("# {key} = "))),
                "{key} missing:\n{text}"
            );
        }
        let uncommented: String = block
            .iter()
            .map(|l| format!("{}\n", l.trim_start_matches("# ")))
            .collect();
        let parsed = Config::from_toml(&uncommented, Path::new("t"));
        #[cfg(feature = "fleet")]
        {
            let c = parsed.unwrap();
            let f = c.fleet.expect("fleet table");
            assert_eq!((f.name.as_str(), f.resync_ms), ("cell-1", 10_000));
            // Every key of the table is in the template.
            let all = toml::to_string(&f).unwrap();
            for line in all.lines().filter(|l| l.contains(" = ")) {
                let key = line.split(" = ").next().unwrap();
                assert!(
                    block.iter().any(|l| l.starts_with(&format!("# {key} = "))),
                    "{key} missing from the template"
                );
            }
        }
        #[cfg(not(feature = "fleet"))]
        assert!(parsed.is_err());
    }

    /// The `[cell]` template, uncommented, is a cell the daemon accepts: anchored, its
    /// boxes, the canvas rules off; bad boxes and numbers are refused by name.
    #[test]
    fn the_cell_table_turns_the_canvas_off_and_checks_its_boxes() {
        let text = Config::default_toml();
        let block: String = text
            .lines()
            .skip_while(|l| *l != "# [cell]")
            .take_while(|l| !l.starts_with("# [fleet]:"))
            .map(|l| format!("{}\n", l.trim_start_matches("# ")))
            .collect();
        let c = Config::from_toml(&block, Path::new("t")).unwrap();
        let station = c.station().unwrap();
        let cell = station.cell();
        assert!(cell.anchored);
        assert_eq!(cell.place, PlaceRule::DEFAULT);
        assert_eq!(cell.keep_out.len(), 1);
        assert!(cell.allowed.is_some());
        assert!(!station.workcell().enabled);
        // `enabled` set in [workcell] wins.
        let c = Config::from_toml(
            &format!("{block}[workcell]\nenabled = true\n"),
            Path::new("t"),
        )
        .unwrap();
        assert!(c.station().unwrap().workcell().enabled);
        // Without [cell], nothing changes.
        let s = Config::default().station().unwrap();
        assert!(s.workcell().enabled && !s.cell().anchored && !s.cell().has_regions());
        for bad in [
            "[cell]\nkeep-out = [{ min = [0.0, 0.0, 1.0], max = [0.1, 0.1, 0.5] }]\n",
            "[cell]\nplace-tolerance = 0.0\n",
            "[cell]\nanchored = true\nplace = 1\n",
        ] {
            assert!(Config::from_toml(bad, Path::new("t")).is_err(), "{bad}");
        }
    }

    #[test]
    fn default_config_round_trips_and_unknown_keys_fail() {
        let text = Config::default_toml();
        let c = Config::from_toml(&text, Path::new("default")).unwrap();
        assert_eq!(c, Config::default());
        let e = Config::from_toml("servce-name = \"x\"\n", Path::new("t")).unwrap_err();
        assert!(e.to_string().contains("servce-name"), "{e}");
        let c = Config::from_toml(
            "serving-mode = \"spin-then-sleep\"\n[iceoryx2]\nprefix = \"t_\"\n",
            Path::new("t"),
        )
        .unwrap();
        assert_eq!(c.serving_mode, ServingMode::SpinThenSleep);
        assert_eq!(c.iceoryx2.prefix.as_deref(), Some("t_"));
        assert!(Config::from_toml("k-nearest = 0\n", Path::new("t")).is_err());
        assert!(matches!(
            Config::from_toml("k-nearest = 257\n", Path::new("t")),
            Err(LoadConfigError::Invalid {
                source: ConfigError::KNearest(257),
                ..
            })
        ));
        assert!(Config::from_toml("default-threshold = -1.0\n", Path::new("t")).is_err());
        assert!(Config::from_toml("max-classes = 0\n", Path::new("t")).is_err());
        assert!(Config::from_toml("[admin]\ngids = [65534]\n", Path::new("t")).is_err());
        let c = Config::from_toml(
            "max-classes = 3\n[admin]\nseparation = true\nuids = [0, 1000]\n",
            Path::new("t"),
        )
        .unwrap();
        assert_eq!((c.max_classes, c.admin.separation), (3, true));
        assert_eq!(c.admin.uids, [0, 1000]);
        // The robot: built-in names, a description path, or an error naming it.
        let c = Config::from_toml(
            "robot = \"ur5e\"\n[workcell]\ncanvas-z = 0.2\n",
            Path::new("t"),
        )
        .unwrap();
        let station = c.station().unwrap();
        assert_eq!(station.robot().joints(), 6);
        let cell = station.workcell();
        assert_eq!((cell.canvas_z, cell.canvas_side), (0.2, 0.15));
        // An unknown robot is refused when it is resolved, naming it.
        let c = Config::from_toml("robot = \"kuka\"\n", Path::new("t")).unwrap();
        let e = c.station().unwrap_err();
        assert!(matches!(e, ConfigError::Robot(_)), "{e}");
        assert!(e.to_string().contains("kuka"), "{e}");
        let e = Config::from_toml("[workcell]\ncanvas-zz = 0.2\n", Path::new("t")).unwrap_err();
        assert!(e.to_string().contains("canvas-zz"), "{e}");
        assert!(matches!(
            Config::from_toml("[workcell]\nhover = -1.0\n", Path::new("t")),
            Err(LoadConfigError::Invalid {
                source: ConfigError::Workcell(_),
                ..
            })
        ));
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/robots/ur5e.toml");
        let c = Config::from_toml(
            &format!("robot = {:?}\n", path.display().to_string()),
            Path::new("t"),
        )
        .unwrap();
        assert_eq!(c.station().unwrap().robot().name(), "ur5e");
    }

    /// A `[fleet]` table is refused with a typed error by a daemon built without the
    /// feature, and checked by one built with it.
    #[test]
    fn fleet_table_needs_the_feature() {
        let text = "[fleet]\nname = \"cell\"\nmember = \"a\"\nlisten = [\"tcp/127.0.0.1:7447\"]\nsigning-key = \"/k\"\n";
        let r = Config::from_toml(text, Path::new("t"));
        #[cfg(not(feature = "fleet"))]
        assert!(
            matches!(
                r,
                Err(LoadConfigError::Invalid {
                    source: ConfigError::FleetNotBuilt,
                    ..
                })
            ),
            "{r:?}"
        );
        #[cfg(feature = "fleet")]
        {
            assert_eq!(r.unwrap().fleet.unwrap().member, "a");
            let bad = text.replace("member = \"a\"", "member = \"a/b\"");
            assert!(matches!(
                Config::from_toml(&bad, Path::new("t")),
                Err(LoadConfigError::Invalid {
                    source: ConfigError::Fleet(_),
                    ..
                })
            ));
        }
    }

    #[test]
    fn the_daemons_own_uid_is_an_admin_only_without_separation() {
        let open = AdminConfig::default();
        assert_eq!(open.effective_uids(1000), [0, 1000]);
        assert_eq!(open.effective_uids(0), [0]);
        let separated = AdminConfig {
            separation: true,
            ..AdminConfig::default()
        };
        assert_eq!(separated.effective_uids(1000), [0]);
        assert_eq!(open.effective_uids(OVERFLOW_ID), [0]);
    }

    #[test]
    fn every_shipped_sample_config_parses() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../systemd");
        let mut n = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let p = entry.unwrap().path();
            if p.extension().is_some_and(|e| e == "toml") {
                match Config::from_file(&p) {
                    Ok(_) => {}
                    // A fleet sample needs the feature; without it, the typed refusal.
                    Err(LoadConfigError::Invalid {
                        source: ConfigError::FleetNotBuilt,
                        ..
                    }) if cfg!(not(feature = "fleet")) => {}
                    Err(e) => panic!("{}: {e}", p.display()),
                }
                n += 1;
            }
        }
        assert!(n >= 1, "no sample config in {}", dir.display());
    }
}
