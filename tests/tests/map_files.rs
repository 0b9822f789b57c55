//! Maps as files: a map two robots made and merged (`tests/data/two_wings.json`) exported,
//! imported into another server's maps, and exported again gives the same bytes, the same map
//! to the last bit and the same walls, doorways, rooms and corridors; files cut short, changed
//! or of another kind are refused, each with its reason. Through the real server's API the
//! same file goes in and out, and a robot that walks the building goes on in the imported map.

use std::sync::Arc;
use std::time::{Duration, Instant};
use vsgraphs_eval::scenario::{self, ScenarioOptions};
use vsgraphs_pipeline::maps::{ImportError, MapService};
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_proto::api::MapView;
use vsgraphs_sdk::player::Rate;
use vsgraphs_sdk::simulated::{self, SimOptions};
use vsgraphs_sdk::{ClientError, Delivery, Robot, RobotConfig};
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_slam::archive::{self, ArchiveError};
use vsgraphs_slam::MapWriter;
use vsgraphs_tests::{wait_for, TestServer};

#[test]
fn a_map_exported_and_imported_is_the_same_map() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/data/two_wings.json");
    let scenario = Scenario::load(path).unwrap();
    let config = PipelineConfig::default();
    let (made, _) = scenario::mapped(&config, &scenario, &ScenarioOptions::default()).unwrap();
    let maps = made.all();
    assert_eq!(maps.len(), 1, "the two robots' maps merged");
    let id = maps[0].0;
    let original = made.maps().into_iter().find(|m| m.id() == id).unwrap();
    let started = Instant::now();
    let bytes = made.export(id).unwrap();
    let written_ms = started.elapsed().as_secs_f64() * 1e3;
    {
        let map = original.read();
        eprintln!(
            "map {}: {} keyframes ({} culled), {} points, {} markers, {} loops, {} trajectory starts: {} bytes",
            id.0,
            map.keyframes.len(),
            map.keyframes.len() - map.live_keyframes(),
            map.points.len(),
            map.markers.len(),
            map.loop_edges.len(),
            map.trajectory_starts.len(),
            bytes.len()
        );
        // What the test needs the map to hold to mean anything.
        assert!(map.markers.len() >= 4 && !map.trajectory_starts.is_empty());
        assert!(!map.loop_edges.is_empty() && map.points.iter().any(|p| p.bad));
        // Read back, every field is as it was (the debug form prints floats exactly).
        let started = Instant::now();
        let read = archive::decode(&bytes).unwrap();
        eprintln!(
            "written in {written_ms:.0} ms, read back in {:.0} ms",
            started.elapsed().as_secs_f64() * 1e3
        );
        assert!(
            format!("{read:?}") == format!("{:?}", *map),
            "decoded map differs"
        );
    }

    // Another server's maps, with the same semantic settings, take it in.
    let other = MapService::with_semantics(true, made.dictionary().map(|d| (*d).clone()))
        .with_mapping(config.tracking.tracker().mapping());
    let imported = other.import(&bytes).unwrap();
    assert_eq!(
        other.export(imported).unwrap(),
        bytes,
        "exported again: the same bytes"
    );

    // Its walls, doorways and spaces as the original's (the imported map's layer is built
    // moments after the import).
    let layer = |view: &MapView| {
        serde_json::to_string(&(
            &view.keyframes,
            &view.points,
            &view.markers,
            &view.walls,
            &view.doorways,
            &view.spaces,
        ))
        .unwrap()
    };
    let want = made.snapshot(id).unwrap();
    assert!(!want.spaces.is_empty() && !want.doorways.is_empty());
    let started = Instant::now();
    loop {
        let got = other.snapshot(imported).unwrap();
        if layer(&got) == layer(&want) {
            eprintln!(
                "imported: {} walls, {} doorways, {} spaces as the original's",
                got.walls.len(),
                got.doorways.len(),
                got.spaces.len()
            );
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the imported map's layer differs:\n{:?}\n{:?}\n{:?}\nagainst\n{:?}\n{:?}\n{:?}",
            got.walls,
            got.doorways,
            got.spaces,
            want.walls,
            want.doorways,
            want.spaces
        );
        std::thread::sleep(Duration::from_millis(100));
    }

    // Damaged files: refused with what is wrong, nothing added.
    let refused = |bytes: &[u8]| match other.import(bytes) {
        Err(ImportError::File(e)) => e,
        other => panic!("{other:?}"),
    };
    let cut = refused(&bytes[..bytes.len() / 2]);
    assert!(matches!(cut, ArchiveError::Truncated { .. }), "{cut}");
    let mut flipped = bytes.clone();
    let middle = flipped.len() / 2;
    flipped[middle] ^= 0x10;
    assert_eq!(refused(&flipped), ArchiveError::Checksum);
    let mut newer = bytes.clone();
    newer[8] = 99;
    assert_eq!(refused(&newer), ArchiveError::Version { found: 99 });
    assert_eq!(refused(b"{\"keyframes\": []}"), ArchiveError::NotAMap);
    let mut longer = bytes.clone();
    longer.extend_from_slice(b"more");
    assert_eq!(refused(&longer), ArchiveError::Trailing(4));
    for e in [cut, ArchiveError::Checksum] {
        eprintln!("refused: {e}");
    }
    assert_eq!(other.len(), 1);

    // Over HTTP, into a running server, and a robot walking the building maps in it.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(served(&scenario, &bytes));
}

/// The map file imported into the real server through its API (as `vsgraphs-server import`
/// does), read back to the same bytes, and a robot that walks the first robot's route from its
/// start ends in that map; damaged files and unknown maps answered with what is wrong.
async fn served(scenario: &Scenario, bytes: &[u8]) {
    let test = TestServer::start().await;
    let map = test.client.import_map(bytes.to_vec()).await.unwrap();
    assert!(map.keyframes > 0 && map.markers > 0, "{map:?}");
    assert_eq!(test.client.export_map(map.id).await.unwrap(), bytes);
    match test.client.import_map(b"not a map".to_vec()).await {
        Err(ClientError::Api { status, body, .. }) => {
            assert_eq!(
                (status, body.error.as_str()),
                (400, "bad_map_file"),
                "{body:?}"
            );
            eprintln!("refused over HTTP: {}", body.message);
        }
        other => panic!("{other:?}"),
    }
    match test.client.export_map(map.id + 7).await {
        Err(ClientError::Api { status, body, .. }) => {
            assert_eq!(
                (status, body.error.as_str()),
                (404, "map_not_found"),
                "{body:?}"
            )
        }
        other => panic!("{other:?}"),
    }

    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Arc::new(Renderer::new(
        &scenario.plan,
        &building,
        scenario.render.clone(),
        ScenarioOptions::default().seed,
    ));
    let walk = Arc::new(scenario.walks().unwrap().swap_remove(0));
    let mut config = RobotConfig::connecting_to(walk.robot.as_str(), &test.zenoh_endpoint);
    config.delivery = Delivery::Reliable;
    let robot = Robot::connect(config).await.unwrap();
    let frames = 90;
    let options = SimOptions {
        rate: Rate::Hz(15.0),
        limit: Some(frames),
        ..SimOptions::default()
    };
    simulated::stream(&robot, renderer, walk.clone(), &options, |_, _| {})
        .await
        .unwrap();
    let status = wait_for("every frame processed", Duration::from_secs(60), || async {
        let status = test.client.robot(&walk.robot).await.ok()?;
        let f = &status.frames;
        (f.processed + f.dropped + f.rejected >= frames as u64).then_some(status)
    })
    .await;
    let tracking = status.tracking.unwrap();
    eprintln!("robot in the imported map: {:?}", tracking.recent_events);
    assert_eq!(tracking.map_id, Some(map.id), "{tracking:?}");
    // Its own first map merged into the imported one without costing a frame.
    assert!(
        tracking
            .recent_events
            .iter()
            .all(|e| !e.event.starts_with("error")),
        "{tracking:?}"
    );
    let maps = test.client.server_maps().await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert!(maps[0].keyframes >= map.keyframes, "{maps:?}");
    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}
