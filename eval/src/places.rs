//! Place recognition on its own: `vsgraphs-eval vocabulary` trains the visual vocabulary from
//! simulated frames, and `vsgraphs-eval places` measures how well the place index finds the
//! places a simulated walk comes back to, against the truth of the walk.
//!
//! A revisit is defined by geometry, not by the words: a keyframe revisits an older one when
//! at least `revisit_overlap` of the surface it sees (its depth, sampled on a grid) is seen by
//! the older one too (in its image, not hidden behind something nearer), both at their true
//! poses. A returned candidate is right when it shares at least `correct_overlap` of the view,
//! enough for geometric verification to find matches; else it is a false candidate.

use anyhow::Context;
use nalgebra::{Isometry3, Point3};
use serde::Serialize;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::walk::Walk;
use vsgraphs_sim::{Building, Camera, Frame, Renderer};
use vsgraphs_slam::places::{verify, PlaceCandidate, PlaceIndex, PlaceView, GROUPING_LEVEL};
use vsgraphs_slam::{DepthResidual, KeyFrameId, Keypoint, Pinhole, Rig, TrackerConfig};
use vsgraphs_vision::brief::Descriptor;
use vsgraphs_vision::depth::DepthImage;
use vsgraphs_vision::orb::{OrbExtractor, OrbParams};
use vsgraphs_vision::vocabulary::{Training, Vocabulary};
use vsgraphs_vision::GreyImage;

/// Descriptors of every `every`-th frame of every robot of `scenarios`, rendered with each of
/// `seeds` (which choose the textures); two threads. `progress(done, total)` per frame.
pub fn training_images(
    scenarios: &[String],
    seeds: &[u64],
    every: usize,
    progress: impl Fn(usize, usize) + Sync,
) -> anyhow::Result<Vec<Vec<Descriptor>>> {
    struct Job {
        renderer: std::sync::Arc<Renderer>,
        walk: std::sync::Arc<Walk>,
        frame: usize,
    }
    let mut jobs = Vec::new();
    for name in scenarios {
        let scenario = vsgraphs_sim::scenarios::Scenario::load(name)
            .with_context(|| format!("loading scenario {name}"))?;
        let building = Building::from_plan(&scenario.plan).context("building the plan")?;
        let walks: Vec<_> = scenario
            .walks()
            .context("planning the walks")?
            .into_iter()
            .map(std::sync::Arc::new)
            .collect();
        for &seed in seeds {
            let renderer = std::sync::Arc::new(Renderer::new(
                &scenario.plan,
                &building,
                scenario.render.clone(),
                seed,
            ));
            for walk in &walks {
                for frame in (0..walk.times.len()).step_by(every.max(1)) {
                    jobs.push(Job {
                        renderer: renderer.clone(),
                        walk: walk.clone(),
                        frame,
                    });
                }
            }
        }
    }
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let images: Mutex<Vec<Option<Vec<Descriptor>>>> = Mutex::new(vec![None; jobs.len()]);
    let failure: Mutex<Option<anyhow::Error>> = Mutex::new(None);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| {
                let mut extractor = match OrbExtractor::new(OrbParams::default()) {
                    Ok(e) => e,
                    Err(e) => {
                        *failure.lock().expect("not poisoned") = Some(e.into());
                        return;
                    }
                };
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(job) = jobs.get(i) else { break };
                    let frame = render_frame(&job.renderer, &job.walk, job.frame);
                    match describe(&mut extractor, &frame) {
                        Ok(d) => images.lock().expect("not poisoned")[i] = Some(d),
                        Err(e) => {
                            *failure.lock().expect("not poisoned") = Some(e);
                            break;
                        }
                    }
                    progress(done.fetch_add(1, Ordering::Relaxed) + 1, jobs.len());
                }
            });
        }
    });
    if let Some(e) = failure.into_inner().expect("not poisoned") {
        return Err(e);
    }
    Ok(images
        .into_inner()
        .expect("not poisoned")
        .into_iter()
        .flatten()
        .collect())
}

/// A rendered frame's ORB descriptors, as the tracker extracts them.
fn describe(extractor: &mut OrbExtractor, frame: &Frame) -> anyhow::Result<Vec<Descriptor>> {
    let grey = GreyImage::from_pixels(frame.width, frame.height, &frame.grey())?;
    Ok(extractor.extract(&grey, None)?.descriptors)
}

/// Trains the vocabulary on `images` (see [`training_images`]).
pub fn train(images: &[Vec<Descriptor>], training: &Training) -> anyhow::Result<Vocabulary> {
    Ok(Vocabulary::train(images, training)?)
}

/// How `vsgraphs-eval places` samples and judges a walk.
#[derive(Clone, Debug)]
pub struct PlacesOptions {
    pub seed: u64,
    /// A keyframe when the camera has moved this far since the last one, metres …
    pub keyframe_step_m: f64,
    /// … or turned this far, degrees.
    pub keyframe_turn_deg: f64,
    /// Keyframes this recent are the query's own neighbourhood: never candidates, and the
    /// bar a candidate must reach is the query's lowest score against them, seconds.
    pub recent_s: f64,
    /// Share of the view an older keyframe must see for the query to count as a revisit.
    pub revisit_overlap: f64,
    /// Share of the view a candidate must see to count as right: matchable for the words'
    /// first candidate, at any scale and angle for a confirmed one (geometry may match what
    /// the overlap judges too far).
    pub correct_overlap: f64,
    /// Inliers verification needs.
    pub min_inliers: usize,
}

impl Default for PlacesOptions {
    fn default() -> Self {
        Self {
            seed: 1,
            keyframe_step_m: 0.3,
            keyframe_turn_deg: 15.0,
            recent_s: 10.0,
            revisit_overlap: 0.4,
            correct_overlap: 0.2,
            min_inliers: vsgraphs_slam::places::MIN_INLIERS,
        }
    }
}

/// The figures of one walk.
#[derive(Clone, Debug, Default, Serialize)]
pub struct PlacesRun {
    pub robot: String,
    pub keyframes: usize,
    /// Keyframes with an older keyframe (outside their recent neighbourhood) to query.
    pub queries: usize,
    /// Queries whose place an older keyframe shows (overlap ≥ revisit_overlap).
    pub revisits: usize,
    /// The words alone: queries that returned a candidate, and those whose first candidate
    /// shows the place (overlap ≥ correct_overlap).
    pub words_answered: usize,
    pub words_right: usize,
    /// Revisits with a right candidate among the first `VERIFIED_CANDIDATES`.
    pub words_revisits_found: usize,
    /// Verified: queries for which a candidate was confirmed by geometry, those whose
    /// candidate shows the place (a false one would be a false loop), and the revisits
    /// among them.
    pub verified: usize,
    pub verified_right: usize,
    pub verified_revisits_found: usize,
    /// verified_right / verified: the precision of what loop closing would be handed.
    pub precision: f64,
    /// verified_revisits_found / revisits.
    pub recall: f64,
    /// Inliers of each confirmed candidate that was wrong, and the fewest of a right one.
    pub wrong_inliers: Vec<usize>,
    pub right_inliers_min: Option<usize>,
    /// The right ones' transform against the truth: median, 90th percentile and largest,
    /// metres and degrees. One keyframe's matches can leave a direction weakly held (a far
    /// cluster of points turns with the camera); loop closing refines with the local map.
    pub transform_error_m: [f64; 3],
    pub transform_error_deg: [f64; 3],
    /// Lookup in the index, and verification of the candidates, per query, median ms.
    pub median_query_ms: f64,
    pub median_verify_ms: f64,
}

/// Candidates verified per query, best group first (ORB-SLAM3 verifies three).
pub const VERIFIED_CANDIDATES: usize = 3;

/// A keyframe as the evaluation keeps it.
struct Sample {
    time_s: f64,
    world_from_camera: Isometry3<f64>,
    /// Surface points in the world on a grid over the image.
    points: Vec<Point3<f64>>,
    /// Depth on the same grid (0: none), to test whether a point is hidden.
    depth: Vec<f32>,
    keypoints: Vec<Keypoint>,
    descriptors: Vec<Descriptor>,
}

/// Largest ratio of distances at which a patch is still matched (two levels of ORB's 1.2).
const MATCHABLE_SCALE: f64 = 1.44;

/// Grid step over the image, pixels.
const GRID: u32 = 8;

/// Runs every robot of `scenario` (by its walk) through keyframe sampling, the vocabulary,
/// the place index and verification, and scores each answer against the truth.
pub fn run(
    scenario: &vsgraphs_sim::scenarios::Scenario,
    vocabulary: &Vocabulary,
    options: &PlacesOptions,
    progress: impl Fn(usize, usize),
) -> anyhow::Result<Vec<PlacesRun>> {
    let (_, renderer) = scenario.build(options.seed).context("building the plan")?;
    let camera = &scenario.render.camera;
    let rig = rig_of(camera);
    let mut extractor = OrbExtractor::new(OrbParams::default())?;
    let mut runs = Vec::new();
    for walk in scenario.walks().context("planning the walks")? {
        let chosen = keyframes_of(&walk, options);
        let mut samples: Vec<Sample> = Vec::with_capacity(chosen.len());
        let mut index = PlaceIndex::new();
        let mut run = PlacesRun {
            robot: walk.robot.clone(),
            keyframes: chosen.len(),
            ..PlacesRun::default()
        };
        let (mut query_ms, mut verify_ms) = (Vec::new(), Vec::new());
        let (mut translation_errors, mut rotation_errors) = (Vec::new(), Vec::new());
        let mut right_inliers = Vec::new();
        for (k, &i) in chosen.iter().enumerate() {
            progress(k + 1, chosen.len());
            let frame = render_frame(&renderer, &walk, i);
            let sample = sample_of(
                &mut extractor,
                &frame,
                &rig,
                camera,
                walk.times[i],
                walk.world_from_camera[i],
            )?;
            let bag = vocabulary.transform(&sample.descriptors, GROUPING_LEVEL);
            let recent = |j: usize| sample.time_s - samples[j].time_s < options.recent_s;
            if (0..samples.len()).any(|j| !recent(j)) {
                run.queries += 1;
                let overlaps: Vec<f64> = (0..samples.len())
                    .map(|j| overlap(&sample, &samples[j], camera, true))
                    .collect();
                let revisit = (0..samples.len())
                    .any(|j| !recent(j) && overlaps[j] >= options.revisit_overlap);
                run.revisits += usize::from(revisit);
                let started = std::time::Instant::now();
                // Its covisible keyframes: recent ones that see its place.
                let neighbourhood: Vec<KeyFrameId> = (0..samples.len())
                    .filter(|&j| recent(j) && overlaps[j] >= options.revisit_overlap)
                    .map(|j| KeyFrameId(j as u32))
                    .collect();
                let bar = index.lowest_score(&bag, &neighbourhood).unwrap_or(0.0);
                let count = samples.len();
                let mut found = index.candidates(
                    &bag,
                    bar,
                    |kf| recent(kf.0 as usize),
                    // Keyframes next to each other in time stand for covisible ones.
                    |kf| {
                        let j = kf.0 as usize;
                        (j.saturating_sub(2)..(j + 3).min(count))
                            .filter(|&n| n != j)
                            .map(|n| KeyFrameId(n as u32))
                            .collect()
                    },
                );
                query_ms.push(started.elapsed().as_secs_f64() * 1e3);
                found.truncate(VERIFIED_CANDIDATES);
                let shows =
                    |c: &PlaceCandidate| overlaps[c.keyframe.0 as usize] >= options.correct_overlap;
                if let Some(first) = found.first() {
                    run.words_answered += 1;
                    run.words_right += usize::from(shows(first));
                }
                run.words_revisits_found += usize::from(revisit && found.iter().any(shows));
                let started = std::time::Instant::now();
                let query = PlaceView {
                    keypoints: &sample.keypoints,
                    descriptors: &sample.descriptors,
                    bag: &bag,
                };
                let confirmed = found
                    .iter()
                    .filter_map(|c| {
                        let other = &samples[c.keyframe.0 as usize];
                        let view = PlaceView {
                            keypoints: &other.keypoints,
                            descriptors: &other.descriptors,
                            bag: index.bag(c.keyframe).expect("indexed"),
                        };
                        verify(query, view, &rig, options.min_inliers).map(|v| (c.keyframe, v))
                    })
                    .max_by_key(|(_, v)| v.inliers);
                verify_ms.push(started.elapsed().as_secs_f64() * 1e3);
                if let Some((keyframe, verified)) = confirmed {
                    run.verified += 1;
                    let other = &samples[keyframe.0 as usize];
                    if overlap(&sample, other, camera, false) >= options.correct_overlap {
                        run.verified_right += 1;
                        run.verified_revisits_found += usize::from(revisit);
                        right_inliers.push(verified.inliers);
                        let truth = sample.world_from_camera.inverse() * other.world_from_camera;
                        let error = truth.inverse() * verified.query_from_candidate.to_isometry();
                        translation_errors.push(error.translation.vector.norm());
                        rotation_errors.push(error.rotation.angle().to_degrees());
                    } else {
                        run.wrong_inliers.push(verified.inliers);
                    }
                }
            }
            index.insert(KeyFrameId(k as u32), bag);
            samples.push(sample);
        }
        run.precision = ratio(run.verified_right, run.verified);
        run.recall = ratio(run.verified_revisits_found, run.revisits);
        run.median_query_ms = median(&mut query_ms);
        run.median_verify_ms = median(&mut verify_ms);
        run.right_inliers_min = right_inliers.iter().copied().min();
        run.transform_error_m = percentiles(&mut translation_errors);
        run.transform_error_deg = percentiles(&mut rotation_errors);
        runs.push(run);
    }
    Ok(runs)
}

/// The figures as a table.
pub fn print_table(runs: &[PlacesRun]) {
    println!(
        "robot\tkeyframes\tqueries\trevisits\twords right/answered\twords recall@{VERIFIED_CANDIDATES}\tverified right/all\tprecision\trecall\tinliers wrong / right min\terror m (median, p90, max)\terror deg\tquery ms\tverify ms"
    );
    for r in runs {
        println!(
            "{}\t{}\t{}\t{}\t{}/{}\t{:.3}\t{}/{}\t{:.3}\t{:.3}\t{:?} / {:?}\t{:.3?}\t{:.2?}\t{:.2}\t{:.2}",
            r.robot,
            r.keyframes,
            r.queries,
            r.revisits,
            r.words_right,
            r.words_answered,
            ratio(r.words_revisits_found, r.revisits),
            r.verified_right,
            r.verified,
            r.precision,
            r.recall,
            r.wrong_inliers,
            r.right_inliers_min,
            r.transform_error_m,
            r.transform_error_deg,
            r.median_query_ms,
            r.median_verify_ms
        );
    }
}

/// Median, 90th percentile and largest.
fn percentiles(values: &mut [f64]) -> [f64; 3] {
    values.sort_by(f64::total_cmp);
    let at = |q: f64| {
        values
            .get(((values.len() as f64 * q) as usize).min(values.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0.0)
    };
    [at(0.5), at(0.9), values.last().copied().unwrap_or(0.0)]
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(0.0)
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 {
        0.0
    } else {
        a as f64 / b as f64
    }
}

/// Frames where the camera has moved or turned enough since the last chosen one.
fn keyframes_of(walk: &Walk, options: &PlacesOptions) -> Vec<usize> {
    let mut chosen: Vec<usize> = Vec::new();
    for (i, pose) in walk.world_from_camera.iter().enumerate() {
        let far = chosen.last().is_none_or(|&last| {
            let from = walk.world_from_camera[last];
            let moved = (pose.translation.vector - from.translation.vector).norm();
            let turned = pose.rotation.angle_to(&from.rotation).to_degrees();
            moved >= options.keyframe_step_m || turned >= options.keyframe_turn_deg
        });
        if far {
            chosen.push(i);
        }
    }
    chosen
}

/// The tracker's rig for the simulated camera, with its default settings.
fn rig_of(camera: &Camera) -> Rig {
    let tracker = TrackerConfig::default();
    Rig {
        camera: Pinhole::new(camera.fx, camera.fy, camera.cx, camera.cy),
        width: camera.width,
        height: camera.height,
        bf: camera.fx * tracker.virtual_baseline_m,
        depth_residual: DepthResidual::Disparity,
        close_depth: tracker.close_depth_baselines * tracker.virtual_baseline_m,
        scale_factor: tracker.orb.scale_factor,
        levels: tracker.orb.levels,
    }
}

fn sample_of(
    extractor: &mut OrbExtractor,
    frame: &Frame,
    rig: &Rig,
    camera: &Camera,
    time_s: f64,
    pose: Isometry3<f64>,
) -> anyhow::Result<Sample> {
    let (w, h) = (frame.width, frame.height);
    let mut points = Vec::new();
    let mut depth = Vec::new();
    for y in (GRID / 2..h).step_by(GRID as usize) {
        for x in (GRID / 2..w).step_by(GRID as usize) {
            let z = frame.depth[(y * w + x) as usize];
            depth.push(z);
            if z > 0.0 {
                let ray = camera.ray(f64::from(x), f64::from(y));
                points.push(pose * Point3::from(ray * f64::from(z)));
            }
        }
    }
    let grey = GreyImage::from_pixels(w, h, &frame.grey())?;
    let depth_image = DepthImage {
        width: w,
        height: h,
        data: frame.depth_units(1000.0),
        depth_scale: 1000.0,
        registered: true,
    };
    let extraction = extractor.extract(&grey, Some((&depth_image, rig.bf)))?;
    let keyframe = vsgraphs_slam::Frame::new(0, &extraction, rig);
    Ok(Sample {
        time_s,
        world_from_camera: pose,
        points,
        depth,
        keypoints: keyframe.keypoints,
        descriptors: keyframe.descriptors,
    })
}

/// Share of `a`'s surface points that `b` sees: in its image, in front, not behind what its
/// depth shows there (5 cm and 5 % of the range allowed); if `matchable`, only those it sees
/// from a distance within two pyramid levels of `a`'s (a patch seen more than 1.2² larger or
/// smaller is described on levels whose descriptors differ) and a direction within 60° (where
/// ORB-SLAM stops looking for a point).
fn overlap(a: &Sample, b: &Sample, camera: &Camera, matchable: bool) -> f64 {
    if a.points.is_empty() {
        return 0.0;
    }
    let camera_from_world = b.world_from_camera.inverse();
    let (a_centre, b_centre) = (
        Point3::from(a.world_from_camera.translation.vector),
        Point3::from(b.world_from_camera.translation.vector),
    );
    let columns = camera.width.div_ceil(GRID) as i64;
    let rows = camera.height.div_ceil(GRID) as i64;
    let seen = a
        .points
        .iter()
        .filter(|p| {
            let q = camera_from_world * **p;
            if q.z <= 0.1 {
                return false;
            }
            let u = camera.fx * q.x / q.z + camera.cx;
            let v = camera.fy * q.y / q.z + camera.cy;
            let (c, r) = (
                ((u - f64::from(GRID / 2)) / f64::from(GRID)).round() as i64,
                ((v - f64::from(GRID / 2)) / f64::from(GRID)).round() as i64,
            );
            if !(0..columns).contains(&c) || !(0..rows).contains(&r) {
                return false;
            }
            let there = f64::from(b.depth[(r * columns + c) as usize]);
            if there <= 0.0 || q.z > there + 0.05 + 0.05 * there {
                return false;
            }
            let (from_a, from_b) = (**p - a_centre, **p - b_centre);
            let ratio = from_a.norm() / from_b.norm();
            !matchable
                || (1.0 / MATCHABLE_SCALE..=MATCHABLE_SCALE).contains(&ratio)
                    && from_a.normalize().dot(&from_b.normalize()) >= 0.5
        })
        .count();
    seen as f64 / a.points.len() as f64
}
