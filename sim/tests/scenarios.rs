//! Every built-in scenario: its robots walk inside the building through its doors, see every
//! marker, render without holes in the world, and write complete sequences.

use nalgebra::{Vector2, Vector3};
use std::collections::BTreeSet;
use vsgraphs_sim::plan::FloorPlan;
use vsgraphs_sim::scenarios::{Scenario, NAMES};
use vsgraphs_sim::sequence::{self, WriteOptions, TUM_DEPTH_SCALE};
use vsgraphs_sim::walk::{walk, Motion, Route, Tour, Visit, WalkError};
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_vision::image::GreyImage;

/// Distance from `p` to the nearest wall it could walk into: inside a space, its distance to
/// that space's sides, except sides it may cross through a door near `p`.
fn clearance(plan: &FloorPlan, p: Vector2<f64>) -> Option<f64> {
    let space = plan
        .spaces
        .iter()
        .find(|s| (0..2).all(|k| p[k] >= s.min[k] - 1e-9 && p[k] <= s.max[k] + 1e-9))?;
    let mut nearest = f64::INFINITY;
    for k in 0..2 {
        for at in [space.min[k], space.max[k]] {
            let through_door = plan.doors.iter().any(|d| {
                (d.at[k] - at).abs() < 1e-9 && (p[1 - k] - d.at[1 - k]).abs() < d.width / 2.0 - 0.15
            });
            if !through_door {
                nearest = nearest.min((p[k] - at).abs());
            }
        }
    }
    Some(nearest)
}

#[test]
fn robots_walk_inside_smoothly_at_walking_speed() {
    for name in NAMES {
        let scenario = Scenario::builtin(name).unwrap();
        let motion = &scenario.motion;
        for walk in scenario.walks().unwrap() {
            let who = format!("{name} {}", walk.robot);
            assert!(walk.times.len() > 300, "{who}: {} frames", walk.times.len());
            for (i, p) in walk.floor.iter().enumerate() {
                let c = clearance(&scenario.plan, Vector2::from(*p))
                    .unwrap_or_else(|| panic!("{who}: frame {i} at {p:?} is outside every space"));
                assert!(c > 0.3, "{who}: frame {i} at {p:?} is {c:.2} m from a wall");
            }
            let dt = 1.0 / motion.rate_hz;
            let mut fastest_turn = 0.0f64;
            for (i, w) in walk.world_from_camera.windows(2).enumerate() {
                let speed = (w[1].translation.vector - w[0].translation.vector)
                    .xy()
                    .norm()
                    / dt;
                assert!(
                    speed < motion.speed * 1.05,
                    "{who}: {speed:.2} m/s at frame {i}"
                );
                fastest_turn =
                    fastest_turn.max((w[0].rotation.inverse() * w[1].rotation).angle() / dt);
            }
            assert!(
                fastest_turn.to_degrees() < 60.0,
                "{who}: turns at {:.0}°/s",
                fastest_turn.to_degrees()
            );
            // It comes back to where it began: the route closes a loop.
            let (first, last) = (walk.floor[0], walk.floor[walk.floor.len() - 1]);
            assert!(
                (Vector2::from(first) - Vector2::from(last)).norm() < 1.0,
                "{who}"
            );
        }
    }
}

#[test]
fn every_marker_is_seen_and_no_ray_leaves_the_building() {
    for name in NAMES {
        let scenario = Scenario::builtin(name).unwrap();
        let building = Building::from_plan(&scenario.plan).unwrap();
        let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
        let mut seen = BTreeSet::new();
        for walk in scenario.walks().unwrap() {
            for (i, pose) in walk.world_from_camera.iter().enumerate().step_by(5) {
                seen.extend(renderer.visible_markers(&building, pose, 3.5, 60.0));
                if i % 60 == 0 {
                    let frame = renderer.render(i as u64, walk.times[i], &[*pose]);
                    assert_eq!(frame.misses, 0, "{name} {} frame {i}", walk.robot);
                    let valid = frame.depth.iter().filter(|&&z| z > 0.0).count();
                    assert!(
                        valid * 2 > frame.depth.len(),
                        "{name} frame {i}: {valid} depth pixels"
                    );
                }
            }
        }
        // Every wall marker, and every doorway by at least one of its two markers (the other
        // faces away on a route that crosses that door one way only).
        let walls_missed: Vec<u32> = building
            .markers
            .iter()
            .filter(|m| m.doorway.is_none() && !seen.contains(&m.id))
            .map(|m| m.id)
            .collect();
        assert!(
            walls_missed.is_empty(),
            "{name}: wall markers never seen: {walls_missed:?}"
        );
        for doorway in &building.doorways {
            assert!(
                doorway.markers.iter().any(|id| seen.contains(id)),
                "{name}: no marker of {} seen",
                doorway.name
            );
        }
    }
}

/// The hall of two_robots is a room only in the robots' joined map: together, but neither
/// alone, they come near enough to each of its four wall markers (the dictionary's group) for
/// the server to map it.
#[test]
fn in_two_robots_only_both_robots_together_can_map_every_hall_wall_marker() {
    use vsgraphs_slam::markers::{MAX_MAPPING_DISTANCE_M, MAX_MAPPING_VIEW_ANGLE_DEG};
    let scenario = Scenario::builtin("two_robots").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let hall = building.spaces.iter().find(|s| s.name == "Hall").unwrap();
    let hall_wall_markers: BTreeSet<u32> = hall
        .walls
        .iter()
        .flat_map(|&w| building.walls[w].markers.iter().copied())
        .collect();
    assert_eq!(hall_wall_markers.len(), 4, "{hall_wall_markers:?}");
    let mappable: Vec<BTreeSet<u32>> = scenario
        .walks()
        .unwrap()
        .iter()
        .map(|walk| {
            let mut seen = BTreeSet::new();
            for pose in walk.world_from_camera.iter().step_by(3) {
                seen.extend(renderer.visible_markers(
                    &building,
                    pose,
                    MAX_MAPPING_DISTANCE_M,
                    MAX_MAPPING_VIEW_ANGLE_DEG,
                ));
            }
            seen.retain(|id| hall_wall_markers.contains(id));
            seen
        })
        .collect();
    assert_eq!(mappable.len(), 2);
    for (robot, markers) in mappable.iter().enumerate() {
        assert!(
            markers.len() < 4,
            "robot {robot} alone can map every hall wall marker: {markers:?}"
        );
    }
    let union: BTreeSet<u32> = mappable.iter().flatten().copied().collect();
    assert_eq!(
        union, hall_wall_markers,
        "together they can map {mappable:?}"
    );
}

#[test]
fn every_scenario_writes_a_complete_sequence() {
    let dir = tempfile::tempdir().unwrap();
    for name in NAMES {
        let scenario = Scenario::builtin(name).unwrap();
        let out = dir.path().join(name);
        let options = WriteOptions {
            limit: Some(3),
            ..WriteOptions::default()
        };
        let written = sequence::write(&scenario, &out, &options, |_, _| {}).unwrap();
        assert_eq!(written.len(), scenario.routes.len());
        for file in ["plan.json", "dictionary.json", "ground_truth.json"] {
            assert!(out.join(file).is_file(), "{name}: {file}");
        }
        let walks = scenario.walks().unwrap();
        for (robot, walk) in written.iter().zip(&walks) {
            let list = |file: &str| -> Vec<Vec<String>> {
                std::fs::read_to_string(robot.dir.join(file))
                    .unwrap()
                    .lines()
                    .filter(|l| !l.starts_with('#'))
                    .map(|l| l.split_whitespace().map(str::to_owned).collect())
                    .collect()
            };
            let (rgb, depth, truth) = (list("rgb.txt"), list("depth.txt"), list("groundtruth.txt"));
            assert_eq!((rgb.len(), depth.len(), truth.len()), (3, 3, 3), "{name}");
            for ((r, d), t) in rgb.iter().zip(&depth).zip(&truth) {
                assert_eq!(r[0], d[0]);
                assert_eq!(r[0], t[0]);
                let stamp: f64 = t[0].parse().unwrap();
                let i = (stamp * scenario.motion.rate_hz).round() as usize;
                let pose = walk.world_from_camera[i];
                let position: Vec<f64> = t[1..4].iter().map(|v| v.parse().unwrap()).collect();
                assert!(
                    (Vector3::from_column_slice(&position) - pose.translation.vector).norm() < 1e-6
                );
                let decoder =
                    png::Decoder::new(std::fs::File::open(robot.dir.join(&d[1])).unwrap());
                let mut reader = decoder.read_info().unwrap();
                let mut buffer = vec![0; reader.output_buffer_size()];
                reader.next_frame(&mut buffer).unwrap();
                assert_eq!((reader.info().width, reader.info().height), (640, 480));
                assert_eq!(reader.info().bit_depth, png::BitDepth::Sixteen);
                let metres: Vec<f64> = buffer
                    .chunks_exact(2)
                    .map(|b| f64::from(u16::from_be_bytes([b[0], b[1]])) / TUM_DEPTH_SCALE)
                    .filter(|&z| z > 0.0)
                    .collect();
                assert!(metres.len() > 640 * 480 / 2, "{name}: depth mostly missing");
                assert!(metres.iter().all(|&z| (0.2..=8.5).contains(&z)));
                assert!(robot.dir.join(&r[1]).is_file());
            }
            let camera: serde_json::Value = serde_json::from_str(
                &std::fs::read_to_string(robot.dir.join("camera.json")).unwrap(),
            )
            .unwrap();
            assert_eq!(camera["depth_scale"], TUM_DEPTH_SCALE);
        }
    }
}

/// Colour as JPEG (what robots send): listed under its own name, close to the lossless image,
/// a fraction of its size; depth as without it.
#[test]
fn colour_can_be_written_as_jpeg() {
    let dir = tempfile::tempdir().unwrap();
    let scenario = Scenario::builtin("seq01").unwrap();
    let write = |name: &str, jpeg_quality| {
        let out = dir.path().join(name);
        let options = WriteOptions {
            limit: Some(2),
            jpeg_quality,
            ..WriteOptions::default()
        };
        sequence::write(&scenario, &out, &options, |_, _| {}).unwrap();
        out
    };
    let (png, jpeg) = (write("png", None), write("jpeg", Some(90)));
    let listed = |out: &std::path::Path, list: &str| -> Vec<String> {
        std::fs::read_to_string(out.join(list))
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split_whitespace().nth(1).unwrap().to_owned())
            .collect()
    };
    let (png_colour, jpeg_colour) = (listed(&png, "rgb.txt"), listed(&jpeg, "rgb.txt"));
    assert_eq!(jpeg_colour.len(), 2);
    for (p, j) in png_colour.iter().zip(&jpeg_colour) {
        assert_eq!(p.strip_suffix(".png"), j.strip_suffix(".jpg"), "{p} {j}");
        let size = |path: std::path::PathBuf| std::fs::metadata(path).unwrap().len();
        let (png_bytes, jpeg_bytes) = (size(png.join(p)), size(jpeg.join(j)));
        assert!(
            jpeg_bytes * 3 < png_bytes,
            "{jpeg_bytes} vs {png_bytes} bytes"
        );
        let a = GreyImage::read(&png.join(p)).unwrap();
        let b = GreyImage::read(&jpeg.join(j)).unwrap();
        assert_eq!((b.width(), b.height()), (640, 480));
        let difference = a
            .pixels()
            .iter()
            .zip(b.pixels())
            .map(|(&x, &y)| f64::from(x.abs_diff(y)))
            .sum::<f64>()
            / a.pixels().len() as f64;
        assert!(difference < 2.0, "mean grey difference {difference}");
    }
    for (p, j) in listed(&png, "depth.txt")
        .iter()
        .zip(&listed(&jpeg, "depth.txt"))
    {
        assert_eq!(
            std::fs::read(png.join(p)).unwrap(),
            std::fs::read(jpeg.join(j)).unwrap()
        );
    }
}

#[test]
fn broken_routes_are_refused_with_their_reason() {
    let scenario = Scenario::builtin("seq06").unwrap();
    let plan = &scenario.plan;
    let motion = Motion::default();
    let route = |visits: Vec<Visit>, start: Option<[f64; 2]>| Route {
        robot: "r".into(),
        start,
        visits,
    };
    let visit = |space: &str, tour: Tour| Visit {
        space: space.into(),
        tour,
    };
    assert!(matches!(
        walk(
            plan,
            &route(vec![visit("Kitchen", Tour::Loop)], None),
            &motion
        ),
        Err(WalkError::UnknownSpace { .. })
    ));
    assert!(matches!(
        walk(plan, &route(vec![], None), &motion),
        Err(WalkError::Empty { .. })
    ));
    assert!(matches!(
        walk(
            plan,
            &route(vec![visit("Lab", Tour::Points(vec![[9.0, 9.0]]))], None),
            &motion
        ),
        Err(WalkError::PointOutside { .. })
    ));
    assert!(matches!(
        walk(
            plan,
            &route(vec![visit("Lab", Tour::Loop)], Some([0.05, 2.0])),
            &motion
        ),
        Err(WalkError::PointOutside { .. })
    ));
    let mut two = scenario.clone();
    two.plan.spaces.push(vsgraphs_sim::plan::Space {
        name: "Shed".into(),
        kind: vsgraphs_sim::plan::SpaceKind::Room,
        min: [20.0, 0.0],
        max: [23.0, 3.0],
        looks_like: None,
    });
    assert!(matches!(
        walk(
            &two.plan,
            &route(
                vec![visit("Lab", Tour::Loop), visit("Shed", Tour::Loop)],
                None
            ),
            &motion
        ),
        Err(WalkError::NoDoor { .. })
    ));
    let fast = Motion {
        speed: f64::NAN,
        ..Motion::default()
    };
    assert_eq!(
        walk(plan, &route(vec![visit("Lab", Tour::Loop)], None), &fast).unwrap_err(),
        WalkError::Motion("speed")
    );
}

#[test]
fn repeated_laps_keep_the_clock_running() {
    let walk = Scenario::builtin("seq06")
        .unwrap()
        .walks()
        .unwrap()
        .remove(0);
    let n = walk.times.len();
    let period = walk.times[1];
    // The second lap starts one frame period after the first ends, at the first pose.
    assert_eq!(walk.lap_frame(n - 1), (n - 1, walk.times[n - 1]));
    let (index, time) = walk.lap_frame(n);
    assert_eq!(index, 0);
    assert!((time - (walk.times[n - 1] + period)).abs() < 1e-12);
    assert!((walk.lap_frame(n + 5).1 - time - walk.times[5]).abs() < 1e-12);
    // The trajectory over two laps steps forward by one period everywhere.
    let trajectory = walk.trajectory(100.0, 2 * n);
    assert_eq!(trajectory.len(), 2 * n);
    assert!(trajectory
        .stamps
        .windows(2)
        .all(|w| (w[1] - w[0] - period).abs() < 1e-6));
    assert_eq!(trajectory.poses[n], walk.world_from_camera[0]);
}
