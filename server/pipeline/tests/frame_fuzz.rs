//! Frames as a hostile or broken robot could send them, through the whole frame pipeline
//! (protobuf, header checks, JPEG, PNG, raw colour, RVL, PNG16 and raw depth, marker
//! detection, tracking): valid frames of every encoding, then changed field by field (sizes,
//! encodings, numbers, strings, repeated fields) and byte by byte. Every frame is processed or
//! refused with a reason; none panics, and none makes the pipeline allocate beyond what the
//! frame's own size and its camera's image justify.
//!
//! `PROPTEST_CASES` sets the number of frames (CI runs the default; BENCHMARKS.md has a longer
//! run).
#![allow(unsafe_code)]

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use proptest::prelude::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::Instant;
use vsgraphs_pipeline::config::{MarkerConfig, TrackingConfig, DEFAULT_MAX_FRAME_BYTES};
use vsgraphs_pipeline::validate::{FrameHeader, MAX_MESSAGE_CHARS};
use vsgraphs_pipeline::{FrameProcessor, MapService};
use vsgraphs_proto::v1::{ImuSample, OdometryPrior};
use vsgraphs_proto::{
    encode, png16, ColourEncoding, DepthEncoding, Message, PixelFormat, RgbdFrame,
};
use vsgraphs_vision::camera::PinholeCamera;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::{render, PlacedMarker};

/// The system allocator, noting the largest single allocation made on a thread while it is
/// `WATCHING`: the robot's worker, where a frame is decoded, its markers detected (not beside
/// it, in this test) and tracked. The map's own thread, whose allocations follow the map's
/// growth rather than any one frame, is not watched.
struct Watched;

thread_local! {
    static WATCHING: Cell<bool> = const { Cell::new(false) };
}
static LARGEST: AtomicUsize = AtomicUsize::new(0);

fn note(size: usize) {
    if WATCHING.with(Cell::get) {
        LARGEST.fetch_max(size, Ordering::Relaxed);
    }
}

// SAFETY: every call is passed unchanged to the system allocator; the only addition is an
// atomic maximum, which neither allocates nor touches the memory.
unsafe impl GlobalAlloc for Watched {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        // SAFETY: the caller's contract for `alloc` is the system allocator's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        // SAFETY: as for `alloc`.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from this allocator, which is the system allocator.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        // SAFETY: as for `dealloc`; `new_size` is the caller's, checked by its contract.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Watched = Watched;

const WIDTH: u32 = 160;
const HEIGHT: u32 = 120;
const ROBOT: &str = "fuzz";

/// Valid frames of a marker on a wall, one per colour and depth encoding.
fn valid_frames() -> &'static [RgbdFrame] {
    static FRAMES: OnceLock<Vec<RgbdFrame>> = OnceLock::new();
    FRAMES.get_or_init(|| {
        let camera = PinholeCamera::new(WIDTH, HEIGHT, [150.0, 150.0, 80.0, 60.0], vec![]).unwrap();
        let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
        let marker = PlacedMarker {
            id: 7,
            side_m: 0.15,
            camera_from_marker: Isometry3::from_parts(
                Translation3::new(0.0, 0.0, 0.8),
                UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
            ),
        };
        let rendered = render(&camera, &dictionary, &[marker], 1.5).unwrap();
        let grey = rendered.grey_bytes();
        let rgb: Vec<u8> = grey.iter().flat_map(|&g| [g, g, g]).collect();
        let grey16: Vec<u16> = grey.iter().map(|&g| u16::from(g) << 8).collect();
        let colours = [
            encode::colour_jpeg(grey, WIDTH, HEIGHT, PixelFormat::Mono8, 90).unwrap(),
            encode::colour_jpeg(&rgb, WIDTH, HEIGHT, PixelFormat::Rgb8, 80).unwrap(),
            encode::colour_raw(&rgb, WIDTH, HEIGHT, PixelFormat::Bgr8).unwrap(),
            encode::colour_raw(grey, WIDTH, HEIGHT, PixelFormat::Mono8).unwrap(),
            vsgraphs_proto::ColourImage {
                encoding: ColourEncoding::Png as i32,
                pixel_format: PixelFormat::Mono8 as i32,
                data: png16::encode(&grey16, WIDTH, HEIGHT).unwrap(),
            },
        ];
        let depths = [
            DepthEncoding::Rvl,
            DepthEncoding::Raw16,
            DepthEncoding::Png16,
        ]
        .map(|e| encode::depth(&rendered.depth_mm, WIDTH, HEIGHT, e).unwrap());
        let mut frames = Vec::new();
        for colour in &colours {
            for depth in &depths {
                frames.push(RgbdFrame {
                    robot_id: ROBOT.into(),
                    session_id: "s".into(),
                    sequence: 0,
                    timestamp_ns: 1,
                    camera: Some(camera.to_wire()),
                    depth_scale: 1000.0,
                    colour: Some(colour.clone()),
                    depth: Some(depth.clone()),
                    odometry: None,
                    imu: vec![],
                });
            }
        }
        frames
    })
}

/// A change to a frame's fields, each of which a robot controls.
#[derive(Debug, Clone)]
enum Edit {
    CameraSize(u32, u32),
    Intrinsics([f64; 4]),
    Distortion(Vec<f64>),
    DepthScale(f64),
    ColourEncoding(i32, i32),
    DepthEncoding(i32),
    /// Bytes of the colour (true) or depth image changed: (offset, xor) pairs.
    ImageBytes(bool, Vec<(usize, u8)>),
    /// The colour (true) or depth image cut to this fraction of its length.
    ImageCut(bool, u8),
    /// The size an image's header states (JPEG frame header, PNG IHDR, RVL header).
    HeaderSize(bool, u16, u16),
    ImageReplaced(bool, Vec<u8>),
    Strings(String, String),
    Stamps(u64, u64),
    /// Empty IMU samples (two bytes each on the wire).
    EmptyImu(usize),
    LongImu(usize),
    Odometry(Vec<f64>, Vec<f64>),
    Missing(u8),
}

fn any_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => -2000.0..2000.0f64,
        1 => Just(0.0),
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => any::<f64>(),
    ]
}

fn any_side() -> impl Strategy<Value = u32> {
    prop_oneof![
        Just(WIDTH),
        Just(HEIGHT),
        0u32..4,
        0u32..400,
        Just(8192),
        Just(65535),
        any::<u32>(),
    ]
}

fn edit() -> impl Strategy<Value = Edit> {
    let colour_or_depth = any::<bool>();
    prop_oneof![
        (any_side(), any_side()).prop_map(|(w, h)| Edit::CameraSize(w, h)),
        prop::array::uniform4(any_f64()).prop_map(Edit::Intrinsics),
        prop::collection::vec(any_f64(), 0..40).prop_map(Edit::Distortion),
        any_f64().prop_map(Edit::DepthScale),
        (-2i32..6, -2i32..6).prop_map(|(e, f)| Edit::ColourEncoding(e, f)),
        (-2i32..6).prop_map(Edit::DepthEncoding),
        (
            colour_or_depth,
            prop::collection::vec((any::<usize>(), 1u8..=255), 1..8)
        )
            .prop_map(|(c, flips)| Edit::ImageBytes(c, flips)),
        (colour_or_depth, any::<u8>()).prop_map(|(c, f)| Edit::ImageCut(c, f)),
        (
            colour_or_depth,
            prop_oneof![Just(0u16), 1u16..400, any::<u16>()],
            prop_oneof![Just(0u16), 1u16..400, any::<u16>()]
        )
            .prop_map(|(c, w, h)| Edit::HeaderSize(c, w, h)),
        (colour_or_depth, prop::collection::vec(any::<u8>(), 0..64))
            .prop_map(|(c, bytes)| Edit::ImageReplaced(c, bytes)),
        (".{0,40}", prop_oneof![".{0,8}", ".{200,400}"])
            .prop_map(|(robot, session)| Edit::Strings(robot, session)),
        (any::<u64>(), any::<u64>()).prop_map(|(s, t)| Edit::Stamps(s, t)),
        prop_oneof![0usize..100, 100_000usize..400_000].prop_map(Edit::EmptyImu),
        (0usize..5000).prop_map(Edit::LongImu),
        (
            prop::collection::vec(any_f64(), 0..9),
            prop::collection::vec(any_f64(), 0..9)
        )
            .prop_map(|(t, r)| Edit::Odometry(t, r)),
        (0u8..3).prop_map(Edit::Missing),
    ]
}

/// Where a JPEG's frame header states its height and width: after the first SOF marker.
fn jpeg_size_at(data: &[u8]) -> Option<usize> {
    data.windows(2)
        .position(|w| w[0] == 0xFF && matches!(w[1], 0xC0..=0xC3))
        .map(|at| at + 5)
}

fn apply(frame: &mut RgbdFrame, edit: Edit) {
    let camera = frame.camera.get_or_insert_with(Default::default);
    match edit {
        Edit::CameraSize(w, h) => (camera.width, camera.height) = (w, h),
        Edit::Intrinsics([fx, fy, cx, cy]) => {
            (camera.fx, camera.fy, camera.cx, camera.cy) = (fx, fy, cx, cy)
        }
        Edit::Distortion(d) => camera.distortion = d,
        Edit::DepthScale(s) => frame.depth_scale = s,
        Edit::ColourEncoding(e, f) => {
            let colour = frame.colour.get_or_insert_with(Default::default);
            (colour.encoding, colour.pixel_format) = (e, f);
        }
        Edit::DepthEncoding(e) => frame.depth.get_or_insert_with(Default::default).encoding = e,
        Edit::ImageBytes(colour, flips) => {
            let data = image(frame, colour);
            if !data.is_empty() {
                let n = data.len();
                for (at, xor) in flips {
                    data[at % n] ^= xor;
                }
            }
        }
        Edit::ImageCut(colour, fraction) => {
            let data = image(frame, colour);
            data.truncate(data.len() * usize::from(fraction) / 256);
        }
        Edit::HeaderSize(colour, w, h) => {
            let data = image(frame, colour);
            let (w4, h4) = (u32::from(w).to_be_bytes(), u32::from(h).to_be_bytes());
            if data.starts_with(&[0xFF, 0xD8]) {
                if let Some(at) = jpeg_size_at(data).filter(|&at| at + 4 <= data.len()) {
                    data[at..at + 2].copy_from_slice(&h.to_be_bytes());
                    data[at + 2..at + 4].copy_from_slice(&w.to_be_bytes());
                }
            } else if data.starts_with(&[0x89, b'P']) && data.len() >= 24 {
                data[16..20].copy_from_slice(&w4);
                data[20..24].copy_from_slice(&h4);
            } else if data.len() >= 12 {
                // RVL: magic, then width and height little-endian.
                data[4..8].copy_from_slice(&u32::from(w).to_le_bytes());
                data[8..12].copy_from_slice(&u32::from(h).to_le_bytes());
            }
        }
        Edit::ImageReplaced(colour, bytes) => *image(frame, colour) = bytes,
        Edit::Strings(robot, session) => {
            if !robot.is_empty() {
                frame.robot_id = robot;
            }
            frame.session_id = session;
        }
        Edit::Stamps(sequence, stamp) => (frame.sequence, frame.timestamp_ns) = (sequence, stamp),
        Edit::EmptyImu(n) => frame.imu = vec![ImuSample::default(); n],
        Edit::LongImu(n) => {
            frame.imu = vec![ImuSample {
                timestamp_ns: 1,
                angular_velocity: vec![0.5; n],
                linear_acceleration: vec![9.8; n],
            }]
        }
        Edit::Odometry(translation, rotation_xyzw) => {
            frame.odometry = Some(OdometryPrior {
                translation,
                rotation_xyzw,
                timestamp_ns: 1,
            })
        }
        Edit::Missing(0) => frame.camera = None,
        Edit::Missing(1) => frame.colour = None,
        Edit::Missing(_) => frame.depth = None,
    }
}

fn image(frame: &mut RgbdFrame, colour: bool) -> &mut Vec<u8> {
    if colour {
        &mut frame.colour.get_or_insert_with(Default::default).data
    } else {
        &mut frame.depth.get_or_insert_with(Default::default).data
    }
}

/// The pipeline of one robot, kept from frame to frame as a server keeps it.
struct Robot {
    processor: FrameProcessor,
    previous: Option<FrameHeader>,
}

fn robot() -> &'static Mutex<Robot> {
    static ROBOT: OnceLock<Mutex<Robot>> = OnceLock::new();
    ROBOT.get_or_init(|| {
        let markers = MarkerConfig {
            beside_features: false,
            ..MarkerConfig::default()
        };
        let processor = FrameProcessor::new(
            &markers,
            &TrackingConfig::default(),
            DEFAULT_MAX_FRAME_BYTES,
            MapService::new(),
        )
        .unwrap();
        Mutex::new(Robot {
            processor,
            previous: None,
        })
    })
}

/// What a frame may cost in any one allocation: a copy of its bytes, four bytes per pixel of
/// the image its camera states (within the camera's limits, where the frame is refused
/// otherwise), and a fixed mebibyte for the pipeline's own work.
fn budget(bytes: &[u8]) -> usize {
    let pixels = RgbdFrame::decode(bytes)
        .ok()
        .and_then(|f| f.camera)
        .map_or(0, |c| u64::from(c.width) * u64::from(c.height))
        .min(vsgraphs_vision::camera::MAX_PIXELS);
    bytes.len() + 4 * pixels as usize + (1 << 20)
}

fn cases() -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(2000)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(), ..ProptestConfig::default() })]

    #[test]
    fn any_frame_is_processed_or_refused_within_its_budget(
        base in 0usize..15,
        edits in prop::collection::vec(edit(), 0..4),
        flips in prop_oneof![
            3 => Just(vec![]),
            1 => prop::collection::vec((any::<usize>(), 1u8..=255), 1..6)
        ],
        cut in prop_oneof![4 => Just(None), 1 => any::<u16>().prop_map(Some)],
        follows in any::<bool>(),
    ) {
        let mut robot = robot().lock().unwrap_or_else(|p| p.into_inner());
        let previous = if follows { robot.previous.clone() } else { None };
        let mut frame = valid_frames()[base].clone();
        // Unchanged, the frame follows the last one accepted, as a robot's next frame would.
        if let Some(previous) = &robot.previous {
            frame.session_id = previous.session_id.clone();
            frame.sequence = previous.sequence.wrapping_add(1);
            frame.timestamp_ns = previous.timestamp_ns.saturating_add(33_000_000);
        }
        for edit in edits {
            apply(&mut frame, edit);
        }
        let mut bytes = frame.encode_to_vec();
        let n = bytes.len();
        for (at, xor) in flips {
            bytes[at % n] ^= xor;
        }
        if let Some(cut) = cut {
            bytes.truncate(usize::from(cut) % (n + 1));
        }

        LARGEST.store(0, Ordering::Relaxed);
        WATCHING.set(true);
        let result = robot.processor.process(ROBOT, &bytes, previous.as_ref());
        WATCHING.set(false);
        let largest = LARGEST.load(Ordering::Relaxed);

        prop_assert!(
            largest <= budget(&bytes),
            "a frame of {} bytes made an allocation of {} bytes (budget {})",
            bytes.len(), largest, budget(&bytes)
        );
        match result {
            Ok(processed) => {
                let camera = frame.camera.as_ref().unwrap();
                prop_assert_eq!(
                    (processed.image_width, processed.image_height),
                    (camera.width, camera.height)
                );
                robot.previous = Some(FrameHeader {
                    session_id: processed.session_id,
                    sequence: processed.sequence,
                    timestamp_ns: processed.timestamp_ns,
                    accepted: Some(Instant::now()),
                });
            }
            Err(rejection) => {
                prop_assert!(!rejection.reason.code().is_empty());
                prop_assert!(rejection.message.chars().count() <= MAX_MESSAGE_CHARS + 1);
            }
        }
    }
}

/// The valid frames are processed: the fuzzing starts from frames that go all the way through.
#[test]
fn every_valid_frame_is_processed_with_its_marker() {
    let mut robot = robot().lock().unwrap_or_else(|p| p.into_inner());
    for (i, frame) in valid_frames().iter().enumerate() {
        let mut frame = frame.clone();
        frame.session_id = "valid".into();
        frame.timestamp_ns = 1_000 + i as u64;
        let processed = robot
            .processor
            .process(ROBOT, &frame.encode_to_vec(), None)
            .unwrap_or_else(|e| panic!("frame {i}: {e:?}"));
        let ids: Vec<i32> = processed.markers.iter().map(|m| m.id).collect();
        assert_eq!(ids, [7], "frame {i}");
    }
}
