//! Synthetic sample trajectories for tests: valid Panda joint paths (inside the limits,
//! tool 0/1), one smooth joint-space pattern per task class, with small per-"drawer"
//! changes of amplitude, phase, speed and waypoint count. They are not Omniglot drawings
//! and do not draw on the canvas (a daemon with the workcell rules on answers them no-go
//! `Workcell`); they only exercise the protocol and the decision rule. The demo on real
//! drawings is the demo (`cargo run --release --example demo`).

use crate::Waypoint;

/// Joints of the Panda, the robot these samples are for.
pub const JOINTS: usize = 7;

/// The Franka ready pose (rad).
pub const READY: [f32; 7] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785];

/// Sample `drawer` of synthetic task `class`.
pub fn task(class: u32, drawer: u32) -> Vec<Waypoint> {
    let n = 60 + (drawer as usize * 7) % 40;
    let c = class as f32;
    let d = drawer as f32;
    let amp = 0.25 * (1.0 + 0.03 * (d * 1.7).sin());
    let phase = 0.05 * (d * 2.3).cos();
    (0..n)
        .map(|i| {
            let t = i as f32 / (n - 1) as f32;
            let s = t + 0.03 * (d + 1.0).sin() * (std::f32::consts::PI * t).sin();
            let mut w = [0.0f32; guardian_shared::trajectory::SLOTS];
            for (j, q) in w.iter_mut().take(7).enumerate() {
                let f = 1.0 + ((class as usize * 3 + j * 5) % 4) as f32;
                let ph = c * 1.3 + j as f32 * 0.7 + phase;
                let scale = if j == 3 { 0.5 } else { 1.0 };
                *q = READY[j] + amp * scale * (std::f32::consts::TAU * f * s + ph).sin();
            }
            w[3] = w[3].clamp(-3.0, -0.1);
            w[5] = w[5].clamp(0.0, 3.7);
            let band = ((s * (2.0 + (class % 3) as f32)) as u32) % 2;
            w[guardian_shared::trajectory::TOOL] = if band == 0 { 1.0 } else { 0.0 };
            w
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use guardian_shared::trajectory::{JointLimits, validate};

    #[test]
    fn samples_are_valid() {
        // The Panda's published limits.
        let limits = JointLimits::new(
            vec![
                -2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973,
            ],
            vec![2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973],
        )
        .unwrap();
        for c in 0..8 {
            for d in 0..40 {
                validate(&super::task(c, d), &limits).unwrap();
            }
        }
    }
}
