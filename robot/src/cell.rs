//! A cell that is not a canvas: the rules a pick-and-place (or any) cell sets for the tool
//! tip in the robot's base frame, and whether its tasks are anchored to their place.
//!
//! The canvas rules of [`crate::workcell`] assume a pen on a plane. A cell instead names
//! where the tool may go: an optional **allowed** box (the tool tip stays inside it) and
//! **keep-out** boxes (fixtures, the operator's side, a conveyor's frame: the tool tip never
//! enters one). Both are checked on every waypoint of the plan as sent, with the same
//! forward kinematics as the canvas rules, before any network runs. **Anchored** cells also
//! compare every plan with its class by place ([`crate::place`]). The daemon reads all of it
//! from its `[cell]` section (`docs/cells.md`).

use guardian_shared::workcell::{WorkcellKind, WorkcellViolation};
use serde::{Deserialize, Serialize};

use crate::place::PlaceRule;

/// An axis-aligned box in the robot's base frame (m).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Region {
    /// Lowest corner `[x, y, z]`.
    pub min: [f64; 3],
    /// Highest corner `[x, y, z]`.
    pub max: [f64; 3],
}

impl Region {
    /// `p` is inside the box (faces included).
    pub fn contains(&self, p: &[f64; 3]) -> bool {
        (0..3).all(|d| self.min[d] <= p[d] && p[d] <= self.max[d])
    }

    /// Finite, and `min <= max` on every axis.
    pub fn is_valid(&self) -> bool {
        (0..3).all(|d| {
            self.min[d].is_finite() && self.max[d].is_finite() && self.min[d] <= self.max[d]
        })
    }
}

/// A cell's rules: anchoring and the tool tip's regions.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Cell {
    /// Plans are compared with their class by place as well as by shape.
    pub anchored: bool,
    /// The place rule's numbers (used when `anchored`).
    pub place: PlaceRule,
    /// The tool tip stays inside this box, if set.
    pub allowed: Option<Region>,
    /// The tool tip never enters these boxes.
    pub keep_out: Vec<Region>,
}

/// A cell configuration is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum InvalidCell {
    /// A box is not finite or has `min > max` on an axis.
    #[error("{which}: every value must be finite and min <= max on every axis")]
    Region {
        /// `allowed` or `keep-out[i]`.
        which: String,
    },
    /// The place rule's numbers are out of range.
    #[error("place-spread must be finite and >= 0, place-tolerance finite and > 0")]
    Place,
}

impl Cell {
    /// No rules, not anchored: a canvas deployment.
    pub const NONE: Self = Self {
        anchored: false,
        place: PlaceRule::DEFAULT,
        allowed: None,
        keep_out: Vec::new(),
    };

    /// Every box and number usable.
    pub fn validate(&self) -> Result<(), InvalidCell> {
        if let Some(a) = &self.allowed
            && !a.is_valid()
        {
            return Err(InvalidCell::Region {
                which: "allowed".into(),
            });
        }
        if let Some(i) = self.keep_out.iter().position(|r| !r.is_valid()) {
            return Err(InvalidCell::Region {
                which: format!("keep-out[{i}]"),
            });
        }
        if !self.place.is_valid() {
            return Err(InvalidCell::Place);
        }
        Ok(())
    }

    /// The cell sets region rules.
    pub fn has_regions(&self) -> bool {
        self.allowed.is_some() || !self.keep_out.is_empty()
    }

    /// The first waypoint whose tool tip (`positions`, base frame, one per waypoint as sent)
    /// leaves the allowed box or enters a keep-out box. A position that is not finite
    /// breaks the rule it is checked against.
    pub fn violation(&self, positions: &[[f64; 3]]) -> Option<WorkcellViolation> {
        positions.iter().enumerate().find_map(|(i, p)| {
            let kind = if self.allowed.is_some_and(|a| !a.contains(p)) {
                Some(WorkcellKind::OutsideCell)
            } else if self.keep_out.iter().any(|r| r.contains(p))
                || p.iter().any(|v| !v.is_finite())
            {
                Some(WorkcellKind::KeepOut)
            } else {
                None
            };
            kind.map(|kind| WorkcellViolation {
                kind,
                index: u32::try_from(i).unwrap_or(u32::MAX),
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell() -> Cell {
        Cell {
            allowed: Some(Region {
                min: [0.2, -0.5, 0.0],
                max: [0.8, 0.5, 0.6],
            }),
            keep_out: vec![Region {
                min: [0.45, -0.05, 0.0],
                max: [0.55, 0.05, 0.3],
            }],
            ..Cell::NONE
        }
    }

    #[test]
    fn the_first_waypoint_out_of_bounds_is_reported_with_its_rule() {
        let c = cell();
        assert!(c.validate().is_ok() && c.has_regions());
        let ok = [[0.3, 0.0, 0.2], [0.5, 0.2, 0.2], [0.5, 0.0, 0.35]];
        assert_eq!(c.violation(&ok), None);
        let into_box = [[0.3, 0.0, 0.2], [0.4, 0.0, 0.2], [0.5, 0.0, 0.2]];
        assert_eq!(
            c.violation(&into_box),
            Some(WorkcellViolation {
                kind: WorkcellKind::KeepOut,
                index: 2
            })
        );
        let out = [[0.3, 0.0, 0.2], [0.9, 0.0, 0.2], [0.5, 0.0, 0.2]];
        assert_eq!(
            c.violation(&out).map(|v| (v.kind, v.index)),
            Some((WorkcellKind::OutsideCell, 1))
        );
        let nan = [[0.3, 0.0, f64::NAN]];
        assert!(c.violation(&nan).is_some());
        assert_eq!(Cell::NONE.violation(&into_box), None);
    }

    #[test]
    fn unusable_boxes_and_numbers_are_refused() {
        let mut c = cell();
        c.keep_out.push(Region {
            min: [0.0, 0.0, 1.0],
            max: [0.1, 0.1, 0.5],
        });
        assert_eq!(
            c.validate(),
            Err(InvalidCell::Region {
                which: "keep-out[1]".into()
            })
        );
        let c = Cell {
            place: PlaceRule {
                spread: 1.0,
                route: 1.0,
                shape: 1.0,
                tolerance: 0.0,
            },
            ..Cell::NONE
        };
        assert_eq!(c.validate(), Err(InvalidCell::Place));
    }
}
