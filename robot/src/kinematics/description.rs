//! The robot description file: which URDF, which links bound the chain, the tool frame, the
//! home seed and the workcell defaults of one arm (`models/robots/<name>.toml`, format in
//! `docs/robots.md`), and the robots built into guardian.

use std::path::{Path, PathBuf};

use guardian_shared::workcell::{InvalidWorkcell, Workcell};
use serde::Deserialize;

use super::urdf::{PANDA_URDF, UR5E_URDF, UrdfLoadError};
use super::{Frame, JointVector, MAX_JOINTS, Robot, joint_vector};

/// The robot a daemon or the lab uses when none is named.
pub const DEFAULT_ROBOT: &str = "panda";

/// The descriptions built into guardian: name, description text, URDF text.
const BUILTIN: [(&str, &str, &str); 2] = [
    (
        "panda",
        include_str!("../../../models/robots/panda.toml"),
        PANDA_URDF,
    ),
    (
        "ur5e",
        include_str!("../../../models/robots/ur5e.toml"),
        UR5E_URDF,
    ),
];

/// Names of the built-in robots ([`RobotDescription::named`]).
pub const BUILTIN_ROBOTS: [&str; 2] = [BUILTIN[0].0, BUILTIN[1].0];

/// The tool frame in the flange frame, as written in a description (`[tool]`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolSpec {
    /// Translation (m).
    pub xyz: [f64; 3],
    /// Roll, pitch, yaw (rad), as a URDF origin.
    #[serde(default)]
    pub rpy: [f64; 3],
}

/// The file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct DescriptionFile {
    name: String,
    urdf: PathBuf,
    #[serde(default)]
    base_link: Option<String>,
    #[serde(default)]
    tip_link: Option<String>,
    tool: ToolSpec,
    home_seed: Vec<f64>,
    #[serde(default)]
    workcell: Option<toml::Table>,
}

/// Where a description came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RobotSource {
    /// Built into guardian under this name.
    Builtin(&'static str),
    /// Read from this description file.
    File(PathBuf),
}

impl std::fmt::Display for RobotSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Builtin(name) => write!(f, "built-in robot {name:?}"),
            Self::File(path) => write!(f, "{}", path.display()),
        }
    }
}

/// One arm as guardian uses it: the chain with its tool, where drawing starts from, and the
/// workcell rules' defaults.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotDescription {
    /// The chain with the description's tool frame.
    pub robot: Robot,
    /// The tool as written.
    pub tool: ToolSpec,
    /// Seed of the home-pose IK (slots past the joints 0).
    pub home_seed: JointVector,
    /// Workcell defaults for this robot.
    pub workcell: Workcell,
    /// Where it came from.
    pub source: RobotSource,
}

/// A robot description could not be loaded. Every variant names the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RobotLoadError {
    /// Neither a built-in robot nor an existing file.
    #[error("unknown robot {name:?}: not one of {BUILTIN_ROBOTS:?} and no such description file")]
    Unknown {
        /// What was asked for.
        name: String,
    },
    /// A file could not be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The description is not valid TOML of the expected shape.
    #[error("{robot}: {message}")]
    Description {
        /// The description.
        robot: RobotSource,
        /// What is wrong (names the key).
        message: String,
    },
    /// The URDF is malformed or not a supported chain.
    #[error("{}: {error}", urdf.display())]
    Urdf {
        /// The URDF file.
        urdf: PathBuf,
        /// What is wrong, naming the element.
        error: UrdfLoadError,
    },
    /// `home-seed` does not have one value per joint, or is outside the limits.
    #[error("{robot}: home-seed {message}")]
    HomeSeed {
        /// The description.
        robot: RobotSource,
        /// What is wrong.
        message: String,
    },
    /// The `[tool]` frame has a non-finite value.
    #[error("{robot}: [tool] values must be finite")]
    Tool {
        /// The description.
        robot: RobotSource,
    },
    /// The `[workcell]` defaults are unusable.
    #[error("{robot}: [workcell]: {error}")]
    Workcell {
        /// The description.
        robot: RobotSource,
        /// What is wrong.
        error: InvalidWorkcell,
    },
}

impl RobotDescription {
    /// A built-in robot ([`BUILTIN_ROBOTS`]), needing no file at run time.
    pub fn named(name: &str) -> Result<Self, RobotLoadError> {
        let (builtin, text, urdf) =
            BUILTIN
                .iter()
                .find(|(n, _, _)| *n == name)
                .ok_or_else(|| RobotLoadError::Unknown {
                    name: name.to_string(),
                })?;
        // The URDF is built in too; errors name it by its path in the repository.
        Self::parse(text, RobotSource::Builtin(builtin), |_| {
            Ok((
                PathBuf::from(format!("models/robots/{builtin}.urdf")),
                (*urdf).to_string(),
            ))
        })
    }

    /// A built-in robot by name, else a description file at that path.
    pub fn resolve(name_or_path: &str) -> Result<Self, RobotLoadError> {
        if BUILTIN_ROBOTS.contains(&name_or_path) {
            return Self::named(name_or_path);
        }
        let path = Path::new(name_or_path);
        if path.is_file() {
            return Self::load(path);
        }
        Err(RobotLoadError::Unknown {
            name: name_or_path.to_string(),
        })
    }

    /// Read a description file; its `urdf` path is relative to the file's folder.
    pub fn load(path: &Path) -> Result<Self, RobotLoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| RobotLoadError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Self::parse(&text, RobotSource::File(path.to_path_buf()), |file| {
            let urdf = dir.join(file);
            let text = std::fs::read_to_string(&urdf).map_err(|source| RobotLoadError::Read {
                path: urdf.clone(),
                source,
            })?;
            Ok((urdf, text))
        })
    }

    fn parse(
        text: &str,
        source: RobotSource,
        read_urdf: impl FnOnce(&Path) -> Result<(PathBuf, String), RobotLoadError>,
    ) -> Result<Self, RobotLoadError> {
        let file: DescriptionFile =
            toml::from_str(text).map_err(|e| RobotLoadError::Description {
                robot: source.clone(),
                message: e.to_string(),
            })?;
        let (urdf_path, urdf_text) = read_urdf(&file.urdf)?;
        let tool = file.tool;
        if tool.xyz.iter().chain(&tool.rpy).any(|v| !v.is_finite()) {
            return Err(RobotLoadError::Tool { robot: source });
        }
        // Built with its tool at once: the specialised FK is built and verified once.
        let robot = Robot::from_urdf_chain_with_tool(
            &urdf_text,
            &file.name,
            file.base_link.as_deref(),
            file.tip_link.as_deref(),
            Frame::from_xyz_rpy(tool.xyz, tool.rpy),
        )
        .map_err(|error| RobotLoadError::Urdf {
            urdf: urdf_path,
            error,
        })?;
        let n = robot.joints();
        if file.home_seed.len() != n {
            return Err(RobotLoadError::HomeSeed {
                robot: source,
                message: format!("has {} values, the chain {n} joints", file.home_seed.len()),
            });
        }
        let home_seed = joint_vector(&file.home_seed[..n.min(MAX_JOINTS)]);
        let margin = robot.limit_margin(&home_seed);
        if margin.is_nan() || margin < 0.0 {
            return Err(RobotLoadError::HomeSeed {
                robot: source,
                message: "is outside the joint limits".to_string(),
            });
        }
        let workcell = workcell_defaults(file.workcell, &source)?;
        Ok(Self {
            robot,
            tool,
            home_seed,
            workcell,
            source,
        })
    }

    /// This robot's workcell with `overrides` (a `[workcell]` table, kebab-case keys)
    /// applied key by key on top of the description's defaults.
    pub fn workcell_with(
        &self,
        overrides: Option<&toml::Table>,
    ) -> Result<Workcell, WorkcellOverrideError> {
        apply_workcell_overrides(self.workcell, overrides)
    }
}

/// A `[workcell]` override table does not fit.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WorkcellOverrideError {
    /// An unknown key or a value of the wrong type.
    #[error(transparent)]
    Key(#[from] Box<toml::de::Error>),
    /// The resulting workcell is unusable.
    #[error(transparent)]
    Invalid(#[from] guardian_shared::workcell::InvalidWorkcell),
    /// The base workcell could not be written as a table (not expected).
    #[error(transparent)]
    Encode(#[from] toml::ser::Error),
}

/// `base` with `overrides` (a `[workcell]` table, kebab-case keys) applied key by key,
/// checked ([`Workcell::validate`]).
pub fn apply_workcell_overrides(
    base: Workcell,
    overrides: Option<&toml::Table>,
) -> Result<Workcell, WorkcellOverrideError> {
    let Some(overrides) = overrides else {
        return Ok(base);
    };
    let mut table = toml::Table::try_from(base)?;
    for (k, v) in overrides {
        table.insert(k.clone(), v.clone());
    }
    let cell: Workcell = table.try_into().map_err(Box::new)?;
    cell.validate()?;
    Ok(cell)
}

fn workcell_defaults(
    table: Option<toml::Table>,
    source: &RobotSource,
) -> Result<Workcell, RobotLoadError> {
    let cell: Workcell = match table {
        None => Workcell::default(),
        Some(t) => t
            .try_into()
            .map_err(|e: toml::de::Error| RobotLoadError::Description {
                robot: source.clone(),
                message: format!("[workcell]: {e}"),
            })?,
    };
    cell.validate().map_err(|error| RobotLoadError::Workcell {
        robot: source.clone(),
        error,
    })?;
    Ok(cell)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{PANDA_JOINTS, READY_POSE};
    use nalgebra::{Matrix4, Vector3};
    use std::f64::consts::{FRAC_PI_2, PI};

    #[test]
    fn the_builtin_panda_is_the_published_one_bit_for_bit() {
        let d = RobotDescription::named("panda").unwrap();
        assert_eq!(d.robot, Robot::panda());
        assert_eq!(d.home_seed, READY_POSE);
        assert_eq!(d.workcell, Workcell::default());
        assert_eq!(d.robot.joints(), PANDA_JOINTS);
        assert_eq!(d.robot.channels(), 8);
    }

    /// The DH product of the issue: Rz(q) Tz(d) Tx(a) Rx(alpha) per joint.
    fn dh_flange(q: &[f64; 6]) -> Matrix4<f64> {
        let d = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996];
        let a = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0];
        let alpha = [FRAC_PI_2, 0.0, 0.0, FRAC_PI_2, -FRAC_PI_2, 0.0];
        let mut t = Matrix4::identity();
        for i in 0..6 {
            let (s, c) = q[i].sin_cos();
            let (sa, ca) = alpha[i].sin_cos();
            #[rustfmt::skip]
            let ti = Matrix4::new(
                c, -s * ca, s * sa, a[i] * c,
                s, c * ca, -c * sa, a[i] * s,
                0.0, sa, ca, d[i],
                0.0, 0.0, 0.0, 1.0,
            );
            t *= ti;
        }
        t
    }

    #[test]
    fn ur5e_fk_matches_the_dh_product() {
        let d = RobotDescription::named("ur5e").unwrap();
        let ur = &d.robot;
        assert_eq!(ur.joints(), 6);
        assert_eq!(ur.channels(), 7);
        assert!(ur.q_max().iter().all(|&v| v == 2.0 * PI));
        assert!(
            ur.position_fk().is_some(),
            "the UR5e's origins are permutations"
        );
        let check = [PI, -FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, -FRAC_PI_2, 0.0];
        let f = ur.flange(&joint_vector(&check));
        assert!(
            (f.translation - Vector3::new(0.4919, 0.1333, 0.4879)).norm() < 1e-4,
            "{}",
            f.translation
        );
        let poses = [
            check,
            [0.0; 6],
            [0.3, -1.2, 1.1, -0.4, 0.9, -2.5],
            [-2.0, -0.5, -1.7, 2.2, -1.1, 3.0],
            [5.9, 1.0, 0.2, -6.0, 0.0, 1.3],
        ];
        for q in &poses {
            let dh = dh_flange(q);
            let f = ur.flange(&joint_vector(q));
            let p = Vector3::new(dh[(0, 3)], dh[(1, 3)], dh[(2, 3)]);
            assert!((f.translation - p).norm() < 1e-12, "{q:?}");
            assert!(
                (f.rotation - dh.fixed_view::<3, 3>(0, 0)).amax() < 1e-12,
                "{q:?}"
            );
            // The pen: 0.15 m along flange z.
            let pen = ur.pen_tip(&joint_vector(q));
            let want = p + dh.fixed_view::<3, 3>(0, 0) * Vector3::new(0.0, 0.0, 0.15);
            assert!((pen.translation - want).norm() < 1e-12);
            assert!((ur.pen_tip_position(&joint_vector(q)) - want).norm() < 1e-12);
        }
    }

    #[test]
    fn bad_descriptions_are_typed_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, text: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            p
        };
        write("arm.urdf", UR5E_URDF);
        let good =
            include_str!("../../../models/robots/ur5e.toml").replace("ur5e.urdf", "arm.urdf");
        let ok = write("ok.toml", &good);
        let d = RobotDescription::load(&ok).unwrap();
        assert_eq!(d.robot, RobotDescription::named("ur5e").unwrap().robot);
        assert_eq!(d.source, RobotSource::File(ok.clone()));
        assert_eq!(
            RobotDescription::resolve(ok.to_str().unwrap())
                .unwrap()
                .robot
                .joints(),
            6
        );

        let e = RobotDescription::load(&write("typo.toml", &good.replace("tip-link", "tip-lnk")))
            .unwrap_err();
        assert!(matches!(e, RobotLoadError::Description { .. }), "{e}");
        assert!(e.to_string().contains("typo.toml"), "{e}");

        let e = RobotDescription::load(&write("tip.toml", &good.replace("\"flange\"", "\"hand\"")))
            .unwrap_err();
        assert!(
            matches!(
                &e,
                RobotLoadError::Urdf {
                    error: UrdfLoadError::UnknownLink { .. },
                    ..
                }
            ),
            "{e}"
        );
        assert!(
            e.to_string().contains("arm.urdf") && e.to_string().contains("hand"),
            "{e}"
        );

        let e = RobotDescription::load(&write(
            "seed.toml",
            &good.replace("-1.5707963267948966, 0.0]", "-1.5707963267948966]"),
        ))
        .unwrap_err();
        assert!(matches!(e, RobotLoadError::HomeSeed { .. }), "{e}");

        let e = RobotDescription::load(&write(
            "missing.toml",
            &good.replace("arm.urdf", "none.urdf"),
        ))
        .unwrap_err();
        assert!(matches!(e, RobotLoadError::Read { .. }), "{e}");
        assert!(e.to_string().contains("none.urdf"), "{e}");

        let e = RobotDescription::load(&write(
            "cell.toml",
            &good.replace("hover = 0.02", "hover = -1.0"),
        ))
        .unwrap_err();
        assert!(matches!(e, RobotLoadError::Workcell { .. }), "{e}");

        assert!(matches!(
            RobotDescription::resolve("kuka"),
            Err(RobotLoadError::Unknown { .. })
        ));
    }

    #[test]
    fn workcell_overrides_apply_key_by_key() {
        let d = RobotDescription::named("ur5e").unwrap();
        let t: toml::Table = toml::from_str("canvas-z = 0.2\nenabled = false").unwrap();
        let cell = d.workcell_with(Some(&t)).unwrap();
        assert_eq!(cell.canvas_z, 0.2);
        assert!(!cell.enabled);
        assert_eq!(cell.canvas_side, d.workcell.canvas_side);
        let bad: toml::Table = toml::from_str("canvas-zz = 0.2").unwrap();
        assert!(d.workcell_with(Some(&bad)).is_err());
        assert_eq!(d.workcell_with(None).unwrap(), d.workcell);
    }
}
