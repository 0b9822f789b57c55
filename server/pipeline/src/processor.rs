//! One frame's way from bytes to a pose: validation ([`crate::validate`]), image decoding,
//! ArUco detection and marker poses beside ORB feature extraction, then tracking. Runs on a
//! robot's worker thread (or the offline runner's), never on an async runtime; every failure is
//! a [`Rejection`] with a reason code and a readable message.

use crate::config::{load_dictionary, MarkerConfig, TrackingConfig};
use crate::maps::{MapService, Snapshots};
use crate::validate::{self, decode_rejection, reject, FrameHeader, Reason, Rejection};
use std::sync::Arc;
use std::time::{Duration, Instant};
use vsgraphs_proto::api::{DistanceSource, MarkerDetection, MarkerPose};
use vsgraphs_proto::api::{MapView, TrackingState};
use vsgraphs_proto::DepthRegistration;
use vsgraphs_slam::{ExtractedFrame, FrameResult, MarkerSighting, Tracker};
use vsgraphs_vision::aruco::MarkerDetector;
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::decode;
use vsgraphs_vision::dictionary::DictionaryError;
use vsgraphs_vision::marker_search::MarkerSearch;
use vsgraphs_vision::pose::{MarkerPoseEstimate, PoseEstimator};
use vsgraphs_vision::GreyImage;

/// A frame after validation and detection.
#[derive(Debug, Clone)]
pub struct Processed {
    pub session_id: String,
    pub sequence: u64,
    pub timestamp_ns: u64,
    pub image_width: u32,
    pub image_height: u32,
    pub markers: Vec<MarkerDetection>,
    /// Absent when tracking is off.
    pub tracking: Option<FrameTracking>,
    pub processing: Duration,
    /// Parts of it: protobuf and image decoding, and marker detection with pose estimation.
    pub decode: Duration,
    pub detection: Duration,
}

/// What tracking made of a frame.
#[derive(Debug, Clone)]
pub struct FrameTracking {
    pub state: TrackingState,
    /// The tracker's account (absent when the frame could not be tracked at all).
    pub result: Option<FrameResult>,
    /// The Atlas after the frame: maps, and the active map's size.
    pub maps: usize,
    pub keyframes: usize,
    pub map_points: usize,
    /// Marker landmarks of the active map.
    pub markers: usize,
    /// Why the frame could not be tracked, when it is an error rather than a lost track.
    pub error: Option<String>,
    /// The active map's snapshots when the frame changed it (a keyframe was made): its writer
    /// publishes the map as the keyframe left it there, after answering the tracker.
    pub map_snapshots: Option<Snapshots>,
    /// The snapshots of the maps the robot's maps were merged into, by the robot's index of
    /// each (see [`FrameResult::followed`]).
    pub followed_snapshots: Vec<(usize, Snapshots)>,
}

/// Frame processing state of one worker thread (OpenCV objects are per thread).
pub struct FrameProcessor {
    detector: MarkerDetector,
    /// Where the robot's markers are searched for: the whole image, or around those it saw.
    search: MarkerSearch,
    settings: MarkerConfig,
    max_frame_bytes: usize,
    /// Pose estimation is set up per camera model; robots rarely change theirs.
    estimator: Option<PoseEstimator>,
    /// The robot's camera tracking, when enabled.
    tracker: Option<Tracker>,
    /// Where the robot's maps live.
    maps: MapService,
}

impl FrameProcessor {
    /// Frame processing for one robot, whose maps `maps` holds.
    pub fn new(
        settings: &MarkerConfig,
        tracking: &TrackingConfig,
        max_frame_bytes: usize,
        maps: MapService,
    ) -> Result<Self, SetupError> {
        let dictionary = load_dictionary(settings)?;
        let mut detector = MarkerDetector::new(dictionary, settings.corner_refinement)?;
        detector.set_threshold_windows(settings.threshold_windows);
        let tracker = if tracking.enabled {
            Some(Tracker::new(tracking.tracker())?)
        } else {
            None
        };
        Ok(Self {
            detector,
            search: MarkerSearch::new(settings.full_search_every),
            settings: settings.clone(),
            max_frame_bytes,
            estimator: None,
            tracker,
            maps,
        })
    }

    /// Lands the active map's pending work (the last local BA), so that the maps are final:
    /// for the end of an offline run.
    pub fn flush_tracking(&mut self) -> Result<(), vsgraphs_slam::TrackError> {
        match self.tracker.as_mut() {
            Some(tracker) => tracker.flush(&mut self.maps),
            None => Ok(()),
        }
    }

    /// The latest snapshot of each of the robot's maps, in the robot's order (the last one of a
    /// map merged since the robot's last frame).
    pub fn map_views(&self) -> Vec<Arc<MapView>> {
        let Some(tracker) = &self.tracker else {
            return Vec::new();
        };
        tracker
            .maps()
            .iter()
            .filter_map(|m| self.maps.last_snapshot(m.id()))
            .collect()
    }

    /// The robot's tracker, when tracking is on.
    pub fn tracker(&self) -> Option<&Tracker> {
        self.tracker.as_ref()
    }

    /// Validates, decodes and detects. `previous` is the last accepted frame of the robot.
    pub fn process(
        &mut self,
        robot_id: &str,
        bytes: &[u8],
        previous: Option<&FrameHeader>,
    ) -> Result<Processed, Rejection> {
        let started = Instant::now();
        let frame = validate::parse(robot_id, bytes, self.max_frame_bytes)?;
        validate::check_order(&frame, previous)?;
        let sequence = Some(frame.sequence);
        let wire_camera = frame.camera.as_ref().expect("checked by parse");
        let camera = PinholeCamera::from_wire(wire_camera)
            .map_err(|e| reject(Reason::BadCamera, e.to_string(), sequence))?;
        let colour = frame.colour.as_ref().expect("checked by parse");
        let grey = decode::colour_to_grey(colour, camera.width, camera.height)
            .map_err(|e| decode_rejection(e, Reason::ColourDecode, sequence))?;
        let depth_wire = frame.depth.as_ref().expect("checked by parse");
        let mut depth = decode::depth(
            depth_wire.encoding,
            &depth_wire.data,
            camera.width,
            camera.height,
            frame.depth_scale,
        )
        .map_err(|e| decode_rejection(e, Reason::DepthDecode, sequence))?;
        // Unknown values (a newer robot) are taken as registered, as unspecified is.
        depth.registered = depth_wire.registration() != DepthRegistration::Unregistered;
        // Decoding: the protobuf, the colour image and the depth image.
        let decode = started.elapsed();

        // Markers are followed within a session; frames skipped since the last one (by the
        // robot, or dropped here) count as frames passed.
        let frames_passed = previous
            .filter(|p| p.session_id == frame.session_id)
            .map(|p| frame.sequence.saturating_sub(p.sequence));
        if frames_passed.is_none() {
            self.search.restart();
        }
        let frames_passed = u32::try_from(frames_passed.unwrap_or(1)).unwrap_or(u32::MAX);
        // Markers are detected on a second thread while this one extracts the frame's
        // features (unless `beside_features` is off): both only read the image, and together
        // they are most of a frame's work.
        let Self {
            detector,
            search,
            settings,
            estimator,
            tracker,
            maps,
            ..
        } = self;
        let beside_features = settings.beside_features;
        let mut detect = || {
            let started = Instant::now();
            let found = detect_markers(
                detector,
                (search, frames_passed),
                estimator,
                settings,
                &camera,
                &grey,
                &depth,
            );
            (found, started.elapsed())
        };
        let mut extract_features = || {
            tracker
                .as_mut()
                .map(|t| extract(t, &camera, frame.timestamp_ns, &grey, &depth))
        };
        let (markers, extracted) = if beside_features {
            std::thread::scope(|scope| {
                let markers = scope.spawn(detect);
                let extracted = extract_features();
                let markers = markers
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                (markers, extracted)
            })
        } else {
            let extracted = extract_features();
            (detect(), extracted)
        };
        let ((markers, sightings), detection) = match markers {
            (Ok(found), elapsed) => (found, elapsed),
            (Err((reason, e)), _) => return Err(reject(reason, e, sequence)),
        };
        let tracking = tracker.as_mut().zip(extracted).map(|(tracker, extracted)| {
            if previous.is_some_and(|p| p.session_id != frame.session_id) {
                tracker.restart();
            }
            track(tracker, maps, extracted, sightings)
        });
        Ok(Processed {
            session_id: frame.session_id,
            sequence: frame.sequence,
            timestamp_ns: frame.timestamp_ns,
            image_width: wire_camera.width,
            image_height: wire_camera.height,
            markers,
            tracking,
            processing: started.elapsed(),
            decode,
            detection,
        })
    }
}

/// Why frame processing could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error(transparent)]
    Dictionary(#[from] DictionaryError),
    #[error("tracking: {0}")]
    Tracking(#[from] vsgraphs_slam::TrackError),
}

impl From<vsgraphs_vision::CvError> for SetupError {
    fn from(e: vsgraphs_vision::CvError) -> Self {
        SetupError::Dictionary(DictionaryError::from(e))
    }
}

/// Detects the frame's markers and estimates their poses; the estimator is set up again when
/// the camera changes. A pose that cannot be computed leaves its detection without one.
fn detect_markers(
    detector: &mut MarkerDetector,
    (search, frames_passed): (&mut MarkerSearch, u32),
    estimator: &mut Option<PoseEstimator>,
    settings: &MarkerConfig,
    camera: &PinholeCamera,
    grey: &GreyImage,
    depth: &vsgraphs_vision::depth::DepthImage,
) -> Result<(Vec<MarkerDetection>, Vec<MarkerSighting>), (Reason, String)> {
    let detections = search
        .detect(detector, grey, frames_passed)
        .map_err(|e| (Reason::Detection, e.to_string()))?;
    if estimator.as_ref().is_none_or(|e| e.camera() != camera) {
        let made = PoseEstimator::new(camera.clone(), settings.side_m);
        *estimator = Some(made.map_err(|e| (Reason::BadCamera, e.to_string()))?);
    }
    let estimator = estimator.as_ref().expect("set above");
    let depth_check = settings
        .depth_refinement
        .then_some((depth, settings.depth_agreement));
    let mut markers = Vec::with_capacity(detections.len());
    let mut sightings = Vec::with_capacity(detections.len());
    for detection in detections {
        let estimate = estimator.estimate(&detection, depth_check).ok();
        sightings.push(MarkerSighting::from_detection(
            &detection,
            settings.side_m,
            estimate.as_ref(),
        ));
        markers.push(MarkerDetection {
            id: detection.id,
            corners_px: detection.corners,
            pose: estimate.as_ref().map(marker_pose),
        });
    }
    Ok((markers, sightings))
}

/// Tracking's part of a frame before its markers are known. Lens distortion is refused:
/// keypoints are not undistorted yet, and tracking a distorted image as if it were rectified
/// would give wrong poses, not no pose.
// One per frame, on the stack for a moment: boxing the large variant would buy nothing.
#[allow(clippy::large_enum_variant)]
enum Extracted {
    Features(Result<ExtractedFrame, vsgraphs_slam::TrackError>),
    UnsupportedCamera,
}

/// Extracts the frame's features for tracking (see [`Extracted`]).
fn extract(
    tracker: &mut Tracker,
    camera: &PinholeCamera,
    timestamp_ns: u64,
    grey: &GreyImage,
    depth: &vsgraphs_vision::depth::DepthImage,
) -> Extracted {
    if !camera.is_undistorted() {
        return Extracted::UnsupportedCamera;
    }
    let pinhole = vsgraphs_slam::Pinhole::new(camera.fx, camera.fy, camera.cx, camera.cy);
    Extracted::Features(tracker.extract(timestamp_ns, &pinhole, grey, depth))
}

/// Tracks one decoded frame whose features are extracted; `maps` writes the robot's maps.
fn track(
    tracker: &mut Tracker,
    maps: &mut MapService,
    extracted: Extracted,
    sightings: Vec<MarkerSighting>,
) -> FrameTracking {
    let summary =
        |tracker: &Tracker, maps: &MapService, state, result: Option<FrameResult>, error| {
            let active = tracker.active_map();
            let (keyframes, map_points, markers) = active.map_or((0, 0, 0), |(_, m)| {
                let map = m.read();
                (map.live_keyframes(), map.live_points(), map.markers.len())
            });
            // A keyframe changed the map (its writer publishes the map as it left it), or the
            // robot moved into the map its own was merged into, or relocalised in another.
            let changed = result
                .as_ref()
                .is_some_and(|r| r.keyframe.is_some() || !r.followed.is_empty() || r.joined);
            let map_snapshots = active
                .filter(|_| changed)
                .and_then(|(_, m)| maps.snapshots(m.id()));
            let followed_snapshots = result
                .iter()
                .flat_map(|r| &r.followed)
                .filter_map(|f| Some((f.index, maps.snapshots(f.into)?)))
                .collect();
            FrameTracking {
                state,
                result,
                maps: tracker.maps().len(),
                keyframes,
                map_points,
                markers,
                error,
                map_snapshots,
                followed_snapshots,
            }
        };
    let extracted = match extracted {
        Extracted::Features(extracted) => extracted,
        Extracted::UnsupportedCamera => {
            return summary(tracker, maps, TrackingState::UnsupportedCamera, None, None)
        }
    };
    // On an error the frame has no pose (it counts as untracked); the state is the tracker's.
    let tracked =
        extracted.and_then(|extracted| tracker.track_extracted(maps, extracted, sightings));
    let (result, error) = match tracked {
        Ok(result) => (Some(result), None),
        Err(e) => (None, Some(e.to_string())),
    };
    // A keyframe may have mapped a marker another map holds, or show a place another map
    // shows: the maps may be one now. The robot of a map merged away follows it at its next
    // frame.
    if let (Some(keyframe), Some((_, map))) = (
        result.as_ref().and_then(|r| r.keyframe),
        tracker.active_map(),
    ) {
        maps.look_for_merges(map.id(), keyframe);
    }
    let state = match tracker.state() {
        vsgraphs_slam::TrackingState::Initialising => TrackingState::Initialising,
        vsgraphs_slam::TrackingState::Tracking => TrackingState::Tracking,
        vsgraphs_slam::TrackingState::Lost => TrackingState::Lost,
    };
    summary(tracker, maps, state, result, error)
}

/// A marker's pose estimate as the API reports it.
pub fn marker_pose(estimate: &MarkerPoseEstimate) -> MarkerPose {
    let q = estimate.camera_from_marker.rotation.coords;
    let t = estimate.camera_from_marker.translation.vector;
    MarkerPose {
        translation_m: [t.x, t.y, t.z],
        rotation_xyzw: [q.x, q.y, q.z, q.w],
        reprojection_error_px: estimate.reprojection_error_px,
        distance_source: if estimate.used_depth {
            DistanceSource::Depth
        } else {
            DistanceSource::Corners
        },
        depth_distance_m: estimate.depth_distance_m,
        corners_distance_m: estimate.corners_distance_m,
    }
}
