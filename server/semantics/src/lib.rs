//! The S-Graph's semantic layer: what the markers of a building mean. [`dictionary`] reads the
//! semantic dictionary (the reference implementation's "env database"), which says which marker
//! ids bound which room or corridor and which open which door; [`walls`] gathers a map's wall
//! markers into walls; [`doorways`] finds the openings that door markers label; [`spaces`] makes
//! the dictionary's rooms and corridors of the walls, checked against geometry.
//! [`SemanticMap::build`] does all of it for a map.
//!
//! Rooms and corridors from geometry alone, and the optimisation of the whole with the map, join
//! this crate with the rest of the S-Graph issue. Must not depend on zenoh, tokio or the
//! pipeline: the pipeline runs it on each map's writer.

pub mod dictionary;
pub mod doorways;
pub mod spaces;
pub mod topology;
pub mod wall_points;
pub mod walls;

pub use dictionary::{Dictionary, DictionaryError, MarkerId, MarkerRole, SpaceKind};
pub use doorways::{Doorway, Openings};
pub use spaces::{Missing, Space, SpaceChecks};
pub use wall_points::{MapPoint, WallPoints};
pub use walls::{Wall, WallAssociation};

use nalgebra::Vector3;
use vsgraphs_optim::Se3;

/// What the semantic layer reads of a map.
#[derive(Clone, Copy, Debug)]
pub struct MapInput<'a> {
    /// Each marker landmark's id with its pose in the map.
    pub markers: &'a [(MarkerId, Se3)],
    pub points: &'a [MapPoint],
    /// The keyframes' camera centres, which points name by index.
    pub cameras: &'a [Vector3<f64>],
}

/// A map's semantic layer as its markers make it now.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SemanticMap {
    pub walls: Vec<Wall>,
    pub doorways: Vec<Doorway>,
    pub spaces: Vec<Space>,
    /// The dictionary's spaces not found, with why.
    pub missing: Vec<Missing>,
}

impl SemanticMap {
    /// Walls from the map's markers and points, then the doorways of its door markers and the
    /// rooms and corridors of `dictionary` that they make (none of either without one).
    pub fn build(map: &MapInput<'_>, dictionary: Option<&Dictionary>) -> Self {
        let markers = map.markers;
        let started = std::time::Instant::now();
        let walls = walls::walls_of(
            markers,
            map.points,
            dictionary,
            &WallAssociation::default(),
            &WallPoints::default(),
        );
        let Some(dictionary) = dictionary else {
            return Self {
                walls,
                ..Self::default()
            };
        };
        let position = |m: MarkerId| {
            markers
                .iter()
                .find(|(id, _)| *id == m)
                .map(|(_, pose)| pose.translation)
        };
        let (spaces, missing) =
            spaces::spaces_of(dictionary, &walls, position, &SpaceChecks::default());
        let walls_done = std::time::Instant::now();
        let doorways = doorways::doorways_of(
            markers,
            &walls,
            map.points,
            map.cameras,
            dictionary,
            &Openings::default(),
        );
        tracing::trace!(
            walls_and_spaces_ms = (walls_done - started).as_secs_f64() * 1e3,
            doorways_ms = walls_done.elapsed().as_secs_f64() * 1e3,
            "semantic layer built"
        );
        Self {
            walls,
            doorways,
            spaces,
            missing,
        }
    }
}

#[cfg(test)]
mod testing {
    use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
    use vsgraphs_optim::Se3;

    /// A marker at `at` whose face points along `facing` (horizontal), upright.
    pub fn marker(at: [f64; 3], facing: [f64; 3]) -> Se3 {
        let z = Vector3::from(facing).normalize();
        let x = Vector3::z().cross(&z);
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, Vector3::z(), z]));
        Se3::new(UnitQuaternion::from_rotation_matrix(&r), Vector3::from(at))
    }
}
