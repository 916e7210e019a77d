//! Who may claim the task (`claim-from`, docs/ros2.md, "Who may claim the task").
//!
//! A claim on `<gate>/task` is a sample from some DDS writer. ROS 2 says which node owns a
//! writer on `ros_discovery_info` (`rmw_dds_common/ParticipantEntitiesInfo`, published by
//! every RMW's participant): the gate reads it and takes a claim only from a writer of a
//! node named in `claim-from`. A claim from any other writer is refused (logged, counted in
//! /diagnostics) and changes nothing: neither the claimed task nor identify mode.
//!
//! The claim and the discovery sample come on different topics, so a claim may arrive
//! before the gate knows its writer's node: it waits (the latest per writer, at most
//! [`MAX_WAITING`] writers) until the writer is known, and then counts only if no newer
//! claim has been taken meanwhile. A claim whose writer no node owns after
//! [`WRITER_WAIT`] (a raw DDS writer, or one its participant does not list) is refused.
//!
//! With `claim-from` empty every writer may claim (the behaviour before the key existed).
//! A node name is what its participant says of itself: this keeps a misconfigured or
//! stray node from steering the gate, not a hostile participant, which only DDS Security
//! (SROS2 permissions on `rt/<gate>/task`) can keep out.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// A DDS writer's id (its GUID: participant prefix and entity id, 16 bytes).
pub type WriterId = [u8; 16];

/// Claims from writers whose node is not known yet, kept at most.
pub const MAX_WAITING: usize = 64;

/// How long a claim waits for its writer's node before it is refused. An RMW publishes its
/// participant's `ros_discovery_info` as it creates a writer; this covers the two topics'
/// different delivery, not a writer that no node will ever own.
pub const WRITER_WAIT: Duration = Duration::from_secs(2);

/// The node named in a refusal when the writer belongs to none.
pub const NO_NODE: &str = "(no ROS node)";

/// What became of a claim sample.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Taken {
    /// It is the claim now (an empty task: identify mode).
    Claimed(String),
    /// Refused: its writer belongs to this node, not one of `claim-from`.
    Refused {
        /// The writer's node.
        node: String,
        /// The claim.
        task: String,
    },
    /// Its writer's node is not known yet: it waits.
    Waiting,
}

/// The claim and who may make it.
#[derive(Debug, Default)]
pub struct Claims {
    allowed: Vec<String>,
    /// Writer -> fully qualified name of its node, per participant (the participant's
    /// latest `ros_discovery_info` sample replaces its entries).
    nodes: BTreeMap<[u8; 12], BTreeMap<WriterId, String>>,
    /// Claims whose writer is not known yet: writer -> (arrival, when, task).
    waiting: BTreeMap<WriterId, (u64, Instant, String)>,
    /// The claim taken last: (arrival, task; empty for identify mode).
    current: Option<(u64, String)>,
    arrivals: u64,
    refused: u64,
}

impl Claims {
    /// Claims from writers of these nodes (fully qualified names); empty: any writer.
    pub fn new(allowed: Vec<String>) -> Self {
        Self {
            allowed,
            ..Self::default()
        }
    }

    /// Whether claims are limited to the nodes of `claim-from`.
    pub fn limited(&self) -> bool {
        !self.allowed.is_empty()
    }

    /// A participant's nodes and their writers (a `ros_discovery_info` sample). Claims
    /// waiting for one of these writers are decided now; returns them in arrival order.
    pub fn participant(
        &mut self,
        participant: [u8; 12],
        nodes: impl IntoIterator<Item = (String, Vec<WriterId>)>,
    ) -> Vec<Taken> {
        let mut writers = BTreeMap::new();
        for (node, ids) in nodes {
            for id in ids {
                writers.insert(id, node.clone());
            }
        }
        let mut known: Vec<(u64, WriterId, String)> = self
            .waiting
            .iter()
            .filter(|(id, _)| writers.contains_key(*id))
            .map(|(id, (at, _, task))| (*at, *id, task.clone()))
            .collect();
        known.sort();
        self.nodes.insert(participant, writers);
        known
            .into_iter()
            .map(|(at, id, task)| {
                self.waiting.remove(&id);
                self.decide(at, &id, task)
            })
            .collect()
    }

    /// A claim sample from `writer`, arrived at `now`.
    pub fn claim(&mut self, writer: WriterId, task: &str, now: Instant) -> Taken {
        self.arrivals += 1;
        let task = task.trim().to_owned();
        if !self.limited() {
            self.current = Some((self.arrivals, task.clone()));
            return Taken::Claimed(task);
        }
        if self.node_of(&writer).is_none() {
            if self.waiting.len() >= MAX_WAITING && !self.waiting.contains_key(&writer) {
                // The oldest waiting claim gives way.
                if let Some(oldest) = self
                    .waiting
                    .iter()
                    .min_by_key(|(_, (at, _, _))| *at)
                    .map(|(id, _)| *id)
                {
                    self.waiting.remove(&oldest);
                }
            }
            self.waiting.insert(writer, (self.arrivals, now, task));
            return Taken::Waiting;
        }
        self.decide(self.arrivals, &writer, task)
    }

    /// Refuses the claims that have waited [`WRITER_WAIT`] for their writer's node by `now`.
    pub fn expire(&mut self, now: Instant) -> Vec<Taken> {
        let late: Vec<(u64, WriterId)> = self
            .waiting
            .iter()
            .filter(|(_, (_, when, _))| now.saturating_duration_since(*when) >= WRITER_WAIT)
            .map(|(id, (at, _, _))| (*at, *id))
            .collect();
        let mut late = late;
        late.sort();
        late.into_iter()
            .filter_map(|(_, id)| self.waiting.remove(&id))
            .map(|(_, _, task)| {
                self.refused += 1;
                Taken::Refused {
                    node: NO_NODE.into(),
                    task,
                }
            })
            .collect()
    }

    fn decide(&mut self, at: u64, writer: &WriterId, task: String) -> Taken {
        let node = self.node_of(writer).unwrap_or_default().to_owned();
        if !self.allowed.contains(&node) {
            self.refused += 1;
            return Taken::Refused { node, task };
        }
        if self.current.as_ref().is_none_or(|(was, _)| *was < at) {
            self.current = Some((at, task.clone()));
        }
        Taken::Claimed(task)
    }

    fn node_of(&self, writer: &WriterId) -> Option<&str> {
        let prefix: [u8; 12] = writer[..12].try_into().ok()?;
        self.nodes.get(&prefix)?.get(writer).map(String::as_str)
    }

    /// The claimed task; `None`: identify mode.
    pub fn current(&self) -> Option<&str> {
        self.current
            .as_ref()
            .map(|(_, t)| t.as_str())
            .filter(|t| !t.is_empty())
    }

    /// Claims refused so far.
    pub fn refused(&self) -> u64 {
        self.refused
    }

    /// Claims waiting for their writer's node.
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn writer(participant: u8, entity: u8) -> WriterId {
        let mut w = [participant; 16];
        w[12..].copy_from_slice(&[0, 0, entity, 3]);
        w
    }

    fn t0() -> Instant {
        thread_local!(static T0: Instant = Instant::now());
        T0.with(|t| *t)
    }

    fn prefix(participant: u8) -> [u8; 12] {
        [participant; 12]
    }

    #[test]
    fn anyone_may_claim_when_unlimited() {
        let mut c = Claims::new(vec![]);
        assert_eq!(
            c.claim(writer(1, 1), " task-a ", t0()),
            Taken::Claimed("task-a".into())
        );
        assert_eq!(c.current(), Some("task-a"));
        assert_eq!(
            c.claim(writer(2, 1), "", t0()),
            Taken::Claimed(String::new())
        );
        assert_eq!(c.current(), None);
        assert_eq!(c.refused(), 0);
    }

    #[test]
    fn only_the_named_nodes_claim_and_a_refusal_changes_nothing() {
        let mut c = Claims::new(vec!["/cell/executive".into()]);
        c.participant(prefix(1), [("/cell/executive".into(), vec![writer(1, 1)])]);
        c.participant(prefix(2), [("/intruder".into(), vec![writer(2, 1)])]);
        assert_eq!(
            c.claim(writer(1, 1), "task-a", t0()),
            Taken::Claimed("task-a".into())
        );
        for task in ["task-b", ""] {
            assert_eq!(
                c.claim(writer(2, 1), task, t0()),
                Taken::Refused {
                    node: "/intruder".into(),
                    task: task.into()
                }
            );
            assert_eq!(
                c.current(),
                Some("task-a"),
                "a refused {task:?} changed the claim"
            );
        }
        assert_eq!(c.refused(), 2);
        // Another writer of the allowed node's participant that is not the node's is
        // unknown, not allowed.
        assert_eq!(c.claim(writer(1, 9), "task-c", t0()), Taken::Waiting);
        assert_eq!(c.current(), Some("task-a"));
    }

    #[test]
    fn a_claim_before_its_writers_node_is_known_waits_and_keeps_its_order() {
        let mut c = Claims::new(vec!["/exec".into()]);
        assert_eq!(c.claim(writer(1, 1), "old", t0()), Taken::Waiting);
        assert_eq!(c.claim(writer(3, 1), "stray", t0()), Taken::Waiting);
        assert_eq!(c.current(), None);
        // A newer claim from a known writer of the allowed node...
        c.participant(prefix(2), [("/exec".into(), vec![writer(2, 1)])]);
        assert_eq!(
            c.claim(writer(2, 1), "new", t0()),
            Taken::Claimed("new".into())
        );
        // ...is not overtaken by the older waiting one once its node is known.
        let decided = c.participant(prefix(1), [("/exec".into(), vec![writer(1, 1)])]);
        assert_eq!(decided, vec![Taken::Claimed("old".into())]);
        assert_eq!(c.current(), Some("new"));
        let decided = c.participant(prefix(3), [("/stray".into(), vec![writer(3, 1)])]);
        assert_eq!(
            decided,
            vec![Taken::Refused {
                node: "/stray".into(),
                task: "stray".into()
            }]
        );
        assert_eq!((c.current(), c.waiting()), (Some("new"), 0));
    }

    #[test]
    fn a_claim_whose_writer_no_node_owns_is_refused_after_the_wait() {
        let mut c = Claims::new(vec!["/exec".into()]);
        c.participant(prefix(1), [("/exec".into(), vec![writer(1, 1)])]);
        assert_eq!(c.claim(writer(1, 1), "a", t0()), Taken::Claimed("a".into()));
        // A second writer of the same participant that its sample does not list.
        assert_eq!(c.claim(writer(1, 2), "stray", t0()), Taken::Waiting);
        assert!(c.expire(t0() + WRITER_WAIT / 2).is_empty());
        assert_eq!(
            c.expire(t0() + WRITER_WAIT),
            vec![Taken::Refused {
                node: NO_NODE.into(),
                task: "stray".into()
            }]
        );
        assert_eq!((c.current(), c.waiting(), c.refused()), (Some("a"), 0, 1));
        assert!(c.expire(t0() + WRITER_WAIT * 2).is_empty());
    }

    #[test]
    fn waiting_claims_are_bounded() {
        let mut c = Claims::new(vec!["/exec".into()]);
        for p in 0..(MAX_WAITING as u8 + 10) {
            assert_eq!(c.claim(writer(p, 1), "x", t0()), Taken::Waiting);
        }
        assert_eq!(c.waiting(), MAX_WAITING);
        // The oldest gave way: writer 0's claim is gone, the newest is kept.
        assert!(
            c.participant(prefix(0), [("/exec".into(), vec![writer(0, 1)])])
                .is_empty()
        );
        let last = MAX_WAITING as u8 + 9;
        assert_eq!(
            c.participant(prefix(last), [("/exec".into(), vec![writer(last, 1)])]),
            vec![Taken::Claimed("x".into())]
        );
    }

    #[test]
    fn a_participants_new_sample_replaces_its_writers() {
        let mut c = Claims::new(vec!["/exec".into()]);
        c.participant(prefix(1), [("/exec".into(), vec![writer(1, 1)])]);
        c.participant(prefix(1), [("/other".into(), vec![writer(1, 2)])]);
        assert_eq!(c.claim(writer(1, 1), "a", t0()), Taken::Waiting);
        assert!(matches!(
            c.claim(writer(1, 2), "a", t0()),
            Taken::Refused { .. }
        ));
    }
}
