//! A local bundle adjustment of the optimiser's goal size (20 keyframes, 3,000 points, 30,000
//! RGB-D observations, 5 iterations), with and without the Schur complement of the points.
//! The sparsity analysis is included: a local window changes with every keyframe.
use criterion::{criterion_group, criterion_main, Criterion};
use vsgraphs_sgraph::testing::{bundle_scene, BundleConfig};
use vsgraphs_sgraph::{Options, Solver};

fn bundle(c: &mut Criterion) {
    let config = BundleConfig::default();
    let mut group = c.benchmark_group("local_ba");
    group.sample_size(10);
    for eliminate_points in [true, false] {
        let options = Options {
            max_iterations: 5,
            eliminate_points,
            ..Options::default()
        };
        let mut scene = bundle_scene(&config, 1);
        let report = Solver::new(options.clone())
            .solve(&mut scene.problem)
            .unwrap();
        let sum = |f: fn(&vsgraphs_sgraph::Iteration) -> std::time::Duration| {
            report.iterations.iter().map(f).sum::<std::time::Duration>()
        };
        eprintln!(
            "schur {eliminate_points}: {} observations, cost {:.0} -> {:.0}; analysis {:?}, \
             linearise {:?}, solve {:?}, total {:?}",
            scene.observations,
            report.initial_cost,
            report.final_cost,
            report.analysis_time,
            sum(|i| i.linearize_time),
            sum(|i| i.solve_time),
            report.total_time
        );
        let name = if eliminate_points {
            "schur"
        } else {
            "sparse_cholesky"
        };
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
