//! A virtual robot walks seq06 and streams over real zenoh to the real server, which processes
//! every frame, tracks the robot through all of them, and reports the markers it detected: those
//! the robot had in view, and no others. With the building's semantic dictionary, its map's
//! walls gather the mapped markers as the building hangs them, and the room appears once its
//! four walls are mapped.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;
use vsgraphs_sdk::player::Rate;
use vsgraphs_sdk::simulated::{self, SimOptions};
use vsgraphs_sdk::{Delivery, Robot, RobotConfig};
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_tests::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_simulated_robot_streams_seq06_and_the_server_reports_its_frames_and_markers() {
    let site = SimulatedSite::builtin("seq06");
    let test = site.server().await;
    let building = &site.building;
    let renderer = site.renderer.clone();
    let walk = site.walks().remove(0);
    let frames = 240;
    // Markers squarely in view and near in the frames sent: the server must find each.
    let mut expected = BTreeSet::new();
    for pose in &walk.world_from_camera[..frames] {
        expected.extend(renderer.visible_markers(building, pose, 2.5, 45.0));
    }
    assert!(
        expected.len() >= 3,
        "the first frames show markers: {expected:?}"
    );

    let mut config = RobotConfig::connecting_to("sim-1", &test.zenoh_endpoint);
    config.delivery = Delivery::Reliable;
    let robot = Robot::connect(config).await.unwrap();
    let options = SimOptions {
        // A rate the server keeps up with while it tracks (keyframes cost tens of ms in this
        // build), so that every frame is processed.
        rate: Rate::Hz(10.0),
        limit: Some(frames),
        ..SimOptions::default()
    };
    let summary = simulated::stream(&robot, renderer.clone(), walk.clone(), &options, |_, _| {})
        .await
        .unwrap();
    assert_eq!(summary.frames_sent, frames as u64);

    let status = wait_for("every frame processed", Duration::from_secs(60), || async {
        let status = test.client.robot("sim-1").await.ok()?;
        let f = &status.frames;
        (f.processed + f.dropped + f.rejected >= frames as u64).then_some(status)
    })
    .await;
    assert_eq!(
        status.frames.processed, frames as u64,
        "{:?}",
        status.frames
    );
    // The robot was tracked all the way (accuracy is measured by the tracking tests).
    let tracking = status.tracking.as_ref().expect("tracking is on by default");
    assert_eq!(tracking.frames_tracked, frames as u64, "{tracking:?}");
    let detected: BTreeSet<u32> = status
        .markers_detected
        .keys()
        .map(|&id| id as u32)
        .collect();
    let building_ids: BTreeSet<u32> = building.markers.iter().map(|m| m.id).collect();
    assert!(
        detected.is_subset(&building_ids),
        "detected {detected:?}, building {building_ids:?}"
    );
    assert!(
        expected.is_subset(&detected),
        "in view {expected:?}, detected {detected:?}"
    );
    // The markers seen near enough became landmarks of the robot's map, and the API serves
    // the map (decimated points, keyframes, markers) and its building model.
    let maps = test.client.maps("sim-1").await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert!(maps[0].points.is_empty() && maps[0].keyframes.is_empty());
    // The writer publishes a keyframe's semantic layer after answering the tracker: wait until
    // the last one has every marker on a wall (the assertions below say which did not).
    let last = || async {
        let map = test.client.map("sim-1", 0, 500).await.ok()?;
        let on_walls: usize = map.walls.iter().map(|w| w.markers.len()).sum();
        (map.keyframe_count == tracking.keyframes && on_walls == map.markers.len()).then_some(map)
    };
    let map = match tokio::time::timeout(Duration::from_secs(20), async {
        loop {
            if let Some(map) = last().await {
                return map;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
    {
        Ok(map) => map,
        Err(_) => test.client.map("sim-1", 0, 500).await.unwrap(),
    };
    assert!(map.points.len() <= 500 && !map.points.is_empty());
    assert_eq!(map.keyframes.len() as u64, map.keyframe_count);
    let mapped: BTreeSet<u32> = map.markers.iter().map(|m| m.id as u32).collect();
    assert!(
        !mapped.is_empty() && mapped.is_subset(&detected),
        "mapped {mapped:?}"
    );
    let model = test.client.model("sim-1", 0).await.unwrap();
    assert_eq!(model.markers.len(), map.markers.len());
    // Every mapped marker is on one wall of the map, and the markers of one wall of the map hang
    // on one wall of the building.
    let mut on_walls: Vec<u32> = map
        .walls
        .iter()
        .flat_map(|w| w.markers.iter().map(|&id| id as u32))
        .collect();
    on_walls.sort_unstable();
    assert_eq!(on_walls, mapped.iter().copied().collect::<Vec<_>>());
    for wall in &map.walls {
        let true_walls: BTreeSet<usize> = wall
            .markers
            .iter()
            .map(|&id| building.markers[id as usize].wall)
            .collect();
        assert_eq!(true_walls.len(), 1, "{wall:?}");
    }
    // The Lab is a room once its four wall markers are mapped, and not before.
    let lab = &building.spaces[0];
    let lab_mapped = lab
        .walls
        .iter()
        .flat_map(|&w| &building.walls[w].markers)
        .all(|id| mapped.contains(id));
    let rooms: Vec<&str> = map.spaces.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        rooms.contains(&"Lab"),
        lab_mapped,
        "{rooms:?}, mapped {mapped:?}"
    );
    assert_eq!(model.walls.len(), map.walls.len());
    assert_eq!(tracking.markers, map.marker_count);
    eprintln!(
        "{frames} frames; markers in view {expected:?}; detected (id: frames) {:?}; mapped {mapped:?}",
        status.markers_detected
    );
    robot.close().await.unwrap();
}

/// A robot that streams, maps and leaves is forgotten once it has been neither online nor
/// heard from for `[ingest] forget_after_s`: it leaves the robot list and its worker ends,
/// while its map stays; the same id streaming again is a new robot with fresh counters.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_that_left_is_forgotten_and_its_map_stays() {
    let scenario = Scenario::builtin("seq06").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let test = TestServer::start_with(|c| c.ingest.forget_after_s = 1.0).await;
    let renderer = Arc::new(Renderer::new(
        &scenario.plan,
        &building,
        scenario.render.clone(),
        1,
    ));
    let walk = Arc::new(scenario.walks().unwrap().remove(0));
    let stream = |frames: usize| {
        let (renderer, walk, endpoint) = (renderer.clone(), walk.clone(), &test.zenoh_endpoint);
        async move {
            let mut config = RobotConfig::connecting_to("leaver", endpoint);
            config.delivery = Delivery::Reliable;
            let robot = Robot::connect(config).await.unwrap();
            let options = SimOptions {
                rate: Rate::Hz(10.0),
                limit: Some(frames),
                ..SimOptions::default()
            };
            simulated::stream(&robot, renderer, walk, &options, |_, _| {})
                .await
                .unwrap();
            robot
        }
    };
    let processed = |frames: u64| {
        let client = &test.client;
        move || async move {
            let status = client.robot("leaver").await.ok()?;
            (status.frames.processed == frames).then_some(status)
        }
    };

    let robot = stream(40).await;
    wait_for(
        "40 frames processed",
        Duration::from_secs(60),
        processed(40),
    )
    .await;
    let maps = test.client.server_maps().await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert_eq!(maps[0].robots, ["leaver"]);
    let keyframes = maps[0].keyframes;
    assert!(keyframes > 0);
    robot.close().await.unwrap();

    // Gone from the robots within the idle time and a sweep, its map kept whole.
    wait_for("the robot forgotten", Duration::from_secs(10), || async {
        let robots = test.client.robots().await.ok()?;
        robots.is_empty().then_some(())
    })
    .await;
    let maps = test.client.server_maps().await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert_eq!(maps[0].keyframes, keyframes);
    assert!(maps[0].robots.is_empty(), "{maps:?}");

    // Back again: a new robot, counting from zero.
    let robot = stream(10).await;
    let status = wait_for(
        "10 frames processed",
        Duration::from_secs(60),
        processed(10),
    )
    .await;
    assert_eq!(status.frames.received, 10, "{status:?}");
    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}
