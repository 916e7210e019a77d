//! The pen (tool) path: the tool tip of a resampled trajectory by forward kinematics, in
//! the canvas's drawing axes, and its pen-down box. The one place joints become the
//! robot-independent path the networks, the workcell rules and the plan geometry read.

use guardian_shared::trajectory::{Resampled, STEPS, TOOL};

use crate::kinematics::Robot;

/// One pen-tip sample: `x`, `y` on the canvas (m; x = drawing "right", y = drawing "up")
/// and the pen state (1 down, 0 up).
pub type PenPoint = [f32; 3];

/// Pen-tip path of a resampled Panda trajectory by forward kinematics (the specialised
/// position FK of [`crate::kinematics::PositionFk`] when available; no allocation).
pub fn pen_path(x: &Resampled) -> [PenPoint; STEPS] {
    pen_path_with(crate::kinematics::default_panda(), x)
}

/// [`pen_path`] of a trajectory of `robot`: the one place joints become the model's
/// robot-independent input.
pub fn pen_path_with(robot: &Robot, x: &Resampled) -> [PenPoint; STEPS] {
    let mut positions = [[0.0f64; 3]; STEPS];
    robot.pen_tip_positions_into(x, &mut positions);
    let mut out = [[0.0f32; 3]; STEPS];
    for ((o, p), w) in out.iter_mut().zip(positions.iter()).zip(x.iter()) {
        // Base +x is drawing "up", base -y is drawing "right".
        *o = [-p[1] as f32, p[0] as f32, w[TOOL]];
    }
    out
}

/// [`pen_path`] through the general chain (full frames per joint), the reference the fast
/// path is tested against (feature `test-support`).
#[cfg(any(test, feature = "test-support"))]
pub fn pen_path_reference(x: &Resampled) -> [PenPoint; STEPS] {
    pen_path_reference_with(crate::kinematics::default_panda(), x)
}

/// [`pen_path_reference`] of a trajectory of `robot` (feature `test-support`).
#[cfg(any(test, feature = "test-support"))]
pub fn pen_path_reference_with(robot: &Robot, x: &Resampled) -> [PenPoint; STEPS] {
    let mut out = [[0.0f32; 3]; STEPS];
    for (o, w) in out.iter_mut().zip(x.iter()) {
        let p = robot.pen_tip_position_general(&crate::kinematics::joints_of(w));
        *o = [-p[1] as f32, p[0] as f32, w[TOOL]];
    }
    out
}
/// Bounding box `(min, max)` of the `x, y` of `points` (infinite bounds for none).
fn bounds<'a>(points: impl Iterator<Item = &'a PenPoint>) -> ([f32; 2], [f32; 2]) {
    let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    for q in points {
        for d in 0..2 {
            lo[d] = lo[d].min(q[d]);
            hi[d] = hi[d].max(q[d]);
        }
    }
    (lo, hi)
}

/// Bounding box `(min, max)` of a path's pen-down part (all of it if the pen never
/// touches): what the pen features normalise position and size by.
pub fn pen_down_box(path: &[PenPoint]) -> ([f32; 2], [f32; 2]) {
    let any_down = path.iter().any(|q| q[2] > 0.5);
    bounds(path.iter().filter(|q| !any_down || q[2] > 0.5))
}
