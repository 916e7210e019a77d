//! `guardianctl enroll --bag` and `check --bag` on an MCAP file written by the `mcap`
//! crate's writer with CDR-encoded `trajectory_msgs/msg/JointTrajectory` messages, against
//! a real guardiand.

use std::path::Path;
use std::process::Command;

use guardian_client::samples;
use guardian_gate::bag::write_bag;
use guardian_gate::cdr;
use guardian_gate::msgs::{JointTrajectory, JointTrajectoryPoint, StringMsg};
use guardian_tests::harness::{Daemon, Setup, ctl_bin};

/// Synthetic task `class`, drawer `drawer` as a JointTrajectory with a pen joint.
fn trajectory(class: u32, drawer: u32) -> JointTrajectory {
    let mut joint_names: Vec<String> = (1..=7).map(|i| format!("panda_joint{i}")).collect();
    joint_names.insert(3, "pen".into());
    JointTrajectory {
        joint_names,
        points: samples::task(class, drawer)
            .iter()
            .map(|w| {
                let mut positions: Vec<f64> = w[..7].iter().map(|&v| v as f64).collect();
                positions.insert(3, w[guardian_shared::trajectory::TOOL] as f64);
                JointTrajectoryPoint {
                    positions,
                    ..Default::default()
                }
            })
            .collect(),
        ..Default::default()
    }
}

const JT: &str = "trajectory_msgs/msg/JointTrajectory";

#[test]
fn enroll_and_check_from_a_recording() {
    let mut s = Setup::new(41);
    s.model = guardian_tests::harness::workspace_root().join("models/embedder.safetensors");
    let admin = s.dir.path().join("admin.sock");
    s.extra = format!("[admin]\nsocket = {admin:?}\n");
    let _d = Daemon::start(&s);

    let enroll_bag = s.dir.path().join("enroll.mcap");
    let mut messages: Vec<(&str, &str, Vec<u8>)> = (0..5)
        .map(|d| ("/plans", JT, cdr::encode(&trajectory(0, d)).unwrap()))
        .collect();
    messages.push((
        "/chatter",
        "std_msgs/msg/String",
        cdr::encode(&StringMsg {
            data: "hello".into(),
        })
        .unwrap(),
    ));
    write_bag(&enroll_bag, &messages).unwrap();
    let check_bag = s.dir.path().join("check.mcap");
    write_bag(
        &check_bag,
        &[
            ("/executed", JT, cdr::encode(&trajectory(0, 7)).unwrap()),
            ("/executed", JT, cdr::encode(&trajectory(0, 8)).unwrap()),
            ("/other", JT, cdr::encode(&trajectory(1, 7)).unwrap()),
        ],
    )
    .unwrap();

    let ctl = |args: &[&str]| {
        let out = Command::new(ctl_bin())
            .args(["--service", &s.service, "--iceoryx2-prefix", &s.prefix])
            .arg("--iceoryx2-root-path")
            .arg(s.dir.path().join("iox"))
            .arg("--admin-socket")
            .arg(&admin)
            .args(args)
            .output()
            .expect("run guardianctl");
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let bag = |p: &Path| p.to_string_lossy().into_owned();

    // Enroll: each message one example.
    let (code, out, err) = ctl(&[
        "enroll",
        "task-a",
        "--bag",
        &bag(&enroll_bag),
        "--topic",
        "/plans",
        "--tool-joint",
        "pen",
    ]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("enrolled task-a: 5 examples"), "{out}");

    // The class then serves checks of recorded plans.
    let (code, out, err) = ctl(&[
        "check",
        "--class",
        "task-a",
        "--bag",
        &bag(&check_bag),
        "--topic",
        "/executed",
        "--tool-joint",
        "pen",
    ]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("2/2 go"), "{out}");
    let (code, out, err) = ctl(&[
        "check",
        "--class",
        "task-a",
        "--bag",
        &bag(&check_bag),
        "--topic",
        "/other",
        "--tool-joint",
        "pen",
    ]);
    assert_eq!(code, Some(1), "{out}{err}");
    assert!(out.contains("NO-GO") && out.contains("0/1 go"), "{out}");

    // Clear errors: no such topic, wrong type, joints that are not the robot's.
    let (code, _, err) = ctl(&[
        "check",
        "--class",
        "task-a",
        "--bag",
        &bag(&enroll_bag),
        "--topic",
        "/missing",
    ]);
    assert_eq!(code, Some(1));
    assert!(
        err.contains("no messages on topic \"/missing\"")
            && err.contains("/plans (trajectory_msgs/msg/JointTrajectory)"),
        "{err}"
    );
    let (code, _, err) = ctl(&[
        "enroll",
        "task-x",
        "--bag",
        &bag(&enroll_bag),
        "--topic",
        "/chatter",
    ]);
    assert_eq!(code, Some(1));
    assert!(err.contains("has type \"std_msgs/msg/String\""), "{err}");
    let (code, _, err) = ctl(&[
        "check",
        "--class",
        "task-a",
        "--bag",
        &bag(&check_bag),
        "--topic",
        "/executed",
    ]);
    assert_eq!(code, Some(1));
    assert!(err.contains("unknown joint \"pen\""), "{err}");
}
