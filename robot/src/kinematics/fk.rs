//! Forward kinematics of the flange and the pen tip through the general chain (full frames
//! per joint, the source of truth), and the pen-tip position paths that use the specialised
//! [`PositionFk`](super::PositionFk) when the chain has one.

use guardian_shared::trajectory::Waypoint;
use nalgebra::{Matrix3, Vector3};

use super::{Frame, Joint, JointKind, JointVector, Robot};

impl Joint {
    /// `t * origin * motion(q)`: the frame after this joint at position `q`.
    #[inline]
    pub(crate) fn apply(&self, t: &Frame, q: f64) -> Frame {
        let t = t.compose(&self.origin);
        if self.about_z() {
            return t.rotate_z(q);
        }
        match self.kind {
            JointKind::Revolute => t.compose(&Frame::rotation_about(&self.axis, q)),
            JointKind::Prismatic => Frame {
                rotation: t.rotation,
                translation: t.translation + t.rotation * (self.axis * q),
            },
        }
    }
}

impl Robot {
    /// Frame after the last movable joint (before the flange offset).
    #[inline]
    fn last_link(&self, q: &JointVector) -> Frame {
        let mut t = Frame::identity();
        for (joint, &qi) in self.joints.iter().zip(q.iter()) {
            t = joint.apply(&t, qi);
        }
        t
    }

    /// Forward kinematics of the flange (the description's tip link) in the base frame.
    pub fn flange(&self, q: &JointVector) -> Frame {
        self.last_link(q).compose(&self.flange)
    }

    /// Forward kinematics of the pen tip (tool frame) in the base frame.
    pub fn pen_tip(&self, q: &JointVector) -> Frame {
        self.flange(q).compose(&self.tool)
    }

    /// Pen-tip position only (m), the fast path for path lengths and features: the
    /// specialised [`PositionFk`] when the joint origins allow it, else the general chain
    /// ([`Robot::pen_tip`]).
    #[inline]
    pub fn pen_tip_position(&self, q: &JointVector) -> Vector3<f64> {
        match &self.position_fk {
            Some(fk) => Vector3::from(fk.position(q)),
            None => self.pen_tip(q).translation,
        }
    }

    /// Pen-tip position through the general chain (full frames), the reference
    /// [`Robot::pen_tip_position`] is tested against (feature `test-support`).
    #[cfg(any(test, feature = "test-support"))]
    pub fn pen_tip_position_general(&self, q: &JointVector) -> Vector3<f64> {
        self.pen_tip(q).translation
    }

    /// The joint part of a waypoint as f64 (slots past the robot's joints 0).
    #[inline]
    pub fn joints_of(&self, w: &Waypoint) -> JointVector {
        let mut q = [0.0; super::MAX_JOINTS];
        for j in 0..self.joints() {
            q[j] = f64::from(w[j]);
        }
        q
    }

    /// Pen-tip positions (m, base frame) of the joint parts of `waypoints` into `out`
    /// (same length; extra slots are left alone). Uses [`PositionFk::positions_into`] when
    /// available; allocates nothing.
    pub fn pen_tip_positions_into(&self, waypoints: &[Waypoint], out: &mut [[f64; 3]]) {
        match &self.position_fk {
            Some(fk) => fk.positions_into(waypoints, out),
            None => {
                for (o, w) in out.iter_mut().zip(waypoints) {
                    *o = self.pen_tip(&self.joints_of(w)).translation.into();
                }
            }
        }
    }

    /// Pen-tip positions and tool rotations (base frame) of the joint parts of `waypoints`
    /// (pairs up to the shortest of the three): [`PositionFk::poses_into`] when available,
    /// else the general chain. The positions equal [`Robot::pen_tip_positions_into`]'s bit for
    /// bit. Allocates nothing.
    pub fn pen_tip_poses_into(
        &self,
        waypoints: &[Waypoint],
        positions: &mut [[f64; 3]],
        rotations: &mut [Matrix3<f64>],
    ) {
        match &self.position_fk {
            Some(fk) => fk.poses_into(waypoints, positions, rotations),
            None => {
                for ((p, r), w) in positions.iter_mut().zip(rotations).zip(waypoints) {
                    let f = self.pen_tip(&self.joints_of(w));
                    *p = f.translation.into();
                    *r = f.rotation;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::READY_POSE;

    #[test]
    fn flange_at_the_check_pose() {
        let panda = Robot::panda();
        let f = panda.flange(&READY_POSE);
        let expected = Vector3::new(0.3069, 0.0, 0.5903);
        assert!(
            (f.translation - expected).norm() < 1e-4,
            "{}",
            f.translation
        );
        // Flange z points straight down at the ready pose.
        assert!((f.rotation.column(2) - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-9);
        // The pen tip is 0.15 m further down, its x axis along base +x.
        let p = panda.pen_tip(&READY_POSE);
        assert!((p.translation - (expected - Vector3::new(0.0, 0.0, 0.15))).norm() < 1e-4);
        assert!((p.rotation.column(0) - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-9);
    }
}
