//! A serial chain read from a URDF with urdf-rs: revolute joints about z, then the fixed
//! flange, then fixed joints composed into the tool frame.

use guardian_shared::trajectory::JOINTS;

use super::{Frame, Panda};

/// The robot model shipped with guardian (kinematic only).
pub const PANDA_URDF: &str = include_str!("../../panda.urdf");

/// Building a [`Panda`] from a URDF failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum UrdfLoadError {
    /// urdf-rs could not parse the text.
    #[error("cannot parse URDF: {0}")]
    Parse(String),
    /// No single root link (a link that is nobody's child) was found.
    #[error("URDF has {roots} root links, expected 1")]
    Root {
        /// Number of root links found.
        roots: usize,
    },
    /// A link has more than one child joint: not a serial chain.
    #[error("link {link} has {children} child joints; a serial chain is expected")]
    Branching {
        /// The link name.
        link: String,
        /// Number of child joints.
        children: usize,
    },
    /// The chain does not have 7 revolute joints.
    #[error("expected {expected} revolute joints, got {got}")]
    JointCount {
        /// Revolute joints expected.
        expected: usize,
        /// Revolute joints found.
        got: usize,
    },
    /// A joint type other than revolute or fixed, or a fixed joint between revolute ones.
    #[error("joint {joint}: unsupported {kind} here")]
    Unsupported {
        /// The joint name.
        joint: String,
        /// What was found.
        kind: String,
    },
    /// A revolute joint does not rotate about its z axis.
    #[error("joint {joint}: axis {axis:?} is not +z")]
    Axis {
        /// The joint name.
        joint: String,
        /// The axis in the URDF.
        axis: [f64; 3],
    },
    /// No fixed joint after the last revolute joint (the flange).
    #[error("no fixed flange joint after the last revolute joint")]
    NoFlange,
}

impl Panda {
    /// Parse the shipped `panda.urdf` ([`PANDA_URDF`]).
    pub fn from_embedded_urdf() -> Result<Self, UrdfLoadError> {
        Self::from_urdf_str(PANDA_URDF)
    }

    /// Parse a URDF: a serial chain of 7 revolute joints about z, then one fixed joint (the
    /// flange), then optionally more fixed joints composed into the tool frame (identity if
    /// none).
    pub fn from_urdf_str(text: &str) -> Result<Self, UrdfLoadError> {
        let robot =
            urdf_rs::read_from_string(text).map_err(|e| UrdfLoadError::Parse(e.to_string()))?;
        let roots: Vec<&str> = robot
            .links
            .iter()
            .map(|l| l.name.as_str())
            .filter(|name| !robot.joints.iter().any(|j| j.child.link == *name))
            .collect();
        if roots.len() != 1 {
            return Err(UrdfLoadError::Root { roots: roots.len() });
        }
        let mut link = roots[0].to_string();
        let mut revolute: Vec<(Frame, f64, f64)> = Vec::new();
        let mut fixed_after: Vec<Frame> = Vec::new();
        loop {
            let children: Vec<&urdf_rs::Joint> = robot
                .joints
                .iter()
                .filter(|j| j.parent.link == link)
                .collect();
            let joint = match children.as_slice() {
                [] => break,
                [j] => *j,
                _ => {
                    return Err(UrdfLoadError::Branching {
                        link,
                        children: children.len(),
                    });
                }
            };
            let origin = Frame::from_xyz_rpy(*joint.origin.xyz, *joint.origin.rpy);
            match joint.joint_type {
                urdf_rs::JointType::Revolute => {
                    if !fixed_after.is_empty() {
                        return Err(UrdfLoadError::Unsupported {
                            joint: joint.name.clone(),
                            kind: "revolute joint after a fixed joint".into(),
                        });
                    }
                    let axis = *joint.axis.xyz;
                    if axis != [0.0, 0.0, 1.0] {
                        return Err(UrdfLoadError::Axis {
                            joint: joint.name.clone(),
                            axis,
                        });
                    }
                    revolute.push((origin, joint.limit.lower, joint.limit.upper));
                }
                urdf_rs::JointType::Fixed => {
                    if revolute.is_empty() {
                        return Err(UrdfLoadError::Unsupported {
                            joint: joint.name.clone(),
                            kind: "fixed joint before the first revolute joint".into(),
                        });
                    }
                    fixed_after.push(origin);
                }
                ref other => {
                    return Err(UrdfLoadError::Unsupported {
                        joint: joint.name.clone(),
                        kind: format!("{other:?} joint"),
                    });
                }
            }
            link = joint.child.link.clone();
        }
        if revolute.len() != JOINTS {
            return Err(UrdfLoadError::JointCount {
                expected: JOINTS,
                got: revolute.len(),
            });
        }
        let flange = *fixed_after.first().ok_or(UrdfLoadError::NoFlange)?;
        let tool = fixed_after[1..]
            .iter()
            .fold(Frame::identity(), |acc, f| acc.compose(f));
        let mut joints = [Frame::identity(); JOINTS];
        let mut q_min = [0.0; JOINTS];
        let mut q_max = [0.0; JOINTS];
        for (i, (origin, lo, hi)) in revolute.into_iter().enumerate() {
            joints[i] = origin;
            q_min[i] = lo;
            q_max[i] = hi;
        }
        Ok(Self {
            joints,
            flange,
            tool,
            q_min,
            q_max,
            position_fk: None,
        }
        .with_position_fk())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::READY_POSE;
    use nalgebra::Vector3;

    #[test]
    fn urdf_parse_matches_the_published_numbers() {
        let parsed = Panda::from_embedded_urdf().expect("shipped URDF parses");
        let builtin = Panda::default();
        assert_eq!(parsed.q_min, builtin.q_min);
        assert_eq!(parsed.q_max, builtin.q_max);
        for (a, b) in parsed.joints.iter().zip(builtin.joints.iter()) {
            assert!((a.rotation - b.rotation).amax() < 1e-15);
            assert!((a.translation - b.translation).amax() < 1e-15);
        }
        assert!((parsed.tool.rotation - builtin.tool.rotation).amax() < 1e-15);
        assert!((parsed.tool.translation - builtin.tool.translation).amax() < 1e-15);
        let f = parsed.flange(&READY_POSE);
        assert!((f.translation - Vector3::new(0.3069, 0.0, 0.5903)).norm() < 1e-4);
    }

    #[test]
    fn malformed_urdf_is_a_typed_error() {
        assert!(matches!(
            Panda::from_urdf_str("<robot"),
            Err(UrdfLoadError::Parse(_))
        ));
        let six = PANDA_URDF.replace(
            r#"<joint name="panda_joint7" type="revolute">"#,
            r#"<joint name="panda_joint7" type="fixed">"#,
        );
        assert!(matches!(
            Panda::from_urdf_str(&six),
            Err(UrdfLoadError::JointCount {
                expected: 7,
                got: 6
            })
        ));
        let tilted = PANDA_URDF.replacen(r#"<axis xyz="0 0 1"/>"#, r#"<axis xyz="1 0 0"/>"#, 1);
        assert!(matches!(
            Panda::from_urdf_str(&tilted),
            Err(UrdfLoadError::Axis { .. })
        ));
    }
}
