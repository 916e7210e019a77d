//! The Zenoh side of a member: a session in peer mode (multicast and gossip scouting off,
//! explicit endpoints only), the record publisher and subscriber, the catch-up queryable
//! and periodic catch-up queries, and the remote-check queryable.
//!
//! Key expressions (`<fleet>`, `<member>` from [`FleetConfig`]):
//! - `guardian/<fleet>/records`: every member publishes its new records, every member
//!   subscribes;
//! - `guardian/<fleet>/<member>/records`: queryable answering, to a peer whose digest of
//!   the winners differs, every winning record (one reply, frames of `u32` length + record);
//! - `guardian/<fleet>/<member>/check`: queryable for remote check / identify / status
//!   ([`crate::remote`]);
//! - `guardian/<fleet>/acks`: every member publishes a signed acknowledgement of each
//!   record it takes ([`crate::ack`]), every member subscribes (a signer counts those of its
//!   own records).
//!
//! Zenoh runs its own threads; everything received is handed to a `sink` closure (the
//! daemon sends it through a channel to its serving loop), so nothing here touches the
//! screen.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use zenoh::Wait;
use zenoh::query::{ConsolidationMode, Query};
use zenoh::sample::Locality;

use crate::config::FleetConfig;

/// Starting the Zenoh session or declaring on it failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum NodeError {
    /// A Zenoh operation failed.
    #[error("zenoh: {what}: {detail}")]
    Zenoh {
        /// What was being done.
        what: &'static str,
        /// Zenoh's error.
        detail: String,
    },
}

fn zerr(what: &'static str) -> impl FnOnce(zenoh::Error) -> NodeError {
    move |e| NodeError::Zenoh {
        what,
        detail: e.to_string(),
    }
}

/// Something a member received.
#[derive(Debug)]
pub enum Incoming {
    /// A record published by a peer.
    Record(Vec<u8>),
    /// A record of a catch-up reply (may well be older than what the member holds).
    CaughtUp(Vec<u8>),
    /// A remote request, to be answered with [`RemoteCall::reply`].
    Call(RemoteCall),
    /// A peer's holding acknowledgement ([`crate::ack`]), not verified yet.
    Ack(Vec<u8>),
}

/// A remote request waiting for its answer.
#[derive(Debug)]
pub struct RemoteCall {
    query: Query,
}

impl RemoteCall {
    /// The request envelope.
    pub fn payload(&self) -> Vec<u8> {
        self.query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default()
    }

    /// Answer with a response envelope.
    pub fn reply(self, envelope: Vec<u8>) {
        if let Err(e) = self
            .query
            .reply(self.query.key_expr().clone(), envelope)
            .wait()
        {
            tracing::warn!(error = %e, "cannot send a remote answer");
        }
    }

    /// Refuse with a short reason (the caller gets a reply error).
    pub fn refuse(self, reason: &str) {
        if let Err(e) = self.query.reply_err(reason.to_owned()).wait() {
            tracing::warn!(error = %e, "cannot send a remote refusal");
        }
    }
}

/// What the catch-up queryable serves: the winners' digest and their frames.
#[derive(Debug, Default)]
struct Served {
    digest: [u8; 32],
    frames: Arc<Vec<u8>>,
}

/// A running member's Zenoh entities.
pub struct Node {
    session: zenoh::Session,
    records_key: String,
    acks_key: String,
    served: Arc<Mutex<Served>>,
    stop: Arc<AtomicBool>,
    resync: Option<std::thread::JoinHandle<()>>,
    // Declared entities live as long as the node.
    _subscriber: zenoh::pubsub::Subscriber<()>,
    _acks: zenoh::pubsub::Subscriber<()>,
    _records: zenoh::query::Queryable<()>,
    _check: zenoh::query::Queryable<()>,
}

impl std::fmt::Debug for Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Node")
            .field("records_key", &self.records_key)
            .finish_non_exhaustive()
    }
}

/// A Zenoh configuration: peer mode, the given endpoints, no scouting of any kind.
pub fn zenoh_config(listen: &[String], connect: &[String]) -> Result<zenoh::Config, NodeError> {
    let mut c = zenoh::Config::default();
    let json = |v: &[String]| {
        let items: Vec<String> = v.iter().map(|e| format!("{e:?}")).collect();
        format!("[{}]", items.join(","))
    };
    let set =
        |c: &mut zenoh::Config, k: &str, v: &str| c.insert_json5(k, v).map_err(zerr("config"));
    set(&mut c, "mode", "\"peer\"")?;
    set(&mut c, "scouting/multicast/enabled", "false")?;
    set(&mut c, "scouting/gossip/enabled", "false")?;
    set(&mut c, "listen/endpoints", &json(listen))?;
    set(&mut c, "connect/endpoints", &json(connect))?;
    Ok(c)
}

/// Open a Zenoh session with [`zenoh_config`].
pub fn open_session(listen: &[String], connect: &[String]) -> Result<zenoh::Session, NodeError> {
    zenoh::open(zenoh_config(listen, connect)?)
        .wait()
        .map_err(zerr("open session"))
}

/// Frame records for a catch-up reply: per record `u32` length + bytes.
pub fn frame_batch<'a>(records: impl IntoIterator<Item = &'a [u8]>) -> Vec<u8> {
    let mut out = Vec::new();
    for r in records {
        out.extend_from_slice(&(r.len() as u32).to_le_bytes());
        out.extend_from_slice(r);
    }
    out
}

/// Split a catch-up reply into records; a cut-short last frame is returned as the error's
/// byte count (the whole frames before it are kept).
pub fn split_batch(mut b: &[u8]) -> (Vec<Vec<u8>>, usize) {
    let mut out = Vec::new();
    while !b.is_empty() {
        if b.len() < 4 {
            return (out, b.len());
        }
        let len = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize;
        if b.len() - 4 < len {
            return (out, b.len());
        }
        out.push(b[4..4 + len].to_vec());
        b = &b[4 + len..];
    }
    (out, 0)
}

impl Node {
    /// Open the session and declare everything; start the catch-up thread (once now, then
    /// every `resync-ms`). Everything received goes to `sink`.
    pub fn start(
        config: &FleetConfig,
        sink: Arc<dyn Fn(Incoming) + Send + Sync>,
    ) -> Result<Self, NodeError> {
        let session = open_session(&config.listen, &config.connect)?;
        let served = Arc::new(Mutex::new(Served::default()));
        let s = sink.clone();
        let subscriber = session
            .declare_subscriber(config.records_key())
            .callback(move |sample| s(Incoming::Record(sample.payload().to_bytes().into_owned())))
            .wait()
            .map_err(zerr("declare record subscriber"))?;
        let s = sink.clone();
        let acks = session
            .declare_subscriber(config.acks_key())
            .callback(move |sample| s(Incoming::Ack(sample.payload().to_bytes().into_owned())))
            .wait()
            .map_err(zerr("declare acknowledgement subscriber"))?;
        let sv = served.clone();
        let records = session
            .declare_queryable(config.member_records_key())
            .callback(move |query| {
                let (digest, frames) = match sv.lock() {
                    Ok(s) => (s.digest, s.frames.clone()),
                    Err(_) => return,
                };
                let theirs = query.payload().map(|p| p.to_bytes().into_owned());
                if theirs.as_deref() == Some(&digest[..]) || frames.is_empty() {
                    return;
                }
                if let Err(e) = query
                    .reply(query.key_expr().clone(), frames.as_slice().to_vec())
                    .wait()
                {
                    tracing::warn!(error = %e, "cannot answer a catch-up query");
                }
            })
            .wait()
            .map_err(zerr("declare catch-up queryable"))?;
        let s = sink.clone();
        let check = session
            .declare_queryable(config.check_key())
            .callback(move |query| s(Incoming::Call(RemoteCall { query })))
            .wait()
            .map_err(zerr("declare check queryable"))?;
        let stop = Arc::new(AtomicBool::new(false));
        let resync = {
            let session = session.clone();
            let stop = stop.clone();
            let served = served.clone();
            let selector = format!("guardian/{}/*/records", config.name);
            let every = Duration::from_millis(config.resync_ms);
            std::thread::Builder::new()
                .name("fleet-resync".into())
                .spawn(move || {
                    let mut next = Instant::now();
                    while !stop.load(Ordering::SeqCst) {
                        if Instant::now() >= next {
                            let digest = served.lock().map(|s| s.digest).unwrap_or_default();
                            for r in catch_up(&session, &selector, digest) {
                                sink(Incoming::CaughtUp(r));
                            }
                            next = Instant::now() + every;
                        }
                        std::thread::sleep(Duration::from_millis(20));
                    }
                })
                .map_err(|e| NodeError::Zenoh {
                    what: "spawn the catch-up thread",
                    detail: e.to_string(),
                })?
        };
        tracing::info!(
            fleet = %config.name,
            member = %config.member,
            zid = %session.zid(),
            listen = ?config.listen,
            connect = ?config.connect,
            "fleet session open (peer mode, scouting off)"
        );
        Ok(Self {
            session,
            records_key: config.records_key(),
            acks_key: config.acks_key(),
            served,
            stop,
            resync: Some(resync),
            _subscriber: subscriber,
            _acks: acks,
            _records: records,
            _check: check,
        })
    }

    /// Publish a record to the fleet (to the peers only: a member's own subscriber does
    /// not receive it back, so a record arriving live twice is a replay).
    pub fn publish(&self, record: &[u8]) -> Result<(), NodeError> {
        self.session
            .put(&self.records_key, record.to_vec())
            .allowed_destination(Locality::Remote)
            .wait()
            .map_err(zerr("publish record"))
    }

    /// Publish a holding acknowledgement ([`crate::ack`]) to the peers.
    pub fn acknowledge(&self, ack: Vec<u8>) -> Result<(), NodeError> {
        self.session
            .put(&self.acks_key, ack)
            .allowed_destination(Locality::Remote)
            .wait()
            .map_err(zerr("publish acknowledgement"))
    }

    /// Set what the catch-up queryable serves (after every change of the winners).
    pub fn serve(&self, digest: [u8; 32], frames: Vec<u8>) {
        if let Ok(mut s) = self.served.lock() {
            s.digest = digest;
            s.frames = Arc::new(frames);
        }
    }

    /// Peers currently connected (their Zenoh ids).
    pub fn peers(&self) -> usize {
        self.session.info().peers_zid().wait().count()
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.resync.take() {
            let _ = t.join();
        }
    }
}

/// Ask every other member for the winners, sending our digest (peers with the same
/// digest stay silent). Returns the records received.
fn catch_up(session: &zenoh::Session, selector: &str, digest: [u8; 32]) -> Vec<Vec<u8>> {
    let replies = match session
        .get(selector)
        .payload(digest.to_vec())
        .allowed_destination(Locality::Remote)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .wait()
    {
        Ok(r) => r,
        Err(e) => {
            tracing::warn!(error = %e, "fleet catch-up query failed");
            return Vec::new();
        }
    };
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv() {
        match reply.result() {
            Ok(sample) => {
                let (records, torn) = split_batch(&sample.payload().to_bytes());
                if torn > 0 {
                    tracing::warn!(torn, "catch-up reply with a cut-short last frame");
                }
                out.extend(records);
            }
            Err(e) => tracing::debug!(error = ?e, "catch-up reply error"),
        }
    }
    out
}

/// Publish `bytes` on `key` from `session` (tools and tests; members use [`Node::publish`]).
pub fn put(session: &zenoh::Session, key: &str, bytes: Vec<u8>) -> Result<(), NodeError> {
    session.put(key, bytes).wait().map_err(zerr("put"))
}

/// A remote caller's Zenoh session (peer mode, no scouting, connecting to `connect`).
pub struct Caller {
    session: zenoh::Session,
}

impl std::fmt::Debug for Caller {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Caller").finish_non_exhaustive()
    }
}

impl Caller {
    /// Open a session connecting to `connect`.
    pub fn connect(connect: &[String]) -> Result<Self, NodeError> {
        Ok(Self {
            session: open_session(&[], connect)?,
        })
    }

    /// Send one request envelope to `member` of `fleet`; the answer envelope, or the
    /// member's refusal text.
    pub fn call(
        &self,
        fleet: &str,
        member: &str,
        envelope: Vec<u8>,
        timeout: Duration,
    ) -> Result<Result<Vec<u8>, String>, NodeError> {
        call(&self.session, fleet, member, envelope, timeout)
    }
}

/// Send one remote request envelope to `member` of `fleet` and wait for its answer
/// envelope (or a refusal text).
pub fn call(
    session: &zenoh::Session,
    fleet: &str,
    member: &str,
    envelope: Vec<u8>,
    timeout: Duration,
) -> Result<Result<Vec<u8>, String>, NodeError> {
    let replies = session
        .get(crate::config::check_key(fleet, member))
        .payload(envelope)
        .timeout(timeout)
        .wait()
        .map_err(zerr("send remote request"))?;
    match replies.recv() {
        Ok(reply) => Ok(match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(e) => Err(e
                .payload()
                .try_to_string()
                .map_or_else(|_| "refused".to_owned(), |s| s.into_owned())),
        }),
        Err(_) => Err(NodeError::Zenoh {
            what: "wait for the remote answer",
            detail: format!("no answer from {member} within {timeout:?}"),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_round_trip_and_report_a_cut() {
        let recs: [&[u8]; 3] = [b"a", b"", b"xyz"];
        let b = frame_batch(recs);
        assert_eq!(
            split_batch(&b),
            (recs.iter().map(|r| r.to_vec()).collect(), 0)
        );
        let (got, torn) = split_batch(&b[..b.len() - 1]);
        assert_eq!((got.len(), torn), (2, 6));
    }

    #[test]
    fn config_is_peer_mode_without_scouting() {
        let c = zenoh_config(&["tcp/127.0.0.1:0".into()], &[]).unwrap();
        let s = format!("{c}");
        assert!(s.contains("\"mode\":\"peer\""), "{s}");
        let m = c.get_json("scouting/multicast/enabled").unwrap();
        assert_eq!(m, "false");
        assert_eq!(c.get_json("scouting/gossip/enabled").unwrap(), "false");
    }

    /// Two sessions on loopback: a record published by one reaches the other, and a
    /// catch-up query returns the served winners.
    #[test]
    fn records_flow_between_two_nodes() {
        let port = free_port();
        let cfg = |member: &str, listen: Vec<String>, connect: Vec<String>| FleetConfig {
            name: "unit".into(),
            member: member.into(),
            listen,
            connect,
            signing_key: "/nonexistent".into(),
            admin_keys: vec![],
            caller_keys: vec![],
            resync_ms: 200,
            replicas: 0,
            replica_timeout_ms: 2_000,
        };
        let (tx_a, _rx_a) = std::sync::mpsc::channel();
        let tx_a = Mutex::new(tx_a);
        let a = Node::start(
            &cfg("a", vec![format!("tcp/127.0.0.1:{port}")], vec![]),
            Arc::new(move |i| {
                let _ = tx_a.lock().unwrap().send(i);
            }),
        )
        .unwrap();
        a.serve([1; 32], frame_batch([&b"old"[..]]));
        let (tx_b, rx_b) = std::sync::mpsc::channel();
        let tx_b = Mutex::new(tx_b);
        let _b = Node::start(
            &cfg("b", vec![], vec![format!("tcp/127.0.0.1:{port}")]),
            Arc::new(move |i| {
                let _ = tx_b.lock().unwrap().send(i);
            }),
        )
        .unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        let mut got = Vec::new();
        while Instant::now() < deadline
            && !(got.contains(&b"old".to_vec()) && got.contains(&b"new".to_vec()))
        {
            let _ = a.publish(b"new");
            if let Ok(Incoming::Record(r) | Incoming::CaughtUp(r)) =
                rx_b.recv_timeout(Duration::from_millis(100))
            {
                got.push(r);
            }
        }
        assert!(got.contains(&b"old".to_vec()), "catch-up: {got:?}");
        assert!(got.contains(&b"new".to_vec()), "publish: {got:?}");
    }

    fn free_port() -> u16 {
        std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port()
    }
}
