//! ORB features as ORB-SLAM extracts them: spread over the image more evenly than OpenCV's ORB,
//! on real and simulated frames, and matching across frames where the true motion says.

use nalgebra::Vector3;
use opencv::core::{KeyPoint, Mat, Vector};
use opencv::features2d::{ORB_ScoreType, ORB};
use opencv::prelude::*;
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_tests::*;
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::orb::{OrbExtractor, OrbParams};

/// Fraction of the 10 × 8 grid cells of a 640×480 image holding at least one point.
fn coverage(points: impl Iterator<Item = (f32, f32)>) -> f64 {
    let mut cells = [[false; 10]; 8];
    for (x, y) in points {
        let (c, r) = ((x / 64.0) as usize, (y / 60.0) as usize);
        if c < 10 && r < 8 {
            cells[r][c] = true;
        }
    }
    cells.iter().flatten().filter(|&&c| c).count() as f64 / 80.0
}

/// 7-Scenes colour frame `i` of the shared data, as grey.
fn seven_scenes_grey(data: &std::path::Path, i: usize) -> Mat {
    let path = data.join(format!("7scenes-a/frame-{i:06}.color.jpg"));
    let image =
        opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_GRAYSCALE)
            .unwrap();
    assert!(!image.empty(), "{}", path.display());
    image
}

fn grey_mat(grey: &[u8]) -> Mat {
    Mat::new_rows_cols_with_data(480, 640, grey)
        .unwrap()
        .try_clone()
        .unwrap()
}

/// Coverage of ours and of OpenCV's ORB (same budget and pyramid) on one image.
fn both_coverages(image: &Mat) -> (f64, f64, usize) {
    let mut ours = OrbExtractor::new(OrbParams::default()).unwrap();
    let extraction = ours.extract(image, None).unwrap();
    let mut opencv =
        ORB::create(1000, 1.2, 8, 19, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
    let mut keypoints = Vector::<KeyPoint>::new();
    opencv
        .detect(image, &mut keypoints, &opencv::core::no_array())
        .unwrap();
    (
        coverage(extraction.features.iter().map(|f| (f.x, f.y))),
        coverage(keypoints.iter().map(|k| (k.pt().x, k.pt().y))),
        extraction.features.len(),
    )
}

#[test]
fn features_cover_the_image_better_than_opencv_orb() {
    let mut images = Vec::new();
    if let Some(data) = data_dir("features_cover_the_image_better_than_opencv_orb") {
        for i in [0, 100, 200, 300] {
            images.push((format!("7scenes frame {i}"), seven_scenes_grey(&data, i)));
        }
    }
    let scenario = Scenario::builtin("seq03").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let walk = scenario.walks().unwrap().remove(0);
    for i in [0, 900, 1800, 2700] {
        let frame = renderer.render(i as u64, walk.times[i], &[walk.world_from_camera[i]]);
        images.push((format!("seq03 frame {i}"), grey_mat(&frame.grey())));
    }
    let (mut sum_ours, mut sum_theirs) = (0.0, 0.0);
    for (name, image) in &images {
        let (ours, theirs, count) = both_coverages(image);
        eprintln!("{name}: {count} features, grid coverage ours {ours:.2}, OpenCV ORB {theirs:.2}");
        assert!(count >= 900, "{name}: {count} features");
        assert!(
            ours >= theirs,
            "{name}: ours {ours:.2} < OpenCV {theirs:.2}"
        );
        sum_ours += ours;
        sum_theirs += theirs;
    }
    assert!(sum_ours > sum_theirs, "on average ours spreads wider");
}

fn hamming(a: &[u8], b: &[u8]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

#[test]
fn features_match_where_the_true_motion_puts_them() {
    let scenario = Scenario::builtin("seq06").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let walk = scenario.walks().unwrap().remove(0);
    let camera = &scenario.render.camera;
    let focal_baseline = camera.fx * scenario.render.depth.baseline;
    let mut extractor = OrbExtractor::new(OrbParams::default()).unwrap();
    let (mut all_matches, mut all_inliers) = (0, 0);
    for (a, b) in [(300, 303), (1200, 1206), (2000, 2003)] {
        let extract = |i: usize, extractor: &mut OrbExtractor| {
            let frame = renderer.render(i as u64, walk.times[i], &[walk.world_from_camera[i]]);
            let depth = DepthImage {
                width: 640,
                height: 480,
                data: frame.depth_units(1000.0),
                depth_scale: 1000.0,
            };
            extractor
                .extract(&grey_mat(&frame.grey()), Some((&depth, focal_baseline)))
                .unwrap()
        };
        let (first, second) = (extract(a, &mut extractor), extract(b, &mut extractor));
        let with_depth = first.features.iter().filter(|f| f.depth.is_some()).count();
        assert!(
            with_depth * 10 >= first.features.len() * 8,
            "{with_depth} of {} with depth",
            first.features.len()
        );
        for f in first.features.iter().filter(|f| f.depth.is_some()) {
            let expected = f.x - (focal_baseline / f64::from(f.depth.unwrap())) as f32;
            assert!((f.right_x.unwrap() - expected).abs() < 1e-3);
        }
        // Brute-force Hamming matching, ratio test and mutual check (as without a motion prior),
        // then the true motion as the judge.
        let b_from_a = walk.world_from_camera[b].inverse() * walk.world_from_camera[a];
        let (mut matches, mut inliers) = (0, 0);
        for (i, f) in first.features.iter().enumerate() {
            let Some(z) = f.depth else { continue };
            let d = first.descriptors[i];
            let mut best = (u32::MAX, u32::MAX, 0);
            for j in 0..second.features.len() {
                let distance = hamming(&d, &second.descriptors[j]);
                if distance < best.0 {
                    best = (distance, best.0, j);
                } else if distance < best.1 {
                    best.1 = distance;
                }
            }
            if best.0 > 50 || best.0 as f64 > 0.8 * best.1 as f64 {
                continue;
            }
            // Mutual: the match's best partner in the first frame is this feature.
            let back = second.descriptors[best.2];
            let mutual = (0..first.features.len())
                .min_by_key(|&k| hamming(&back, &first.descriptors[k]))
                == Some(i);
            if !mutual {
                continue;
            }
            matches += 1;
            let ray = Vector3::new(
                (f64::from(f.x) - camera.cx) / camera.fx,
                (f64::from(f.y) - camera.cy) / camera.fy,
                1.0,
            );
            let p = b_from_a * nalgebra::Point3::from(ray * f64::from(z));
            let (u, v) = (
                camera.fx * p.x / p.z + camera.cx,
                camera.fy * p.y / p.z + camera.cy,
            );
            let g = &second.features[best.2];
            let error = ((u - f64::from(g.x)).powi(2) + (v - f64::from(g.y)).powi(2)).sqrt();
            inliers += usize::from(error < 3.0);
        }
        eprintln!("frames {a}→{b}: {} and {} features, {matches} matches, {inliers} where the motion puts them", first.features.len(), second.features.len());
        assert!(matches >= 150, "frames {a}→{b}: {matches} matches");
        // Without a motion prior, repeated patterns (stripes, tiles) give some wrong matches;
        // a feature placed at the wrong level or position would give mostly wrong ones.
        assert!(
            inliers * 100 >= matches * 70,
            "frames {a}→{b}: {inliers} of {matches}"
        );
        all_matches += matches;
        all_inliers += inliers;
    }
    assert!(
        all_inliers * 100 >= all_matches * 85,
        "{all_inliers} of {all_matches}"
    );
}

/// Our rotated BRIEF, on our own pyramid, gives OpenCV's `ORB::compute` bits for the same
/// keypoints at every level: the descriptors the tracker matches are ORB's.
#[test]
fn descriptors_are_opencvs_at_every_level() {
    let scenario = Scenario::builtin("seq03").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let walk = scenario.walks().unwrap().remove(0);
    let mut images = vec![grey_mat(
        &renderer
            .render(900, walk.times[900], &[walk.world_from_camera[900]])
            .grey(),
    )];
    if let Some(data) = data_dir("descriptors_are_opencvs_at_every_level") {
        images.push(seven_scenes_grey(&data, 100));
    }
    let mut ours = OrbExtractor::new(OrbParams::default()).unwrap();
    let mut opencv =
        ORB::create(1000, 1.2, 8, 16, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
    for image in &images {
        let extraction = ours.extract(image, None).unwrap();
        let mut keypoints = Vector::<KeyPoint>::new();
        let (width, height) = (f64::from(image.cols()), f64::from(image.rows()));
        for f in &extraction.features {
            let nominal = 1.2f64.powi(f.octave);
            // OpenCV finds a keypoint's level pixel as its coordinates over the nominal scale;
            // ours map level pixels back with the level's true (rounded-size) scale. Hand
            // OpenCV the same level pixel in its convention.
            let to_opencv = |x: f32, extent: f64| {
                let level_extent = (extent / nominal).round();
                let level_pixel = ((f64::from(x) + 0.5) * level_extent / extent - 0.5).round();
                (level_pixel * nominal) as f32
            };
            let size = 31.0 * 1.2f32.powi(f.octave);
            keypoints.push(
                KeyPoint::new_coords(
                    to_opencv(f.x, width),
                    to_opencv(f.y, height),
                    size,
                    f.angle,
                    f.response,
                    f.octave,
                    -1,
                )
                .unwrap(),
            );
        }
        let mut theirs = Mat::default();
        opencv.compute(image, &mut keypoints, &mut theirs).unwrap();
        assert_eq!(keypoints.len(), extraction.features.len());
        let mut per_level = [0usize; 8];
        for (i, (f, d)) in extraction
            .features
            .iter()
            .zip(&extraction.descriptors)
            .enumerate()
        {
            let row = theirs.at_row::<u8>(i as i32).unwrap();
            assert_eq!(&d[..], row, "feature {i} at level {}", f.octave);
            per_level[f.octave as usize] += 1;
        }
        eprintln!("descriptors equal to OpenCV's, per level: {per_level:?}");
        assert!(per_level.iter().all(|&n| n > 0), "every level has features");
    }
}
