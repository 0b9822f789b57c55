//! A local bundle adjustment of the optimiser's goal size (20 keyframes, 3,000 points, 30,000
//! RGB-D observations, 5 iterations): with the Schur complement of the points on one and two
//! threads, and plain sparse Cholesky. The sparsity analysis is included: a local window
//! changes with every keyframe.
use criterion::{criterion_group, criterion_main, Criterion};
use std::time::Duration;
use vsgraphs_optim::testing::{bundle_scene, BundleConfig};
use vsgraphs_optim::{Iteration, Options, Solver};

fn bundle(c: &mut Criterion) {
    let config = BundleConfig::default();
    let mut group = c.benchmark_group("local_ba");
    group.sample_size(20);
    for (name, eliminate_points, threads) in [
        ("schur_1_thread", true, 1),
        ("schur_2_threads", true, 2),
        ("sparse_cholesky_1_thread", false, 1),
    ] {
        let options = Options {
            max_iterations: 5,
            eliminate_points,
            threads,
            ..Options::default()
        };
        // The fastest of ten runs, phase by phase, printed once.
        let mut best = [Duration::MAX; 4];
        let mut costs = (0.0, 0.0);
        for _ in 0..10 {
            let mut scene = bundle_scene(&config, 1);
            let report = Solver::new(options.clone())
                .solve(&mut scene.problem)
                .unwrap();
            let sum = |f: fn(&Iteration) -> Duration| report.iterations.iter().map(f).sum();
            let phases = [
                report.analysis_time,
                sum(|i| i.linearize_time),
                sum(|i| i.solve_time),
                report.total_time,
            ];
            for (b, p) in best.iter_mut().zip(phases) {
                *b = (*b).min(p);
            }
            costs = (report.initial_cost, report.final_cost);
        }
        eprintln!(
            "{name}: cost {:.0} -> {:.0}; fastest analysis {:?}, linearise {:?}, solve {:?}, total {:?}",
            costs.0, costs.1, best[0], best[1], best[2], best[3]
        );
        group.bench_function(name, |b| {
            b.iter_batched(
                || bundle_scene(&config, 1).problem,
                |mut problem| Solver::new(options.clone()).solve(&mut problem).unwrap(),
                criterion::BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

criterion_group!(benches, bundle);
criterion_main!(benches);
