//! The serving loop: iceoryx2 ports, waiting strategy, signals, systemd notifications.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::port::listener::ListenerWaitError;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::request_response::PortFactory as RpcFactory;

use guardian_shared::verdict::{NoGoReason, Verdict};
use guardian_shared::wire::{
    ClassEntry, Failure, MAX_RESPONSE_ENTRIES, RequestHeader, ResponseHeader, request_event_name,
    response_event_name,
};

use crate::admin::{AdminEndpoint, AdminPolicy, WakerFactory};
use crate::config::{Config, ServingMode};
use crate::metrics::{ClassLabels, Metrics};
use crate::notify::SdNotify;
use crate::record::{Entry, Record, RemoteCheck};
use crate::screen::{Answer, Screen};
use crate::state::{LoadStateError, load_bank, load_model};
use crate::wakers::{ClientWakers, Woken};

/// Flags set from signal handlers (or a test harness) to steer the loop.
#[derive(Debug, Clone, Default)]
pub struct Control {
    /// Stop gracefully: answer what is queued, flush state, exit.
    pub shutdown: Arc<AtomicBool>,
    /// Reload model and bank; keep the old ones if that fails.
    pub reload: Arc<AtomicBool>,
}

/// Starting or running the daemon failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RunError {
    /// Model or bank could not be loaded at start-up.
    #[error(transparent)]
    Load(Box<LoadStateError>),
    /// The state directory could not be created.
    #[error("cannot create state directory {path}: {source}")]
    StateDir {
        /// The directory.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The state directory exists but cannot be written (a read-only file system, its
    /// permissions): no change could ever be persisted, so the daemon does not start.
    #[error(
        "state directory {path} is not writable ({source}): enrolled classes and fleet records could not be persisted; make it writable by the daemon's user (a read-only file system must be remounted read-write)"
    )]
    StateDirNotWritable {
        /// The directory.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The iceoryx2 root path or prefix is unusable.
    #[error(transparent)]
    Iceoryx2Config(#[from] guardian_shared::ipc::Iceoryx2ConfigError),
    /// An iceoryx2 setup or port operation failed.
    #[error(transparent)]
    Iceoryx(#[from] guardian_shared::ipc::Iceoryx2Error),
    /// The admin socket could not be served.
    #[error(transparent)]
    Admin(#[from] crate::admin::AdminSocketError),
    /// Compacting the bank journal at start failed.
    #[error("cannot compact the class bank journal at start: {0}")]
    Compact(guardian_bank::SaveBankError),
    /// Saving the bank at shutdown failed.
    #[error("cannot flush class bank at shutdown: {0}")]
    Flush(#[from] guardian_bank::SaveBankError),
    /// Fleet membership could not be started.
    #[cfg(feature = "fleet")]
    #[error("cannot join the fleet: {0}")]
    Fleet(#[from] crate::fleet::FleetError),
}

#[cfg(feature = "fleet")]
use crate::fleet::Member;

/// Without the `fleet` feature there is no fleet member: the type has no values, so a
/// daemon built without it is never in a fleet and the calls below compile to nothing.
#[cfg(not(feature = "fleet"))]
enum Member {}

#[cfg(not(feature = "fleet"))]
impl Member {
    fn poll(&mut self, _: &mut Screen, _: &mut dyn FnMut(RemoteCheck)) -> usize {
        match *self {}
    }

    fn after_admin(&mut self, _: &mut Screen) {
        match *self {}
    }

    fn answer_admin(
        &mut self,
        _: crate::admin::AdminJob,
        _: (
            guardian_shared::wire::ResponseHeader,
            Vec<guardian_shared::wire::ClassEntry>,
        ),
    ) -> Option<u32> {
        match *self {}
    }

    fn settle(&mut self, _: bool) -> Vec<(u32, u32)> {
        match *self {}
    }
}

#[cfg(not(feature = "fleet"))]
impl crate::screen::ChangeLog for Member {
    fn record(&mut self, _: &str, _: Option<&guardian_bank::Class>) -> Result<(), String> {
        match *self {}
    }

    fn retract(&mut self, _: &str) {
        match *self {}
    }

    fn committed(&mut self, _: &str) {
        match *self {}
    }
}

/// The fleet member, when the daemon is built with the `fleet` feature and configured.
type Fleet = Option<Member>;

#[cfg(feature = "fleet")]
fn start_fleet(
    config: &Config,
    screen: &mut Screen,
    iox_config: &iceoryx2::config::Config,
) -> Result<Fleet, RunError> {
    let Some(f) = &config.fleet else {
        return Ok(None);
    };
    // Every bank change must become a signed record: planners may not enroll or forget.
    screen.set_admin_separation(true);
    let wake = (iox_config.clone(), request_event_name(&config.service_name));
    let member = Member::start(f, &config.state_dir(), screen, wake)?;
    tracing::info!(fleet = %f.name, member = %f.member, "fleet membership on; enroll and forget only through the admin socket");
    Ok(Some(member))
}

#[cfg(not(feature = "fleet"))]
fn start_fleet(
    _: &Config,
    _: &mut Screen,
    _: &iceoryx2::config::Config,
) -> Result<Fleet, RunError> {
    Ok(None)
}

impl From<LoadStateError> for RunError {
    fn from(e: LoadStateError) -> Self {
        Self::Load(Box::new(e))
    }
}

fn iox<E: std::error::Error + Send + Sync + 'static>(
    what: &'static str,
) -> impl FnOnce(E) -> RunError {
    let during = guardian_shared::ipc::Iceoryx2Error::during(what);
    move |e| during(e).into()
}

/// The iceoryx2 configuration for `config` (root path and prefix applied).
pub fn iceoryx2_config(config: &Config) -> Result<iceoryx2::config::Config, RunError> {
    Ok(guardian_shared::ipc::iceoryx2_config(
        config.iceoryx2.root_path.as_deref(),
        config.iceoryx2.prefix.as_deref(),
    )?)
}

/// How often the serving loop reclaims resources of dead planner processes.
const DEAD_NODE_CLEANUP: Duration = Duration::from_secs(30);
/// How often the serving loop drops per-client notifiers of disconnected clients.
const WAKER_SWEEP: Duration = Duration::from_secs(1);

type ActiveRequest = iceoryx2::active_request::ActiveRequest<
    ipc::Service,
    [f32],
    RequestHeader,
    [ClassEntry],
    ResponseHeader,
>;

type Rpc = RpcFactory<ipc::Service, [f32], RequestHeader, [ClassEntry], ResponseHeader>;

type Server = iceoryx2::port::server::Server<
    ipc::Service,
    [f32],
    RequestHeader,
    [ClassEntry],
    ResponseHeader,
>;

/// Load model and bank, open the services and serve until `control.shutdown` is set: the
/// start-up (state directory, model and bank, observers, iceoryx2 ports, admin socket,
/// fleet), then [`serve`].
pub fn run(config: Config, control: Control) -> Result<(), RunError> {
    let sd = SdNotify::from_env();
    let mut screen = start_screen(&config)?;
    let (obs, http) = start_observers(&config, &screen);
    let iox_config = iceoryx2_config(&config)?;
    let ports = Ports::open(&config, &iox_config)?;
    let admin = start_admin(&config, &iox_config)?;
    let fleet = start_fleet(&config, &mut screen, &iox_config)?;
    serve(
        &config,
        &control,
        &sd,
        &iox_config,
        &ports,
        screen,
        obs,
        http,
        admin,
        fleet,
    )
}

/// The state directory made and checked, the model and the bank loaded, the screen ready
/// (its journal folded into the snapshot).
fn start_screen(config: &Config) -> Result<Screen, RunError> {
    let state_dir = config.state_dir();
    // Owner-only, as the package's tmpfiles.d entry makes it: the bank holds the enrolled
    // plans. An existing directory keeps the mode its owner gave it. A new one is set to
    // 0700 explicitly: the mode given to mkdir is cut by the inherited umask, and a parent
    // that uses iceoryx2 may pass on a transient one (its Unix datagram socket bind sets
    // the process umask to the socket's permissions, e.g. 0177, which leaves 0600: a
    // directory its owner cannot enter).
    let existed = state_dir.exists();
    let state_dir_error = |source| RunError::StateDir {
        path: state_dir.clone(),
        source,
    };
    std::os::unix::fs::DirBuilderExt::mode(std::fs::DirBuilder::new().recursive(true), 0o700)
        .create(&state_dir)
        .map_err(state_dir_error)?;
    if !existed {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&state_dir, std::fs::Permissions::from_mode(0o700))
            .map_err(state_dir_error)?;
    }

    // Refuse a state directory that cannot be written before anything is loaded or
    // written: every enroll would fail later, far from the cause.
    check_writable(&state_dir)?;
    // A daemon killed while persisting leaves its temporary file (never a damaged bank).
    match guardian_bank::remove_stale_temporaries(&config.bank_path()) {
        Ok(removed) if !removed.is_empty() => {
            tracing::warn!(?removed, "removed temporaries of an interrupted bank save")
        }
        Ok(_) => {}
        Err(e) => tracing::warn!(error = %e, "cannot remove stale bank temporaries"),
    }
    let (embedder, station) = load_model(config)?;
    tracing::info!(
        model = %config.model_path().display(),
        version = embedder.version(),
        robot = station.robot().name(),
        joints = station.robot().joints(),
        urdf_sha256 = %station.robot().urdf_sha256_hex(),
        "model loaded"
    );
    let (bank, source) = load_bank(config, &embedder, &station)?;
    if bank.is_empty() {
        tracing::info!(%source, "class bank is empty: enroll classes before checking");
    } else {
        tracing::info!(%source, classes = bank.len(), version = bank.generation(), "class bank loaded");
    }
    for w in crate::state::limit_warnings(&bank, &config.limits()) {
        tracing::warn!(%source, "configured limits below the loaded bank: {w}");
    }
    let mut screen = Screen::new(
        embedder,
        station,
        bank,
        config.bank_path(),
        config.k_nearest,
    );
    screen.set_limits(config.limits());
    screen.set_admin_separation(config.admin.separation);
    // Start from a snapshot alone: fold a journal left by the last run into it (an empty
    // one, left by a kill between its creation and its first record, is removed too).
    if screen.journal_bytes() > 0 || screen.has_journal() {
        let bytes = screen.journal_bytes();
        screen.flush().map_err(RunError::Compact)?;
        tracing::info!(
            journal_bytes = bytes,
            "compacted the bank journal into the snapshot"
        );
    }

    Ok(screen)
}

/// The HTTP listeners' threads and their stop flag.
struct Http {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

/// The metrics, the verdict record and the HTTP listeners (`/metrics`, the page).
fn start_observers(config: &Config, screen: &Screen) -> (Observe, Http) {
    // Metrics and the verdict record: neither ever stops checks (a failure turns them off
    // with an error line).
    let metrics = Metrics::default();
    metrics.set_state(
        screen.bank().len(),
        screen.bank().generation(),
        screen.embedder().version(),
    );
    let record = if config.record.enabled {
        Record::open(config.record_settings(), metrics.clone())
    } else {
        Record::disabled(metrics.clone())
    };
    let http_stop = Arc::new(AtomicBool::new(false));
    let mut http_threads = Vec::new();
    if let Some(t) = start_metrics(config, &metrics, &http_stop) {
        http_threads.push(t);
    }
    if let Some(t) = crate::web::start(config, screen.station().robot().clone(), &http_stop) {
        http_threads.push(t);
    }
    let obs = Observe {
        record,
        metrics,
        labels: ClassLabels::new(config.metrics.max_class_labels),
        published: screen.bank().generation(),
    };

    (
        obs,
        Http {
            stop: http_stop,
            threads: http_threads,
        },
    )
}

/// The daemon's iceoryx2 node, its request-response service and server port, and the
/// request and response events.
struct Ports {
    node: Node<ipc::Service>,
    rpc: Rpc,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    server: Server,
}

impl Ports {
    /// Clean up what crashed processes left, then open the services and create the ports.
    fn open(config: &Config, iox_config: &iceoryx2::config::Config) -> Result<Self, RunError> {
        // Before the node: creating it opens the prefix's segments (dead-node clean-up), and a
        // zero-byte one left by a kill would stall it (crate::recovery).
        for file in crate::recovery::remove_unsized_segments(iox_config) {
            tracing::warn!(
                file = %file.display(),
                "removed an unsized iceoryx2 shared-memory segment (its creator was killed before sizing it)"
            );
        }
        let node = NodeBuilder::new()
            .config(iox_config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(iox("create node"))?;
        // What a crashed daemon or planner left behind: dead nodes (their ports, connections
        // and service tags), and files of the daemon's own services whose creation a kill
        // interrupted (which would make every open `HangsInCreation`).
        let cleaned = node.try_cleanup_dead_nodes();
        if cleaned.cleanups > 0 || cleaned.failed_cleanups > 0 {
            tracing::warn!(
                nodes = cleaned.cleanups,
                failed = cleaned.failed_cleanups,
                "removed resources of dead iceoryx2 nodes"
            );
        }
        for (file, bytes) in
            crate::recovery::remove_half_created_services(iox_config, &config.service_name)
        {
            tracing::warn!(
                file = %file.display(),
                bytes,
                "removed a half-created iceoryx2 service file (its creator was killed during start-up)"
            );
        }
        let max_clients = config.max_clients;
        let max_nodes = max_clients * 2 + 4;
        let rpc_name =
            ServiceName::new(&config.service_name).map_err(iox("invalid service name"))?;
        let rpc: Rpc = node
            .service_builder(&rpc_name)
            .request_response::<[f32], [ClassEntry]>()
            .request_user_header::<RequestHeader>()
            .response_user_header::<ResponseHeader>()
            .max_clients(max_clients)
            .max_servers(1)
            .max_nodes(max_nodes)
            .max_active_requests_per_client(4)
            // One response per request, copied out by the client at once. iceoryx2 sizes the
            // server's response pool as max-clients x 8 x (buffer + borrowed + loaned) chunks
            // and, whenever a client connects or disconnects, walks one flag per chunk for
            // each segment the pool may have — inside receive/loan, on the serving loop. With
            // 4 + 2 + 2 slots and a growable pool (255 segments) that was 1M flags per client
            // (50-350 ms on a loaded 2-core host, issue 39); with 1 + 1 + 1, the pool below
            // and one static segment it is 256 (docs/performance.md, "A connecting client").
            .max_response_buffer_size(1)
            .max_borrowed_responses_per_pending_response(1)
            .open_or_create()
            .map_err(iox("open request-response service"))?;
        let event = |name: String, what: &'static str| {
            let n = ServiceName::new(&name).map_err(iox("invalid service name"))?;
            node.service_builder(&n)
                .event()
                .max_listeners(max_clients + 2)
                .max_notifiers(max_clients + 2)
                .max_nodes(max_nodes)
                .open_or_create()
                .map_err(iox(what))
        };
        let wake_in = event(
            request_event_name(&config.service_name),
            "open request event service",
        )?;
        let wake_out = event(
            response_event_name(&config.service_name),
            "open response event service",
        )?;
        // The listener exists before the server port, so no request notification is lost.
        let listener = wake_in
            .listener_builder()
            .create()
            .map_err(iox("create listener"))?;
        let notifier = wake_out
            .notifier_builder()
            .create()
            .map_err(iox("create notifier"))?;
        // Exactly one response per request: at most one response chunk per request the server
        // may hold (max-clients x 2 x 4, iceoryx2's worst case of requests), not one per
        // buffer + borrowed + loaned slot (its worst case when a request has several responses).
        let per_request_slots = 3;
        let server = rpc
            .server_builder()
            .max_loaned_responses_per_request(1)
            .override_response_preallocation(move |worst| worst / per_request_slots)
            // Every chunk preallocated at the largest answer (a page of the class list), in one
            // static segment: iceoryx2 walks each segment a growable pool may have (255) on
            // every client connect or leave; a static pool has one (issue 39).
            .initial_max_slice_len(MAX_RESPONSE_ENTRIES)
            .allocation_strategy(AllocationStrategy::Static)
            .create()
            .map_err(iox(
                "create server port (is another guardiand serving this service name?)",
            ))?;

        Ok(Self {
            node,
            rpc,
            listener,
            notifier,
            server,
        })
    }
}

/// The admin socket and the locator that names it.
struct Admin {
    endpoint: AdminEndpoint,
    _locator: Option<crate::locator::AdminLocator>,
}

/// Serve the admin socket (its requests wake the loop through the request event).
fn start_admin(config: &Config, iox_config: &iceoryx2::config::Config) -> Result<Admin, RunError> {
    let admin_path = config.admin_socket();
    let make_wake = admin_waker(iox_config, request_event_name(&config.service_name));
    let admin_uids = config
        .admin
        .effective_uids(rustix::process::getuid().as_raw());
    let admin = AdminEndpoint::start(
        &admin_path,
        AdminPolicy {
            uids: admin_uids.clone(),
            gids: config.admin.gids.clone(),
        },
        make_wake,
    )?;
    let locator = crate::locator::AdminLocator::publish_or_warn(
        iox_config,
        &config.service_name,
        &admin_path,
    );
    tracing::info!(socket = %admin_path.display(), separation = config.admin.separation, uids = ?admin_uids, gids = ?config.admin.gids, "admin socket ready");
    Ok(Admin {
        endpoint: admin,
        _locator: locator,
    })
}

/// The serving loop: answer queued requests, the admin socket and the fleet; follow reload,
/// the watchdog and client churn; sleep as the serving mode says; on shutdown answer what
/// is queued, stop the listeners and flush the bank.
#[allow(clippy::too_many_arguments)]
fn serve(
    config: &Config,
    control: &Control,
    sd: &SdNotify,
    iox_config: &iceoryx2::config::Config,
    ports: &Ports,
    mut screen: Screen,
    mut obs: Observe,
    http: Http,
    admin: Admin,
    mut fleet: Fleet,
) -> Result<(), RunError> {
    let Ports {
        node,
        rpc,
        listener,
        notifier,
        server,
    } = ports;
    let admin = admin.endpoint;
    let watchdog = if config.watchdog {
        sd.watchdog_timeout().map(|t| t / 2)
    } else {
        None
    };
    tracing::info!(
        service = %config.service_name,
        mode = ?config.serving_mode,
        watchdog = ?watchdog,
        "{}", screen.summary()
    );
    sd.ready(&screen.summary());
    let tick = match watchdog {
        Some(w) => config.tick().min(w),
        None => config.tick(),
    };
    // A fleet member sleeps like any daemon: fleet items wake the loop through the request
    // event. (A 10 ms cap on its sleep was once added for records seen waiting for the
    // tick; the loop was in fact blocked inside iceoryx2's connection update for clients
    // coming and going, fixed with the response pool's size — docs/performance.md.)
    let mut last_ping = Instant::now();
    let mut last_cleanup = Instant::now();
    let mut last_request = Instant::now();
    let mut last_sweep = Instant::now();
    let spin = Duration::from_micros(config.spin_us);
    let mut wakers = ClientWakers::new(&config.service_name, config.max_clients, iox_config);
    let mut live_clients: Vec<u128> = Vec::with_capacity(config.max_clients);
    let mut out = Outbox {
        shared: notifier,
        wakers: &mut wakers,
        batch: Vec::with_capacity(config.max_batch),
        answered: Vec::with_capacity(config.max_batch),
        deferred: std::collections::VecDeque::new(),
        fair: config.fair_batching,
    };

    loop {
        // Answer everything queued first, so that a stop answers in-flight requests.
        let served = drain(server, &mut out, &mut screen, config.max_batch, &mut obs)?;
        let changed = serve_admin(&admin, &mut screen, &mut fleet, &obs.metrics)
            + fleet.as_mut().map_or(0, |m| {
                m.poll(&mut screen, &mut |a: RemoteCheck| {
                    obs.checked(a.request, a.response, a.check, a.plan, a.client, a.took)
                })
            });
        // Admin answers waiting for the fleet's peers to hold their change.
        if let Some(m) = fleet.as_mut() {
            for (op, status) in m.settle(false) {
                obs.metrics.count_admin(op, status);
            }
        }
        let served = served + changed;
        if served > 0 {
            last_request = Instant::now();
        }
        // Enrolls and forgets arrive on either path; the gauges follow the bank.
        if changed > 0 || screen.bank().generation() != obs.published {
            obs.publish_state(&screen);
        }
        screen.maintain();
        if control.shutdown.load(Ordering::SeqCst) {
            break;
        }
        if control.reload.swap(false, Ordering::SeqCst) {
            reload(config, &mut screen, sd);
            obs.publish_state(&screen);
        }
        if let Some(w) = watchdog
            && last_ping.elapsed() >= w
        {
            sd.watchdog();
            last_ping = Instant::now();
        }
        // Planners killed without cleanup keep client slots; reclaim them now and then.
        if last_cleanup.elapsed() >= DEAD_NODE_CLEANUP {
            let c = node.try_cleanup_dead_nodes();
            if c.cleanups > 0 {
                tracing::info!(
                    nodes = c.cleanups,
                    "removed resources of dead iceoryx2 nodes"
                );
            }
            last_cleanup = Instant::now();
        }
        // Per-client notifiers of clients that disconnected are dropped.
        if last_sweep.elapsed() >= WAKER_SWEEP {
            if !out.wakers.is_empty() {
                live_clients.clear();
                rpc.dynamic_config().list_clients(|c| {
                    live_clients.push(c.client_id.value());
                    CallbackProgression::Continue
                });
                out.wakers.retain_connected(|id| live_clients.contains(&id));
            }
            last_sweep = Instant::now();
        }
        if served > 0 {
            continue;
        }
        let sleep = match config.serving_mode {
            ServingMode::Event => true,
            ServingMode::BusyPoll => false,
            ServingMode::SpinThenSleep => last_request.elapsed() >= spin,
        };
        if sleep {
            // Wake on a client notification, or after one tick to re-check has_requests,
            // flags and the watchdog.
            let mut woken = false;
            match listener.timed_wait(|_| woken = true, tick) {
                // A signal (SIGHUP, SIGTERM) interrupted the wait: loop to look at the flags.
                Ok(_) | Err(ListenerWaitError::InterruptSignal) => {}
                Err(e) => return Err(iox("wait on request events")(e)),
            }
            // A request found after a whole tick with no notification, before or since, may
            // have waited for the tick: its client's wake-up did not come. Said, so that
            // it cannot hide in a latency tail (issue 39).
            if !woken && server.has_requests().unwrap_or(false) {
                let mut late = false;
                let _ = listener.try_wait(|_| late = true);
                if !late {
                    tracing::warn!(
                        tick_ms = tick.as_millis() as u64,
                        "a request was found after a tick without its wake-up"
                    );
                }
            }
        } else {
            // Drop accumulated notifications so the queue does not fill up.
            match listener.try_wait(|_| {}) {
                Ok(_) | Err(ListenerWaitError::InterruptSignal) => {}
                Err(e) => return Err(iox("drain request events")(e)),
            }
            // Give the core to any other runnable task while idle, so the scheduler has less
            // reason to preempt this process in the middle of a check (see
            // docs/performance.md, busy-poll tail).
            std::thread::yield_now();
        }
    }

    sd.stopping();
    tracing::info!("stopping: answering queued requests and flushing state");
    let _ = drain(server, &mut out, &mut screen, config.max_batch, &mut obs)?;
    let _ = serve_admin(&admin, &mut screen, &mut fleet, &obs.metrics);
    if let Some(m) = fleet.as_mut() {
        for (op, status) in m.settle(true) {
            obs.metrics.count_admin(op, status);
        }
    }
    drop(admin);
    http.stop.store(true, Ordering::SeqCst);
    for t in http.threads {
        let _ = t.join();
    }
    // The record's writer commits what is queued.
    drop(obs);
    screen.flush()?;
    tracing::info!("stopped");
    Ok(())
}

/// Name of the probe file [`check_writable`] creates and removes at once.
const WRITE_PROBE: &str = ".guardiand-write-probe";

/// Whether files can be created in `dir`: create (exclusively) and remove a probe file. A
/// probe left by a daemon killed between the two is removed first.
fn check_writable(dir: &std::path::Path) -> Result<(), RunError> {
    let probe = dir.join(WRITE_PROBE);
    let _ = std::fs::remove_file(&probe);
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .and_then(|_| std::fs::remove_file(&probe))
        .map_err(|source| RunError::StateDirNotWritable {
            path: dir.to_owned(),
            source,
        })
}

fn reload(config: &Config, screen: &mut Screen, sd: &SdNotify) {
    tracing::info!("reload requested (SIGHUP)");
    sd.status("reloading");
    // A new model and a new station (the robot resolved again, once), then the bank for them.
    let result = load_model(config).and_then(|(embedder, station)| {
        let (bank, source) = load_bank(config, &embedder, &station)?;
        Ok((embedder, station, bank, source))
    });
    match result {
        Ok((embedder, station, bank, source)) => {
            for w in crate::state::limit_warnings(&bank, &config.limits()) {
                tracing::warn!(%source, "configured limits below the loaded bank: {w}");
            }
            screen.replace(embedder, station, bank, config.k_nearest);
            tracing::info!(%source, "reload complete: {}", screen.summary());
        }
        Err(e) => {
            tracing::error!(error = %e, "reload failed; keeping the current model and bank");
        }
    }
    sd.status(&screen.summary());
}

/// Answer the admins' queued requests (their credentials were checked by the endpoint).
fn serve_admin(
    admin: &AdminEndpoint,
    screen: &mut Screen,
    fleet: &mut Fleet,
    metrics: &Metrics,
) -> usize {
    let mut n = 0;
    while let Ok(job) = admin.jobs.try_recv() {
        // A change whose requester has gone is not applied (the endpoint logs it).
        if !job.take() {
            continue;
        }
        // A fleet member's change is recorded (signed, appended, fsynced) before the bank
        // journals it and published after, all before the admin hears it is done.
        let log = fleet
            .as_mut()
            .map(|m| m as &mut dyn crate::screen::ChangeLog);
        let answer = screen.handle_admin_logged(&job.header, &job.payload, log);
        if let Some(m) = fleet.as_mut() {
            m.after_admin(screen);
        }
        let op = job.header.op;
        let answered = match fleet.as_mut() {
            Some(m) => m.answer_admin(job, (answer.response, answer.entries)),
            None => {
                let status = answer.response.status;
                job.answer((answer.response, answer.entries));
                Some(status)
            }
        };
        if let Some(status) = answered {
            metrics.count_admin(op, status);
        }
        n += 1;
    }
    n
}

/// The admin endpoint's waker: its own node and notifier on the request event, made in the
/// endpoint's thread. Without it admin requests wait for the loop's next tick.
fn admin_waker(config: &iceoryx2::config::Config, event: String) -> WakerFactory {
    let config = config.clone();
    Box::new(move || {
        let ports = (|| {
            let node = NodeBuilder::new()
                .config(&config)
                .signal_handling_mode(SignalHandlingMode::Disabled)
                .create::<ipc::Service>()
                .ok()?;
            let service = node
                .service_builder(&ServiceName::new(&event).ok()?)
                .event()
                .open()
                .ok()?;
            let notifier = service.notifier_builder().create().ok()?;
            // The notifier drops before its node.
            Some((notifier, node))
        })();
        if ports.is_none() {
            tracing::warn!(
                "admin socket: cannot wake the serving loop; admin requests wait for its tick"
            );
        }
        Box::new(move || {
            if let Some((notifier, _)) = &ports {
                let _ = notifier.notify();
            }
        })
    })
}

/// What watches the serving loop: the metrics and the verdict record.
struct Observe {
    record: Record,
    metrics: Metrics,
    labels: ClassLabels,
    /// The bank generation the gauges show.
    published: u64,
}

impl Observe {
    /// Count and record one answered check (never waits: [`Record::submit`]).
    fn checked(
        &mut self,
        request: RequestHeader,
        response: ResponseHeader,
        check: Result<Verdict, Failure>,
        plan: Option<Vec<f32>>,
        client: String,
        took: Duration,
    ) {
        let claimed = guardian_shared::wire::decode_text(&request.class_name);
        let unknown = matches!(&check, Ok(v) if v.reason() == Some(&NoGoReason::UnknownClass));
        let label = self.labels.label(&claimed, unknown);
        self.metrics.count_check(&check, label, took);
        self.record.submit(Entry {
            time_ms: crate::record::now_ms(),
            client,
            request,
            response,
            check,
            plan,
        });
    }

    /// The bank's size and version, the model, a fleet member's position.
    fn publish_state(&mut self, screen: &Screen) {
        self.published = screen.bank().generation();
        self.metrics.set_state(
            screen.bank().len(),
            screen.bank().generation(),
            screen.embedder().version(),
        );
        let position: Vec<(String, u64)> = screen
            .status_entries()
            .iter()
            .filter_map(|e| {
                let name = guardian_shared::wire::decode_text(&e.name);
                let signer = name.strip_prefix("fleet:")?.to_owned();
                Some((
                    signer,
                    u64::from(e.examples) | (u64::from(e.calibrated) << 32),
                ))
            })
            .collect();
        if !position.is_empty() {
            self.metrics.set_fleet(&position, None);
        }
    }
}

/// Serve `/metrics` on its own thread, if an address is configured. A bind failure is
/// logged and the daemon serves without it.
fn start_metrics(
    config: &Config,
    metrics: &Metrics,
    stop: &Arc<AtomicBool>,
) -> Option<std::thread::JoinHandle<()>> {
    let address = config.metrics.address.trim();
    if address.is_empty() {
        tracing::info!("metrics off ([metrics] address is empty)");
        return None;
    }
    let server = match crate::http::Listener::bind(address) {
        Ok(s) => s,
        Err(e) => {
            tracing::error!(address, error = %e, "cannot serve /metrics; serving checks without it");
            return None;
        }
    };
    let bound = server.address();
    tracing::info!(address = %bound, "metrics served at http://{bound}/metrics");
    let registry = metrics.registry();
    let stop = stop.clone();
    std::thread::Builder::new()
        .name("metrics".into())
        .spawn(move || crate::metrics::serve_metrics(server, registry, stop))
        .map_err(|e| tracing::error!(error = %e, "cannot start the metrics thread"))
        .ok()
}

/// Where wake-ups for answered clients go.
struct Outbox<'a> {
    /// The shared response event, for clients without an event service of their own.
    shared: &'a iceoryx2::port::notifier::Notifier<ipc::Service>,
    wakers: &'a mut ClientWakers,
    /// Requests being answered (reused: the busy-poll loop calls `drain` continuously).
    batch: Vec<ActiveRequest>,
    /// Clients answered in the current batch (each is woken once).
    answered: Vec<u128>,
    /// Requests held back for a later batch because their client already had one in the
    /// batch being built (per-client fairness).
    deferred: std::collections::VecDeque<ActiveRequest>,
    /// Take at most one request per client into a batch.
    fair: bool,
}

/// Answer every queued request, taking up to `max_batch` at a time so that queued checks
/// are embedded in one forward pass; returns how many.
fn drain(
    server: &Server,
    out: &mut Outbox<'_>,
    screen: &mut Screen,
    max_batch: usize,
    obs: &mut Observe,
) -> Result<usize, RunError> {
    let mut n = 0;
    let mut batch = std::mem::take(&mut out.batch);
    let mut answered = std::mem::take(&mut out.answered);
    let has = |batch: &[ActiveRequest], r: &ActiveRequest| {
        let origin = r.origin().value();
        batch.iter().any(|b| b.origin().value() == origin)
    };
    loop {
        // Per-client fairness: held-back requests first (they waited a batch), then new
        // ones; a client with a request in the batch already waits for the next batch, so
        // a client with many queued requests cannot fill a batch ahead of the others.
        let mut i = 0;
        while i < out.deferred.len() && batch.len() < max_batch {
            if has(&batch, &out.deferred[i]) {
                i += 1;
            } else if let Some(r) = out.deferred.remove(i) {
                batch.push(r);
            }
        }
        while batch.len() < max_batch {
            match server.receive() {
                Ok(Some(r)) if out.fair && has(&batch, &r) => out.deferred.push_back(r),
                Ok(Some(r)) => batch.push(r),
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!(error = ?e, "receiving a request failed");
                    break;
                }
            }
        }
        if batch.is_empty() {
            break;
        }
        let start = Instant::now();
        let answers = if batch.len() == 1 {
            let r = &batch[0];
            vec![screen.handle(r.user_header(), r.payload())]
        } else {
            let items: Vec<(RequestHeader, &[f32])> = batch
                .iter()
                .map(|r| (*r.user_header(), r.payload()))
                .collect();
            screen.handle_batch(&items)
        };
        let size = batch.len();
        answered.clear();
        for (request, answer) in batch.drain(..).zip(answers) {
            let Answer {
                response,
                entries,
                check,
            } = answer;
            let header = *request.user_header();
            let origin = request.origin().value();
            // A no-go's plan is kept (copied before the request's memory is released).
            let plan = (matches!(&check, Some(Ok(v)) if !v.is_go()) && obs.record.is_on())
                .then(|| request.payload().to_vec());
            let span = tracing::debug_span!("request", id = header.request_id, op = header.op);
            let _enter = span.enter();
            let sent = request
                .loan_slice_uninit(entries.len())
                .map(|mut r| {
                    *r.user_header_mut() = response;
                    r.write_from_slice(&entries)
                })
                .map_err(|e| format!("{e:?}"))
                .and_then(|r| r.send().map_err(|e| format!("{e:?}")));
            drop(request);
            match sent {
                Ok(()) => {
                    if !answered.contains(&origin) {
                        answered.push(origin);
                    }
                }
                Err(e) => tracing::warn!(error = %e, "cannot send response (client gone?)"),
            }
            let elapsed = start.elapsed();
            screen.record_latency(elapsed);
            if let Some(check) = check {
                obs.checked(
                    header,
                    response,
                    check,
                    plan,
                    format!("{origin:032x}"),
                    elapsed,
                );
            }
            tracing::debug!(
                status = response.status,
                verdict = response.verdict,
                reason = response.reason,
                batch = size,
                micros = elapsed.as_micros() as u64,
                "answered"
            );
            n += 1;
        }
        // Wake only the clients that were answered, each on its own event service; clients
        // without one share the common response event (one notification for all of them).
        let mut shared = false;
        for &client in &answered {
            shared |= out.wakers.wake(client) == Woken::NeedsShared;
        }
        if shared && let Err(e) = out.shared.notify() {
            tracing::warn!(error = ?e, "cannot notify clients");
        }
    }
    out.batch = batch;
    out.answered = answered;
    Ok(n)
}
