//! The one preprocessing step shared by training, evaluation and serving: validate a raw
//! planner trajectory, measure its pen-tip path length by forward kinematics and resample it
//! to [`STEPS`](guardian_shared::trajectory::STEPS) samples uniform in that length.

use guardian_shared::trajectory::{InvalidTrajectory, Resampled, Waypoint};
use guardian_shared::workcell::Workcell;
use nalgebra::Vector3;

#[cfg(any(test, feature = "test-support"))]
use crate::kinematics::joints_of;
use crate::kinematics::{Robot, default_panda};
use crate::workcell::cumulative_lengths;

/// Pen-tip positions (m, base frame) of each waypoint, with the default robot.
pub fn pen_tip_positions(waypoints: &[Waypoint]) -> Vec<Vector3<f64>> {
    pen_tip_positions_with(default_panda(), waypoints)
}

/// Pen-tip positions (m, base frame) of each waypoint, with a given robot.
pub fn pen_tip_positions_with(robot: &Robot, waypoints: &[Waypoint]) -> Vec<Vector3<f64>> {
    let mut out = vec![[0.0; 3]; waypoints.len()];
    robot.pen_tip_positions_into(waypoints, &mut out);
    out.into_iter().map(Vector3::from).collect()
}

/// Cumulative pen-tip path length (m) by forward kinematics: element `i` is the length of
/// the polyline through the pen-tip positions of waypoints `0..=i` (element 0 is 0).
pub fn pen_path_lengths(waypoints: &[Waypoint]) -> Vec<f64> {
    pen_path_lengths_with(default_panda(), waypoints)
}

/// [`pen_path_lengths`] with a given robot.
pub fn pen_path_lengths_with(robot: &Robot, waypoints: &[Waypoint]) -> Vec<f64> {
    let mut positions = vec![[0.0; 3]; waypoints.len()];
    let mut out = vec![0.0; waypoints.len()];
    robot.pen_tip_positions_into(waypoints, &mut positions);
    cumulative_lengths(&positions, &mut out);
    out
}

/// [`pen_path_lengths_with`] through the general chain ([`Robot::pen_tip_position_general`],
/// full frames per joint): the reference the fast path is tested against (feature
/// `test-support`).
#[cfg(any(test, feature = "test-support"))]
pub fn pen_path_lengths_reference(robot: &Robot, waypoints: &[Waypoint]) -> Vec<f64> {
    let mut out = Vec::with_capacity(waypoints.len());
    let mut total = 0.0;
    let mut prev: Option<Vector3<f64>> = None;
    for w in waypoints {
        let p = robot.pen_tip_position_general(&joints_of(w));
        if let Some(pp) = prev {
            total += (p - pp).norm();
        }
        out.push(total);
        prev = Some(p);
    }
    out
}

/// [`preprocess_with`] the default robot, the Panda: validate `raw` against its limits
/// ([`guardian_shared::trajectory::validate`]) and resample it to [`STEPS`](guardian_shared::trajectory::STEPS)
/// waypoints uniformly in pen-tip path length ([`guardian_shared::trajectory::resample`]).
pub fn preprocess(raw: &[Waypoint]) -> Result<Resampled, InvalidTrajectory> {
    preprocess_with(default_panda(), raw)
}

/// [`preprocess`] with a given robot (another arm, or another pen length): validated
/// against its limits, path length by its forward kinematics. This is the one
/// preprocessing path, [`crate::workcell::inspect_with`], with the workcell rules off: the
/// daemon's checks (rules on), its identify and enroll, and the dataset generator all
/// resample a trajectory with the same code, so it is seen the same way in training and in
/// service.
pub fn preprocess_with(robot: &Robot, raw: &[Waypoint]) -> Result<Resampled, InvalidTrajectory> {
    crate::workcell::inspect_with(robot, &Workcell::OFF, raw).map(|i| i.resampled)
}

/// [`preprocess_with`] as it was before the specialised FK: path lengths through the
/// general chain ([`pen_path_lengths_reference`]). The reference for equivalence tests
/// (feature `test-support`).
#[cfg(any(test, feature = "test-support"))]
pub fn preprocess_reference(
    robot: &Robot,
    raw: &[Waypoint],
) -> Result<Resampled, InvalidTrajectory> {
    guardian_shared::trajectory::validate(raw, robot.limits())?;
    let cumulative = pen_path_lengths_reference(robot, raw);
    Ok(guardian_shared::trajectory::resample(
        raw,
        &cumulative,
        robot.joints(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::JointVector;
    use crate::kinematics::READY_POSE;
    use guardian_shared::trajectory::{InvalidKind, STEPS, TOOL};

    fn wp(q: &JointVector, tool: f32) -> Waypoint {
        let mut w = [0.0f32; guardian_shared::trajectory::SLOTS];
        for j in 0..crate::kinematics::PANDA_JOINTS {
            w[j] = q[j] as f32;
        }
        w[TOOL] = tool;
        w
    }

    #[test]
    fn path_length_follows_the_pen_tip() {
        // Joint 1 swings the pen tip on a circle of radius r around the base z axis.
        let mut q = READY_POSE;
        let r = {
            let p = default_panda().pen_tip_position(&q);
            (p.x * p.x + p.y * p.y).sqrt()
        };
        let mut ws = Vec::new();
        for k in 0..=100 {
            q[0] = 0.5 * k as f64 / 100.0;
            ws.push(wp(&q, 0.0));
        }
        let lens = pen_path_lengths(&ws);
        assert_eq!(lens[0], 0.0);
        assert!(
            (lens[100] - 0.5 * r).abs() < 1e-5,
            "{} vs {}",
            lens[100],
            0.5 * r
        );
        let out = preprocess(&ws).expect("valid");
        assert_eq!(out.len(), STEPS);
        assert!((f64::from(out[STEPS - 1][0]) - 0.5).abs() < 1e-6);
    }

    #[test]
    fn invalid_input_is_rejected() {
        let mut q = READY_POSE;
        q[3] = 0.5; // beyond joint 4's upper limit
        let ws = vec![wp(&READY_POSE, 0.0), wp(&q, 0.0)];
        assert_eq!(
            preprocess(&ws).unwrap_err().kind,
            InvalidKind::JointOutOfLimits
        );
        assert_eq!(
            preprocess(&ws[..1]).unwrap_err().kind,
            InvalidKind::TooFewWaypoints
        );
    }
}
