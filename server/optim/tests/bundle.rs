//! Synthetic RGB-D bundle adjustment: the optimiser recovers the ground truth within the noise,
//! with and without the Schur complement of the points, and the two agree.

use vsgraphs_optim::testing::{bundle_scene, BundleConfig, BundleScene};
use vsgraphs_optim::{Options, Solver, Termination};

fn rms(errors: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = errors.fold((0.0, 0), |(s, n), e| (s + e * e, n + 1));
    (sum / n as f64).sqrt()
}

fn keyframe_rmse(scene: &BundleScene) -> f64 {
    let values = scene.problem.values();
    rms(scene
        .keyframes
        .iter()
        .zip(&scene.true_keyframes)
        .map(|(k, t)| (values.get(*k).translation - t.translation).norm()))
}

fn point_rmse(scene: &BundleScene) -> f64 {
    let values = scene.problem.values();
    rms(scene
        .points
        .iter()
        .zip(&scene.true_points)
        .map(|(k, t)| (values.get(*k) - t).norm()))
}

#[test]
fn local_bundle_adjustment_recovers_the_ground_truth() {
    let config = BundleConfig::default();
    let mut scene = bundle_scene(&config, 7);
    assert!(scene.observations > 29_000, "{}", scene.observations);
    let (kf_before, points_before) = (keyframe_rmse(&scene), point_rmse(&scene));
    let report = Solver::new(Options::default())
        .solve(&mut scene.problem)
        .expect("solves");
    let (kf_after, points_after) = (keyframe_rmse(&scene), point_rmse(&scene));
    println!(
        "keyframes {kf_before:.4} -> {kf_after:.5} m, points {points_before:.4} -> {points_after:.4} m, \
         cost {:.1} -> {:.1} in {} iterations ({:?})",
        report.initial_cost,
        report.final_cost,
        report.iterations.len(),
        report.termination
    );
    assert_eq!(report.eliminated_points, config.points);
    assert_eq!(
        report.reduced_dim,
        6 * (config.keyframes - config.fixed_keyframes)
    );
    assert!(matches!(
        report.termination,
        Termination::CostConverged | Termination::GradientConverged | Termination::StepConverged
    ));
    assert!(kf_after < kf_before / 5.0, "keyframe RMSE {kf_after}");
    assert!(
        points_after < points_before / 2.0,
        "point RMSE {points_after}"
    );
    // The optimum reached from the noisy start is the one reached from the ground truth: what
    // error is left is the noise's, not the solver's.
    let mut from_truth = bundle_scene(&config, 7);
    for (k, t) in from_truth
        .keyframes
        .clone()
        .iter()
        .zip(&scene.true_keyframes)
    {
        from_truth.problem.values_mut().set(*k, *t);
    }
    for (k, t) in from_truth.points.clone().iter().zip(&scene.true_points) {
        from_truth.problem.values_mut().set(*k, *t);
    }
    Solver::new(Options::default())
        .solve(&mut from_truth.problem)
        .expect("solves");
    let gap = rms(scene.keyframes.iter().map(|k| {
        (scene.problem.values().get(*k).translation
            - from_truth.problem.values().get(*k).translation)
            .norm()
    }));
    assert!(gap < 1e-5, "the two optima differ by {gap} m");
    // Each observation's squared whitened error averages about 1 at the optimum: 3 residuals per
    // observation, less the parameters fitted.
    let dof = 3 * scene.observations - 3 * config.points - 6 * (config.keyframes - 2);
    let per_dof = report.final_cost / dof as f64;
    assert!(
        (0.8..1.2).contains(&per_dof),
        "cost per degree of freedom {per_dof}"
    );
}

#[test]
fn the_schur_complement_changes_nothing_but_speed() {
    let config = BundleConfig {
        keyframes: 8,
        points: 300,
        observations_per_point: 4,
        ..BundleConfig::default()
    };
    let mut with = bundle_scene(&config, 3);
    let mut without = bundle_scene(&config, 3);
    let options = |eliminate_points| Options {
        eliminate_points,
        max_iterations: 6,
        ..Options::default()
    };
    let a = Solver::new(options(true)).solve(&mut with.problem).unwrap();
    let b = Solver::new(options(false))
        .solve(&mut without.problem)
        .unwrap();
    assert_eq!(a.eliminated_points, 300);
    assert_eq!(b.eliminated_points, 0);
    assert_same_steps(&a, &b);
    // With every keyframe fixed, only the points move (structure-only adjustment): nothing is
    // left to factor after elimination, and the points still improve.
    for k in &with.keyframes {
        with.problem.values_mut().set_fixed(k.id, true);
    }
    let report = Solver::new(options(true)).solve(&mut with.problem).unwrap();
    assert_eq!(report.reduced_dim, 0);
    assert!(report.final_cost <= report.initial_cost);
}

/// Two solves took the same steps: as many iterations, each accepted or not alike, with the
/// same tried cost to 1e-9.
fn assert_same_steps(a: &vsgraphs_optim::Report, b: &vsgraphs_optim::Report) {
    assert_eq!(a.iterations.len(), b.iterations.len());
    for (x, y) in a.iterations.iter().zip(&b.iterations) {
        assert_eq!(x.accepted, y.accepted, "iteration {}", x.iteration);
        assert!(
            (x.tried_cost - y.tried_cost).abs() <= 1e-9 * y.tried_cost,
            "iteration {}: {} vs {}",
            x.iteration,
            x.tried_cost,
            y.tried_cost
        );
    }
}

/// Runs the same solve on one thread and on `threads`, and checks both take the same steps.
fn same_on_threads(
    mut one: vsgraphs_optim::Problem,
    mut many: vsgraphs_optim::Problem,
    threads: usize,
    eliminate_points: bool,
) {
    let options = |threads| Options {
        eliminate_points,
        threads,
        max_iterations: 4,
        ..Options::default()
    };
    let a = Solver::new(options(1)).solve(&mut one).unwrap();
    let b = Solver::new(options(threads)).solve(&mut many).unwrap();
    assert_eq!((a.threads, b.threads), (1, threads));
    assert_same_steps(&a, &b);
}

#[test]
fn threads_share_the_work_without_changing_the_steps() {
    // Big enough to be split (several thousand factors), with and without elimination, and an
    // S-Graph whose walls, markers and odometry hold no eliminated point.
    let config = BundleConfig {
        keyframes: 10,
        points: 1500,
        observations_per_point: 4,
        ..BundleConfig::default()
    };
    for (threads, eliminate) in [(2, true), (3, true), (2, false)] {
        let one = bundle_scene(&config, 5).problem;
        let many = bundle_scene(&config, 5).problem;
        same_on_threads(one, many, threads, eliminate);
    }
    let building = vsgraphs_optim::testing::BuildingConfig {
        points_per_wall: 200,
        ..Default::default()
    };
    let one = vsgraphs_optim::testing::building_scene(&building, 2).problem;
    let many = vsgraphs_optim::testing::building_scene(&building, 2).problem;
    assert!(one.num_factors() >= 4000, "{}", one.num_factors());
    same_on_threads(one, many, 2, true);
}

#[test]
fn a_small_s_graph_is_eliminated_as_exactly_as_a_bundle_adjustment() {
    // Few keyframes, so that S is small enough to be laid out dense, and map points tied to
    // walls: eliminated points then couple with planes as well as poses.
    let building = vsgraphs_optim::testing::BuildingConfig {
        keyframe_spacing: 2.5,
        points_per_wall: 20,
        ..Default::default()
    };
    let mut with = vsgraphs_optim::testing::building_scene(&building, 4).problem;
    let mut without = vsgraphs_optim::testing::building_scene(&building, 4).problem;
    let options = |eliminate_points| Options {
        eliminate_points,
        max_iterations: 5,
        ..Options::default()
    };
    let a = Solver::new(options(true)).solve(&mut with).unwrap();
    let b = Solver::new(options(false)).solve(&mut without).unwrap();
    assert!(a.eliminated_points > 0);
    assert!(
        a.reduced_dim <= 300,
        "S has {} rows, not dense",
        a.reduced_dim
    );
    assert_same_steps(&a, &b);
}
