//! The gate end to end over real DDS on loopback, in three processes: this test (a MoveIt
//! stand-in action client and a controller stand-in action server, each its own DDS
//! participant), the `guardian-gate` binary, and a real `guardiand` with enrolled classes.
//! The DDS domain is the test's own and discovery is limited to 127.0.0.1.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures::{FutureExt, StreamExt, pin_mut};
use guardian_client::samples;
use guardian_client::{Decision, Trajectory};
use guardian_gate::msgs::{
    DiagnosticArray, FollowJointTrajectoryFeedback as Feedback, FollowJointTrajectoryGoal as Goal,
    FollowJointTrajectoryResult as GoalResult, JointTrajectory, JointTrajectoryPoint, StringMsg,
    Verdict, error_code,
};
use guardian_gate::node::{action_client, action_server, context};
use guardian_tests::harness::{Daemon, Setup, workspace_root};
use ros2_client::action::{ActionClient, GoalEndStatus, GoalStatusEnum};
use ros2_client::qos::{Durability, History};
use ros2_client::{MessageTypeName, Name, Node, NodeName, NodeOptions, QosProfile, ServiceMapping};

/// Functional bound for one exchange (not a performance claim).
const PATIENCE: Duration = Duration::from_secs(30);
/// A goal whose `goal_time_tolerance.sec` is this runs until canceled (or 20 s).
const LONG: i32 = 99;
/// A goal whose `goal_time_tolerance.sec` is this is answered only after [`SLOW_ACCEPT`]
/// (past the gate's `controller-timeout-ms`, 5 s here), then runs as a `LONG` one.
const SLOW: i32 = 98;
const SLOW_ACCEPT: Duration = Duration::from_secs(6);

fn loopback() -> Vec<std::net::IpAddr> {
    vec!["127.0.0.1".parse().unwrap()]
}

/// Takes `/diagnostics` samples until `done` (given a value getter and the status; it may
/// assert on every sample) says one is what the step waits for; panics after [`PATIENCE`].
async fn wait_diagnostics(
    diagnostics: &ros2_client::Subscription<DiagnosticArray>,
    what: String,
    done: impl Fn(&dyn Fn(&str) -> Option<String>, &guardian_gate::msgs::DiagnosticStatus) -> bool,
) {
    let deadline = Instant::now() + PATIENCE;
    loop {
        assert!(Instant::now() < deadline, "/diagnostics never {what}");
        let (d, _) = diagnostics.async_take().await.expect("diagnostics");
        let st = &d.status[0];
        let get = |k: &str| {
            st.values
                .iter()
                .find(|v| v.key == k)
                .map(|v| v.value.clone())
        };
        if done(&get, st) {
            return;
        }
    }
}

fn node(domain: u16, name: &str) -> Node {
    let ctx = context(domain, &loopback()).expect("DDS participant");
    let mut node = ctx
        .new_node(
            NodeName::new("/", name).unwrap(),
            NodeOptions::new().enable_rosout(false),
        )
        .expect("node");
    smol::spawn(node.spinner().unwrap().spin()).detach();
    node
}

/// The joint names of the Panda's URDF and a pen joint carrying the tool channel.
fn joint_names() -> Vec<String> {
    let mut n: Vec<String> = (1..=7).map(|i| format!("panda_joint{i}")).collect();
    n.push("pen".into());
    n
}

/// A synthetic task plan as a FollowJointTrajectory goal, joints in `order`.
fn goal(class: u32, drawer: u32, order: &[usize]) -> Goal {
    let names = joint_names();
    let rows = samples::task(class, drawer);
    let points = rows
        .iter()
        .enumerate()
        .map(|(i, w)| {
            let row: Vec<f64> = (0..8)
                .map(|j| {
                    if j < 7 {
                        w[j] as f64
                    } else {
                        w[guardian_shared::trajectory::TOOL] as f64
                    }
                })
                .collect();
            JointTrajectoryPoint {
                positions: order.iter().map(|&j| row[j]).collect(),
                time_from_start: guardian_gate::msgs::Duration {
                    sec: i as i32 / 10,
                    nanosec: (i as u32 % 10) * 100_000_000,
                },
                ..Default::default()
            }
        })
        .collect();
    Goal {
        trajectory: JointTrajectory {
            joint_names: order.iter().map(|&j| names[j].clone()).collect(),
            points,
            ..Default::default()
        },
        ..Default::default()
    }
}

fn in_order() -> Vec<usize> {
    (0..8).collect()
}

/// What the controller stand-in saw.
#[derive(Default)]
struct Seen {
    goals: Mutex<Vec<Goal>>,
    cancels: AtomicUsize,
    /// Cancels that came for a goal not accepted yet (refused as unknown).
    early_cancels: AtomicUsize,
}

/// The controller stand-in: accepts every goal, sends feedback every 20 ms, succeeds after
/// 5 of them (a `LONG` goal runs until canceled; a `SLOW` one is answered late).
fn controller(
    domain: u16,
    ns: &str,
    seen: Arc<Seen>,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<()> {
    let ns = ns.to_string();
    std::thread::spawn(move || {
        smol::block_on(async move {
            let mut node = node(domain, "controller_standin");
            let server = action_server(&mut node, ServiceMapping::Enhanced, &ns).unwrap();
            while !stop.load(Ordering::Relaxed) {
                let next = server.receive_new_goal().fuse();
                let tick = FutureExt::fuse(smol::Timer::after(Duration::from_millis(100)));
                pin_mut!(next, tick);
                let handle = futures::select! {
                    h = next => h.unwrap(),
                    _ = tick => continue,
                };
                let g = server.get_new_goal(handle.clone()).unwrap();
                let slow = g.goal_time_tolerance.sec == SLOW;
                let long = g.goal_time_tolerance.sec == LONG || slow;
                seen.goals.lock().unwrap().push(g);
                // A late answer. Meanwhile a cancel is refused as for an unknown goal, as
                // ros2_control's controller refuses a cancel for a goal it does not hold.
                let until = Instant::now() + if slow { SLOW_ACCEPT } else { Duration::ZERO };
                while Instant::now() < until {
                    let cancel = server.receive_cancel_request().fuse();
                    let tick = FutureExt::fuse(smol::Timer::after(Duration::from_millis(20)));
                    pin_mut!(cancel, tick);
                    futures::select! {
                        c = cancel => {
                            seen.early_cancels.fetch_add(1, Ordering::SeqCst);
                            server.respond_to_cancel_requests(&c.unwrap(), std::iter::empty()).await.unwrap();
                        }
                        _ = tick => {}
                    }
                }
                let accepted = server.accept_goal(handle).await.unwrap();
                let executing = server.start_executing_goal(accepted).await.unwrap();
                let mut sent = 0;
                let deadline = Instant::now() + Duration::from_secs(20);
                let end = loop {
                    let cancel = server.receive_cancel_request().fuse();
                    let tick = FutureExt::fuse(smol::Timer::after(Duration::from_millis(20)));
                    pin_mut!(cancel, tick);
                    futures::select! {
                        c = cancel => {
                            let c = c.unwrap();
                            let mine = executing.goal_id();
                            if c.contains_goal(&mine) {
                                seen.cancels.fetch_add(1, Ordering::SeqCst);
                                server.respond_to_cancel_requests(&c, std::iter::once(mine)).await.unwrap();
                                break GoalEndStatus::Canceled;
                            }
                            server.respond_to_cancel_requests(&c, std::iter::empty()).await.unwrap();
                        }
                        _ = tick => {
                            server.publish_feedback(executing.clone(), Feedback {
                                joint_names: vec![format!("step {sent}")],
                                ..Default::default()
                            }).await.unwrap();
                            sent += 1;
                            if (!long && sent >= 5) || Instant::now() > deadline {
                                break GoalEndStatus::Succeeded;
                            }
                        }
                    }
                };
                let result = GoalResult {
                    error_code: error_code::SUCCESSFUL,
                    error_string: if end == GoalEndStatus::Canceled {
                        "canceled".into()
                    } else {
                        "done".into()
                    },
                };
                server
                    .send_result_response(executing, end, result)
                    .await
                    .unwrap();
            }
            drop(node);
        })
    })
}

/// The MoveIt stand-in's view of one goal.
#[derive(Debug)]
struct Sent {
    accepted: bool,
    status: Option<GoalStatusEnum>,
    result: Option<GoalResult>,
    feedback: usize,
}

async fn send(
    client: &ActionClient<Goal, GoalResult, Feedback>,
    g: Goal,
    cancel_after_feedback: bool,
) -> Sent {
    let sending = client.async_send_goal(g).fuse();
    let timeout = FutureExt::fuse(smol::Timer::after(PATIENCE));
    pin_mut!(sending, timeout);
    let (id, resp) = futures::select! {
        r = sending => r.expect("send goal"),
        _ = timeout => panic!("no answer to a goal within {PATIENCE:?}"),
    };
    if !resp.accepted {
        return Sent {
            accepted: false,
            status: None,
            result: None,
            feedback: 0,
        };
    }
    let count = std::cell::Cell::new(0usize);
    let feedback = async {
        let s = client.feedback_stream(id);
        pin_mut!(s);
        while let Some(f) = s.next().await {
            f.expect("feedback");
            count.set(count.get() + 1);
            if cancel_after_feedback && count.get() == 2 {
                let r = client
                    .async_cancel_goal(id, ros2_client::builtin_interfaces::Time::ZERO)
                    .await
                    .expect("cancel");
                assert_eq!(r.goals_canceling.len(), 1, "the gate accepted the cancel");
            }
        }
        futures::future::pending::<()>().await
    }
    .fuse();
    let result = client.async_request_result(id).fuse();
    let timeout = FutureExt::fuse(smol::Timer::after(PATIENCE));
    pin_mut!(feedback, result, timeout);
    let (status, r) = futures::select! {
        r = result => r.expect("result"),
        () = feedback => unreachable!(),
        _ = timeout => panic!("no result within {PATIENCE:?}"),
    };
    Sent {
        accepted: true,
        status: Some(status),
        result: Some(r),
        feedback: count.get(),
    }
}

/// `f`'s output, or a panic after [`PATIENCE`] (the gate stalled).
async fn within<T>(f: impl std::future::Future<Output = T>, what: &str) -> T {
    smol::future::or(async { Some(f.await) }, async {
        smol::Timer::after(PATIENCE).await;
        None
    })
    .await
    .unwrap_or_else(|| panic!("{what} not within {PATIENCE:?} (the gate stalled?)"))
}

fn latched() -> QosProfile {
    QosProfile::publisher_default()
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

fn reliable(depth: usize) -> QosProfile {
    QosProfile::publisher_default().history(History::KeepLast { depth })
}

#[test]
fn gate_screens_forwards_relays_and_fails_closed() {
    // guardiand on the shipped model, two enrolled tasks.
    let mut s = Setup::new(40);
    s.model = workspace_root().join("models/embedder.safetensors");
    let mut daemon = Daemon::start(&s);
    let direct = s.client();
    for (name, class) in [("task-a", 0u32), ("task-b", 1)] {
        let examples: Vec<Trajectory> = (0..5)
            .map(|d| Trajectory::from_waypoints(&samples::task(class, d), 7))
            .collect();
        direct.enroll(name, &examples).expect("enroll");
    }
    let plan = |c: u32, d: u32| Trajectory::from_waypoints(&samples::task(c, d), 7);
    // Preconditions on guardiand itself, so a failure below is the gate's.
    assert_eq!(
        direct.check(&plan(0, 7), "task-a").unwrap().decision,
        Decision::Go
    );
    assert!(!direct.check(&plan(1, 7), "task-a").unwrap().is_go());
    let outlier_class = (4..12)
        .find(|&c| {
            let r = direct.identify(&plan(c, 7)).unwrap();
            r.nearest[0].distance > r.nearest[0].threshold
        })
        .expect("some never-enrolled task is an outlier for guardiand");

    // The gate.
    let domain = 100 + (std::process::id() % 100) as u16;
    // The controller on a domain of its own, which only the gate bridges.
    let ctrl_domain = domain + 30;
    let gate_ns = format!("/gate_t{}", std::process::id());
    let ctrl_ns = format!("/ctrl_t{}", std::process::id());
    let config = s.dir.path().join("gate.toml");
    std::fs::write(
        &config,
        format!(
            "gate = {gate_ns:?}\ncontroller = {ctrl_ns:?}\ndomain-id = {domain}\ncontroller-domain-id = {ctrl_domain}\nonly-networks = [\"127.0.0.1\"]\ncontroller-timeout-ms = 5000\nclaim-from = [\"/moveit_standin\"]\n\
             [tool]\nsource = \"joint\"\njoint = \"pen\"\n\
             [guardiand]\nservice-name = {:?}\ntimeout-ms = 1000\niceoryx2-root-path = {:?}\niceoryx2-prefix = {:?}\n",
            s.service,
            s.dir.path().join("iox"),
            s.prefix
        ),
    )
    .unwrap();
    struct Kill(std::process::Child);
    impl Drop for Kill {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let _gate = Kill(
        std::process::Command::new(env!("CARGO_BIN_EXE_guardian-gate"))
            .arg("--config")
            .arg(&config)
            .env("RUST_LOG", "warn")
            .spawn()
            .expect("start guardian-gate"),
    );

    let seen = Arc::new(Seen::default());
    let stop = Arc::new(AtomicBool::new(false));
    let ctrl = controller(ctrl_domain, &ctrl_ns, seen.clone(), stop.clone());

    smol::block_on(async {
        let mut moveit = node(domain, "moveit_standin");
        let client = action_client(&mut moveit, ServiceMapping::Enhanced, &gate_ns).unwrap();
        let task_topic = moveit
            .create_topic(
                &Name::new(&gate_ns, "task").unwrap(),
                MessageTypeName::new("std_msgs", "String"),
                &latched(),
            )
            .unwrap();
        let task = moveit
            .create_publisher::<StringMsg>(&task_topic, Some(latched()))
            .unwrap();
        let verdict_topic = moveit
            .create_topic(
                &Name::new(&gate_ns, "verdicts").unwrap(),
                MessageTypeName::new("guardian_msgs", "Verdict"),
                &reliable(10),
            )
            .unwrap();
        let verdicts = moveit
            .create_subscription::<Verdict>(&verdict_topic, Some(reliable(100)))
            .unwrap();
        let diag_topic = moveit
            .create_topic(
                &Name::new("/", "diagnostics").unwrap(),
                MessageTypeName::new("diagnostic_msgs", "DiagnosticArray"),
                &reliable(10),
            )
            .unwrap();
        let diagnostics = moveit
            .create_subscription::<DiagnosticArray>(&diag_topic, Some(reliable(10)))
            .unwrap();

        // Discovery, bounded.
        let ready = async {
            client.goal_client().wait_for_service(&moveit).await;
            verdicts.wait_for_publisher(&moveit).await;
        };
        let t = smol::Timer::after(PATIENCE);
        assert!(
            smol::future::or(
                async {
                    ready.await;
                    true
                },
                async {
                    t.await;
                    false
                }
            )
            .await,
            "the gate was not discovered within {PATIENCE:?}"
        );

        // The claim reaches the gate: /diagnostics (1 Hz) reports it.
        let claim = |c: &str| {
            task.publish(StringMsg { data: c.into() }).unwrap();
        };
        let wait_claim = |want: &'static str| {
            wait_diagnostics(
                &diagnostics,
                format!("reported the claim {want:?}"),
                move |get, st| {
                    assert_eq!(
                        get("guardiand reachable").as_deref(),
                        Some("true"),
                        "{st:?}"
                    );
                    assert_eq!(get("bank size").as_deref(), Some("2"), "{st:?}");
                    let claimed = get("claimed task").as_deref() == Some(want);
                    if claimed {
                        // Identify mode says what it lets through.
                        let mode = get("mode").unwrap_or_default();
                        assert_eq!(mode.starts_with("identify"), want.is_empty(), "{st:?}");
                    }
                    claimed
                },
            )
        };
        let next_verdict = || async {
            let t = smol::Timer::after(PATIENCE);
            let v = async { verdicts.async_take().await.expect("verdict").0 };
            smol::future::or(async { Some(v.await) }, async {
                t.await;
                None
            })
            .await
            .expect("a verdict within PATIENCE")
        };

        claim("task-a");
        wait_claim("task-a").await;

        // 0. The controller is on a domain only the gate bridges: from MoveIt's domain it is
        // not there (a direct goal has nowhere to go), while the gate reaches it (1.).
        let direct = action_client(&mut moveit, ServiceMapping::Enhanced, &ctrl_ns).unwrap();
        let found = smol::future::or(
            async {
                direct.goal_client().wait_for_service(&moveit).await;
                true
            },
            async {
                smol::Timer::after(Duration::from_secs(3)).await;
                false
            },
        )
        .await;
        assert!(
            !found,
            "the controller is reachable from MoveIt's domain, around the gate"
        );
        drop(direct);

        // 0b. Only the node of claim-from may claim: another participant's claims, of another
        // task and of identify mode, are refused (counted in /diagnostics) and change nothing;
        // the intruder stays on the domain, its latched claim with it, through 1-3.
        let mut intruder = node(domain, "intruder");
        let intruder_topic = intruder
            .create_topic(
                &Name::new(&gate_ns, "task").unwrap(),
                MessageTypeName::new("std_msgs", "String"),
                &latched(),
            )
            .unwrap();
        let intruder_task = intruder
            .create_publisher::<StringMsg>(&intruder_topic, Some(latched()))
            .unwrap();
        let wait_refused = |want: u64| {
            wait_diagnostics(
                &diagnostics,
                format!("counted {want} refused claims"),
                move |get, st| {
                    assert_eq!(get("claimed task").as_deref(), Some("task-a"), "{st:?}");
                    get("claims refused").unwrap().parse::<u64>().unwrap() >= want
                },
            )
        };
        for (i, other) in ["task-b", ""].into_iter().enumerate() {
            intruder_task
                .publish(StringMsg { data: other.into() })
                .unwrap();
            wait_refused(i as u64 + 1).await;
        }

        // 1. A genuine plan is forwarded; feedback and result are relayed.
        let r = send(&client, goal(0, 7, &in_order()), false).await;
        assert!(r.accepted, "{r:?}");
        assert_eq!(r.status, Some(GoalStatusEnum::Succeeded), "{r:?}");
        assert_eq!(r.result.as_ref().unwrap().error_string, "done");
        assert!(r.feedback >= 1, "feedback relayed: {r:?}");
        assert_eq!(seen.goals.lock().unwrap().len(), 1);
        assert_eq!(
            seen.goals.lock().unwrap()[0],
            goal(0, 7, &in_order()),
            "forwarded unchanged"
        );
        let v = next_verdict().await;
        assert_eq!(
            (
                v.verdict.as_str(),
                v.reason.as_str(),
                v.claimed_task.as_str()
            ),
            ("go", "genuine", "task-a"),
            "{v:?}"
        );
        assert!(v.distance <= v.threshold, "{v:?}");
        assert_eq!(v.waypoints as usize, samples::task(0, 7).len());
        let genuine_sha = v.trajectory_sha256.clone();

        // 2. Shuffled joint order: the same plan, the same verdict.
        let shuffled = [5, 2, 7, 0, 6, 3, 1, 4];
        let r = send(&client, goal(0, 7, &shuffled), false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Succeeded), "{r:?}");
        let v = next_verdict().await;
        assert_eq!(v.verdict, "go", "{v:?}");
        assert_eq!(v.trajectory_sha256, genuine_sha);
        assert_eq!(seen.goals.lock().unwrap().len(), 2);

        // 3. A wrong-task plan is refused with its reason; the controller never sees it.
        let r = send(&client, goal(1, 7, &in_order()), false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Aborted), "{r:?}");
        let res = r.result.unwrap();
        assert_eq!(res.error_code, error_code::INVALID_GOAL);
        for part in ["wrong task", "task-b", "task-a", "distance", "threshold"] {
            assert!(
                res.error_string.contains(part),
                "{part:?} in {:?}",
                res.error_string
            );
        }
        assert_eq!(
            seen.goals.lock().unwrap().len(),
            2,
            "the controller saw the wrong-task plan"
        );
        let v = next_verdict().await;
        assert_eq!(
            (
                v.verdict.as_str(),
                v.reason.as_str(),
                v.nearest_class.as_str()
            ),
            ("no-go", "wrong-task", "task-b"),
            "{v:?}"
        );
        assert!(v.distance > v.threshold, "{v:?}");
        drop(intruder_task);
        drop(intruder);

        // 4. An unknown joint: INVALID_JOINTS, not forwarded.
        let mut g = goal(0, 7, &in_order());
        g.trajectory.joint_names[2] = "elbow_joint".into();
        let r = send(&client, g, false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Aborted), "{r:?}");
        let res = r.result.unwrap();
        assert_eq!(res.error_code, error_code::INVALID_JOINTS, "{res:?}");
        assert!(res.error_string.contains("elbow_joint"), "{res:?}");
        assert_eq!(next_verdict().await.reason, "invalid-joints");
        assert_eq!(seen.goals.lock().unwrap().len(), 2);

        // 5. A cancel during execution is relayed to the controller and back.
        let mut g = goal(0, 7, &in_order());
        g.goal_time_tolerance.sec = LONG;
        let r = send(&client, g, true).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Canceled), "{r:?}");
        assert_eq!(r.result.unwrap().error_string, "canceled");
        assert_eq!(seen.cancels.load(Ordering::SeqCst), 1);
        assert_eq!(seen.goals.lock().unwrap().len(), 3);
        assert_eq!(next_verdict().await.verdict, "go");

        // 5b. The controller answers only after the gate's timeout: MoveIt hears aborted, and
        // the goal, which the controller accepts late, is cancelled there (a first cancel is
        // refused as unknown, the one after the late acceptance lands).
        let mut g = goal(0, 7, &in_order());
        g.goal_time_tolerance.sec = SLOW;
        let r = send(&client, g, false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Aborted), "{r:?}");
        let res = r.result.unwrap();
        assert_eq!(res.error_code, error_code::INVALID_GOAL);
        assert!(res.error_string.contains("did not answer"), "{res:?}");
        let screened = next_verdict().await;
        assert_eq!(screened.verdict, "go");
        // The verdicts topic then says the goal was not executed: an error for the same goal.
        let failed = next_verdict().await;
        assert_eq!(
            (
                failed.verdict.as_str(),
                failed.reason.as_str(),
                failed.goal_id.as_str()
            ),
            ("error", "controller-timeout", screened.goal_id.as_str()),
            "{failed:?}"
        );
        let deadline = Instant::now() + PATIENCE;
        while seen.cancels.load(Ordering::SeqCst) < 2 {
            assert!(
                Instant::now() < deadline,
                "the late goal was not cancelled at the controller"
            );
            smol::Timer::after(Duration::from_millis(20)).await;
        }
        assert!(seen.early_cancels.load(Ordering::SeqCst) >= 1);
        assert_eq!(seen.goals.lock().unwrap().len(), 4);

        // 6. Identify mode (no claim): an outlier is refused, a genuine plan goes.
        claim("");
        wait_claim("").await;
        let r = send(&client, goal(outlier_class, 7, &in_order()), false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Aborted), "{r:?}");
        let res = r.result.unwrap();
        assert_eq!(res.error_code, error_code::INVALID_GOAL);
        assert!(res.error_string.contains("outlier"), "{res:?}");
        let v = next_verdict().await;
        assert_eq!(
            (
                v.verdict.as_str(),
                v.reason.as_str(),
                v.claimed_task.as_str()
            ),
            ("no-go", "outlier", ""),
            "{v:?}"
        );
        assert_eq!(seen.goals.lock().unwrap().len(), 4);
        let r = send(&client, goal(1, 8, &in_order()), false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Succeeded), "{r:?}");
        let v = next_verdict().await;
        assert_eq!(
            (v.verdict.as_str(), v.nearest_class.as_str()),
            ("go", "task-b"),
            "{v:?}"
        );
        assert_eq!(seen.goals.lock().unwrap().len(), 5);

        // 6b. A sender that never asks for its result, and one that leaves after its goal is
        // answered, stall nothing: the next goal is screened and relayed, and the first
        // one's result is still there when it is asked for later.
        let (silent, resp) = within(
            client.async_send_goal(goal(outlier_class, 7, &in_order())),
            "a goal's answer",
        )
        .await
        .expect("send goal");
        assert!(resp.accepted);
        assert_eq!(next_verdict().await.verdict, "no-go");
        {
            let mut gone = node(domain, "vanishing_sender");
            let vanishing = action_client(&mut gone, ServiceMapping::Enhanced, &gate_ns).unwrap();
            let found = smol::future::or(
                async {
                    vanishing.goal_client().wait_for_service(&gone).await;
                    true
                },
                async {
                    smol::Timer::after(PATIENCE).await;
                    false
                },
            )
            .await;
            assert!(found, "the second sender did not discover the gate");
            let (_, resp) = within(
                vanishing.async_send_goal(goal(outlier_class, 8, &in_order())),
                "the second sender's goal's answer",
            )
            .await
            .expect("send goal");
            assert!(resp.accepted);
            assert_eq!(next_verdict().await.verdict, "no-go");
        }
        let gone_at = Instant::now();
        let sending = send(&client, goal(1, 8, &in_order()), false);
        let screened = async {
            let v = next_verdict().await;
            (v, gone_at.elapsed())
        };
        let (r, (v, after)) = futures::join!(sending, screened);
        eprintln!(
            "6b: next goal screened {after:?} after the second sender left (the first never asked for its result)"
        );
        assert_eq!(r.status, Some(GoalStatusEnum::Succeeded), "{r:?}");
        assert_eq!(v.verdict, "go", "{v:?}");
        assert_eq!(seen.goals.lock().unwrap().len(), 6);
        let kept = smol::future::or(
            async { Some(client.async_request_result(silent).await.expect("result")) },
            async {
                smol::Timer::after(PATIENCE).await;
                None
            },
        )
        .await;
        let (status, res) = kept.expect("the silent sender's result was kept");
        assert_eq!(status, GoalStatusEnum::Aborted);
        assert!(res.error_string.contains("outlier"), "{res:?}");

        // 7. guardiand killed: the goal is refused, never forwarded.
        daemon.child.kill().unwrap();
        daemon.child.wait().unwrap();
        claim("task-a");
        let r = send(&client, goal(0, 7, &in_order()), false).await;
        assert_eq!(r.status, Some(GoalStatusEnum::Aborted), "{r:?}");
        let res = r.result.unwrap();
        assert_eq!(res.error_code, error_code::INVALID_GOAL);
        assert!(res.error_string.contains("fail closed"), "{res:?}");
        assert_eq!(
            seen.goals.lock().unwrap().len(),
            6,
            "a goal was forwarded without a verdict"
        );
        let v = next_verdict().await;
        assert_eq!(v.verdict, "error", "{v:?}");
        drop(moveit);
    });
    stop.store(true, Ordering::Relaxed);
    ctrl.join().unwrap();
}
