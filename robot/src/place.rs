//! Where a plan happens: the **place signature** of a plan, its tool-tip path in the
//! robot's base frame reduced to a few key points, and the **place rule** that compares it
//! with the enrolled examples of a class.
//!
//! The networks and the plan geometry see a plan without its position in the cell (an "A"
//! drawn anywhere on the canvas is the same task). In a cell the place *is* the task: the
//! same pick-and-place motion to the neighbouring bin is another task. A deployment that
//! serves a cell turns on *anchoring* (`[cell] anchored = true`), and then a plan must be its
//! claimed class in shape (the embedding) *and* in place (this module).
//!
//! **Signature.** The plan's tool-tip path (forward kinematics of the resampled plan) is cut
//! into segments where the tool channel changes (for a pick-and-place plan: approach, carry,
//! retreat; the grasp and the release are segment ends). Each segment, from the last point
//! of the previous one, gives [`POINTS_PER_SEGMENT`] key points by arc length: its ends,
//! the points 3 and 6 cm from each end (the way into and out of a grasp or a release,
//! whatever heights the planner chose) and its quarter points; of the
//! first segment only its last [`FIRST_SEGMENT`] metres count (where a plan starts is where
//! the robot happens to be). Two
//! signatures compare point by point only if their segments have the same tool states in
//! the same order.
//!
//! **Rule.** For the enrolled examples `e` of a class whose segments match the plan's, key
//! point `j` has the examples' mean `μ_j` and the demonstrated spread
//! `r_j = max_e |e_j − μ_j|`. The plan's **place excess** is how far its worst key point
//! lies beyond what the demonstrations cover:
//!
//! `excess = max_j ( |p_j − μ_j| − spread · r_j ) / w_j`   (metres)
//!
//! with `w_j = 1` at and near a grasp or a release (where the tool channel changes: the
//! task fixes where and how they happen) and `w_j = route` at every other key point (the planner chooses the
//! way between them).
//!
//! and the plan is in another place if `excess > tolerance` (or is not a number, or no
//! example has its segments). `spread` and `tolerance` are calibrated on generated cells
//! (`guardian-lab cell`, `docs/cells.md`). A spread that the demonstrations did not show is
//! not granted: enroll demonstrations that vary as the real runs do (at least three).

use guardian_shared::trajectory::{Resampled, STEPS, TOOL};
use serde::{Deserialize, Serialize};

use crate::kinematics::Robot;

/// Key points per segment of a [`PlaceSignature`].
pub const POINTS_PER_SEGMENT: usize = 9;

/// Where along a segment its key points lie: `(from, metres, share)`, the point at arc
/// length `metres + share × length` from the start (`from = 0`) or before the end
/// (`from = 1`), clamped to the segment. The ends, the tool's way into and out of them
/// (3 and 6 cm: how a grasp or a release is approached, whatever heights the planner
/// chose) and the quarter points of the way between.
const KEY_POINTS: [(u8, f64, f64); POINTS_PER_SEGMENT] = [
    (0, 0.0, 0.0),
    (0, 0.03, 0.0),
    (0, 0.06, 0.0),
    (0, 0.0, 0.25),
    (0, 0.0, 0.5),
    (0, 0.0, 0.75),
    (1, 0.06, 0.0),
    (1, 0.03, 0.0),
    (1, 0.0, 0.0),
];

/// Key points of a segment within this many from an end belong to that end.
const NEAR_END: usize = 3;

/// A plan's tool-tip path in the base frame reduced to key points (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaceSignature {
    /// Tool state (on = channel > 0.5) of each segment, in order.
    pub tools: Vec<bool>,
    /// [`POINTS_PER_SEGMENT`] points (m, base frame) per segment, segment by segment.
    pub points: Vec<[f32; 3]>,
}

impl PlaceSignature {
    /// The signature of a tool-tip path: `positions` (m, base frame) with the tool on or off
    /// at each. `None` for an empty path or lengths that differ.
    pub fn of_path(positions: &[[f64; 3]], tool_on: &[bool]) -> Option<Self> {
        if positions.is_empty() || positions.len() != tool_on.len() {
            return None;
        }
        let mut tools = Vec::new();
        let mut points = Vec::new();
        let mut start = 0;
        while start < positions.len() {
            let on = tool_on[start];
            let mut end = start;
            while end + 1 < positions.len() && tool_on[end + 1] == on {
                end += 1;
            }
            // The segment runs from the previous segment's last point, so the grasp or
            // release point belongs to both.
            let from = start.saturating_sub(1);
            if start == 0 {
                // Where a plan starts is where the robot happens to be, not the task: the
                // first segment counts from its last `FIRST_SEGMENT` metres.
                resample(&tail(&positions[from..=end], FIRST_SEGMENT), &mut points);
            } else {
                resample(&positions[from..=end], &mut points);
            }
            tools.push(on);
            start = end + 1;
        }
        Some(Self { tools, points })
    }

    /// The signature of a resampled plan of `robot` (its tool tip by forward kinematics).
    pub fn of_plan(robot: &Robot, x: &Resampled) -> Self {
        let mut positions = [[0.0f64; 3]; STEPS];
        robot.pen_tip_positions_into(x, &mut positions);
        let tool_on: Vec<bool> = x.iter().map(|w| w[TOOL] > 0.5).collect();
        Self::of_path(&positions, &tool_on).unwrap_or(Self {
            tools: Vec::new(),
            points: Vec::new(),
        })
    }

    /// Well formed ([`POINTS_PER_SEGMENT`] points per segment, at least one segment) and
    /// every value finite.
    pub fn is_valid(&self) -> bool {
        !self.tools.is_empty()
            && self.points.len() == self.tools.len() * POINTS_PER_SEGMENT
            && self.points.iter().flatten().all(|v| v.is_finite())
    }
}

/// How much of the first segment counts, from its end (m).
pub const FIRST_SEGMENT: f64 = 0.10;

/// The last `length` metres of `polyline` (all of it if shorter), starting at an
/// interpolated point.
fn tail(polyline: &[[f64; 3]], length: f64) -> Vec<[f64; 3]> {
    let mut out = vec![polyline[polyline.len() - 1]];
    let mut left = length;
    for w in polyline.windows(2).rev() {
        let (a, b) = (w[0], w[1]);
        let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        if d >= left {
            let t = if d > 0.0 { left / d } else { 0.0 };
            out.push([0, 1, 2].map(|k| b[k] + t * (a[k] - b[k])));
            break;
        }
        left -= d;
        out.push(a);
    }
    out.reverse();
    out
}

/// Append the [`KEY_POINTS`] of `polyline`.
fn resample(polyline: &[[f64; 3]], out: &mut Vec<[f32; 3]>) {
    let dist = |a: &[f64; 3], b: &[f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let mut cumulative = Vec::with_capacity(polyline.len());
    let mut total = 0.0;
    cumulative.push(0.0);
    for w in polyline.windows(2) {
        total += dist(&w[0], &w[1]);
        cumulative.push(total);
    }
    for &(from, metres, share) in &KEY_POINTS {
        let along = (metres + share * total).min(total);
        let s = if from == 0 { along } else { total - along };
        let mut i = 0;
        while i + 1 < polyline.len() && cumulative[i + 1] < s {
            i += 1;
        }
        let p = if i + 1 >= polyline.len() {
            polyline[polyline.len() - 1]
        } else {
            let span = cumulative[i + 1] - cumulative[i];
            let t = if span > 0.0 {
                ((s - cumulative[i]) / span).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (a, b) = (polyline[i], polyline[i + 1]);
            [0, 1, 2].map(|d| a[d] + t * (b[d] - a[d]))
        };
        out.push(p.map(|v| v as f32));
    }
}

/// The place rule's two numbers (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct PlaceRule {
    /// How many times its demonstrated spread a key point may deviate from the examples'
    /// mean before the deviation counts (≥ 0).
    pub spread: f32,
    /// How many times more a route point (any key point but a grasp or a release: where
    /// the tool channel changes) may deviate than a grasp or a release (≥ 1): the planner
    /// chooses the way between them, the task fixes where they happen.
    #[serde(default = "one")]
    pub route: f32,
    /// Factor on the claimed class's embedding threshold (the shape rule) in an anchored
    /// deployment (> 0): the class thresholds are calibrated on drawings, and runs of a
    /// cell task spread differently in shape.
    #[serde(default = "one")]
    pub shape: f32,
    /// Largest place excess (m) of a plan in its class's place (> 0).
    pub tolerance: f32,
}

fn one() -> f32 {
    1.0
}

impl PlaceRule {
    /// The rule calibrated on generated cells (`docs/cells.md`).
    pub const DEFAULT: Self = Self {
        spread: 1.5,
        route: 2.0,
        shape: 1.2,
        tolerance: 0.015,
    };

    /// Both numbers finite, `spread >= 0`, `tolerance > 0`.
    pub fn is_valid(&self) -> bool {
        self.spread.is_finite()
            && self.spread >= 0.0
            && self.route.is_finite()
            && self.route >= 1.0
            && self.shape.is_finite()
            && self.shape > 0.0
            && self.tolerance.is_finite()
            && self.tolerance > 0.0
    }

    /// The place rule, the one place it is written: a plan whose place excess exceeds the
    /// tolerance, or is not a number, is in another place.
    pub fn is_other_place(&self, excess: f32) -> bool {
        // NaN compares to nothing, so only a number at most the tolerance passes.
        !matches!(
            excess.partial_cmp(&self.tolerance),
            Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
        )
    }
}

impl Default for PlaceRule {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// A plan's place against a class: the excess and the key point that decided it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaceScore {
    /// Place excess (m); infinite when no example has the plan's segments.
    pub excess: f32,
    /// The deciding key point (index into [`PlaceSignature::points`]); `None` when no
    /// example has the plan's segments.
    pub point: Option<usize>,
    /// That key point's distance from the examples' mean (m).
    pub deviation: f32,
}

/// The place excess of `plan` against a class's enrolled `examples` under `rule` (see the
/// module docs). `None` without examples.
pub fn score(
    plan: &PlaceSignature,
    examples: &[PlaceSignature],
    rule: &PlaceRule,
) -> Option<PlaceScore> {
    if examples.is_empty() {
        return None;
    }
    let matching: Vec<&PlaceSignature> = examples
        .iter()
        .filter(|e| e.tools == plan.tools && e.points.len() == plan.points.len())
        .collect();
    if matching.is_empty() || plan.points.is_empty() {
        return Some(PlaceScore {
            excess: f32::INFINITY,
            point: None,
            deviation: f32::INFINITY,
        });
    }
    let n = matching.len() as f32;
    let mut worst = PlaceScore {
        excess: f32::NEG_INFINITY,
        point: Some(0),
        deviation: 0.0,
    };
    for (j, p) in plan.points.iter().enumerate() {
        let mut mean = [0.0f32; 3];
        for e in &matching {
            for (m, v) in mean.iter_mut().zip(&e.points[j]) {
                *m += v / n;
            }
        }
        let r = matching
            .iter()
            .map(|e| norm(&e.points[j], &mean))
            .fold(0.0f32, f32::max);
        let deviation = norm(p, &mean);
        let excess = (deviation - rule.spread * r) / weight(plan, j, rule.route);
        if excess.is_nan() {
            return Some(PlaceScore {
                excess: f32::NAN,
                point: Some(j),
                deviation,
            });
        }
        if excess > worst.excess {
            worst = PlaceScore {
                excess,
                point: Some(j),
                deviation,
            };
        }
    }
    Some(worst)
}

/// The divisor of key point `j`'s excess: 1 at and near a grasp or release (a segment end
/// where the tool channel changes), `route` elsewhere.
fn weight(plan: &PlaceSignature, j: usize, route: f32) -> f32 {
    let (segment, k) = (j / POINTS_PER_SEGMENT, j % POINTS_PER_SEGMENT);
    let event = (k >= POINTS_PER_SEGMENT - NEAR_END && segment + 1 < plan.tools.len())
        || (k < NEAR_END && segment > 0);
    if event { 1.0 } else { route }
}

fn norm(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pick-and-place tool path: approach from `start` to the pick, carry to `place`,
    /// retreat up; 10 points a leg.
    fn pick_place(pick: [f64; 3], place: [f64; 3]) -> (Vec<[f64; 3]>, Vec<bool>) {
        let start = [0.4, 0.0, 0.4];
        let up = |p: [f64; 3]| [p[0], p[1], p[2] + 0.1];
        let legs = [
            (start, pick, false),
            (pick, place, true),
            (place, up(place), false),
        ];
        let mut pos = vec![start];
        let mut tool = vec![false];
        for (a, b, on) in legs {
            for i in 1..=10 {
                let t = f64::from(i) / 10.0;
                pos.push([0, 1, 2].map(|d| a[d] + t * (b[d] - a[d])));
                tool.push(on);
            }
        }
        (pos, tool)
    }

    fn sig(pick: [f64; 3], place: [f64; 3]) -> PlaceSignature {
        let (p, t) = pick_place(pick, place);
        PlaceSignature::of_path(&p, &t).unwrap()
    }

    #[test]
    fn segments_follow_the_tool_and_share_their_ends() {
        let s = sig([0.5, 0.1, 0.1], [0.5, -0.2, 0.1]);
        assert_eq!(s.tools, vec![false, true, false]);
        assert_eq!(s.points.len(), 3 * POINTS_PER_SEGMENT);
        assert!(s.is_valid());
        // The approach ends at the pick, the carry starts there and ends at the place.
        let pick = s.points[POINTS_PER_SEGMENT - 1];
        assert!(norm(&pick, &[0.5, 0.1, 0.1]) < 1e-6, "{pick:?}");
        assert_eq!(s.points[POINTS_PER_SEGMENT], pick);
        // Of the approach only its last FIRST_SEGMENT metres count.
        let d = norm(&s.points[0], &pick);
        assert!((f64::from(d) - FIRST_SEGMENT).abs() < 1e-6, "{d}");
        let place = s.points[2 * POINTS_PER_SEGMENT - 1];
        assert!(norm(&place, &[0.5, -0.2, 0.1]) < 1e-6, "{place:?}");
        // 3 cm into the carry, and its middle point half way in arc length.
        let into = s.points[POINTS_PER_SEGMENT + 1];
        assert!(norm(&into, &[0.5, 0.07, 0.1]) < 1e-6, "{into:?}");
        let mid = s.points[POINTS_PER_SEGMENT + 4];
        assert!(norm(&mid, &[0.5, -0.05, 0.1]) < 1e-6, "{mid:?}");
        assert!(PlaceSignature::of_path(&[], &[]).is_none());
        assert!(PlaceSignature::of_path(&[[0.0; 3]], &[]).is_none());
    }

    #[test]
    fn the_neighbouring_bin_is_another_place_and_the_demonstrated_spread_is_not() {
        let rule = PlaceRule::DEFAULT;
        // Five demonstrations: the part lies up to 1.5 cm elsewhere, the bin is fixed.
        let picks = [
            [0.0, 0.0],
            [0.015, 0.0],
            [-0.015, 0.01],
            [0.0, -0.015],
            [0.01, 0.015],
        ];
        let examples: Vec<PlaceSignature> = picks
            .iter()
            .map(|d| sig([0.5 + d[0], 0.2 + d[1], 0.1], [0.5, -0.2, 0.1]))
            .collect();
        // A new run with the part elsewhere within the same range: in place.
        let genuine = sig([0.512, 0.188, 0.1], [0.503, -0.2, 0.1]);
        let s = score(&genuine, &examples, &rule).unwrap();
        assert!(!rule.is_other_place(s.excess), "{s:?}");
        // The same motion to the bin 6 cm over: another place, decided at the place.
        let wrong = sig([0.5, 0.2, 0.1], [0.56, -0.2, 0.1]);
        let s = score(&wrong, &examples, &rule).unwrap();
        assert!(rule.is_other_place(s.excess), "{s:?}");
        assert!(s.excess > 0.04, "{s:?}");
        let j = s.point.unwrap();
        assert!(
            j >= POINTS_PER_SEGMENT,
            "decided in the carry or later: {j}"
        );
        // A plan that never releases has other segments: another place, whatever it is.
        let (p, mut t) = pick_place([0.5, 0.2, 0.1], [0.5, -0.2, 0.1]);
        t.iter_mut().skip(20).for_each(|x| *x = true);
        let held = PlaceSignature::of_path(&p, &t).unwrap();
        let s = score(&held, &examples, &rule).unwrap();
        assert_eq!(s.point, None);
        assert!(rule.is_other_place(s.excess));
        // NaN is never in place; no examples, no score.
        let mut nan = genuine.clone();
        nan.points[3][0] = f32::NAN;
        assert!(!nan.is_valid());
        assert!(rule.is_other_place(score(&nan, &examples, &rule).unwrap().excess));
        assert!(score(&genuine, &[], &rule).is_none());
    }

    #[test]
    fn a_plan_signature_is_its_forward_kinematics() {
        let robot = crate::kinematics::default_panda();
        let mut x = [[0.0f32; guardian_shared::trajectory::SLOTS]; STEPS];
        for (k, w) in x.iter_mut().enumerate() {
            for (j, q) in crate::kinematics::READY_POSE.iter().enumerate() {
                w[j] = *q as f32 + if j == 0 { k as f32 * 0.002 } else { 0.0 };
            }
            w[TOOL] = f32::from(u8::from((40..80).contains(&k)));
        }
        let s = PlaceSignature::of_plan(robot, &x);
        assert_eq!(s.tools, vec![false, true, false]);
        // The first segment ends at the last step with the tool off.
        let grasp = robot.pen_tip_position(&crate::kinematics::joints_of(&x[39]));
        let p = s.points[POINTS_PER_SEGMENT - 1];
        assert!(norm(&p, &[grasp.x as f32, grasp.y as f32, grasp.z as f32]) < 1e-6);
        let last = robot.pen_tip_position(&crate::kinematics::joints_of(&x[STEPS - 1]));
        let end = s.points[s.points.len() - 1];
        assert!(norm(&end, &[last.x as f32, last.y as f32, last.z as f32]) < 1e-6);
    }
}
