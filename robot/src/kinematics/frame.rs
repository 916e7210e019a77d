//! Rigid transforms between the frames of the chain.

use nalgebra::{Matrix3, Rotation3, Vector3};

/// A rigid transform: `p_parent = rotation * p_child + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Orientation of the child frame in the parent frame.
    pub rotation: Matrix3<f64>,
    /// Origin of the child frame in the parent frame (m).
    pub translation: Vector3<f64>,
}

impl Frame {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// A URDF `<origin xyz rpy>`: rotation `Rz(yaw) * Ry(pitch) * Rx(roll)`.
    pub fn from_xyz_rpy(xyz: [f64; 3], rpy: [f64; 3]) -> Self {
        Self {
            rotation: Rotation3::from_euler_angles(rpy[0], rpy[1], rpy[2]).into_inner(),
            translation: Vector3::new(xyz[0], xyz[1], xyz[2]),
        }
    }

    /// `self * other`.
    pub fn compose(&self, other: &Frame) -> Frame {
        Frame {
            rotation: self.rotation * other.rotation,
            translation: self.translation + self.rotation * other.translation,
        }
    }

    /// A rotation by `angle` about the unit `axis` (Rodrigues), no translation.
    pub fn rotation_about(axis: &Vector3<f64>, angle: f64) -> Frame {
        let r = Rotation3::from_axis_angle(&nalgebra::Unit::new_unchecked(*axis), angle);
        Frame {
            rotation: r.into_inner(),
            translation: Vector3::zeros(),
        }
    }

    /// `self * Rz(q)`: the frame after a revolute joint about its z axis.
    #[inline]
    pub(super) fn rotate_z(&self, q: f64) -> Frame {
        let (s, c) = q.sin_cos();
        let r = &self.rotation;
        let x = r.column(0) * c + r.column(1) * s;
        let y = r.column(1) * c - r.column(0) * s;
        Frame {
            rotation: Matrix3::from_columns(&[x, y, r.column(2).into_owned()]),
            translation: self.translation,
        }
    }
}
