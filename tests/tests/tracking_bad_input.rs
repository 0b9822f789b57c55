//! Tracking under bad input: black and blank images, frames without depth, time jumps, a
//! session restart. Each says what happened through the tracker's state and events, nothing
//! panics, and the robot relocalises in its map when good frames come back, or in another
//! robot's map when it is there.

use vsgraphs_optim::Pinhole;
use vsgraphs_pipeline::MapService;
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::{Building, Renderer};
use vsgraphs_slam::{FrameResult, Tracker, TrackerConfig, TrackingState};
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::GreyImage;

/// A frame in memory: stamp (s), grey image, depth (mm).
type RawFrame = (f64, Vec<u8>, Vec<u16>);

/// The first `count` frames of seq06, with the camera and the image size.
fn frames(count: usize) -> (Pinhole, Vec<RawFrame>, (u32, u32)) {
    let scenario = Scenario::builtin("seq06").unwrap();
    let building = Building::from_plan(&scenario.plan).unwrap();
    let renderer = Renderer::new(&scenario.plan, &building, scenario.render.clone(), 3);
    let walk = scenario.walks().unwrap().remove(0);
    let c = &scenario.render.camera;
    let frames = (0..count)
        .map(|i| {
            let frame = render_frame(&renderer, &walk, i);
            (walk.times[i], frame.grey(), frame.depth_units(1000.0))
        })
        .collect();
    (
        Pinhole::new(c.fx, c.fy, c.cx, c.cy),
        frames,
        (c.width, c.height),
    )
}

/// A grey image of a place no walk sees: noise in blocks of 4×4 pixels, so that FAST finds
/// corners at every scale.
fn noise_wall(size: (u32, u32)) -> Vec<u8> {
    let (width, height) = (size.0 as usize, size.1 as usize);
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let noise: Vec<u8> = (0..width * height)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 56) as u8
        })
        .collect();
    (0..width * height)
        .map(|i| noise[(i / width / 4) * width + (i % width) / 4])
        .collect()
}

struct Rig {
    tracker: Tracker,
    maps: MapService,
    camera: Pinhole,
    size: (u32, u32),
}

impl Rig {
    fn track(&mut self, stamp_s: f64, grey: &[u8], depth: &[u16]) -> FrameResult {
        let (width, height) = self.size;
        let image = GreyImage::from_pixels(width, height, grey).unwrap();
        let depth = DepthImage {
            width,
            height,
            data: depth.to_vec(),
            depth_scale: 1000.0,
            registered: true,
        };
        let stamp = (stamp_s * 1e9).round() as u64;
        self.tracker
            .track(
                &mut self.maps,
                stamp,
                &self.camera,
                &image,
                &depth,
                Vec::new(),
            )
            .expect("bad frames are tracking outcomes, not errors")
    }
}

#[test]
fn bad_frames_lose_track_and_good_ones_bring_it_back() {
    let (camera, frames, size) = frames(40);
    let n = (size.0 * size.1) as usize;
    let mut rig = Rig {
        tracker: Tracker::new(TrackerConfig::default()).unwrap(),
        maps: MapService::new(),
        camera,
        size,
    };
    // A black frame before any map: still initialising, no map made from nothing.
    let result = rig.track(0.0, &vec![0; n], &vec![0; n]);
    assert_eq!(result.state, TrackingState::Initialising);
    assert!(rig.tracker.maps().is_empty());
    for (t, grey, depth) in &frames[..20] {
        let r = rig.track(t + 1.0, grey, depth);
        assert_eq!(r.state, TrackingState::Tracking, "t={t}: {r:?}");
    }
    let t0 = frames[20].0 + 1.0;
    // Black, then blank white: no features, so no pose; the track is lost and says so.
    let black = rig.track(t0, &vec![0; n], &frames[20].2);
    assert_eq!(
        (black.state, black.world_from_camera, black.event.as_deref()),
        (TrackingState::Lost, None, Some("tracking lost"))
    );
    let blank = rig.track(t0 + 0.03, &vec![255; n], &frames[20].2);
    assert_eq!(
        (blank.state, blank.world_from_camera),
        (TrackingState::Lost, None)
    );
    // A good frame: relocalised in the same map.
    let back = rig.track(t0 + 0.06, &frames[21].1, &frames[21].2);
    assert_eq!(back.state, TrackingState::Tracking, "{back:?}");
    assert_eq!(back.event.as_deref(), Some("relocalised"));
    assert_eq!(rig.tracker.maps().len(), 1);

    // A frame without any valid depth: its keypoints have no depth, so it is tracked on the
    // map's points by reprojection alone, or lost; either way it says which.
    let no_depth = rig.track(t0 + 0.09, &frames[22].1, &vec![0; n]);
    assert!(
        matches!(
            (no_depth.state, no_depth.world_from_camera),
            (TrackingState::Tracking, Some(_)) | (TrackingState::Lost, None)
        ),
        "{no_depth:?}"
    );
    assert_eq!(no_depth.features_with_depth, 0);

    // Time jumps forward by a minute: the motion model is bounded, and the frame still finds
    // its place (or relocalises on the next).
    let jump = rig.track(t0 + 60.0, &frames[23].1, &frames[23].2);
    let after = rig.track(t0 + 60.03, &frames[24].1, &frames[24].2);
    assert!(
        jump.state == TrackingState::Tracking || after.state == TrackingState::Tracking,
        "{jump:?} / {after:?}"
    );

    // A session restart: motion is unknown, so the next frame relocalises in the same map.
    rig.tracker.restart();
    assert_eq!(rig.tracker.state(), TrackingState::Lost);
    let restarted = rig.track(t0 + 61.0, &frames[30].1, &frames[30].2);
    assert_eq!(restarted.state, TrackingState::Tracking, "{restarted:?}");
    assert_eq!(restarted.event.as_deref(), Some("relocalised"));
    assert_eq!(rig.tracker.maps().len(), 1);
}

#[test]
fn a_robot_that_never_comes_back_starts_a_new_map() {
    let (camera, frames, size) = frames(12);
    let n = (size.0 * size.1) as usize;
    let mut rig = Rig {
        tracker: Tracker::new(TrackerConfig::default()).unwrap(),
        maps: MapService::new(),
        camera,
        size,
    };
    for (t, grey, depth) in &frames[..10] {
        rig.track(*t, grey, depth);
    }
    // Black frames: lost, relocalising in the one map for `new_map_after_s` (3 s)...
    let t0 = frames[9].0;
    for i in 1..=7 {
        let r = rig.track(t0 + 0.4 * f64::from(i), &vec![0; n], &vec![0; n]);
        assert_eq!(r.state, TrackingState::Lost);
    }
    // ...then waiting for a frame good enough to start a new map.
    let r = rig.track(t0 + 3.5, &vec![0; n], &vec![0; n]);
    assert_eq!(r.state, TrackingState::Initialising);
    assert_eq!(rig.tracker.maps().len(), 1);
    // Somewhere the map has never seen (a textured wall 2 m away, blurred noise):
    // relocalisation fails, and as more than 3 s have passed, a second map starts.
    let elsewhere = noise_wall(size);
    let r = rig.track(t0 + 4.5, &elsewhere, &vec![2000; n]);
    assert_eq!(r.state, TrackingState::Tracking, "{r:?}");
    assert_eq!(r.map, 1);
    assert!(
        r.event.as_deref().unwrap_or("").contains("map 1 started"),
        "{r:?}"
    );
    assert_eq!(rig.tracker.maps().len(), 2);
}

#[test]
fn a_robot_carried_back_to_where_it_began_relocalises_there_at_once() {
    let (camera, frames, size) = frames(120);
    let mut rig = Rig {
        tracker: Tracker::new(TrackerConfig::default()).unwrap(),
        maps: MapService::new(),
        camera,
        size,
    };
    let mut poses = Vec::new();
    for (t, grey, depth) in &frames {
        let r = rig.track(*t, grey, depth);
        assert_eq!(r.state, TrackingState::Tracking, "t={t}: {r:?}");
        poses.push(r.world_from_camera.unwrap());
    }
    let keyframes = rig.tracker.maps()[0].read().keyframes.len();
    assert!(keyframes >= 12, "{keyframes} keyframes");
    // Restarted where it began: the newest keyframes see elsewhere, and relocalisation tries
    // only a few keyframes a frame, so the place must be found by its words.
    rig.tracker.restart();
    let (t, grey, depth) = &frames[3];
    let back = rig.track(frames[119].0 + 1.0 + t, grey, depth);
    assert_eq!(back.state, TrackingState::Tracking, "{back:?}");
    assert_eq!(back.event.as_deref(), Some("relocalised"));
    let error = poses[3].inverse().compose(&back.world_from_camera.unwrap());
    assert!(error.translation.norm() < 0.05, "{error:?}");
}

#[test]
fn a_lost_robot_relocalises_in_another_robots_map() {
    let (camera, frames, size) = frames(90);
    let n = (size.0 * size.1) as usize;
    let maps = MapService::new();
    let rig = |maps: &MapService| Rig {
        tracker: Tracker::new(TrackerConfig::default()).unwrap(),
        maps: maps.clone(),
        camera,
        size,
    };
    // The first robot maps the start of the walk.
    let mut first = rig(&maps);
    let mut poses = Vec::new();
    for (t, grey, depth) in &frames[..60] {
        let r = first.track(*t, grey, depth);
        assert_eq!(r.state, TrackingState::Tracking, "t={t}: {r:?}");
        poses.push(r.world_from_camera.unwrap());
    }
    first.tracker.flush(&mut first.maps).unwrap();
    let walked = first.tracker.maps()[0].id();
    // The second starts elsewhere, in a map of its own, then restarts where the first began:
    // its own map knows nothing of the place, the first robot's does.
    let mut second = rig(&maps);
    let started = second.track(0.0, &noise_wall(size), &vec![2000; n]);
    assert_eq!(started.state, TrackingState::Tracking, "{started:?}");
    assert_ne!(second.tracker.maps()[0].id(), walked);
    second.tracker.restart();
    let (t, grey, depth) = &frames[5];
    let found = second.track(1.0 + t, grey, depth);
    assert_eq!(found.state, TrackingState::Tracking, "{found:?}");
    assert!(found.joined, "{found:?}");
    assert_eq!(found.map, 1);
    assert_eq!(second.tracker.maps()[1].id(), walked);
    assert!(
        found
            .event
            .as_deref()
            .is_some_and(|e| e.starts_with(&format!("relocalised in map {}", walked.0))),
        "{found:?}"
    );
    // In the first robot's frame, where the first robot was.
    let error = poses[5]
        .inverse()
        .compose(&found.world_from_camera.unwrap());
    assert!(error.translation.norm() < 0.05, "{error:?}");
    // And it goes on tracking there, on past where the first robot stopped, adding keyframes
    // to the shared map.
    let before = first.tracker.maps()[0].read().keyframes.len();
    for (t, grey, depth) in &frames[6..] {
        let r = second.track(1.0 + t, grey, depth);
        assert_eq!((r.state, r.map), (TrackingState::Tracking, 1), "{r:?}");
    }
    second.tracker.flush(&mut second.maps).unwrap();
    let map = second.tracker.maps()[1].read();
    assert!(
        map.keyframes.len() > before,
        "{} keyframes",
        map.keyframes.len()
    );
}
