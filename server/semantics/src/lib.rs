//! The S-Graph's semantic layer: what the markers of a building mean. [`dictionary`] reads the
//! semantic dictionary (the reference implementation's "env database"), which says which marker
//! ids bound which room or corridor and which open which door; [`walls`] gathers a map's wall
//! markers into walls; [`spaces`] makes the dictionary's rooms and corridors of them, checked
//! against geometry. [`SemanticMap::build`] does both for a map's markers.
//!
//! Doorways, rooms and corridors from geometry alone, and the optimisation of the whole with the
//! map, join this crate with the rest of the S-Graph issue. Must not depend on zenoh, tokio or the
//! pipeline: the pipeline runs it on each map's writer.

pub mod dictionary;
pub mod spaces;
pub mod wall_points;
pub mod walls;

pub use dictionary::{Dictionary, DictionaryError, MarkerId, MarkerRole, SpaceKind};
pub use spaces::{Missing, Space, SpaceChecks};
pub use wall_points::{MapPoint, WallPoints};
pub use walls::{Wall, WallAssociation};

use vsgraphs_optim::Se3;

/// A map's semantic layer as its markers make it now.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SemanticMap {
    pub walls: Vec<Wall>,
    pub spaces: Vec<Space>,
    /// The dictionary's spaces not found, with why.
    pub missing: Vec<Missing>,
}

impl SemanticMap {
    /// Walls from `markers` (each id with its pose in the map) and the map's `points`, then the
    /// rooms and corridors of `dictionary` that they make (none without one).
    pub fn build(
        markers: &[(MarkerId, Se3)],
        points: &[MapPoint],
        dictionary: Option<&Dictionary>,
    ) -> Self {
        let walls = walls::walls_of(
            markers,
            points,
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
        Self {
            walls,
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
