//! A building-sized S-Graph: 20 rooms on a 40 m corridor, ~560 keyframes, ~50,000 map points on
//! ~80 walls, markers, rooms, corridor and doorways, optimised jointly from dead reckoning.
use criterion::{criterion_group, criterion_main, Criterion};
use vsgraphs_optim::testing::{building_scene, BuildingConfig};
use vsgraphs_optim::Solver;

fn sgraph(c: &mut Criterion) {
    let config = BuildingConfig {
        rooms_per_side: 10,
        keyframe_spacing: 0.5,
        points_per_wall: 620,
        ..BuildingConfig::default()
    };
    let mut scene = building_scene(&config, 1);
    let report = Solver::default().solve(&mut scene.problem).unwrap();
    let sum = |f: fn(&vsgraphs_optim::Iteration) -> std::time::Duration| {
        report.iterations.iter().map(f).sum::<std::time::Duration>()
    };
    eprintln!(
        "building: {} keyframes, {} walls, {} rooms and corridors, {} markers ({} sightings), \
         {} points ({} observations), {} factors; cost {:.0} -> {:.0} in {} iterations; \
         analysis {:?}, linearise {:?}, solve {:?}, total {:?}",
        scene.keyframes.len(),
        scene.walls.len(),
        scene.centres.len(),
        scene.markers_seen,
        scene.marker_observations,
        scene.points,
        scene.point_observations,
        scene.problem.num_factors(),
        report.initial_cost,
        report.final_cost,
        report.iterations.len(),
        report.analysis_time,
        sum(|i| i.linearize_time),
        sum(|i| i.solve_time),
        report.total_time
    );
    let mut group = c.benchmark_group("sgraph");
    group.sample_size(10);
    group.bench_function("building_20_rooms", |b| {
        b.iter_batched(
            || building_scene(&config, 1).problem,
            |mut problem| Solver::default().solve(&mut problem).unwrap(),
            criterion::BatchSize::LargeInput,
        )
    });
    group.finish();
}

criterion_group!(benches, sgraph);
criterion_main!(benches);
