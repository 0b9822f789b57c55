//! Tracking through the whole system: the 7-Scenes frames streamed by the SDK player over real
//! zenoh to the real server give exactly the trajectory `vsgraphs-server offline` computes from
//! the same files, and the API reports the robot's tracking.

use std::time::Duration;
use vsgraphs_proto::api::{TrackingState, TrajectoryPose};
use vsgraphs_sdk::player::{play, PlayOptions, Rate};
use vsgraphs_sdk::proto::DepthEncoding;
use vsgraphs_sdk::{dataset, Delivery, Robot, RobotConfig};
use vsgraphs_server::config::Config;
use vsgraphs_tests::*;

/// Frames streamed: enough for several keyframes and local bundle adjustments.
const FRAMES: usize = 120;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_tracking_matches_the_offline_run() {
    let Some(dir) = data_dir("live_tracking_matches_the_offline_run") else {
        return;
    };
    let dataset = dataset::open(&dir.join("7scenes-a")).unwrap();
    let offline_dataset = dataset.clone();
    let (summary, trajectories) = tokio::task::spawn_blocking(move || {
        vsgraphs_pipeline::offline::run(
            &Config::default().pipeline(),
            &offline_dataset,
            Some(FRAMES),
            |_, _| {},
        )
    })
    .await
    .unwrap()
    .unwrap();
    assert_eq!(summary.tracked, FRAMES, "{:?}", summary.events);
    // The refined trajectory puts a keyframe's frame where the final map has the keyframe,
    // which local BA has moved since the frame was tracked.
    let view = summary.map_views.last().expect("a map");
    let first_ns = trajectories.refined[0].timestamp_ns;
    let mut moved = 0;
    for keyframe in &view.keyframes {
        // Offline stamps start at 1 ns; the trajectory keeps the files' stamps.
        let stamp = first_ns + keyframe.timestamp_ns - 1;
        let at = |poses: &[vsgraphs_proto::api::TrajectoryPose]| {
            poses
                .iter()
                .find(|p| p.timestamp_ns == stamp)
                .expect("every keyframe's frame is in the trajectory")
                .world_from_camera
        };
        let (refined, tracked) = (at(&trajectories.refined), at(&trajectories.as_tracked));
        assert!(
            largest_difference(&refined, &keyframe.world_from_camera) < 1e-9,
            "keyframe {}: {refined:?} in the trajectory, {:?} in the map",
            keyframe.id,
            keyframe.world_from_camera
        );
        if largest_difference(&refined, &tracked) > 1e-6 {
            moved += 1;
        }
    }
    eprintln!(
        "local BA moved {moved} of {} keyframes after they were tracked",
        view.keyframes.len()
    );
    assert!(
        moved * 2 > view.keyframes.len(),
        "local BA moved only {moved} of {} keyframes",
        view.keyframes.len()
    );
    // The API serves the refined trajectory too.
    let offline = trajectories.refined;
    assert!(summary.keyframes >= 3, "{} keyframes", summary.keyframes);

    // A queue as long as the run: the comparison needs every frame, and a busy machine can
    // hold the worker up for longer than the default queue of 4 covers (seen once in CI under
    // extra load: 5 frames dropped).
    let test = TestServer::start_with(|config| config.ingest.queue_capacity = FRAMES).await;
    let mut config = RobotConfig::connecting_to("kinect", &test.zenoh_endpoint);
    config.delivery = Delivery::Reliable;
    let robot = Robot::connect(config).await.unwrap();
    // Slow enough that the server never has to drop a frame (a dropped frame would change the
    // motion model's prediction, and so the trajectory).
    // Preloaded: the frames sent from memory must be the frames read one by one.
    let options = PlayOptions {
        rate: Rate::Hz(8.0),
        depth_codec: DepthEncoding::Rvl,
        limit: Some(FRAMES),
        preload: true,
        ..PlayOptions::default()
    };
    let played = play(&robot, &dataset, &options, |_, _| {}).await.unwrap();
    let shift_ns = played
        .recording_to_stream_ns
        .expect("frames follow the recording's clock");
    let status = wait_for("all frames processed", Duration::from_secs(120), || async {
        let status = test.client.robot("kinect").await.ok()?;
        (status.frames.processed + status.frames.dropped + status.frames.rejected == FRAMES as u64
            && status.frames.queued == 0)
            .then_some(status)
    })
    .await;
    assert_eq!(status.frames.dropped, 0, "the comparison needs every frame");
    let tracking = status.tracking.expect("tracking is on by default");
    assert_eq!(tracking.state, TrackingState::Tracking);
    assert_eq!(tracking.frames_tracked, FRAMES as u64);
    assert_eq!(tracking.keyframes as usize, summary.keyframes);
    assert!(tracking.features_ms_mean.is_some());
    // The map's start is the one event of a walk tracked throughout, at the first frame's stamp.
    let events: Vec<&str> = tracking
        .recent_events
        .iter()
        .map(|e| e.event.as_str())
        .collect();
    assert_eq!(events.len(), 1, "{events:?}");
    assert!(events[0].starts_with("map 0 started"), "{events:?}");
    let live = test.client.trajectory("kinect").await.unwrap();
    assert_eq!(live.len(), offline.len());
    let mut worst: f64 = 0.0;
    for (a, b) in live.iter().zip(&offline) {
        assert_eq!(a.map, b.map);
        // The shift the player reports takes each pose back to its frame in the recording.
        assert_eq!(
            i128::from(a.timestamp_ns) - shift_ns,
            i128::from(b.timestamp_ns)
        );
        worst = worst.max(largest_difference(
            &a.world_from_camera,
            &b.world_from_camera,
        ));
    }
    // Read in pages of 7, the same poses.
    let mut paged = Vec::new();
    loop {
        let after = paged.last().map_or(0, |p: &TrajectoryPose| p.timestamp_ns);
        let page = test
            .client
            .trajectory_page("kinect", after, 7)
            .await
            .unwrap();
        assert!(page.len() <= 7);
        if page.is_empty() {
            break;
        }
        paged.extend(page);
    }
    assert_eq!(paged, live);
    eprintln!(
        "{FRAMES} frames live and offline: largest difference {worst:e}; {} keyframes",
        summary.keyframes
    );
    assert!(
        worst < 1e-9,
        "live and offline trajectories differ by {worst}"
    );
    let metrics = assert_metrics_agree(&test, "kinect").await;
    // Every frame tracked: each stage of tracking saw every frame.
    for stage in ["features", "tracking", "mapping"] {
        assert_eq!(metrics.observations(stage), FRAMES as f64, "{stage}");
    }
    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}

/// The largest difference of two poses' translations (m) and quaternion components.
fn largest_difference(a: &vsgraphs_proto::api::Pose, b: &vsgraphs_proto::api::Pose) -> f64 {
    let translation = a.translation_m.iter().zip(&b.translation_m);
    let rotation = a.rotation_xyzw.iter().zip(&b.rotation_xyzw);
    translation
        .chain(rotation)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}
