//! `guardianctl robot`: load a robot description (a built-in name or a file), print its
//! chain, and check its kinematics before a daemon serves it or a data set is drawn with it:
//! the specialised FK against the general chain, the Jacobian against finite differences,
//! IK round trips, and the drawing workspace (home pose above the canvas centre, every
//! canvas corner reachable at pen height with the commanded tool orientation).

use guardian_robot::kinematics::{
    IkOptions, JointKind, JointVector, MAX_JOINTS, Robot, RobotDescription,
};
use nalgebra::{DMatrix, Vector3};
use rand::{Rng, SeedableRng, rngs::StdRng};

use guardian_omniglot::path::{Geometry, PathPoint, PathSolver};

/// One check and its outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    /// What was checked.
    pub name: String,
    /// The figure measured, as text.
    pub figure: String,
    /// Whether it passed.
    pub passed: bool,
}

/// Everything `guardianctl robot` found.
#[derive(Debug, Clone)]
pub struct RobotReport {
    /// The description.
    pub description: RobotDescription,
    /// The home pose (IK for the pen 2 cm above the canvas centre from the home seed), if
    /// it was found.
    pub home: Option<JointVector>,
    /// The checks, in order.
    pub checks: Vec<Check>,
}

impl RobotReport {
    /// Every check passed.
    pub fn passed(&self) -> bool {
        self.checks.iter().all(|c| c.passed)
    }
}

/// Random joint vectors inside `robot`'s limits, 10 % away from each limit.
fn random_q(rng: &mut StdRng, robot: &Robot) -> JointVector {
    let mut q = [0.0; MAX_JOINTS];
    for ((v, &lo), &hi) in q.iter_mut().zip(robot.q_min()).zip(robot.q_max()) {
        let pad = 0.1 * (hi - lo);
        *v = if hi - lo > 0.0 {
            rng.random_range(lo + pad..hi - pad)
        } else {
            lo
        };
    }
    q
}

/// Smallest singular value of the pen-tip Jacobian at `q` (its first `joints` columns).
pub fn smallest_singular_value(robot: &Robot, q: &JointVector) -> f64 {
    let (_, jac) = robot.jacobian(q);
    let n = robot.joints();
    let m = DMatrix::from_fn(6, n, |r, c| jac[(r, c)]);
    m.singular_values()
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min)
}

/// Run every check on `description` (deterministic: seeded).
pub fn check(description: RobotDescription) -> RobotReport {
    let robot = &description.robot;
    let mut rng = StdRng::seed_from_u64(1);
    let mut checks = Vec::new();

    // 1. The specialised position FK against the general chain.
    let mut worst = 0.0f64;
    for _ in 0..1000 {
        let q = random_q(&mut rng, robot);
        let fast = robot.pen_tip_position(&q);
        let general = robot.pen_tip(&q).translation;
        worst = worst.max((fast - general).norm());
    }
    checks.push(Check {
        name: "pen-tip FK, fast path vs general chain (1,000 poses)".into(),
        figure: match robot.position_fk() {
            Some(_) => format!("specialised SIMD FK, worst {worst:.1e} m"),
            None => "general chain only (origins are not axis permutations)".into(),
        },
        passed: worst <= 1e-12,
    });

    // 2. The Jacobian against central finite differences.
    let mut worst = 0.0f64;
    let h = 1e-6;
    for _ in 0..100 {
        let q = random_q(&mut rng, robot);
        let (tip, jac) = robot.jacobian(&q);
        for j in 0..robot.joints() {
            let (mut qp, mut qm) = (q, q);
            qp[j] += h;
            qm[j] -= h;
            let (fp, fm) = (robot.pen_tip(&qp), robot.pen_tip(&qm));
            let lin = (fp.translation - fm.translation) / (2.0 * h);
            let s = (fp.rotation - fm.rotation) * tip.rotation.transpose() / (2.0 * h);
            let w = Vector3::new(s[(2, 1)], s[(0, 2)], s[(1, 0)]);
            for k in 0..3 {
                worst = worst
                    .max((jac[(k, j)] - lin[k]).abs())
                    .max((jac[(3 + k, j)] - w[k]).abs());
            }
        }
    }
    checks.push(Check {
        name: "Jacobian vs finite differences (100 poses)".into(),
        figure: format!("worst {worst:.1e}"),
        passed: worst <= 1e-6,
    });

    // 3. IK round trips from a nearby seed.
    let opts = IkOptions::default();
    let (mut solved, trials) = (0, 200);
    for _ in 0..trials {
        let q_true = random_q(&mut rng, robot);
        let target = robot.pen_tip(&q_true);
        let mut seed = q_true;
        for q in &mut seed[..robot.joints()] {
            *q += rng.random_range(-0.05..0.05);
        }
        if let Ok(q) = robot.ik(&target, &seed, &opts) {
            let got = robot.pen_tip(&q).translation;
            if (got - target.translation).norm() <= opts.position_tolerance
                && robot.limit_margin(&q) >= 0.0
            {
                solved += 1;
            }
        }
    }
    checks.push(Check {
        name: format!("IK round trips ({trials} poses, seed within 0.05 of the solution)"),
        figure: format!("{solved}/{trials} solved"),
        passed: solved == trials,
    });

    // 4. The drawing workspace: home pose, canvas corners at pen height.
    let name = match &description.source {
        guardian_robot::kinematics::RobotSource::Builtin(n) => (*n).to_string(),
        guardian_robot::kinematics::RobotSource::File(p) => p.display().to_string(),
    };
    let mut home = None;
    match Geometry::for_robot(&name).and_then(|g| Ok((PathSolver::new(&g)?, g))) {
        Err(e) => checks.push(Check {
            name: "home pose: pen 2 cm above the canvas centre".into(),
            figure: e.to_string(),
            passed: false,
        }),
        Ok((solver, g)) => {
            let q = *solver.home();
            home = Some(q);
            checks.push(Check {
                name: "home pose: pen 2 cm above the canvas centre".into(),
                figure: format!(
                    "found, smallest Jacobian singular value {:.3}",
                    smallest_singular_value(robot, &q)
                ),
                passed: true,
            });
            let half = 0.5 * g.canvas_side;
            let (cx, cy) = (g.canvas_center[0], g.canvas_center[1]);
            let mut reached = 0;
            let mut smallest = f64::INFINITY;
            let mut failures = Vec::new();
            for (sx, sy) in [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)] {
                let p = Vector3::new(cx + sx * half, cy + sy * half, g.canvas_z);
                let path = [PathPoint {
                    position: p,
                    pen_down: true,
                }];
                match solver.solve(&path) {
                    Ok(dense) => {
                        reached += 1;
                        let q = robot.joints_of(&dense.waypoints[0]);
                        smallest = smallest.min(smallest_singular_value(robot, &q));
                    }
                    Err(e) => failures.push(format!("({:.3}, {:.3}): {e}", p.x, p.y)),
                }
            }
            checks.push(Check {
                name: "canvas corners at pen height, tool orientation held".into(),
                figure: if failures.is_empty() {
                    format!("4/4 reached, smallest Jacobian singular value {smallest:.3}")
                } else {
                    format!("{reached}/4 reached; {}", failures.join("; "))
                },
                passed: failures.is_empty(),
            });
        }
    }
    RobotReport {
        description,
        home,
        checks,
    }
}

/// Run `guardianctl robot ROBOT` (exit status 1 if a check fails).
pub fn run(robot: &str) -> anyhow::Result<()> {
    let d = RobotDescription::resolve(robot)?;
    let report = check(d);
    let d = &report.description;
    let r = &d.robot;
    println!("robot        {} ({})", r.name(), d.source);
    println!("URDF sha256  {}", r.urdf_sha256_hex());
    println!(
        "joints       {} (trajectories: {} channels, q1..q{} then the tool)",
        r.joints(),
        r.channels(),
        r.joints()
    );
    println!("  #  name                    kind       axis            lower      upper   velocity");
    for (j, joint) in r.joint_list().iter().enumerate() {
        let a = joint.axis;
        println!(
            "  {:<2} {:<23} {:<10} [{:>4.1} {:>4.1} {:>4.1}] {:>9.4} {:>9.4}   {}",
            j + 1,
            joint.name,
            match joint.kind {
                JointKind::Revolute => "revolute",
                JointKind::Prismatic => "prismatic",
            },
            a.x,
            a.y,
            a.z,
            r.q_min()[j],
            r.q_max()[j],
            joint
                .velocity
                .map_or("-".to_string(), |v| format!("{v:.4}"))
        );
    }
    let f = r.flange_offset().translation;
    let t = &d.tool;
    println!(
        "flange       [{:.4}, {:.4}, {:.4}] m after the last joint",
        f.x, f.y, f.z
    );
    println!(
        "tool         xyz {:?} m, rpy {:?} rad (in the flange frame)",
        t.xyz, t.rpy
    );
    let n = r.joints();
    println!("home seed    {:?}", &d.home_seed[..n]);
    if let Some(h) = &report.home {
        let rounded: Vec<String> = h[..n].iter().map(|v| format!("{v:.4}")).collect();
        println!("home         [{}]", rounded.join(", "));
    }
    let w = &d.workcell;
    println!(
        "workcell     canvas {:.3} m square at ({:.3}, {:.3}), pen height {:.3} m, hover {:.3} m, rules {}",
        w.canvas_side,
        w.canvas_x,
        w.canvas_y,
        w.canvas_z,
        w.hover,
        if w.enabled { "on" } else { "off" }
    );
    println!("checks");
    for c in &report.checks {
        println!(
            "  {}  {:<62} {}",
            if c.passed { "ok  " } else { "FAIL" },
            c.name,
            c.figure
        );
    }
    if !report.passed() {
        anyhow::bail!("{}: a kinematics check failed", r.name());
    }
    Ok(())
}

/// The checks on the shipped robots and on a description whose canvas the arm cannot reach.
#[cfg(test)]
mod tests {
    use super::*;
    use guardian_robot::kinematics::{RobotDescription, UR5E_URDF};

    #[test]
    fn both_shipped_robots_pass_every_check() {
        for name in ["panda", "ur5e"] {
            let report = check(RobotDescription::named(name).unwrap());
            for c in &report.checks {
                assert!(c.passed, "{name}: {} — {}", c.name, c.figure);
            }
            assert_eq!(report.checks.len(), 5, "{name}");
            let home = report.home.expect("home pose");
            // The home pose holds the pen 2 cm above the canvas centre.
            let p = report.description.robot.pen_tip(&home).translation;
            assert!(
                (p - nalgebra::Vector3::new(0.5, 0.0, 0.17)).norm() < 1e-5,
                "{name}: {p}"
            );
        }
        // The UR5e home is elbow up, as seeded, and well conditioned (measured ~0.23).
        let ur = check(RobotDescription::named("ur5e").unwrap());
        let sv = smallest_singular_value(&ur.description.robot, &ur.home.unwrap());
        assert!(sv > 0.1, "{sv}");
    }

    #[test]
    fn a_canvas_out_of_reach_fails_the_workspace_check() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("ur5e.urdf"), UR5E_URDF).unwrap();
        let far = include_str!("../../models/robots/ur5e.toml")
            .replace("canvas-x = 0.5", "canvas-x = 1.5");
        let path = dir.path().join("far.toml");
        std::fs::write(&path, far).unwrap();
        let report = check(RobotDescription::load(&path).unwrap());
        assert!(!report.passed());
        let home = report
            .checks
            .iter()
            .find(|c| c.name.starts_with("home"))
            .unwrap();
        assert!(!home.passed, "{}", home.figure);
        // The chain itself is fine.
        assert!(report.checks[..3].iter().all(|c| c.passed));
    }
}
