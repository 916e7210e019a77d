//! Per-client response notification: one notifier per client on that client's own event
//! service ([`client_response_event_name`]), so an answer wakes only the client it is for
//! instead of every waiting client.
//!
//! The table is bounded (the least recently used entry is dropped when it is full) and
//! cleaned of clients that disconnected ([`ClientWakers::retain_connected`], called about
//! once a second by the serving loop) or whose listener is gone (a notification that
//! reached no listener). A client without an event service of its own (an older client)
//! gets a negative entry; the caller then notifies the shared response event instead.

use std::collections::HashMap;
use std::time::Instant;

use guardian_shared::wire::client_response_event_name;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;

struct Entry {
    /// `None`: the client has no own event service (use the shared one).
    notifier: Option<Notifier<ipc::Service>>,
    last_used: Instant,
}

/// Notifiers for the clients' own response event services, by client id.
pub struct ClientWakers {
    service: String,
    capacity: usize,
    table: HashMap<u128, Entry>,
}

impl std::fmt::Debug for ClientWakers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClientWakers")
            .field("service", &self.service)
            .field("capacity", &self.capacity)
            .field("entries", &self.table.len())
            .finish()
    }
}

/// What [`ClientWakers::wake`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Woken {
    /// The client's own listener was notified.
    Own,
    /// The client has no own listener: notify the shared response event.
    NeedsShared,
}

impl ClientWakers {
    /// An empty table for the request-response service `service`, holding at most
    /// `capacity` clients (at least 1).
    pub fn new(service: &str, capacity: usize) -> Self {
        Self {
            service: service.to_owned(),
            capacity: capacity.max(1),
            table: HashMap::with_capacity(capacity.max(1)),
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

    /// Wake client `client_id` (the value of its `UniqueClientId`): opens its event service
    /// on first use.
    pub fn wake(&mut self, node: &Node<ipc::Service>, client_id: u128) -> Woken {
        let now = Instant::now();
        if !self.table.contains_key(&client_id) {
            if self.table.len() >= self.capacity
                && let Some(oldest) = self
                    .table
                    .iter()
                    .min_by_key(|(_, e)| e.last_used)
                    .map(|(id, _)| *id)
            {
                self.table.remove(&oldest);
            }
            let notifier = self.open(node, client_id);
            self.table.insert(
                client_id,
                Entry {
                    notifier,
                    last_used: now,
                },
            );
        }
        let Some(entry) = self.table.get_mut(&client_id) else {
            return Woken::NeedsShared;
        };
        entry.last_used = now;
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
                self.table.remove(&client_id);
                Woken::NeedsShared
            }
        }
    }

    /// Drop the entries of clients for which `connected` is false.
    pub fn retain_connected(&mut self, mut connected: impl FnMut(u128) -> bool) {
        self.table.retain(|id, _| connected(*id));
    }

    fn open(&self, node: &Node<ipc::Service>, client_id: u128) -> Option<Notifier<ipc::Service>> {
        let name = client_response_event_name(&self.service, client_id);
        let name = ServiceName::new(&name).ok()?;
        let service = node.service_builder(&name).event().open().ok()?;
        service.notifier_builder().create().ok()
    }
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
        let mut w = ClientWakers::new(service, 2);
        let (l1, l2, l3) = (listen(1), listen(2), listen(3));
        assert_eq!(w.wake(&node, 1), Woken::Own);
        assert_eq!(w.wake(&node, 2), Woken::Own);
        assert_eq!((count(&l1), count(&l2), count(&l3)), (1, 1, 0));
        // Full: the least recently used client (1) makes room for 3.
        assert_eq!(w.wake(&node, 2), Woken::Own);
        assert_eq!(w.wake(&node, 3), Woken::Own);
        assert_eq!(w.len(), 2);
        assert_eq!((count(&l1), count(&l2), count(&l3)), (0, 1, 1));
        // A client without its own service: negative entry, shared event.
        assert_eq!(w.wake(&node, 4), Woken::NeedsShared);
        assert_eq!(w.len(), 2);
        // A client whose listener is gone is forgotten at its next wake-up.
        drop(l3);
        assert_eq!(w.wake(&node, 3), Woken::NeedsShared);
        assert_eq!(w.len(), 1);
        // Disconnected clients are swept.
        w.retain_connected(|id| id == 1);
        assert!(w.is_empty());
        assert_eq!(w.wake(&node, 1), Woken::Own);
        assert_eq!(count(&l1), 1);
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
