//! A ROS 2 `JointTrajectory` → guardian's plan: the served robot's joints in URDF order,
//! found by name in any order, then the tool channel (docs/ros2.md, "Goal → plan").

use guardian_robot::kinematics::{Robot, RobotDescription, joint_vector};
use guardian_shared::workcell::Workcell;
use serde::Deserialize;
use sha2::{Digest, Sha256};

use crate::msgs::JointTrajectory;

/// Where the tool channel (pen down = 1, up = 0) comes from.
#[derive(Debug, Clone, PartialEq, Default, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, tag = "source")]
pub enum ToolSource {
    /// A joint of the trajectory (a pen or gripper joint): down while its position is at or
    /// above `down-at`. The joint must be in every goal.
    Joint {
        /// Its name in `joint_names`.
        joint: String,
        /// Position (rad or m) at and above which the tool counts as down.
        #[serde(default = "half")]
        down_at: f64,
    },
    /// The workcell: down while the pen tip (forward kinematics of the served robot's
    /// description) is within the workcell's height tolerance of the canvas plane.
    #[default]
    PenHeight,
}

fn half() -> f64 {
    0.5
}

/// A goal's joints do not fit the served robot (answered with `INVALID_JOINTS`).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PlanError {
    /// A joint of the served robot (or the configured tool joint) is not in `joint_names`.
    #[error("joint {joint:?} of {robot} is missing from joint_names {given:?}")]
    MissingJoint {
        /// The robot.
        robot: String,
        /// The missing joint.
        joint: String,
        /// What the goal named.
        given: Vec<String>,
    },
    /// `joint_names` has a joint the served robot (and the tool) does not have.
    #[error("unknown joint {joint:?}: {robot} has {expected:?}")]
    UnknownJoint {
        /// The robot.
        robot: String,
        /// The unknown name.
        joint: String,
        /// The joints it has (and the tool joint, if configured).
        expected: Vec<String>,
    },
    /// A name appears twice in `joint_names`.
    #[error("joint {joint:?} appears twice in joint_names")]
    DuplicateJoint {
        /// The name.
        joint: String,
    },
    /// A point has not one position per joint name.
    #[error("point {index} has {got} positions for {expected} joint names")]
    PositionCount {
        /// Point index.
        index: usize,
        /// Positions given.
        got: usize,
        /// Joint names.
        expected: usize,
    },
    /// No points at all.
    #[error("the trajectory has no points")]
    Empty,
}

/// Maps trajectories of one robot to plans. Built once from the robot description.
#[derive(Debug, Clone)]
pub struct PlanMapper {
    robot: Robot,
    names: Vec<String>,
    tool: ToolSource,
    workcell: Workcell,
}

/// A mapped plan: row-major `joints + 1` channels per waypoint.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Flat rows.
    pub data: Vec<f32>,
    /// Channels per row (joints + tool).
    pub channels: usize,
}

impl Plan {
    /// Waypoints.
    pub fn waypoints(&self) -> usize {
        self.data.len() / self.channels.max(1)
    }

    /// SHA-256 (hex) of the plan's f32 values, little-endian, row-major.
    pub fn sha256(&self) -> String {
        let mut h = Sha256::new();
        for v in &self.data {
            h.update(v.to_le_bytes());
        }
        h.finalize()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect::<String>()
    }
}

impl PlanMapper {
    /// For `description` (its URDF joint names and, for [`ToolSource::PenHeight`], its
    /// kinematics and workcell).
    pub fn new(description: &RobotDescription, tool: ToolSource) -> Self {
        let names = description
            .robot
            .joint_list()
            .iter()
            .map(|j| j.name.clone())
            .collect();
        Self {
            robot: description.robot.clone(),
            names,
            tool,
            workcell: description.workcell,
        }
    }

    /// The served robot's joint names, in URDF order.
    pub fn joint_names(&self) -> &[String] {
        &self.names
    }

    /// The robot's name.
    pub fn robot_name(&self) -> &str {
        self.robot.name()
    }

    /// Map `t`: every robot joint found once by name, no unknown or duplicated name, one
    /// position per name in every point. Velocities and times are not used.
    pub fn map(&self, t: &JointTrajectory) -> Result<Plan, PlanError> {
        let robot = self.robot.name().to_string();
        let tool_joint = match &self.tool {
            ToolSource::Joint { joint, .. } => Some(joint.as_str()),
            ToolSource::PenHeight => None,
        };
        let mut seen = std::collections::HashSet::new();
        for n in &t.joint_names {
            if !seen.insert(n.as_str()) {
                return Err(PlanError::DuplicateJoint { joint: n.clone() });
            }
            if !self.names.iter().any(|m| m == n) && tool_joint != Some(n.as_str()) {
                let mut expected = self.names.clone();
                expected.extend(tool_joint.map(str::to_string));
                return Err(PlanError::UnknownJoint {
                    robot,
                    joint: n.clone(),
                    expected,
                });
            }
        }
        let index_of = |name: &str| {
            t.joint_names
                .iter()
                .position(|n| n == name)
                .ok_or_else(|| PlanError::MissingJoint {
                    robot: robot.clone(),
                    joint: name.to_string(),
                    given: t.joint_names.clone(),
                })
        };
        let order: Vec<usize> = self
            .names
            .iter()
            .map(|n| index_of(n))
            .collect::<Result<_, _>>()?;
        let tool_index = tool_joint.map(index_of).transpose()?;
        if t.points.is_empty() {
            return Err(PlanError::Empty);
        }
        let channels = self.names.len() + 1;
        let mut data = Vec::with_capacity(t.points.len() * channels);
        for (index, p) in t.points.iter().enumerate() {
            if p.positions.len() != t.joint_names.len() {
                return Err(PlanError::PositionCount {
                    index,
                    got: p.positions.len(),
                    expected: t.joint_names.len(),
                });
            }
            let q: Vec<f64> = order.iter().map(|&i| p.positions[i]).collect();
            data.extend(q.iter().map(|&v| v as f32));
            let down = match (&self.tool, tool_index) {
                (ToolSource::Joint { down_at, .. }, Some(i)) => p.positions[i] >= *down_at,
                _ => self.pen_down(&q),
            };
            data.push(if down { 1.0 } else { 0.0 });
        }
        Ok(Plan { data, channels })
    }

    /// The pen tip is within the height tolerance of the canvas plane.
    fn pen_down(&self, q: &[f64]) -> bool {
        let tip = self.robot.pen_tip_position(&joint_vector(q));
        (tip.z - self.workcell.canvas_z).abs() <= self.workcell.height_tolerance
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::JointTrajectoryPoint;
    use guardian_robot::kinematics::IkOptions;

    fn panda(tool: ToolSource) -> PlanMapper {
        PlanMapper::new(&RobotDescription::named("panda").unwrap(), tool)
    }

    fn traj(names: &[&str], rows: &[Vec<f64>]) -> JointTrajectory {
        JointTrajectory {
            joint_names: names.iter().map(|s| s.to_string()).collect(),
            points: rows
                .iter()
                .map(|r| JointTrajectoryPoint {
                    positions: r.clone(),
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    const READY: [f64; 7] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

    fn names() -> Vec<String> {
        (1..=7).map(|i| format!("panda_joint{i}")).collect()
    }

    #[test]
    fn any_order_gives_the_same_plan() {
        let m = panda(ToolSource::Joint {
            joint: "pen".into(),
            down_at: 0.5,
        });
        let mut n: Vec<String> = names();
        n.push("pen".into());
        let row: Vec<f64> = READY.iter().copied().chain([1.0]).collect();
        let refs: Vec<&str> = n.iter().map(String::as_str).collect();
        let a = m.map(&traj(&refs, &[row.clone(), row.clone()])).unwrap();
        // Reverse the names and the positions alike.
        let rev_names: Vec<&str> = refs.iter().rev().copied().collect();
        let rev_row: Vec<f64> = row.iter().rev().copied().collect();
        let b = m
            .map(&traj(&rev_names, &[rev_row.clone(), rev_row]))
            .unwrap();
        assert_eq!(a, b);
        assert_eq!(a.channels, 8);
        assert_eq!(a.waypoints(), 2);
        assert_eq!(a.data[7], 1.0);
        assert_eq!(a.sha256(), b.sha256());
    }

    #[test]
    fn joint_errors_are_typed() {
        let m = panda(ToolSource::PenHeight);
        let n = names();
        let refs: Vec<&str> = n.iter().map(String::as_str).collect();
        let row = READY.to_vec();
        // Missing.
        let e = m.map(&traj(&refs[..6], &[row[..6].to_vec()])).unwrap_err();
        assert!(matches!(e, PlanError::MissingJoint { ref joint, .. } if joint == "panda_joint7"));
        // Unknown.
        let mut extra = refs.clone();
        extra.push("elbow_joint");
        let mut r8 = row.clone();
        r8.push(0.0);
        let e = m.map(&traj(&extra, &[r8])).unwrap_err();
        assert!(matches!(e, PlanError::UnknownJoint { ref joint, .. } if joint == "elbow_joint"));
        // Duplicated.
        let mut dup = refs.clone();
        dup[6] = "panda_joint1";
        let e = m.map(&traj(&dup, std::slice::from_ref(&row))).unwrap_err();
        assert_eq!(
            e,
            PlanError::DuplicateJoint {
                joint: "panda_joint1".into()
            }
        );
        // Ragged point.
        let e = m.map(&traj(&refs, &[row[..5].to_vec()])).unwrap_err();
        assert!(matches!(
            e,
            PlanError::PositionCount {
                index: 0,
                got: 5,
                expected: 7
            }
        ));
        assert_eq!(m.map(&traj(&refs, &[])).unwrap_err(), PlanError::Empty);
    }

    #[test]
    fn pen_height_tool_follows_the_canvas() {
        let d = RobotDescription::named("panda").unwrap();
        let m = PlanMapper::new(&d, ToolSource::PenHeight);
        let n = names();
        let refs: Vec<&str> = n.iter().map(String::as_str).collect();
        // The ready pose puts the pen tip well above the canvas plane: up.
        let up = m.map(&traj(&refs, &[READY.to_vec()])).unwrap();
        assert_eq!(up.data[7], 0.0);
        // Solve a pose with the pen tip on the canvas centre by the models' IK.
        let target = guardian_robot::kinematics::Frame::from_xyz_rpy(
            [
                d.workcell.canvas_x,
                d.workcell.canvas_y,
                d.workcell.canvas_z,
            ],
            [std::f64::consts::PI, 0.0, 0.0],
        );
        let q = d
            .robot
            .ik(&target, &d.home_seed, &IkOptions::default())
            .expect("IK to the canvas centre");
        let on: Vec<f64> = q[..7].to_vec();
        let down = m.map(&traj(&refs, &[on])).unwrap();
        assert_eq!(down.data[7], 1.0);
    }
}
