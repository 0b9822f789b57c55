//! Time to the optimum on the public pose-graph benchmarks, from the files' initial values
//! (the optimise call only, as the peers in ../shared/data/posegraph/README.md were timed).
use criterion::{criterion_group, criterion_main, Criterion};
use std::path::PathBuf;
use vsgraphs_optim::factors::pose::PoseError;
use vsgraphs_optim::g2o::PoseGraph;
use vsgraphs_optim::Solver;

fn posegraph(c: &mut Criterion) {
    let dir = std::env::var_os("VSGRAPHS_TEST_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
        .join("posegraph");
    let mut group = c.benchmark_group("posegraph");
    group.sample_size(10);
    for name in ["sphere2500", "parking-garage"] {
        let Ok(graph) = PoseGraph::read(&dir.join(format!("{name}.g2o"))) else {
            eprintln!("skipped: {name}.g2o not found in {}", dir.display());
            continue;
        };
        for (error, label) in [
            (PoseError::Quaternion, "g2o"),
            (PoseError::LogMap, "logmap"),
        ] {
            let report = Solver::default()
                .solve(&mut graph.to_problem(error).unwrap().0)
                .unwrap();
            eprintln!(
                "{name} {label}: cost {:.6} -> {:.6}, {} iterations",
                report.initial_cost,
                report.final_cost,
                report.iterations.len()
            );
            group.bench_function(format!("{name}_{label}"), |b| {
                b.iter_batched(
                    || graph.to_problem(error).unwrap().0,
                    |mut problem| Solver::default().solve(&mut problem).unwrap(),
                    criterion::BatchSize::LargeInput,
                )
            });
        }
    }
    group.finish();
}

criterion_group!(benches, posegraph);
criterion_main!(benches);
