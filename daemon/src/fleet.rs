//! Fleet membership (cargo feature `fleet`, config `[fleet]`; `docs/fleet.md`): enrolls
//! and forgets accepted on the admin path become signed records published to the fleet;
//! records from peers are verified and applied to the bank; remote check / identify /
//! status requests are answered. Zenoh runs on its own threads and hands everything to the
//! serving loop through a channel that [`Member::poll`] drains between requests, waking
//! the loop through the request event like the admin endpoint does.
//!
//! With `[fleet] replicas = N` an admin's enroll or forget is answered only once N peers
//! have acknowledged holding its record ([`guardian_fleet::ack`]), or `replica-timeout-ms`
//! has passed (then `Unreplicated`, saying how many did); the serving loop goes on
//! meanwhile, the answer waits in [`Member`].

use std::collections::BTreeSet;
use std::path::Path;
use std::sync::Arc;
use std::sync::mpsc;
use std::time::Instant;

use guardian_bank::Class;
use guardian_fleet::config::FleetConfig;
use guardian_fleet::keys::{KeyError, hex, read_signing_key};
use guardian_fleet::node::{Incoming, Node, NodeError, RemoteCall, frame_batch};
use guardian_fleet::record::{Change, Record, Unsigned};
use guardian_fleet::remote::{Gate, now_ms, seal_response};
use guardian_fleet::store::{Offer, STORE_FILE, Store, StoreError, Undo};
use guardian_fleet::{SigningKey, VerifyingKey};
use guardian_shared::wire::{
    ClassEntry, Failure, ResponseHeader, Status, admin, encode_failure, encode_text,
};

use crate::admin::AdminJob;
use crate::record::RemoteCheck;
use crate::screen::{ChangeLog, Screen};

/// Starting fleet membership failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FleetError {
    /// The signing key or a public key is unusable.
    #[error("fleet key: {0}")]
    Key(#[from] KeyError),
    /// The record store cannot be opened.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The Zenoh session cannot be started.
    #[error(transparent)]
    Node(#[from] NodeError),
}

/// Counters of what the member refused (for tests and logs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Refusals {
    /// Records refused (malformed, untrusted, other fleet/robot/model, stale).
    pub records: u64,
    /// Remote requests refused by the gate.
    pub calls: u64,
    /// Acknowledgements refused (malformed, other fleet, untrusted).
    pub acks: u64,
}

/// An admin's answer waiting for the peers to hold its change.
#[derive(Debug)]
struct Waiting {
    lamport: u64,
    class: String,
    /// Peers (their keys) that acknowledged the record.
    held: BTreeSet<[u8; 32]>,
    since: Instant,
    job: AdminJob,
    answer: (ResponseHeader, Vec<ClassEntry>),
}

/// A running fleet member.
#[derive(Debug)]
pub struct Member {
    config: FleetConfig,
    key: SigningKey,
    trusted: Vec<VerifyingKey>,
    store: Store,
    gate: Gate,
    node: Node,
    /// Items from the Zenoh threads, with when they were handed over.
    rx: mpsc::Receiver<(std::time::Instant, Incoming)>,
    robot: String,
    model: String,
    refused: Refusals,
    /// The own record of the admin change in progress (recorded, not yet committed).
    pending: Option<(Record, Undo)>,
    /// The winners changed since the last [`Member::refresh`].
    dirty: bool,
    /// The Lamport counter of the admin change just published (until its answer).
    published: Option<u64>,
    /// Admin answers waiting for `replicas` peers.
    waiting: Vec<Waiting>,
}

/// The robot identity records carry: `<name>/<joints>/<URDF sha256>`.
pub fn robot_id(screen: &Screen) -> String {
    let r = screen.station().robot();
    format!("{}/{}/{}", r.name(), r.joints(), r.urdf_sha256_hex())
}

impl Member {
    /// Open the record store in `state_dir`, bring the bank in line with it, start the
    /// Zenoh node. `wake` makes the waker that interrupts the serving loop's sleep.
    pub fn start(
        config: &FleetConfig,
        state_dir: &Path,
        screen: &mut Screen,
        wake: (iceoryx2::config::Config, String),
    ) -> Result<Self, FleetError> {
        let key = read_signing_key(&config.signing_key)?;
        let mut trusted = config.admin_public_keys()?;
        if !trusted.contains(&key.verifying_key()) {
            trusted.push(key.verifying_key());
        }
        let (store, report) = Store::open(&state_dir.join(STORE_FILE), &trusted)?;
        if report.torn_bytes > 0 {
            tracing::warn!(
                torn_bytes = report.torn_bytes,
                "fleet record store: cut off an incomplete last record (a crash while appending it, before its change reached the bank or any peer): a peer's record comes again with the next catch-up; an own change was never acknowledged and is lost everywhere alike (enroll it again)"
            );
        }
        if report.untrusted > 0 {
            tracing::warn!(
                records = report.untrusted,
                "fleet record store: dropped records of keys no longer trusted"
            );
        }
        let (tx, rx) = mpsc::channel();
        let (wake_tx, wake_rx) = mpsc::channel::<()>();
        std::thread::Builder::new()
            .name("fleet-wake".into())
            .spawn(move || wake_loop(&wake.0, &wake.1, &wake_rx))
            .map_err(|e| NodeError::Zenoh {
                what: "spawn the wake thread",
                detail: e.to_string(),
            })?;
        let sink = Arc::new(move |i: Incoming| {
            if tx.send((std::time::Instant::now(), i)).is_ok() {
                let _ = wake_tx.send(());
            }
        });
        let node = Node::start(config, sink)?;
        let mut member = Self {
            config: config.clone(),
            gate: Gate::new(&config.name, &config.member, config.caller_public_keys()?),
            key,
            trusted,
            store,
            node,
            rx,
            robot: robot_id(screen),
            model: screen.embedder().version().to_owned(),
            refused: Refusals::default(),
            pending: None,
            dirty: false,
            published: None,
            waiting: Vec::new(),
        };
        screen.set_report_bank_digest(true);
        member.reconcile(screen);
        member.refresh(screen);
        tracing::info!(
            key = %hex(member.key.verifying_key().as_bytes()),
            records = member.store.winners().count(),
            compacted = report.compacted,
            clock = member.store.clock(),
            "fleet member ready"
        );
        Ok(member)
    }

    /// After a crash between a record's append and the bank's journal, the bank may lack
    /// the store's last winners: apply every winner the bank does not hold as recorded.
    fn reconcile(&mut self, screen: &mut Screen) {
        let mut fixed = 0;
        let winners: Vec<Record> = self.store.winners().cloned().collect();
        for r in winners {
            let f = r.fields();
            if f.robot != self.robot || f.model != self.model {
                continue;
            }
            let held = screen.bank().class(&f.class).map(serde_json::to_vec);
            let (matches, class) = match &f.change {
                Change::Forget => (held.is_none(), None),
                Change::Put(v) => (
                    matches!(&held, Some(Ok(b)) if b == v),
                    serde_json::from_slice::<Class>(v).ok(),
                ),
            };
            if matches || (class.is_none() && f.change != Change::Forget) {
                continue;
            }
            match screen.apply_replicated(&f.class, class) {
                Ok(()) => fixed += 1,
                Err(e) => {
                    tracing::error!(class = %f.class, error = ?e, "cannot apply a recorded fleet change to the bank")
                }
            }
        }
        if fixed > 0 {
            tracing::warn!(
                classes = fixed,
                "applied fleet records the bank was missing (interrupted apply)"
            );
        }
    }

    /// Update what the catch-up queryable serves and the position status reports.
    fn refresh(&mut self, screen: &mut Screen) {
        let frames = frame_batch(self.store.winners().map(Record::bytes));
        self.node.serve(self.store.digest(), frames);
        screen.set_status_entries(position_entries(&self.store.position()));
    }

    /// What was refused so far.
    pub fn refusals(&self) -> Refusals {
        self.refused
    }

    /// Handle everything received since the last call; returns how many items. Each
    /// answered remote check is handed to `checked` (the verdict record and the metrics).
    pub fn poll(&mut self, screen: &mut Screen, checked: &mut dyn FnMut(RemoteCheck)) -> usize {
        let mut n = 0;
        let mut changed = false;
        while let Ok((handed, item)) = self.rx.try_recv() {
            n += 1;
            // From the Zenoh thread's hand-over to the serving loop taking the item: the
            // wake-up's latency (figures: tests/benches/fleet.rs).
            tracing::debug!(
                waited_us = handed.elapsed().as_micros() as u64,
                "fleet item taken by the serving loop"
            );
            match item {
                Incoming::Record(bytes) => changed |= self.receive(&bytes, screen, true),
                Incoming::CaughtUp(bytes) => changed |= self.receive(&bytes, screen, false),
                Incoming::Call(call) => self.answer(call, screen, checked),
                Incoming::Ack(bytes) => self.take_ack(&bytes),
            }
        }
        if changed {
            self.refresh(screen);
        }
        n
    }

    fn refuse(&mut self, live: bool, reason: &str, detail: &str) {
        self.refused.records += 1;
        if live {
            tracing::warn!(reason, detail, "fleet record refused; bank unchanged");
        } else {
            tracing::debug!(reason, detail, "catch-up record refused; bank unchanged");
        }
    }

    /// Verify, store and apply one record; true if the bank changed.
    fn receive(&mut self, bytes: &[u8], screen: &mut Screen, live: bool) -> bool {
        let started = std::time::Instant::now();
        tracing::debug!(bytes = bytes.len(), live, "fleet record received");
        let record = match Record::decode(bytes) {
            Ok(r) => r,
            Err(e) => {
                self.refuse(true, "malformed", &e.to_string());
                return false;
            }
        };
        if let Err(e) = record.verify(&self.trusted) {
            self.refuse(true, "signature", &e.to_string());
            return false;
        }
        let f = record.fields();
        let mismatch = if f.fleet != self.config.name {
            Some(("other fleet", &f.fleet))
        } else if f.robot != self.robot {
            Some(("other robot", &f.robot))
        } else if f.model != self.model {
            Some(("other model", &f.model))
        } else {
            None
        };
        if let Some((reason, got)) = mismatch {
            let detail = format!("class {:?}: record is for {got:?}", f.class);
            self.refuse(true, reason, &detail);
            return false;
        }
        let class = match &f.change {
            Change::Forget => None,
            Change::Put(v) => match serde_json::from_slice::<Class>(v) {
                Ok(c) => Some(c),
                Err(e) => {
                    self.refuse(true, "malformed class", &e.to_string());
                    return false;
                }
            },
        };
        let name = f.class.clone();
        let (lamport, signer) = (f.lamport, hex(&record.signer()[..8]));
        let signer_key = *record.signer();
        let checked = started.elapsed();
        let offered = self.store.offer(record);
        let stored = started.elapsed();
        // Once this member holds the record (stored, and applied to the bank) or a later
        // one of its class, it says so to the signer, which may be waiting to answer its
        // admin. Records a catch-up brings again are not acknowledged again.
        let holds = matches!(offered, Ok(Offer::Applied)) || (live && offered.is_ok());
        let changed = match offered {
            Ok(Offer::Applied) => match screen.apply_replicated(&name, class) {
                Ok(()) => {
                    tracing::info!(
                        class = %name,
                        lamport,
                        signer = %signer,
                        checked_us = checked.as_micros() as u64,
                        stored_us = stored.as_micros() as u64,
                        applied_us = started.elapsed().as_micros() as u64,
                        "fleet change applied"
                    );
                    true
                }
                Err(e) => {
                    tracing::error!(class = %name, lamport, error = ?e, "fleet change recorded but not applied to the bank");
                    true
                }
            },
            Ok(Offer::Duplicate) if !live => false,
            Ok(Offer::Duplicate) => {
                // Own publications do not come back (published to remote peers only), so
                // a live duplicate is a replay, or a publication a catch-up delivered first.
                let detail = format!(
                    "class {name:?}: lamport {lamport} by {signer} is the record already held: replayed (or delivered by a catch-up first)"
                );
                self.refuse(live, "duplicate", &detail);
                false
            }
            Ok(Offer::Stale { winner_lamport }) => {
                let detail = format!(
                    "class {name:?}: lamport {lamport} by {signer} is older than the current record (lamport {winner_lamport}): replayed or superseded"
                );
                self.refuse(live, "stale", &detail);
                false
            }
            Err(e) => {
                tracing::error!(class = %name, error = %e, "cannot persist a fleet record; not applied");
                false
            }
        };
        if holds {
            self.acknowledge(&signer_key, lamport);
        }
        changed
    }

    fn acknowledge(&self, signer: &[u8; 32], lamport: u64) {
        let ack = guardian_fleet::ack::sign(&self.config.name, signer, lamport, &self.key);
        if let Err(e) = self.node.acknowledge(ack) {
            tracing::debug!(error = %e, "cannot publish a holding acknowledgement");
        }
    }

    /// A peer's acknowledgement: count it for the admin answer waiting for that record.
    fn take_ack(&mut self, bytes: &[u8]) {
        let ack = match guardian_fleet::ack::open(bytes, &self.config.name, &self.trusted) {
            Ok(a) => a,
            Err(e) => {
                self.refused.acks += 1;
                tracing::warn!(error = %e, "fleet acknowledgement refused");
                return;
            }
        };
        let own = self.key.verifying_key();
        if ack.signer != *own.as_bytes() || ack.holder == *own.as_bytes() {
            return;
        }
        for w in self.waiting.iter_mut().filter(|w| w.lamport == ack.lamport) {
            w.held.insert(ack.holder);
        }
    }

    /// Answer an admin request now, or, for an enroll or forget this member just published
    /// while `replicas` is set, once enough peers hold it ([`Member::settle`]). The status
    /// answered now, if it was.
    pub fn answer_admin(
        &mut self,
        job: AdminJob,
        answer: (ResponseHeader, Vec<ClassEntry>),
    ) -> Option<u32> {
        let published = self.published.take();
        match published {
            Some(lamport) if self.config.replicas > 0 && answer.0.status == Status::Ok as u32 => {
                self.waiting.push(Waiting {
                    lamport,
                    class: guardian_shared::wire::decode_text(&answer.0.class_name),
                    held: BTreeSet::new(),
                    since: Instant::now(),
                    job,
                    answer,
                });
                None
            }
            _ => {
                let status = answer.0.status;
                job.answer(answer);
                Some(status)
            }
        }
    }

    /// Answer the admin requests whose change enough peers hold, or whose time is up
    /// (`Unreplicated`), or every one of them when `all` (the daemon stops). Returns each
    /// answered request's op and status.
    pub fn settle(&mut self, all: bool) -> Vec<(u32, u32)> {
        let (wanted, timeout) = (self.config.replicas, self.config.replica_timeout());
        let mut answered = Vec::new();
        let mut i = 0;
        while i < self.waiting.len() {
            let w = &self.waiting[i];
            let held = w.held.len();
            if held < wanted && w.since.elapsed() < timeout && !all {
                i += 1;
                continue;
            }
            let Waiting {
                lamport,
                class,
                since,
                job,
                mut answer,
                ..
            } = self.waiting.swap_remove(i);
            let waited_ms = since.elapsed().as_millis() as u64;
            if held >= wanted {
                tracing::info!(
                    class,
                    lamport,
                    peers = held,
                    waited_ms,
                    "fleet change held by the peers required"
                );
            } else {
                let message = format!(
                    "class {class:?} changed here (lamport {lamport}), held by {held} of the {wanted} peers required after {waited_ms} ms{}; the others get it when they catch up",
                    if all { " (the daemon is stopping)" } else { "" }
                );
                tracing::warn!(
                    class,
                    lamport,
                    peers = held,
                    wanted,
                    waited_ms,
                    "fleet change not acknowledged by enough peers in time"
                );
                encode_failure(&mut answer.0, &Failure::Unreplicated { message });
            }
            answered.push((answer.0.op, answer.0.status));
            job.answer(answer);
        }
        answered
    }

    /// An admin request was answered: publish what changed to the catch-up queryable and
    /// the status (the record itself was signed, stored and published by the
    /// [`ChangeLog`] steps before the admin hears it is done).
    pub fn after_admin(&mut self, screen: &mut Screen) {
        if let Some((record, _)) = self.pending.take() {
            // A change neither committed nor retracted cannot happen (the screen always
            // does one or the other); keep the record, as the next start would.
            tracing::error!(class = %record.class(), "fleet record of an unfinished admin change kept");
            self.dirty = true;
        }
        if std::mem::take(&mut self.dirty) {
            self.refresh(screen);
        }
    }

    /// Answer one remote request.
    fn answer(
        &mut self,
        call: RemoteCall,
        screen: &mut Screen,
        checked: &mut dyn FnMut(RemoteCheck),
    ) {
        let started = std::time::Instant::now();
        let opened = match self.gate.open(&call.payload(), now_ms()) {
            Ok(o) => o,
            Err(e) => {
                self.refused.calls += 1;
                tracing::warn!(error = %e, "remote request refused");
                call.refuse(&e.to_string());
                return;
            }
        };
        let (h, payload) = match admin::decode_request(&opened.body) {
            Ok(x) => x,
            Err(e) => {
                tracing::warn!(error = %e, "remote request with a bad frame");
                call.refuse(&format!("bad request frame: {e}"));
                return;
            }
        };
        let span = tracing::debug_span!("remote", id = h.request_id, op = h.op);
        let _enter = span.enter();
        let answer = screen.handle_remote(&h, &payload);
        let frame = admin::encode_response(&answer.response, &answer.entries);
        let envelope = seal_response(
            &self.key,
            &self.config.name,
            &self.config.member,
            opened.nonce,
            &frame[4..],
        );
        call.reply(envelope);
        if let Some(check) = answer.check {
            let no_go = matches!(&check, Ok(v) if !v.is_go());
            checked(RemoteCheck {
                request: h,
                response: answer.response,
                check,
                plan: no_go.then_some(payload),
                client: format!("remote:{}", hex(&opened.caller[..8])),
                took: started.elapsed(),
            });
        }
    }
}

/// The admin path's changes, made durable as signed records before the bank journals them
/// (`docs/fleet.md`, "Persistence and crashes"): record (append + fsync), journal, publish.
impl ChangeLog for Member {
    fn record(&mut self, class: &str, state: Option<&Class>) -> Result<(), String> {
        let change = match state {
            Some(c) => Change::Put(
                serde_json::to_vec(c).map_err(|e| format!("cannot encode class {class:?}: {e}"))?,
            ),
            None => Change::Forget,
        };
        let record = Record::sign(
            Unsigned {
                fleet: self.config.name.clone(),
                robot: self.robot.clone(),
                model: self.model.clone(),
                class: class.to_owned(),
                change,
                lamport: self.store.next_lamport(),
            },
            &self.key,
        );
        let (offer, undo) = self
            .store
            .offer_own(record.clone())
            .map_err(|e| e.to_string())?;
        if offer != Offer::Applied {
            // Cannot happen: an own record takes the clock + 1, past every record held.
            let _ = self.store.retract(undo);
            return Err(format!(
                "own fleet record did not win its class ({offer:?})"
            ));
        }
        self.pending = Some((record, undo));
        crate::faults::hit(crate::faults::FLEET_AFTER_RECORD);
        Ok(())
    }

    fn retract(&mut self, class: &str) {
        let Some((record, undo)) = self.pending.take() else {
            return;
        };
        match self.store.retract(undo) {
            Ok(()) => tracing::warn!(
                class,
                lamport = record.lamport(),
                "fleet record taken back: the bank could not persist its change"
            ),
            Err(e) => {
                tracing::error!(
                    class,
                    lamport = record.lamport(),
                    error = %e,
                    "cannot take back the fleet record of a change the bank could not persist: the record stays, peers receive it at their next catch-up and this member applies it at its next start"
                );
                self.dirty = true;
            }
        }
    }

    fn committed(&mut self, class: &str) {
        let Some((record, _)) = self.pending.take() else {
            return;
        };
        self.dirty = true;
        if let Err(e) = self.node.publish(record.bytes()) {
            tracing::warn!(class, error = %e, "cannot publish the fleet record; peers get it at their next catch-up");
        }
        self.published = Some(record.lamport());
        crate::faults::hit(crate::faults::FLEET_AFTER_PUBLISH);
        tracing::info!(class, lamport = record.lamport(), "fleet change published");
    }
}

/// The wake thread: on each signal from the Zenoh side, notify the serving loop's request
/// event (its own iceoryx2 node and notifier, like the admin endpoint's waker).
fn wake_loop(config: &iceoryx2::config::Config, event: &str, signals: &mpsc::Receiver<()>) {
    use iceoryx2::prelude::*;
    let ports = (|| {
        let node = NodeBuilder::new()
            .config(config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .ok()?;
        let notifier = node
            .service_builder(&ServiceName::new(event).ok()?)
            .event()
            .open()
            .ok()?
            .notifier_builder()
            .create()
            .ok()?;
        // The notifier drops before its node.
        Some((notifier, node))
    })();
    let Some((notifier, _node)) = ports else {
        tracing::warn!("fleet: cannot wake the serving loop; fleet items wait for its tick");
        while signals.recv().is_ok() {}
        return;
    };
    while signals.recv().is_ok() {
        while signals.try_recv().is_ok() {}
        if let Err(e) = notifier.notify() {
            tracing::debug!(error = ?e, "fleet: cannot notify the serving loop");
        }
    }
}

/// The fleet position as status entries: per signer, name `fleet:<first 16 hex digits of
/// its key>`, the Lamport counter in `examples` (low 32 bits) and `calibrated` (high 32
/// bits), distance and threshold NaN.
pub fn position_entries(position: &std::collections::BTreeMap<[u8; 32], u64>) -> Vec<ClassEntry> {
    position
        .iter()
        .map(|(signer, &lamport)| ClassEntry {
            name: encode_text(&format!("fleet:{}", hex(&signer[..8]))),
            distance: f32::NAN,
            threshold: f32::NAN,
            examples: lamport as u32,
            calibrated: (lamport >> 32) as u32,
        })
        .collect()
}
