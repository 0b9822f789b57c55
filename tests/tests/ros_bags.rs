//! A ROS 2 bag (MCAP or SQLite, written by `rosbags` from the 7-Scenes frames as a RealSense
//! driver's topics: `ros/make_bag.py`) plays like the folder it was made from: the same frames,
//! camera and depth registration, and through the pipeline the same trajectory. A message that
//! is not CDR is skipped and counted.

use std::path::Path;
use std::process::Command;
use vsgraphs_datasets::{dataset, load_frame, BagTopics};
use vsgraphs_proto::{png16, DepthEncoding, DepthRegistration};
use vsgraphs_server::config::Config;
use vsgraphs_tests::*;

/// Enough frames for keyframes and a local bundle adjustment.
const FRAMES: usize = 60;
/// The bag's stamps start here (see `make_bag.py`); the folder's at 0.
const BASE_NS: u64 = 1_700_000_000_000_000_000;

#[test]
fn an_mcap_bag_with_a_broken_message_plays_as_the_folder() {
    bag_plays_as_the_folder(
        "an_mcap_bag_with_a_broken_message_plays_as_the_folder",
        "mcap",
        true,
    );
}

#[test]
fn a_sqlite_bag_plays_as_the_folder() {
    bag_plays_as_the_folder("a_sqlite_bag_plays_as_the_folder", "db3", false);
}

#[test]
fn a_ros1_bag_with_a_broken_message_plays_as_the_folder() {
    bag_plays_as_the_folder(
        "a_ros1_bag_with_a_broken_message_plays_as_the_folder",
        "bag",
        true,
    );
}

fn bag_plays_as_the_folder(test: &str, extension: &str, corrupt: bool) {
    let (Some(data), Some(python)) = (data_dir(test), python_with_rosbags(test)) else {
        return;
    };
    let folder = dataset::open(&data.join("7scenes-a")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    // A rosbag2 folder, or a ROS 1 bag file.
    let bag_dir = match extension {
        "bag" => dir.path().join("kinect_bag.bag"),
        _ => dir.path().join("kinect_bag"),
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("ros/make_bag.py");
    let mut command = Command::new(&python);
    command
        .arg(&script)
        .arg(data.join("7scenes-a"))
        .arg(&bag_dir)
        .arg(FRAMES.to_string());
    match extension {
        "db3" => drop(command.args(["--storage", "sqlite3"])),
        "bag" => drop(command.args(["--storage", "ros1"])),
        _ => {}
    }
    if corrupt {
        command.arg("--corrupt");
    }
    assert!(
        command.status().unwrap().success(),
        "{} failed",
        script.display()
    );
    let bag_file = match extension {
        "bag" => bag_dir.clone(),
        _ => bag_dir.join(format!("kinect_bag.{extension}")),
    };
    assert!(bag_file.is_file(), "{}", bag_file.display());

    // The bag opens as a dataset, its frames extracted once, counted as they are.
    let mut counted = Vec::new();
    let bag =
        dataset::open_bag_with_progress(&bag_file, &BagTopics::default(), &mut |n| counted.push(n))
            .unwrap();
    assert_eq!(counted, (1..=FRAMES).collect::<Vec<_>>());
    assert!(
        bag.warnings.iter().any(|w| w.contains("extracted")),
        "{:?}",
        bag.warnings
    );
    let skipped = bag.warnings.iter().find(|w| w.contains("skipped"));
    if corrupt {
        let note = skipped.expect("the broken message is skipped and counted");
        assert!(
            note.starts_with("1 unreadable messages skipped")
                && note.contains("/camera/camera/color/image_raw/compressed"),
            "{note}"
        );
    } else {
        assert_eq!(skipped, None);
    }
    assert!(
        dataset::open(&bag_dir).unwrap().warnings.is_empty(),
        "extracted again"
    );
    assert_eq!(bag.frames.len(), FRAMES);
    assert_eq!(
        bag.camera, folder.camera,
        "CameraInfo's camera is the folder's"
    );
    assert_eq!(bag.depth_scale, folder.depth_scale);
    assert_eq!(bag.depth_registration, DepthRegistration::Unregistered);
    for (b, f) in bag.frames.iter().zip(&folder.frames) {
        assert_eq!(
            b.timestamp_ns,
            BASE_NS + f.timestamp_ns,
            "the header's stamp"
        );
        let (bag_colour, bag_depth, _) =
            load_frame(b, DepthEncoding::Png16, bag.depth_registration).unwrap();
        let (colour, depth, _) =
            load_frame(f, DepthEncoding::Png16, folder.depth_registration).unwrap();
        assert_eq!(bag_colour, colour, "the JPEG bytes as recorded");
        assert_eq!(bag_depth.registration, depth.registration);
        assert_eq!(
            png16::decode(&bag_depth.data).unwrap(),
            png16::decode(&depth.data).unwrap(),
            "the depth values as recorded"
        );
    }

    // Through the pipeline: the same poses, stamped with the bag's times.
    let run = |dataset| {
        vsgraphs_pipeline::offline::run(&Config::default().pipeline(), dataset, None, |_, _| {})
            .unwrap()
            .1
            .refined
    };
    let mut folder_head = folder.clone();
    folder_head.frames.truncate(FRAMES);
    let (from_bag, from_folder) = (run(&bag), run(&folder_head));
    assert_eq!(from_bag.len(), FRAMES, "every frame tracked");
    assert_eq!(from_bag.len(), from_folder.len());
    for (b, f) in from_bag.iter().zip(&from_folder) {
        assert_eq!(b.timestamp_ns, BASE_NS + f.timestamp_ns);
        assert_eq!(
            b.world_from_camera, f.world_from_camera,
            "at {}",
            f.timestamp_ns
        );
    }

    // Topics that are not in the bag are named with the bag's topics.
    let topics = BagTopics {
        colour: Some("/camera/color/image_raw".into()),
        ..BagTopics::default()
    };
    let error = dataset::open_bag(&bag_file, &topics)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("/camera/color/image_raw is not in the bag")
            && error.contains("/camera/camera/color/image_raw/compressed"),
        "{error}"
    );
    // The extracted frames live in the temporary folder; this test's bag is gone after it.
    let frames = vsgraphs_datasets::rosbag::frames_dir(&bag_file, &BagTopics::default()).unwrap();
    std::fs::remove_dir_all(frames).unwrap();
}
