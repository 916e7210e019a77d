//! Plans from a rosbag2 recording (MCAP storage, ROS 2 CDR messages): every message on one
//! topic of type `trajectory_msgs/msg/JointTrajectory`, or a FollowJointTrajectory goal
//! (`control_msgs/action/FollowJointTrajectory_Goal`, or the action's
//! `…_SendGoal_Request`), mapped to a plan by the gate's [`PlanMapper`]. `guardianctl
//! enroll --bag` and `check --bag` use it.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::cdr::{self, CdrError};
use crate::msgs::{FollowJointTrajectoryGoal, JointTrajectory};
use crate::plan::{Plan, PlanError, PlanMapper};

/// The message types a trajectory topic may carry.
pub const TRAJECTORY_TYPES: [&str; 3] = [
    "trajectory_msgs/msg/JointTrajectory",
    "control_msgs/action/FollowJointTrajectory_Goal",
    "control_msgs/action/FollowJointTrajectory_SendGoal_Request",
];

/// A bag could not give plans.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BagError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not a readable MCAP file.
    #[error("{}: not a readable MCAP file: {source}", path.display())]
    Mcap {
        /// The file.
        path: PathBuf,
        /// Why.
        source: mcap::McapError,
    },
    /// No message on the topic.
    #[error("{}: no messages on topic {topic:?}; topics in the bag: {available}", path.display())]
    NoSuchTopic {
        /// The file.
        path: PathBuf,
        /// The topic asked for.
        topic: String,
        /// `topic (type)` of every topic in the bag.
        available: String,
    },
    /// The topic's type is not a trajectory.
    #[error("{}: topic {topic:?} has type {got:?} (encoding {encoding:?}); expected one of {TRAJECTORY_TYPES:?} in cdr", path.display())]
    WrongType {
        /// The file.
        path: PathBuf,
        /// The topic.
        topic: String,
        /// Its schema name.
        got: String,
        /// Its message encoding.
        encoding: String,
    },
    /// A message did not decode.
    #[error("{}: message {index} on {topic:?}: {source}", path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// The topic.
        topic: String,
        /// Message index on the topic (0-based).
        index: usize,
        /// Why.
        source: CdrError,
    },
    /// A message's joints do not fit the robot.
    #[error("{}: message {index} on {topic:?}: {source}", path.display())]
    Joints {
        /// The file.
        path: PathBuf,
        /// The topic.
        topic: String,
        /// Message index on the topic (0-based).
        index: usize,
        /// Why.
        source: Box<PlanError>,
    },
}

#[derive(Deserialize)]
struct SendGoalRequest {
    _goal_id: [u8; 16],
    goal: FollowJointTrajectoryGoal,
}

/// Every message on `topic` of the bag at `path`, as a plan, in log order.
pub fn read_plans(path: &Path, topic: &str, mapper: &PlanMapper) -> Result<Vec<Plan>, BagError> {
    let bytes = std::fs::read(path).map_err(|source| BagError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let mcap_err = |source| BagError::Mcap {
        path: path.to_path_buf(),
        source,
    };
    let mut topics: Vec<(String, String)> = Vec::new();
    let mut plans = Vec::new();
    for message in mcap::MessageStream::new(&bytes).map_err(mcap_err)? {
        let message = message.map_err(mcap_err)?;
        let ch = &message.channel;
        let schema = ch
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        if !topics.iter().any(|(t, _)| t == &ch.topic) {
            topics.push((ch.topic.clone(), schema.clone()));
        }
        if ch.topic != topic {
            continue;
        }
        if ch.message_encoding != "cdr" || !TRAJECTORY_TYPES.contains(&schema.as_str()) {
            return Err(BagError::WrongType {
                path: path.to_path_buf(),
                topic: topic.to_string(),
                got: schema,
                encoding: ch.message_encoding.clone(),
            });
        }
        let index = plans.len();
        let decode_err = |source| BagError::Decode {
            path: path.to_path_buf(),
            topic: topic.to_string(),
            index,
            source,
        };
        let trajectory: JointTrajectory = match schema.as_str() {
            "trajectory_msgs/msg/JointTrajectory" => {
                cdr::decode(&message.data).map_err(decode_err)?
            }
            "control_msgs/action/FollowJointTrajectory_Goal" => {
                cdr::decode::<FollowJointTrajectoryGoal>(&message.data)
                    .map_err(decode_err)?
                    .trajectory
            }
            _ => {
                cdr::decode::<SendGoalRequest>(&message.data)
                    .map_err(decode_err)?
                    .goal
                    .trajectory
            }
        };
        plans.push(mapper.map(&trajectory).map_err(|source| BagError::Joints {
            path: path.to_path_buf(),
            topic: topic.to_string(),
            index,
            source: Box::new(source),
        })?);
    }
    if plans.is_empty() {
        return Err(BagError::NoSuchTopic {
            path: path.to_path_buf(),
            topic: topic.to_string(),
            available: if topics.is_empty() {
                "none".into()
            } else {
                topics
                    .iter()
                    .map(|(t, s)| format!("{t} ({s})"))
                    .collect::<Vec<_>>()
                    .join(", ")
            },
        });
    }
    Ok(plans)
}

/// Write `(topic, message type, CDR bytes)` messages as a rosbag2-style MCAP file (profile
/// `ros2`, `ros2msg` schemas, `cdr` channels, one message a millisecond): what
/// [`read_plans`] reads, for tests and tools that make recordings.
pub fn write_bag(path: &Path, messages: &[(&str, &str, Vec<u8>)]) -> Result<(), mcap::McapError> {
    let file = std::io::BufWriter::new(std::fs::File::create(path)?);
    let mut w = mcap::WriteOptions::new().profile("ros2").create(file)?;
    let mut channels = std::collections::BTreeMap::new();
    for (seq, (topic, schema, data)) in messages.iter().enumerate() {
        let id = match channels.get(*topic) {
            Some(&id) => id,
            None => {
                let s = w.add_schema(schema, "ros2msg", b"")?;
                let id = w.add_channel(s, topic, "cdr", &std::collections::BTreeMap::new())?;
                channels.insert(topic.to_string(), id);
                id
            }
        };
        let t = 1_700_000_000_000_000_000 + seq as u64 * 1_000_000;
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: id,
                sequence: seq as u32,
                log_time: t,
                publish_time: t,
            },
            data,
        )?;
    }
    w.finish()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{JointTrajectoryPoint, StringMsg};
    use crate::plan::ToolSource;
    use guardian_robot::kinematics::RobotDescription;

    fn trajectory(names: &[String], q: f64) -> JointTrajectory {
        JointTrajectory {
            joint_names: names.to_vec(),
            points: (0..3)
                .map(|i| JointTrajectoryPoint {
                    positions: names.iter().map(|_| q + 0.01 * i as f64).collect(),
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn reads_trajectories_goals_and_names_the_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plans.mcap");
        let mapper = PlanMapper::new(
            &RobotDescription::named("panda").unwrap(),
            ToolSource::PenHeight,
        );
        let names = mapper.joint_names().to_vec();
        let goal = FollowJointTrajectoryGoal {
            trajectory: trajectory(&names, 0.2),
            ..Default::default()
        };
        let mut request = vec![0x00, 0x01, 0x00, 0x00];
        request.extend([7u8; 16]);
        request.extend(&cdr::encode(&goal).unwrap()[4..]);
        write_bag(
            &path,
            &[
                (
                    "/plans",
                    TRAJECTORY_TYPES[0],
                    cdr::encode(&trajectory(&names, 0.1)).unwrap(),
                ),
                (
                    "/chatter",
                    "std_msgs/msg/String",
                    cdr::encode(&StringMsg { data: "hi".into() }).unwrap(),
                ),
                ("/goals", TRAJECTORY_TYPES[1], cdr::encode(&goal).unwrap()),
                (
                    "/plans",
                    TRAJECTORY_TYPES[0],
                    cdr::encode(&trajectory(&names, 0.3)).unwrap(),
                ),
                ("/send_goal", TRAJECTORY_TYPES[2], request),
            ],
        )
        .unwrap();
        let plans = read_plans(&path, "/plans", &mapper).unwrap();
        assert_eq!(plans.len(), 2);
        assert_eq!(plans[0].data[0], 0.1f32);
        assert_eq!(plans[1].data[0], 0.3f32);
        let goals = read_plans(&path, "/goals", &mapper).unwrap();
        assert_eq!(goals[0], mapper.map(&goal.trajectory).unwrap());
        let sent = read_plans(&path, "/send_goal", &mapper).unwrap();
        assert_eq!(sent, goals);

        let e = read_plans(&path, "/nothing", &mapper).unwrap_err();
        assert!(matches!(e, BagError::NoSuchTopic { .. }), "{e}");
        assert!(
            e.to_string().contains("/chatter (std_msgs/msg/String)"),
            "{e}"
        );
        let e = read_plans(&path, "/chatter", &mapper).unwrap_err();
        assert!(
            matches!(e, BagError::WrongType { ref got, .. } if got == "std_msgs/msg/String"),
            "{e}"
        );
        let not_mcap = dir.path().join("x.mcap");
        std::fs::write(&not_mcap, b"not an mcap file").unwrap();
        assert!(matches!(
            read_plans(&not_mcap, "/plans", &mapper),
            Err(BagError::Mcap { .. })
        ));
    }
}
