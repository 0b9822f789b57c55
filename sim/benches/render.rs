//! Rendering speed: one 640×480 RGB-D frame along a walk (colour, depth with the sensor model),
//! with and without motion blur, and building a scene (texture generation).

use criterion::{criterion_group, criterion_main, Criterion};
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::{Building, Renderer};

fn render(c: &mut Criterion) {
    for name in ["seq03", "seq06"] {
        let mut scenario = Scenario::builtin(name).unwrap();
        let building = Building::from_plan(&scenario.plan).unwrap();
        let walk = scenario.walks().unwrap().remove(0);
        let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
        // Every 97th frame of the walk, in turn: rooms, corridors, doors, near and far walls.
        let frames: Vec<usize> = (0..walk.times.len()).step_by(97).collect();
        let mut next = 0;
        c.bench_function(&format!("render_frame_{name}"), |b| {
            b.iter(|| {
                next = (next + 1) % frames.len();
                render_frame(&renderer, &walk, frames[next])
            })
        });
        scenario.render.blur_samples = 4;
        let blurred = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
        c.bench_function(&format!("render_frame_blur4_{name}"), |b| {
            b.iter(|| {
                next = (next + 1) % frames.len();
                render_frame(&blurred, &walk, frames[next])
            })
        });
    }
    let scenario = Scenario::builtin("seq03").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let mut group = c.benchmark_group("scene");
    group.sample_size(10);
    group.bench_function("build_seq03", |b| {
        b.iter(|| Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1))
    });
    group.finish();
}

criterion_group!(benches, render);
criterion_main!(benches);
