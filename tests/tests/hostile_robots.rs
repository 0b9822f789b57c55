//! Hostile robots over real zenoh: a robot that floods the server, one that makes up robot ids,
//! and frames built to make the server allocate far more than they weigh. Each is refused or
//! limited and counted, the server's memory stays within its limits, and a well-behaved robot
//! keeps its pace.
//!
//! Impersonation and eavesdropping are refused by the transport (`secure_transport.rs`); a
//! frame stamped at the end of time, malformed bytes and oversized frames by validation
//! (`bad_input.rs`).

// The heap is watched by a global allocator wrapped around the system's.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use vsgraphs_proto::api::RobotStatus;
use vsgraphs_proto::{encode, keys, DepthEncoding, Message, PixelFormat, RgbdFrame};
use vsgraphs_sdk::robot::now_ns;
use vsgraphs_sdk::Robot;
use vsgraphs_tests::*;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::render;

/// Counts the bytes the process holds on the heap and the most it held since the last reset.
struct Watched;

static HELD: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn held(grown: usize) {
    let now = HELD.fetch_add(grown, Ordering::Relaxed) + grown;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

// SAFETY: every call is passed unchanged to the system allocator; the only additions are
// atomic counters, which neither allocate nor touch the memory.
unsafe impl GlobalAlloc for Watched {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `alloc` is the system allocator's.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            held(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            held(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, layout: Layout) {
        // SAFETY: `p` came from this allocator, which is the system allocator.
        unsafe { System.dealloc(p, layout) };
        HELD.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, p: *mut u8, layout: Layout, size: usize) -> *mut u8 {
        // SAFETY: as for `dealloc`; `size` is the caller's, checked by its contract.
        let moved = unsafe { System.realloc(p, layout, size) };
        if !moved.is_null() {
            HELD.fetch_sub(layout.size(), Ordering::Relaxed);
            held(size);
        }
        moved
    }
}

#[global_allocator]
static ALLOCATOR: Watched = Watched;

/// The tests of this file one at a time, so that the heap each one watches is its own.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// A frame of the D435 looking at a blank wall two metres away.
fn wall_frame(robot_id: &str) -> RgbdFrame {
    let camera = d435();
    let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
    let rendered = render(&camera, &dictionary, &[], 2.0).unwrap();
    let (colour, depth) = encode_rendered(&camera, &rendered);
    RgbdFrame {
        robot_id: robot_id.into(),
        session_id: "s".into(),
        sequence: 0,
        timestamp_ns: now_ns(),
        camera: Some(camera.to_wire()),
        depth_scale: 1000.0,
        colour: Some(colour),
        depth: Some(depth),
        odometry: None,
        imu: vec![],
    }
}

async fn send(robot: &Robot, frame: &RgbdFrame) {
    let frame = frame.clone();
    robot
        .publish(
            now_ns(),
            frame.camera.unwrap(),
            frame.depth_scale,
            frame.colour.unwrap(),
            frame.depth.unwrap(),
        )
        .await
        .unwrap();
}

async fn status(test: &TestServer, robot_id: &str) -> Option<RobotStatus> {
    test.client.robot(robot_id).await.ok()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flooding_robot_is_held_to_its_rate_and_another_keeps_its_pace() {
    let _alone = ONE_AT_A_TIME.lock().await;
    const RATE_HZ: f64 = 20.0;
    const STEADY_FRAMES: u64 = 25;
    let test = TestServer::start_with(|c| c.ingest.max_rate_hz = RATE_HZ).await;
    let steady = test.robot("steady").await;
    let flood = test.robot("flood").await;
    let frame = wall_frame("");

    // The flood: frames as fast as the robot's session takes them, while the steady robot
    // sends one every 200 ms.
    let started = Instant::now();
    let (stop, mut stopped) = tokio::sync::oneshot::channel::<()>();
    let flooding = {
        let frame = frame.clone();
        tokio::spawn(async move {
            let mut sent = 0u64;
            while stopped.try_recv().is_err() {
                send(&flood, &frame).await;
                sent += 1;
                tokio::task::yield_now().await;
            }
            (flood, sent)
        })
    };
    for _ in 0..STEADY_FRAMES {
        send(&steady, &frame).await;
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    stop.send(()).unwrap();
    let (flood, sent) = flooding.await.unwrap();
    let flooded_s = started.elapsed().as_secs_f64();

    let steady_status = wait_for(
        "the steady robot's frames",
        Duration::from_secs(30),
        || async {
            let s = status(&test, "steady").await?;
            (s.frames.processed + s.frames.dropped + s.frames.rejected + s.frames.lost
                == STEADY_FRAMES)
                .then_some(s)
        },
    )
    .await;
    let flood_status = wait_for(
        "the flood accounted for",
        Duration::from_secs(30),
        || async {
            let s = status(&test, "flood").await?;
            let f = &s.frames;
            (f.queued == 0 && f.received == f.processed + f.dropped + f.rejected).then_some(s)
        },
    )
    .await;
    let f = &flood_status.frames;
    let admitted = f.received - f.dropped_over_rate;
    eprintln!(
        "flood: {sent} sent in {flooded_s:.1} s, {} received, {admitted} admitted, {} dropped \
         over the rate, {} dropped by its queue, {} processed, {} lost; steady: {:?}",
        f.received,
        f.dropped_over_rate,
        f.dropped - f.dropped_over_rate,
        f.processed,
        f.lost,
        steady_status.frames
    );
    assert!(f.dropped_over_rate > 0, "the flood outran its rate");
    // A second's worth at once, then the rate (and a second of slack for frames in transit).
    assert!(
        admitted as f64 <= RATE_HZ * (flooded_s + 2.0),
        "{admitted} admitted in {flooded_s:.1} s"
    );
    assert_eq!(f.rejected, 0);
    // Frames the flood's own session could not put on the wire are lost; those dropped over
    // the rate are not.
    assert!(
        f.received + f.lost <= sent,
        "{} received and {} lost of {sent} sent",
        f.received,
        f.lost
    );
    let s = &steady_status.frames;
    assert_eq!(
        (s.processed, s.dropped, s.rejected, s.lost),
        (STEADY_FRAMES, 0, 0, 0)
    );

    flood.close().await.unwrap();
    steady.close().await.unwrap();
    test.server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn made_up_robot_ids_hold_no_place_for_long() {
    let _alone = ONE_AT_A_TIME.lock().await;
    const MAX_ROBOTS: usize = 4;
    // Long enough that the late robot below finds the places still full on a loaded machine.
    const FORGET_AFTER_S: f64 = 10.0;
    let test = TestServer::start_with(|c| {
        c.ingest.max_robots = MAX_ROBOTS;
        c.ingest.forget_after_s = FORGET_AFTER_S;
    })
    .await;
    let frame = wall_frame("");
    let processed = |id: &'static str, count: u64| {
        let test = &test;
        async move {
            wait_for(id, Duration::from_secs(30), || async {
                (status(test, id).await?.frames.processed >= count).then_some(())
            })
            .await
        }
    };
    let steady = test.robot("steady").await;
    send(&steady, &frame).await;
    processed("steady", 1).await;

    // Frames under twenty made-up ids from one zenoh session, without liveliness.
    let mut config = zenoh::Config::default();
    config
        .insert_json5(
            "connect/endpoints",
            &format!("[\"{}\"]", test.zenoh_endpoint),
        )
        .unwrap();
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    let attacker = zenoh::open(config).await.unwrap();
    for n in 0..20 {
        let id = format!("made-up-{n}");
        let mut fake = frame.clone();
        fake.robot_id = id.clone();
        attacker
            .put(keys::frames(&id), fake.encode_to_vec())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
    }
    let health = wait_for(
        "the made-up ids refused",
        Duration::from_secs(30),
        || async {
            let health = test.client.health().await.ok()?;
            (health.frames_on_bad_keys >= 20 - (MAX_ROBOTS as u64 - 1)).then_some(health)
        },
    )
    .await;
    let robots = test.client.robots().await.unwrap();
    eprintln!(
        "{} robots registered, {} frames on ids beyond max_robots",
        robots.len(),
        health.frames_on_bad_keys
    );
    assert_eq!(robots.len(), MAX_ROBOTS, "the places are full");
    assert!(robots.iter().any(|r| r.robot_id == "steady"));

    // The robot already there goes on; a new one finds no place until the made-up ones, never
    // online, are forgotten.
    send(&steady, &frame).await;
    processed("steady", 2).await;
    let late = test.robot("late").await;
    send(&late, &frame).await;
    wait_for(
        "the late robot refused",
        Duration::from_secs(30),
        || async {
            let refused = test.client.health().await.ok()?.frames_on_bad_keys;
            (refused > health.frames_on_bad_keys).then_some(())
        },
    )
    .await;
    let robots = test.client.robots().await.unwrap();
    assert_eq!(robots.len(), MAX_ROBOTS, "{robots:?}");
    assert!(
        !robots.iter().any(|r| r.robot_id == "late"),
        "no place while the made-up ids hold them"
    );
    let forgotten = wait_for(
        "the made-up ids forgotten",
        Duration::from_secs(60),
        || async {
            let robots = test.client.robots().await.ok()?;
            (!robots.iter().any(|r| r.robot_id.starts_with("made-up"))).then_some(robots)
        },
    )
    .await;
    assert!(
        forgotten.iter().any(|r| r.robot_id == "steady"),
        "online robots stay"
    );
    send(&late, &frame).await;
    processed("late", 1).await;

    attacker.close().await.unwrap();
    late.close().await.unwrap();
    steady.close().await.unwrap();
    test.server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_that_would_decode_to_far_more_than_they_weigh_are_refused_unopened() {
    let _alone = ONE_AT_A_TIME.lock().await;
    // Maps in memory: no store commits beside the frames watched.
    let test = TestServer::start_with(|c| c.store.path = Default::default()).await;
    let robot = test.robot("bomber").await;
    let mut good = wall_frame("bomber");
    good.sequence = 1;
    robot.publish_raw(good.encode_to_vec()).await.unwrap();
    let count = |reason: &'static str| {
        let test = &test;
        async move {
            status(test, "bomber")
                .await
                .and_then(|s| s.frames.rejected_by_reason.get(reason).copied())
                .unwrap_or(0)
        }
    };
    wait_for("the first frame", Duration::from_secs(30), || async {
        (status(&test, "bomber").await?.frames.processed == 1).then_some(())
    })
    .await;

    // Images of the largest camera the server takes (4096 × 3072), each a few hundred
    // kilobytes or less, sent as the D435's 640 × 480 images: decoded, they would take 12.6 MB
    // (grey) to 25 MB (depth).
    let (width, height) = (4096u32, 3072u32);
    let pixels = (width * height) as usize;
    let black = vec![0u8; pixels];
    let jpeg = encode::colour_jpeg(&black, width, height, PixelFormat::Mono8, 90).unwrap();
    let zeros = vec![0u16; pixels];
    let png16 = encode::depth(&zeros, width, height, DepthEncoding::Png16).unwrap();
    let rvl = encode::depth(&zeros, width, height, DepthEncoding::Rvl).unwrap();
    drop((black, zeros));
    let mut long_session = good.clone();
    long_session.session_id = "s".repeat(1 << 20);
    let bombs = [
        (
            "a JPEG",
            "size_mismatch",
            RgbdFrame {
                colour: Some(jpeg),
                ..good.clone()
            },
        ),
        (
            "a PNG depth image",
            "size_mismatch",
            RgbdFrame {
                depth: Some(png16),
                ..good.clone()
            },
        ),
        (
            "an RVL depth image",
            "size_mismatch",
            RgbdFrame {
                depth: Some(rvl),
                ..good.clone()
            },
        ),
        ("a session id of a mebibyte", "malformed", long_session),
    ];
    let mut sequence = 100;
    for (what, reason, mut bomb) in bombs {
        let before = count(reason).await;
        sequence += 1;
        bomb.sequence = sequence;
        bomb.timestamp_ns = now_ns();
        let bytes = bomb.encode_to_vec();
        let weight = bytes.len();
        let baseline = HELD.load(Ordering::Relaxed);
        PEAK.store(baseline, Ordering::Relaxed);
        robot.publish_raw(bytes).await.unwrap();
        wait_for(what, Duration::from_secs(30), || async {
            (count(reason).await > before).then_some(())
        })
        .await;
        let grown = PEAK.load(Ordering::Relaxed).saturating_sub(baseline);
        eprintln!("{what}: {weight} bytes on the wire, the heap grew by at most {grown} bytes");
        // The frame's own bytes a few times over (zenoh's buffer, the queue, the decoded
        // message) and the server's ordinary work, far below what decoding would take.
        assert!(
            grown < 4 * weight + (4 << 20),
            "{what} of {weight} bytes grew the heap by {grown} bytes"
        );
    }
    // The robot goes on.
    good.sequence = sequence + 1;
    good.timestamp_ns = now_ns();
    robot.publish_raw(good.encode_to_vec()).await.unwrap();
    wait_for(
        "a good frame after the bombs",
        Duration::from_secs(30),
        || async { (status(&test, "bomber").await?.frames.processed == 2).then_some(()) },
    )
    .await;
    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}
