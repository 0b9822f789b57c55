//! Infinite planes (walls) as a unit normal and an offset, with a minimal 3-parameter update.
//!
//! A plane is `{x : n·x + d = 0}` with `|n| = 1`. Its update `π ⊕ δ`, `δ = [a, b, e]`, moves the
//! normal along the sphere by the tangent vector `a·t₁ + b·t₂` (an exponential map on S²) and adds
//! `e` to the offset. The tangent basis `t₁, t₂` is computed from the current normal each time, so
//! the update has no singular direction: every normal has a well-conditioned neighbourhood.

use crate::lie::Se3;
use nalgebra::{Matrix3x2, Unit, Vector2, Vector3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    pub normal: Unit<Vector3<f64>>,
    pub offset: f64,
}

impl Plane {
    /// The plane `n·x + d = 0`; `n` need not be unit length (it is normalised with `d`).
    /// `None` for a zero or non-finite normal.
    pub fn new(n: Vector3<f64>, d: f64) -> Option<Self> {
        let norm = n.norm();
        (norm > 1e-12 && norm.is_finite() && d.is_finite()).then(|| Self {
            normal: Unit::new_unchecked(n / norm),
            offset: d / norm,
        })
    }

    /// The plane through `point` with normal `n`.
    pub fn from_point_normal(point: &Vector3<f64>, n: &Unit<Vector3<f64>>) -> Self {
        Self {
            normal: *n,
            offset: -n.dot(point),
        }
    }

    /// Signed distance of a point (positive on the normal's side).
    pub fn distance(&self, p: &Vector3<f64>) -> f64 {
        self.normal.dot(p) + self.offset
    }

    /// The plane with the normal and offset negated: the same point set.
    pub fn flipped(&self) -> Self {
        Self {
            normal: -self.normal,
            offset: -self.offset,
        }
    }

    /// This plane (given in frame B) expressed in frame A, for `a_from_b`.
    pub fn transformed(&self, a_from_b: &Se3) -> Self {
        let normal = Unit::new_unchecked(a_from_b.rotation * self.normal.into_inner());
        Self {
            normal,
            offset: self.offset - normal.dot(&a_from_b.translation),
        }
    }

    /// An orthonormal basis of the tangent plane of the normal's sphere at `n`.
    pub fn tangent_basis(n: &Unit<Vector3<f64>>) -> Matrix3x2<f64> {
        // Cross with the axis least aligned with n: never closer than 54.7° to n.
        let abs = n.abs();
        let axis = if abs.x <= abs.y && abs.x <= abs.z {
            Vector3::x()
        } else if abs.y <= abs.z {
            Vector3::y()
        } else {
            Vector3::z()
        };
        let t1 = n.cross(&axis).normalize();
        let t2 = n.cross(&t1);
        Matrix3x2::from_columns(&[t1, t2])
    }

    /// `π ⊕ δ`.
    pub fn retract(&self, delta: &Vector3<f64>) -> Self {
        let v = Self::tangent_basis(&self.normal) * Vector2::new(delta.x, delta.y);
        let angle = v.norm();
        let normal = if angle < 1e-12 {
            Unit::new_normalize(self.normal.into_inner() + v)
        } else {
            Unit::new_normalize(self.normal.into_inner() * angle.cos() + v * (angle.sin() / angle))
        };
        Self {
            normal,
            offset: self.offset + delta.z,
        }
    }

    /// `other ⊖ self`, so that `self ⊕ (other ⊖ self) = other` (for normals less than π apart).
    pub fn local(&self, other: &Self) -> Vector3<f64> {
        let n = self.normal.into_inner();
        let m = other.normal.into_inner();
        let cos = n.dot(&m).clamp(-1.0, 1.0);
        let perpendicular = m - n * cos;
        let sin = perpendicular.norm();
        let v = if sin < 1e-12 {
            perpendicular
        } else {
            perpendicular * (sin.atan2(cos) / sin)
        };
        let ab = Self::tangent_basis(&self.normal).transpose() * v;
        Vector3::new(ab.x, ab.y, other.offset - self.offset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{numeric_jacobian, random_se3};
    use nalgebra::DVector;
    use proptest::prelude::*;

    fn plane() -> impl Strategy<Value = Plane> {
        (prop::array::uniform3(-1.0..1.0f64), -5.0..5.0f64)
            .prop_filter_map("normal", |(n, d)| Plane::new(Vector3::from(n), d))
    }

    proptest! {
        #[test]
        fn retract_and_local_are_inverse(p in plane(), delta in prop::array::uniform3(-1.0..1.0f64)) {
            let delta = Vector3::from(delta);
            let q = p.retract(&delta);
            prop_assert!((q.normal.norm() - 1.0).abs() < 1e-12);
            prop_assert!((p.local(&q) - delta).norm() < 1e-9);
            prop_assert!(p.local(&p).norm() < 1e-15);
        }

        #[test]
        fn basis_is_orthonormal_everywhere(p in plane()) {
            let b = Plane::tangent_basis(&p.normal);
            prop_assert!((b.transpose() * b - nalgebra::Matrix2::identity()).norm() < 1e-12);
            prop_assert!((b.transpose() * p.normal.into_inner()).norm() < 1e-12);
        }

        #[test]
        fn retract_derivative_is_the_basis(p in plane()) {
            let numeric = numeric_jacobian(3, &DVector::zeros(3), |d| {
                let q = p.retract(&Vector3::new(d[0], d[1], d[2]));
                DVector::from_column_slice(&[q.normal.x, q.normal.y, q.normal.z, q.offset])
            });
            let b = Plane::tangent_basis(&p.normal);
            for r in 0..3 {
                for c in 0..2 {
                    prop_assert!((numeric[(r, c)] - b[(r, c)]).abs() < 1e-8);
                }
            }
            prop_assert!((numeric[(3, 2)] - 1.0).abs() < 1e-8);
        }

        #[test]
        fn transformed_keeps_points_on_the_plane(p in plane(), seed in any::<u64>()) {
            let a_from_b = random_se3(seed);
            let on_plane_b = -p.normal.into_inner() * p.offset
                + Plane::tangent_basis(&p.normal).column(0) * 0.7;
            let on_plane_a = a_from_b.transform_point(&on_plane_b);
            prop_assert!(p.transformed(&a_from_b).distance(&on_plane_a).abs() < 1e-12);
        }
    }

    #[test]
    fn axis_aligned_normals_have_no_singularity() {
        for n in [Vector3::x(), Vector3::y(), Vector3::z(), -Vector3::z()] {
            let p = Plane::new(n, 1.0).unwrap();
            let q = p.retract(&Vector3::new(1e-3, -2e-3, 0.0));
            assert!((p.local(&q) - Vector3::new(1e-3, -2e-3, 0.0)).norm() < 1e-12);
        }
        assert!(Plane::new(Vector3::zeros(), 1.0).is_none());
    }
}
