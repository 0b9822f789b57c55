//! Bad frames over real zenoh: each is rejected with its reason visible in the API, the server
//! keeps serving, the next good frame is processed, and a robot that vanishes is seen offline.

use std::time::Duration;
use vsgraphs_proto::api::Presence;
use vsgraphs_proto::{ColourEncoding, DepthEncoding, DepthImage, Message, RgbdFrame};
use vsgraphs_sdk::robot::now_ns;
use vsgraphs_tests::*;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::{render, PlacedMarker};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_frames_are_rejected_with_reasons_and_the_stream_goes_on() {
    // A frame limit of a mebibyte: this test's good frames fit, and frames beyond it are cheap.
    const LIMIT: usize = 1 << 20;
    let test = TestServer::start_with(|c| c.ingest.max_frame_bytes = LIMIT).await;
    let robot = test.robot("clumsy").await;
    let camera = d435();
    let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
    let marker = PlacedMarker {
        id: 5,
        side_m: 0.08,
        camera_from_marker: nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::new(0.0, 0.0, 1.0),
            nalgebra::UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        ),
    };
    let rendered = render(&camera, &dictionary, &[marker], 2.0).unwrap();
    let (colour, depth) = encode_rendered(&camera, &rendered);
    let model = camera.to_wire();

    // Sends one good frame and waits until the server has processed it.
    let good = |label: &'static str| {
        let (robot, colour, depth, model, client) = (
            &robot,
            colour.clone(),
            depth.clone(),
            model.clone(),
            test.client.clone(),
        );
        async move {
            let (sequence, _) = robot
                .publish(now_ns(), model, 1000.0, colour, depth)
                .await
                .unwrap();
            let detections = wait_for(label, Duration::from_secs(20), || async {
                client
                    .detections("clumsy")
                    .await
                    .ok()
                    .filter(|d| d.sequence == sequence)
            })
            .await;
            assert_eq!(
                detections.markers.iter().map(|m| m.id).collect::<Vec<_>>(),
                [5],
                "{label}"
            );
        }
    };
    // Waits until `reason` has been counted `count` times, and checks it is the latest rejection.
    let rejected_times = |reason: &'static str, count: u64| {
        let client = test.client.clone();
        async move {
            let status = wait_for(reason, Duration::from_secs(20), || async {
                let status = client.robot("clumsy").await.ok()?;
                (status.frames.rejected_by_reason.get(reason) == Some(&count)).then_some(status)
            })
            .await;
            let last = status.last_rejection.expect("a rejection is reported");
            assert_eq!(last.reason, reason);
            assert!(!last.message.is_empty());
            eprintln!("{reason}: {}", last.message);
        }
    };
    let rejected = |reason: &'static str| rejected_times(reason, 1);

    good("first good frame").await;

    let mut truncated = colour.clone();
    truncated.data.truncate(truncated.data.len() * 2 / 3);
    robot
        .publish(now_ns(), model.clone(), 1000.0, truncated, depth.clone())
        .await
        .unwrap();
    rejected("colour_decode").await;
    good("after a truncated JPEG").await;

    let small_depth =
        vsgraphs_sdk::encode::depth(&vec![1000; 320 * 240], 320, 240, DepthEncoding::Raw16)
            .unwrap();
    robot
        .publish(now_ns(), model.clone(), 1000.0, colour.clone(), small_depth)
        .await
        .unwrap();
    rejected("size_mismatch").await;
    good("after depth of the wrong size").await;

    let mut unknown = colour.clone();
    unknown.encoding = 17;
    robot
        .publish(now_ns(), model.clone(), 1000.0, unknown, depth.clone())
        .await
        .unwrap();
    rejected("unknown_encoding").await;
    let odd_depth = DepthImage {
        encoding: 9,
        data: depth.data.clone(),
        registration: 0,
    };
    robot
        .publish(now_ns(), model.clone(), 1000.0, colour.clone(), odd_depth)
        .await
        .unwrap();
    // One frame at a time: a live robot's publisher drops a frame sent while the one before is
    // still on the wire, and this test is about the server, not about congestion.
    rejected_times("unknown_encoding", 2).await;
    good("after unknown encodings").await;

    let mut no_focal = model.clone();
    no_focal.fx = 0.0;
    robot
        .publish(now_ns(), no_focal, 1000.0, colour.clone(), depth.clone())
        .await
        .unwrap();
    rejected("bad_camera").await;
    good("after a zero focal length").await;

    robot
        .publish_raw(b"\xff\x00garbage that is no protobuf \x13\x37".to_vec())
        .await
        .unwrap();
    rejected("malformed").await;
    good("after garbage bytes").await;

    // A frame of the robot's own session stamped at the end of time: refused, and the frames
    // after it, stamped now, still pass (it would have made every one of them look old).
    robot
        .publish(
            u64::MAX,
            model.clone(),
            1000.0,
            colour.clone(),
            depth.clone(),
        )
        .await
        .unwrap();
    rejected("bad_timestamp").await;
    good("after a frame stamped at the end of time").await;

    let impostor = RgbdFrame {
        robot_id: "someone-else".into(),
        session_id: "s".into(),
        sequence: 0,
        timestamp_ns: now_ns(),
        camera: Some(model.clone()),
        depth_scale: 1000.0,
        colour: Some(colour.clone()),
        depth: Some(depth.clone()),
        odometry: None,
        imu: vec![],
    };
    robot.publish_raw(impostor.encode_to_vec()).await.unwrap();
    rejected("robot_id_mismatch").await;
    good("after a frame naming another robot").await;

    // Above the limit: refused before it is decoded. So is a frame within it whose IMU
    // samples (two bytes each on the wire, a whole struct each once decoded) are too many.
    let mut padded = colour.clone();
    padded.data.resize(LIMIT + 1000, 0);
    robot
        .publish(now_ns(), model.clone(), 1000.0, padded, depth.clone())
        .await
        .unwrap();
    rejected("too_large").await;
    good("after a frame too large").await;
    let mut samples = impostor.clone();
    samples.robot_id = "clumsy".into();
    samples.imu = vec![Default::default(); 100_000];
    robot.publish_raw(samples.encode_to_vec()).await.unwrap();
    rejected_times("too_large", 2).await;
    good("after a frame of a hundred thousand IMU samples").await;
    // Beyond twice the limit zenoh drops the message before it is whole: never received, so
    // not counted; its sequence number is missing, and the stream goes on.
    let mut huge = colour.clone();
    huge.data.resize(3 * LIMIT, 0);
    robot
        .publish(now_ns(), model.clone(), 1000.0, huge, depth.clone())
        .await
        .unwrap();
    // Three mebibytes on loopback take milliseconds; the next frame must not find the
    // publisher still busy with them (it would drop it, as a live robot's does).
    tokio::time::sleep(Duration::from_millis(500)).await;
    good("after a frame zenoh dropped").await;

    let status = test.client.robot("clumsy").await.unwrap();
    let f = &status.frames;
    assert_eq!(f.processed, 11);
    assert_eq!(f.rejected, 10);
    assert_eq!(f.rejected_by_reason["unknown_encoding"], 2);
    assert_eq!(f.rejected_by_reason["too_large"], 2);
    assert_eq!(f.received, f.processed + f.rejected + f.dropped);
    assert_eq!(f.lost, 1, "the frame zenoh dropped");
    assert_eq!(status.presence, Presence::Online);
    assert_eq!(ColourEncoding::Jpeg as i32, colour.encoding);
    // Prometheus sees the same counts, rejections by reason among them.
    assert_metrics_agree(&test, "clumsy").await;

    // A second robot vanishes mid-stream without saying goodbye.
    let ghost = test.robot("ghost").await;
    ghost
        .publish(
            now_ns(),
            model.clone(),
            1000.0,
            colour.clone(),
            depth.clone(),
        )
        .await
        .unwrap();
    wait_for("the ghost online", Duration::from_secs(20), || async {
        let s = test.client.robot("ghost").await.ok()?;
        (s.presence == Presence::Online && s.frames.processed == 1).then_some(())
    })
    .await;
    drop(ghost);
    let ghost_status = wait_for("the ghost offline", Duration::from_secs(30), || async {
        let s = test.client.robot("ghost").await.ok()?;
        (s.presence == Presence::Offline).then_some(s)
    })
    .await;
    assert!(ghost_status.last_seen_ns.is_some());
    // The server still serves, and the other robot still streams.
    assert_eq!(test.client.health().await.unwrap().status, "ok");
    good("after another robot vanished").await;

    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}
