//! The server binary killed with SIGKILL in the middle of a robot's walk comes back, on the same
//! store, with every keyframe it reported stored before the kill; the robot, connecting again,
//! goes on mapping, and its new map joins the one read back. Stopped with SIGTERM, it tells the
//! robots and comes back with every keyframe.

#![cfg(unix)]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};
use vsgraphs_sdk::player::Rate;
use vsgraphs_sdk::simulated::{self, SimOptions};
use vsgraphs_sdk::{Client, Delivery, Robot, RobotConfig};
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::walk::Walk;

/// The server binary on `store`, its zenoh on `zenoh`; returns it and its HTTP client once it
/// serves.
fn serve(store: &Path, zenoh: &str, dictionary: &Path) -> (Child, Client) {
    let mut server = Command::new(env!("CARGO_BIN_EXE_vsgraphs-server"))
        .args([
            "--http-listen",
            "127.0.0.1:0",
            "--no-scouting",
            "--zenoh-listen",
            zenoh,
        ])
        .arg("--store")
        .arg(store)
        .arg("--semantic-dictionary")
        .arg(dictionary)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(server.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("the server did not start: {line:?}"))
        .trim_end_matches('/')
        .to_owned();
    (server, Client::new(url))
}

async fn wait_for<T, F: std::future::Future<Output = Option<T>>>(
    what: &str,
    timeout: Duration,
    mut check: impl FnMut() -> F,
) -> T {
    let start = Instant::now();
    loop {
        if let Some(value) = check().await {
            return value;
        }
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Frames `from..to` of `walk`, as a walk of their own.
fn part(walk: &Walk, from: usize, to: usize) -> Walk {
    Walk {
        robot: walk.robot.clone(),
        times: walk.times[from..to]
            .iter()
            .map(|t| t - walk.times[from])
            .collect(),
        world_from_camera: walk.world_from_camera[from..to].to_vec(),
        floor: walk.floor[from..to].to_vec(),
    }
}

/// Robot `id` on `zenoh`, whose frames are all delivered.
async fn robot(zenoh: &str, id: &str) -> Robot {
    let mut config = RobotConfig::connecting_to(id, zenoh);
    config.delivery = Delivery::Reliable;
    Robot::connect(config).await.unwrap()
}

/// Streams `walk` as `robot` at 10 frames/s, a rate the server keeps up with in a test build.
async fn stream(robot: &Robot, renderer: &Arc<vsgraphs_sim::Renderer>, walk: Walk) -> u64 {
    let options = SimOptions {
        rate: Rate::Hz(10.0),
        ..SimOptions::default()
    };
    simulated::stream(robot, renderer.clone(), Arc::new(walk), &options, |_, _| {})
        .await
        .unwrap()
        .frames_sent
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_killed_mid_walk_comes_back_with_its_stored_map() {
    let scenario = Scenario::builtin("seq06").unwrap();
    let (building, renderer) = scenario.build(1).unwrap();
    let renderer = Arc::new(renderer);
    let walk = scenario.walks().unwrap().remove(0);
    let dir = tempfile::tempdir().unwrap();
    let dictionary = dir.path().join("building.json");
    std::fs::write(&dictionary, building.dictionary_v1().to_string()).unwrap();
    let store = dir.path().join("maps.redb");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let zenoh = format!("tcp/127.0.0.1:{port}");

    // The robot walks; the server is killed while frames still arrive, once it has stored a
    // few keyframes.
    let (mut server, client) = serve(&store, &zenoh, &dictionary);
    let first = robot(&zenoh, "sim-1").await;
    let walking = {
        let renderer = renderer.clone();
        let walk = part(&walk, 0, 200);
        tokio::spawn(async move {
            stream(&first, &renderer, walk).await;
            first
        })
    };
    let before = wait_for("keyframes stored", Duration::from_secs(60), || async {
        let maps = client.server_maps().await.ok()?;
        let map = maps.first()?.clone();
        (map.stored_keyframes? >= 10).then_some(map)
    })
    .await;
    // Read right before the kill: the store holds at least this much when it comes.
    let stored = client.server_maps().await.unwrap()[0]
        .stored_keyframes
        .unwrap();
    let processed = client.robot("sim-1").await.unwrap().frames.processed as usize;
    server.kill().unwrap();
    server.wait().unwrap();
    assert!(!walking.is_finished(), "the walk went on after the kill");
    walking.await.unwrap().close().await.unwrap();

    let (mut server, client) = serve(&store, &zenoh, &dictionary);
    let maps = client.server_maps().await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    let back = maps[0].clone();
    assert_eq!(back.id, before.id);
    assert!(
        back.stored_keyframes.unwrap() >= stored,
        "stored {stored} before the kill, {:?} after",
        back.stored_keyframes
    );
    assert!(back.markers >= before.markers, "{before:?} then {back:?}");
    assert!(back.updated_ns > 0, "{back:?}");

    // The robot connects again a little behind where it was (the frames sent while the server
    // was down are lost) and walks on: its new map joins the one read back, and the walls of
    // the whole are the building's.
    let second = robot(&zenoh, "sim-1").await;
    let from = processed.saturating_sub(30);
    let frames = stream(&second, &renderer, part(&walk, from, from + 150)).await;
    wait_for("every frame handled", Duration::from_secs(120), || async {
        let f = client.robot("sim-1").await.ok()?.frames;
        (f.processed + f.dropped + f.rejected >= frames).then_some(())
    })
    .await;
    second.close().await.unwrap();
    let merged = wait_for(
        "the robot's map merged into the stored one",
        Duration::from_secs(60),
        || async {
            let maps = client.server_maps().await.ok()?;
            (maps.len() == 1).then(|| maps[0].clone())
        },
    )
    .await;
    assert_eq!(merged.id, before.id, "{merged:?}");
    assert!(
        merged.keyframes > back.keyframes,
        "{back:?} then {merged:?}"
    );
    let walls = client.walls(merged.id).await.unwrap();
    assert!(!walls.is_empty());
    for wall in &walls {
        let true_walls: std::collections::BTreeSet<usize> = wall
            .markers
            .iter()
            .map(|&id| building.markers[id as usize].wall)
            .collect();
        assert_eq!(true_walls.len(), 1, "{wall:?}");
    }

    // SIGTERM, by contrast, loses nothing: the server says goodbye to the robots still
    // connected and stores every keyframe before it exits.
    let watcher = robot(&zenoh, "watcher").await;
    wait_for(
        "the robot sees the server",
        Duration::from_secs(10),
        || async { watcher.server_online().then_some(()) },
    )
    .await;
    let last = client.server_maps().await.unwrap()[0].clone();
    let terminated = Command::new("kill")
        .args(["-TERM", &server.id().to_string()])
        .status()
        .unwrap();
    assert!(terminated.success());
    wait_for(
        "the robot sees the server go",
        Duration::from_secs(30),
        || async { (!watcher.server_online()).then_some(()) },
    )
    .await;
    assert!(server.wait().unwrap().success());
    let (mut server, client) = serve(&store, &zenoh, &dictionary);
    let maps = client.server_maps().await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert_eq!(maps[0].id, last.id);
    assert_eq!(
        maps[0].keyframes, last.keyframes,
        "{last:?} then {:?}",
        maps[0]
    );
    assert_eq!(maps[0].stored_keyframes, Some(last.keyframes));
    wait_for(
        "the robot sees the server back",
        Duration::from_secs(30),
        || async { watcher.server_online().then_some(()) },
    )
    .await;
    watcher.close().await.unwrap();
    let _ = server.kill();
    let _ = server.wait();
    eprintln!(
        "before the kill {before:?} (stored {stored}); read back {back:?}; after the walk \
         {merged:?}; after SIGTERM {:?}",
        maps[0]
    );
}
