//! The gate's TOML config (`/etc/guardian/guardian-gate.toml`), kebab-case, unknown keys
//! rejected, every key optional (docs/ros2.md, "Config").

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

use crate::plan::ToolSource;

/// Where the installed config lives.
pub const DEFAULT_CONFIG_PATH: &str = "/etc/guardian/guardian-gate.toml";

/// The whole config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct GateConfig {
    /// The gate's namespace: it serves `<gate>/follow_joint_trajectory` and uses
    /// `<gate>/task` and `<gate>/verdicts`. MoveIt's `action_ns` points here.
    pub gate: String,
    /// The real controller's namespace: go goals are sent to
    /// `<controller>/follow_joint_trajectory`.
    pub controller: String,
    /// ROS node name.
    pub node_name: String,
    /// DDS domain; unset: `$ROS_DOMAIN_ID`, else 0.
    pub domain_id: Option<u16>,
    /// The controller's DDS domain, when it is not the gate's: the gate then bridges the two
    /// (its action server on `domain-id`, its client of the controller on this one), so
    /// nothing on MoveIt's domain can reach the controller around the gate. Unset: the gate's.
    pub controller_domain_id: Option<u16>,
    /// Limit DDS to the interfaces with these addresses (e.g. `["127.0.0.1"]` when
    /// MoveIt, the controller and the gate share the host): announced, sent and received
    /// on that interface only; the addresses must be on one interface
    /// (the `sockets` module). Empty: every interface.
    pub only_networks: Vec<std::net::IpAddr>,
    /// The ROS nodes (fully qualified names, e.g. `"/cell/executive"`) whose claims on
    /// `<gate>/task` count; a claim from any other node is refused and changes nothing.
    /// Empty: any participant may claim (warned at start).
    pub claim_from: Vec<String>,
    /// The robot served: `panda`, `ur5e` or a robot description path; must be guardiand's.
    pub robot: String,
    /// Where the tool channel comes from.
    pub tool: ToolSource,
    /// How long to wait for the controller to accept or reject a forwarded goal (ms).
    pub controller_timeout_ms: u64,
    /// How long a goal's result is kept for its sender to ask for it (s; ROS 2's action
    /// servers keep results 900 s). The next goals never wait for it.
    pub result_keep_s: u64,
    /// Results kept at once for senders that have not asked yet; a result beyond is
    /// dropped (logged).
    pub max_pending_results: usize,
    /// How the action's services map onto DDS: that of the RMW MoveIt and the controller
    /// use (the same for both).
    pub service_mapping: ServiceMappingName,
    /// How to reach guardiand.
    pub guardiand: GuardiandConfig,
}

/// The DDS mapping of ROS 2 services (and so of actions), which depends on the RMW.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ServiceMappingName {
    /// rmw_fastrtps_cpp (ROS 2 Jazzy's default RMW) and rmw_connextdds: the request id in
    /// the sample's related-sample identity.
    #[default]
    Enhanced,
    /// rmw_cyclonedds_cpp: the request id at the head of the payload.
    Cyclone,
    /// The DDS-RPC basic mapping.
    Basic,
}

/// How the gate reaches guardiand (the same keys as guardiand's own config).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct GuardiandConfig {
    /// guardiand's request-response service name.
    pub service_name: String,
    /// Longest wait for one answer (ms); past it the goal is rejected.
    pub timeout_ms: u64,
    /// iceoryx2 root path (guardiand's `[iceoryx2] root-path`).
    pub iceoryx2_root_path: Option<PathBuf>,
    /// iceoryx2 prefix (guardiand's `[iceoryx2] prefix`).
    pub iceoryx2_prefix: Option<String>,
}

impl Default for GateConfig {
    fn default() -> Self {
        Self {
            gate: "/guardian_gate".into(),
            controller: "/panda_arm_controller".into(),
            node_name: "guardian_gate".into(),
            domain_id: None,
            controller_domain_id: None,
            only_networks: Vec::new(),
            claim_from: Vec::new(),
            robot: "panda".into(),
            tool: ToolSource::default(),
            controller_timeout_ms: 2000,
            result_keep_s: 900,
            max_pending_results: 256,
            service_mapping: ServiceMappingName::default(),
            guardiand: GuardiandConfig::default(),
        }
    }
}

impl Default for GuardiandConfig {
    fn default() -> Self {
        Self {
            service_name: guardian_shared::wire::DEFAULT_SERVICE_NAME.into(),
            timeout_ms: 500,
            iceoryx2_root_path: None,
            iceoryx2_prefix: None,
        }
    }
}

/// The config could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not TOML of the expected shape (names the key).
    #[error("{}: {source}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// Why.
        source: Box<toml::de::Error>,
    },
    /// A name is not a valid ROS 2 name.
    #[error("{key} = {value:?} is not an absolute ROS 2 namespace (like \"/guardian_gate\")")]
    Name {
        /// The key.
        key: &'static str,
        /// Its value.
        value: String,
    },
    /// A DDS domain id beyond what the RTPS port mapping fits in a UDP port.
    #[error(
        "{key} = {value} is not a DDS domain id: 0..={MAX_DOMAIN_ID} (ROS 2 advises 0..=101 on Linux)"
    )]
    Domain {
        /// The key (or `ROS_DOMAIN_ID`).
        key: &'static str,
        /// Its value.
        value: u16,
    },
}

/// The largest domain id whose RTPS ports (7400 + 250 × domain + offsets) fit in 16 bits.
pub const MAX_DOMAIN_ID: u16 = 232;

impl GateConfig {
    /// Parse `text` (errors name `path`).
    pub fn parse(text: &str, path: &Path) -> Result<Self, ConfigError> {
        let c: Self = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
        c.validate()?;
        Ok(c)
    }

    /// Read and parse a file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    fn validate(&self) -> Result<(), ConfigError> {
        for (key, value) in [("gate", &self.gate), ("controller", &self.controller)] {
            let ok = value.starts_with('/')
                && value.len() > 1
                && !value.ends_with('/')
                && value[1..].split('/').all(|p| {
                    !p.is_empty() && p.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                });
            if !ok {
                return Err(ConfigError::Name {
                    key,
                    value: value.clone(),
                });
            }
        }
        if let Some(bad) = self
            .claim_from
            .iter()
            .find(|n| !n.starts_with('/') || n.ends_with('/') || n.len() < 2 || n.contains("//"))
        {
            return Err(ConfigError::Name {
                key: "claim-from",
                value: bad.clone(),
            });
        }
        let key = if self.domain_id.is_some() {
            "domain-id"
        } else {
            "ROS_DOMAIN_ID"
        };
        for (key, value) in [
            (key, self.domain()),
            ("controller-domain-id", self.controller_domain()),
        ] {
            if value > MAX_DOMAIN_ID {
                return Err(ConfigError::Domain { key, value });
            }
        }
        if self.gate == self.controller {
            return Err(ConfigError::Name {
                key: "controller",
                value: format!(
                    "{} (the same as gate: the gate would forward to itself)",
                    self.controller
                ),
            });
        }
        Ok(())
    }

    /// The controller's domain id: `controller-domain-id`, else the gate's.
    pub fn controller_domain(&self) -> u16 {
        self.controller_domain_id.unwrap_or_else(|| self.domain())
    }

    /// The domain id: the config's, else `$ROS_DOMAIN_ID`, else 0.
    pub fn domain(&self) -> u16 {
        self.domain_id
            .or_else(|| std::env::var("ROS_DOMAIN_ID").ok()?.parse().ok())
            .unwrap_or(0)
    }

    /// The controller answer timeout.
    pub fn controller_timeout(&self) -> Duration {
        Duration::from_millis(self.controller_timeout_ms)
    }

    /// How long a goal's result waits for its sender.
    pub fn result_keep(&self) -> Duration {
        Duration::from_secs(self.result_keep_s)
    }

    /// The installed config as commented TOML (`--print-default-config`): the defaults
    /// with the installed guardiand's iceoryx2 root path.
    pub fn default_toml() -> &'static str {
        include_str!("../guardian-gate.toml")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_sample_is_the_default_for_the_installed_guardiand() {
        let c = GateConfig::parse(GateConfig::default_toml(), Path::new("sample")).unwrap();
        let mut want = GateConfig::default();
        want.guardiand.iceoryx2_root_path = Some("/run/guardian/iceoryx2/".into());
        assert_eq!(c, want);
    }

    #[test]
    fn tool_joint_and_errors() {
        let c = GateConfig::parse(
            "controller = \"/arm\"\n[tool]\nsource = \"joint\"\njoint = \"pen\"\n",
            Path::new("x"),
        )
        .unwrap();
        assert_eq!(
            c.tool,
            ToolSource::Joint {
                joint: "pen".into(),
                down_at: 0.5
            }
        );
        let c = GateConfig::parse("service-mapping = \"cyclone\"\n", Path::new("x")).unwrap();
        assert_eq!(c.service_mapping, ServiceMappingName::Cyclone);
        assert!(GateConfig::parse("service-mapping = \"zenoh\"\n", Path::new("x")).is_err());
        let e = GateConfig::parse("bogus = 1\n", Path::new("x")).unwrap_err();
        assert!(e.to_string().contains("bogus"), "{e}");
        let e = GateConfig::parse("gate = \"no_slash\"\n", Path::new("x")).unwrap_err();
        assert!(matches!(e, ConfigError::Name { key: "gate", .. }));
        let c = GateConfig::parse("claim-from = [\"/cell/executive\"]\n", Path::new("x")).unwrap();
        assert_eq!(c.claim_from, ["/cell/executive"]);
        let e = GateConfig::parse("claim-from = [\"executive\"]\n", Path::new("x")).unwrap_err();
        assert!(matches!(
            e,
            ConfigError::Name {
                key: "claim-from",
                ..
            }
        ));
        let e = GateConfig::parse("domain-id = 240\n", Path::new("x")).unwrap_err();
        assert!(
            matches!(
                e,
                ConfigError::Domain {
                    key: "domain-id",
                    value: 240
                }
            ),
            "{e}"
        );
        let e = GateConfig::parse(
            "domain-id = 5\ncontroller-domain-id = 233\n",
            Path::new("x"),
        )
        .unwrap_err();
        assert!(matches!(
            e,
            ConfigError::Domain {
                key: "controller-domain-id",
                ..
            }
        ));
        assert!(GateConfig::parse("domain-id = 232\n", Path::new("x")).is_ok());
        let e = GateConfig::parse("controller = \"/guardian_gate\"\n", Path::new("x")).unwrap_err();
        assert!(matches!(
            e,
            ConfigError::Name {
                key: "controller",
                ..
            }
        ));
    }
}
