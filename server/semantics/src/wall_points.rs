//! The plane of the wall a marker hangs on, from the map points around it (the paper's
//! point-on-wall). A marker's own normal comes from four corners a few centimetres apart and is
//! degrees off, tens of degrees when it was only seen small or at a grazing angle; the wall's
//! texture around it gives tens to hundreds of points over a metre, whose plane is far better.
//! The marker's centre is placed to a few centimetres, so a hypothesis is a plane through the
//! centre and two points, counted over a band that wide; the best one is refitted to its inliers
//! with a tolerance taken from the points' own spread, and kept only when the points pin its
//! normal down and the marker lies on it. Only points seen from the marker's side count: the
//! other face of a partition is a parallel plane a wall's thickness away, full of points.

use crate::cloud::Cloud;
use nalgebra::{Matrix3, SymmetricEigen, Unit, Vector3};
use vsgraphs_optim::Plane;

/// How points around a marker make its wall's plane.
#[derive(Clone, Debug, PartialEq)]
pub struct WallPoints {
    /// Points within this distance of the marker's centre are candidates.
    pub radius_m: f64,
    /// A hypothesis's normal is within this angle of the marker's.
    pub max_angle_rad: f64,
    /// The coarse inlier band of a hypothesis, before the fit sets its own.
    pub hypothesis_band_m: f64,
    /// The fitted band never gets narrower than this.
    pub min_band_m: f64,
    /// Inliers a plane needs.
    pub min_points: usize,
    /// The fitted normal's standard error must be below this.
    pub max_normal_error_rad: f64,
    /// Hypotheses tried per marker.
    pub hypotheses: usize,
}

impl Default for WallPoints {
    /// A metre around the marker: on a textured wall that holds tens of points, and a wall is one
    /// plane that far from a marker hung away from corners and frames. A marker's normal is seldom
    /// more than a few degrees off, but one seen small can be 40° off, and the nearest other
    /// plane (a perpendicular wall, the floor) is 90° away: 60° sits between. A band of 5 cm
    /// holds a wall's points at the ranges a robot maps from (RGB-D depth noise grows with the
    /// square of the range: about 1 cm at 2 m, 4 cm at 4 m), the refit then narrows it to three
    /// robust standard deviations, never below 5 mm (the texture's relief). The fewest points the
    /// reference fits a plane to is 6. A normal known to 1° is as good as the goal for walls.
    /// With half the points near a marker on its wall, 64 draws of two all miss it with
    /// probability (3/4)^64 ≈ 1e-8.
    fn default() -> Self {
        Self {
            radius_m: 1.0,
            max_angle_rad: 60f64.to_radians(),
            hypothesis_band_m: 0.05,
            min_band_m: 0.005,
            min_points: 6,
            max_normal_error_rad: 1f64.to_radians(),
            hypotheses: 64,
        }
    }
}

/// The plane of the wall under a marker (centre `centre`, face `marker`), its normal on the
/// marker's side; `None` when the points around it do not make one well enough.
pub fn wall_plane(
    marker: &Plane,
    centre: &Vector3<f64>,
    points: &Cloud<'_>,
    settings: &WallPoints,
) -> Option<Plane> {
    let near: Vec<Vector3<f64>> = points
        .near(centre, settings.radius_m)
        .into_iter()
        .filter(|p| {
            (p.position - centre).norm() <= settings.radius_m
                && p.toward_cameras.dot(&marker.normal) > 0.0
        })
        .map(|p| p.position)
        .collect();
    if near.len() < settings.min_points {
        return None;
    }
    let cos_limit = settings.max_angle_rad.cos();
    // Hypotheses by a fixed pseudo-random sequence: the same points give the same wall.
    let mut random = SplitMix(near.len() as u64 ^ centre.x.to_bits());
    let mut best: Option<(usize, Plane)> = None;
    for _ in 0..settings.hypotheses {
        let a = near[random.below(near.len())];
        let b = near[random.below(near.len())];
        let Some(plane) = Plane::new((a - centre).cross(&(b - centre)), 0.0) else {
            continue;
        };
        let plane = Plane::from_point_normal(centre, &plane.normal);
        let plane = if plane.normal.dot(&marker.normal) < 0.0 {
            plane.flipped()
        } else {
            plane
        };
        if plane.normal.dot(&marker.normal) < cos_limit {
            continue;
        }
        let count = near
            .iter()
            .filter(|p| plane.distance(p).abs() <= settings.hypothesis_band_m)
            .count();
        if best.as_ref().is_none_or(|(n, _)| count > *n) {
            best = Some((count, plane));
        }
    }
    let (_, mut plane) = best?;
    let mut band = settings.hypothesis_band_m;
    let mut fit = None;
    for _ in 0..3 {
        let inliers: Vec<Vector3<f64>> = near
            .iter()
            .filter(|p| plane.distance(p).abs() <= band)
            .copied()
            .collect();
        if inliers.len() < settings.min_points {
            return None;
        }
        let f = fit_plane(&inliers)?;
        plane = if f.plane.normal.dot(&marker.normal) < 0.0 {
            f.plane.flipped()
        } else {
            f.plane
        };
        band = (3.0 * f.robust_sigma_m).clamp(settings.min_band_m, settings.hypothesis_band_m);
        fit = Some(f);
    }
    let fit = fit?;
    // A wall stands out of the cloud: its band holds several times the points that the same
    // width beside it does (a cloud with no plane in it has as many beside as in it).
    let (mut inside, mut beside) = (0usize, 0usize);
    for p in &near {
        let d = plane.distance(p).abs();
        if d <= band {
            inside += 1;
        } else if d <= 2.0 * band {
            beside += 1;
        }
    }
    let good = plane.normal.dot(&marker.normal) >= cos_limit
        && fit.normal_error_rad <= settings.max_normal_error_rad
        && plane.distance(centre).abs() <= settings.hypothesis_band_m
        && inside >= 4 * beside;
    good.then_some(plane)
}

/// A least-squares plane and how well its points fix it.
struct Fit {
    plane: Plane,
    /// 1.4826 × the median absolute distance: the points' spread about the plane.
    robust_sigma_m: f64,
    /// Standard error of the normal's tilt about the in-plane axis the points span least.
    normal_error_rad: f64,
}

/// The total least-squares plane of `points` (through their centroid, normal along the least
/// spread).
fn fit_plane(points: &[Vector3<f64>]) -> Option<Fit> {
    let n = points.len() as f64;
    let centroid = points.iter().sum::<Vector3<f64>>() / n;
    let scatter = points.iter().fold(Matrix3::zeros(), |s, p| {
        let d = p - centroid;
        s + d * d.transpose()
    }) / n;
    let eigen = SymmetricEigen::new(scatter);
    let mut order = [0, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    let normal = Unit::try_new(eigen.eigenvectors.column(order[0]).into_owned(), 1e-12)?;
    let plane = Plane::from_point_normal(&centroid, &normal);
    let mut distances: Vec<f64> = points.iter().map(|p| plane.distance(p).abs()).collect();
    distances.sort_by(f64::total_cmp);
    let robust_sigma_m = 1.4826 * distances[distances.len() / 2];
    // The normal tilts about an in-plane axis by σ / (√n · the spread along the other one).
    let spread = eigen.eigenvalues[order[1]].max(0.0).sqrt();
    let sigma = (eigen.eigenvalues[order[0]].max(0.0)).sqrt();
    let normal_error_rad = if spread > 0.0 {
        (sigma / (n.sqrt() * spread)).atan()
    } else {
        f64::INFINITY
    };
    Some(Fit {
        plane,
        robust_sigma_m,
        normal_error_rad,
    })
}

/// A small deterministic pseudo-random sequence (SplitMix64).
pub(crate) struct SplitMix(pub(crate) u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    pub(crate) fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::MapPoint;

    /// Points on a grid over the wall x = 4 (facing -x) around (4, 1, 1.2), ±`noise` m off it
    /// in a fixed pattern, plus points of the floor and of a side wall y = 1.8, all seen from
    /// the room (x < 4), and the other face of a thin partition 3 cm behind (nearer than a
    /// marker's own error), seen from beyond it.
    fn scene(noise: f64) -> Vec<MapPoint> {
        let mut points = Vec::new();
        for i in 0..15 {
            for j in 0..15 {
                let (u, v) = (i as f64 * 0.12 - 0.84, j as f64 * 0.12 - 0.84);
                let wobble = noise * (((i * 7 + j * 3) % 5) as f64 - 2.0) / 2.0;
                let room = Vector3::new(-1.0, 0.0, 0.0);
                let seen = |position, toward_cameras| MapPoint {
                    position,
                    toward_cameras,
                    cameras: Vec::new(),
                };
                points.push(seen(Vector3::new(4.0 + wobble, 1.0 + u, 1.2 + v), room));
                points.push(seen(Vector3::new(3.0 + u * 0.5, 1.0 + v, 0.0), room));
                points.push(seen(Vector3::new(3.5 + u * 0.5, 1.8, 1.2 + v), room));
                // Twice as dense as the near face, as if mapped more thoroughly.
                for back in [4.03, 4.035] {
                    points.push(seen(Vector3::new(back, 1.0 + u, 1.2 + v), -room));
                }
            }
        }
        points
    }

    fn tilted_marker(degrees: f64) -> Plane {
        let a = degrees.to_radians();
        let normal = Unit::new_normalize(Vector3::new(-a.cos(), a.sin() * 0.6, a.sin() * 0.8));
        Plane::from_point_normal(&Vector3::new(4.0, 1.0, 1.2), &normal)
    }

    #[test]
    fn the_points_straighten_a_marker_that_is_far_off() {
        let centre = Vector3::new(4.0, 1.0, 1.2);
        for degrees in [3.0, 25.0, 45.0] {
            let plane = wall_plane(
                &tilted_marker(degrees),
                &centre,
                &Cloud::new(&scene(0.01), &[]),
                &WallPoints::default(),
            )
            .expect("a wall");
            let angle = plane.normal.dot(&-Vector3::x()).clamp(-1.0, 1.0).acos();
            assert!(
                angle.to_degrees() < 0.5,
                "{degrees}°: {}°",
                angle.to_degrees()
            );
            assert!(plane.distance(&centre).abs() < 0.005);
        }
    }

    #[test]
    fn too_few_or_scattered_points_leave_the_marker_alone() {
        let centre = Vector3::new(4.0, 1.0, 1.2);
        let few: Vec<MapPoint> = scene(0.0)
            .into_iter()
            .filter(|p| p.toward_cameras.x < 0.0)
            .step_by(150)
            .collect();
        assert!(few.len() < 6);
        assert_eq!(
            wall_plane(
                &tilted_marker(3.0),
                &centre,
                &Cloud::new(&few, &[]),
                &WallPoints::default()
            ),
            None
        );
        // A cloud with no wall in it, dense enough that any slab of it fixes a normal well.
        let mut random = SplitMix(3);
        let cloud: Vec<MapPoint> = (0..3000)
            .map(|_| {
                let mut c = || random.below(1000) as f64 / 1000.0 - 0.5;
                MapPoint {
                    position: centre + Vector3::new(c(), c(), c()),
                    toward_cameras: -Vector3::x(),
                    cameras: Vec::new(),
                }
            })
            .collect();
        assert_eq!(
            wall_plane(
                &tilted_marker(3.0),
                &centre,
                &Cloud::new(&cloud, &[]),
                &WallPoints::default()
            ),
            None
        );
    }
}
