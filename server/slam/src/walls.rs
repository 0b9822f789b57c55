//! Walls in local bundle adjustment (the S-Graph's first structural layer optimised with the
//! keyframes and markers): the map's semantic layer says which markers hang on which wall; a
//! local BA that adjusts one of them gets the wall as a plane variable, each of its markers in
//! the problem on it (marker-on-wall) and the window's points on it (point-on-wall). Markers on
//! one wall then hold each other's orientation, and points on a wall its plane, where corners a
//! few centimetres apart and single depth readings cannot.
//!
//! Semantics must never make the map worse, so a wall only enters where the window agrees
//! with it: a marker that the starting values put off the plane or turned from it (a wrong
//! association, a wall that is not flat) stays out, and so does a wall left with no marker.

use nalgebra::Vector3;
use std::collections::HashMap;
use vsgraphs_optim::factors::wall::{MarkerOnWallFactor, PointOnWallFactor};
use vsgraphs_optim::{Information, Kernel, Key, Plane, Problem, Se3};

/// A wall of the map's semantic layer, as local BA takes it: its plane (normal into its space)
/// and the ids of the markers on it.
#[derive(Clone, Debug, PartialEq)]
pub struct WallPrior {
    pub plane: Plane,
    pub markers: Vec<i32>,
}

/// How walls enter local BA. The tolerances are a built wall's: flat to a few millimetres
/// (plaster and paint; the semantic layer's narrowest point band, 5 mm, is the same relief),
/// a printed marker flat on it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WallTerms {
    /// Standard deviation of a point's or marker's distance from its wall, metres.
    pub flatness_m: f64,
    /// Standard deviation of a marker's turn from its wall, radians.
    pub marker_turn_rad: f64,
    /// Points within this distance of the wall's plane (at the start) and of one of its
    /// markers are taken for its points.
    pub point_band_m: f64,
    pub point_radius_m: f64,
    /// A marker farther from the plane, or turned more from it, at the start is not on it.
    pub gate_distance_m: f64,
    pub gate_turn_rad: f64,
}

impl Default for WallTerms {
    /// Points: the semantic layer's own search (a metre around a marker, a band of 5 cm, which
    /// holds a wall's points at mapping ranges). Gate: a marker landmark is placed to a few
    /// centimetres and its normal to a few degrees; one 10 cm or 15° off its wall was put on the
    /// wrong wall, or the wall bends.
    fn default() -> Self {
        Self {
            flatness_m: 0.005,
            marker_turn_rad: 1f64.to_radians(),
            point_band_m: 0.05,
            point_radius_m: 1.0,
            gate_distance_m: 0.10,
            gate_turn_rad: 15f64.to_radians(),
        }
    }
}

/// What the walls added to one local BA.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WallReport {
    pub walls: usize,
    pub markers: usize,
    pub points: usize,
    /// Markers of a wall in the problem that the gate kept out.
    pub gated: usize,
}

/// χ² at 95 % for 1 and 3 degrees of freedom.
const CHI2_1D: f64 = 3.841;
const CHI2_3D: f64 = 7.815;

/// A marker variable of the problem, with its id and starting pose.
#[derive(Clone, Copy, Debug)]
pub struct MarkerVar {
    pub id: i32,
    pub key: Key<Se3>,
    pub world_from_marker: Se3,
}

/// A point variable of the problem, with its starting position and the mean direction from it
/// to the cameras that saw it.
#[derive(Clone, Copy, Debug)]
pub struct PointVar {
    pub key: Key<Vector3<f64>>,
    pub position: Vector3<f64>,
    pub toward_cameras: Vector3<f64>,
}

/// Adds `walls` to a local BA problem whose marker and point variables are `markers` and
/// `points`. Only walls with a marker among them enter.
pub fn add_wall_terms(
    problem: &mut Problem,
    walls: &[WallPrior],
    markers: &[MarkerVar],
    points: &[PointVar],
    terms: &WallTerms,
) -> WallReport {
    let marker_vars: HashMap<i32, &MarkerVar> = markers.iter().map(|m| (m.id, m)).collect();
    let mut report = WallReport::default();
    let marker_information = Information::from_sigmas(&[
        terms.marker_turn_rad.sin(),
        terms.marker_turn_rad.sin(),
        terms.flatness_m,
    ])
    .expect("positive sigmas");
    let point_information = Information::isotropic(1, terms.flatness_m).expect("positive sigma");
    for wall in walls {
        let on_wall: Vec<(Key<Se3>, Vector3<f64>)> = wall
            .markers
            .iter()
            .filter_map(|id| marker_vars.get(id))
            .filter_map(|m| {
                let pose = &m.world_from_marker;
                let normal = pose.rotation * Vector3::z();
                let agrees = wall.plane.distance(&pose.translation).abs() <= terms.gate_distance_m
                    && normal.dot(&wall.plane.normal).abs() >= terms.gate_turn_rad.cos();
                if !agrees {
                    report.gated += 1;
                }
                agrees.then_some((m.key, pose.translation))
            })
            .collect();
        if on_wall.is_empty() {
            continue;
        }
        let plane_key = problem.values_mut().add(wall.plane);
        for &(marker_key, _) in &on_wall {
            problem
                .add(
                    MarkerOnWallFactor::new(marker_key, plane_key),
                    marker_information.clone(),
                    Some(Kernel::Huber(CHI2_3D.sqrt())),
                )
                .expect("keys of the problem");
        }
        report.walls += 1;
        report.markers += on_wall.len();
        let normal = wall.plane.normal.into_inner();
        for point in points {
            let near_marker = on_wall
                .iter()
                .any(|(_, centre)| (point.position - centre).norm() <= terms.point_radius_m);
            // Seen from the wall's side: the other face of a partition is a parallel plane a
            // wall's thickness away.
            if near_marker
                && point.toward_cameras.dot(&normal) > 0.0
                && wall.plane.distance(&point.position).abs() <= terms.point_band_m
            {
                problem
                    .add(
                        PointOnWallFactor::new(point.key, plane_key),
                        point_information.clone(),
                        Some(Kernel::Huber(CHI2_1D.sqrt())),
                    )
                    .expect("keys of the problem");
                report.points += 1;
            }
        }
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Unit, UnitQuaternion};
    use vsgraphs_optim::factors::pose::PriorFactor;
    use vsgraphs_optim::{Options, Solver, Values};

    /// The wall x = 0 facing +x (its space), and a marker on it at height `z`, along `y`,
    /// turned by `turn` about the vertical and lifted `off` metres off it.
    fn wall() -> Plane {
        Plane::from_point_normal(&Vector3::zeros(), &Unit::new_normalize(Vector3::x()))
    }

    fn marker_pose(y: f64, turn: f64, off: f64) -> Se3 {
        // The marker's z (out of its face) along +x: a quarter turn about y.
        let facing = UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0);
        let turned = UnitQuaternion::from_euler_angles(0.0, 0.0, turn) * facing;
        Se3::new(turned, Vector3::new(off, y, 1.2))
    }

    fn marker_var(values: &mut Values, id: i32, pose: Se3) -> MarkerVar {
        MarkerVar {
            id,
            key: values.add(pose),
            world_from_marker: pose,
        }
    }

    fn point_var(values: &mut Values, position: Vector3<f64>, toward: Vector3<f64>) -> PointVar {
        PointVar {
            key: values.add(position),
            position,
            toward_cameras: toward,
        }
    }

    fn prior(markers: &[i32]) -> Vec<WallPrior> {
        vec![WallPrior {
            plane: wall(),
            markers: markers.to_vec(),
        }]
    }

    #[test]
    fn a_marker_off_its_wall_or_turned_from_it_stays_out() {
        for (off, turn) in [(0.2, 0.0), (0.0, 30f64.to_radians())] {
            let mut values = Values::new();
            let m = marker_var(&mut values, 3, marker_pose(0.0, turn, off));
            let mut problem = Problem::new(values);
            let report =
                add_wall_terms(&mut problem, &prior(&[3]), &[m], &[], &WallTerms::default());
            assert_eq!((report.walls, report.gated), (0, 1), "{off} {turn}");
            assert_eq!(problem.num_factors(), 0);
        }
        // Within the gate it enters.
        let mut values = Values::new();
        let m = marker_var(&mut values, 3, marker_pose(0.0, 0.1, 0.03));
        let mut problem = Problem::new(values);
        let report = add_wall_terms(&mut problem, &prior(&[3]), &[m], &[], &WallTerms::default());
        assert_eq!((report.walls, report.markers, report.gated), (1, 1, 0));
        assert_eq!(problem.num_factors(), 1);
    }

    #[test]
    fn a_wall_without_a_marker_in_the_problem_stays_out() {
        let mut values = Values::new();
        let m = marker_var(&mut values, 4, marker_pose(0.0, 0.0, 0.0));
        let mut problem = Problem::new(values);
        let report = add_wall_terms(&mut problem, &prior(&[3]), &[m], &[], &WallTerms::default());
        assert_eq!(report, WallReport::default());
        assert_eq!(problem.num_factors(), 0);
    }

    #[test]
    fn a_walls_points_are_those_before_it_near_its_markers() {
        let mut values = Values::new();
        let m = marker_var(&mut values, 3, marker_pose(0.0, 0.0, 0.0));
        let before = Vector3::x();
        let points = [
            // On the wall beside the marker, seen from the room: its point.
            point_var(&mut values, Vector3::new(0.01, 0.5, 1.0), before),
            // The other face of the partition, seen from behind.
            point_var(&mut values, Vector3::new(-0.01, 0.5, 1.0), -before),
            // On the plane but 2 m along the wall from the marker.
            point_var(&mut values, Vector3::new(0.0, 2.0, 1.2), before),
            // In front of the wall, 10 cm out (a picture frame, a radiator).
            point_var(&mut values, Vector3::new(0.1, 0.3, 1.2), before),
        ];
        let mut problem = Problem::new(values);
        let report = add_wall_terms(
            &mut problem,
            &prior(&[3]),
            &[m],
            &points,
            &WallTerms::default(),
        );
        assert_eq!(report.points, 1);
        assert_eq!(problem.num_factors(), 2);
    }

    #[test]
    fn a_turned_marker_is_brought_onto_the_wall_its_points_make() {
        // Two markers on the wall, one turned 4° from it; forty points on the wall, held; the
        // markers held loosely where they are (as their corners would). The wall's plane is free
        // and starts 2° and 1 cm off.
        let mut values = Values::new();
        let straight = marker_pose(-0.5, 0.0, 0.0);
        let turned = marker_pose(0.5, 4f64.to_radians(), 0.0);
        let markers = [
            marker_var(&mut values, 1, straight),
            marker_var(&mut values, 2, turned),
        ];
        let mut points = Vec::new();
        for i in 0..40 {
            let (y, z) = (f64::from(i % 8) * 0.2 - 0.7, f64::from(i / 8) * 0.2 + 0.8);
            let p = point_var(&mut values, Vector3::new(0.0, y, z), Vector3::x());
            values.set_fixed(p.key.id, true);
            points.push(p);
        }
        let mut problem = Problem::new(values);
        let start = Plane::from_point_normal(
            &Vector3::new(0.01, 0.0, 0.0),
            &Unit::new_normalize(Vector3::new(1.0, 2f64.to_radians().tan(), 0.0)),
        );
        let walls = vec![WallPrior {
            plane: start,
            markers: vec![1, 2],
        }];
        let report = add_wall_terms(
            &mut problem,
            &walls,
            &markers,
            &points,
            &WallTerms::default(),
        );
        assert_eq!((report.walls, report.markers, report.points), (1, 2, 40));
        for m in &markers {
            problem
                .add(
                    PriorFactor::new(m.key, m.world_from_marker),
                    Information::isotropic(6, 0.1).unwrap(),
                    None,
                )
                .unwrap();
        }
        Solver::new(Options::default()).solve(&mut problem).unwrap();
        let turn_of = |m: &MarkerVar| {
            let pose = problem.values().get(m.key);
            (pose.rotation * Vector3::z())
                .angle(&Vector3::x())
                .to_degrees()
        };
        assert!(turn_of(&markers[1]) < 0.2, "{}", turn_of(&markers[1]));
        assert!(turn_of(&markers[0]) < 0.2, "{}", turn_of(&markers[0]));
    }
}
