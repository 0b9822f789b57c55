//! The map of one tracking session: keyframes and map points in arenas indexed by typed ids,
//! with the observations that tie them. Culled points stay in the arena marked bad, so ids
//! never dangle.

use crate::frame::{hamming, Descriptor, Frame, Rig};
use crate::places::{self, PlaceIndex};
use nalgebra::Vector3;
use std::collections::BTreeMap;
use vsgraphs_optim::factors::marker::marker_corners;
use vsgraphs_optim::Se3;

pub use crate::ids::{KeyFrameId, MapId, MapPointId};

/// A frame kept in the map, with the map point (if any) behind each keypoint.
#[derive(Clone, Debug)]
pub struct KeyFrame {
    pub id: KeyFrameId,
    pub frame: Frame,
    pub world_from_camera: Se3,
    pub points: Vec<Option<MapPointId>>,
    /// Set when the keyframe was culled as redundant: the keyframe it now hangs from and its
    /// pose relative to that one (`parent_from_this`). A culled keyframe sees no points, so
    /// covisibility and everything built on it pass it by; frames anchored to it follow
    /// its parent ([`Map::world_from_keyframe`]).
    pub parent: Option<(KeyFrameId, Se3)>,
    /// The keyframe the same robot made before this one in this map (none: the first of a
    /// trajectory): robots that map one place at once insert their keyframes in turn, so the
    /// keyframe before in the arena may be another robot's.
    pub previous: Option<KeyFrameId>,
}

impl KeyFrame {
    pub fn camera_centre(&self) -> Vector3<f64> {
        self.world_from_camera.translation
    }

    pub fn is_culled(&self) -> bool {
        self.parent.is_some()
    }
}

/// A frame's pose relative to a keyframe of its map (ORB-SLAM keeps the same per frame for
/// its trajectory files): the frame's best estimate follows the keyframe as it is adjusted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Anchor {
    pub keyframe: KeyFrameId,
    pub keyframe_from_camera: Se3,
}

/// A loop edge: keyframe `newer` seen from the old part of the map, at keyframe `older`
/// ([`crate::loops`]); the whole-map optimisation holds it beside the essential graph.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopEdge {
    pub older: KeyFrameId,
    pub newer: KeyFrameId,
    /// `newer`'s pose relative to `older` as the old part's points put it.
    pub older_from_newer: Se3,
    /// Old points that pose explains.
    pub inliers: usize,
}

/// A 3-D point seen by keyframes.
#[derive(Clone, Debug)]
pub struct MapPoint {
    pub position: Vector3<f64>,
    /// The observation's descriptor closest to all others (ORB-SLAM's distinctive descriptor).
    pub descriptor: Descriptor,
    /// (keyframe, keypoint index).
    pub observations: Vec<(KeyFrameId, usize)>,
    /// Mean viewing direction (unit), from the point toward the cameras that see it.
    pub normal: Vector3<f64>,
    /// Distances over which its descriptor's scale stays within the pyramid.
    pub min_distance: f64,
    pub max_distance: f64,
    /// Frames that should have seen it, and frames that matched it.
    pub visible: u32,
    pub found: u32,
    pub first_keyframe: KeyFrameId,
    pub bad: bool,
}

impl MapPoint {
    /// Matched over predicted: points that are rarely found when in view are unreliable.
    pub fn found_ratio(&self) -> f64 {
        f64::from(self.found) / f64::from(self.visible.max(1))
    }
}

/// Keyframes and map points of one map.
#[derive(Clone, Debug, Default)]
pub struct Map {
    pub keyframes: Vec<KeyFrame>,
    pub points: Vec<MapPoint>,
    /// Marker landmarks by ArUco id.
    pub markers: BTreeMap<i32, MapMarker>,
    /// The camera the map was started with (its first keyframe's).
    pub rig: Option<Rig>,
    /// Its keyframes by their visual words, for relocalisation and loop detection.
    pub places: PlaceIndex,
    /// Loops closed in it, oldest first.
    pub loop_edges: Vec<LoopEdge>,
    /// Keyframes that begin a trajectory of their own in this map (the first keyframe of each
    /// map merged into it): the keyframe before one in the arena is not its predecessor.
    pub trajectory_starts: std::collections::BTreeSet<KeyFrameId>,
    /// Each keyframe's covisible keyframes as of its last refresh (see [`Map::neighbours`]).
    pub(crate) neighbours: Vec<Vec<(KeyFrameId, usize)>>,
    /// Points marked bad, counted as they are: the API reads the live count on every frame,
    /// and a long run's map holds tens of thousands.
    pub(crate) culled_points: usize,
}

impl Map {
    pub fn keyframe(&self, id: KeyFrameId) -> &KeyFrame {
        &self.keyframes[id.0 as usize]
    }

    pub fn keyframe_mut(&mut self, id: KeyFrameId) -> &mut KeyFrame {
        &mut self.keyframes[id.0 as usize]
    }

    pub fn point(&self, id: MapPointId) -> &MapPoint {
        &self.points[id.0 as usize]
    }

    pub fn point_mut(&mut self, id: MapPointId) -> &mut MapPoint {
        &mut self.points[id.0 as usize]
    }

    /// The map points a keyframe sees.
    pub fn points_of(&self, keyframe: KeyFrameId) -> Vec<MapPointId> {
        self.keyframe(keyframe)
            .points
            .iter()
            .flatten()
            .copied()
            .collect()
    }

    /// Points not culled.
    pub fn live_points(&self) -> usize {
        self.points.len() - self.culled_points
    }

    /// Marks a point bad, once.
    fn mark_bad(&mut self, point: MapPointId) {
        let p = &mut self.points[point.0 as usize];
        if !p.bad {
            p.bad = true;
            self.culled_points += 1;
        }
    }

    /// Keyframes not culled.
    pub fn live_keyframes(&self) -> usize {
        self.keyframes.iter().filter(|k| !k.is_culled()).count()
    }

    /// A keyframe's pose now: its own, or for a culled one its parent's (followed up the
    /// chain of culled parents) composed with its pose relative to the parent.
    pub fn world_from_keyframe(&self, id: KeyFrameId) -> Se3 {
        let mut k = self.keyframe(id);
        let mut parent_from_keyframe = Se3::identity();
        while let Some((parent, parent_from_this)) = &k.parent {
            parent_from_keyframe = parent_from_this.compose(&parent_from_keyframe);
            k = self.keyframe(*parent);
        }
        k.world_from_camera.compose(&parent_from_keyframe)
    }

    /// Culls a redundant keyframe: it forgets its points (a point it alone saw is culled) and
    /// hangs from its most covisible keyframe. Returns that parent, or `None` (and leaves the
    /// keyframe alone) when it shares no point with another keyframe.
    pub fn cull_keyframe(&mut self, id: KeyFrameId) -> Option<KeyFrameId> {
        if self.keyframe(id).is_culled() {
            return None;
        }
        let covisible = self.covisible(id);
        let parent = covisible.first()?.0;
        for p in self.points_of(id) {
            self.erase_observation(p, id);
        }
        let parent_from_this = self
            .keyframe(parent)
            .world_from_camera
            .inverse()
            .compose(&self.keyframe(id).world_from_camera);
        self.keyframe_mut(id).parent = Some((parent, parent_from_this));
        self.places.remove(id);
        if let Some(n) = self.neighbours.get_mut(id.0 as usize) {
            n.clear();
        }
        for (k, _) in covisible {
            if (k.0 as usize) < self.neighbours.len() {
                self.neighbours[k.0 as usize] = self.covisible(k);
            }
        }
        Some(parent)
    }

    /// A new keyframe, after the arena's last as one robot's map grows
    /// ([`KeyFrame::previous`]; its writer says otherwise when robots share the map).
    pub fn add_keyframe(&mut self, frame: Frame, world_from_camera: Se3) -> KeyFrameId {
        let id = KeyFrameId(self.keyframes.len() as u32);
        let n = frame.len();
        self.places.insert(id, places::bag_of(&frame));
        self.keyframes.push(KeyFrame {
            id,
            frame,
            world_from_camera,
            points: vec![None; n],
            parent: None,
            previous: id.0.checked_sub(1).map(KeyFrameId),
        });
        id
    }

    /// A new point first observed by keypoint `index` of `keyframe`.
    pub fn add_point(
        &mut self,
        position: Vector3<f64>,
        keyframe: KeyFrameId,
        index: usize,
        rig: &Rig,
    ) -> MapPointId {
        let id = MapPointId(self.points.len() as u32);
        let descriptor = self.keyframe(keyframe).frame.descriptors[index];
        self.points.push(MapPoint {
            position,
            descriptor,
            observations: Vec::new(),
            normal: Vector3::z(),
            min_distance: 0.0,
            max_distance: f64::INFINITY,
            visible: 1,
            found: 1,
            first_keyframe: keyframe,
            bad: false,
        });
        self.add_observation(id, keyframe, index);
        self.update_geometry(id, rig);
        id
    }

    /// Records that keypoint `index` of `keyframe` sees `point` (a keypoint sees one point).
    pub fn add_observation(&mut self, point: MapPointId, keyframe: KeyFrameId, index: usize) {
        let slot = &mut self.keyframes[keyframe.0 as usize].points[index];
        if let Some(old) = *slot {
            if old == point {
                return;
            }
            self.points[old.0 as usize]
                .observations
                .retain(|&(k, i)| (k, i) != (keyframe, index));
        }
        *slot = Some(point);
        let p = &mut self.points[point.0 as usize];
        // One observation per keyframe: a second keypoint of the same keyframe replaces nothing.
        if p.observations.iter().any(|&(k, _)| k == keyframe) {
            self.keyframes[keyframe.0 as usize].points[index] = None;
            return;
        }
        p.observations.push((keyframe, index));
    }

    /// Removes a point from the map (its keyframes forget it).
    pub fn cull_point(&mut self, point: MapPointId) {
        let observations = std::mem::take(&mut self.points[point.0 as usize].observations);
        for (k, i) in observations {
            let slot = &mut self.keyframes[k.0 as usize].points[i];
            if *slot == Some(point) {
                *slot = None;
            }
        }
        self.mark_bad(point);
    }

    /// Drops the observation of `point` by `keyframe`; a point left with none is culled.
    pub fn erase_observation(&mut self, point: MapPointId, keyframe: KeyFrameId) {
        let p = &mut self.points[point.0 as usize];
        if let Some(pos) = p.observations.iter().position(|&(k, _)| k == keyframe) {
            let (_, i) = p.observations.swap_remove(pos);
            self.keyframes[keyframe.0 as usize].points[i] = None;
        }
        if self.points[point.0 as usize].observations.is_empty() {
            self.cull_point(point);
        }
    }

    /// Merges `gone` into `kept`: every keyframe that saw `gone` now sees `kept` (unless it
    /// already does), and `gone` is culled. Used when two points turn out to be one.
    pub fn replace_point(&mut self, gone: MapPointId, kept: MapPointId) {
        if gone == kept || self.point(gone).bad || self.point(kept).bad {
            return;
        }
        let observations = std::mem::take(&mut self.points[gone.0 as usize].observations);
        let (visible, found) = (self.point(gone).visible, self.point(gone).found);
        for (k, i) in observations {
            self.keyframes[k.0 as usize].points[i] = None;
            if !self.point(kept).observations.iter().any(|&(o, _)| o == k) {
                self.add_observation(kept, k, i);
            }
        }
        let p = &mut self.points[kept.0 as usize];
        p.visible += visible;
        p.found += found;
        self.mark_bad(gone);
    }

    /// Recomputes a point's viewing direction, distance range and distinctive descriptor from
    /// its observations.
    pub fn update_geometry(&mut self, point: MapPointId, rig: &Rig) {
        self.update_normal_and_depth(point, rig);
        self.update_descriptor(point);
    }

    /// Recomputes a point's viewing direction and distance range: enough after it moved
    /// without gaining or losing observations (as after bundle adjustment).
    pub fn update_normal_and_depth(&mut self, point: MapPointId, rig: &Rig) {
        let p = &self.points[point.0 as usize];
        if p.observations.is_empty() {
            return;
        }
        let mut normal = Vector3::zeros();
        for &(k, _) in &p.observations {
            let to_camera = self.keyframe(k).camera_centre() - p.position;
            normal += to_camera / to_camera.norm().max(1e-9);
        }
        let (k, i) = p.observations[0];
        let reference = self.keyframe(k);
        let distance = (p.position - reference.camera_centre()).norm();
        let level = usize::from(reference.frame.keypoints[i].level);
        let max_distance = distance * rig.scale(level);
        let min_distance = max_distance / rig.scale(rig.levels - 1);
        let p = &mut self.points[point.0 as usize];
        p.normal = normal.try_normalize(1e-12).unwrap_or(Vector3::z());
        p.max_distance = max_distance;
        p.min_distance = min_distance;
    }

    /// Recomputes a point's distinctive descriptor (ORB-SLAM's: the observation's descriptor
    /// with the least median distance to the others), after its observations changed.
    pub fn update_descriptor(&mut self, point: MapPointId) {
        let p = &self.points[point.0 as usize];
        if p.observations.is_empty() {
            return;
        }
        let descriptors: Vec<Descriptor> = p
            .observations
            .iter()
            .map(|&(k, i)| self.keyframe(k).frame.descriptors[i])
            .collect();
        self.points[point.0 as usize].descriptor = distinctive(&descriptors);
    }

    /// [`Map::covisible`] as of the last [`Map::refresh_neighbours`] of `keyframe`: tracking asks
    /// for the neighbours of dozens of keyframes every frame, and counting shared points each
    /// time was a fifth of its cost.
    pub fn neighbours(&self, keyframe: KeyFrameId) -> &[(KeyFrameId, usize)] {
        self.neighbours
            .get(keyframe.0 as usize)
            .map_or(&[], |n| n.as_slice())
    }

    /// Recounts the covisibility of `keyframe` and of every keyframe sharing points with it
    /// (the only ones whose counts a new or changed keyframe alters).
    pub fn refresh_neighbours(&mut self, keyframe: KeyFrameId) {
        if self.neighbours.len() < self.keyframes.len() {
            self.neighbours.resize(self.keyframes.len(), Vec::new());
        }
        let list = self.covisible(keyframe);
        for &(k, _) in &list {
            self.neighbours[k.0 as usize] = self.covisible(k);
        }
        self.neighbours[keyframe.0 as usize] = list;
    }

    /// Keyframes sharing points with `keyframe`, most shared first, with the count.
    pub fn covisible(&self, keyframe: KeyFrameId) -> Vec<(KeyFrameId, usize)> {
        // Counted in a slot per keyframe (ids are dense), cheaper than hashing each sighting.
        let mut counts = vec![0u32; self.keyframes.len()];
        let mut list: Vec<(KeyFrameId, usize)> = Vec::new();
        for point in self.keyframe(keyframe).points.iter().flatten() {
            for &(k, _) in &self.point(*point).observations {
                if k != keyframe {
                    let count = &mut counts[k.0 as usize];
                    if *count == 0 {
                        list.push((k, 0));
                    }
                    *count += 1;
                }
            }
        }
        for (k, shared) in &mut list {
            *shared = counts[k.0 as usize] as usize;
        }
        list.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        list
    }
}

/// The descriptor with the least median distance to the others.
fn distinctive(descriptors: &[Descriptor]) -> Descriptor {
    if descriptors.len() <= 2 {
        return descriptors[0];
    }
    let mut best = (u32::MAX, 0);
    let mut row = Vec::with_capacity(descriptors.len());
    for (i, a) in descriptors.iter().enumerate() {
        row.clear();
        row.extend(descriptors.iter().map(|b| hamming(a, b)));
        row.sort_unstable();
        let median = row[(row.len() - 1) / 2];
        if median < best.0 {
            best = (median, i);
        }
    }
    descriptors[best.1]
}

/// A mapped marker.
#[derive(Clone, Debug, PartialEq)]
pub struct MapMarker {
    pub id: i32,
    pub side_m: f64,
    pub world_from_marker: Se3,
    /// Keyframes that saw it, with the index of the sighting in the keyframe's frame.
    pub observations: Vec<(KeyFrameId, usize)>,
}

impl MapMarker {
    /// Its corners in the world, in sighting order.
    pub fn corners_in_world(&self) -> [nalgebra::Vector3<f64>; 4] {
        marker_corners(self.side_m).map(|c| self.world_from_marker.transform_point(&c))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::frame::Keypoint;

    use crate::frame::tests::rig;

    /// A frame of `n` keypoints in a row, each with depth and a descriptor of its own.
    pub(crate) fn frame(n: usize, rig: &Rig) -> Frame {
        let keypoints = (0..n)
            .map(|i| Keypoint {
                x: 10.0 * i as f64,
                y: 100.0,
                level: 0,
                angle: 0.0,
                depth: Some(2.0),
                right_x: None,
            })
            .collect();
        let descriptors = (0..n).map(|i| [i as u8; 32]).collect();
        Frame::from_parts(0, keypoints, descriptors, rig)
    }

    #[test]
    fn observations_and_covisibility_stay_consistent() {
        let rig = rig();
        let mut map = Map::default();
        let a = map.add_keyframe(frame(5, &rig), Se3::identity());
        let b = map.add_keyframe(frame(5, &rig), Se3::identity());
        let c = map.add_keyframe(frame(5, &rig), Se3::identity());
        let points: Vec<_> = (0..5)
            .map(|i| map.add_point(Vector3::new(i as f64, 0.0, 2.0), a, i, &rig))
            .collect();
        for &p in &points[..3] {
            let i = points.iter().position(|&q| q == p).unwrap();
            map.add_observation(p, b, i);
        }
        map.add_observation(points[4], c, 0);
        assert_eq!(map.covisible(a), vec![(b, 3), (c, 1)]);
        assert_eq!(map.covisible(c), vec![(a, 1)]);
        assert!(map.neighbours(a).is_empty());
        map.refresh_neighbours(c);
        assert_eq!(map.neighbours(c), &[(a, 1)]);
        assert_eq!(map.neighbours(a), &[(b, 3), (c, 1)]);
        // A point seen twice by one keyframe keeps one observation.
        map.add_observation(points[4], c, 1);
        assert_eq!(map.point(points[4]).observations.len(), 2);
        assert_eq!(map.keyframe(c).points[1], None);
        // Culling a point clears its keyframes' slots.
        map.cull_point(points[0]);
        assert!(map.point(points[0]).bad);
        assert_eq!(map.keyframe(a).points[0], None);
        assert_eq!(map.keyframe(b).points[0], None);
        assert_eq!(map.covisible(a), vec![(b, 2), (c, 1)]);
        assert_eq!(map.live_points(), 4);
        map.cull_point(points[0]);
        assert_eq!(map.live_points(), 4, "a point is culled once");
        // Erasing the last observation culls.
        map.erase_observation(points[4], c);
        map.erase_observation(points[4], a);
        assert!(map.point(points[4]).bad);
        assert_eq!(map.live_points(), 3);
        // Merging culls the merged point; a culled one is not merged again.
        map.replace_point(points[3], points[2]);
        map.replace_point(points[3], points[1]);
        assert!(map.point(points[3]).bad);
        assert_eq!(map.live_points(), 2);
        let counted = map.points.iter().filter(|p| !p.bad).count();
        assert_eq!(map.live_points(), counted);
    }

    #[test]
    fn the_distinctive_descriptor_is_the_median_one() {
        // b is two bits from each of the others, which are four bits from one another.
        let with = |bits: u8| {
            let mut d = [0u8; 32];
            d[0] = bits;
            d
        };
        let b = with(0);
        let others = [with(0b11), with(0b1100), with(0b11_0000), with(0b1100_0000)];
        assert_eq!(
            distinctive(&[others[0], others[1], b, others[2], others[3]]),
            b
        );
    }
}
