//! Renders frame N of a scenario's first robot to `frame.png`:
//! `cargo run --release -p vsgraphs-sim --example render_frame -- seq06 1640`.

use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::{images, Building, Renderer};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let name = args.first().map_or("seq06", String::as_str);
    let index: usize = args.get(1).map_or(Ok(0), |a| a.parse())?;
    let scenario = Scenario::load(name)?;
    let building = Building::from_plan(&scenario.plan)?;
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let walk = scenario.walks()?.remove(0);
    let index = index.min(walk.times.len() - 1);
    let frame = render_frame(&renderer, &walk, index);
    images::write_rgb("frame.png".as_ref(), frame.width, frame.height, &frame.rgb)?;
    println!(
        "frame {index} of {} at {:?}",
        walk.times.len(),
        walk.world_from_camera[index].translation.vector
    );
    Ok(())
}
