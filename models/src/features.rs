//! Features the embedder computes from a resampled joint trajectory, inside `embed`, so
//! callers only ever pass [`Resampled`].
//!
//! * [`FeatureKind::Joints`] — the paper's input: the 7 joint angles scaled to `[-1, 1]` by
//!   the Panda limits, and the tool channel as `±1` (Panda trajectories only).
//! * [`FeatureKind::Pen`] — the pen-tip path on the canvas from forward kinematics, with the
//!   drawing's position and size normalised away: `x, y` (bounding box of the pen-down part
//!   centred, longest side scaled to 2), the pen state, the undirected tangent
//!   `(cos 2θ, sin 2θ)` (the same for a stroke drawn either way) and the directed unit tangent.
//!   What varies between drawers of one character (where and how large they drew it, speed)
//!   is removed here; what joint angles hide (the pen path is their forward kinematics) is
//!   made explicit.

use guardian_shared::trajectory::{Resampled, STEPS, TOOL};

use guardian_robot::kinematics::{PANDA_JOINTS, PANDA_Q_MAX, PANDA_Q_MIN};
use guardian_robot::pen::{PenPoint, pen_down_box, pen_path};
use serde::{Deserialize, Serialize};

/// Which features the network sees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum FeatureKind {
    /// Joint angles and tool state, scaled (8 channels).
    Joints,
    /// Normalised pen-tip path features from forward kinematics (7 channels).
    Pen,
    /// A picture of the pen-down path: the segments whose both ends are pen down, splatted
    /// bilinearly into a [`PICTURE_SIDE`] x [`PICTURE_SIDE`] image after the pen features'
    /// bounding-box normalisation (see [`picture`]). Blind to stroke order and direction by
    /// construction. One channel, [`PICTURE_SIDE`]² "steps" (pixels, row-major, top row
    /// first).
    Picture,
}

impl FeatureKind {
    /// Feature channels per step (per pixel for [`FeatureKind::Picture`]).
    pub fn channels(self) -> usize {
        match self {
            Self::Joints => 8,
            Self::Pen => PEN_CHANNELS,
            Self::Picture => 1,
        }
    }

    /// Steps of the network input: [`STEPS`] time steps, or the pixels of a picture.
    pub fn steps(self) -> usize {
        match self {
            Self::Picture => PICTURE_SIDE * PICTURE_SIDE,
            _ => STEPS,
        }
    }

    /// Values of one network input: `steps() * channels()`.
    pub fn values(self) -> usize {
        self.steps() * self.channels()
    }

    /// A picture, read by a 2D network, rather than a sequence.
    pub fn is_picture(self) -> bool {
        self == Self::Picture
    }
}

/// Side of the picture of [`FeatureKind::Picture`] (pixels).
pub const PICTURE_SIDE: usize = 32;

/// Channels of [`FeatureKind::Pen`].
pub const PEN_CHANNELS: usize = 7;

/// A geometric augmentation applied to the pen path before normalisation (training, and a
/// model's test-time views: [`Augment::of_view`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Augment {
    /// Rotation about the drawing's centre (rad).
    pub rotation: f32,
    /// Horizontal shear (x += shear * y).
    pub shear: f32,
    /// Scale of x.
    pub scale_x: f32,
    /// Scale of y.
    pub scale_y: f32,
    /// Reverse time (every stroke drawn backwards, strokes in reverse order).
    pub reverse: bool,
}

impl Default for Augment {
    fn default() -> Self {
        Self {
            rotation: 0.0,
            shear: 0.0,
            scale_x: 1.0,
            scale_y: 1.0,
            reverse: false,
        }
    }
}

impl Augment {
    /// The augmentation of a test-time view (see [`TestView`]), optionally
    /// time-reversed.
    pub fn of_view(view: &TestView, reverse: bool) -> Self {
        let stretch = f32::from(view.stretch) * 1e-3;
        Self {
            rotation: f32::from(view.rotation) * 1e-3,
            shear: f32::from(view.shear) * 1e-3,
            scale_x: 1.0 + stretch,
            scale_y: 1.0 - stretch,
            reverse,
        }
    }
}

/// Write the features of the Panda trajectory `x` for `kind` into `out`
/// (`STEPS * kind.channels()`, row-major by time step).
pub fn compute(kind: FeatureKind, x: &Resampled, out: &mut [f32]) {
    match kind {
        FeatureKind::Joints => joint_features(x, out),
        FeatureKind::Pen => pen_features(&pen_path(x), &Augment::default(), out),
        FeatureKind::Picture => picture(&pen_path(x), &Augment::default(), out),
    }
}

/// Features of `kind` from a pen path after an augmentation (pen kinds only; joint
/// features ignore the path and are written as zeros).
pub fn path_features(kind: FeatureKind, path: &[PenPoint; STEPS], aug: &Augment, out: &mut [f32]) {
    match kind {
        FeatureKind::Pen => pen_features(path, aug, out),
        FeatureKind::Picture => picture(path, aug, out),
        FeatureKind::Joints => out.fill(0.0),
    }
}

/// The picture of a pen path after an augmentation ([`FeatureKind::Picture`]) into `out`
/// (`PICTURE_SIDE`², row-major, top row first): the pen-down box of the path is centred and
/// its longest side scaled to `PICTURE_SIDE - 4` pixels (the pen features' normalisation, with
/// a two-pixel margin); every segment between two pen-down samples is splatted bilinearly at
/// four points (its start and three quarters), and a pixel saturates at 1. A path that never
/// touches the canvas gives a blank picture.
pub fn picture(path: &[PenPoint; STEPS], aug: &Augment, out: &mut [f32]) {
    const R: usize = PICTURE_SIDE;
    let out = &mut out[..R * R];
    out.fill(0.0);
    let p = augmented(path, aug);
    let (lo, hi) = pen_down_box(&p);
    let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
    let half = (0.5 * (hi[0] - lo[0]).max(hi[1] - lo[1])).max(2e-3);
    if !half.is_finite() || !centre[0].is_finite() || !centre[1].is_finite() {
        return;
    }
    // Normalised [-1, 1] -> pixel coordinates, the longest side spanning R - 4 pixels.
    let scale = 0.5 * (R as f32 - 4.0);
    let mid = 0.5 * (R as f32 - 1.0);
    let px = |q: &PenPoint| {
        [
            (q[0] - centre[0]) / half * scale + mid,
            (q[1] - centre[1]) / half * scale + mid,
        ]
    };
    let last = (R - 1) as f32;
    for w in p.windows(2) {
        if w[0][2] <= 0.5 || w[1][2] <= 0.5 {
            continue;
        }
        let (a, b) = (px(&w[0]), px(&w[1]));
        for s in 0..4 {
            let t = s as f32 * 0.25;
            let (x, y) = (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t);
            let (x0, y0) = (x.floor(), y.floor());
            let (fx, fy) = (x - x0, y - y0);
            for (dx, dy, wgt) in [
                (0.0, 0.0, (1.0 - fx) * (1.0 - fy)),
                (1.0, 0.0, fx * (1.0 - fy)),
                (0.0, 1.0, (1.0 - fx) * fy),
                (1.0, 1.0, fx * fy),
            ] {
                let xi = (x0 + dx).clamp(0.0, last) as usize;
                let yi = (y0 + dy).clamp(0.0, last) as usize;
                // Drawing "up" is the top of the picture.
                out[(R - 1 - yi) * R + xi] += wgt;
            }
        }
    }
    for v in out.iter_mut() {
        *v = v.min(1.0);
    }
}

/// Rotate, shear, scale and optionally reverse a path (see [`Augment`]).
fn augmented(path: &[PenPoint; STEPS], aug: &Augment) -> [PenPoint; STEPS] {
    let mut p = *path;
    if aug.reverse {
        p.reverse();
    }
    let (cr, sr) = (aug.rotation.cos(), aug.rotation.sin());
    for pt in p.iter_mut() {
        let (x, y) = (pt[0], pt[1]);
        let (x, y) = (cr * x - sr * y, sr * x + cr * y);
        let x = x + aug.shear * y;
        pt[0] = x * aug.scale_x;
        pt[1] = y * aug.scale_y;
    }
    p
}

fn joint_features(x: &Resampled, out: &mut [f32]) {
    let c = FeatureKind::Joints.channels();
    for (t, w) in x.iter().enumerate() {
        let row = &mut out[t * c..(t + 1) * c];
        for j in 0..PANDA_JOINTS {
            let mid = 0.5 * (PANDA_Q_MAX[j] + PANDA_Q_MIN[j]);
            let half = 0.5 * (PANDA_Q_MAX[j] - PANDA_Q_MIN[j]);
            row[j] = ((f64::from(w[j]) - mid) / half) as f32;
        }
        row[PANDA_JOINTS] = 2.0 * w[TOOL] - 1.0;
    }
}

/// Pen features of a pen path after an augmentation (see the module docs).
pub fn pen_features(path: &[PenPoint; STEPS], aug: &Augment, out: &mut [f32]) {
    let c = PEN_CHANNELS;
    let p = augmented(path, aug);
    // Normalise by the bounding box of the pen-down part (all points if never down).
    let (lo, hi) = pen_down_box(&p);
    let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
    let half = (0.5 * (hi[0] - lo[0]).max(hi[1] - lo[1])).max(2e-3);
    for t in 0..STEPS {
        let a = p[t.saturating_sub(1)];
        let b = p[(t + 1).min(STEPS - 1)];
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len = (dx * dx + dy * dy).sqrt();
        let (ux, uy) = if len > 1e-6 {
            (dx / len, dy / len)
        } else {
            (0.0, 0.0)
        };
        let row = &mut out[t * c..(t + 1) * c];
        row[0] = (p[t][0] - centre[0]) / half;
        row[1] = (p[t][1] - centre[1]) / half;
        row[2] = 2.0 * p[t][2] - 1.0;
        row[3] = ux * ux - uy * uy;
        row[4] = 2.0 * ux * uy;
        row[5] = ux;
        row[6] = uy;
    }
}

/// One geometric view of a pen path for test-time augmentation
/// ([`crate::net::NetConfig::test_views`]), in integer thousandths so a config stays exact
/// (and `Eq`): rotated about the drawing's centre by `rotation` mrad, sheared
/// (x += shear/1000 * y), and stretched (x scaled by 1 + stretch/1000, y by
/// 1 - stretch/1000).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct TestView {
    /// Rotation (mrad).
    #[serde(default)]
    pub rotation: i16,
    /// Horizontal shear (thousandths).
    #[serde(default)]
    pub shear: i16,
    /// Stretch of x against y (thousandths).
    #[serde(default)]
    pub stretch: i16,
}

/// Most test views a network may have (each costs one more forward pass per plan).
pub const MAX_TEST_VIEWS: usize = 8;

/// Test views from their specs (see [`TestView`]'s `FromStr`); `none` stands for no view.
pub fn parse_test_views(specs: &[String]) -> Result<Vec<TestView>, String> {
    specs
        .iter()
        .filter(|v| v.as_str() != "none")
        .map(|v| v.parse())
        .collect()
}

impl std::str::FromStr for TestView {
    type Err = String;

    /// `r<mrad>`, `s<thousandths>`, `x<thousandths>`, joined by `+` (e.g. `r100`,
    /// `r-50+x100`).
    fn from_str(spec: &str) -> Result<Self, String> {
        let mut view = TestView::default();
        for part in spec.split('+') {
            let part = part.trim();
            let key = part.chars().next().unwrap_or(' ');
            let value: i16 = part[key.len_utf8().min(part.len())..]
                .parse()
                .map_err(|e| format!("test view {spec:?}: {part:?}: {e}"))?;
            match key {
                'r' => view.rotation = value,
                's' => view.shear = value,
                'x' => view.stretch = value,
                _ => {
                    return Err(format!(
                        "test view {spec:?}: {part:?} is not r<mrad>, s<shear> or x<stretch> (thousandths)"
                    ));
                }
            }
        }
        Ok(view)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straight_line(scale: f32, offset: f32) -> [PenPoint; STEPS] {
        let mut p = [[0.0f32; 3]; STEPS];
        for (t, q) in p.iter_mut().enumerate() {
            let s = t as f32 / (STEPS - 1) as f32;
            *q = [offset + scale * s, offset + 0.5 * scale * s, 1.0];
        }
        p
    }

    #[test]
    fn a_picture_ignores_position_size_stroke_order_and_direction() {
        const N: usize = PICTURE_SIDE * PICTURE_SIDE;
        // Two strokes (a horizontal bar, then a vertical one) with travel between them.
        let draw = |scale: f32, offset: [f32; 2], swapped: bool, reversed: bool| {
            let mut p = [[0.0f32; 3]; STEPS];
            let bar = |t: usize| [t as f32 / 59.0, 0.5];
            let post = |t: usize| [0.5, t as f32 / 59.0];
            for (t, q) in p.iter_mut().enumerate() {
                let (xy, down) = match t {
                    0..60 => (bar(t), true),
                    60..68 => ([0.5, 1.0], false),
                    _ => (post(t - 68), true),
                };
                *q = [
                    offset[0] + scale * xy[0],
                    offset[1] + scale * xy[1],
                    f32::from(down),
                ];
            }
            if swapped {
                let (a, b) = p.split_at_mut(60);
                let bar: Vec<PenPoint> = a.to_vec();
                let post: Vec<PenPoint> = b[8..].to_vec();
                p[..60].copy_from_slice(&post);
                p[60..68].fill([offset[0], offset[1], 0.0]);
                p[68..].copy_from_slice(&bar);
            }
            if reversed {
                p.reverse();
            }
            p
        };
        let render = |p: &[PenPoint; STEPS]| {
            let mut img = vec![0.0f32; N];
            picture(p, &Augment::default(), &mut img);
            img
        };
        let base = render(&draw(0.05, [0.1, 0.2], false, false));
        let ink: f32 = base.iter().sum();
        assert!(ink > 20.0, "the strokes leave ink ({ink})");
        assert!(base.iter().all(|v| (0.0..=1.0).contains(v)));
        let diff = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>();
        // Where and how large it was drawn does not matter.
        let moved = render(&draw(0.02, [-0.3, 0.4], false, false));
        assert!(diff(&base, &moved) < 0.02 * ink, "{}", diff(&base, &moved));
        // Nor the order or direction of the strokes (up to where the quarter points fall).
        for (swapped, reversed) in [(true, false), (false, true), (true, true)] {
            let other = render(&draw(0.05, [0.1, 0.2], swapped, reversed));
            assert!(
                diff(&base, &other) < 0.15 * ink,
                "swapped {swapped} reversed {reversed}: {}",
                diff(&base, &other)
            );
        }
        // A different shape does matter: the bar alone.
        let mut bar_only = draw(0.05, [0.1, 0.2], false, false);
        for q in bar_only[60..].iter_mut() {
            q[2] = 0.0;
        }
        let bar = render(&bar_only);
        assert!(diff(&base, &bar) > 0.3 * ink);
        // The bar is horizontal: its ink lies in few rows and many columns.
        let rows = (0..PICTURE_SIDE)
            .filter(|r| {
                bar[r * PICTURE_SIDE..(r + 1) * PICTURE_SIDE]
                    .iter()
                    .any(|v| *v > 0.0)
            })
            .count();
        assert!(rows <= 3, "{rows} rows");
        // A path that never touches the canvas is a blank picture.
        let mut up = draw(0.05, [0.1, 0.2], false, false);
        for q in up.iter_mut() {
            q[2] = 0.0;
        }
        assert!(render(&up).iter().all(|v| *v == 0.0));
    }

    #[test]
    fn pen_features_ignore_position_and_size() {
        let c = PEN_CHANNELS;
        let mut a = vec![0.0; STEPS * c];
        let mut b = vec![0.0; STEPS * c];
        pen_features(&straight_line(0.05, 0.0), &Augment::default(), &mut a);
        pen_features(&straight_line(0.02, 0.3), &Augment::default(), &mut b);
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-3, "{x} vs {y}");
        }
        // Longest side spans [-1, 1].
        assert!((a[0] + 1.0).abs() < 1e-5 && (a[(STEPS - 1) * c] - 1.0).abs() < 1e-5);
        // Undirected tangent is the same when reversed; directed tangent flips.
        let aug = Augment {
            reverse: true,
            ..Augment::default()
        };
        pen_features(&straight_line(0.05, 0.0), &aug, &mut b);
        let mid = STEPS / 2 * c;
        assert!((a[mid + 3] - b[mid + 3]).abs() < 1e-5);
        assert!((a[mid + 4] - b[mid + 4]).abs() < 1e-5);
        assert!((a[mid + 5] + b[mid + 5]).abs() < 1e-5);
    }
}
