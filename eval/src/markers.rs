//! Marker detection measured on its own: a scenario's rendered frames, whose markers' true
//! corners are known, give recall by distance, false detections and corner error; any frames
//! (rendered or real) give the detector's CPU time per frame.

use anyhow::Context;
use nalgebra::Point3;
use serde::Serialize;
use std::path::Path;
use vsgraphs_sim::scenarios::Scenario;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_vision::aruco::{CornerRefinement, MarkerDetector, ThresholdWindows};
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::marker_search::MarkerSearch;
use vsgraphs_vision::GreyImage;

/// Upper ends of the distance bins recall is counted in, metres.
pub const DISTANCE_BINS_M: [f64; 6] = [1.0, 2.0, 3.0, 4.0, 6.0, f64::INFINITY];

/// Markers further than this are "far" in [`MarkersRun::corner_error_far_px`], metres.
pub const FAR_M: f64 = 2.0;

/// What is measured on a scenario's frames.
#[derive(Debug, Clone)]
pub struct MarkersOptions {
    /// Renderer noise and texture seed.
    pub seed: u64,
    /// Every how many frames of each walk one is rendered and searched.
    pub every: usize,
    /// Markers seen further off their normal than this are not counted as in view.
    pub max_angle_deg: f64,
    /// How the detector refines corners.
    pub refinement: CornerRefinement,
    /// The detector's threshold windows.
    pub windows: ThresholdWindows,
}

impl Default for MarkersOptions {
    fn default() -> Self {
        Self {
            seed: 1,
            every: 10,
            max_angle_deg: 60.0,
            refinement: CornerRefinement::Subpixel,
            windows: ThresholdWindows::Three,
        }
    }
}

/// Markers in view and found within one distance bin.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DistanceBin {
    pub up_to_m: f64,
    pub in_view: usize,
    pub found: usize,
}

/// A spread of values: median, 99th percentile, largest.
#[derive(Debug, Clone, Serialize, PartialEq, Default)]
pub struct Spread {
    pub count: usize,
    pub median: f64,
    pub p99: f64,
    pub max: f64,
    pub mean: f64,
}

impl Spread {
    pub fn of(mut values: Vec<f64>) -> Self {
        if values.is_empty() {
            return Self::default();
        }
        values.sort_by(f64::total_cmp);
        let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
        Self {
            count: values.len(),
            median: at(0.5),
            p99: at(0.99),
            max: values[values.len() - 1],
            mean: values.iter().sum::<f64>() / values.len() as f64,
        }
    }
}

/// Detection on one scenario's frames.
#[derive(Debug, Clone, Serialize)]
pub struct MarkersRun {
    pub frames: usize,
    pub by_distance: Vec<DistanceBin>,
    /// Frame index and id of each detection of a marker the building does not hold, or of one
    /// found where none of that id is in the image.
    pub false_detections: Vec<(usize, i32)>,
    /// Found markers' corners against their projections, pixels (the worst of each marker's
    /// four).
    pub corner_error_px: Spread,
    /// The same for markers further than [`FAR_M`]: small in the image, where the outline's
    /// first place matters most.
    pub corner_error_far_px: Spread,
    /// The detector's CPU time per frame, milliseconds.
    pub cpu_ms: Spread,
    /// The same on frames where no marker is in view at all.
    pub cpu_ms_no_marker: Spread,
}

/// Detection timed on real colour frames (a folder of `*.color.jpg`, as 7-Scenes holds).
#[derive(Debug, Clone, Serialize)]
pub struct ImagesRun {
    pub frames: usize,
    pub detections: usize,
    pub cpu_ms: Spread,
}

/// Runs the detector over every `options.every`-th frame of every walk of `scenario`.
pub fn run(
    scenario: &Scenario,
    options: &MarkersOptions,
    progress: impl Fn(usize, usize),
) -> anyhow::Result<MarkersRun> {
    // Timed on this thread's CPU clock: every part of the detection must run on it.
    vsgraphs_vision::opencv_on_one_thread()?;
    let (building, renderer) = scenario.build(options.seed).context("building the plan")?;
    let camera = &scenario.render.camera;
    let mut detector = detector_for(scenario, options)?;
    let walks = scenario.walks().context("planning the walks")?;
    let total: usize = walks
        .iter()
        .map(|w| w.times.len().div_ceil(options.every.max(1)))
        .sum();
    let mut bins: Vec<DistanceBin> = DISTANCE_BINS_M
        .iter()
        .map(|&up_to_m| DistanceBin {
            up_to_m,
            in_view: 0,
            found: 0,
        })
        .collect();
    let (mut corner_errors, mut far_errors) = (Vec::new(), Vec::new());
    let (mut cpu, mut cpu_no_marker) = (Vec::new(), Vec::new());
    let mut false_detections = Vec::new();
    let mut frames = 0;
    for walk in &walks {
        for i in (0..walk.times.len()).step_by(options.every.max(1)) {
            frames += 1;
            progress(frames, total);
            let pose = walk.world_from_camera[i];
            let frame = render_frame(&renderer, walk, i);
            let grey = frame.grey();
            let image = GreyImage::from_pixels(camera.width, camera.height, &grey)?;
            let started = vsgraphs_slam::cpu_time::thread();
            let detections = detector.detect(&image)?;
            let ms = (vsgraphs_slam::cpu_time::thread() - started).as_secs_f64() * 1e3;
            cpu.push(ms);
            let in_view = renderer.visible_markers(&building, &pose, 1e3, options.max_angle_deg);
            // Markers seen obliquely may be found too; a detection is false when its id is not
            // wholly in the image and its corners are not where that marker projects (one cut
            // by the image's edge, found where it hangs, is not false).
            let anywhere = renderer.visible_markers(&building, &pose, 1e3, 89.0);
            if anywhere.is_empty() {
                cpu_no_marker.push(ms);
            }
            let camera_from_world = pose.inverse();
            for detection in &detections {
                let Some(marker) = building
                    .markers
                    .iter()
                    .find(|m| m.id as i32 == detection.id)
                else {
                    false_detections.push((i, detection.id));
                    continue;
                };
                let h = marker.side / 2.0;
                let projected = [(-h, h), (h, h), (h, -h), (-h, -h)].map(|(x, y)| {
                    let p = camera_from_world * (marker.world_from_marker * Point3::new(x, y, 0.0));
                    [
                        camera.fx * p.x / p.z + camera.cx,
                        camera.fy * p.y / p.z + camera.cy,
                    ]
                });
                let error = detection
                    .corners
                    .iter()
                    .zip(&projected)
                    .map(|(c, t)| (f64::from(c[0]) - t[0]).hypot(f64::from(c[1]) - t[1]))
                    .fold(0.0, f64::max);
                if !in_view.contains(&marker.id) && !anywhere.contains(&marker.id) && error > 5.0 {
                    false_detections.push((i, detection.id));
                } else if in_view.contains(&marker.id) {
                    corner_errors.push(error);
                    let distance = (marker.world_from_marker.translation.vector
                        - pose.translation.vector)
                        .norm();
                    if distance > FAR_M {
                        far_errors.push(error);
                    }
                }
            }
            for id in in_view {
                let marker = building
                    .markers
                    .iter()
                    .find(|m| m.id == id)
                    .expect("a marker in view is the building's");
                let distance =
                    (marker.world_from_marker.translation.vector - pose.translation.vector).norm();
                let bin = bins
                    .iter_mut()
                    .find(|b| distance <= b.up_to_m)
                    .expect("the last bin has no end");
                bin.in_view += 1;
                bin.found += usize::from(detections.iter().any(|d| d.id == id as i32));
            }
        }
    }
    Ok(MarkersRun {
        frames,
        by_distance: bins,
        false_detections,
        corner_error_px: Spread::of(corner_errors),
        corner_error_far_px: Spread::of(far_errors),
        cpu_ms: Spread::of(cpu),
        cpu_ms_no_marker: Spread::of(cpu_no_marker),
    })
}

/// The detector of a scenario's dictionary, set as `options` say.
fn detector_for(scenario: &Scenario, options: &MarkersOptions) -> anyhow::Result<MarkerDetector> {
    let dictionary = MarkerDictionary::predefined(&scenario.plan.markers.dictionary)?;
    let mut detector = MarkerDetector::new(dictionary, options.refinement)?;
    detector.set_threshold_windows(options.windows);
    Ok(detector)
}

/// Markers followed from frame to frame ([`MarkerSearch`]) against the whole image searched in
/// every frame, over every frame of a scenario's walks.
#[derive(Debug, Clone, Serialize)]
pub struct FollowRun {
    pub frames: usize,
    /// Every how many frames the followed search looks at the whole image.
    pub full_every: u32,
    /// Markers found by searching every whole frame (one per marker and frame).
    pub whole: usize,
    /// Of those, the followed search missed these: markers it was not following (coming into
    /// view, or not seen for a while, waiting for the next whole search) ...
    pub missed_new: usize,
    /// ... and markers it was following, lost by the search around them.
    pub missed_followed: usize,
    /// Found by the followed search only (none expected).
    pub extra: usize,
    /// Found by both with corners more than 0.01 px apart.
    pub corners_differ: usize,
    /// CPU time per frame, milliseconds: the whole image, and the followed search.
    pub cpu_ms_whole: Spread,
    pub cpu_ms_followed: Spread,
}

/// Runs both searches over every frame of every walk of `scenario`.
pub fn run_followed(
    scenario: &Scenario,
    options: &MarkersOptions,
    full_every: u32,
    progress: impl Fn(usize, usize),
) -> anyhow::Result<FollowRun> {
    // Timed on this thread's CPU clock: every part of the detection must run on it.
    vsgraphs_vision::opencv_on_one_thread()?;
    let (_, renderer) = scenario.build(options.seed).context("building the plan")?;
    let camera = &scenario.render.camera;
    let mut detector = detector_for(scenario, options)?;
    let walks = scenario.walks().context("planning the walks")?;
    let total: usize = walks.iter().map(|w| w.times.len()).sum();
    let mut run = FollowRun {
        frames: 0,
        full_every,
        whole: 0,
        missed_new: 0,
        missed_followed: 0,
        extra: 0,
        corners_differ: 0,
        cpu_ms_whole: Spread::default(),
        cpu_ms_followed: Spread::default(),
    };
    let (mut cpu_whole, mut cpu_followed) = (Vec::new(), Vec::new());
    for walk in &walks {
        let mut search = MarkerSearch::new(full_every);
        for i in 0..walk.times.len() {
            run.frames += 1;
            progress(run.frames, total);
            let frame = render_frame(&renderer, walk, i);
            let image = GreyImage::from_pixels(camera.width, camera.height, &frame.grey())?;
            let followed_before: Vec<i32> = search.followed_ids().collect();
            let started = vsgraphs_slam::cpu_time::thread();
            let whole = detector.detect(&image)?;
            let middle = vsgraphs_slam::cpu_time::thread();
            let followed = search.detect(&mut detector, &image, 1)?;
            let ended = vsgraphs_slam::cpu_time::thread();
            cpu_whole.push((middle - started).as_secs_f64() * 1e3);
            cpu_followed.push((ended - middle).as_secs_f64() * 1e3);
            run.whole += whole.len();
            for w in &whole {
                match followed.iter().find(|f| f.id == w.id) {
                    None if followed_before.contains(&w.id) => run.missed_followed += 1,
                    None => run.missed_new += 1,
                    Some(f) => {
                        let apart =
                            f.corners.iter().zip(&w.corners).any(|(a, b)| {
                                (a[0] - b[0]).abs() > 0.01 || (a[1] - b[1]).abs() > 0.01
                            });
                        run.corners_differ += usize::from(apart);
                    }
                }
            }
            run.extra += followed
                .iter()
                .filter(|f| !whole.iter().any(|w| w.id == f.id))
                .count();
        }
    }
    run.cpu_ms_whole = Spread::of(cpu_whole);
    run.cpu_ms_followed = Spread::of(cpu_followed);
    Ok(run)
}

/// Times the detector on every `*.color.jpg` of `folder` (the dictionary by OpenCV's name).
pub fn run_images(
    folder: &Path,
    dictionary: &str,
    refinement: CornerRefinement,
    windows: ThresholdWindows,
) -> anyhow::Result<ImagesRun> {
    let mut paths: Vec<_> = std::fs::read_dir(folder)
        .with_context(|| format!("reading {}", folder.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(".color.jpg"))
        .collect();
    paths.sort();
    anyhow::ensure!(
        !paths.is_empty(),
        "{} holds no *.color.jpg frame",
        folder.display()
    );
    // Timed on this thread's CPU clock: every part of the detection must run on it.
    vsgraphs_vision::opencv_on_one_thread()?;
    let mut detector = MarkerDetector::new(MarkerDictionary::predefined(dictionary)?, refinement)?;
    detector.set_threshold_windows(windows);
    let (mut cpu, mut detections) = (Vec::new(), 0);
    for path in &paths {
        let grey = GreyImage::read(path).with_context(|| format!("reading {}", path.display()))?;
        let started = vsgraphs_slam::cpu_time::thread();
        detections += detector.detect(&grey)?.len();
        cpu.push((vsgraphs_slam::cpu_time::thread() - started).as_secs_f64() * 1e3);
    }
    Ok(ImagesRun {
        frames: paths.len(),
        detections,
        cpu_ms: Spread::of(cpu),
    })
}

/// The followed search against the whole image, as a few lines.
pub fn print_followed(run: &FollowRun) {
    println!(
        "{} frames; the whole image searched every {} frames, and around the markers between",
        run.frames, run.full_every
    );
    println!(
        "markers found searching every whole frame: {}; the followed search missed {} coming \
         into view and {} it was following; found only by it: {}; corners apart: {}",
        run.whole, run.missed_new, run.missed_followed, run.extra, run.corners_differ
    );
    let (w, f) = (&run.cpu_ms_whole, &run.cpu_ms_followed);
    println!(
        "CPU ms per frame, whole / followed: median {:.2} / {:.2}, mean {:.2} / {:.2}, \
         p99 {:.2} / {:.2}",
        w.median, f.median, w.mean, f.mean, w.p99, f.p99
    );
}

/// The run as a table.
pub fn print_table(run: &MarkersRun) {
    println!("{} frames", run.frames);
    println!("| up to | in view | found | recall |");
    println!("|---|---|---|---|");
    for bin in &run.by_distance {
        println!(
            "| {} m | {} | {} | {:.3} |",
            bin.up_to_m,
            bin.in_view,
            bin.found,
            bin.found as f64 / bin.in_view.max(1) as f64
        );
    }
    for (name, c) in [
        ("", &run.corner_error_px),
        (&*format!(" beyond {FAR_M} m"), &run.corner_error_far_px),
    ] {
        println!(
            "corner error{name}, px: median {:.3}, p99 {:.3}, max {:.3} ({} markers)",
            c.median, c.p99, c.max, c.count
        );
    }
    println!("false detections: {:?}", run.false_detections);
    for (name, s) in [
        ("every frame", &run.cpu_ms),
        ("no marker", &run.cpu_ms_no_marker),
    ] {
        println!(
            "CPU ms per frame, {name}: median {:.2}, mean {:.2}, p99 {:.2} ({} frames)",
            s.median, s.mean, s.p99, s.count
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_spread_takes_the_nearest_rank() {
        let s = Spread::of((1..=101).rev().map(f64::from).collect());
        assert_eq!(
            (s.count, s.median, s.p99, s.max, s.mean),
            (101, 51.0, 100.0, 101.0, 51.0)
        );
        assert_eq!(Spread::of(Vec::new()), Spread::default());
    }

    /// The measurement on a few frames of a walk: near markers found, none made up, corners
    /// within a pixel, whichever windows.
    #[test]
    fn markers_in_view_are_found_where_they_project() {
        let scenario = Scenario::builtin("seq01").unwrap();
        for windows in [ThresholdWindows::Three, ThresholdWindows::One] {
            let options = MarkersOptions {
                every: 60,
                windows,
                ..Default::default()
            };
            let run = run(&scenario, &options, |_, _| {}).unwrap();
            let near = &run.by_distance[..2];
            let (found, in_view): (usize, usize) = near
                .iter()
                .fold((0, 0), |a, b| (a.0 + b.found, a.1 + b.in_view));
            assert!(in_view >= 10 && found == in_view, "{windows:?}: {run:?}");
            assert!(run.false_detections.is_empty(), "{windows:?}: {run:?}");
            assert!(run.corner_error_px.median < 1.0, "{windows:?}: {run:?}");
            assert_eq!(run.cpu_ms.count, run.frames);
        }
    }
}
