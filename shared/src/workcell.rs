//! The workcell: where a plan may put the pen, and how the tool must be held.
//!
//! These are absolute, physical rules a robotics engineer expects of every drawing plan,
//! independent of the learned model (`docs/operating.md`): the canvas geometry and the
//! commanded tool orientation of `shared/GUIDE.md` §3, with tolerances. The check itself
//! (forward kinematics of every waypoint) lives in `guardian_robot::workcell`; this module
//! holds the configuration, the violation kinds carried on the wire, and the names of the
//! plan-geometry features a class is compared on.

use serde::{Deserialize, Serialize};

/// Workcell geometry and tolerances. The defaults are the dataset's workcell (canvas 0.15 m
/// square centred at (0.50, 0.00) m, pen-tip height 0.15 m when drawing, 2 cm hover; tool z
/// straight down, tool x along base +x).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields, default)]
pub struct Workcell {
    /// Apply the workcell rules at all.
    pub enabled: bool,
    /// Canvas centre, base-frame x (m).
    pub canvas_x: f64,
    /// Canvas centre, base-frame y (m).
    pub canvas_y: f64,
    /// Side of the square canvas (m).
    pub canvas_side: f64,
    /// Pen-tip height of the canvas plane, base-frame z (m).
    pub canvas_z: f64,
    /// Hover height of the pen tip above the canvas when the pen is up (m).
    pub hover: f64,
    /// Largest allowed rotation between the tool frame and the commanded orientation (rad).
    pub orientation_tolerance: f64,
    /// Pen down: largest allowed distance of the pen tip from the canvas plane (m).
    pub height_tolerance: f64,
    /// How far outside the canvas square (pen down and up) and above the hover height (pen
    /// up) the pen tip may go (m).
    pub margin: f64,
}

impl Default for Workcell {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl Workcell {
    /// The paper's workcell, rules on: a 0.15 m canvas 0.5 m in front of the base.
    pub const DEFAULT: Self = Self {
        enabled: true,
        canvas_x: 0.50,
        canvas_y: 0.00,
        canvas_side: 0.15,
        canvas_z: 0.15,
        hover: 0.02,
        orientation_tolerance: 0.002,
        height_tolerance: 0.002,
        margin: 0.01,
    };

    /// No rules: what plain preprocessing (validation and resampling, no workcell) uses.
    pub const OFF: Self = Self {
        enabled: false,
        ..Self::DEFAULT
    };
}

/// A workcell configuration is unusable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum InvalidWorkcell {
    /// A value is NaN or infinite.
    #[error("workcell values must be finite")]
    NonFinite,
    /// The canvas side is not positive or the hover height is negative.
    #[error("workcell canvas-side must be > 0 and hover >= 0")]
    Canvas,
    /// A tolerance is not positive (or the margin is negative).
    #[error("workcell tolerances must be > 0 (margin >= 0)")]
    Tolerance,
}

impl Workcell {
    /// The configuration is usable: finite, positive sizes and tolerances.
    pub fn validate(&self) -> Result<(), InvalidWorkcell> {
        let finite = [
            self.canvas_x,
            self.canvas_y,
            self.canvas_side,
            self.canvas_z,
            self.hover,
            self.orientation_tolerance,
            self.height_tolerance,
            self.margin,
        ]
        .iter()
        .all(|v| v.is_finite());
        if !finite {
            return Err(InvalidWorkcell::NonFinite);
        }
        if self.canvas_side <= 0.0 || self.hover < 0.0 {
            return Err(InvalidWorkcell::Canvas);
        }
        if self.orientation_tolerance <= 0.0 || self.height_tolerance <= 0.0 || self.margin < 0.0 {
            return Err(InvalidWorkcell::Tolerance);
        }
        Ok(())
    }
}

/// Which workcell rule a plan broke (wire value in `ResponseHeader::workcell_kind`).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, num_enum::TryFromPrimitive,
)]
#[serde(rename_all = "kebab-case")]
#[repr(u8)]
#[non_exhaustive]
pub enum WorkcellKind {
    /// The tool is rotated away from the commanded orientation by more than the tolerance
    /// (e.g. a joint offset: any single-joint offset of d rad rotates the tool by d).
    ToolOrientation = 1,
    /// Pen down, but the pen tip is off the canvas plane by more than the tolerance.
    PenHeight = 2,
    /// The pen tip leaves the canvas square (plus margin).
    OffCanvas = 3,
    /// Pen up, but the pen tip is below the canvas plane or above the hover height (plus
    /// margin).
    HoverHeight = 4,
    /// The tool tip enters one of the cell's keep-out boxes (`[cell] keep-out`).
    KeepOut = 5,
    /// The tool tip leaves the cell's allowed region (`[cell] allowed`).
    OutsideCell = 6,
}

/// The first waypoint that broke a workcell rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkcellViolation {
    /// Which rule.
    pub kind: WorkcellKind,
    /// Index of the first offending waypoint (of the trajectory as sent).
    pub index: u32,
}

/// Features of a plan's pen path compared with the enrolled examples of its class (wire
/// value in `ResponseHeader::geometry_feature`). Positions in metres in drawing coordinates
/// (x right = base −y, y up = base +x); sizes, length and stroke count as natural
/// logarithms (their spread grows with their value); start and end points relative to the
/// drawing's size, the direction relative to its pen-down length.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, num_enum::TryFromPrimitive,
)]
#[serde(rename_all = "kebab-case")]
#[repr(u8)]
#[non_exhaustive]
pub enum GeometryFeature {
    /// Centre of the pen-down bounding box, x.
    CentreX = 1,
    /// Centre of the pen-down bounding box, y.
    CentreY = 2,
    /// Width of the pen-down bounding box (log).
    Width = 3,
    /// Height of the pen-down bounding box (log).
    Height = 4,
    /// Pen-down path length (log).
    PenDownLength = 5,
    /// Number of strokes (pen-down runs, log).
    Strokes = 6,
    /// First pen-down point relative to the box centre, x (÷ the box's longer side).
    StartX = 7,
    /// First pen-down point relative to the box centre, y.
    StartY = 8,
    /// Last pen-down point relative to the box centre, x.
    EndX = 9,
    /// Last pen-down point relative to the box centre, y.
    EndY = 10,
    /// Net drawing direction: sum over strokes of (stroke end − stroke start), x (÷ the
    /// pen-down length).
    DirectionX = 11,
    /// Net drawing direction, y.
    DirectionY = 12,
    /// Where the plan happens in the cell: its tool path in the robot's base frame against
    /// the enrolled examples' (anchored deployments only; the score is the place excess in
    /// metres, `guardian_robot::place`). Not a descriptor feature: not in [`Self::ALL`].
    Place = 13,
}

/// Number of [`GeometryFeature`]s.
pub const GEOMETRY_FEATURES: usize = 12;

impl GeometryFeature {
    /// Every feature, in descriptor order (index `i` is wire value `i + 1`).
    pub const ALL: [GeometryFeature; GEOMETRY_FEATURES] = [
        Self::CentreX,
        Self::CentreY,
        Self::Width,
        Self::Height,
        Self::PenDownLength,
        Self::Strokes,
        Self::StartX,
        Self::StartY,
        Self::EndX,
        Self::EndY,
        Self::DirectionX,
        Self::DirectionY,
    ];

    /// Kebab-case name, e.g. `centre-x`.
    pub fn name(self) -> &'static str {
        match self {
            Self::CentreX => "centre-x",
            Self::CentreY => "centre-y",
            Self::Width => "width",
            Self::Height => "height",
            Self::PenDownLength => "pen-down-length",
            Self::Strokes => "strokes",
            Self::StartX => "start-x",
            Self::StartY => "start-y",
            Self::EndX => "end-x",
            Self::EndY => "end-y",
            Self::DirectionX => "direction-x",
            Self::DirectionY => "direction-y",
            Self::Place => "place",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::decode_code;

    #[test]
    fn codes_round_trip_and_defaults_are_valid() {
        for (i, f) in GeometryFeature::ALL.iter().enumerate() {
            assert_eq!(*f as u32, i as u32 + 1);
            assert_eq!(decode_code::<GeometryFeature>(*f as u32), Some(*f));
        }
        assert_eq!(decode_code::<GeometryFeature>(0), None);
        assert_eq!(
            decode_code::<GeometryFeature>(13),
            Some(GeometryFeature::Place)
        );
        assert_eq!(decode_code::<GeometryFeature>(14), None);
        for v in 1..=6 {
            assert_eq!(decode_code::<WorkcellKind>(v).map(|k| k as u32), Some(v));
        }
        assert_eq!(decode_code::<WorkcellKind>(7), None);
        assert!(Workcell::default().validate().is_ok());
        let bad = Workcell {
            margin: f64::NAN,
            ..Workcell::default()
        };
        assert!(bad.validate().is_err());
    }
}
