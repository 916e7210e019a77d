//! A serial chain read from a URDF with urdf-rs: the movable (revolute, prismatic) joints
//! from a base link to a tip link, fixed joints composed into the next joint's origin or
//! into the flange.

use guardian_shared::trajectory::{JointLimits, MAX_JOINTS};
use nalgebra::Vector3;

use super::{Frame, Joint, JointKind, Robot, sha256};

/// The Panda's URDF shipped with guardian (kinematic only), `models/robots/panda.urdf`.
pub const PANDA_URDF: &str = include_str!("../../../models/robots/panda.urdf");
/// The UR5e's URDF shipped with guardian (kinematic only, from UR's standard DH table),
/// `models/robots/ur5e.urdf`.
pub const UR5E_URDF: &str = include_str!("../../../models/robots/ur5e.urdf");

/// Building a [`Robot`] from a URDF failed. Every variant names the URDF element at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
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
    /// A link named in the description (base or tip) is not in the URDF.
    #[error("link {link:?} ({role} link) is not in the URDF")]
    UnknownLink {
        /// The link name.
        link: String,
        /// `base` or `tip`.
        role: &'static str,
    },
    /// The tip link is not below the base link.
    #[error("link {tip:?} is not below link {base:?}: no chain between them")]
    NoChain {
        /// The base link.
        base: String,
        /// The tip link.
        tip: String,
    },
    /// Walking from the root without a tip link, a link has more than one child joint.
    #[error(
        "link {link:?} has {children} child joints; a serial chain is expected (name a tip-link)"
    )]
    Branching {
        /// The link name.
        link: String,
        /// Number of child joints.
        children: usize,
    },
    /// The chain has no movable joint, or more than [`MAX_JOINTS`].
    #[error("the chain has {got} movable joints, expected 1..={max}")]
    JointCount {
        /// Most joints supported.
        max: usize,
        /// Movable joints found.
        got: usize,
    },
    /// A joint type the chain cannot hold (floating, planar, spherical).
    #[error("joint {joint:?}: unsupported {kind} joint")]
    Unsupported {
        /// The joint name.
        joint: String,
        /// What was found.
        kind: String,
    },
    /// A continuous joint: it has no limits, and trajectories are validated against limits.
    #[error(
        "joint {joint:?}: continuous joint without limits; make it revolute with <limit lower upper>"
    )]
    Unlimited {
        /// The joint name.
        joint: String,
    },
    /// A joint's limits are not a finite range (`lower <= upper`).
    #[error("joint {joint:?}: <limit lower={lower} upper={upper}> is not a finite range")]
    Limits {
        /// The joint name.
        joint: String,
        /// Lower limit.
        lower: f64,
        /// Upper limit.
        upper: f64,
    },
    /// A number of a joint's element is not finite.
    #[error("joint {joint:?}: <{element}> has a non-finite value")]
    NonFinite {
        /// The joint name.
        joint: String,
        /// `origin` or `axis`.
        element: &'static str,
    },
    /// A joint axis of (near) zero length.
    #[error("joint {joint:?}: <axis xyz={axis:?}> has no direction")]
    Axis {
        /// The joint name.
        joint: String,
        /// The axis in the URDF.
        axis: [f64; 3],
    },
}

impl Robot {
    /// Parse the shipped Panda URDF with the shipped description's links and tool
    /// ([`Robot::panda`] builds the same chain without parsing).
    pub fn from_embedded_urdf() -> Result<Self, UrdfLoadError> {
        Self::from_urdf_chain_with_tool(
            PANDA_URDF,
            "panda",
            None,
            Some("panda_link8"),
            Frame::from_xyz_rpy([0.0, 0.0, super::PEN_LENGTH], [0.0, 0.0, super::PEN_YAW]),
        )
    }

    /// Parse a URDF as a serial chain from its root to its one leaf; the first fixed joint
    /// after the last movable one is the flange, the fixed joints after it make up the tool
    /// (identity if none). The robot is named after the URDF's `<robot name>`.
    pub fn from_urdf_str(text: &str) -> Result<Self, UrdfLoadError> {
        let robot = parse(text)?;
        let chain = walk_down(&robot, &root(&robot)?)?;
        let name = robot.name.clone();
        build(text, name, &chain, None)
    }

    /// Parse the serial chain of `text` from `base` (the root link if `None`) to `tip` (the
    /// one leaf if `None`; branches off the chain are allowed when a tip is named). Every
    /// fixed joint after the last movable one is composed into the flange; the tool is the
    /// identity ([`Robot::with_tool_frame`] sets another; [`Robot::from_urdf_chain_with_tool`]
    /// builds the robot with its tool at once).
    pub fn from_urdf_chain(
        text: &str,
        name: &str,
        base: Option<&str>,
        tip: Option<&str>,
    ) -> Result<Self, UrdfLoadError> {
        Self::from_urdf_chain_with_tool(text, name, base, tip, Frame::identity())
    }

    /// [`Robot::from_urdf_chain`] with the tool frame (in the flange frame) given, so the
    /// specialised FK is built and verified once, for the robot as it will serve.
    pub fn from_urdf_chain_with_tool(
        text: &str,
        name: &str,
        base: Option<&str>,
        tip: Option<&str>,
        tool: Frame,
    ) -> Result<Self, UrdfLoadError> {
        let robot = parse(text)?;
        let base = match base {
            Some(b) => {
                if !robot.links.iter().any(|l| l.name == b) {
                    return Err(UrdfLoadError::UnknownLink {
                        link: b.to_string(),
                        role: "base",
                    });
                }
                b.to_string()
            }
            None => root(&robot)?,
        };
        let chain = match tip {
            None => walk_down(&robot, &base)?,
            Some(tip) => walk_up(&robot, &base, tip)?,
        };
        build(text, name.to_string(), &chain, Some(tool))
    }
}

fn parse(text: &str) -> Result<urdf_rs::Robot, UrdfLoadError> {
    urdf_rs::read_from_string(text).map_err(|e| UrdfLoadError::Parse(e.to_string()))
}

fn root(robot: &urdf_rs::Robot) -> Result<String, UrdfLoadError> {
    let roots: Vec<&str> = robot
        .links
        .iter()
        .map(|l| l.name.as_str())
        .filter(|name| !robot.joints.iter().any(|j| j.child.link == *name))
        .collect();
    match roots.as_slice() {
        [r] => Ok((*r).to_string()),
        _ => Err(UrdfLoadError::Root { roots: roots.len() }),
    }
}

/// The joints from `link` down to the one leaf.
fn walk_down<'a>(
    robot: &'a urdf_rs::Robot,
    link: &str,
) -> Result<Vec<&'a urdf_rs::Joint>, UrdfLoadError> {
    let mut link = link.to_string();
    let mut chain = Vec::new();
    loop {
        let children: Vec<&urdf_rs::Joint> = robot
            .joints
            .iter()
            .filter(|j| j.parent.link == link)
            .collect();
        match children.as_slice() {
            [] => return Ok(chain),
            [j] => {
                chain.push(*j);
                link = j.child.link.clone();
            }
            _ => {
                return Err(UrdfLoadError::Branching {
                    link,
                    children: children.len(),
                });
            }
        }
        if chain.len() > robot.joints.len() {
            // A cycle; urdf-rs does not reject them.
            return Err(UrdfLoadError::Root { roots: 0 });
        }
    }
}

/// The joints from `base` to `tip`, found by walking up from the tip (a tree has one path).
fn walk_up<'a>(
    robot: &'a urdf_rs::Robot,
    base: &str,
    tip: &str,
) -> Result<Vec<&'a urdf_rs::Joint>, UrdfLoadError> {
    if !robot.links.iter().any(|l| l.name == tip) {
        return Err(UrdfLoadError::UnknownLink {
            link: tip.to_string(),
            role: "tip",
        });
    }
    let mut chain = Vec::new();
    let mut link = tip.to_string();
    while link != base {
        let Some(joint) = robot.joints.iter().find(|j| j.child.link == link) else {
            return Err(UrdfLoadError::NoChain {
                base: base.to_string(),
                tip: tip.to_string(),
            });
        };
        chain.push(joint);
        link = joint.parent.link.clone();
        if chain.len() > robot.joints.len() {
            return Err(UrdfLoadError::NoChain {
                base: base.to_string(),
                tip: tip.to_string(),
            });
        }
    }
    chain.reverse();
    Ok(chain)
}

/// The robot of a chain of URDF joints. Without a `given_tool`, the first fixed joint after
/// the last movable one is the flange and the rest the tool; with one, they are all the
/// flange and the tool is the one given.
fn build(
    text: &str,
    name: String,
    chain: &[&urdf_rs::Joint],
    given_tool: Option<Frame>,
) -> Result<Robot, UrdfLoadError> {
    let mut joints: Vec<Joint> = Vec::new();
    let (mut lower, mut upper) = (Vec::new(), Vec::new());
    // Fixed joints seen since the last movable one, composed.
    let mut pending = Frame::identity();
    let mut after_last: Vec<Frame> = Vec::new();
    for joint in chain {
        let xyz = *joint.origin.xyz;
        let rpy = *joint.origin.rpy;
        if xyz.iter().chain(&rpy).any(|v| !v.is_finite()) {
            return Err(UrdfLoadError::NonFinite {
                joint: joint.name.clone(),
                element: "origin",
            });
        }
        let origin = Frame::from_xyz_rpy(xyz, rpy);
        let kind = match joint.joint_type {
            urdf_rs::JointType::Revolute => JointKind::Revolute,
            urdf_rs::JointType::Prismatic => JointKind::Prismatic,
            urdf_rs::JointType::Continuous => {
                return Err(UrdfLoadError::Unlimited {
                    joint: joint.name.clone(),
                });
            }
            urdf_rs::JointType::Fixed => {
                pending = pending.compose(&origin);
                after_last.push(origin);
                continue;
            }
            ref other => {
                return Err(UrdfLoadError::Unsupported {
                    joint: joint.name.clone(),
                    kind: format!("{other:?}").to_lowercase(),
                });
            }
        };
        let axis = *joint.axis.xyz;
        if axis.iter().any(|v| !v.is_finite()) {
            return Err(UrdfLoadError::NonFinite {
                joint: joint.name.clone(),
                element: "axis",
            });
        }
        let a = Vector3::from(axis);
        if a.norm() < 1e-9 {
            return Err(UrdfLoadError::Axis {
                joint: joint.name.clone(),
                axis,
            });
        }
        let (lo, hi) = (joint.limit.lower, joint.limit.upper);
        if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
            return Err(UrdfLoadError::Limits {
                joint: joint.name.clone(),
                lower: lo,
                upper: hi,
            });
        }
        // A unit axis exactly +z stays exactly +z (the bit-stable fast path).
        let axis = if axis == [0.0, 0.0, 1.0] {
            Vector3::z()
        } else {
            a.normalize()
        };
        let velocity = joint.limit.velocity;
        joints.push(Joint {
            name: joint.name.clone(),
            kind,
            // Bit-identical to `origin` when no fixed joint came before it.
            origin: if after_last.is_empty() {
                origin
            } else {
                pending.compose(&origin)
            },
            axis,
            velocity: (velocity.is_finite() && velocity > 0.0).then_some(velocity),
        });
        lower.push(lo);
        upper.push(hi);
        pending = Frame::identity();
        after_last.clear();
    }
    if joints.is_empty() || joints.len() > MAX_JOINTS {
        return Err(UrdfLoadError::JointCount {
            max: MAX_JOINTS,
            got: joints.len(),
        });
    }
    let (flange, tool) = match given_tool {
        None => {
            let flange = after_last.first().copied().unwrap_or_else(Frame::identity);
            let tool = after_last
                .iter()
                .skip(1)
                .fold(Frame::identity(), |acc, f| acc.compose(f));
            (flange, tool)
        }
        Some(tool) => {
            // One fixed joint is taken as is (bit-identical to the published numbers).
            let flange = match after_last.as_slice() {
                [] => Frame::identity(),
                [one] => *one,
                _ => pending,
            };
            (flange, tool)
        }
    };
    let limits = JointLimits::new(lower, upper).map_err(|_| UrdfLoadError::JointCount {
        max: MAX_JOINTS,
        got: joints.len(),
    })?;
    Ok(Robot {
        name,
        joints,
        flange,
        tool,
        limits,
        urdf_sha256: sha256(text.as_bytes()),
        position_fk: None,
    }
    .with_position_fk())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::READY_POSE;

    #[test]
    fn urdf_parse_matches_the_published_numbers() {
        let parsed = Robot::from_embedded_urdf().expect("shipped URDF parses");
        let builtin = Robot::panda();
        assert_eq!(parsed.limits, builtin.limits);
        assert_eq!(parsed.joints.len(), 7);
        for (a, b) in parsed.joints.iter().zip(builtin.joints.iter()) {
            assert_eq!(a.name, b.name);
            assert_eq!(a.kind, b.kind);
            assert_eq!(a.axis, b.axis);
            assert_eq!(a.velocity, b.velocity);
            assert!((a.origin.rotation - b.origin.rotation).amax() < 1e-15);
            assert!((a.origin.translation - b.origin.translation).amax() < 1e-15);
        }
        assert!((parsed.tool.rotation - builtin.tool.rotation).amax() < 1e-15);
        assert!((parsed.tool.translation - builtin.tool.translation).amax() < 1e-15);
        assert_eq!(parsed.urdf_sha256, builtin.urdf_sha256);
        let f = parsed.flange(&READY_POSE);
        assert!((f.translation - Vector3::new(0.3069, 0.0, 0.5903)).norm() < 1e-4);
        // Root to leaf: the URDF's own pen joint becomes the tool.
        let whole = Robot::from_urdf_str(PANDA_URDF).expect("root to leaf");
        assert!((whole.tool.translation - builtin.tool.translation).amax() < 1e-15);
        assert!((whole.tool.rotation - builtin.tool.rotation).amax() < 1e-15);
    }

    #[test]
    fn malformed_urdf_is_a_typed_error_naming_the_element() {
        assert!(matches!(
            Robot::from_urdf_str("<robot"),
            Err(UrdfLoadError::Parse(_))
        ));
        let chain = |text: &str, tip: &str| Robot::from_urdf_chain(text, "t", None, Some(tip));
        assert_eq!(
            chain(PANDA_URDF, "nope"),
            Err(UrdfLoadError::UnknownLink {
                link: "nope".into(),
                role: "tip"
            })
        );
        assert!(matches!(
            Robot::from_urdf_chain(PANDA_URDF, "t", Some("panda_link8"), Some("panda_link2")),
            Err(UrdfLoadError::NoChain { .. })
        ));
        let continuous = PANDA_URDF.replacen(
            r#"<joint name="panda_joint3" type="revolute">"#,
            r#"<joint name="panda_joint3" type="continuous">"#,
            1,
        );
        assert_eq!(
            chain(&continuous, "panda_link8"),
            Err(UrdfLoadError::Unlimited {
                joint: "panda_joint3".into()
            })
        );
        let nan = PANDA_URDF.replacen(r#"xyz="0 -0.316 0""#, r#"xyz="0 NaN 0""#, 1);
        assert_eq!(
            chain(&nan, "panda_link8"),
            Err(UrdfLoadError::NonFinite {
                joint: "panda_joint3".into(),
                element: "origin"
            })
        );
        let zero_axis = PANDA_URDF.replacen(r#"<axis xyz="0 0 1"/>"#, r#"<axis xyz="0 0 0"/>"#, 1);
        assert!(matches!(
            chain(&zero_axis, "panda_link8"),
            Err(UrdfLoadError::Axis { .. })
        ));
        let floating = PANDA_URDF.replacen(
            r#"<joint name="panda_joint3" type="revolute">"#,
            r#"<joint name="panda_joint3" type="floating">"#,
            1,
        );
        assert!(matches!(
            chain(&floating, "panda_link8"),
            Err(UrdfLoadError::Unsupported { .. })
        ));
        // A second child of link 3: branching without a tip, fine with one.
        let branch = PANDA_URDF.replacen(
            "</robot>",
            r#"<link name="camera"/><joint name="cam" type="fixed"><parent link="panda_link3"/><child link="camera"/></joint></robot>"#,
            1,
        );
        assert!(matches!(
            Robot::from_urdf_str(&branch),
            Err(UrdfLoadError::Branching { .. })
        ));
        assert_eq!(chain(&branch, "panda_link8").map(|r| r.joints()), Ok(7));
        // Seventeen joints: too many.
        let mut many = String::from(r#"<robot name="m"><link name="l0"/>"#);
        for i in 1..=17 {
            many += &format!(
                r#"<link name="l{i}"/><joint name="j{i}" type="revolute"><parent link="l{}"/><child link="l{i}"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"#,
                i - 1
            );
        }
        many += "</robot>";
        assert_eq!(
            Robot::from_urdf_str(&many),
            Err(UrdfLoadError::JointCount { max: 16, got: 17 })
        );
        assert_eq!(chain(&many, "l16").map(|r| r.joints()), Ok(16));
        let bad_limits = PANDA_URDF.replacen(
            r#"lower="-2.8973" upper="2.8973""#,
            r#"lower="1" upper="-1""#,
            1,
        );
        assert!(matches!(
            chain(&bad_limits, "panda_link8"),
            Err(UrdfLoadError::Limits { .. })
        ));
    }
}
