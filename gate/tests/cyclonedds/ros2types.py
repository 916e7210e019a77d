"""ROS 2 message types as Cyclone DDS (PyPI `cyclonedds`) sees them: the DDS type names
rosidl gives them (`<pkg>::msg::dds_::<Name>_`). Shared by the gate's Cyclone DDS tests.
"""
from dataclasses import dataclass, field
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import sequence, array, uint8, int8, uint16, int32, uint32, uint64, int64, float32, float64

@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32
@dataclass
class Duration_(IdlStruct, typename="builtin_interfaces::msg::dds_::Duration_"):
    sec: int32
    nanosec: uint32
@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_
    frame_id: str
@dataclass
class JointTrajectoryPoint_(IdlStruct, typename="trajectory_msgs::msg::dds_::JointTrajectoryPoint_"):
    positions: sequence[float64]
    velocities: sequence[float64]
    accelerations: sequence[float64]
    effort: sequence[float64]
    time_from_start: Duration_
@dataclass
class JointTrajectory_(IdlStruct, typename="trajectory_msgs::msg::dds_::JointTrajectory_"):
    header: Header_
    joint_names: sequence[str]
    points: sequence[JointTrajectoryPoint_]
@dataclass
class Vector3_(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64
@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64
@dataclass
class Transform_(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3_
    rotation: Quaternion_
@dataclass
class Twist_(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3_
    angular: Vector3_
@dataclass
class MultiDOFJointTrajectoryPoint_(IdlStruct, typename="trajectory_msgs::msg::dds_::MultiDOFJointTrajectoryPoint_"):
    transforms: sequence[Transform_]
    velocities: sequence[Twist_]
    accelerations: sequence[Twist_]
    time_from_start: Duration_
@dataclass
class MultiDOFJointTrajectory_(IdlStruct, typename="trajectory_msgs::msg::dds_::MultiDOFJointTrajectory_"):
    header: Header_
    joint_names: sequence[str]
    points: sequence[MultiDOFJointTrajectoryPoint_]
@dataclass
class JointTolerance_(IdlStruct, typename="control_msgs::msg::dds_::JointTolerance_"):
    name: str
    position: float64
    velocity: float64
    acceleration: float64
@dataclass
class JointComponentTolerance_(IdlStruct, typename="control_msgs::msg::dds_::JointComponentTolerance_"):
    joint_name: str
    component: uint16
    position: float64
    velocity: float64
    acceleration: float64
@dataclass
class Goal_(IdlStruct, typename="control_msgs::action::dds_::FollowJointTrajectory_Goal_"):
    trajectory: JointTrajectory_
    multi_dof_trajectory: MultiDOFJointTrajectory_
    path_tolerance: sequence[JointTolerance_]
    component_path_tolerance: sequence[JointComponentTolerance_]
    goal_tolerance: sequence[JointTolerance_]
    component_goal_tolerance: sequence[JointComponentTolerance_]
    goal_time_tolerance: Duration_
@dataclass
class UUID_(IdlStruct, typename="unique_identifier_msgs::msg::dds_::UUID_"):
    uuid: array[uint8, 16]
@dataclass
class SendGoalRequest_(IdlStruct, typename="control_msgs::action::dds_::FollowJointTrajectory_SendGoal_Request_"):
    client_guid: uint64
    seq: int64
    goal_id: UUID_
    goal: Goal_
@dataclass
class SendGoalResponse_(IdlStruct, typename="control_msgs::action::dds_::FollowJointTrajectory_SendGoal_Response_"):
    client_guid: uint64
    seq: int64
    accepted: bool
    stamp: Time_
@dataclass
class GetResultRequest_(IdlStruct, typename="control_msgs::action::dds_::FollowJointTrajectory_GetResult_Request_"):
    client_guid: uint64
    seq: int64
    goal_id: UUID_
@dataclass
class Result_(IdlStruct, typename="control_msgs::action::dds_::FollowJointTrajectory_Result_"):
    error_code: int32
    error_string: str
@dataclass
class GetResultResponse_(IdlStruct, typename="control_msgs::action::dds_::FollowJointTrajectory_GetResult_Response_"):
    client_guid: uint64
    seq: int64
    status: int8
    result: Result_
@dataclass
class Verdict_(IdlStruct, typename="guardian_msgs::msg::dds_::Verdict_"):
    header: Header_
    goal_id: str
    claimed_task: str
    verdict: str
    reason: str
    detail: str
    nearest_class: str
    distance: float32
    threshold: float32
    model_version: str
    bank_version: uint64
    trajectory_sha256: str
    waypoints: uint32


@dataclass
class String_(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str
@dataclass
class KeyValue_(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str
@dataclass
class DiagnosticStatus_(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: uint8
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue_]
@dataclass
class DiagnosticArray_(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header_
    status: sequence[DiagnosticStatus_]
