//! The joint S-Graph of a synthetic marked building: keyframes from noisy odometry, markers seen
//! by their corners, and the semantic layers (walls, rooms, corridor, doorways). The trajectory
//! error must fall when the markers are added, and fall again with the semantic factors.
//!
//! Correct extra information lowers the expected error, not the error of every noise draw, so
//! the semantic layers are judged over ten draws: lower on average and in most of them.

use vsgraphs_optim::testing::{building_scene, BuildingConfig, BuildingScene};
use vsgraphs_optim::{Options, Solver, Termination};

fn position_rmse(scene: &BuildingScene, estimate: impl Fn(usize) -> nalgebra::Vector3<f64>) -> f64 {
    let n = scene.true_keyframes.len();
    let sum: f64 = (0..n)
        .map(|i| (estimate(i) - scene.true_keyframes[i].translation).norm_squared())
        .sum();
    (sum / n as f64).sqrt()
}

/// Optimises the scene; returns the keyframes' position RMSE before and after.
fn optimise(scene: &mut BuildingScene) -> (f64, f64) {
    let before = position_rmse(scene, |i| scene.odometry_keyframes[i].translation);
    let report = Solver::new(Options::default())
        .solve(&mut scene.problem)
        .expect("solves");
    assert!(
        matches!(
            report.termination,
            Termination::CostConverged
                | Termination::GradientConverged
                | Termination::StepConverged
        ),
        "{:?}",
        report.termination
    );
    let values = scene.problem.values();
    let after = position_rmse(scene, |i| values.get(scene.keyframes[i]).translation);
    (before, after)
}

#[test]
fn semantic_factors_lower_the_trajectory_error() {
    let seeds = 10;
    let (mut sum_odometry, mut sum_markers, mut sum_semantics, mut better) = (0.0, 0.0, 0.0, 0);
    for seed in 1..=seeds {
        let markers_only = BuildingConfig {
            semantic: false,
            ..BuildingConfig::default()
        };
        let mut plain = building_scene(&markers_only, seed);
        let mut full = building_scene(&BuildingConfig::default(), seed);
        assert_eq!(plain.marker_observations, full.marker_observations);
        assert!(
            full.markers_seen >= 10,
            "{} markers seen",
            full.markers_seen
        );
        let (odometry, with_markers) = optimise(&mut plain);
        let (_, with_semantics) = optimise(&mut full);
        println!(
            "seed {seed}: {} keyframes, {} markers, {} sightings; position RMSE: odometry {odometry:.3} m, \
             + markers {with_markers:.4} m, + walls/rooms/doorways {with_semantics:.4} m",
            full.keyframes.len(),
            full.markers_seen,
            full.marker_observations
        );
        sum_odometry += odometry;
        sum_markers += with_markers;
        sum_semantics += with_semantics;
        better += usize::from(with_semantics < with_markers);
        // Walls and centres come out where the building has them, give or take the drift the
        // trajectory keeps (a few centimetres and a degree or two).
        let values = full.problem.values();
        for (key, truth) in &full.walls {
            let estimate = values.get(*key);
            let estimate = if estimate.normal.dot(&truth.normal) < 0.0 {
                estimate.flipped()
            } else {
                *estimate
            };
            let angle = estimate.normal.dot(&truth.normal).clamp(-1.0, 1.0).acos();
            assert!(angle < 0.06, "wall normal off by {angle} rad");
            assert!(
                (estimate.offset - truth.offset).abs() < 0.15,
                "wall offset {} vs {}",
                estimate.offset,
                truth.offset
            );
        }
        assert_eq!(full.centres.len(), 3, "the corridor and both rooms");
        for (key, truth) in &full.centres {
            let error = (values.get(*key) - truth).norm();
            assert!(error < 0.15, "centre {error} m from the truth");
        }
    }
    let n = seeds as f64;
    let (mean_odometry, mean_markers, mean_semantics) =
        (sum_odometry / n, sum_markers / n, sum_semantics / n);
    println!(
        "mean position RMSE over {seeds} draws: odometry {mean_odometry:.4} m, + markers {mean_markers:.4} m, \
         + semantics {mean_semantics:.4} m; semantics better in {better}"
    );
    assert!(mean_markers < mean_odometry / 1.5);
    assert!(mean_semantics < 0.97 * mean_markers);
    assert!(better >= 7, "better in only {better} of {seeds} draws");
}
