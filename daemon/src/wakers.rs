//! Per-client response notification: one notifier per client on that client's own event
//! service ([`client_response_event_name`]), so an answer wakes only the client it is for
//! instead of every waiting client.
//!
//! **Opening a client's event service never runs on the serving loop.** Opening an iceoryx2
//! service and creating a port on it can block for milliseconds to tens of milliseconds
//! (iceoryx2 retries an open in 25 ms ticks while a service is in flux, and a client's
//! service is created, and removed again when the client goes, by another process at any
//! time). So a client's first answer asks an opener
//! thread for its notifier and returns at once; the opener (its own thread-safe iceoryx2
//! node) opens the service, hands the notifier to the table *before* it notifies the client
//! once for that first answer (on the shared response event if the client has no own
//! service), so when the client's next request is answered the loop finds the notifier and
//! notifies it itself (the hand-over happens-before the wake-up). (Opening measured 1.8-2.3
//! ms p50, up to 36 ms on a loaded host; the larger stall of a connecting client was
//! iceoryx2's connection update, `docs/performance.md`, "A connecting client".)
//!
//! The table is bounded (the least recently used entry is dropped when it is full) and
//! cleaned of clients that disconnected ([`ClientWakers::retain_connected`], called about
//! once a second by the serving loop) or whose listener is gone (a notification that
//! reached no listener). A client without an event service of its own (an older client)
//! gets a negative entry; the caller then notifies the shared response event instead.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::sync::mpsc;
use std::time::Instant;

use guardian_shared::wire::{client_response_event_name, response_event_name};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;

/// A client's notifier, shared by the opener (for the first wake-up) and the table.
type ClientNotifier = Arc<Notifier<ipc_threadsafe::Service>>;

struct Entry {
    /// `None`: the client has no own event service (use the shared one).
    notifier: Option<ClientNotifier>,
    last_used: Instant,
}

/// Notifiers for the clients' own response event services, by client id.
pub struct ClientWakers {
    service: String,
    capacity: usize,
    table: HashMap<u128, Entry>,
    /// Clients whose notifier the opener is making.
    pending: HashSet<u128>,
    /// Work for the opener thread (`None` when it could not be started).
    to_opener: Option<mpsc::Sender<Job>>,
    /// The opener's results: the client's notifier, or `None` if it has no own service.
    opened: mpsc::Receiver<(u128, Option<ClientNotifier>)>,
    /// The opener thread, joined on drop (so its node is removed before the daemon exits).
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for ClientWakers {
    fn drop(&mut self) {
        self.table.clear();
        self.to_opener = None;
        while self.opened.try_recv().is_ok() {}
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl std::fmt::Debug for ClientWakers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClientWakers")
            .field("service", &self.service)
            .field("capacity", &self.capacity)
            .field("entries", &self.table.len())
            .field("pending", &self.pending.len())
            .finish()
    }
}

/// Work for the opener thread.
enum Job {
    /// Open the notifier of this client.
    Open(u128),
    /// Drop this notifier (a client that went away): dropping the last port of a client's
    /// service removes the service, which is file-system work the serving loop need not do.
    Drop(ClientNotifier),
}

/// What [`ClientWakers::wake`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Woken {
    /// The client's own listener was notified.
    Own,
    /// The client has no own listener: notify the shared response event (older clients
    /// listen there).
    NeedsShared,
    /// The client's notifier is being opened; the opener thread wakes the client when it is
    /// ready (its own listener, or the shared event for a client without one).
    Pending,
}

impl ClientWakers {
    /// An empty table for the request-response service `service`, holding at most
    /// `capacity` clients (at least 1); the opener thread's node uses `config`.
    pub fn new(service: &str, capacity: usize, config: &iceoryx2::config::Config) -> Self {
        let (to_opener, requests) = mpsc::channel::<Job>();
        let (results, opened) = mpsc::channel();
        let (config, name) = (config.clone(), service.to_owned());
        let started = std::thread::Builder::new()
            .name("client-wakers".into())
            .spawn(move || opener(&config, &name, &requests, &results));
        let (to_opener, thread) = match started {
            Ok(t) => (Some(to_opener), Some(t)),
            Err(e) => {
                tracing::warn!(error = %e, "cannot start the client notifier thread; clients are woken through the shared response event");
                (None, None)
            }
        };
        Self {
            service: service.to_owned(),
            capacity: capacity.max(1),
            table: HashMap::with_capacity(capacity.max(1)),
            pending: HashSet::new(),
            to_opener,
            opened,
            thread,
        }
    }

    /// Number of clients in the table.
    pub fn len(&self) -> usize {
        self.table.len()
    }

    /// Whether the table is empty.
    pub fn is_empty(&self) -> bool {
        self.table.is_empty()
    }

    /// Take the opener's finished notifiers into the table.
    fn collect(&mut self) {
        while let Ok((client_id, notifier)) = self.opened.try_recv() {
            self.pending.remove(&client_id);
            if self.table.len() >= self.capacity
                && let Some(oldest) = self
                    .table
                    .iter()
                    .min_by_key(|(_, e)| e.last_used)
                    .map(|(id, _)| *id)
                && let Some(e) = self.table.remove(&oldest)
            {
                self.retire(e);
            }
            self.table.insert(
                client_id,
                Entry {
                    notifier,
                    last_used: Instant::now(),
                },
            );
        }
    }

    /// Wake client `client_id` (the value of its `UniqueClientId`). A client not in the
    /// table yet is handed to the opener (which wakes it once its notifier is ready); this
    /// never blocks on iceoryx2 service set-up.
    pub fn wake(&mut self, client_id: u128) -> Woken {
        self.collect();
        let Some(entry) = self.table.get_mut(&client_id) else {
            if !self.pending.contains(&client_id)
                && self.pending.len() < self.capacity
                && let Some(tx) = &self.to_opener
            {
                if tx.send(Job::Open(client_id)).is_ok() {
                    self.pending.insert(client_id);
                    return Woken::Pending;
                }
                self.to_opener = None;
            }
            if self.pending.contains(&client_id) {
                return Woken::Pending;
            }
            return Woken::NeedsShared;
        };
        entry.last_used = Instant::now();
        let Some(notifier) = &entry.notifier else {
            return Woken::NeedsShared;
        };
        match notifier.notify() {
            Ok(listeners) if listeners > 0 => Woken::Own,
            outcome => {
                // Nobody listens any more (the client is going away) or the port broke:
                // forget it; a live client gets a fresh notifier on its next request.
                if let Err(e) = outcome {
                    tracing::debug!(error = ?e, client = client_id, "client notification failed");
                }
                if let Some(e) = self.table.remove(&client_id) {
                    self.retire(e);
                }
                Woken::NeedsShared
            }
        }
    }

    /// Drop the entries of clients for which `connected` is false.
    pub fn retain_connected(&mut self, mut connected: impl FnMut(u128) -> bool) {
        self.collect();
        let gone: Vec<u128> = self
            .table
            .keys()
            .copied()
            .filter(|id| !connected(*id))
            .collect();
        for id in gone {
            if let Some(e) = self.table.remove(&id) {
                self.retire(e);
            }
        }
    }

    /// Hand a removed entry's notifier to the opener thread to drop.
    fn retire(&mut self, entry: Entry) {
        if let (Some(n), Some(tx)) = (entry.notifier, &self.to_opener) {
            let _ = tx.send(Job::Drop(n));
        }
    }
}

/// The opener thread: for each client id, open the client's event service and create a
/// notifier on it with its own thread-safe node, hand it over, then wake the client once.
/// Ends when the table is dropped.
fn opener(
    config: &iceoryx2::config::Config,
    service: &str,
    requests: &mpsc::Receiver<Job>,
    results: &mpsc::Sender<(u128, Option<ClientNotifier>)>,
) {
    let node = match NodeBuilder::new()
        .config(config)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc_threadsafe::Service>()
    {
        Ok(n) => n,
        Err(e) => {
            tracing::warn!(error = ?e, "client notifier thread: cannot create its node; clients are woken through the shared response event");
            while let Ok(job) = requests.recv() {
                if let Job::Open(id) = job
                    && results.send((id, None)).is_err()
                {
                    return;
                }
            }
            return;
        }
    };
    // The shared response event, for the first answer of a client without its own.
    let shared = ServiceName::new(&response_event_name(service))
        .ok()
        .and_then(|name| node.service_builder(&name).event().open().ok())
        .and_then(|s| s.notifier_builder().create().ok());
    while let Ok(job) = requests.recv() {
        let client_id = match job {
            Job::Open(id) => id,
            Job::Drop(notifier) => {
                drop(notifier);
                continue;
            }
        };
        let started = Instant::now();
        let notifier = ServiceName::new(&client_response_event_name(service, client_id))
            .ok()
            .and_then(|name| node.service_builder(&name).event().open().ok())
            .and_then(|s| s.notifier_builder().create().ok())
            .map(Arc::new);
        tracing::debug!(
            client = client_id,
            own = notifier.is_some(),
            micros = started.elapsed().as_micros() as u64,
            "client notifier opened"
        );
        // Handed over before the wake-up: the client's next request finds it in the table.
        if results.send((client_id, notifier.clone())).is_err() {
            return;
        }
        let first = match (&notifier, &shared) {
            (Some(n), _) => n.notify().map(drop),
            (None, Some(sh)) => sh.notify().map(drop),
            (None, None) => Ok(()),
        };
        if let Err(e) = first {
            tracing::debug!(error = ?e, client = client_id, "first client notification failed");
        }
    }
    // The notifiers handed over hold the node's shared state; it ends with the last one.
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounded_and_cleaned_when_clients_go_away() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut ic = iceoryx2::config::Config::default();
        let root = format!("{}/", dir.path().display());
        ic.global
            .set_root_path(&Path::new(root.as_bytes()).expect("root path"));
        ic.global.prefix =
            FileName::new(format!("gw{}_", std::process::id()).as_bytes()).expect("prefix");
        let node = NodeBuilder::new()
            .config(&ic)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .expect("node");
        let service = "guardian-wakers-test/v1/rpc";
        let listen = |id: u128| {
            let name = client_response_event_name(service, id);
            node.service_builder(&ServiceName::new(&name).expect("name"))
                .event()
                .create()
                .expect("event service")
                .listener_builder()
                .create()
                .expect("listener")
        };
        let count = |l: &iceoryx2::port::listener::Listener<ipc::Service>| {
            l.try_wait(|_| {}).expect("try_wait")
        };
        // Wait (bounded in count) until the opener's notifier for `id` is in the table:
        // the first wake-up is the opener's, after which the loop wakes the client itself.
        let settle = |w: &mut ClientWakers, id: u128| {
            for _ in 0..10_000 {
                w.collect();
                if !w.pending.contains(&id) {
                    return;
                }
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            panic!("opener never answered for {id}");
        };
        let mut w = ClientWakers::new(service, 2, &ic);
        let (l1, l2, l3) = (listen(1), listen(2), listen(3));
        // A new client: handed to the opener, which wakes it once.
        assert_eq!(w.wake(1), Woken::Pending);
        settle(&mut w, 1);
        assert_eq!(count(&l1), 1);
        assert_eq!(w.wake(1), Woken::Own);
        assert_eq!(w.wake(2), Woken::Pending);
        settle(&mut w, 2);
        assert_eq!((count(&l1), count(&l2), count(&l3)), (1, 1, 0));
        // Full: the least recently used client (1) makes room for 3.
        assert_eq!(w.wake(2), Woken::Own);
        assert_eq!(w.wake(3), Woken::Pending);
        settle(&mut w, 3);
        assert_eq!(w.len(), 2);
        assert_eq!((count(&l1), count(&l2), count(&l3)), (0, 1, 1));
        assert_eq!(w.wake(3), Woken::Own);
        assert_eq!(count(&l3), 1);
        // A client without its own service: negative entry, shared event.
        assert_eq!(w.wake(4), Woken::Pending);
        settle(&mut w, 4);
        assert_eq!(w.wake(4), Woken::NeedsShared);
        assert_eq!(w.len(), 2);
        // A client whose listener is gone is forgotten at its next wake-up.
        drop(l3);
        w.retain_connected(|id| id != 4);
        assert_eq!(w.wake(3), Woken::NeedsShared);
        assert!(!w.table.contains_key(&3));
        // Disconnected clients are swept.
        w.retain_connected(|id| id == 1);
        assert!(w.is_empty());
        assert_eq!(w.wake(1), Woken::Pending);
        settle(&mut w, 1);
        assert_eq!(w.wake(1), Woken::Own);
        assert_eq!(count(&l1), 2);
        drop((l1, l2, w, node));
        // iceoryx2 keeps one small global_mgmt file per prefix in /dev/shm.
        let prefix = format!("gw{}_", std::process::id());
        for entry in std::fs::read_dir("/dev/shm")
            .into_iter()
            .flatten()
            .flatten()
        {
            if entry.file_name().to_string_lossy().starts_with(&prefix) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
}
