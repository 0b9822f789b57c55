//! One frame's way through the pipeline, from the bytes a robot sends to marker detections:
//! protobuf decode, validation, JPEG and RVL decode, detection, poses, tracking.
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use vsgraphs_pipeline::config::{MarkerConfig, TrackingConfig, DEFAULT_MAX_FRAME_BYTES};
use vsgraphs_pipeline::{FrameProcessor, MapService};
use vsgraphs_proto::encode;
use vsgraphs_proto::{DepthEncoding, Message, PixelFormat, RgbdFrame};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::{render, PlacedMarker};

fn ingest(c: &mut Criterion) {
    let camera = PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![]).unwrap();
    let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
    let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
    let markers: Vec<PlacedMarker> = (0..3)
        .map(|i| PlacedMarker {
            id: i * 5,
            side_m: 0.08,
            camera_from_marker: Isometry3::from_parts(
                Translation3::new(f64::from(i) * 0.15 - 0.15, 0.0, 1.0),
                facing,
            ),
        })
        .collect();
    let frame = render(&camera, &dictionary, &markers, 2.0).unwrap();
    let colour = encode::colour_jpeg(frame.grey_bytes(), 640, 480, PixelFormat::Mono8, 90).unwrap();
    let depth = encode::depth(&frame.depth_mm, 640, 480, DepthEncoding::Rvl).unwrap();
    let bytes = RgbdFrame {
        robot_id: "bench".into(),
        session_id: "s".into(),
        sequence: 1,
        timestamp_ns: 1,
        camera: Some(camera.to_wire()),
        depth_scale: 1000.0,
        colour: Some(colour),
        depth: Some(depth),
        odometry: None,
        imu: vec![],
    }
    .encode_to_vec();
    let mut processor = FrameProcessor::new(
        &MarkerConfig::default(),
        &TrackingConfig::default(),
        DEFAULT_MAX_FRAME_BYTES,
        MapService::new(),
    )
    .unwrap();
    assert_eq!(
        processor
            .process("bench", &bytes, None)
            .unwrap()
            .markers
            .len(),
        3
    );
    eprintln!("frame on the wire: {} bytes", bytes.len());
    c.bench_function("ingest_frame_bytes_to_detections_640x480", |b| {
        b.iter(|| processor.process("bench", &bytes, None).unwrap())
    });
}

criterion_group!(benches, ingest);
criterion_main!(benches);
