//! The gate's added latency: goal sent → goal arrives at the controller, through the gate
//! (screened by a real guardiand) and directly, interleaved in one run over DDS on
//! loopback. Prints p50 / p99 of both and of the difference.
//! Run: cargo bench -p guardian-gate --bench latency [-- GOALS]   (default 200 of each)

use std::sync::mpsc;
use std::time::{Duration, Instant};

use futures::{FutureExt, pin_mut};
use guardian_client::{Trajectory, samples};
use guardian_gate::msgs::{
    FollowJointTrajectoryFeedback as Feedback, FollowJointTrajectoryGoal as Goal,
    FollowJointTrajectoryResult as GoalResult, JointTrajectory, JointTrajectoryPoint,
};
use guardian_gate::node::{Controller, action_client, action_server, context};
use guardian_tests::harness::{Daemon, Setup, machine_line, workspace_root};
use ros2_client::action::{ActionClient, GoalEndStatus};
use ros2_client::{Node, NodeName, NodeOptions, ServiceMapping};

fn node(domain: u16, name: &str) -> Node {
    let ctx = context(domain, &["127.0.0.1".parse().unwrap()]).expect("DDS participant");
    let mut node = ctx
        .new_node(
            NodeName::new("/", name).unwrap(),
            NodeOptions::new().enable_rosout(false),
        )
        .expect("node");
    smol::spawn(node.spinner().unwrap().spin()).detach();
    node
}

fn goal() -> Goal {
    let mut joint_names: Vec<String> = (1..=7).map(|i| format!("panda_joint{i}")).collect();
    joint_names.push("pen".into());
    Goal {
        trajectory: JointTrajectory {
            joint_names,
            points: samples::task(0, 7)
                .iter()
                .map(|w| JointTrajectoryPoint {
                    positions: w[..7]
                        .iter()
                        .chain([&w[guardian_shared::trajectory::TOOL]])
                        .map(|&v| v as f64)
                        .collect(),
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        },
        ..Default::default()
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let goals: usize = std::env::args()
        .filter_map(|a| a.parse().ok())
        .next()
        .unwrap_or(200);
    let mut s = Setup::new(42);
    s.model = workspace_root().join("models/embedder.safetensors");
    let _daemon = Daemon::start(&s);
    let direct = s.client();
    let examples: Vec<Trajectory> = (0..5)
        .map(|d| Trajectory::from_waypoints(&samples::task(0, d), 7))
        .collect();
    direct.enroll("task-a", &examples).expect("enroll");

    let domain = 150 + (std::process::id() % 50) as u16;
    let gate_ns = format!("/bench_gate{}", std::process::id());
    let ctrl_ns = format!("/bench_ctrl{}", std::process::id());
    let config = s.dir.path().join("gate.toml");
    std::fs::write(
        &config,
        format!(
            "gate = {gate_ns:?}\ncontroller = {ctrl_ns:?}\ndomain-id = {domain}\nonly-networks = [\"127.0.0.1\"]\n\
             [tool]\nsource = \"joint\"\njoint = \"pen\"\n\
             [guardiand]\nservice-name = {:?}\niceoryx2-root-path = {:?}\niceoryx2-prefix = {:?}\n",
            s.service,
            s.dir.path().join("iox"),
            s.prefix
        ),
    )
    .unwrap();
    let exe = std::env::current_exe().unwrap();
    let gate_bin = exe
        .parent()
        .unwrap()
        .parent()
        .unwrap()
        .join("guardian-gate");
    let mut gate = std::process::Command::new(&gate_bin)
        .arg("--config")
        .arg(&config)
        .env("RUST_LOG", "warn")
        .spawn()
        .unwrap_or_else(|e| {
            panic!(
                "{}: {e} (cargo build -p guardian-gate first)",
                gate_bin.display()
            )
        });

    // The controller stand-in: reports each goal's arrival time, succeeds at once.
    let (arrivals, arrived) = mpsc::channel::<Instant>();
    let ctrl_ns2 = ctrl_ns.clone();
    std::thread::spawn(move || {
        smol::block_on(async move {
            let mut node = node(domain, "bench_controller");
            let server = action_server(&mut node, ServiceMapping::Enhanced, &ctrl_ns2).unwrap();
            loop {
                let h = server.receive_new_goal().await.unwrap();
                let _ = arrivals.send(Instant::now());
                let a = server.accept_goal(h).await.unwrap();
                let x = server.start_executing_goal(a).await.unwrap();
                server
                    .send_result_response(x, GoalEndStatus::Succeeded, GoalResult::default())
                    .await
                    .unwrap();
            }
        })
    });

    let (through_gate, straight) = smol::block_on(async {
        let mut moveit = node(domain, "bench_moveit");
        let client = |ns: &str, moveit: &mut Node| -> Controller {
            action_client(moveit, ServiceMapping::Enhanced, ns).unwrap()
        };
        let via_gate = client(&gate_ns, &mut moveit);
        let to_ctrl = client(&ctrl_ns, &mut moveit);
        let wait = async {
            via_gate.goal_client().wait_for_service(&moveit).await;
            to_ctrl.goal_client().wait_for_service(&moveit).await;
        };
        let t = smol::Timer::after(Duration::from_secs(60));
        assert!(
            smol::future::or(
                async {
                    wait.await;
                    true
                },
                async {
                    t.await;
                    false
                }
            )
            .await,
            "discovery took over 60 s"
        );
        // Warm-up, then interleaved measurements.
        for _ in 0..10 {
            one(&via_gate, &arrived).await;
            one(&to_ctrl, &arrived).await;
        }
        let mut through_gate = Vec::with_capacity(goals);
        let mut straight = Vec::with_capacity(goals);
        for _ in 0..goals {
            through_gate.push(one(&via_gate, &arrived).await);
            straight.push(one(&to_ctrl, &arrived).await);
        }
        drop(moveit);
        (through_gate, straight)
    });
    let _ = gate.kill();
    let _ = gate.wait();
    let added: Vec<f64> = through_gate
        .iter()
        .zip(&straight)
        .map(|(g, d)| g - d)
        .collect();
    println!("{}", machine_line());
    println!(
        "goal sent -> goal at the controller, {goals} goals each, interleaved, DDS on loopback (us)"
    );
    println!("{:<28} {:>10} {:>10} {:>10}", "", "p50", "p99", "max");
    for (name, mut v) in [
        ("through the gate", through_gate),
        ("direct", straight),
        ("added (pairwise)", added),
    ] {
        v.sort_by(f64::total_cmp);
        println!(
            "{name:<28} {:>10.0} {:>10.0} {:>10.0}",
            percentile(&v, 0.5),
            percentile(&v, 0.99),
            v[v.len() - 1]
        );
    }
}

/// One goal: its time from sending to its arrival at the controller (us), after its result.
async fn one(
    c: &ActionClient<Goal, GoalResult, Feedback>,
    arrived: &mpsc::Receiver<Instant>,
) -> f64 {
    let t0 = Instant::now();
    let sending = c.async_send_goal(goal()).fuse();
    let timeout = FutureExt::fuse(smol::Timer::after(Duration::from_secs(30)));
    pin_mut!(sending, timeout);
    let (id, resp) = futures::select! {
        r = sending => r.expect("send goal"),
        _ = timeout => panic!("no answer within 30 s"),
    };
    assert!(resp.accepted, "goal refused");
    c.async_request_result(id).await.expect("result");
    let at = arrived
        .recv_timeout(Duration::from_secs(5))
        .expect("arrival");
    (at - t0).as_secs_f64() * 1e6
}
