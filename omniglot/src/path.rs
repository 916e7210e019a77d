//! From strokes to a dense joint path: canvas geometry, the Cartesian pen path (hover,
//! descent, strokes, lifts, travel, final lift) and inverse kinematics along it.
//!
//! The default [`Geometry`] is the one in the engineering guide (§3), so datasets stay
//! comparable: the Panda, a horizontal 0.15 m canvas centred at (0.50, 0.00) m at pen-tip
//! height z = 0.15 m, 1 motor unit = 1.25 mm, motor +y -> base +x, motor +x -> base -y, 2 cm
//! hover and lifts, pen 0.15 m along flange z rotated -pi/4, tool z straight down and tool x
//! along base +x while drawing. [`Geometry::for_robot`] draws the same with another arm (its
//! description's pen, home seed and canvas).

use guardian_robot::kinematics::{
    DEFAULT_ROBOT, Frame, IkError, IkOptions, JointVector, READY_POSE, Robot, RobotDescription,
    joint_vector,
};
use guardian_shared::trajectory::{MAX_WAYPOINTS, Waypoint};
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::strokes::Stroke;

/// Canvas, pen and path parameters. Recorded in every dataset file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case", default)]
pub struct Geometry {
    /// The robot: a built-in name (`panda`, `ur5e`) or a robot description file.
    pub robot: String,
    /// Canvas centre (x, y) in the base frame (m).
    pub canvas_center: [f64; 2],
    /// Canvas side (m); informational (drawings are not rescaled or clipped).
    pub canvas_side: f64,
    /// Pen-tip height of the canvas surface in the base frame (m).
    pub canvas_z: f64,
    /// Motor coordinates that map to the canvas centre.
    pub motor_center: [f64; 2],
    /// Metres per Omniglot motor unit.
    pub metres_per_motor_unit: f64,
    /// Hover height above the first point of each stroke before descending (m).
    pub hover: f64,
    /// Lift height after each stroke; travel happens at this height (m).
    pub lift: f64,
    /// Pen length along the flange z axis (m).
    pub pen_length: f64,
    /// Pen rotation about the flange z axis (rad).
    pub pen_yaw: f64,
    /// Largest spacing of the dense Cartesian path solved by IK (m).
    pub spacing: f64,
    /// Seed of the home-pose IK, one value per joint (the Panda: the Franka ready pose).
    pub ready_pose: Vec<f64>,
    /// IK acceptance: pen-tip position error (m).
    pub ik_position_tolerance: f64,
    /// IK acceptance: pen orientation error (rad).
    pub ik_orientation_tolerance: f64,
}

impl Default for Geometry {
    fn default() -> Self {
        Self {
            robot: DEFAULT_ROBOT.to_string(),
            canvas_center: [0.50, 0.00],
            canvas_side: 0.15,
            canvas_z: 0.15,
            motor_center: [52.5, -52.5],
            metres_per_motor_unit: 0.00125,
            hover: 0.02,
            lift: 0.02,
            pen_length: guardian_robot::kinematics::PEN_LENGTH,
            pen_yaw: guardian_robot::kinematics::PEN_YAW,
            spacing: 0.0015,
            ready_pose: READY_POSE[..guardian_robot::kinematics::PANDA_JOINTS].to_vec(),
            ik_position_tolerance: 1e-5,
            ik_orientation_tolerance: 1e-4,
        }
    }
}

impl Geometry {
    /// A motor-coordinate point on the canvas surface, in the base frame (m).
    pub fn motor_to_base(&self, x: f64, y: f64) -> Vector3<f64> {
        let s = self.metres_per_motor_unit;
        Vector3::new(
            self.canvas_center[0] + (y - self.motor_center[1]) * s,
            self.canvas_center[1] - (x - self.motor_center[0]) * s,
            self.canvas_z,
        )
    }

    /// The default geometry drawn with another robot (a built-in name or a description
    /// file): its description's pen (a tool along flange z, rotated about it), home seed
    /// and canvas; spacing, hover, lifts and the motor mapping as for the Panda.
    pub fn for_robot(robot: &str) -> Result<Self, SolvePathError> {
        let d =
            RobotDescription::resolve(robot).map_err(|e| SolvePathError::Robot(e.to_string()))?;
        let t = d.tool;
        if t.xyz[0] != 0.0 || t.xyz[1] != 0.0 || t.rpy[0] != 0.0 || t.rpy[1] != 0.0 {
            return Err(SolvePathError::Robot(format!(
                "{}: the drawing geometry needs a pen along flange z ([tool] xyz = [0, 0, length], rpy = [0, 0, yaw])",
                d.source
            )));
        }
        let n = d.robot.joints();
        Ok(Self {
            robot: robot.to_string(),
            canvas_center: [d.workcell.canvas_x, d.workcell.canvas_y],
            canvas_side: d.workcell.canvas_side,
            canvas_z: d.workcell.canvas_z,
            pen_length: t.xyz[2],
            pen_yaw: t.rpy[2],
            ready_pose: d.home_seed[..n].to_vec(),
            ..Self::default()
        })
    }

    /// The robot with this geometry's pen.
    pub fn robot(&self) -> Result<Robot, SolvePathError> {
        let d = RobotDescription::resolve(&self.robot)
            .map_err(|e| SolvePathError::Robot(e.to_string()))?;
        if self.ready_pose.len() != d.robot.joints() {
            return Err(SolvePathError::Robot(format!(
                "ready-pose has {} values, robot {} has {} joints",
                self.ready_pose.len(),
                d.robot.name(),
                d.robot.joints()
            )));
        }
        Ok(d.robot.with_tool(self.pen_length, self.pen_yaw))
    }

    /// Pen orientation while drawing: tool z down (-z of the base), tool x along base +x.
    pub fn tool_rotation(&self) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
    }
}

/// One point of the Cartesian pen path.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathPoint {
    /// Pen-tip position in the base frame (m).
    pub position: Vector3<f64>,
    /// Pen on the paper (tool channel 1).
    pub pen_down: bool,
}

/// Points from `from` (excluded) to `to` (included if `include_end`) spaced <= `spacing`.
fn push_line(
    out: &mut Vec<PathPoint>,
    from: Vector3<f64>,
    to: Vector3<f64>,
    pen_down: bool,
    spacing: f64,
    include_end: bool,
) {
    let len = (to - from).norm();
    if len <= 0.0 {
        return;
    }
    let n = (len / spacing).ceil().max(1.0) as usize;
    let last = if include_end { n } else { n - 1 };
    for i in 1..=last {
        out.push(PathPoint {
            position: from + (to - from) * (i as f64 / n as f64),
            pen_down,
        });
    }
}

/// The dense Cartesian pen path of a drawing: hover above the first point, descend, draw
/// each stroke with the pen down, lift by `lift` and travel (pen up) to above the next
/// stroke, descend, ..., final lift. Consecutive points are at most `spacing` apart (the
/// stroke's own points are kept, repeated points dropped). A one-point stroke (a dot) gives
/// one pen-down point. Empty input gives an empty path.
pub fn cartesian_path(strokes: &[Stroke], geometry: &Geometry, spacing: f64) -> Vec<PathPoint> {
    let mut out = Vec::new();
    let up = |p: Vector3<f64>, h: f64| p + Vector3::new(0.0, 0.0, h);
    let mut current: Option<Vector3<f64>> = None;
    for stroke in strokes.iter().filter(|s| !s.is_empty()) {
        let first = geometry.motor_to_base(stroke[0].x, stroke[0].y);
        let hover = up(first, geometry.hover);
        match current {
            None => out.push(PathPoint {
                position: hover,
                pen_down: false,
            }),
            Some(c) => push_line(&mut out, c, hover, false, spacing, true),
        }
        push_line(&mut out, hover, first, false, spacing, false);
        out.push(PathPoint {
            position: first,
            pen_down: true,
        });
        let mut last = first;
        for p in &stroke[1..] {
            let q = geometry.motor_to_base(p.x, p.y);
            push_line(&mut out, last, q, true, spacing, true);
            last = q;
        }
        let lifted = up(last, geometry.lift);
        push_line(&mut out, last, lifted, false, spacing, true);
        current = Some(lifted);
    }
    out
}

/// Solving the joint path failed.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum SolvePathError {
    /// The robot could not be loaded, or does not fit this geometry.
    #[error("robot: {0}")]
    Robot(String),
    /// The home pose (pen hovering above the canvas centre) has no IK solution.
    #[error("no IK solution for the home pose: {0}")]
    Home(IkError),
    /// A path point has no IK solution from the previous one.
    #[error("IK failed at path point {index} of {len} (position {position:?} m): {source}")]
    Ik {
        /// Index into the Cartesian path (`usize::MAX` for the unrecorded approach).
        index: usize,
        /// Path length.
        len: usize,
        /// Target pen-tip position (m).
        position: [f64; 3],
        /// The IK failure.
        source: IkError,
    },
    /// The path is empty.
    #[error("empty path")]
    Empty,
}

/// A solved dense joint path with its quality figures.
#[derive(Debug, Clone, PartialEq)]
pub struct DensePath {
    /// One waypoint per Cartesian path point: the robot's joints (f32) and the tool channel.
    pub waypoints: Vec<Waypoint>,
    /// Largest distance between the target pen tip and the FK of the stored (f32) joints (m).
    pub max_fk_error: f64,
    /// Smallest distance of a stored joint value to its limit (rad).
    pub min_limit_margin: f64,
}

/// IK along Cartesian paths for one geometry: the robot, the home pose and the settings.
#[derive(Debug, Clone)]
pub struct PathSolver {
    robot: Robot,
    rotation: Matrix3<f64>,
    home: JointVector,
    geometry: Geometry,
    options: IkOptions,
}

impl PathSolver {
    /// Build the robot for `geometry` and solve the home pose (pen 2 cm above the canvas
    /// centre, from the ready pose, along an unrecorded straight approach).
    pub fn new(geometry: &Geometry) -> Result<Self, SolvePathError> {
        let robot = geometry.robot()?;
        let rotation = geometry.tool_rotation();
        let options = IkOptions {
            position_tolerance: geometry.ik_position_tolerance,
            orientation_tolerance: geometry.ik_orientation_tolerance,
            ..IkOptions::default()
        };
        let seed = joint_vector(&geometry.ready_pose);
        let mut solver = Self {
            robot,
            rotation,
            home: seed,
            geometry: geometry.clone(),
            options,
        };
        let centre = geometry.motor_to_base(geometry.motor_center[0], geometry.motor_center[1])
            + Vector3::new(0.0, 0.0, geometry.hover);
        let home = solver.approach(&seed, centre).map_err(|e| match e {
            SolvePathError::Ik { source, .. } => SolvePathError::Home(source),
            other => other,
        })?;
        solver.home = home;
        Ok(solver)
    }

    /// The robot model used.
    pub fn robot(&self) -> &Robot {
        &self.robot
    }

    /// The home pose every drawing starts from.
    pub fn home(&self) -> &JointVector {
        &self.home
    }

    /// The geometry this solver was built for.
    pub fn geometry(&self) -> &Geometry {
        &self.geometry
    }

    fn target(&self, position: Vector3<f64>) -> Frame {
        Frame {
            rotation: self.rotation,
            translation: position,
        }
    }

    /// Move the pen from FK(`from`) to `to` in straight steps of at most 1 cm (not recorded).
    fn approach(
        &self,
        from: &JointVector,
        to: Vector3<f64>,
    ) -> Result<JointVector, SolvePathError> {
        let start = self.robot.pen_tip_position(from);
        let len = (to - start).norm();
        let n = (len / 0.01).ceil().max(1.0) as usize;
        let mut q = *from;
        for i in 1..=n {
            let p = start + (to - start) * (i as f64 / n as f64);
            q = self
                .robot
                .ik(&self.target(p), &q, &self.options)
                .map_err(|source| SolvePathError::Ik {
                    index: usize::MAX,
                    len: n,
                    position: p.into(),
                    source,
                })?;
        }
        Ok(q)
    }

    /// Solve a Cartesian path: from the home pose, an unrecorded approach to the first
    /// point, then IK at every point seeded with the previous solution. Joints are stored as
    /// f32 inside the limits.
    pub fn solve(&self, path: &[PathPoint]) -> Result<DensePath, SolvePathError> {
        let first = path.first().ok_or(SolvePathError::Empty)?;
        let mut state = self
            .robot
            .ik_state(&self.approach(&self.home, first.position)?);
        let mut waypoints = Vec::with_capacity(path.len());
        let mut max_fk_error = 0.0f64;
        let mut min_limit_margin = f64::INFINITY;
        for (index, point) in path.iter().enumerate() {
            self.robot
                .ik_from(&self.target(point.position), &mut state, &self.options)
                .map_err(|source| SolvePathError::Ik {
                    index,
                    len: path.len(),
                    position: point.position.into(),
                    source,
                })?;
            let q = &state.q;
            let w = self
                .robot
                .waypoint(q, if point.pen_down { 1.0 } else { 0.0 });
            let stored = self.robot.joints_of(&w);
            let err = (self.robot.pen_tip_position(&stored) - point.position).norm();
            max_fk_error = max_fk_error.max(err);
            min_limit_margin = min_limit_margin.min(self.robot.limit_margin(&stored));
            waypoints.push(w);
        }
        Ok(DensePath {
            waypoints,
            max_fk_error,
            min_limit_margin,
        })
    }

    /// Strokes -> dense Cartesian path (at the geometry's spacing, widened if needed so the
    /// path fits in [`MAX_WAYPOINTS`]) -> dense joint path. A drawing with more raw points
    /// than that keeps them all (the shared validation then rejects it).
    pub fn solve_strokes(
        &self,
        strokes: &[Stroke],
    ) -> Result<(Vec<PathPoint>, DensePath), SolvePathError> {
        let mut spacing = self.geometry.spacing;
        let mut path = cartesian_path(strokes, &self.geometry, spacing);
        // The strokes' own points are always kept, so widening cannot shrink every path;
        // give up after a few rounds and let validation report the count.
        for _ in 0..8 {
            if path.len() <= MAX_WAYPOINTS {
                break;
            }
            spacing *= path.len() as f64 / (MAX_WAYPOINTS as f64 * 0.95);
            path = cartesian_path(strokes, &self.geometry, spacing);
        }
        let dense = self.solve(&path)?;
        Ok((path, dense))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strokes::Point;

    fn pt(x: f64, y: f64) -> Point {
        Point { x, y, t: 0.0 }
    }

    #[test]
    fn default_mapping_follows_the_guide() {
        let g = Geometry::default();
        let c = g.motor_to_base(52.5, -52.5);
        assert!((c - Vector3::new(0.5, 0.0, 0.15)).norm() < 1e-12);
        // Motor "up" -> base +x, motor "right" -> base -y, 1 unit = 1.25 mm.
        let up = g.motor_to_base(52.5, -51.5) - c;
        assert!((up - Vector3::new(0.00125, 0.0, 0.0)).norm() < 1e-12);
        let right = g.motor_to_base(53.5, -52.5) - c;
        assert!((right - Vector3::new(0.0, -0.00125, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn path_has_hover_strokes_lifts_and_dots() {
        let g = Geometry::default();
        let strokes = vec![
            vec![pt(10.0, -10.0), pt(30.0, -10.0)],
            vec![pt(50.0, -50.0)],
        ];
        let path = cartesian_path(&strokes, &g, 0.001);
        // Starts hovering 2 cm above the first point, ends 2 cm above the dot.
        let first = g.motor_to_base(10.0, -10.0);
        assert!((path[0].position - (first + Vector3::new(0.0, 0.0, 0.02))).norm() < 1e-12);
        assert!(!path[0].pen_down);
        let dot = g.motor_to_base(50.0, -50.0);
        let end = path.last().map(|p| p.position);
        assert_eq!(end, Some(dot + Vector3::new(0.0, 0.0, 0.02)));
        // Two pen-down runs; the dot is exactly one point.
        let mut runs = Vec::new();
        let mut i = 0;
        while i < path.len() {
            if path[i].pen_down {
                let a = i;
                while i < path.len() && path[i].pen_down {
                    i += 1;
                }
                runs.push(i - a);
            } else {
                i += 1;
            }
        }
        assert_eq!(runs.len(), 2);
        assert_eq!(runs[1], 1);
        // Pen-down points lie on the canvas; spacing is respected.
        assert!(
            path.iter()
                .filter(|p| p.pen_down)
                .all(|p| (p.position.z - 0.15).abs() < 1e-12)
        );
        assert!(
            path.windows(2)
                .all(|w| (w[1].position - w[0].position).norm() <= 0.001 + 1e-12)
        );
    }

    #[test]
    fn f32_rounding_stays_inside_limits() {
        let hi = -0.0698f64;
        let x = guardian_robot::kinematics::f32_within(hi, -3.0718, hi);
        assert!(f64::from(x) <= hi);
        let lo = -1.7628f64;
        assert!(f64::from(guardian_robot::kinematics::f32_within(lo, lo, 1.7628)) >= lo);
    }
}
