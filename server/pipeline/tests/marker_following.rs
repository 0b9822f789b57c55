//! A robot's markers followed between whole-image searches (`[markers] full_search_every`),
//! through the frame pipeline: the frames between search only around the markers seen, a new
//! session or frames skipped bring the next whole search.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use vsgraphs_pipeline::config::{MarkerConfig, TrackingConfig, DEFAULT_MAX_FRAME_BYTES};
use vsgraphs_pipeline::validate::FrameHeader;
use vsgraphs_pipeline::{FrameProcessor, MapService};
use vsgraphs_proto::{encode, DepthEncoding, Message, PixelFormat, RgbdFrame};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::{render, PlacedMarker};

const ROBOT: &str = "follower";

/// A frame showing one marker, at the image's left (x < 0) or right.
fn frame_with(id: i32, x: f64) -> RgbdFrame {
    let camera = PinholeCamera::new(640, 480, [500.0, 500.0, 320.0, 240.0], vec![]).unwrap();
    let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
    let marker = PlacedMarker {
        id,
        side_m: 0.08,
        camera_from_marker: Isometry3::from_parts(
            Translation3::new(x, 0.0, 0.8),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        ),
    };
    let rendered = render(&camera, &dictionary, &[marker], 2.0).unwrap();
    RgbdFrame {
        robot_id: ROBOT.into(),
        session_id: String::new(),
        sequence: 0,
        timestamp_ns: 0,
        camera: Some(camera.to_wire()),
        depth_scale: 1000.0,
        colour: Some(
            encode::colour_jpeg(rendered.grey_bytes(), 640, 480, PixelFormat::Mono8, 95).unwrap(),
        ),
        depth: Some(encode::depth(&rendered.depth_mm, 640, 480, DepthEncoding::Rvl).unwrap()),
        odometry: None,
        imu: vec![],
    }
}

#[test]
fn markers_are_followed_within_a_session_and_searched_whole_after_a_new_one_or_a_gap() {
    let markers = MarkerConfig {
        full_search_every: 3,
        beside_features: false,
        ..MarkerConfig::default()
    };
    let tracking = TrackingConfig {
        enabled: false,
        ..TrackingConfig::default()
    };
    let mut processor = FrameProcessor::new(
        &markers,
        &tracking,
        DEFAULT_MAX_FRAME_BYTES,
        MapService::new(),
    )
    .unwrap();
    let (left, right) = (frame_with(7, -0.25), frame_with(9, 0.25));
    let mut previous: Option<FrameHeader> = None;
    let mut found = |image: &RgbdFrame, session: &str, sequence: u64| -> Vec<i32> {
        let mut frame = image.clone();
        frame.session_id = session.into();
        frame.sequence = sequence;
        frame.timestamp_ns = 1 + sequence * 33_000_000;
        let processed = processor
            .process(ROBOT, &frame.encode_to_vec(), previous.as_ref())
            .unwrap();
        previous = Some(FrameHeader {
            session_id: processed.session_id.clone(),
            sequence,
            timestamp_ns: processed.timestamp_ns,
            accepted: None,
        });
        processed.markers.iter().map(|m| m.id).collect()
    };
    // The first frame is searched whole; the next only around marker 7, so marker 9 waits.
    assert_eq!(found(&left, "a", 0), [7]);
    assert_eq!(found(&right, "a", 1), Vec::<i32>::new());
    // A new session: searched whole.
    assert_eq!(found(&right, "b", 2), [9]);
    assert_eq!(found(&left, "b", 3), Vec::<i32>::new());
    // Two frames skipped: three frames since the whole search, so this one is whole again.
    assert_eq!(found(&left, "b", 5), [7]);
}
