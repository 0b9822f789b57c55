//! The renderer checked against geometry: markers are found where they hang, depth is the
//! ray–plane distance within the sensor model, and the bits are OpenCV's.

use nalgebra::{Point3, Vector3};
use vsgraphs_sim::aruco::Dictionary;
use vsgraphs_sim::scenarios::scenario;
use vsgraphs_sim::walk::looking_at;
use vsgraphs_sim::{Building, RenderOptions, Renderer};
use vsgraphs_vision::aruco::{CornerRefinement, MarkerDetector};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::pose::PoseEstimator;
use vsgraphs_vision::GreyImage;

#[test]
fn marker_bits_are_opencvs() {
    for size in [4, 5, 6] {
        for count in [50, 100, 250, 1000] {
            let name = format!("DICT_{size}X{size}_{count}");
            let ours = Dictionary::by_name(&name).unwrap();
            let theirs = MarkerDictionary::predefined(&name).unwrap();
            assert_eq!(ours.markers, theirs.markers as usize, "{name}");
            for id in 0..theirs.markers {
                let image = theirs.draw(id, size + 2).unwrap();
                let bits = ours.marker(id as u32).unwrap();
                for row in 0..size + 2 {
                    for col in 0..size + 2 {
                        let white = image.get(col as u32, row as u32).unwrap() > 127;
                        assert_eq!(
                            bits.white(row as usize, col as usize),
                            white,
                            "{name} id {id} cell ({row}, {col})"
                        );
                    }
                }
            }
        }
    }
}

fn vision_camera(options: &RenderOptions) -> PinholeCamera {
    let c = &options.camera;
    PinholeCamera::new(c.width, c.height, [c.fx, c.fy, c.cx, c.cy], vec![]).unwrap()
}

#[test]
fn a_marker_rendered_at_one_metre_is_found_within_1cm_and_1deg() {
    let plan = scenario("seq06").unwrap();
    let building = Building::from_plan(&plan).unwrap();
    let options = RenderOptions::default();
    let renderer = Renderer::new(&plan, &building, options.clone(), 3);
    let camera = vision_camera(&options);
    let dictionary = MarkerDictionary::predefined(&plan.markers.dictionary).unwrap();
    let mut detector = MarkerDetector::new(dictionary, CornerRefinement::Subpixel).unwrap();
    let estimator = PoseEstimator::new(camera, plan.markers.side).unwrap();
    let mut checked = 0;
    let mut worst = (0.0f64, 0.0f64);
    let mut worst_corner = 0.0f64;
    for marker in building.markers.iter().filter(|m| m.doorway.is_none()) {
        let centre = marker.world_from_marker.translation.vector;
        let normal = marker.world_from_marker.rotation * Vector3::z();
        let along = marker.world_from_marker.rotation * Vector3::x();
        // Straight on, and 25° off to either side, all at 1 m; the camera a little lower.
        for (k, angle) in [0.0f64, 25.0, -25.0].into_iter().enumerate() {
            let a = angle.to_radians();
            let eye = centre + (normal * a.cos() + along * a.sin()) - Vector3::z() * 0.1;
            let aim = centre + along * 0.05 * (k as f64 - 1.0);
            let world_from_camera = looking_at(eye, aim);
            let frame = renderer.render(k as u64, 0.0, &[world_from_camera]);
            let grey = frame.grey();
            let image = GreyImage::from_pixels(640, 480, &grey).unwrap();
            let detections = detector.detect(&image).unwrap();
            let found: Vec<_> = detections
                .iter()
                .filter(|d| d.id == marker.id as i32)
                .collect();
            assert_eq!(found.len(), 1, "marker {} at {angle}°", marker.id);
            let depth = DepthImage {
                width: 640,
                height: 480,
                data: frame.depth_units(1000.0),
                depth_scale: 1000.0,
                registered: true,
            };
            let estimate = estimator.estimate(found[0], Some((&depth, 0.15))).unwrap();
            // The detected corners against the true ones (top-left, top-right, bottom-right,
            // bottom-left as printed).
            let h = plan.markers.side / 2.0;
            let camera_from_world = world_from_camera.inverse();
            for (corner, (x, y)) in
                found[0]
                    .corners
                    .iter()
                    .zip([(-h, h), (h, h), (h, -h), (-h, -h)])
            {
                let p = camera_from_world * (marker.world_from_marker * Point3::new(x, y, 0.0));
                let truth = (
                    options.camera.fx * p.x / p.z + options.camera.cx,
                    options.camera.fy * p.y / p.z + options.camera.cy,
                );
                let error = ((f64::from(corner[0]) - truth.0).powi(2)
                    + (f64::from(corner[1]) - truth.1).powi(2))
                .sqrt();
                worst_corner = worst_corner.max(error);
            }
            let truth = world_from_camera.inverse() * marker.world_from_marker;
            let error = truth.inverse() * estimate.camera_from_marker;
            let (metres, degrees) = (
                error.translation.vector.norm(),
                error.rotation.angle().to_degrees(),
            );
            assert!(
                metres < 0.01 && degrees < 1.0,
                "marker {} at {angle}°: {:.1} mm, {degrees:.2}°",
                marker.id,
                metres * 1e3
            );
            worst = (worst.0.max(metres), worst.1.max(degrees));
            checked += 1;
        }
    }
    assert_eq!(checked, 3 * 6);
    // The detector's corner refinement, not the rendering (see the next test), limits this.
    assert!(worst_corner < 0.5, "{worst_corner} px");
    eprintln!(
        "worst marker pose error at 1 m: {:.2} mm, {:.3}°; corner {worst_corner:.3} px",
        worst.0 * 1e3,
        worst.1
    );
}

#[test]
fn marker_edges_are_rendered_where_they_project() {
    let plan = scenario("seq06").unwrap();
    let building = Building::from_plan(&plan).unwrap();
    let options = RenderOptions {
        image_noise: 0.0,
        vignetting: 0.0,
        exposure_variation: 0.0,
        ..RenderOptions::default()
    };
    let renderer = Renderer::new(&plan, &building, options.clone(), 3);
    let c = &options.camera;
    let mut worst = 0.0f64;
    for (k, marker) in building.markers.iter().enumerate() {
        let centre = marker.world_from_marker.translation.vector;
        let normal = marker.world_from_marker.rotation * Vector3::z();
        // Straight on from 0.6–1.1 m, so the outer edges run along pixel rows and columns.
        let eye = centre + normal * (0.6 + 0.1 * k as f64);
        let world_from_camera = looking_at(eye, centre);
        let grey = renderer.render(0, 0.0, &[world_from_camera]).grey();
        let at = |x: i64, y: i64| f64::from(grey[(y * 640 + x) as usize]);
        let camera_from_world = world_from_camera.inverse();
        let h = marker.side / 2.0;
        // Mid-points of the left, right, top and bottom outer edges, and which way is outward.
        for (x, y, out) in [
            (-h, 0.0, (-1, 0)),
            (h, 0.0, (1, 0)),
            (0.0, h, (0, -1)),
            (0.0, -h, (0, 1)),
        ] {
            let p = camera_from_world * (marker.world_from_marker * Point3::new(x, y, 0.0));
            let (u, v) = (c.fx * p.x / p.z + c.cx, c.fy * p.y / p.z + c.cy);
            // Take a row (or column) a few pixels off the mid-point to miss the inner bits, and
            // read the edge from the one pixel it crosses: its grey is the white fraction.
            let (edge, across) = if out.0 != 0 {
                (u, v + 2.0)
            } else {
                (v, u + 2.0)
            };
            let pixel = edge.round() as i64;
            let sample = |d: i64| {
                if out.0 != 0 {
                    at(pixel + d, across.round() as i64)
                } else {
                    at(across.round() as i64, pixel + d)
                }
            };
            let sign: i32 = if out.0 + out.1 > 0 { 1 } else { -1 };
            let (white, black) = (sample(3 * i64::from(sign)), sample(-3 * i64::from(sign)));
            let white_fraction = (sample(0) - black) / (white - black);
            // White lies outward: the edge sits `white_fraction` of a pixel in from the
            // pixel's outer border.
            let measured = pixel as f64 + f64::from(sign) * (0.5 - white_fraction);
            worst = worst.max((measured - edge).abs());
        }
    }
    // Supersampling resolves 1/16 px along the grid (at most 1/32 off), and one grey level of
    // the ~120 between black and white is another 0.01 px.
    assert!(worst < 0.045, "an edge is {worst:.3} px off its projection");
    eprintln!("worst marker edge: {worst:.3} px off its projection");
}

#[test]
fn depth_is_the_ray_plane_distance_within_the_sensor_model() {
    let plan = scenario("seq01").unwrap();
    let building = Building::from_plan(&plan).unwrap();
    let options = RenderOptions::default();
    let renderer = Renderer::new(&plan, &building, options.clone(), 5);
    let sensor = &options.depth;
    let c = &options.camera;
    // In Lab A ([0, 5] × [0, 4]), looking at its west wall x = 0 obliquely from 3 m.
    let world_from_camera = looking_at(Vector3::new(3.0, 1.5, 1.1), Vector3::new(0.0, 2.5, 1.3));
    let frame = renderer.render(0, 0.0, &[world_from_camera]);
    assert_eq!(frame.misses, 0);
    let (mut sum, mut sum_sq, mut count, mut holes) = (0.0, 0.0, 0usize, 0usize);
    for y in (0..c.height).step_by(3) {
        for x in (0..c.width).step_by(3) {
            let ray = Vector3::new(
                (f64::from(x) - c.cx) / c.fx,
                (f64::from(y) - c.cy) / c.fy,
                1.0,
            );
            let world_ray = world_from_camera.rotation * ray;
            let origin = world_from_camera.translation.vector;
            // Where the ray meets the plane x = 0, if that is on the wall and clear of its edges.
            let z = -origin.x / world_ray.x;
            let hit = origin + world_ray * z;
            if !(z > 0.0 && hit.y > 0.1 && hit.y < 3.9 && hit.z > 0.1 && hit.z < 2.5) {
                continue;
            }
            let measured = f64::from(frame.depth[(y * c.width + x) as usize]);
            if measured == 0.0 {
                holes += 1;
                continue;
            }
            // Disparity noise and its quantisation, carried to depth.
            let step = sensor.disparity_step;
            let sigma_disparity = (sensor.disparity_sigma.powi(2) + step * step / 12.0).sqrt();
            let sigma = z * z * sigma_disparity / (c.fx * sensor.baseline);
            let error = measured - z;
            assert!(
                error.abs() < 5.0 * sigma + sensor.quantisation_at(z, c.fx) + 1e-6,
                "pixel ({x}, {y}): depth {measured:.4} m, plane {z:.4} m, σ {sigma:.4} m"
            );
            sum += error / sigma;
            sum_sq += (error / sigma).powi(2);
            count += 1;
        }
    }
    assert!(count > 5000, "{count} wall pixels");
    let mean = sum / count as f64;
    let std = (sum_sq / count as f64 - mean * mean).sqrt();
    // The noise is as large as the model says: not absent, not larger.
    assert!(mean.abs() < 0.1, "mean error {mean:.3} σ");
    assert!((0.85..1.15).contains(&std), "error spread {std:.3} σ");
    assert!(holes < count / 50, "{holes} holes on a plain wall");
    eprintln!("{count} wall pixels: error mean {mean:.3} σ, spread {std:.3} σ, {holes} holes");
}

#[test]
fn depth_has_holes_beyond_range_and_at_grazing_angles() {
    let plan = scenario("seq03").unwrap();
    let building = Building::from_plan(&plan).unwrap();
    let mut options = RenderOptions::default();
    options.depth.max_range = 6.0;
    let renderer = Renderer::new(&plan, &building, options.clone(), 5);
    // Down the 20 m corridor: the far end is out of range, the side walls graze.
    let eye = Vector3::new(0.5, 1.0, 1.2);
    let world_from_camera = looking_at(eye, Vector3::new(20.0, 1.0, 1.2));
    let frame = renderer.render(0, 0.0, &[world_from_camera]);
    let centre = (240 * 640 + 320) as usize;
    assert_eq!(
        frame.depth[centre], 0.0,
        "the corridor's end is 19.5 m away"
    );
    let camera_from_world = world_from_camera.inverse();
    // A pixel on the south wall (y = 0) far down the corridor sees it at a grazing angle.
    let far = camera_from_world * Point3::new(7.0, 0.0, 1.2);
    let (u, v) = (
        options.camera.fx * far.x / far.z + options.camera.cx,
        options.camera.fy * far.y / far.z + options.camera.cy,
    );
    let incidence = (1.0f64 / 6.5).atan().to_degrees();
    assert!(incidence < 90.0 - options.depth.grazing_limit_deg);
    assert_eq!(frame.depth[v as usize * 640 + u as usize], 0.0);
    // Near it on the same wall, well within range and angle, there is depth.
    let near = camera_from_world * Point3::new(3.0, 0.0, 1.2);
    let (u, v) = (
        options.camera.fx * near.x / near.z + options.camera.cx,
        options.camera.fy * near.y / near.z + options.camera.cy,
    );
    assert!(frame.depth[v as usize * 640 + u as usize] > 0.0);
}

/// ORB features as tracking extracts them (ORB-SLAM's extractor and settings: 1000 features,
/// 8 levels, scale 1.2, FAST 20 then 7 per cell) in every 40th frame of a walk.
fn orb_counts(name: &str) -> Vec<usize> {
    use vsgraphs_vision::orb::{OrbExtractor, OrbParams};
    let scenario = vsgraphs_sim::scenarios::Scenario::builtin(name).unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
    let mut extractor = OrbExtractor::new(OrbParams::default()).unwrap();
    let walk = &scenario.walks().unwrap()[0];
    let mut counts = Vec::new();
    for i in (0..walk.times.len()).step_by(40) {
        let frame = renderer.render(i as u64, walk.times[i], &[walk.world_from_camera[i]]);
        let grey = frame.grey();
        let image = GreyImage::from_pixels(640, 480, &grey).unwrap();
        counts.push(extractor.extract(&image, None).unwrap().features.len());
    }
    counts
}

#[test]
fn surfaces_give_orb_features_everywhere_on_a_walk() {
    for name in ["seq03", "seq06"] {
        let mut counts = orb_counts(name);
        counts.sort_unstable();
        let median = counts[counts.len() / 2];
        eprintln!(
            "{name}: ORB features per frame: min {}, median {median}",
            counts[0]
        );
        // The extractor asks for 1000; flat colours would give next to none.
        assert!(counts[0] >= 500 && median >= 900, "{name}: {counts:?}");
    }
}

#[test]
fn the_detector_finds_the_markers_in_view_and_nothing_else() {
    for name in vsgraphs_sim::scenarios::NAMES {
        let scenario = vsgraphs_sim::scenarios::Scenario::builtin(name).unwrap();
        let building = Building::from_plan(&scenario.plan).unwrap();
        let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 1);
        let dictionary = MarkerDictionary::predefined(&scenario.plan.markers.dictionary).unwrap();
        let mut detector = MarkerDetector::new(dictionary, CornerRefinement::Subpixel).unwrap();
        let (mut in_view, mut found, mut strangers) = (0, 0, Vec::new());
        for walk in scenario.walks().unwrap() {
            for i in (0..walk.times.len()).step_by(30) {
                let pose = walk.world_from_camera[i];
                let frame = renderer.render(i as u64, walk.times[i], &[pose]);
                let grey = frame.grey();
                let image = GreyImage::from_pixels(640, 480, &grey).unwrap();
                let detected: Vec<i32> = detector
                    .detect(&image)
                    .unwrap()
                    .iter()
                    .map(|d| d.id)
                    .collect();
                strangers.extend(
                    detected
                        .iter()
                        .filter(|&&id| !building.markers.iter().any(|m| m.id as i32 == id))
                        .map(|&id| (i, id)),
                );
                // Markers squarely in view and near: a detector should not miss them.
                for id in renderer.visible_markers(&building, &pose, 2.5, 45.0) {
                    in_view += 1;
                    found += usize::from(detected.contains(&(id as i32)));
                }
            }
        }
        eprintln!(
            "{name}: {found} of {in_view} markers in view found; false detections {strangers:?}"
        );
        // The textures hold no marker look-alikes (no dark squares, no framed block grids).
        assert!(
            strangers.is_empty(),
            "{name}: markers that are not in the building: {strangers:?}"
        );
        assert!(
            in_view >= 5 && found * 100 >= in_view * 90,
            "{name}: {found} of {in_view}"
        );
    }
}

/// Two rooms side by side, the second (`east` its east wall's x) copying the first's look
/// when `alike`.
fn twin_rooms(alike: bool, east: f64) -> Result<vsgraphs_sim::FloorPlan, vsgraphs_sim::PlanError> {
    let looks_like = if alike { r#", "looks_like": "A""# } else { "" };
    vsgraphs_sim::FloorPlan::from_json(&format!(
        r#"{{"name": "twins", "spaces": [
            {{"name": "A", "kind": "room", "min": [0, 0], "max": [4, 4]}},
            {{"name": "B", "kind": "room", "min": [6, 0], "max": [{east}, 4]{looks_like}}}
        ]}}"#
    ))
}

/// Share of pixels of the same grey level in the same view of room A and of room B (6 m
/// east): a corner of the north wall and the ceiling, away from the markers. The walls'
/// textures are of low contrast, so only equal pixels tell a copy from another texture.
fn alike_share(plan: &vsgraphs_sim::FloorPlan) -> f64 {
    let building = Building::from_plan(plan).unwrap();
    let renderer = Renderer::new(plan, &building, RenderOptions::default(), 1);
    let view = |dx: f64| {
        let eye = Vector3::new(1.5 + dx, 2.0, 1.5);
        let pose = looking_at(eye, Vector3::new(0.3 + dx, 4.0, 2.2));
        renderer.render(0, 0.0, &[pose]).grey()
    };
    let (a, b) = (view(0.0), view(6.0));
    let same = a.iter().zip(&b).filter(|(p, q)| p == q).count();
    same as f64 / a.len() as f64
}

#[test]
fn a_room_that_looks_like_another_is_drawn_alike() {
    let alike = alike_share(&twin_rooms(true, 10.0).unwrap());
    let unlike = alike_share(&twin_rooms(false, 10.0).unwrap());
    eprintln!("pixels alike: {alike:.3} copied, {unlike:.3} not");
    assert!(alike > 0.95, "{alike}");
    assert!(unlike < 0.3, "{unlike}");
    // Only a space of the same kind and size can be copied.
    assert!(matches!(
        twin_rooms(true, 11.0),
        Err(vsgraphs_sim::PlanError::LooksLike { .. })
    ));
}
