//! The ROS 2 node: the gate's action server, the action client of the real controller,
//! the task subscription, the verdict and diagnostics publishers, and the loop that ties
//! them together (docs/ros2.md).
//!
//! One goal is screened and relayed at a time (as MoveIt sends them to one controller); a
//! goal that arrives meanwhile waits in the DDS queue until the active one has ended. A goal
//! has ended when its result is known: the result then waits for its sender to ask for it
//! (a [`Delivery`], kept up to `result-keep-s`) beside the next goals, so a sender that never
//! asks, or is gone, stalls nothing.

use std::cell::{Cell, RefCell};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context as _, anyhow};
use futures::{FutureExt, StreamExt, pin_mut};
use guardian_robot::kinematics::RobotDescription;
use ros2_client::action::{
    ActionClient, ActionClientQosPolicies, ActionServerQosPolicies, AsyncActionServer,
    ExecutingGoalHandle, GoalEndStatus, GoalId, GoalStatusEnum, SendGoalResponse,
};
use ros2_client::{
    ActionTypeName, Context, MessageTypeName, Name, NodeName, NodeOptions, Publisher, QosProfile,
    ServiceMapping, Subscription,
    qos::{Durability, History},
};

use crate::claim::{Claims, Taken};
use crate::config::{GateConfig, ServiceMappingName};
use crate::guardiand::{Outcome, Screen};
use crate::msgs::{
    DiagnosticArray, DiagnosticStatus, FollowJointTrajectoryFeedback as Feedback,
    FollowJointTrajectoryGoal as Goal, FollowJointTrajectoryResult as GoalResult, Header, KeyValue,
    ParticipantEntitiesInfo, StringMsg, Time, Verdict, error_code,
};
use crate::plan::PlanMapper;
use crate::sockets;

/// A FollowJointTrajectory action server (the gate's own, a controller's).
pub type Server = AsyncActionServer<Goal, GoalResult, Feedback>;
/// A FollowJointTrajectory action client (the gate's to its controller, MoveIt's).
pub type Controller = ActionClient<Goal, GoalResult, Feedback>;
/// The controller's pending answer to a goal the gate sent.
type GoalAnswer<'a> =
    futures::future::LocalBoxFuture<'a, ros2_client::ReadResult<SendGoalResponse>>;

/// How long a goal the gate aborted for an unanswered controller is watched for a late
/// acceptance, which is cancelled.
const LATE_WINDOW: Duration = Duration::from_secs(10);

/// ROS 2's service default: reliable, volatile, keep last 10.
fn service_qos() -> QosProfile {
    QosProfile::publisher_default()
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

/// Reliable, transient local, keep last 1: the claimed task, and action status.
fn latched_qos() -> QosProfile {
    QosProfile::publisher_default()
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// QoS of an action server as ROS 2 sets it up.
pub fn action_server_qos() -> ActionServerQosPolicies {
    ActionServerQosPolicies {
        goal_service: service_qos(),
        result_service: service_qos(),
        cancel_service: service_qos(),
        feedback_publisher: service_qos(),
        status_publisher: latched_qos(),
    }
}

/// QoS of an action client as ROS 2 sets it up.
pub fn action_client_qos() -> ActionClientQosPolicies {
    ActionClientQosPolicies {
        goal_service: service_qos(),
        result_service: service_qos(),
        cancel_service: service_qos(),
        feedback_subscription: service_qos(),
        status_subscription: latched_qos(),
    }
}

/// The ros2-client mapping for a configured name.
pub fn service_mapping(name: ServiceMappingName) -> ServiceMapping {
    match name {
        ServiceMappingName::Enhanced => ServiceMapping::Enhanced,
        ServiceMappingName::Cyclone => ServiceMapping::Cyclone,
        ServiceMappingName::Basic => ServiceMapping::Basic,
    }
}

/// The action type the gate serves and forwards.
pub fn follow_joint_trajectory() -> ActionTypeName {
    ActionTypeName::new("control_msgs", "FollowJointTrajectory")
}

/// `<namespace>/follow_joint_trajectory`.
pub fn action_name(namespace: &str) -> anyhow::Result<Name> {
    Name::new(namespace, "follow_joint_trajectory")
        .map_err(|e| anyhow!("action name under {namespace:?}: {e:?}"))
}

/// The FollowJointTrajectory action server `<namespace>/follow_joint_trajectory` on `node`,
/// with ROS 2's action QoS.
pub fn action_server(
    node: &mut ros2_client::Node,
    mapping: ServiceMapping,
    namespace: &str,
) -> anyhow::Result<Server> {
    Ok(AsyncActionServer::new(
        node.create_action_server::<Goal, GoalResult, Feedback>(
            mapping,
            &action_name(namespace)?,
            &follow_joint_trajectory(),
            action_server_qos(),
        )
        .map_err(|e| anyhow!("action server under {namespace:?}: {e:?}"))?,
    ))
}

/// A FollowJointTrajectory action client of `<namespace>/follow_joint_trajectory` on `node`,
/// with ROS 2's action QoS.
pub fn action_client(
    node: &mut ros2_client::Node,
    mapping: ServiceMapping,
    namespace: &str,
) -> anyhow::Result<Controller> {
    node.create_action_client::<Goal, GoalResult, Feedback>(
        mapping,
        &action_name(namespace)?,
        &follow_joint_trajectory(),
        action_client_qos(),
    )
    .map_err(|e| anyhow!("action client of {namespace:?}: {e:?}"))
}

/// How many participant ids [`context`] passes over whose user-traffic port another process
/// holds, before it gives up.
const TAKEN_IDS_MAX: usize = 8;

/// A DDS participant on `domain`, limited to the interfaces with `only_networks` (all if
/// empty), as a ros2-client context. With `only_networks`, its UDP sockets only take
/// datagrams that came in on their interface ([`sockets`]); that failing is an error.
///
/// RustDDS takes the first participant id whose discovery port is free, and if that id's
/// user-traffic port is taken (a participant of another DDS that numbers its ports
/// otherwise, started at the same moment: seen with Fast DDS) it listens on an ephemeral
/// port but still announces its writers on the taken one, so readers send their
/// acknowledgements elsewhere and a reliable topic stalls at its first lost sample. Such a
/// participant is dropped and built again while the gate holds that id's discovery port,
/// which moves RustDDS to the next id.
pub fn context(domain: u16, only_networks: &[std::net::IpAddr]) -> anyhow::Result<Context> {
    let device = sockets::interface_of(only_networks)?;
    let mut held = Vec::new();
    for _ in 0..=TAKEN_IDS_MAX {
        let before = sockets::sockets()?;
        let mut b = ros2_client::dds::rustdds::DomainParticipantBuilder::new(domain);
        if !only_networks.is_empty() {
            b = b.with_only_networks(only_networks.iter().copied());
        }
        let dp = b
            .build()
            .map_err(|e| anyhow!("DDS participant on domain {domain}: {e:?}"))?;
        let id = dp.participant_id();
        let user_port = sockets::user_unicast_port(domain, id);
        if !sockets::new_udp_ports(&before)?
            .iter()
            .any(|&p| u32::from(p) == user_port)
        {
            tracing::warn!(
                "DDS participant id {id} on domain {domain}: another process holds its \
                 user-traffic port {user_port}; taking the next id"
            );
            drop(dp);
            // If this fails, someone else holds the port, which moves RustDDS on as well.
            if let Ok(port) = u16::try_from(sockets::discovery_unicast_port(domain, id))
                && let Ok(s) = std::net::UdpSocket::bind((std::net::Ipv4Addr::UNSPECIFIED, port))
            {
                held.push(s);
            }
            continue;
        }
        if let Some(device) = &device {
            // On an error `dp` is dropped here, closing its sockets.
            let n = sockets::bind_new(&before, device)?;
            tracing::info!(
                "DDS sockets restricted to interface {device} ({n} sockets, domain {domain})"
            );
        }
        return Context::from_domain_participant(dp).map_err(|e| anyhow!("ROS 2 context: {e:?}"));
    }
    Err(anyhow!(
        "DDS participant on domain {domain}: the user-traffic ports of {} participant ids in a \
         row are held by other processes",
        TAKEN_IDS_MAX + 1
    ))
}

enum Event {
    Goal(ros2_client::ReadResult<ros2_client::action::NewGoalHandle<Goal>>),
    Done(Option<Delivery>),
    Delivered,
    Cancel(ros2_client::ReadResult<ros2_client::action::CancelHandle>),
    Tick,
}

/// A goal's result waiting for its sender's result request (ROS 2 actions answer results on
/// request): delivered beside the next goals, dropped after `result-keep-s`.
struct Delivery {
    executing: ExecutingGoalHandle<Goal>,
    end: GoalEndStatus,
    result: GoalResult,
}

/// How often a waiting delivery looks again for its result request (another delivery may
/// have read it off the shared request stream meanwhile, into the server's table).
const DELIVERY_RETRY: Duration = Duration::from_millis(100);

/// Counters for /diagnostics.
#[derive(Debug, Default)]
struct Counts {
    go: Cell<u64>,
    no_go: Cell<u64>,
    errors: Cell<u64>,
}

struct Gate<'a> {
    config: &'a GateConfig,
    mapper: PlanMapper,
    screen: Screen,
    server: Server,
    controller: Controller,
    task: Subscription<StringMsg>,
    /// `ros_discovery_info`, read when `claim-from` limits who may claim.
    discovery: Option<Subscription<ParticipantEntitiesInfo>>,
    claims: RefCell<Claims>,
    verdicts: Publisher<Verdict>,
    counts: Counts,
    /// The active goal: (ours, the controller's) once forwarded.
    forwarded: Cell<Option<(GoalId, GoalId)>>,
    /// guardiand's reachability at the last /diagnostics (logged when it changes).
    reachable: Cell<Option<bool>>,
}

/// A node named `name` on `ctx`'s domain, its spinner running.
fn spinning_node(ctx: &Context, name: &str) -> anyhow::Result<ros2_client::Node> {
    let mut node = ctx
        .new_node(
            NodeName::new("/", name).map_err(|e| anyhow!("node name {name:?}: {e:?}"))?,
            NodeOptions::new().enable_rosout(false),
        )
        .map_err(|e| anyhow!("creating the node on domain {}: {e:?}", ctx.domain_id()))?;
    let spinner = node.spinner().map_err(|e| anyhow!("node spinner: {e:?}"))?;
    smol::spawn(spinner.spin()).detach();
    Ok(node)
}

/// Run the gate until `stop` is set.
pub fn run(config: GateConfig, stop: Arc<AtomicBool>) -> anyhow::Result<()> {
    let description = RobotDescription::resolve(&config.robot)
        .with_context(|| format!("robot {:?}", config.robot))?;
    let mapper = PlanMapper::new(&description, config.tool.clone());
    let screen = Screen::start(&config.guardiand).context("starting the guardiand client")?;
    let ctx = context(config.domain(), &config.only_networks)?;
    let mut node = spinning_node(&ctx, &config.node_name)?;

    let mapping = service_mapping(config.service_mapping);
    let server = action_server(&mut node, mapping, &config.gate)?;
    // The controller on a domain of its own: a second participant, which only the gate uses
    // (kept until the gate stops).
    let mut controller_node = None;
    let controller = if config.controller_domain() == config.domain() {
        action_client(&mut node, mapping, &config.controller)?
    } else {
        let ctx = context(config.controller_domain(), &config.only_networks)?;
        let mut n = spinning_node(&ctx, &config.node_name)?;
        let client = action_client(&mut n, mapping, &config.controller)?;
        controller_node = Some((n, ctx));
        client
    };
    let task_topic = node
        .create_topic(
            &Name::new(&config.gate, "task").map_err(|e| anyhow!("task topic: {e:?}"))?,
            MessageTypeName::new("std_msgs", "String"),
            &latched_qos(),
        )
        .map_err(|e| anyhow!("task topic: {e:?}"))?;
    let task = node
        .create_subscription::<StringMsg>(&task_topic, Some(latched_qos()))
        .map_err(|e| anyhow!("task subscription: {e:?}"))?;
    // Who owns which writer, from every participant's ROS 2 discovery sample (transient
    // local: each participant's latest comes when the gate joins).
    let discovery = if config.claim_from.is_empty() {
        tracing::warn!(
            gate = %config.gate,
            "any participant on the domain may claim the task on {}/task: set claim-from to the task executive's node",
            config.gate
        );
        None
    } else {
        let qos = latched_qos().history(History::KeepLast { depth: 64 });
        let topic = ctx
            .create_topic(
                "ros_discovery_info".into(),
                MessageTypeName::new("rmw_dds_common", "ParticipantEntitiesInfo"),
                &qos,
            )
            .map_err(|e| anyhow!("ros_discovery_info topic: {e:?}"))?;
        Some(
            node.create_subscription::<ParticipantEntitiesInfo>(&topic, Some(qos))
                .map_err(|e| anyhow!("ros_discovery_info subscription: {e:?}"))?,
        )
    };
    let verdict_topic = node
        .create_topic(
            &Name::new(&config.gate, "verdicts").map_err(|e| anyhow!("verdict topic: {e:?}"))?,
            MessageTypeName::new("guardian_msgs", "Verdict"),
            &service_qos(),
        )
        .map_err(|e| anyhow!("verdict topic: {e:?}"))?;
    let verdicts = node
        .create_publisher::<Verdict>(&verdict_topic, Some(service_qos()))
        .map_err(|e| anyhow!("verdict publisher: {e:?}"))?;
    let diag_topic = node
        .create_topic(
            &Name::new("/", "diagnostics").map_err(|e| anyhow!("diagnostics topic: {e:?}"))?,
            MessageTypeName::new("diagnostic_msgs", "DiagnosticArray"),
            &service_qos(),
        )
        .map_err(|e| anyhow!("diagnostics topic: {e:?}"))?;
    let diagnostics = node
        .create_publisher::<DiagnosticArray>(&diag_topic, Some(service_qos()))
        .map_err(|e| anyhow!("diagnostics publisher: {e:?}"))?;

    let gate = Gate {
        config: &config,
        mapper,
        screen,
        server,
        controller,
        task,
        discovery,
        claims: RefCell::new(Claims::new(config.claim_from.clone())),
        verdicts,
        counts: Counts::default(),
        forwarded: Cell::new(None),
        reachable: Cell::new(None),
    };
    tracing::info!(
        gate = %config.gate,
        controller = %config.controller,
        domain = config.domain(),
        controller_domain = config.controller_domain(),
        robot = %config.robot,
        "guardian-gate serving {}/follow_joint_trajectory",
        config.gate
    );
    // Until a claim arrives the gate identifies.
    if gate.current_claim().is_none() {
        gate.warn_identify_mode();
    }
    smol::block_on(gate.serve(&stop, &diagnostics));
    tracing::info!("guardian-gate stopped");
    drop(controller_node);
    drop(node);
    Ok(())
}

impl Gate<'_> {
    async fn serve(&self, stop: &AtomicBool, diagnostics: &Publisher<DiagnosticArray>) {
        let mut active: Option<futures::future::LocalBoxFuture<'_, Option<Delivery>>> = None;
        let mut deliveries = futures::stream::FuturesUnordered::new();
        let mut ticks = StreamExt::fuse(smol::Timer::interval(Duration::from_millis(100)));
        let mut last_diag = Instant::now() - Duration::from_secs(2);
        while !stop.load(Ordering::Relaxed) {
            if last_diag.elapsed() >= Duration::from_secs(1) {
                last_diag = Instant::now();
                self.publish_diagnostics(diagnostics).await;
            }
            let has_active = active.is_some();
            let event = {
                let new_goal = async {
                    if has_active {
                        futures::future::pending().await
                    } else {
                        self.server.receive_new_goal().await
                    }
                }
                .fuse();
                let running = async {
                    match active.as_mut() {
                        Some(f) => f.await,
                        None => futures::future::pending().await,
                    }
                }
                .fuse();
                let cancel = self.server.receive_cancel_request().fuse();
                let delivered = async {
                    if deliveries.is_empty() {
                        futures::future::pending().await
                    } else {
                        deliveries.next().await
                    }
                }
                .fuse();
                pin_mut!(new_goal, running, cancel, delivered);
                futures::select! {
                    g = new_goal => Event::Goal(g),
                    d = running => Event::Done(d),
                    c = cancel => Event::Cancel(c),
                    _ = delivered => Event::Delivered,
                    _ = ticks.next() => Event::Tick,
                }
            };
            match event {
                Event::Goal(Ok(handle)) => active = Some(self.handle_goal(handle).boxed_local()),
                Event::Goal(Err(e)) => tracing::warn!("receiving a goal: {e:?}"),
                Event::Done(delivery) => {
                    active = None;
                    self.forwarded.set(None);
                    if let Some(d) = delivery {
                        if deliveries.len() >= self.config.max_pending_results {
                            tracing::warn!(
                                pending = deliveries.len(),
                                "too many results waiting for their senders; the oldest are kept, this one is dropped"
                            );
                        } else {
                            deliveries.push(self.deliver(d).boxed_local());
                        }
                    }
                }
                Event::Delivered => {}
                Event::Cancel(Ok(handle)) => self.relay_cancel(handle).await,
                Event::Cancel(Err(e)) => tracing::warn!("receiving a cancel request: {e:?}"),
                Event::Tick => {}
            }
        }
    }

    /// The latest claim on `<gate>/task` from a writer that may claim ([`Claims`]; an empty
    /// string clears it: identify mode). Entering identify mode is said with a WARN: a plan
    /// then passes as whichever enrolled class it is nearest to.
    fn current_claim(&self) -> Option<String> {
        let was = self.claims.borrow().current().map(str::to_owned);
        let mut taken = Vec::new();
        if let Some(discovery) = &self.discovery {
            while let Ok(Some((info, _))) = discovery.take() {
                let nodes = info.node_entities_info_seq.iter().map(|n| {
                    let writers = n.writer_gid_seq.iter().map(|g| g.data).collect();
                    (n.fully_qualified_name(), writers)
                });
                let prefix = info.gid.data[..12].try_into().unwrap_or_default();
                taken.extend(self.claims.borrow_mut().participant(prefix, nodes));
            }
        }
        while let Ok(Some((msg, info))) = self.task.take() {
            let writer = info.publisher_gid().to_bytes16();
            taken.push(
                self.claims
                    .borrow_mut()
                    .claim(writer, &msg.data, Instant::now()),
            );
        }
        taken.extend(self.claims.borrow_mut().expire(Instant::now()));
        for t in taken {
            match t {
                Taken::Claimed(claim) => tracing::info!(claim = %claim, "claimed task"),
                Taken::Refused { node, task } => tracing::warn!(
                    node = %node,
                    claim = %task,
                    allowed = ?self.config.claim_from,
                    "claim refused: its writer's node is not one of claim-from; the claim is unchanged"
                ),
                Taken::Waiting => tracing::debug!("a claim waits for its writer's node"),
            }
        }
        let now = self.claims.borrow().current().map(str::to_owned);
        if was.is_some() && now.is_none() {
            self.warn_identify_mode();
        }
        now
    }

    /// What identify mode lets through, said once each time the gate enters it.
    fn warn_identify_mode(&self) {
        tracing::warn!(
            gate = %self.config.gate,
            "identify mode (no claimed task): a plan passes as whichever class guardiand serves it is nearest to, \
             any enrolled class, those of a shipped default bank too; publish the task on {}/task to check plans against it",
            self.config.gate
        );
    }

    async fn handle_goal(
        &self,
        handle: ros2_client::action::NewGoalHandle<Goal>,
    ) -> Option<Delivery> {
        let goal_id = handle.goal_id();
        let Some(goal) = self.server.get_new_goal(handle.clone()) else {
            tracing::warn!("goal {goal_id:?} vanished before it was screened");
            return None;
        };
        let claim = self.current_claim();
        let id_hex = uuid_hex(&goal_id);
        let plan = match self.mapper.map(&goal.trajectory) {
            Ok(p) => p,
            Err(e) => {
                let detail = format!("guardian: INVALID_JOINTS: {e}");
                tracing::info!(goal = %id_hex, verdict = "no-go", reason = "invalid-joints", "{detail}");
                self.publish_verdict(
                    &id_hex,
                    &claim,
                    &Outcome {
                        verdict: "no-go",
                        ..Outcome::failed("invalid-joints", detail.clone())
                    },
                    "",
                    0,
                );
                self.counts.no_go.set(self.counts.no_go.get() + 1);
                return self
                    .refuse(handle, error_code::INVALID_JOINTS, detail)
                    .await;
            }
        };
        let sha = plan.sha256();
        let waypoints = plan.waypoints() as u32;
        let outcome = self.screen.screen(plan, claim.clone()).await;
        self.publish_verdict(&id_hex, &claim, &outcome, &sha, waypoints);
        tracing::info!(goal = %id_hex, verdict = outcome.verdict, reason = outcome.reason, "{}", outcome.detail);
        if !outcome.go {
            let c = if outcome.verdict == "error" {
                &self.counts.errors
            } else {
                &self.counts.no_go
            };
            c.set(c.get() + 1);
            return self
                .refuse(handle, error_code::INVALID_GOAL, outcome.detail)
                .await;
        }
        self.counts.go.set(self.counts.go.get() + 1);
        // The screen said go; if the controller then fails the goal, the verdicts topic says
        // so too (a second verdict for the goal), so no one reads a lost goal as executed.
        let (failed, delivery) = self.forward(handle, goal).await;
        if let Some((reason, detail)) = failed {
            tracing::warn!(goal = %id_hex, reason, "{detail}");
            self.publish_verdict(
                &id_hex,
                &claim,
                &Outcome::failed(reason, detail),
                &sha,
                waypoints,
            );
        }
        delivery
    }

    /// Accept, then abort with `code` and `detail`: the only way FollowJointTrajectory
    /// carries an error code and string to MoveIt. Never forwarded. The aborted result is
    /// returned, for its sender to fetch.
    async fn refuse(
        &self,
        handle: ros2_client::action::NewGoalHandle<Goal>,
        code: i32,
        detail: String,
    ) -> Option<Delivery> {
        let executing = async {
            let accepted = self
                .server
                .accept_goal(handle)
                .await
                .map_err(|e| format!("{e:?}"))?;
            self.server
                .start_executing_goal(accepted)
                .await
                .map_err(|e| format!("{e:?}"))
        };
        match executing.await {
            Ok(executing) => Some(Delivery {
                executing,
                end: GoalEndStatus::Aborted,
                result: GoalResult {
                    error_code: code,
                    error_string: detail,
                },
            }),
            Err(e) => {
                tracing::warn!("refusing a goal: {e}");
                None
            }
        }
    }

    /// Answer the result request of a goal that has ended, when its sender asks, for at most
    /// `result-keep-s`.
    async fn deliver(&self, d: Delivery) {
        let id = uuid_hex(&d.executing.goal_id());
        if self
            .deliver_for(d, self.config.result_keep())
            .await
            .is_some()
        {
            tracing::warn!(
                goal = %id,
                keep_s = self.config.result_keep().as_secs(),
                "a goal's result was never asked for (its sender gone?); dropped"
            );
        }
    }

    /// A refused goal's result delivered at once if its sender asks within a second (MoveIt
    /// asks right after the goal's answer), before the gate waits on the controller; what
    /// is still waiting is returned.
    async fn deliver_first(&self, d: Option<Delivery>) -> Option<Delivery> {
        self.deliver_for(d?, Duration::from_secs(1)).await
    }

    /// Answer `d`'s result request if it comes within `keep` (`None`: answered, or the
    /// answer failed and was logged); `d` again if not. Each attempt is bounded, so a
    /// request another delivery read off the shared request stream (into the server's
    /// table) is found at the next attempt.
    async fn deliver_for(&self, d: Delivery, keep: Duration) -> Option<Delivery> {
        let deadline = Instant::now() + keep;
        while Instant::now() < deadline {
            let attempt = self
                .server
                .send_result_response(d.executing.clone(), d.end, d.result.clone())
                .boxed_local();
            match futures::future::select(attempt, smol::Timer::after(DELIVERY_RETRY)).await {
                futures::future::Either::Left((Ok(()), _)) => return None,
                futures::future::Either::Left((Err(e), _)) => {
                    let id = uuid_hex(&d.executing.goal_id());
                    tracing::warn!(goal = %id, "sending a goal's result: {e:?}");
                    return None;
                }
                futures::future::Either::Right(_) => {}
            }
        }
        Some(d)
    }

    /// Send the goal unchanged to the controller and relay its answers. When the controller
    /// never takes the goal (sending failed, its answer was lost or late), MoveIt hears
    /// aborted and the reason and detail are returned.
    async fn forward(
        &self,
        handle: ros2_client::action::NewGoalHandle<Goal>,
        goal: Goal,
    ) -> (Option<(&'static str, String)>, Option<Delivery>) {
        // The gate chooses the controller goal's id when it sends it, so a goal the
        // controller has not answered in time can still be cancelled by id.
        let (request, ctrl_id) = match self.controller.send_goal(goal) {
            Ok(sent) => sent,
            Err(e) => {
                self.counts.errors.set(self.counts.errors.get() + 1);
                let detail = format!(
                    "guardian gate: sending the goal to {} failed: {e:?}",
                    self.config.controller
                );
                let refused = self
                    .refuse(handle, error_code::INVALID_GOAL, detail.clone())
                    .await;
                return (Some(("controller-unreachable", detail)), refused);
            }
        };
        let answer = self
            .controller
            .goal_client()
            .async_receive_response(request)
            .boxed_local();
        let sent =
            futures::future::select(answer, smol::Timer::after(self.config.controller_timeout()))
                .await;
        let response = match sent {
            futures::future::Either::Left((Ok(r), _)) => r,
            futures::future::Either::Left((Err(e), _)) => {
                self.counts.errors.set(self.counts.errors.get() + 1);
                let detail = format!(
                    "guardian gate: the goal's answer from {} was lost: {e:?}",
                    self.config.controller
                );
                let refused = self
                    .refuse(handle, error_code::INVALID_GOAL, detail.clone())
                    .await;
                let pending = self.deliver_first(refused).await;
                self.cancel_late(ctrl_id, None).await;
                return (Some(("controller-lost", detail)), pending);
            }
            futures::future::Either::Right((_, answer)) => {
                // MoveIt hears "aborted"; the controller may still accept the goal later:
                // it is cancelled now, and again if a late acceptance comes.
                self.counts.errors.set(self.counts.errors.get() + 1);
                let detail = format!(
                    "guardian gate: controller {} did not answer within {:?}; the goal is cancelled at the controller",
                    self.config.controller,
                    self.config.controller_timeout()
                );
                let refused = self
                    .refuse(handle, error_code::INVALID_GOAL, detail.clone())
                    .await;
                let pending = self.deliver_first(refused).await;
                self.cancel_late(ctrl_id, Some(answer)).await;
                return (Some(("controller-timeout", detail)), pending);
            }
        };
        if !response.accepted {
            tracing::info!("controller rejected the goal");
            if let Err(e) = self.server.reject_goal(handle).await {
                tracing::warn!("rejecting a goal: {e:?}");
            }
            let detail = format!(
                "guardian gate: controller {} rejected the goal",
                self.config.controller
            );
            return (Some(("controller-rejected", detail)), None);
        }
        let ours = handle.goal_id();
        self.forwarded.set(Some((ours, ctrl_id)));
        let executing = match self.server.accept_goal(handle).await {
            Ok(a) => match self.server.start_executing_goal(a).await {
                Ok(x) => x,
                Err(e) => {
                    tracing::warn!("starting a goal: {e:?}");
                    return (None, None);
                }
            },
            Err(e) => {
                tracing::warn!("accepting a goal: {e:?}");
                return (None, None);
            }
        };
        let fb = executing.clone();
        let feedback = async {
            let stream = self.controller.feedback_stream(ctrl_id);
            pin_mut!(stream);
            while let Some(f) = stream.next().await {
                match f {
                    Ok(f) => {
                        if let Err(e) = self.server.publish_feedback(fb.clone(), f).await {
                            tracing::debug!("relaying feedback: {e:?}");
                        }
                    }
                    Err(e) => tracing::debug!("controller feedback: {e:?}"),
                }
            }
            futures::future::pending::<()>().await;
        }
        .fuse();
        let result = self.controller.async_request_result(ctrl_id).fuse();
        pin_mut!(feedback, result);
        let (status, result) = futures::select! {
            r = result => match r {
                Ok((status, result)) => (status, result),
                Err(e) => (GoalStatusEnum::Aborted, GoalResult {
                    error_code: error_code::INVALID_GOAL,
                    error_string: format!("guardian gate: the controller's result was lost: {e:?}"),
                }),
            },
            () = feedback => unreachable!("the feedback relay never ends"),
        };
        let end = match status {
            GoalStatusEnum::Succeeded => GoalEndStatus::Succeeded,
            GoalStatusEnum::Canceled => GoalEndStatus::Canceled,
            _ => GoalEndStatus::Aborted,
        };
        (
            None,
            Some(Delivery {
                executing,
                end,
                result,
            }),
        )
    }

    /// Cancel controller goal `ctrl_id`, which MoveIt was told is aborted: at once and, if
    /// its acceptance (`answer`) still arrives within [`LATE_WINDOW`], again then (a cancel
    /// that reached the controller before the goal is refused there as unknown). New goals
    /// wait meanwhile: the gate relays one goal at a time.
    async fn cancel_late(&self, ctrl_id: GoalId, answer: Option<GoalAnswer<'_>>) {
        let cancel = || {
            if let Err(e) = self.controller.cancel_goal(ctrl_id) {
                tracing::error!("cancelling an unanswered goal at the controller: {e:?}");
            }
        };
        cancel();
        let Some(answer) = answer else { return };
        match futures::future::select(answer, smol::Timer::after(LATE_WINDOW)).await {
            futures::future::Either::Left((Ok(r), _)) if r.accepted => {
                cancel();
                // Its end, for the log (and an action server that holds a result until
                // it is asked for it).
                let end = futures::future::select(
                    self.controller.async_request_result(ctrl_id).boxed_local(),
                    smol::Timer::after(LATE_WINDOW),
                )
                .await;
                let status = match end {
                    futures::future::Either::Left((Ok((status, _)), _)) => format!("{status:?}"),
                    futures::future::Either::Left((Err(e), _)) => format!("unknown ({e:?})"),
                    futures::future::Either::Right(_) => "unknown (no result in time)".into(),
                };
                tracing::warn!(
                    goal = %uuid_hex(&ctrl_id),
                    %status,
                    "the controller accepted a goal after the gate had aborted it; it was cancelled again"
                );
            }
            futures::future::Either::Left(_) => {}
            futures::future::Either::Right(_) => tracing::warn!(
                goal = %uuid_hex(&ctrl_id),
                window = ?LATE_WINDOW,
                "the controller never answered a goal the gate aborted; a cancel was sent"
            ),
        }
    }

    /// A cancel for the active, forwarded goal goes to the controller; the controller's
    /// answer is ours.
    async fn relay_cancel(&self, handle: ros2_client::action::CancelHandle) {
        let to_cancel: Vec<GoalId> = match self.forwarded.get() {
            Some((ours, ctrl)) if handle.contains_goal(&ours) => {
                match self
                    .controller
                    .async_cancel_goal(ctrl, ros2_client::builtin_interfaces::Time::ZERO)
                    .await
                {
                    Ok(r) if !r.goals_canceling.is_empty() => vec![ours],
                    Ok(_) => Vec::new(),
                    Err(e) => {
                        tracing::warn!("relaying a cancel: {e:?}");
                        Vec::new()
                    }
                }
            }
            _ => Vec::new(),
        };
        if let Err(e) = self
            .server
            .respond_to_cancel_requests(&handle, to_cancel.into_iter())
            .await
        {
            tracing::warn!("answering a cancel: {e:?}");
        }
    }

    fn publish_verdict(
        &self,
        goal_id: &str,
        claim: &Option<String>,
        o: &Outcome,
        sha: &str,
        waypoints: u32,
    ) {
        let v = Verdict {
            header: Header {
                stamp: Time::now(),
                frame_id: String::new(),
            },
            goal_id: goal_id.to_string(),
            claimed_task: claim.clone().unwrap_or_default(),
            verdict: o.verdict.to_string(),
            reason: o.reason.to_string(),
            detail: o.detail.clone(),
            nearest_class: o.nearest.clone(),
            distance: o.distance,
            threshold: o.threshold,
            model_version: o.model_version.clone(),
            bank_version: o.bank_version,
            trajectory_sha256: sha.to_string(),
            waypoints,
        };
        if let Err(e) = self.verdicts.publish(v) {
            tracing::warn!("publishing a verdict: {e:?}");
        }
    }

    async fn publish_diagnostics(&self, diagnostics: &Publisher<DiagnosticArray>) {
        let status = self.screen.status().await;
        let mut values = vec![
            KeyValue {
                key: "guardiand reachable".into(),
                value: status.is_ok().to_string(),
            },
            KeyValue {
                key: "claimed task".into(),
                value: self.current_claim().unwrap_or_default(),
            },
            KeyValue {
                key: "claims refused".into(),
                value: self.claims.borrow().refused().to_string(),
            },
            KeyValue {
                key: "mode".into(),
                value: if self.claims.borrow().current().is_some() {
                    "claimed".into()
                } else {
                    "identify: any enrolled class passes".into()
                },
            },
            KeyValue {
                key: "go".into(),
                value: self.counts.go.get().to_string(),
            },
            KeyValue {
                key: "no-go".into(),
                value: self.counts.no_go.get().to_string(),
            },
            KeyValue {
                key: "errors".into(),
                value: self.counts.errors.get().to_string(),
            },
        ];
        let reachable = status.is_ok();
        if self.reachable.replace(Some(reachable)) != Some(reachable) {
            match &status {
                Ok(s) => tracing::info!(
                    model = %s.model_version,
                    classes = s.classes,
                    robot = %s.robot.name,
                    "guardiand reachable"
                ),
                Err(e) => tracing::warn!("guardiand unreachable, every goal is refused: {e}"),
            }
        }
        let (level, message) = match &status {
            Ok(s) => {
                values.push(KeyValue {
                    key: "model version".into(),
                    value: s.model_version.clone(),
                });
                values.push(KeyValue {
                    key: "bank size".into(),
                    value: s.classes.to_string(),
                });
                values.push(KeyValue {
                    key: "bank version".into(),
                    value: s.bank_version.to_string(),
                });
                values.push(KeyValue {
                    key: "robot".into(),
                    value: s.robot.name.clone(),
                });
                (0u8, "guardiand reachable".to_string())
            }
            Err(e) => (
                2u8,
                format!("guardiand unreachable (every goal is refused): {e}"),
            ),
        };
        let msg = DiagnosticArray {
            header: Header {
                stamp: Time::now(),
                frame_id: String::new(),
            },
            status: vec![DiagnosticStatus {
                level,
                name: format!("{}: guardian gate", self.config.node_name),
                message,
                hardware_id: self.mapper.robot_name().to_string(),
                values,
            }],
        };
        if let Err(e) = diagnostics.publish(msg) {
            tracing::debug!("publishing diagnostics: {e:?}");
        }
    }
}

/// A goal id as 32 hex digits.
pub fn uuid_hex(id: &GoalId) -> String {
    id.uuid.simple().to_string()
}

#[cfg(test)]
mod tests {
    use std::net::UdpSocket;

    use super::*;
    use crate::sockets::{discovery_unicast_port, user_unicast_port};

    fn bind(port: u32) -> std::io::Result<UdpSocket> {
        UdpSocket::bind(("0.0.0.0", u16::try_from(port).unwrap()))
    }

    #[test]
    fn a_participant_whose_user_port_is_taken_is_built_on_the_next_id() {
        // No other test of the project uses domain 231.
        let domain = 231;
        // The id RustDDS would take: the first whose discovery port is free.
        let first = (0..20)
            .find(|&id| bind(discovery_unicast_port(domain, id)).is_ok())
            .expect("a free participant id on domain 231");
        // Another process's participant on that id's user-traffic port.
        let _other = bind(user_unicast_port(domain, first)).unwrap();
        let before = sockets::sockets().unwrap();
        let ctx = context(domain, &[]).unwrap();
        let id = ctx.domain_participant().participant_id();
        assert!(id > first, "participant id {id}, the taken one {first}");
        let ports = sockets::new_udp_ports(&before).unwrap();
        assert!(
            ports
                .iter()
                .any(|&p| u32::from(p) == user_unicast_port(domain, id)),
            "id {id} listens on its user-traffic port: {ports:?}"
        );
        // The taken id's discovery port was held only while building.
        assert!(bind(discovery_unicast_port(domain, first)).is_ok());
    }
}
