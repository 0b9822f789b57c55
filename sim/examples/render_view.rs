//! Renders one view of a scenario to `view.png` / `view_depth.png` and times the renderer:
//! `cargo run --release -p vsgraphs-sim --example render_view -- seq01 X Y YAW_DEG [RUNS]`.

use nalgebra::Vector3;
use std::time::Instant;
use vsgraphs_sim::walk::looking_at;
use vsgraphs_sim::{images, scenarios, Building, RenderOptions, Renderer};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let name = args.first().map_or("seq01", String::as_str);
    let number = |i: usize, default: f64| args.get(i).map_or(Ok(default), |a| a.parse());
    let (x, y, yaw) = (
        number(1, 1.0)?,
        number(2, 1.0)?,
        number(3, 30.0)?.to_radians(),
    );
    let runs = number(4, 10.0)? as usize;
    let plan = scenarios::scenario(name).ok_or_else(|| anyhow::anyhow!("no scenario {name}"))?;
    let building = Building::from_plan(&plan)?;
    let start = Instant::now();
    let renderer = Renderer::new(&plan, &building, RenderOptions::default(), 1);
    println!(
        "scene built in {:.0} ms",
        start.elapsed().as_secs_f64() * 1e3
    );
    let eye = Vector3::new(x, y, 1.0);
    let pose = looking_at(eye, eye + Vector3::new(yaw.cos(), yaw.sin(), 0.0));
    let mut best = f64::MAX;
    let mut frame = None;
    for i in 0..runs.max(1) {
        let start = Instant::now();
        frame = Some(renderer.render(i as u64, i as f64 / 30.0, &[pose]));
        best = best.min(start.elapsed().as_secs_f64());
    }
    println!("render: fastest of {runs}: {:.2} ms", best * 1e3);
    let frame = frame.expect("rendered");
    images::write_rgb("view.png".as_ref(), frame.width, frame.height, &frame.rgb)?;
    let depth: Vec<u16> = frame.depth.iter().map(|z| (z * 8000.0) as u16).collect();
    images::write_depth("view_depth.png".as_ref(), frame.width, frame.height, &depth)?;
    Ok(())
}
