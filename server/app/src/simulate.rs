//! `vsgraphs-server simulate-markers`: a robot that streams rendered frames of ArUco markers on a
//! wall while its camera sways, for demos and for checking a deployment end to end. (The
//! building simulator with ground truth is a separate tool.)

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use std::time::{Duration, Instant};
use vsgraphs_proto::{DepthEncoding, PixelFormat};
use vsgraphs_sdk::robot::now_ns;
use vsgraphs_sdk::{encode, Robot};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::{render, PlacedMarker};

/// Streams until the task is dropped. `side_m` is the markers' side.
pub async fn simulate_markers(
    robot: Robot,
    dictionary: MarkerDictionary,
    side_m: f64,
    rate_hz: f64,
) -> anyhow::Result<()> {
    let camera = PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![])?;
    let model = camera.to_wire();
    let ids: Vec<i32> = (0..6).map(|i| (i * 7) % dictionary.markers).collect();
    let start = Instant::now();
    let period = Duration::from_secs_f64(1.0 / rate_hz.max(0.1));
    let mut next = tokio::time::Instant::now();
    loop {
        let t = start.elapsed().as_secs_f64();
        // Camera 1.2 m from a wall of 3×2 markers, swaying left-right and turning a little.
        let wall_from_camera = Isometry3::from_parts(
            Translation3::new(
                0.25 * (0.4 * t).sin(),
                0.08 * (0.7 * t).sin(),
                -1.2 + 0.15 * (0.3 * t).sin(),
            ),
            UnitQuaternion::from_euler_angles(0.1 * (0.5 * t).sin(), 0.25 * (0.4 * t).sin(), 0.0),
        );
        let camera_from_wall = wall_from_camera.inverse();
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let markers: Vec<PlacedMarker> = ids
            .iter()
            .enumerate()
            .map(|(i, &id)| {
                let x = (i % 3) as f64 * 0.22 - 0.22;
                let y = (i / 3) as f64 * 0.22 - 0.11;
                let wall_from_marker = Isometry3::from_parts(Translation3::new(x, y, 0.0), facing);
                PlacedMarker {
                    id,
                    side_m,
                    camera_from_marker: camera_from_wall * wall_from_marker,
                }
            })
            .collect();
        let dictionary = dictionary.clone();
        let camera_for_render = camera.clone();
        let (colour, depth) = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
            let frame = render(&camera_for_render, &dictionary, &markers, 1.25)?;
            let colour = encode::colour_jpeg(frame.grey_bytes(), 640, 480, PixelFormat::Mono8, 90)?;
            let depth = encode::depth(&frame.depth_mm, 640, 480, DepthEncoding::Rvl)?;
            Ok((colour, depth))
        })
        .await??;
        robot
            .publish(now_ns(), model.clone(), 1000.0, colour, depth)
            .await?;
        next += period;
        tokio::time::sleep_until(next).await;
    }
}
