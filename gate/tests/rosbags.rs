//! A rosbag2 MCAP bag written by the Python `rosbags` package (an independent writer of
//! rosbag2 MCAP with ROS 2 CDR) is enrolled by `guardianctl enroll --bag`, and the class
//! then serves checks. Needs a Python with rosbags: run by `gate/tests/rosbags/run.sh`
//! (which `.ci/run` calls), which sets `GUARDIAN_ROSBAGS_PYTHON`.

use std::io::Write;
use std::process::Command;

use guardian_client::{Decision, Trajectory, samples};
use guardian_tests::harness::{Daemon, Setup, ctl_bin, workspace_root};

#[test]
#[ignore = "needs Python with rosbags: gate/tests/rosbags/run.sh"]
fn a_bag_written_by_rosbags_is_enrolled_and_serves_checks() {
    let python = std::env::var("GUARDIAN_ROSBAGS_PYTHON")
        .expect("GUARDIAN_ROSBAGS_PYTHON: a Python with rosbags (gate/tests/rosbags/run.sh)");
    let mut s = Setup::new(43);
    s.model = workspace_root().join("models/embedder.safetensors");
    let admin = s.dir.path().join("admin.sock");
    s.extra = format!("[admin]\nsocket = {admin:?}\n");
    let _d = Daemon::start(&s);

    // Five drawers of synthetic task 0, joints in a shuffled order with a pen joint.
    let csv = s.dir.path().join("plans.csv");
    let mut f = std::fs::File::create(&csv).unwrap();
    let order = [6usize, 0, 7, 3, 1, 5, 2, 4];
    for d in 0..5u32 {
        for w in samples::task(0, d) {
            let cols: Vec<String> = order
                .iter()
                .map(|&j| match j {
                    7 => format!("pen={}", w[guardian_shared::trajectory::TOOL]),
                    j => format!("panda_joint{}={}", j + 1, w[j]),
                })
                .collect();
            writeln!(f, "p{d},{}", cols.join(",")).unwrap();
        }
    }
    drop(f);
    let out = s.dir.path().join("recorded");
    let script = workspace_root().join("gate/tests/rosbags/write_bag.py");
    let st = Command::new(&python)
        .arg(&script)
        .arg(&csv)
        .arg(&out)
        .arg("/planned_trajectory")
        .status()
        .expect("run the rosbags writer");
    assert!(st.success(), "the rosbags writer failed");
    let bag = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "mcap"))
        .expect("rosbags wrote an .mcap file");

    let o = Command::new(ctl_bin())
        .arg("--admin-socket")
        .arg(&admin)
        .args(["enroll", "task-a", "--bag"])
        .arg(&bag)
        .args(["--topic", "/planned_trajectory", "--tool-joint", "pen"])
        .output()
        .expect("run guardianctl");
    let text =
        String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{text}");
    assert!(text.contains("enrolled task-a: 5 examples"), "{text}");

    // The class serves checks: an unseen drawer goes, another task does not.
    let c = s.client();
    let plan = |class, drawer| Trajectory::from_waypoints(&samples::task(class, drawer), 7);
    assert_eq!(
        c.check(&plan(0, 7), "task-a").unwrap().decision,
        Decision::Go
    );
    assert!(!c.check(&plan(1, 7), "task-a").unwrap().is_go());
}
