//! The real 7-Scenes RGB-D sequence (400 Kinect frames) played by the SDK player through real
//! zenoh into the real server: every frame is accounted for and none is rejected.

use std::time::Duration;
use vsgraphs_sdk::player::{play, PlayOptions, Rate};
use vsgraphs_sdk::proto::DepthEncoding;
use vsgraphs_sdk::{dataset, Delivery, Robot, RobotConfig};
use vsgraphs_tests::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_frame_of_the_sequence_is_accounted_for() {
    let Some(dir) = data_dir("seven_scenes") else {
        return;
    };
    let dataset = dataset::open(&dir.join("7scenes-a")).unwrap();
    assert_eq!(dataset.frames.len(), 400);
    assert_eq!(
        (dataset.camera.fx, dataset.camera.cx, dataset.depth_scale),
        (585.0, 320.0, 1000.0)
    );
    let test = TestServer::start().await;
    let mut config = RobotConfig::connecting_to("kinect", &test.zenoh_endpoint);
    config.delivery = Delivery::Reliable;
    let robot = Robot::connect(config).await.unwrap();
    let options = PlayOptions {
        rate: Rate::Max,
        depth_codec: DepthEncoding::Rvl,
        ..PlayOptions::default()
    };
    let summary = play(&robot, &dataset, &options, |_, _| {}).await.unwrap();
    assert_eq!(summary.frames_sent, 400);
    assert!(summary.skipped.is_empty(), "{:?}", summary.skipped);
    let status = wait_for(
        "all frames accounted for",
        Duration::from_secs(120),
        || async {
            let status = test.client.robot("kinect").await.ok()?;
            let f = &status.frames;
            (f.processed + f.dropped + f.rejected + f.lost == summary.frames_sent && f.queued == 0)
                .then_some(status)
        },
    )
    .await;
    let f = &status.frames;
    eprintln!(
        "7-Scenes: sent {}, processed {}, dropped {}, rejected {}, lost {}; {:.1} MB, depth at {:.1}% of raw; server {:.1} ms/frame",
        summary.frames_sent,
        f.processed,
        f.dropped,
        f.rejected,
        f.lost,
        summary.bytes_sent as f64 / 1e6,
        100.0 * summary.depth_bytes as f64 / summary.depth_raw_bytes as f64,
        status.timing.processing_ms_mean.unwrap_or(f64::NAN),
    );
    assert_eq!(
        f.received, summary.frames_sent,
        "reliable delivery loses nothing on loopback"
    );
    assert_eq!(f.lost, 0);
    assert_eq!(f.rejected, 0, "{:?}", status.last_rejection);
    assert_eq!(f.processed + f.dropped + f.rejected, summary.frames_sent);
    assert!(f.processed > 0);
    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}
