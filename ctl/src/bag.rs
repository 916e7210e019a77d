//! `--bag`: plans from a rosbag2 recording (MCAP storage), one per `JointTrajectory` or
//! FollowJointTrajectory goal message on `--topic`, mapped to the robot's joints by name as
//! guardian-gate maps goals (docs/ros2.md, "Recordings").

use std::path::PathBuf;

use anyhow::Context;
use guardian_client::Trajectory;
use guardian_gate::plan::{PlanMapper, ToolSource};
use guardian_robot::kinematics::RobotDescription;

/// The options of `enroll --bag` and `check --bag`.
#[derive(Debug, clap::Args)]
pub struct BagArgs {
    /// A rosbag2 MCAP file: every trajectory_msgs/msg/JointTrajectory (or
    /// FollowJointTrajectory goal) message on --topic is one plan.
    #[arg(long, requires = "topic")]
    pub bag: Option<PathBuf>,
    /// The topic of --bag.
    #[arg(long, requires = "bag")]
    pub topic: Option<String>,
    /// The robot whose URDF joint names the messages use (guardiand's robot): panda, ur5e
    /// or a robot description path.
    #[arg(long, default_value = "panda")]
    pub robot: String,
    /// Tool channel from this joint (down at position 0.5 and above); unset: down while
    /// the pen tip is at the canvas height (the workcell of --robot).
    #[arg(long)]
    pub tool_joint: Option<String>,
}

impl BagArgs {
    /// The plans of the bag, if `--bag` was given.
    pub fn plans(&self) -> anyhow::Result<Option<Vec<Trajectory>>> {
        let (Some(bag), Some(topic)) = (&self.bag, &self.topic) else {
            return Ok(None);
        };
        let description = RobotDescription::resolve(&self.robot)
            .with_context(|| format!("robot {:?}", self.robot))?;
        let tool = match &self.tool_joint {
            Some(joint) => ToolSource::Joint {
                joint: joint.clone(),
                down_at: 0.5,
            },
            None => ToolSource::PenHeight,
        };
        let mapper = PlanMapper::new(&description, tool);
        let plans = guardian_gate::bag::read_plans(bag, topic, &mapper)?;
        Ok(Some(
            plans
                .into_iter()
                .map(|p| Trajectory::from_flat(p.data, p.channels))
                .collect(),
        ))
    }
}
