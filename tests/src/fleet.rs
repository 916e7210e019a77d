//! Fleet test support: members with their own state, iceoryx2 root and Zenoh port on
//! loopback, keys made by `guardiand --fleet-keygen`, and waits for convergence. Used by
//! `tests/fleet.rs` and `benches/fleet.rs`.

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use guardian_client::remote::{RemoteClient, RemoteConfig};
use guardian_client::{AdminClient, ClassInfo, Client, Trajectory};

use crate::harness::{self, Daemon, Setup, traj};

/// Functional bound for replication (not a performance claim).
pub const CONVERGE: Duration = Duration::from_secs(30);
/// All members serve the same random model, so their records are mutually applicable.
pub const MODEL_SEED: u64 = 11;

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port()
}

/// `guardiand --fleet-keygen <path>`: the public key it prints.
pub fn keygen(path: &std::path::Path) -> String {
    let out = Command::new(harness::bin())
        .arg("--fleet-keygen")
        .arg(path)
        .output()
        .expect("run guardiand --fleet-keygen");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let public = String::from_utf8(out.stdout)
        .expect("utf-8")
        .trim()
        .to_owned();
    assert_eq!(public.len(), 64, "{public}");
    public
}

/// One member. Fields drop in order: the daemon stops before its directories go.
pub struct Member {
    pub daemon: Option<Daemon>,
    pub name: String,
    pub setup: Setup,
    pub port: u16,
    pub key: PathBuf,
    pub public: String,
}

pub struct Fleet {
    pub name: String,
    pub members: Vec<Member>,
    pub caller_key: PathBuf,
    pub keys: tempfile::TempDir,
}

impl Fleet {
    pub fn new(n: usize) -> Self {
        let keys = tempfile::tempdir().expect("tempdir");
        let caller_key = keys.path().join("caller.key");
        let caller_public = keygen(&caller_key);
        let mut members: Vec<Member> = (0..n)
            .map(|i| {
                let name = ["a", "b", "c"][i].to_owned();
                let key = keys.path().join(format!("{name}.key"));
                let public = keygen(&key);
                Member {
                    name,
                    setup: Setup::new(MODEL_SEED),
                    port: free_port(),
                    key,
                    public,
                    daemon: None,
                }
            })
            .collect();
        let fleet = format!("t{}x{}", std::process::id(), free_port());
        let publics: Vec<String> = members.iter().map(|m| format!("{:?}", m.public)).collect();
        let ports: Vec<u16> = members.iter().map(|m| m.port).collect();
        for m in &mut members {
            let connect: Vec<String> = ports
                .iter()
                .filter(|&&p| p != m.port)
                .map(|p| format!("\"tcp/127.0.0.1:{p}\""))
                .collect();
            m.setup.extra = format!(
                "[fleet]\nname = {fleet:?}\nmember = {:?}\nlisten = [\"tcp/127.0.0.1:{}\"]\nconnect = [{}]\nsigning-key = {:?}\nadmin-keys = [{}]\ncaller-keys = [{caller_public:?}]\nresync-ms = 500\n",
                m.name,
                m.port,
                connect.join(", "),
                m.key,
                publics.join(", ")
            );
        }
        Self {
            name: fleet,
            members,
            caller_key,
            keys,
        }
    }

    pub fn start(&mut self, i: usize) {
        self.start_with_env(i, &[]);
    }

    /// Start member `i` with extra environment variables (a fault point, a log filter).
    pub fn start_with_env(&mut self, i: usize, env: &[(&str, String)]) {
        let m = &mut self.members[i];
        let d = Daemon::start_with_env(&m.setup, env);
        d.wait_log("fleet member ready");
        m.daemon = Some(d);
    }

    /// Stop member `i` gracefully (SIGTERM, as its drop does).
    pub fn stop(&mut self, i: usize) {
        self.members[i].daemon = None;
    }

    /// Every running member's fleet position and bank digest, in member order.
    pub fn positions(
        &self,
        running: &[usize],
    ) -> Vec<(Vec<guardian_client::FleetPosition>, Option<String>)> {
        running
            .iter()
            .map(|&i| {
                let s = self.client(i).status().expect("status");
                (s.fleet, s.bank_digest)
            })
            .collect()
    }

    pub fn admin(&self, i: usize) -> AdminClient {
        AdminClient::new(
            self.members[i].setup.state_dir().join("admin.sock"),
            Duration::from_secs(20),
        )
    }

    pub fn client(&self, i: usize) -> Client {
        self.members[i].setup.client()
    }

    pub fn log(&self, i: usize) -> String {
        self.members[i]
            .daemon
            .as_ref()
            .map(Daemon::log)
            .unwrap_or_default()
    }

    pub fn remote(&self, i: usize, caller_key: PathBuf) -> RemoteClient {
        let m = &self.members[i];
        RemoteClient::connect(RemoteConfig {
            connect: vec![format!("tcp/127.0.0.1:{}", m.port)],
            fleet: self.name.clone(),
            member: m.name.clone(),
            caller_key,
            member_key: m.public.clone(),
            timeout: Duration::from_secs(10),
        })
        .expect("remote connect")
    }

    /// Every running member's classes, in member order.
    pub fn banks(&self, running: &[usize]) -> Vec<Vec<ClassInfo>> {
        running
            .iter()
            .map(|&i| self.client(i).classes().expect("classes"))
            .collect()
    }

    /// Wait until every member in `running` holds the same classes and passes `ok`.
    pub fn converge(&self, running: &[usize], ok: impl Fn(&[ClassInfo]) -> bool) -> Vec<ClassInfo> {
        let start = Instant::now();
        loop {
            let banks = self.banks(running);
            if banks.windows(2).all(|w| w[0] == w[1]) && ok(&banks[0]) {
                return banks[0].clone();
            }
            if start.elapsed() > CONVERGE {
                let logs: Vec<String> = running.iter().map(|&i| self.log(i)).collect();
                panic!(
                    "no convergence: {banks:#?}\nlogs:\n{}",
                    logs.join("\n-----\n")
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

pub fn has(classes: &[ClassInfo], name: &str, examples: u32) -> bool {
    classes
        .iter()
        .any(|c| c.name == name && c.examples == examples)
}

pub fn examples(class: u32, drawers: std::ops::Range<u32>) -> Vec<Trajectory> {
    drawers.map(|d| traj(class, d)).collect()
}
