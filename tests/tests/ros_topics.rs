//! A ROS 2 robot joins by configuration alone: the 7-Scenes frames, serialised by `rosbags` as
//! a RealSense driver's topics (`ros/make_bag.py`), are put over real zenoh on the keys rmw_zenoh
//! or zenoh-bridge-ros2dds would use, with rmw_zenoh's attachment, and the server maps them with
//! the trajectory the folder gives (which `live_tracking` shows `vsgraphs-robot play` gives).
//! Bad messages (not CDR, larger than a frame may be, before any camera info) are refused with
//! their reason and counted.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;
use vsgraphs_datasets::{dataset, load_frame, Dataset};
use vsgraphs_proto::api::Presence;
use vsgraphs_proto::ros::MessageType;
use vsgraphs_proto::{png16, DepthEncoding};
use vsgraphs_server::config::{Config, RosKeys, RosRobotConfig};
use vsgraphs_tests::*;

/// Enough frames for keyframes and a local bundle adjustment.
const FRAMES: usize = 60;
/// The bag's stamps start here (see `make_bag.py`); the folder's at 0.
const BASE_NS: u64 = 1_700_000_000_000_000_000;
const NS: &str = "/camera/camera";
/// A type hash as rmw_zenoh puts it in its keys (the server leaves this chunk open).
const TYPE_HASH: &str = "RIHS01_0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compressed_topics_over_rmw_zenoh_track_like_the_folder() {
    ros_robot_tracks_like_the_folder(
        "compressed_topics_over_rmw_zenoh_track_like_the_folder",
        false,
        RosKeys::RmwZenoh,
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn raw_topics_over_the_dds_bridge_track_like_the_folder() {
    ros_robot_tracks_like_the_folder(
        "raw_topics_over_the_dds_bridge_track_like_the_folder",
        true,
        RosKeys::Ros2dds,
    )
    .await;
}

/// The bag's messages in the order they were recorded: topic and CDR bytes.
fn recorded(bag: &Path) -> Vec<(String, Vec<u8>)> {
    let file = std::fs::File::open(bag).unwrap();
    mcap::io::MessageReader::new(std::io::BufReader::new(file))
        .map(|m| {
            let m = m.unwrap();
            (m.channel.topic.clone(), m.data.to_vec())
        })
        .collect()
}

/// Writes each frame's pixels as the server decodes them (grey colour, depth in mm), for
/// `make_bag.py`'s raw images: raw grey pixels then give the same trajectory as the JPEG.
fn decode_frames(folder: &Dataset, out: &Path) {
    for (i, files) in folder.frames.iter().take(FRAMES).enumerate() {
        let (colour, depth, _) =
            load_frame(files, DepthEncoding::Png16, folder.depth_registration).unwrap();
        let grey = vsgraphs_vision::decode::colour_to_grey(&colour, 640, 480).unwrap();
        std::fs::write(out.join(format!("frame-{i:06}.grey")), grey.pixels()).unwrap();
        let mm = png16::decode(&depth.data).unwrap();
        let bytes: Vec<u8> = mm.data.iter().flat_map(|d| d.to_le_bytes()).collect();
        std::fs::write(out.join(format!("frame-{i:06}.depth")), bytes).unwrap();
    }
}

/// rmw_zenoh's attachment: sequence number and source time (little-endian i64s), then the
/// publisher's 16-byte GID after its length.
fn attachment(sequence: i64) -> Vec<u8> {
    let mut bytes = sequence.to_le_bytes().to_vec();
    bytes.extend(1_700_000_000_000_000_000i64.to_le_bytes());
    bytes.push(16);
    bytes.extend([7u8; 16]);
    bytes
}

/// The same message stamped one second earlier (the header's `sec`, right after the 4-byte
/// encapsulation, little-endian).
fn a_second_earlier(cdr: &[u8]) -> Vec<u8> {
    let mut bytes = cdr.to_vec();
    let sec = i32::from_le_bytes(bytes[4..8].try_into().unwrap());
    bytes[4..8].copy_from_slice(&(sec - 1).to_le_bytes());
    bytes
}

async fn ros_robot_tracks_like_the_folder(test: &str, raw: bool, keys: RosKeys) {
    let (Some(data), Some(python)) = (data_dir(test), python_with_rosbags(test)) else {
        return;
    };
    let folder = dataset::open(&data.join("7scenes-a")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let bag_dir = dir.path().join("bag");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("ros/make_bag.py");
    let mut command = Command::new(&python);
    command
        .arg(&script)
        .arg(data.join("7scenes-a"))
        .arg(&bag_dir)
        .arg(FRAMES.to_string());
    if raw {
        let pixels: PathBuf = dir.path().join("pixels");
        std::fs::create_dir(&pixels).unwrap();
        decode_frames(&folder, &pixels);
        command.arg("--raw").arg(&pixels);
    }
    assert!(command.status().unwrap().success(), "{}", script.display());
    let messages = recorded(&bag_dir.join("bag.mcap"));

    let (colour_topic, depth_topic) = if raw {
        (
            format!("{NS}/color/image_raw"),
            format!("{NS}/depth/image_rect_raw"),
        )
    } else {
        (
            format!("{NS}/color/image_raw/compressed"),
            format!("{NS}/depth/image_rect_raw/compressedDepth"),
        )
    };
    let info_topic = format!("{NS}/color/camera_info");
    let robot = RosRobotConfig {
        id: "ros-kinect".into(),
        keys,
        domain_id: 3,
        namespace: "site-a".into(),
        colour: colour_topic.clone(),
        depth: depth_topic.clone(),
        camera_info: info_topic.clone(),
    };
    let format = robot.key_format();

    // The reference: the folder's frames through the pipeline.
    let mut head = folder.clone();
    head.frames.truncate(FRAMES);
    let offline = tokio::task::spawn_blocking(move || {
        vsgraphs_pipeline::offline::run(&Config::default().pipeline(), &head, None, |_, _| {})
            .unwrap()
            .1
            .refined
    })
    .await
    .unwrap();
    assert_eq!(offline.len(), FRAMES);

    let configured = robot.clone();
    let test = TestServer::start_with(move |config| {
        // Every frame is needed for the comparison.
        config.ingest.queue_capacity = FRAMES + 2;
        // Above the frames' size (under 1 MB, raw), below the oversized message sent below.
        config.ingest.max_frame_bytes = 1 << 20;
        config.ros.robots = vec![configured];
    })
    .await;
    let mut zenoh_config = zenoh::Config::default();
    zenoh_config
        .insert_json5(
            "connect/endpoints",
            &format!("[\"{}\"]", test.zenoh_endpoint),
        )
        .unwrap();
    zenoh_config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    let session = zenoh::open(zenoh_config).await.unwrap();
    let types = [
        (&colour_topic, MessageType::of_image_topic(&colour_topic)),
        (&depth_topic, MessageType::of_image_topic(&depth_topic)),
        (&info_topic, MessageType::CameraInfo),
    ];
    let mut publishers = Vec::new();
    for (topic, message) in types {
        let key = format.publication(topic, message, TYPE_HASH);
        let publisher = session
            .declare_publisher(key.clone())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        // A message put before the server's subscription is known here would go nowhere.
        wait_for(
            &format!("a subscriber of {key}"),
            Duration::from_secs(20),
            || async {
                publisher
                    .matching_status()
                    .await
                    .unwrap()
                    .matching()
                    .then_some(())
            },
        )
        .await;
        publishers.push((topic.clone(), publisher));
    }
    let mut sequence = 0;
    let mut put = |topic: &str, bytes: Vec<u8>| {
        let publisher = &publishers.iter().find(|(t, _)| t == topic).unwrap().1;
        sequence += 1;
        let attachment = attachment(sequence);
        async move { publisher.put(bytes).attachment(attachment).await.unwrap() }
    };
    let status = |rejected: u64, processed: u64| {
        let client = &test.client;
        async move {
            let status = client.robot("ros-kinect").await.ok()?;
            (status.frames.rejected == rejected
                && status.frames.processed == processed
                && status.frames.queued == 0)
                .then_some(status)
        }
    };

    // rmw_zenoh's publishers announce themselves: the robot is online while its colour
    // topic's publisher is.
    let token = match keys {
        RosKeys::RmwZenoh => {
            let key = format!(
                "@ros2_lv/3/{}/0/10/MP/%/%/camera/{}/{}/{TYPE_HASH}/::,7:,:,:,,",
                session.zid(),
                colour_topic.replace('/', "%"),
                MessageType::of_image_topic(&colour_topic).dds_name()
            );
            let token = session.liveliness().declare_token(key).await.unwrap();
            wait_for("the robot online", Duration::from_secs(20), || async {
                let status = test.client.robot("ros-kinect").await.ok()?;
                (status.presence == Presence::Online).then_some(())
            })
            .await;
            Some(token)
        }
        RosKeys::Ros2dds => None,
    };

    // Bytes that are no message, and a pair before any camera info: refused, with reasons.
    let first_of = |topic: &str| {
        messages
            .iter()
            .find(|(t, _)| t == topic)
            .map(|(_, bytes)| bytes.clone())
            .unwrap()
    };
    put(&colour_topic, b"\x00\x01\x00\x00garbage".to_vec()).await;
    put(&colour_topic, vec![0; 3 << 19]).await;
    put(&colour_topic, a_second_earlier(&first_of(&colour_topic))).await;
    put(&depth_topic, a_second_earlier(&first_of(&depth_topic))).await;
    let refused = wait_for("three refusals", Duration::from_secs(30), || status(3, 0)).await;
    let by_reason = &refused.frames.rejected_by_reason;
    assert_eq!(by_reason.get("ros_message"), Some(&2), "{by_reason:?}");
    assert_eq!(
        by_reason.get("ros_no_camera_info"),
        Some(&1),
        "{by_reason:?}"
    );

    // The recording, one frame at a time (the IMU topic is not the robot's camera).
    let mut frames = 0;
    for (topic, bytes) in &messages {
        if topic.ends_with("/imu") {
            continue;
        }
        put(topic, bytes.clone()).await;
        if topic == &depth_topic {
            frames += 1;
            wait_for("the frame processed", Duration::from_secs(60), || {
                status(3, frames)
            })
            .await;
        }
    }
    assert_eq!(frames as usize, FRAMES);
    let status = test.client.robot("ros-kinect").await.unwrap();
    assert_eq!(status.frames.dropped, 0);
    assert_eq!(status.frames.lost, 0);
    assert_eq!(status.tracking.unwrap().frames_tracked, FRAMES as u64);
    let live = test.client.trajectory("ros-kinect").await.unwrap();
    assert_eq!(live.len(), FRAMES);
    // The same poses, up to the rounding of their way through the API (as `live_tracking`).
    let mut worst: f64 = 0.0;
    for (l, o) in live.iter().zip(&offline) {
        assert_eq!(l.timestamp_ns, BASE_NS + o.timestamp_ns);
        let (a, b) = (&l.world_from_camera, &o.world_from_camera);
        let translation = a.translation_m.iter().zip(&b.translation_m);
        let rotation = a.rotation_xyzw.iter().zip(&b.rotation_xyzw);
        worst = translation
            .chain(rotation)
            .map(|(x, y)| (x - y).abs())
            .fold(worst, f64::max);
    }
    eprintln!("{FRAMES} frames from ROS topics and from the folder: largest difference {worst:e}");
    assert!(worst < 1e-9, "the trajectories differ by {worst}");
    assert_metrics_agree(&test, "ros-kinect").await;

    if let Some(token) = token {
        token.undeclare().await.unwrap();
        wait_for("the robot offline", Duration::from_secs(20), || async {
            let status = test.client.robot("ros-kinect").await.ok()?;
            (status.presence == Presence::Offline).then_some(())
        })
        .await;
    }
    session.close().await.unwrap();
    test.server.stop().await.unwrap();
}
