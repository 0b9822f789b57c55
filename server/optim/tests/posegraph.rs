//! Pose graphs: the public benchmarks' known optima, and synthetic graphs with known truth.

use nalgebra::{UnitQuaternion, Vector3, Vector6};
use vsgraphs_optim::factors::pose::{BetweenFactor, PoseError};
use vsgraphs_optim::g2o::{PoseGraph, Start};
use vsgraphs_optim::testing::{shared_data, Rng};
use vsgraphs_optim::{
    FactorId, Information, Kernel, Key, Method, Options, Problem, Se3, SolveError, Solver,
    Termination, Values,
};

fn data_file(name: &str) -> Option<std::path::PathBuf> {
    shared_data(&format!("posegraph/{name}"))
}

/// Optimises a benchmark file from its initial values and returns the final cost.
fn optimum(name: &str, error: PoseError) -> Option<f64> {
    let graph = PoseGraph::read(&data_file(name)?).unwrap();
    let (mut problem, _) = graph.to_problem(error).unwrap();
    let report = Solver::default().solve(&mut problem).unwrap();
    eprintln!(
        "{name} {error:?}: {:.6} -> {:.6} in {} iterations ({:?})",
        report.initial_cost,
        report.final_cost,
        report.iterations.len(),
        report.termination
    );
    assert!(matches!(
        report.termination,
        Termination::CostConverged | Termination::StepConverged | Termination::GradientConverged
    ));
    // The cost the solver reports is the cost of the values it leaves in the problem.
    assert!((problem.cost() - report.final_cost).abs() <= 1e-12 * report.final_cost);
    Some(report.final_cost)
}

fn assert_relative(value: f64, reference: f64, tolerance: f64) {
    let relative = (value - reference).abs() / reference;
    assert!(
        relative < tolerance,
        "{value} vs {reference}: relative {relative:e}"
    );
}

// Reference optima from the data README (g2o's own tool for the chi2 of the first two).
#[test]
fn sphere2500_reaches_g2o_optimum() {
    if let Some(cost) = optimum("sphere2500.g2o", PoseError::Quaternion) {
        assert_relative(cost, 727.1495, 1e-4);
    }
}

#[test]
fn parking_garage_reaches_g2o_optimum() {
    if let Some(cost) = optimum("parking-garage.g2o", PoseError::Quaternion) {
        assert_relative(cost, 1.23868, 1e-4);
    }
}

#[test]
fn small_grid_reaches_g2o_optimum() {
    if let Some(cost) = optimum("smallGrid3D.g2o", PoseError::Quaternion) {
        assert_relative(cost, 458.154, 1e-5);
    }
}

#[test]
fn log_map_optima() {
    // The README gives these to four or five significant figures.
    // (smallGrid3D's log-map optimum is not checked: from its initial values and from g2o's
    // optimum alike we reach 1035.85, 1% above the README's "≈ 1025.50"; see BENCHMARKS.md.)
    for (name, reference) in [("sphere2500.g2o", 1351.40), ("parking-garage.g2o", 1.2684)] {
        if let Some(cost) = optimum(name, PoseError::LogMap) {
            assert_relative(cost, reference, 1e-4);
        }
    }
}

/// A robot driving two laps of a square-ish loop, with odometry between consecutive poses and
/// loop closures between the laps; measurements carry Gaussian noise of known size.
struct Synthetic {
    truth: Vec<Se3>,
    problem: Problem,
    keys: Vec<Key<Se3>>,
    residual_dims: usize,
}

const SIGMA_T: f64 = 0.02;
const SIGMA_R: f64 = 0.01;

fn noisy(rng: &mut Rng, z: Se3) -> Se3 {
    let mut xi = Vector6::zeros();
    for i in 0..3 {
        xi[i] = rng.normal() * SIGMA_T;
        xi[i + 3] = rng.normal() * SIGMA_R;
    }
    z.retract(&xi)
}

fn synthetic(seed: u64, kernel: Option<Kernel>) -> Synthetic {
    let mut rng = Rng::new(seed);
    let per_lap = 100;
    let truth: Vec<Se3> = (0..2 * per_lap)
        .map(|k| {
            let a = 2.0 * std::f64::consts::PI * (k % per_lap) as f64 / per_lap as f64;
            let lap = (k / per_lap) as f64;
            Se3::new(
                UnitQuaternion::from_euler_angles(
                    0.05 * a.sin(),
                    0.0,
                    a + std::f64::consts::FRAC_PI_2,
                ),
                Vector3::new(
                    10.0 * a.cos(),
                    10.0 * a.sin(),
                    0.3 * lap + 0.2 * (3.0 * a).sin(),
                ),
            )
        })
        .collect();
    // Initial values: dead reckoning from the noisy odometry.
    let odometry: Vec<Se3> = truth
        .windows(2)
        .map(|w| noisy(&mut rng, w[0].inverse().compose(&w[1])))
        .collect();
    let mut values = Values::new();
    let mut pose = truth[0];
    let mut keys = vec![values.add(pose)];
    for z in &odometry {
        pose = pose.compose(z);
        keys.push(values.add(pose));
    }
    values.set_fixed(keys[0].id, true);
    let mut problem = Problem::new(values);
    let info = || {
        Information::from_sigmas(&[SIGMA_T, SIGMA_T, SIGMA_T, SIGMA_R, SIGMA_R, SIGMA_R]).unwrap()
    };
    let mut residual_dims = 0;
    for (k, z) in odometry.iter().enumerate() {
        problem
            .add(
                BetweenFactor::new(keys[k], keys[k + 1], *z, PoseError::LogMap),
                info(),
                kernel,
            )
            .unwrap();
        residual_dims += 6;
    }
    for k in (0..per_lap).step_by(5) {
        let j = k + per_lap;
        let z = noisy(&mut rng, truth[k].inverse().compose(&truth[j]));
        problem
            .add(
                BetweenFactor::new(keys[k], keys[j], z, PoseError::LogMap),
                info(),
                kernel,
            )
            .unwrap();
        residual_dims += 6;
    }
    Synthetic {
        truth,
        problem,
        keys,
        residual_dims,
    }
}

fn position_rmse(values: &Values, keys: &[Key<Se3>], truth: &[Se3]) -> f64 {
    let sum: f64 = keys
        .iter()
        .zip(truth)
        .map(|(k, t)| (values.get(*k).translation - t.translation).norm_squared())
        .sum();
    (sum / truth.len() as f64).sqrt()
}

#[test]
fn synthetic_pose_graph_recovers_truth_within_noise() {
    let Synthetic {
        truth,
        mut problem,
        keys,
        residual_dims,
    } = synthetic(3, None);
    let before = position_rmse(problem.values(), &keys, &truth);
    let report = Solver::default().solve(&mut problem).unwrap();
    let after = position_rmse(problem.values(), &keys, &truth);
    // With Gaussian noise of the modelled size, the minimum cost is chi-square distributed with
    // (residuals − unknowns) degrees of freedom: its mean per degree of freedom is 1.
    let dof = (residual_dims - 6 * (truth.len() - 1)) as f64;
    let per_dof = report.final_cost / dof;
    eprintln!("position RMSE {before:.3} m -> {after:.3} m, cost per dof {per_dof:.3}");
    assert!(after < 0.25 * before, "{before} -> {after}");
    assert!(after < 0.3, "{after}");
    assert!((0.5..2.0).contains(&per_dof), "{per_dof}");
}

/// A map already optimised receives false loop closures (places metres apart claimed to be
/// the same), as a SLAM system's place recognition sometimes proposes. Loop closures carry the
/// kernel; odometry does not.
fn with_false_closures(kernel: Option<Kernel>) -> f64 {
    let Synthetic {
        truth,
        mut problem,
        keys,
        ..
    } = synthetic(5, None);
    let mut solver = Solver::default();
    solver.solve(&mut problem).unwrap();
    let odometry = truth.len() - 1;
    for f in odometry..problem.num_factors() {
        problem.set_kernel(FactorId(f as u32), kernel);
    }
    let info =
        Information::from_sigmas(&[SIGMA_T, SIGMA_T, SIGMA_T, SIGMA_R, SIGMA_R, SIGMA_R]).unwrap();
    for o in 0..4 {
        let (i, j) = (10 + 17 * o, 60 + 23 * o);
        problem
            .add(
                BetweenFactor::new(keys[i], keys[j], Se3::identity(), PoseError::LogMap),
                info.clone(),
                kernel,
            )
            .unwrap();
    }
    solver.solve(&mut problem).unwrap();
    position_rmse(problem.values(), &keys, &truth)
}

#[test]
fn robust_kernel_rejects_false_loop_closures() {
    let clean = {
        let Synthetic {
            truth,
            mut problem,
            keys,
            ..
        } = synthetic(5, None);
        Solver::default().solve(&mut problem).unwrap();
        position_rmse(problem.values(), &keys, &truth)
    };
    let plain = with_false_closures(None);
    let robust = with_false_closures(Some(Kernel::GemanMcClure(3.0)));
    let cauchy = with_false_closures(Some(Kernel::Cauchy(3.0)));
    eprintln!(
        "position RMSE: no false closures {clean:.3} m; with 4: plain {plain:.3} m, \
         Geman-McClure {robust:.3} m, Cauchy {cauchy:.3} m"
    );
    assert!(plain > 1.0, "{plain}");
    assert!(robust < clean + 0.02, "{robust} vs {clean}");
    assert!(cauchy < plain, "{cauchy} vs {plain}");
}

#[test]
fn gauss_newton_agrees_with_levenberg_marquardt() {
    let Synthetic { mut problem, .. } = synthetic(7, None);
    let lm = Solver::default().solve(&mut problem).unwrap().final_cost;
    let Synthetic { mut problem, .. } = synthetic(7, None);
    let gn = Solver::new(Options {
        method: Method::GaussNewton,
        ..Options::default()
    })
    .solve(&mut problem)
    .unwrap()
    .final_cost;
    assert!((lm - gn).abs() < 1e-6 * lm, "{lm} {gn}");
}

#[test]
fn failure_keeps_the_last_good_values() {
    // No pose fixed: H is singular (the gauge is free), so Gauss–Newton cannot factor it.
    let Synthetic {
        mut problem, keys, ..
    } = synthetic(9, None);
    problem.values_mut().set_fixed(keys[0].id, false);
    let before = problem.values().clone();
    let result = Solver::new(Options {
        method: Method::GaussNewton,
        ..Options::default()
    })
    .solve(&mut problem);
    match result {
        Err(SolveError::LinearSolve { iteration, .. }) => assert_eq!(iteration, 1),
        Ok(report) => panic!("solved a singular system: {:?}", report.termination),
        Err(other) => panic!("{other}"),
    }
    for k in &keys {
        assert_eq!(problem.values().get(*k), before.get(*k));
    }
    // Levenberg–Marquardt's damping makes the same problem solvable.
    let report = Solver::default().solve(&mut problem).unwrap();
    assert!(report.final_cost < report.initial_cost);
}

#[test]
fn nothing_to_do_and_non_finite_input() {
    let Synthetic {
        mut problem, keys, ..
    } = synthetic(11, None);
    for k in &keys {
        problem.values_mut().set_fixed(k.id, true);
    }
    let report = Solver::default().solve(&mut problem).unwrap();
    assert_eq!(report.termination, Termination::NothingToDo);
    problem.values_mut().set_fixed(keys[1].id, false);
    let mut broken = *problem.values().get(keys[1]);
    broken.translation.x = f64::NAN;
    problem.values_mut().set(keys[1], broken);
    assert!(matches!(
        Solver::default().solve(&mut problem),
        Err(SolveError::NonFiniteInitialCost(_))
    ));
}

#[test]
fn analysis_is_reused_until_the_structure_changes() {
    let Synthetic {
        mut problem, keys, ..
    } = synthetic(13, None);
    let mut solver = Solver::default();
    let first = solver.solve(&mut problem).unwrap();
    assert!(first.analysis_time > std::time::Duration::ZERO);
    // Same structure, new values: the analysis is kept.
    let moved = problem
        .values()
        .get(keys[5])
        .retract(&Vector6::repeat(0.01));
    problem.values_mut().set(keys[5], moved);
    let second = solver.solve(&mut problem).unwrap();
    assert_eq!(second.analysis_time, std::time::Duration::ZERO);
    // A new factor changes the sparsity: analysed again, and the result is still right.
    let z = problem
        .values()
        .get(keys[3])
        .inverse()
        .compose(problem.values().get(keys[150]));
    problem
        .add(
            BetweenFactor::new(keys[3], keys[150], z, PoseError::LogMap),
            Information::isotropic(6, 0.05).unwrap(),
            None,
        )
        .unwrap();
    let third = solver.solve(&mut problem).unwrap();
    assert!(third.analysis_time > std::time::Duration::ZERO);
    assert!((third.final_cost - problem.cost()).abs() < 1e-9 * third.final_cost.max(1.0));
}

/// A grid of poses one metre apart, each turned at random, joined to its neighbours along
/// each axis; the first edges are the odometry of a walk that snakes through the grid.
/// Measurements carry rotation noise of `sigma_r` rad (large: poses chained along them are
/// far off) and 2 cm of translation noise.
fn noisy_grid(seed: u64, side: usize, sigma_r: f64) -> (PoseGraph, Vec<Se3>) {
    use vsgraphs_optim::g2o::Edge;
    let mut rng = Rng::new(seed);
    let sigma_t = 0.02;
    let at = |x: usize, y: usize, z: usize| (z * side + y) * side + x;
    let mut truth = vec![Se3::identity(); side * side * side];
    for z in 0..side {
        for y in 0..side {
            for x in 0..side {
                let rotation = UnitQuaternion::from_scaled_axis(rng.vector3(1.0));
                truth[at(x, y, z)] = Se3::new(rotation, Vector3::new(x as f64, y as f64, z as f64));
            }
        }
    }
    // The snake: x back and forth, then y back and forth, then z.
    let mut walk = Vec::new();
    for z in 0..side {
        for yy in 0..side {
            let y = if z.is_multiple_of(2) {
                yy
            } else {
                side - 1 - yy
            };
            for xx in 0..side {
                let x = if (z * side + yy).is_multiple_of(2) {
                    xx
                } else {
                    side - 1 - xx
                };
                walk.push(at(x, y, z));
            }
        }
    }
    let mut pairs: Vec<(usize, usize)> = walk.windows(2).map(|w| (w[0], w[1])).collect();
    for z in 0..side {
        for y in 0..side {
            for x in 0..side {
                let i = at(x, y, z);
                for j in [
                    (x + 1 < side).then(|| at(x + 1, y, z)),
                    (y + 1 < side).then(|| at(x, y + 1, z)),
                    (z + 1 < side).then(|| at(x, y, z + 1)),
                ]
                .into_iter()
                .flatten()
                {
                    if !pairs.contains(&(i, j)) && !pairs.contains(&(j, i)) {
                        pairs.push((i, j));
                    }
                }
            }
        }
    }
    let information = nalgebra::Matrix6::from_diagonal(&Vector6::new(
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_t * sigma_t),
        1.0 / (sigma_r * sigma_r),
        1.0 / (sigma_r * sigma_r),
        1.0 / (sigma_r * sigma_r),
    ));
    let edges = pairs
        .into_iter()
        .enumerate()
        .map(|(line, (i, j))| {
            let mut xi = Vector6::zeros();
            for k in 0..3 {
                xi[k] = rng.normal() * sigma_t;
                xi[k + 3] = rng.normal() * sigma_r;
            }
            Edge {
                from: i as u64,
                to: j as u64,
                measured: truth[i].inverse().compose(&truth[j]).retract(&xi),
                information,
                line,
            }
        })
        .collect();
    let graph = PoseGraph {
        vertices: truth
            .iter()
            .enumerate()
            .map(|(i, p)| (i as u64, *p))
            .collect(),
        edges,
        fixed: vec![0],
        skipped: Default::default(),
    };
    (graph, truth)
}

fn solved_from(graph: &PoseGraph, start: Start) -> f64 {
    let mut graph = graph.clone();
    graph.restart(start).unwrap();
    let (mut problem, _) = graph.to_problem(PoseError::LogMap).unwrap();
    let options = Options {
        max_iterations: 200,
        ..Options::default()
    };
    Solver::new(options).solve(&mut problem).unwrap().final_cost
}

#[test]
fn chordal_start_reaches_the_optimum_where_chained_odometry_does_not() {
    let mut chain_missed = 0;
    // Up to half a radian (29°) of noise on every relative rotation. At 0.7 rad the chordal
    // start too led to a local minimum (BENCHMARKS.md).
    for (seed, sigma_r) in [(1, 0.1), (2, 0.2), (3, 0.3), (4, 0.3), (5, 0.5), (6, 0.5)] {
        let (graph, _) = noisy_grid(seed, 6, sigma_r);
        // From the truth: the optimum nearest it, which with this noise is the global one.
        let from_truth = solved_from(&graph, Start::File);
        let from_chain = solved_from(&graph, Start::Chain);
        let from_chordal = solved_from(&graph, Start::Chordal);
        eprintln!(
            "grid seed {seed}, rotation noise {sigma_r} rad: optimum from the truth \
             {from_truth:.3}, from chained odometry {from_chain:.3}, from chordal {from_chordal:.3}"
        );
        assert!(
            (from_chordal - from_truth).abs() < 1e-6 * from_truth,
            "{from_chordal} vs {from_truth}"
        );
        if from_chain > from_truth * (1.0 + 1e-6) {
            chain_missed += 1;
        }
    }
    // The grids are hard enough to matter: from chained odometry the solver stops short.
    assert!(
        chain_missed >= 2,
        "chained odometry missed only {chain_missed}"
    );
}

#[test]
fn benchmarks_reach_their_optima_from_chained_odometry_and_from_chordal() {
    for (name, reference) in [
        ("smallGrid3D.g2o", 458.154),
        ("sphere2500.g2o", 727.1495),
        ("parking-garage.g2o", 1.23868),
    ] {
        let Some(path) = data_file(name) else { return };
        let graph = PoseGraph::read(&path).unwrap();
        for start in [Start::Chain, Start::Chordal] {
            let mut started = graph.clone();
            started.restart(start).unwrap();
            let (mut problem, _) = started.to_problem(PoseError::Quaternion).unwrap();
            let initial = problem.cost();
            let report = Solver::default().solve(&mut problem).unwrap();
            eprintln!(
                "{name} from {start:?}: {initial:.6} -> {:.6} in {} iterations",
                report.final_cost,
                report.iterations.len()
            );
            assert_relative(report.final_cost, reference, 1e-4);
        }
    }
}
