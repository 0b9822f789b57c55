//! The S-Graph's semantic layer: what the markers of a building mean. [`dictionary`] reads the
//! semantic dictionary (the reference implementation's "env database"), which says which marker
//! ids bound which room or corridor and which open which door; [`walls`] gathers a map's wall
//! markers into walls; [`doorways`] finds the openings that door markers label; [`spaces`] makes
//! the dictionary's rooms and corridors of the walls, checked against geometry.
//! [`geometry`] finds rooms and corridors from the walls alone where no dictionary names them.
//! [`SemanticMap::build`] does all of it for a map. Must not depend on zenoh, tokio or the
//! pipeline: the pipeline runs it on each map's writer.

pub mod cloud;
pub mod dictionary;
pub mod doorways;
pub mod geometry;
pub mod spaces;
pub mod topology;
pub mod wall_points;
pub mod walls;

pub use cloud::{Cloud, MapPoint};
pub use dictionary::{Dictionary, DictionaryError, MarkerId, MarkerRole, SpaceKind};
pub use doorways::{Doorway, Openings};
pub use spaces::{Missing, Space, SpaceChecks};
pub use wall_points::WallPoints;
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

/// The walls of the map's markers and points, as [`SemanticMap::build`] makes them: what the
/// map's optimisation reads of the layer. Points need no cameras for it.
pub fn walls(map: &MapInput<'_>, dictionary: Option<&Dictionary>) -> Vec<Wall> {
    walls::walls_of(
        map.markers,
        &Cloud::new(map.points, map.cameras),
        dictionary,
        &WallAssociation::default(),
        &WallPoints::default(),
    )
}

impl SemanticMap {
    /// Walls from the map's markers and points, then the doorways of its door markers and the
    /// rooms and corridors of `dictionary` that they make, and rooms and corridors from the
    /// geometry of the walls whose markers it does not list (all of them without one).
    pub fn build(map: &MapInput<'_>, dictionary: Option<&Dictionary>) -> Self {
        let markers = map.markers;
        let started = std::time::Instant::now();
        let points = Cloud::new(map.points, map.cameras);
        let gridded = std::time::Instant::now();
        let walls = walls::walls_of(
            markers,
            &points,
            dictionary,
            &WallAssociation::default(),
            &WallPoints::default(),
        );
        let position = |m: MarkerId| {
            markers
                .iter()
                .find(|(id, _)| *id == m)
                .map(|(_, pose)| pose.translation)
        };
        let checks = SpaceChecks::default();
        let (mut spaces, mut missing) = match dictionary {
            Some(dictionary) => spaces::spaces_of(dictionary, &walls, position, &checks),
            None => (Vec::new(), Vec::new()),
        };
        // Walls the dictionary says nothing of (or names only by a version 2 meta marker).
        let usable: Vec<usize> = (0..walls.len())
            .filter(|&w| {
                walls[w].markers.iter().any(|&m| {
                    matches!(
                        dictionary.map(|d| d.role(m)),
                        None | Some(MarkerRole::Unlisted | MarkerRole::Meta { .. })
                    )
                })
            })
            .collect();
        if let Some(up) = doorways::up_direction(&walls, markers).filter(|_| !usable.is_empty()) {
            let mut found = geometry::geometric_spaces(
                &walls,
                &usable,
                position,
                |m| matches!(dictionary.map(|d| d.role(m)), Some(MarkerRole::Door { .. })),
                &points,
                &up,
                &checks,
            );
            if let Some(dictionary) = dictionary {
                name_by_meta_markers(&mut found, &walls, dictionary);
            }
            spaces.extend(found);
        }
        if let Some(dictionary) = dictionary.filter(|d| d.version == dictionary::Version::V2) {
            for (entry, space) in dictionary.spaces.iter().enumerate() {
                if spaces.iter().any(|s| s.entry == Some(entry)) {
                    continue;
                }
                let meta = space.meta_marker;
                let why = match meta.map(|m| (m, position(m).is_some())) {
                    Some((m, true)) => format!(
                        "no room or corridor was found around its meta marker {m} (its walls \
                         are not mapped, or do not make one)"
                    ),
                    Some((m, false)) => format!("its meta marker {m} is not mapped"),
                    None => "it has no meta marker".into(),
                };
                missing.push(Missing { entry, why });
            }
        }
        let walls_done = std::time::Instant::now();
        let doorways = match dictionary {
            Some(dictionary) => doorways::doorways_of(
                markers,
                &walls,
                &points,
                map.cameras,
                dictionary,
                &Openings::default(),
            ),
            None => Vec::new(),
        };
        tracing::trace!(
            grid_ms = (gridded - started).as_secs_f64() * 1e3,
            walls_and_spaces_ms = (walls_done - gridded).as_secs_f64() * 1e3,
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

/// Version 2 names a space by one marker on one of its walls: a space found from geometry
/// whose walls hold the meta marker of a dictionary entry is that entry, of the kind the
/// dictionary gives it (a space two meta markers claim stays unnamed).
fn name_by_meta_markers(spaces: &mut [Space], walls: &[Wall], dictionary: &Dictionary) {
    for space in spaces {
        let mut named = space
            .walls
            .iter()
            .flat_map(|&w| &walls[w].markers)
            .filter_map(|&m| match dictionary.role(m) {
                MarkerRole::Meta { space } => Some(space),
                _ => None,
            })
            .collect::<Vec<usize>>();
        named.dedup();
        if let [entry] = named[..] {
            space.entry = Some(entry);
            space.kind = dictionary.spaces[entry].kind;
        }
    }
}

#[cfg(test)]
mod testing {
    use crate::MarkerId;
    use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
    use vsgraphs_optim::Se3;

    /// Each marker's position by id, as the layer reads it from a map.
    pub fn position_in(
        markers: &[(MarkerId, Se3)],
    ) -> impl Fn(MarkerId) -> Option<Vector3<f64>> + '_ {
        |m| {
            markers
                .iter()
                .find(|(id, _)| *id == m)
                .map(|(_, p)| p.translation)
        }
    }

    /// A marker at `at` whose face points along `facing` (horizontal), upright.
    pub fn marker(at: [f64; 3], facing: [f64; 3]) -> Se3 {
        let z = Vector3::from(facing).normalize();
        let x = Vector3::z().cross(&z);
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, Vector3::z(), z]));
        Se3::new(UnitQuaternion::from_rotation_matrix(&r), Vector3::from(at))
    }
}
