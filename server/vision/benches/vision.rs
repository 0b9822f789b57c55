//! Per-frame vision costs on 640×480: JPEG decode, 16-bit PNG depth decode (OpenCV), ArUco
//! detection with our sub-pixel refinement, and marker pose with the depth check.
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use opencv::core::{no_array, KeyPoint, Mat, Vector};
use opencv::features2d::{ORB_ScoreType, ORB};
use opencv::prelude::*;
use std::path::PathBuf;
use vsgraphs_proto::{ColourEncoding, ColourImage, DepthEncoding, PixelFormat};
use vsgraphs_vision::aruco::{CornerRefinement, MarkerDetector};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::decode;
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::orb::{OrbExtractor, OrbParams};
use vsgraphs_vision::pose::PoseEstimator;
use vsgraphs_vision::synth::{render, PlacedMarker};

fn data() -> PathBuf {
    std::env::var_os("VSGRAPHS_TEST_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"))
}

fn vision(c: &mut Criterion) {
    let dir = data().join("7scenes-a");
    if let (Ok(jpeg), Ok(png)) = (
        std::fs::read(dir.join("frame-000000.color.jpg")),
        std::fs::read(dir.join("frame-000000.depth.png")),
    ) {
        let colour = ColourImage {
            encoding: ColourEncoding::Jpeg as i32,
            pixel_format: PixelFormat::Rgb8 as i32,
            data: jpeg,
        };
        c.bench_function("jpeg_decode_to_grey_640x480", |b| {
            b.iter(|| decode::colour_to_grey(&colour, 640, 480).unwrap())
        });
        c.bench_function("png16_decode_opencv_640x480", |b| {
            b.iter(|| decode::depth(DepthEncoding::Png16 as i32, &png, 640, 480, 1000.0).unwrap())
        });
        // ORB features of a real frame: ours (cells + quadtree, as ORB-SLAM) against OpenCV's
        // ORB with the same budget and pyramid.
        let grey = decode::colour_to_grey(&colour, 640, 480).unwrap();
        let depth = decode::depth(DepthEncoding::Png16 as i32, &png, 640, 480, 1000.0).unwrap();
        let mut extractor = OrbExtractor::new(OrbParams::default()).unwrap();
        c.bench_function("orb_slam_extract_1000_640x480", |b| {
            b.iter(|| extractor.extract(&grey, Some((&depth, 30.0))).unwrap())
        });
        let grey_mat = Mat::new_rows_cols_with_data(480, 640, grey.pixels()).unwrap();
        let mut orb =
            ORB::create(1000, 1.2, 8, 19, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
        c.bench_function("opencv_orb_detect_and_compute_1000_640x480", |b| {
            b.iter(|| {
                let mut keypoints = Vector::<KeyPoint>::new();
                let mut descriptors = Mat::default();
                orb.detect_and_compute(
                    &grey_mat,
                    &no_array(),
                    &mut keypoints,
                    &mut descriptors,
                    false,
                )
                .unwrap();
                descriptors
            })
        });
    } else {
        eprintln!(
            "{} missing: JPEG and PNG decode benchmarks skipped",
            dir.display()
        );
    }

    let camera = PinholeCamera::new(640, 480, [605.86, 606.27, 325.02, 244.76], vec![]).unwrap();
    let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
    let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
    let markers: Vec<PlacedMarker> = (0..4)
        .map(|i| PlacedMarker {
            id: i * 9,
            side_m: 0.08,
            camera_from_marker: Isometry3::from_parts(
                Translation3::new(
                    f64::from(i % 2) * 0.3 - 0.15,
                    f64::from(i / 2) * 0.2 - 0.1,
                    1.0 + 0.1 * f64::from(i),
                ),
                UnitQuaternion::from_euler_angles(0.2, -0.2 * f64::from(i), 0.1) * facing,
            ),
        })
        .collect();
    let frame = render(&camera, &dictionary, &markers, 2.0).unwrap();
    for refinement in [CornerRefinement::None, CornerRefinement::Subpixel] {
        let mut detector = MarkerDetector::new(dictionary.clone(), refinement).unwrap();
        assert_eq!(detector.detect(&frame.grey).unwrap().len(), 4);
        c.bench_function(
            &format!("aruco_detect_4_markers_640x480_{refinement:?}"),
            |b| b.iter(|| detector.detect(&frame.grey).unwrap()),
        );
    }
    let mut detector = MarkerDetector::new(dictionary, CornerRefinement::Subpixel).unwrap();
    let detections = detector.detect(&frame.grey).unwrap();
    let depth = DepthImage {
        width: 640,
        height: 480,
        data: frame.depth_mm.clone(),
        depth_scale: 1000.0,
        registered: true,
    };
    let estimator = PoseEstimator::new(camera, 0.08).unwrap();
    c.bench_function("marker_pose_with_depth_check", |b| {
        b.iter(|| {
            estimator
                .estimate(&detections[0], Some((&depth, 0.15)))
                .unwrap()
        })
    });
}

criterion_group!(benches, vision);
criterion_main!(benches);
