//! Place recognition among a map's keyframes by their visual words: an inverted index from
//! each word to the keyframes holding it, so a query scores only keyframes that share words
//! with it. Candidates are what ORB-SLAM's loop and relocalisation searches return, with our
//! own code: keyframes sharing at least 80 % of the best count of common words, scoring at
//! least what the query scores against keyframes that certainly see its place (so the bar
//! follows how alike the building's views are, not a constant), then summed with their
//! neighbours so that a place many keyframes agree on wins over one lucky keyframe.
//!
//! A candidate is only a hypothesis: whoever uses it verifies it geometrically first.

use crate::frame::{hamming, Descriptor, Frame, Keypoint, Rig};
use crate::ids::KeyFrameId;
use crate::rigid::{agrees, ransac_rigid, Pair};
use vsgraphs_optim::pose_only::{optimise_pose, PoseObservation, PoseOnlyOptions};
use vsgraphs_optim::Se3;
use vsgraphs_vision::vocabulary::{score, BagOfWords, Vocabulary};

/// The tree level whose nodes group a bag's features for matching: the root's grandchildren
/// (100 nodes of the shipped vocabulary, some ten features of an image in each).
pub const GROUPING_LEVEL: usize = 2;

/// A frame's bag of words in the shipped vocabulary.
pub fn bag_of(frame: &Frame) -> BagOfWords {
    Vocabulary::builtin().transform(&frame.descriptors, GROUPING_LEVEL)
}

/// Share of the best count of common words a keyframe needs to be scored at all.
const COMMON_WORDS_SHARE: f32 = 0.8;
/// Share of the best group's summed score another group needs to be returned as well.
const GROUP_SHARE: f32 = 0.75;

/// Descriptor matches of verification: at most this many bits apart (ORB-SLAM's strict
/// threshold) …
const MATCH_DISTANCE: u32 = 50;
/// … and clearly nearer than the second nearest in the same node.
const MATCH_RATIO: f32 = 0.75;
/// Matches a confirmed candidate's transform must explain. Over the simulated walks (seven
/// scenarios, three texture seeds each; BENCHMARKS.md) the fewest a right candidate had at 20
/// was 20 and one wrong candidate had 21; at 30 none was wrong and recall fell from 0.47 to
/// 0.45. A false loop costs more than a missed one.
pub const MIN_INLIERS: usize = 30;
/// RANSAC samples of three matches.
const RANSAC_SAMPLES: usize = 300;
const RANSAC_SEED: u64 = 0x5EED_1005;

/// The inverted index of one map's keyframes.
#[derive(Clone, Debug, Default)]
pub struct PlaceIndex {
    /// Keyframes holding each word, in insertion order.
    pub(crate) by_word: Vec<Vec<KeyFrameId>>,
    /// Each keyframe's bag, by id (`None`: not indexed or removed).
    pub(crate) bags: Vec<Option<BagOfWords>>,
}

/// A keyframe that may show the queried place.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaceCandidate {
    pub keyframe: KeyFrameId,
    /// Its own similarity to the query, in [0, 1].
    pub score: f32,
    /// The sum over it and its neighbours among the scored keyframes.
    pub group_score: f32,
}

impl PlaceIndex {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn insert(&mut self, keyframe: KeyFrameId, bag: BagOfWords) {
        self.remove(keyframe);
        for &(word, _) in &bag.words {
            let word = word as usize;
            if self.by_word.len() <= word {
                self.by_word.resize_with(word + 1, Vec::new);
            }
            self.by_word[word].push(keyframe);
        }
        let at = keyframe.0 as usize;
        if self.bags.len() <= at {
            self.bags.resize_with(at + 1, || None);
        }
        self.bags[at] = Some(bag);
    }

    /// Forgets a keyframe (culled, or merged away).
    pub fn remove(&mut self, keyframe: KeyFrameId) {
        let Some(bag) = self
            .bags
            .get_mut(keyframe.0 as usize)
            .and_then(Option::take)
        else {
            return;
        };
        for (word, _) in bag.words {
            if let Some(list) = self.by_word.get_mut(word as usize) {
                list.retain(|&k| k != keyframe);
            }
        }
    }

    pub fn bag(&self, keyframe: KeyFrameId) -> Option<&BagOfWords> {
        self.bags.get(keyframe.0 as usize).and_then(Option::as_ref)
    }

    pub fn len(&self) -> usize {
        self.bags.iter().filter(|b| b.is_some()).count()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The lowest score of `bag` against the bags of `keyframes` (those that see the query's
    /// place for certain, e.g. its covisible keyframes): the bar a candidate must reach.
    /// `None` when none of them is indexed.
    pub fn lowest_score(&self, bag: &BagOfWords, keyframes: &[KeyFrameId]) -> Option<f32> {
        keyframes
            .iter()
            .filter_map(|&k| self.bag(k))
            .map(|b| score(bag, b))
            .min_by(f32::total_cmp)
    }

    /// Keyframes that may show the place `bag` shows, best group first, one per group:
    /// keyframes for which `excluded` is true are never scored (the query's own neighbours),
    /// those below `min_score` are dropped, and each survivor's score is summed with those of
    /// its `neighbours` that survived too.
    pub fn candidates(
        &self,
        bag: &BagOfWords,
        min_score: f32,
        excluded: impl Fn(KeyFrameId) -> bool,
        neighbours: impl Fn(KeyFrameId) -> Vec<KeyFrameId>,
    ) -> Vec<PlaceCandidate> {
        let mut common = vec![0u32; self.bags.len()];
        for &(word, _) in &bag.words {
            for &k in self
                .by_word
                .get(word as usize)
                .map_or(&[][..], Vec::as_slice)
            {
                common[k.0 as usize] += 1;
            }
        }
        for (k, c) in common.iter_mut().enumerate() {
            if *c > 0 && excluded(KeyFrameId(k as u32)) {
                *c = 0;
            }
        }
        let most = common.iter().copied().max().unwrap_or(0);
        if most == 0 {
            return Vec::new();
        }
        let needed = (COMMON_WORDS_SHARE * most as f32).ceil() as u32;
        let mut scores = vec![None::<f32>; self.bags.len()];
        for (k, &c) in common.iter().enumerate() {
            if c >= needed {
                let s = score(bag, self.bags[k].as_ref().expect("a keyframe with words"));
                if s >= min_score {
                    scores[k] = Some(s);
                }
            }
        }
        let mut groups: Vec<PlaceCandidate> = Vec::new();
        for (k, s) in scores.iter().enumerate() {
            let Some(s) = *s else { continue };
            let keyframe = KeyFrameId(k as u32);
            let mut best = (keyframe, s);
            let mut sum = s;
            for n in neighbours(keyframe) {
                if let Some(Some(ns)) = scores.get(n.0 as usize) {
                    sum += ns;
                    if *ns > best.1 {
                        best = (n, *ns);
                    }
                }
            }
            groups.push(PlaceCandidate {
                keyframe: best.0,
                score: best.1,
                group_score: sum,
            });
        }
        let Some(top) = groups.iter().map(|g| g.group_score).max_by(f32::total_cmp) else {
            return Vec::new();
        };
        groups.retain(|g| g.group_score >= GROUP_SHARE * top);
        groups.sort_by(|a, b| {
            b.group_score
                .total_cmp(&a.group_score)
                .then(a.keyframe.0.cmp(&b.keyframe.0))
        });
        let mut seen = std::collections::HashSet::new();
        groups.retain(|g| seen.insert(g.keyframe));
        groups
    }
}

/// One side of a verification: a view's keypoints (those with depth are placed in 3-D), their
/// descriptors, and its bag of words (for the grouping by node).
#[derive(Clone, Copy, Debug)]
pub struct PlaceView<'a> {
    pub keypoints: &'a [Keypoint],
    pub descriptors: &'a [Descriptor],
    pub bag: &'a BagOfWords,
}

/// A candidate that geometry confirms.
#[derive(Clone, Debug, PartialEq)]
pub struct Verified {
    /// Takes the candidate's camera frame into the query's.
    pub query_from_candidate: Se3,
    /// Matches the pose explains (χ² within 95 %), of `matches`.
    pub inliers: usize,
    pub matches: usize,
}

/// How far apart, in pixels across the image, a candidate's point may land from its match in
/// the query for RANSAC to count it: a keypoint's place is good to a pixel or two on the
/// finest levels of the pyramid, a few on the coarser ones.
const LATERAL_TOLERANCE_PX: f64 = 4.0;

/// Whether `candidate` shows the place `query` shows, and the transform between them:
/// descriptors matched within each node of the bags' grouping level, a rigid transform
/// between the matches' 3-D points by RANSAC, then the query's pose optimised against the
/// candidate's points as tracking optimises a frame's (pixels and depth, robust, each
/// weighted by its level). Confirmed with at least `min_inliers` matches explained.
///
/// RANSAC counts a match when it lands within a few pixels of its partner across the view
/// and within depth noise along it: depth is the weaker measurement, and a tolerance as loose
/// across as along lets the fit turn by degrees around a far cluster of points.
pub fn verify(
    query: PlaceView,
    candidate: PlaceView,
    rig: &Rig,
    min_inliers: usize,
) -> Option<Verified> {
    let matched = match_by_node(query, candidate);
    let pairs: Vec<Pair> = matched
        .iter()
        .filter_map(|&(q, c)| {
            Some((
                query.keypoints[q].back_project(&rig.camera)?,
                candidate.keypoints[c].back_project(&rig.camera)?,
            ))
        })
        .collect();
    if pairs.len() < min_inliers.max(3) {
        return None;
    }
    let tolerance = LATERAL_TOLERANCE_PX / rig.camera.fx;
    let (start, _) = ransac_rigid(&pairs, RANSAC_SEED, RANSAC_SAMPLES, |pose, pair| {
        agrees_in_view(pose, pair, tolerance)
    })?;
    // The candidate's camera is the "world" the query's pose is solved in.
    let observations: Vec<PoseObservation> = matched
        .iter()
        .zip(&pairs)
        .map(|(&(q, _), &(_, from))| query.keypoints[q].observation(rig, from))
        .collect();
    let result = optimise_pose(
        &start.inverse(),
        &rig.camera,
        rig.stereo(),
        &observations,
        &PoseOnlyOptions::default(),
    );
    (result.inlier_count >= min_inliers).then(|| Verified {
        query_from_candidate: result.world_from_camera.inverse(),
        inliers: result.inlier_count,
        matches: pairs.len(),
    })
}

/// `pose` puts the candidate's point within `tolerance` (radians) of the query's ray and
/// within depth noise ([`agrees`]'s) of its range.
fn agrees_in_view(pose: &Se3, (to, from): &Pair, tolerance: f64) -> bool {
    let moved = pose.transform_point(from);
    let (range, moved_range) = (to.norm(), moved.norm());
    if range <= 0.0 || moved_range <= 0.0 {
        return false;
    }
    let across = (to / range).cross(&(moved / moved_range)).norm();
    across < tolerance && agrees(&Se3::identity(), &(*to, moved))
}

/// Matched keypoints `(query, candidate)` with depth on both sides, one candidate keypoint
/// per query keypoint and the other way round, in query order.
fn match_by_node(query: PlaceView, candidate: PlaceView) -> Vec<(usize, usize)> {
    let with_depth = |view: &PlaceView, i: u32| view.keypoints[i as usize].depth.is_some();
    // Candidate keypoint → (distance, query keypoint) of its best match so far.
    let mut taken: std::collections::BTreeMap<u32, (u32, u32)> = Default::default();
    let (a, b) = (&query.bag.features_by_node, &candidate.bag.features_by_node);
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                for &q in a[i].1.iter().filter(|&&q| with_depth(&query, q)) {
                    let (mut best, mut second) = ((u32::MAX, u32::MAX), u32::MAX);
                    for &c in b[j].1.iter().filter(|&&c| with_depth(&candidate, c)) {
                        let d = hamming(
                            &query.descriptors[q as usize],
                            &candidate.descriptors[c as usize],
                        );
                        if d < best.0 {
                            second = best.0;
                            best = (d, c);
                        } else if d < second {
                            second = d;
                        }
                    }
                    let (d, c) = best;
                    if d <= MATCH_DISTANCE
                        && (d as f32) < MATCH_RATIO * second as f32
                        && taken.get(&c).is_none_or(|&(held, _)| d < held)
                    {
                        taken.insert(c, (d, q));
                    }
                }
                i += 1;
                j += 1;
            }
        }
    }
    let mut pairs: Vec<(usize, usize)> = taken
        .into_iter()
        .map(|(c, (_, q))| (q as usize, c as usize))
        .collect();
    pairs.sort_unstable();
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};
    use vsgraphs_optim::{DepthResidual, Pinhole};
    use vsgraphs_vision::vocabulary::Vocabulary;

    fn rig() -> Rig {
        Rig {
            camera: Pinhole::new(600.0, 600.0, 320.0, 240.0),
            width: 640,
            height: 480,
            bf: 600.0 * 0.32,
            depth_residual: DepthResidual::Disparity,
            close_depth: 3.2,
            scale_factor: 1.2,
            levels: 8,
        }
    }

    struct Xorshift(u64);

    impl Xorshift {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }

        fn uniform(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 53) as f64
        }

        fn descriptor(&mut self) -> Descriptor {
            let mut d = [0u8; 32];
            for chunk in d.chunks_mut(8) {
                chunk.copy_from_slice(&self.next().to_le_bytes());
            }
            d
        }
    }

    /// Keypoints (with depth) and descriptors of the world points a camera at
    /// `world_from_camera` sees, one per point in view.
    fn view(
        points: &[(Vector3<f64>, Descriptor)],
        world_from_camera: &Se3,
        rig: &Rig,
    ) -> (Vec<Keypoint>, Vec<Descriptor>) {
        let camera_from_world = world_from_camera.inverse();
        points
            .iter()
            .filter_map(|(p, d)| {
                let c = camera_from_world.transform_point(p);
                let pixel = rig.camera.project(&c);
                (c.z > 0.1 && rig.in_image(pixel.x, pixel.y)).then(|| {
                    let keypoint = Keypoint {
                        x: pixel.x,
                        y: pixel.y,
                        level: 0,
                        angle: 0.0,
                        depth: Some(c.z),
                        right_x: Some(pixel.x - rig.bf / c.z),
                    };
                    (keypoint, *d)
                })
            })
            .unzip()
    }

    #[test]
    fn verification_finds_the_transform_between_two_views_of_one_place() {
        let rig = rig();
        let vocabulary = Vocabulary::builtin();
        let mut random = Xorshift(0x1234_5678);
        // A wall 3 m ahead with things on it, up to 20 cm proud.
        let points: Vec<(Vector3<f64>, Descriptor)> = (0..300)
            .map(|_| {
                let p = Vector3::new(
                    random.uniform() * 4.0 - 2.0,
                    random.uniform() * 3.0 - 1.5,
                    3.0 - 0.2 * random.uniform(),
                );
                (p, random.descriptor())
            })
            .collect();
        let first = Se3::identity();
        let second = Se3::new(
            UnitQuaternion::from_euler_angles(0.02, -0.09, 0.03),
            Vector3::new(0.4, -0.05, 0.3),
        );
        let (query_keypoints, query_descriptors) = view(&points, &second, &rig);
        let (keypoints, descriptors) = view(&points, &first, &rig);
        let query_bag = vocabulary.transform(&query_descriptors, 2);
        let bag = vocabulary.transform(&descriptors, 2);
        let query = PlaceView {
            keypoints: &query_keypoints,
            descriptors: &query_descriptors,
            bag: &query_bag,
        };
        let candidate = PlaceView {
            keypoints: &keypoints,
            descriptors: &descriptors,
            bag: &bag,
        };
        let verified = verify(query, candidate, &rig, 20).expect("one place, seen twice");
        let truth = second.inverse().compose(&first);
        let error = truth
            .inverse()
            .compose(&verified.query_from_candidate)
            .log();
        assert!(error.norm() < 1e-6, "error {error:?}");
        assert!(verified.inliers >= 100, "{} inliers", verified.inliers);

        // The same things in other places (each descriptor on another point): no transform
        // puts enough of them back.
        let mut shuffled = points.clone();
        for i in (1..shuffled.len()).rev() {
            let j = (random.next() % (i as u64 + 1)) as usize;
            let descriptor = shuffled[i].1;
            shuffled[i].1 = shuffled[j].1;
            shuffled[j].1 = descriptor;
        }
        let (keypoints, descriptors) = view(&shuffled, &first, &rig);
        let bag = vocabulary.transform(&descriptors, 2);
        let elsewhere = PlaceView {
            keypoints: &keypoints,
            descriptors: &descriptors,
            bag: &bag,
        };
        assert_eq!(verify(query, elsewhere, &rig, 20), None);
    }

    fn bag(words: &[(u32, f32)]) -> BagOfWords {
        let total: f32 = words.iter().map(|w| w.1).sum();
        BagOfWords {
            words: words.iter().map(|&(w, v)| (w, v / total)).collect(),
            features_by_node: Vec::new(),
        }
    }

    #[test]
    fn the_keyframe_of_the_same_place_is_the_candidate() {
        let mut index = PlaceIndex::new();
        // Three places of distinct words; keyframes 0–1 see place A, 2–3 place B, 4 place C.
        let a = [(1, 1.0), (2, 1.0), (3, 1.0), (4, 1.0)];
        let b = [(10, 1.0), (11, 1.0), (12, 1.0), (4, 1.0)];
        let c = [(20, 1.0), (21, 1.0), (22, 1.0), (23, 1.0)];
        for (k, words) in [a, a, b, b, c].iter().enumerate() {
            index.insert(KeyFrameId(k as u32), bag(words));
        }
        // Seen again, with one word changed.
        let query = bag(&[(10, 1.0), (11, 1.0), (12, 1.0), (30, 1.0)]);
        let neighbours = |k: KeyFrameId| match k.0 {
            0 => vec![KeyFrameId(1)],
            1 => vec![KeyFrameId(0)],
            2 => vec![KeyFrameId(3)],
            3 => vec![KeyFrameId(2)],
            _ => vec![],
        };
        let found = index.candidates(&query, 0.1, |_| false, neighbours);
        // Both keyframes of place B lead a group of the same sum.
        assert_eq!(found.len(), 2, "{found:?}");
        assert!(found.iter().all(|c| matches!(c.keyframe.0, 2 | 3)));
        assert!((found[0].score - 0.75).abs() < 1e-6);
        assert!((found[0].group_score - 1.5).abs() < 1e-6);
        // Excluded keyframes are never returned; a bar above every score returns nothing.
        let found = index.candidates(&query, 0.1, |k| matches!(k.0, 2 | 3), neighbours);
        assert!(found.is_empty(), "{found:?}");
        assert!(index
            .candidates(&query, 0.8, |_| false, neighbours)
            .is_empty());
    }

    #[test]
    fn a_removed_keyframe_is_no_longer_found() {
        let mut index = PlaceIndex::new();
        index.insert(KeyFrameId(0), bag(&[(1, 1.0), (2, 1.0)]));
        index.insert(KeyFrameId(3), bag(&[(1, 1.0), (2, 1.0)]));
        assert_eq!(index.len(), 2);
        index.remove(KeyFrameId(0));
        assert_eq!(index.len(), 1);
        let query = bag(&[(1, 1.0), (2, 1.0)]);
        let found = index.candidates(&query, 0.5, |_| false, |_| vec![]);
        assert_eq!(found.len(), 1);
        assert_eq!(found[0].keyframe, KeyFrameId(3));
        assert_eq!(
            index.lowest_score(&query, &[KeyFrameId(0), KeyFrameId(3)]),
            Some(1.0)
        );
    }
}
