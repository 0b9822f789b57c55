//! A robot that walks the same route again and again (a patrol) maps nothing new after the
//! first round: its map, and so the server's memory, stops growing with time. seq06's first
//! frames are played three times in one session, each round after a jump back to the start (as
//! the soak's robots loop their walks); the map's keyframes, points and loops after the second
//! and third rounds are those after the first.

use vsgraphs_pipeline::offline::{self, FrameSource, OfflineFrame};
use vsgraphs_pipeline::PipelineConfig;
use vsgraphs_proto::DepthEncoding;
use vsgraphs_sim::sequence::render_frame;
use vsgraphs_sim::wire::{camera_model, encode_frame, DEPTH_SCALE};
use vsgraphs_tests::SimulatedSite;

/// Frames of a round: the walk leaves its start and turns, so a round sees a room from
/// several sides.
const ROUND: usize = 200;
const ROUNDS: usize = 3;

#[test]
fn a_walk_played_again_adds_nothing_to_its_map() {
    let site = SimulatedSite::builtin("seq06");
    let walk = site.scenario.walks().unwrap().remove(0);
    let renderer = &site.renderer;
    let frames: Vec<_> = (0..ROUND)
        .map(|i| encode_frame(&render_frame(renderer, &walk, i), 90, DepthEncoding::Rvl).unwrap())
        .collect();
    let period_ns = (walk.times[1] - walk.times[0]) * 1e9;
    // Round r's frame i, stamped on from the round before (a second's gap at each jump).
    let played = (0..ROUNDS).flat_map(|round| {
        frames.iter().enumerate().map(move |(i, (colour, depth))| {
            let at = (round * (ROUND + 30) + i) as f64 * period_ns;
            Ok(OfflineFrame {
                timestamp_ns: at.round() as u64,
                colour: colour.clone(),
                depth: depth.clone(),
                session: 0,
            })
        })
    });
    let config = PipelineConfig::default();
    let service = vsgraphs_eval::scenario::service_for(&config, None);
    let camera = camera_model(renderer);
    let source = FrameSource {
        camera: &camera,
        depth_scale: DEPTH_SCALE,
        total: ROUND * ROUNDS,
        dictionary: None,
        maps: Some(&service),
    };
    // (keyframes, points, loops) of every map at the end of each round.
    let mut sizes = Vec::new();
    let (summary, _) = offline::run_frames(&config, source, played, |done, _| {
        if done % ROUND == 0 {
            let views: Vec<_> = service.all().into_iter().map(|(_, s)| s.latest()).collect();
            sizes.push(
                views
                    .iter()
                    .map(|v| (v.keyframe_count, v.point_count, v.loop_count))
                    .collect::<Vec<_>>(),
            );
        }
    })
    .unwrap();
    eprintln!(
        "{} frames, {} tracked, maps {}; keyframes, points and loops per round: {sizes:?}",
        summary.frames, summary.tracked, summary.maps
    );
    assert_eq!(sizes.len(), ROUNDS);
    assert_eq!(sizes[0].len(), 1, "one map after the first round");
    assert!(
        sizes[0][0].0 >= 10,
        "the first round maps the place: {sizes:?}"
    );
    // Each jump back costs at most the frame it lands on (relocalised on the next).
    assert!(
        summary.tracked + ROUNDS > summary.frames,
        "{} of {} tracked",
        summary.tracked,
        summary.frames
    );
    for (round, size) in sizes.iter().enumerate().skip(1) {
        assert_eq!(size, &sizes[0], "the map after round {}", round + 1);
    }
}
