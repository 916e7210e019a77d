//! The `[fleet]` table of `guardiand.toml`.
//!
//! ```toml
//! [fleet]
//! name = "cell-1"                     # the fleet; key expressions start guardian/<name>/
//! member = "robot-07"                 # this member's name in the fleet
//! listen = ["tcp/127.0.0.1:7447"]     # Zenoh endpoints to listen on
//! connect = ["tcp/127.0.0.1:7448"]    # Zenoh endpoints of peers
//! signing-key = "/etc/guardian/fleet.key"   # this member's admin key (guardiand --fleet-keygen)
//! admin-keys = ["<64 hex>", ...]      # public keys whose records are applied (own key implied)
//! caller-keys = ["<64 hex>", ...]     # public keys of remote callers (check/identify/status)
//! replicas = 1                        # peers that hold an enroll/forget before it is answered
//! replica-timeout-ms = 2000           # how long the answer waits for them
//! ```
//!
//! Zenoh runs in peer mode with multicast and gossip scouting off: a member talks only to
//! the endpoints named here.

use std::path::PathBuf;

use ed25519_dalek::VerifyingKey;
use serde::{Deserialize, Serialize};

use crate::keys::{KeyError, parse_public_key};

/// The `[fleet]` table.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct FleetConfig {
    /// The fleet's name (one key-expression chunk: no `/`, `*`, `$`, `?`, `#`).
    pub name: String,
    /// This member's name in the fleet (same rules).
    pub member: String,
    /// Zenoh endpoints to listen on, e.g. `tcp/127.0.0.1:7447`.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Zenoh endpoints of peers to connect to.
    #[serde(default)]
    pub connect: Vec<String>,
    /// This member's secret admin key file (mode 0600); its records are signed with it.
    pub signing_key: PathBuf,
    /// Public keys (64 hex digits) whose records this member applies; its own is implied.
    #[serde(default)]
    pub admin_keys: Vec<String>,
    /// Public keys (64 hex digits) of remote callers allowed to check, identify and ask
    /// status over Zenoh.
    #[serde(default)]
    pub caller_keys: Vec<String>,
    /// How often a member asks its peers for records it may have missed (after a
    /// partition), milliseconds; it also asks once at start.
    #[serde(default = "default_resync_ms")]
    pub resync_ms: u64,
    /// How many peers must hold an enroll or forget made on this member before its admin
    /// hears "done" (they acknowledge each record they hold, signed). 0: answered once the
    /// change is durable here and published, as before this key existed.
    #[serde(default)]
    pub replicas: usize,
    /// How long the admin's answer waits for `replicas` peers, milliseconds; past it the
    /// admin hears `Unreplicated` (the change is in effect and durable here, fewer peers
    /// acknowledged it; the others get it when they catch up).
    #[serde(default = "default_replica_timeout_ms")]
    pub replica_timeout_ms: u64,
}

fn default_resync_ms() -> u64 {
    10_000
}

fn default_replica_timeout_ms() -> u64 {
    2_000
}

/// What is wrong with a `[fleet]` table.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FleetConfigError {
    /// A name is empty or not one key-expression chunk.
    #[error(
        "[fleet] {key} = {value:?} must be non-empty, at most 64 bytes, without / * $ ? # or white space"
    )]
    Name {
        /// The key.
        key: &'static str,
        /// The value.
        value: String,
    },
    /// Neither `listen` nor `connect` names an endpoint.
    #[error("[fleet] needs at least one endpoint in listen or connect")]
    NoEndpoint,
    /// An endpoint is not `<protocol>/<address>`.
    #[error("[fleet] endpoint {0:?} is not <protocol>/<address> (e.g. tcp/127.0.0.1:7447)")]
    Endpoint(String),
    /// A public key is malformed.
    #[error("[fleet] {0}")]
    Key(#[from] KeyError),
    /// `resync-ms` is 0.
    #[error("[fleet] resync-ms must be at least 1")]
    Resync,
    /// `replica-timeout-ms` is 0 or longer than an admin waits for its answer.
    #[error("[fleet] replica-timeout-ms must be 1..=30000 (an admin waits 60 s for an answer)")]
    ReplicaTimeout,
}

fn chunk_ok(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 64
        && !s
            .chars()
            .any(|c| matches!(c, '/' | '*' | '$' | '?' | '#') || c.is_whitespace())
}

impl FleetConfig {
    /// Check names, endpoints and keys.
    pub fn check(&self) -> Result<(), FleetConfigError> {
        for (key, value) in [("name", &self.name), ("member", &self.member)] {
            if !chunk_ok(value) {
                return Err(FleetConfigError::Name {
                    key,
                    value: value.clone(),
                });
            }
        }
        if self.listen.is_empty() && self.connect.is_empty() {
            return Err(FleetConfigError::NoEndpoint);
        }
        for e in self.listen.iter().chain(&self.connect) {
            match e.split_once('/') {
                Some((p, a)) if !p.is_empty() && !a.is_empty() => {}
                _ => return Err(FleetConfigError::Endpoint(e.clone())),
            }
        }
        if self.resync_ms == 0 {
            return Err(FleetConfigError::Resync);
        }
        if !(1..=30_000).contains(&self.replica_timeout_ms) {
            return Err(FleetConfigError::ReplicaTimeout);
        }
        self.admin_public_keys()?;
        self.caller_public_keys()?;
        Ok(())
    }

    /// The trusted admin keys (without this member's own).
    pub fn admin_public_keys(&self) -> Result<Vec<VerifyingKey>, KeyError> {
        parse_all(&self.admin_keys, "admin-keys")
    }

    /// The trusted remote-caller keys.
    pub fn caller_public_keys(&self) -> Result<Vec<VerifyingKey>, KeyError> {
        parse_all(&self.caller_keys, "caller-keys")
    }

    /// Key expression on which records are published: `guardian/<fleet>/records`.
    pub fn records_key(&self) -> String {
        format!("guardian/{}/records", self.name)
    }

    /// Key expression of holding acknowledgements: `guardian/<fleet>/acks`.
    pub fn acks_key(&self) -> String {
        format!("guardian/{}/acks", self.name)
    }

    /// How long an admin's answer waits for the peers.
    pub fn replica_timeout(&self) -> std::time::Duration {
        std::time::Duration::from_millis(self.replica_timeout_ms)
    }

    /// This member's catch-up queryable: `guardian/<fleet>/<member>/records`.
    pub fn member_records_key(&self) -> String {
        format!("guardian/{}/{}/records", self.name, self.member)
    }

    /// This member's remote-check queryable: `guardian/<fleet>/<member>/check`.
    pub fn check_key(&self) -> String {
        check_key(&self.name, &self.member)
    }
}

/// The remote-check key expression of `member` in `fleet`.
pub fn check_key(fleet: &str, member: &str) -> String {
    format!("guardian/{fleet}/{member}/check")
}

fn parse_all(keys: &[String], what: &str) -> Result<Vec<VerifyingKey>, KeyError> {
    keys.iter()
        .enumerate()
        .map(|(i, k)| parse_public_key(k, &format!("{what}[{i}]")))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> FleetConfig {
        #[derive(Deserialize)]
        struct Doc {
            fleet: FleetConfig,
        }
        toml::from_str::<Doc>(text).unwrap().fleet
    }

    const GOOD: &str = r#"
[fleet]
name = "cell-1"
member = "robot-a"
listen = ["tcp/127.0.0.1:7447"]
signing-key = "/etc/guardian/fleet.key"
admin-keys = ["0101010101010101010101010101010101010101010101010101010101010101"]
"#;

    #[test]
    fn parses_and_checks() {
        let c = parse(GOOD);
        c.check().unwrap();
        assert_eq!(c.resync_ms, 10_000);
        assert_eq!((c.replicas, c.replica_timeout_ms), (0, 2_000));
        assert_eq!(c.acks_key(), "guardian/cell-1/acks");
        assert_eq!(c.check_key(), "guardian/cell-1/robot-a/check");
        assert_eq!(c.records_key(), "guardian/cell-1/records");
        assert_eq!(c.admin_public_keys().unwrap().len(), 1);
    }

    #[test]
    fn refuses_bad_values() {
        let mut c = parse(GOOD);
        c.member = "a/b".into();
        assert!(matches!(
            c.check(),
            Err(FleetConfigError::Name { key: "member", .. })
        ));
        let mut c = parse(GOOD);
        c.listen.clear();
        assert!(matches!(c.check(), Err(FleetConfigError::NoEndpoint)));
        let mut c = parse(GOOD);
        c.connect.push("localhost".into());
        assert!(matches!(c.check(), Err(FleetConfigError::Endpoint(_))));
        let mut c = parse(GOOD);
        c.replica_timeout_ms = 0;
        assert!(matches!(c.check(), Err(FleetConfigError::ReplicaTimeout)));
        let mut c = parse(GOOD);
        c.caller_keys.push("nothex".into());
        assert!(matches!(c.check(), Err(FleetConfigError::Key(_))));
        let unknown = GOOD.replace("listen", "scouting = true\nlisten");
        #[derive(Debug, Deserialize)]
        #[allow(dead_code)]
        struct Doc {
            fleet: FleetConfig,
        }
        assert!(toml::from_str::<Doc>(&unknown).is_err());
    }
}
