//! How a map's rooms and corridors connect: which spaces a doorway joins, the route from one
//! space to another through doorways, and the space a position lies in.

use crate::SemanticMap;
use nalgebra::Vector3;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// A position is in a space when it is no further than this behind any of the space's walls,
/// metres: a robot's camera in a doorway's frame is still in the space it is leaving.
const INSIDE_MARGIN_M: f64 = 0.2;

impl SemanticMap {
    /// The spaces (indices in `spaces`) that doorway `doorway` joins, as far as they are found.
    pub fn doorway_spaces(&self, doorway: usize) -> Vec<usize> {
        self.doorways[doorway]
            .spaces
            .iter()
            .filter_map(|&entry| self.spaces.iter().position(|s| s.entry == Some(entry)))
            .collect()
    }

    /// The doorways (indices) that open into space `space`.
    pub fn doorways_of_space(&self, space: usize) -> Vec<usize> {
        let Some(entry) = self.spaces[space].entry else {
            return Vec::new();
        };
        (0..self.doorways.len())
            .filter(|&d| self.doorways[d].spaces.contains(&entry))
            .collect()
    }

    /// The spaces next to `space` through a doorway, each with the doorway, in doorway order.
    pub fn neighbours(&self, space: usize) -> Vec<(usize, usize)> {
        self.doorways_of_space(space)
            .into_iter()
            .flat_map(|d| {
                self.doorway_spaces(d)
                    .into_iter()
                    .filter(move |&s| s != space)
                    .map(move |s| (s, d))
            })
            .collect()
    }

    /// The shortest way from space `from` to space `to` through doorways, walking from centre to
    /// doorway to centre: the spaces passed (both ends included) and the doorways between them.
    /// `None` when no chain of found doorways joins them.
    pub fn route(&self, from: usize, to: usize) -> Option<(Vec<usize>, Vec<usize>)> {
        let n = self.spaces.len();
        if from >= n || to >= n {
            return None;
        }
        let mut best = vec![f64::INFINITY; n];
        let mut came_from: Vec<Option<(usize, usize)>> = vec![None; n];
        let mut queue = BinaryHeap::new();
        best[from] = 0.0;
        queue.push(Reverse((Ordered(0.0), from)));
        while let Some(Reverse((Ordered(cost), space))) = queue.pop() {
            if space == to {
                break;
            }
            if cost > best[space] {
                continue;
            }
            for (next, doorway) in self.neighbours(space) {
                let at = self.doorways[doorway].world_from_doorway.translation;
                let step = (at - self.spaces[space].centre).norm()
                    + (self.spaces[next].centre - at).norm();
                if cost + step < best[next] {
                    best[next] = cost + step;
                    came_from[next] = Some((space, doorway));
                    queue.push(Reverse((Ordered(cost + step), next)));
                }
            }
        }
        if !best[to].is_finite() {
            return None;
        }
        let (mut spaces, mut doorways) = (vec![to], Vec::new());
        let mut at = to;
        while let Some((previous, doorway)) = came_from[at] {
            spaces.push(previous);
            doorways.push(doorway);
            at = previous;
        }
        spaces.reverse();
        doorways.reverse();
        Some((spaces, doorways))
    }

    /// The space `position` lies in: inside all of its walls, a room before a corridor (a
    /// corridor's walls do not close it at its ends), the nearest centre between equals.
    pub fn space_at(&self, position: &Vector3<f64>) -> Option<usize> {
        (0..self.spaces.len())
            .filter(|&s| {
                let walls = &self.spaces[s].walls;
                !walls.is_empty()
                    && walls
                        .iter()
                        .all(|&w| self.walls[w].plane.distance(position) >= -INSIDE_MARGIN_M)
            })
            .min_by(|&a, &b| {
                let key = |s: usize| {
                    let space = &self.spaces[s];
                    (
                        space.kind != crate::SpaceKind::Room,
                        (space.centre - position).norm(),
                    )
                };
                let (ka, kb) = (key(a), key(b));
                ka.0.cmp(&kb.0).then(ka.1.total_cmp(&kb.1))
            })
    }
}

/// An `f64` that orders totally, for the route's queue.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Ordered(f64);

impl Eq for Ordered {}

impl PartialOrd for Ordered {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Ordered {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&other.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Doorway, Space, SpaceKind, Wall};
    use nalgebra::Unit;
    use vsgraphs_optim::{Plane, Se3};

    /// Rooms A (x 0–4, y 0–4) and B (x 4–8, y 0–4) side by side, corridor C (y 4–6) along both;
    /// doorways A–B at x = 4 and A–C at y = 4; B opens nowhere but into A.
    fn building() -> SemanticMap {
        let mut walls = Vec::new();
        let mut wall = |at: [f64; 3], normal: [f64; 3]| {
            walls.push(Wall {
                plane: Plane::from_point_normal(
                    &Vector3::from(at),
                    &Unit::new_normalize(Vector3::from(normal)),
                ),
                markers: Vec::new(),
                space: None,
            });
            walls.len() - 1
        };
        let a = vec![
            wall([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            wall([4.0, 0.0, 0.0], [-1.0, 0.0, 0.0]),
            wall([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            wall([0.0, 4.0, 0.0], [0.0, -1.0, 0.0]),
        ];
        let b = vec![
            wall([4.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            wall([8.0, 0.0, 0.0], [-1.0, 0.0, 0.0]),
            wall([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            wall([0.0, 4.0, 0.0], [0.0, -1.0, 0.0]),
        ];
        let c = vec![
            wall([0.0, 4.0, 0.0], [0.0, 1.0, 0.0]),
            wall([0.0, 6.0, 0.0], [0.0, -1.0, 0.0]),
        ];
        let space = |entry, kind, walls, centre: [f64; 3]| Space {
            entry: Some(entry),
            kind,
            walls,
            centre: Vector3::from(centre),
        };
        let doorway = |at: [f64; 3], spaces| Doorway {
            markers: Vec::new(),
            walls: Vec::new(),
            world_from_doorway: Se3::new(Default::default(), Vector3::from(at)),
            width_m: 0.9,
            door: None,
            spaces,
        };
        SemanticMap {
            walls,
            // Dictionary entries 7, 8, 9, found in another order than listed.
            spaces: vec![
                space(8, SpaceKind::Room, b, [6.0, 2.0, 1.0]),
                space(9, SpaceKind::Corridor, c, [4.0, 5.0, 1.0]),
                space(7, SpaceKind::Room, a, [2.0, 2.0, 1.0]),
            ],
            doorways: vec![
                doorway([4.0, 2.0, 0.0], vec![7, 8]),
                doorway([2.0, 4.0, 0.0], vec![9, 7]),
                // A door into a space the map has not found.
                doorway([8.0, 1.0, 0.0], vec![8, 3]),
            ],
            missing: Vec::new(),
        }
    }

    #[test]
    fn doorways_join_the_spaces_found() {
        let map = building();
        assert_eq!(map.doorway_spaces(0), vec![2, 0]);
        assert_eq!(map.doorway_spaces(2), vec![0]);
        assert_eq!(map.doorways_of_space(0), vec![0, 2]);
        assert_eq!(map.neighbours(2), vec![(0, 0), (1, 1)]);
        assert_eq!(map.neighbours(0), vec![(2, 0)]);
    }

    #[test]
    fn the_route_goes_through_the_doorways_between() {
        let map = building();
        // From B to the corridor: through A.
        assert_eq!(map.route(0, 1), Some((vec![0, 2, 1], vec![0, 1])));
        assert_eq!(map.route(1, 0), Some((vec![1, 2, 0], vec![1, 0])));
        assert_eq!(map.route(2, 2), Some((vec![2], vec![])));
        let mut cut = building();
        cut.doorways.remove(0);
        assert_eq!(cut.route(0, 1), None);
        assert_eq!(map.route(0, 5), None);
    }

    #[test]
    fn a_position_is_in_the_room_that_encloses_it() {
        let map = building();
        let at = |x, y| map.space_at(&Vector3::new(x, y, 1.0));
        assert_eq!(at(1.0, 1.0), Some(2));
        assert_eq!(at(7.0, 3.0), Some(0));
        assert_eq!(at(6.0, 5.0), Some(1));
        // Just past a wall (a camera in a door's frame, or a wall placed a little short): the
        // space it is leaving, by the margin; where two take it, the one with the nearer centre.
        assert_eq!(at(8.1, 2.0), Some(0));
        assert_eq!(at(4.1, 2.0), Some(0));
        assert_eq!(at(9.0, 2.0), None);
        assert_eq!(at(4.0, 7.0), None);
    }
}
