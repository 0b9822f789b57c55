//! Walls: a marker lies on its wall (paper eq. 3) and a map point lies on its wall.
//!
//! Under the plane update `π ⊕ [a, b, e]` the normal moves by `B·[a, b]` (B the tangent basis at
//! the normal, see [`Plane`]) and the offset by `e`.

use crate::factor::Factor;
use crate::lie::{hat, Se3};
use crate::plane::Plane;
use crate::values::{Key, Kind, Values, VarId};
use nalgebra::{DMatrixViewMut, Vector3};

/// `r = [n_M.x, n_M.y, n·t_M + d]` with `n_M = R_Mᵀ·n`, the wall's normal seen from the marker.
///
/// The first two entries are the sines of the angles between the wall's normal and the marker's
/// z axis about the marker's y and x axes: the paper's azimuth and elevation differences in the
/// marker frame, without the singularity of azimuth/elevation at the poles. The third is the
/// marker's distance from the wall. A wall's normal may point either way: both fit.
#[derive(Clone, Debug)]
pub struct MarkerOnWallFactor {
    keys: [VarId; 2],
}

impl MarkerOnWallFactor {
    pub fn new(world_from_marker: Key<Se3>, wall: Key<Plane>) -> Self {
        Self {
            keys: [world_from_marker.id, wall.id],
        }
    }
}

impl Factor for MarkerOnWallFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose, Kind::Plane]
    }

    fn residual_dim(&self) -> usize {
        3
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let m = values.at::<Se3>(self.keys[0]);
        let wall = values.at::<Plane>(self.keys[1]);
        let r_m = m.rotation.to_rotation_matrix().into_inner();
        let n = wall.normal.into_inner();
        let n_m = r_m.transpose() * n;
        residual[0] = n_m.x;
        residual[1] = n_m.y;
        residual[2] = wall.distance(&m.translation);
        if let Some(mut jac) = jacobian {
            jac.fill(0.0);
            let basis = Plane::tangent_basis(&wall.normal);
            // Exp(−φ)·R_Mᵀ·n ≈ n_M + [n_M]×·φ
            let d_phi = hat(&n_m);
            let d_ab = r_m.transpose() * basis;
            for row in 0..2 {
                for c in 0..3 {
                    jac[(row, 3 + c)] = d_phi[(row, c)];
                }
                jac[(row, 6)] = d_ab[(row, 0)];
                jac[(row, 7)] = d_ab[(row, 1)];
            }
            let d_rho = r_m.transpose() * n;
            for c in 0..3 {
                jac[(2, c)] = d_rho[c];
            }
            jac[(2, 6)] = m.translation.dot(&basis.column(0));
            jac[(2, 7)] = m.translation.dot(&basis.column(1));
            jac[(2, 8)] = 1.0;
        }
    }
}

/// `r = n·p + d`: a map point lies on its wall.
#[derive(Clone, Debug)]
pub struct PointOnWallFactor {
    keys: [VarId; 2],
}

impl PointOnWallFactor {
    pub fn new(point: Key<Vector3<f64>>, wall: Key<Plane>) -> Self {
        Self {
            keys: [point.id, wall.id],
        }
    }
}

impl Factor for PointOnWallFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Point, Kind::Plane]
    }

    fn residual_dim(&self) -> usize {
        1
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let p = values.at::<Vector3<f64>>(self.keys[0]);
        let wall = values.at::<Plane>(self.keys[1]);
        residual[0] = wall.distance(p);
        if let Some(mut jac) = jacobian {
            let basis = Plane::tangent_basis(&wall.normal);
            for c in 0..3 {
                jac[(0, c)] = wall.normal[c];
            }
            jac[(0, 3)] = p.dot(&basis.column(0));
            jac[(0, 4)] = p.dot(&basis.column(1));
            jac[(0, 5)] = 1.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{jacobian_error, random_se3, Rng};
    use nalgebra::{Unit, UnitQuaternion};
    use proptest::prelude::*;

    fn random_plane(rng: &mut Rng) -> Plane {
        Plane::new(rng.vector3(1.0), rng.range(-5.0, 5.0)).expect("non-zero normal")
    }

    proptest! {
        #[test]
        fn marker_on_wall_jacobians_match_differences(seed in any::<u64>(), on_wall in any::<bool>()) {
            let mut rng = Rng::new(seed);
            let wall = random_plane(&mut rng);
            let marker = if on_wall {
                // Near-degenerate: the marker lies on the wall (zero residual).
                let z = wall.normal;
                let rotation = UnitQuaternion::rotation_between(&Vector3::z(), &z).unwrap_or_else(|| UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0));
                let point = -z.into_inner() * wall.offset + Plane::tangent_basis(&z).column(0) * rng.range(-2.0, 2.0);
                Se3::new(rotation * UnitQuaternion::from_euler_angles(0.0, 0.0, rng.range(-3.0, 3.0)), point)
            } else {
                random_se3(seed)
            };
            let mut values = Values::new();
            let m = values.add(marker);
            let w = values.add(wall);
            let f = MarkerOnWallFactor::new(m, w);
            prop_assert!(jacobian_error(&f, &values) < 1e-6);
            if on_wall {
                let mut r = [1.0; 3];
                f.evaluate(&values, &mut r, None);
                prop_assert!(r.iter().all(|v| v.abs() < 1e-9), "{r:?}");
            }
        }

        #[test]
        fn point_on_wall_jacobians_match_differences(seed in any::<u64>()) {
            let mut rng = Rng::new(seed);
            let mut values = Values::new();
            let p = values.add(rng.vector3(3.0));
            let w = values.add(random_plane(&mut rng));
            prop_assert!(jacobian_error(&PointOnWallFactor::new(p, w), &values) < 1e-6);
        }
    }

    #[test]
    fn a_tilted_marker_reports_its_angle() {
        // A wall x = 2 (normal +x); a marker on it turned 0.1 rad about the world's z axis.
        let wall = Plane::new(Vector3::x(), -2.0).unwrap();
        let onto_wall = UnitQuaternion::rotation_between(&Vector3::z(), &Vector3::x()).unwrap();
        let turned = UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::z()), 0.1);
        let mut values = Values::new();
        let m = values.add(Se3::new(turned * onto_wall, Vector3::new(2.05, 1.0, 0.5)));
        let w = values.add(wall);
        let mut r = [0.0; 3];
        MarkerOnWallFactor::new(m, w).evaluate(&values, &mut r, None);
        let angle = r[0].hypot(r[1]).asin();
        assert!((angle - 0.1).abs() < 1e-12, "{r:?}");
        assert!((r[2] - 0.05).abs() < 1e-12);
    }
}
