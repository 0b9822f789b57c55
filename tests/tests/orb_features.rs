//! ORB features as ORB-SLAM extracts them: spread over the image more evenly than OpenCV's ORB,
//! on real and simulated frames, and matching across frames where the true motion says.

use nalgebra::{Isometry3, Vector3};
use opencv::boxed_ref::BoxedRef;
use opencv::core::{KeyPoint, Mat, Vector};
use opencv::features2d::{ORB_ScoreType, ORB};
use opencv::prelude::*;
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::walk::Walk;
use vsgraphs_sim::{Building, Camera, Renderer};
use vsgraphs_tests::*;
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::orb::{Extraction, OrbExtractor, OrbParams};
use vsgraphs_vision::GreyImage;

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
fn seven_scenes_grey(data: &std::path::Path, i: usize) -> GreyImage {
    GreyImage::read(&data.join(format!("7scenes-a/frame-{i:06}.color.jpg"))).unwrap()
}

fn grey_image(grey: &[u8]) -> GreyImage {
    GreyImage::from_pixels(640, 480, grey).unwrap()
}

/// The same pixels as OpenCV's matrix, for OpenCV's own ORB.
fn opencv_view(image: &GreyImage) -> BoxedRef<'_, Mat> {
    Mat::new_rows_cols_with_data(image.height() as i32, image.width() as i32, image.pixels())
        .unwrap()
}

/// Coverage of ours and of OpenCV's ORB (same budget and pyramid) on one image.
fn both_coverages(image: &GreyImage) -> (f64, f64, usize) {
    let mut ours = OrbExtractor::new(OrbParams::default()).unwrap();
    let extraction = ours.extract(image, None).unwrap();
    let mut opencv =
        ORB::create(1000, 1.2, 8, 19, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20).unwrap();
    let mut keypoints = Vector::<KeyPoint>::new();
    opencv
        .detect(
            &opencv_view(image),
            &mut keypoints,
            &opencv::core::no_array(),
        )
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
        images.push((format!("seq03 frame {i}"), grey_image(&frame.grey())));
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

/// seq06's first walk, rendered as its robot sees it.
struct Seq06 {
    renderer: Renderer,
    walk: Walk,
    camera: Camera,
    focal_baseline: f64,
}

impl Seq06 {
    fn new() -> Self {
        let scenario = Scenario::builtin("seq06").unwrap();
        let building = Building::from_plan(&scenario.plan).unwrap();
        let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
        let walk = scenario.walks().unwrap().remove(0);
        let camera = scenario.render.camera.clone();
        let focal_baseline = camera.fx * scenario.render.depth.baseline;
        Self {
            renderer,
            walk,
            camera,
            focal_baseline,
        }
    }

    /// Frame `i`: grey, and depth in millimetres.
    fn frame(&self, i: usize) -> (GreyImage, DepthImage) {
        let pose = self.walk.world_from_camera[i];
        let frame = self.renderer.render(i as u64, self.walk.times[i], &[pose]);
        let depth = DepthImage {
            width: 640,
            height: 480,
            data: frame.depth_units(1000.0),
            depth_scale: 1000.0,
            registered: true,
        };
        (grey_image(&frame.grey()), depth)
    }

    fn extract(
        &self,
        extractor: &mut OrbExtractor,
        (grey, depth): &(GreyImage, DepthImage),
    ) -> Extraction {
        extractor
            .extract(grey, Some((depth, self.focal_baseline)))
            .unwrap()
    }

    /// Camera `b` from camera `a`, the true motion between two frames.
    fn b_from_a(&self, a: usize, b: usize) -> Isometry3<f64> {
        self.walk.world_from_camera[b].inverse() * self.walk.world_from_camera[a]
    }
}

/// Brute-force Hamming matches of `first`'s features with depth in `second` (ratio test and
/// mutual check, as without a motion prior), each with `second`'s pyramid level and its
/// distance in pixels from where the true motion `b_from_a` puts the first feature.
fn errors_against_the_true_motion(
    first: &Extraction,
    second: &Extraction,
    b_from_a: &Isometry3<f64>,
    camera: &Camera,
) -> Vec<(i32, f64)> {
    let mut errors = Vec::new();
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
        errors.push((g.octave, error));
    }
    errors
}

#[test]
fn features_match_where_the_true_motion_puts_them() {
    let seq06 = Seq06::new();
    let focal_baseline = seq06.focal_baseline;
    let mut extractor = OrbExtractor::new(OrbParams::default()).unwrap();
    let (mut all_matches, mut all_inliers) = (0, 0);
    for (a, b) in [(300, 303), (1200, 1206), (2000, 2003)] {
        let [first, second] = [a, b].map(|i| seq06.extract(&mut extractor, &seq06.frame(i)));
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
        let errors =
            errors_against_the_true_motion(&first, &second, &seq06.b_from_a(a, b), &seq06.camera);
        let matches = errors.len();
        let inliers = errors.iter().filter(|&&(_, e)| e < 3.0).count();
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

/// The coarse levels are shrunk from a smoothed image (`coarse_smoothing_sigma`): without it
/// they alias, and their corners match less often and further from where the scene moved.
#[test]
fn smoothed_coarse_levels_follow_the_scene_more_closely() {
    let seq06 = Seq06::new();
    let plain = OrbParams {
        coarse_smoothing_sigma: 0.0,
        ..OrbParams::default()
    };
    assert!(OrbParams::default().coarse_smoothing_sigma > 0.0);
    // Coarse-level matches within 8 px of the truth, and their squared errors, per setting.
    let mut found = [(0usize, 0.0f64); 2];
    for (a, b) in [(300, 303), (700, 702), (1200, 1206), (2000, 2003)] {
        let frames = [a, b].map(|i| seq06.frame(i));
        let b_from_a = seq06.b_from_a(a, b);
        for (params, found) in [plain.clone(), OrbParams::default()]
            .into_iter()
            .zip(&mut found)
        {
            let mut extractor = OrbExtractor::new(params).unwrap();
            let [first, second] =
                [&frames[0], &frames[1]].map(|f| seq06.extract(&mut extractor, f));
            for (level, error) in
                errors_against_the_true_motion(&first, &second, &b_from_a, &seq06.camera)
            {
                if level >= 4 && error < 8.0 {
                    found.0 += 1;
                    found.1 += error * error;
                }
            }
        }
    }
    let rms = |(n, sum): (usize, f64)| (sum / n as f64).sqrt();
    eprintln!(
        "coarse levels: plain {} matches, {:.2} px RMS; smoothed {} matches, {:.2} px RMS",
        found[0].0,
        rms(found[0]),
        found[1].0,
        rms(found[1])
    );
    // Smoothing should give clearly more matches (a tenth), closer to the true motion; the
    // measured figures are in BENCHMARKS.md ("Vision").
    assert!(found[1].0 > found[0].0 * 11 / 10, "{found:?}");
    assert!(rms(found[1]) < rms(found[0]), "{found:?}");
}

/// Our rotated BRIEF, on our own pyramid, gives OpenCV's `ORB::compute` bits for the same
/// keypoints at every level: the descriptors the tracker matches are ORB's.
#[test]
fn descriptors_are_opencvs_at_every_level() {
    let scenario = Scenario::builtin("seq03").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let walk = scenario.walks().unwrap().remove(0);
    let mut images = vec![grey_image(
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
        let (width, height) = (f64::from(image.width()), f64::from(image.height()));
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
        opencv
            .compute(&opencv_view(image), &mut keypoints, &mut theirs)
            .unwrap();
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
