//! Maps as files: a map two robots made and merged (`tests/data/two_wings.json`) exported,
//! imported into another server's maps, and exported again gives the same bytes, the same map
//! to the last bit and the same walls, doorways, rooms and corridors; files cut short, changed
//! or of another kind are refused, each with its reason. Through the real server's API the
//! same file goes in and out, and a robot that walks the building goes on in the imported map.

use std::sync::Arc;
use std::time::{Duration, Instant};
use vsgraphs_eval::scenario::{self, ScenarioOptions};
use vsgraphs_pipeline::maps::{ImportError, MapService};
use vsgraphs_pipeline::store::StoreError;
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

    kept_in_a_store(&config, &bytes);

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

/// The map of `bytes` kept in a map store: written whole when it arrives, read back by the next
/// service on the same store with its id, the same map to the last bit. A store cut short, or
/// with any of its bytes changed, is refused with what is wrong, or read back as it was:
/// never as another map.
fn kept_in_a_store(config: &PipelineConfig, bytes: &[u8]) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("maps.redb");
    let service = || MapService::new().with_mapping(config.tracking.tracker().mapping());
    let first = service().with_store(&path, Duration::from_secs(1)).unwrap();
    let id = first.import(bytes).unwrap();
    first.stop();
    assert_eq!(
        first.stored_keyframes(id),
        Some(archive::decode(bytes).unwrap().keyframes.len() as u32)
    );
    drop(first);
    let size = std::fs::metadata(&path).unwrap().len();

    let started = Instant::now();
    let second = service().with_store(&path, Duration::from_secs(1)).unwrap();
    let read_ms = started.elapsed().as_secs_f64() * 1e3;
    assert_eq!(second.all().iter().map(|m| m.0).collect::<Vec<_>>(), [id]);
    assert!(
        second.export(id).unwrap() == bytes,
        "the map read from the store differs"
    );
    second.stop();
    drop(second);
    eprintln!("store: {size} bytes, read back in {read_ms:.0} ms");

    let original = std::fs::read(&path).unwrap();
    let damaged = dir.path().join("damaged.redb");
    let open = |stored: &[u8]| -> Result<bool, StoreError> {
        std::fs::write(&damaged, stored).unwrap();
        let s = service().with_store(&damaged, Duration::from_secs(1))?;
        let ids: Vec<_> = s.all().iter().map(|m| m.0).collect();
        let same = ids == [id] && s.export(id).unwrap() == bytes;
        s.stop();
        Ok(same)
    };
    let cut = open(&original[..original.len() / 2]).unwrap_err();
    eprintln!("store cut short: {cut}");
    let (mut refused, mut intact) = (0, 0);
    for at in (0..original.len()).step_by(original.len() / 23 + 1) {
        let mut flipped = original.clone();
        flipped[at] ^= 0x10;
        match open(&flipped) {
            Err(e) => {
                refused += 1;
                if refused == 1 {
                    eprintln!("store with a byte changed: {e}");
                }
            }
            Ok(same) => {
                assert!(same, "a byte changed at {at} gave another map");
                intact += 1;
            }
        }
    }
    eprintln!(
        "a byte changed at {} places: {refused} refused, {intact} read back as written",
        refused + intact
    );
    assert!(refused > 0);
}
