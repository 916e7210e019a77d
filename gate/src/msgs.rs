//! The ROS 2 messages the gate and `guardianctl --bag` speak, as serde structs whose field
//! order is the CDR layout of the ROS 2 Jazzy definitions (`trajectory_msgs`,
//! `control_msgs`, `std_msgs`, `diagnostic_msgs`), and the project's own verdict message
//! (`guardian_msgs/msg/Verdict`, defined in `ros2/guardian_msgs/msg/Verdict.msg`).

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds since the epoch.
    pub sec: i32,
    /// Nanoseconds, 0..1e9.
    pub nanosec: u32,
}

impl Time {
    /// The system clock now.
    pub fn now() -> Self {
        let d = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        Self {
            sec: i32::try_from(d.as_secs()).unwrap_or(i32::MAX),
            nanosec: d.subsec_nanos(),
        }
    }
}

/// `builtin_interfaces/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, 0..1e9.
    pub nanosec: u32,
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Time stamp.
    pub stamp: Time,
    /// Frame.
    pub frame_id: String,
}

/// `std_msgs/String`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}

/// `trajectory_msgs/JointTrajectoryPoint`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectoryPoint {
    /// Joint positions (rad or m), in the order of the trajectory's `joint_names`.
    pub positions: Vec<f64>,
    /// Velocities (unused by the screen).
    pub velocities: Vec<f64>,
    /// Accelerations (unused by the screen).
    pub accelerations: Vec<f64>,
    /// Efforts (unused by the screen).
    pub effort: Vec<f64>,
    /// Time from the trajectory's start (unused by the screen).
    pub time_from_start: Duration,
}

/// `trajectory_msgs/JointTrajectory`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectory {
    /// Header.
    pub header: Header,
    /// Joint names (URDF), any order.
    pub joint_names: Vec<String>,
    /// Waypoints.
    pub points: Vec<JointTrajectoryPoint>,
}

/// `geometry_msgs/Vector3`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/Quaternion`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// `geometry_msgs/Transform`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/Twist`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear.
    pub linear: Vector3,
    /// Angular.
    pub angular: Vector3,
}

/// `trajectory_msgs/MultiDOFJointTrajectoryPoint`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiDofJointTrajectoryPoint {
    /// Transforms.
    pub transforms: Vec<Transform>,
    /// Velocities.
    pub velocities: Vec<Twist>,
    /// Accelerations.
    pub accelerations: Vec<Twist>,
    /// Time from start.
    pub time_from_start: Duration,
}

/// `trajectory_msgs/MultiDOFJointTrajectory` (relayed, not screened).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiDofJointTrajectory {
    /// Header.
    pub header: Header,
    /// Joint names.
    pub joint_names: Vec<String>,
    /// Points.
    pub points: Vec<MultiDofJointTrajectoryPoint>,
}

/// `control_msgs/JointTolerance`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTolerance {
    /// Joint.
    pub name: String,
    /// Position tolerance.
    pub position: f64,
    /// Velocity tolerance.
    pub velocity: f64,
    /// Acceleration tolerance.
    pub acceleration: f64,
}

/// `control_msgs/JointComponentTolerance`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointComponentTolerance {
    /// Joint.
    pub joint_name: String,
    /// X_AXIS = 1 .. ROTATION = 5.
    pub component: u16,
    /// Position tolerance.
    pub position: f64,
    /// Velocity tolerance.
    pub velocity: f64,
    /// Acceleration tolerance.
    pub acceleration: f64,
}

/// `control_msgs/action/FollowJointTrajectory` goal (Jazzy).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowJointTrajectoryGoal {
    /// The joint trajectory: what the gate screens.
    pub trajectory: JointTrajectory,
    /// Multi-DOF part (relayed unchanged).
    pub multi_dof_trajectory: MultiDofJointTrajectory,
    /// Path tolerances.
    pub path_tolerance: Vec<JointTolerance>,
    /// Component path tolerances.
    pub component_path_tolerance: Vec<JointComponentTolerance>,
    /// Goal tolerances.
    pub goal_tolerance: Vec<JointTolerance>,
    /// Component goal tolerances.
    pub component_goal_tolerance: Vec<JointComponentTolerance>,
    /// Goal time tolerance.
    pub goal_time_tolerance: Duration,
}

/// `control_msgs/action/FollowJointTrajectory` result.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowJointTrajectoryResult {
    /// [`error_code`] values.
    pub error_code: i32,
    /// Human-readable reason.
    pub error_string: String,
}

/// `FollowJointTrajectory_Result.error_code` values.
pub mod error_code {
    /// Success.
    pub const SUCCESSFUL: i32 = 0;
    /// The goal is not acceptable (guardian's no-go and every fail-closed case).
    pub const INVALID_GOAL: i32 = -1;
    /// The joint names do not fit the served robot.
    pub const INVALID_JOINTS: i32 = -2;
}

/// `control_msgs/action/FollowJointTrajectory` feedback (relayed unchanged).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowJointTrajectoryFeedback {
    /// Header.
    pub header: Header,
    /// Joints.
    pub joint_names: Vec<String>,
    /// Desired.
    pub desired: JointTrajectoryPoint,
    /// Actual.
    pub actual: JointTrajectoryPoint,
    /// Error.
    pub error: JointTrajectoryPoint,
    /// Multi-DOF joints.
    pub multi_dof_joint_names: Vec<String>,
    /// Multi-DOF desired.
    pub multi_dof_desired: MultiDofJointTrajectoryPoint,
    /// Multi-DOF actual.
    pub multi_dof_actual: MultiDofJointTrajectoryPoint,
    /// Multi-DOF error.
    pub multi_dof_error: MultiDofJointTrajectoryPoint,
}

/// `guardian_msgs/msg/Verdict`: one screened goal, published on `<gate>/verdicts`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    /// When the verdict was made.
    pub header: Header,
    /// The action goal's UUID, 32 hex digits.
    pub goal_id: String,
    /// The claimed task; empty in identify mode.
    pub claimed_task: String,
    /// `go`, `no-go` or `error` (fail closed: the goal was not forwarded).
    pub verdict: String,
    /// Why: `genuine`, `wrong-task`, `outlier`, `unknown-class`, `invalid-trajectory`,
    /// `workcell`, `geometry-mismatch`, `invalid-joints`, `guardiand-unreachable`, `timeout`,
    /// `internal`; a second verdict `error` after a go names the controller's failure:
    /// `controller-timeout`, `controller-lost`, `controller-unreachable`, `controller-rejected`.
    pub reason: String,
    /// The full sentence (the result's `error_string` for a no-go).
    pub detail: String,
    /// The nearest enrolled class (empty if none).
    pub nearest_class: String,
    /// Distance to the claimed (identify: nearest) class; NaN if none.
    pub distance: f32,
    /// That class's threshold; NaN if none.
    pub threshold: f32,
    /// The serving model's version.
    pub model_version: String,
    /// The class bank's version.
    pub bank_version: u64,
    /// SHA-256 (hex) of the plan as sent to guardiand (f32 little-endian, row-major).
    pub trajectory_sha256: String,
    /// Waypoints in the plan.
    pub waypoints: u32,
}

/// `diagnostic_msgs/KeyValue`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyValue {
    /// Key.
    pub key: String,
    /// Value.
    pub value: String,
}

/// `diagnostic_msgs/DiagnosticStatus`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// OK = 0, WARN = 1, ERROR = 2, STALE = 3.
    pub level: u8,
    /// Name.
    pub name: String,
    /// Message.
    pub message: String,
    /// Hardware id.
    pub hardware_id: String,
    /// Values.
    pub values: Vec<KeyValue>,
}

/// `diagnostic_msgs/DiagnosticArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// Header.
    pub header: Header,
    /// Statuses.
    pub status: Vec<DiagnosticStatus>,
}

#[cfg(feature = "node")]
mod message_impls {
    use ros2_client::Message;
    impl Message for super::StringMsg {}
    impl Message for super::JointTrajectory {}
    impl Message for super::FollowJointTrajectoryGoal {}
    impl Message for super::FollowJointTrajectoryResult {}
    impl Message for super::FollowJointTrajectoryFeedback {}
    impl Message for super::Verdict {}
    impl Message for super::DiagnosticArray {}
}

/// `rmw_dds_common/Gid` (ROS 2 Iron and later: 16 bytes, the DDS GUID).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Gid {
    /// The GUID: participant prefix (12 bytes) and entity id (4).
    pub data: [u8; 16],
}

/// `rmw_dds_common/NodeEntitiesInfo`: a ROS node and its DDS readers and writers.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct NodeEntitiesInfo {
    /// Its namespace (`/`, `/cell`).
    pub node_namespace: String,
    /// Its name.
    pub node_name: String,
    /// Its readers.
    pub reader_gid_seq: Vec<Gid>,
    /// Its writers.
    pub writer_gid_seq: Vec<Gid>,
}

impl NodeEntitiesInfo {
    /// `/namespace/name`.
    pub fn fully_qualified_name(&self) -> String {
        let ns = self.node_namespace.trim_end_matches('/');
        format!("{ns}/{}", self.node_name)
    }
}

/// `rmw_dds_common/ParticipantEntitiesInfo`, what every ROS 2 participant publishes on the
/// DDS topic `ros_discovery_info`: its nodes and their entities.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ParticipantEntitiesInfo {
    /// The participant's GUID.
    pub gid: Gid,
    /// Its nodes.
    pub node_entities_info_seq: Vec<NodeEntitiesInfo>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn goal_round_trips_through_cdr() {
        let goal = FollowJointTrajectoryGoal {
            trajectory: JointTrajectory {
                header: Header {
                    stamp: Time { sec: 3, nanosec: 4 },
                    frame_id: "base".into(),
                },
                joint_names: vec!["a".into(), "b".into()],
                points: vec![JointTrajectoryPoint {
                    positions: vec![0.5, -1.0],
                    ..Default::default()
                }],
            },
            goal_time_tolerance: Duration { sec: 1, nanosec: 0 },
            ..Default::default()
        };
        let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&goal).unwrap();
        let (back, _) =
            cdr_encoding::from_bytes::<FollowJointTrajectoryGoal, byteorder::LittleEndian>(&bytes)
                .unwrap();
        assert_eq!(back, goal);
    }
}
