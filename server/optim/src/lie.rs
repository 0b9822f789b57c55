//! SO(3) and SE(3): exponential and logarithm maps, adjoints and Jacobians.
//!
//! Convention: a tangent vector of SE(3) is `ξ = [ρ; φ]`, translation part first (as g2o orders
//! its information matrices), and perturbations act on the right: `X ⊕ ξ = X · Exp(ξ)`.
//! Every series expansion switches at a small angle where its truncation error is below 1e-16.

use nalgebra::{
    Isometry3, Matrix3, Matrix6, Quaternion, Translation3, UnitQuaternion, Vector3, Vector6,
};

/// Below this rotation angle (rad) the closed forms are replaced by their Taylor series.
const SMALL_ANGLE: f64 = 1e-4;

/// The skew-symmetric matrix `[v]×` with `[v]× w = v × w`.
pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// SO(3) exponential map: the rotation by `|φ|` about `φ`.
pub fn so3_exp(phi: &Vector3<f64>) -> UnitQuaternion<f64> {
    let theta2 = phi.norm_squared();
    let theta = theta2.sqrt();
    let (w, k) = if theta < SMALL_ANGLE {
        // sin(θ/2)/θ = 1/2 − θ²/48 + …
        (1.0 - theta2 / 8.0, 0.5 - theta2 / 48.0)
    } else {
        ((0.5 * theta).cos(), (0.5 * theta).sin() / theta)
    };
    UnitQuaternion::new_unchecked(Quaternion::new(w, k * phi.x, k * phi.y, k * phi.z))
}

/// SO(3) logarithm, accurate near zero and near π (unlike `acos` of the scalar part).
pub fn so3_log(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let q = q.quaternion();
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.vector())
    } else {
        (q.w, q.vector().into_owned())
    };
    let s = v.norm();
    // θ = 2·atan2(s, w); φ = v · θ / s.
    let scale = if s < SMALL_ANGLE * w {
        // θ/s = (2/w)(1 − s²/(3w²) + …)
        2.0 / w * (1.0 - s * s / (3.0 * w * w))
    } else {
        2.0 * s.atan2(w) / s
    };
    v * scale
}

/// Right Jacobian of SO(3): `Exp(φ + δ) ≈ Exp(φ) · Exp(Jr(φ) δ)`.
pub fn so3_right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = phi.norm_squared();
    let k = hat(phi);
    let (a, b) = if theta2.sqrt() < SMALL_ANGLE {
        (0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0)
    } else {
        let theta = theta2.sqrt();
        (
            (1.0 - theta.cos()) / theta2,
            (theta - theta.sin()) / (theta2 * theta),
        )
    };
    Matrix3::identity() - k * a + k * k * b
}

/// Inverse of [`so3_right_jacobian`].
pub fn so3_right_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = phi.norm_squared();
    let k = hat(phi);
    let c = if theta2.sqrt() < SMALL_ANGLE {
        1.0 / 12.0 + theta2 / 720.0
    } else {
        let theta = theta2.sqrt();
        1.0 / theta2 - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    Matrix3::identity() + k * 0.5 + k * k * c
}

/// Left Jacobian of SO(3), `Jl(φ) = Jr(−φ)`; it maps ρ to the translation of `Exp([ρ; φ])`.
pub fn so3_left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    so3_right_jacobian(&-phi)
}

/// A rigid transform; `Se3` named by its frames, e.g. `world_from_camera`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se3 {
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
}

impl Default for Se3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl Se3 {
    pub fn identity() -> Self {
        Self {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
        }
    }

    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// Exponential map of `ξ = [ρ; φ]`.
    pub fn exp(xi: &Vector6<f64>) -> Self {
        let rho = xi.fixed_rows::<3>(0).into_owned();
        let phi = xi.fixed_rows::<3>(3).into_owned();
        Self {
            rotation: so3_exp(&phi),
            translation: so3_left_jacobian(&phi) * rho,
        }
    }

    /// Logarithm map, the inverse of [`Se3::exp`].
    pub fn log(&self) -> Vector6<f64> {
        let phi = so3_log(&self.rotation);
        // Jl⁻¹(φ) = Jr⁻¹(−φ)
        let rho = so3_right_jacobian_inv(&-phi) * self.translation;
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0).copy_from(&rho);
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        xi
    }

    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        Self {
            rotation,
            translation: -(rotation * self.translation),
        }
    }

    /// `self · other`: with `a_from_b · b_from_c = a_from_c`.
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            rotation: self.rotation * other.rotation,
            translation: self.translation + self.rotation * other.translation,
        }
    }

    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    /// `X ⊕ ξ = X · Exp(ξ)`.
    pub fn retract(&self, xi: &Vector6<f64>) -> Self {
        let mut out = self.compose(&Self::exp(xi));
        out.rotation.renormalize_fast();
        out
    }

    /// `Y ⊖ X = Log(X⁻¹ · Y)`, so that `X ⊕ (Y ⊖ X) = Y`.
    pub fn local(&self, other: &Self) -> Vector6<f64> {
        self.inverse().compose(other).log()
    }

    /// Adjoint: `X · Exp(ξ) = Exp(Ad_X ξ) · X`.
    pub fn adjoint(&self) -> Matrix6<f64> {
        let r = self.rotation.to_rotation_matrix().into_inner();
        let mut ad = Matrix6::zeros();
        ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        ad.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(hat(&self.translation) * r));
        ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
        ad
    }

    pub fn to_isometry(&self) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(self.translation), self.rotation)
    }

    pub fn from_isometry(iso: &Isometry3<f64>) -> Self {
        Self::new(iso.rotation, iso.translation.vector)
    }
}

impl std::ops::Mul for Se3 {
    type Output = Se3;
    fn mul(self, rhs: Se3) -> Se3 {
        self.compose(&rhs)
    }
}

/// The Q block of the SE(3) left Jacobian (Barfoot, State Estimation for Robotics, eq. 7.86).
fn se3_q(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = phi.norm_squared();
    let theta = theta2.sqrt();
    let p = hat(phi);
    let r = hat(rho);
    let (a, b, c) = if theta < 1e-3 {
        (
            1.0 / 6.0 - theta2 / 120.0,
            1.0 / 24.0 - theta2 / 720.0,
            1.0 / 120.0 - theta2 / 2520.0,
        )
    } else {
        let (s, co) = theta.sin_cos();
        (
            (theta - s) / (theta2 * theta),
            (theta2 + 2.0 * co - 2.0) / (2.0 * theta2 * theta2),
            (2.0 * theta - 3.0 * s + theta * co) / (2.0 * theta2 * theta2 * theta),
        )
    };
    let pr = p * r;
    let rp = r * p;
    let prp = pr * p;
    r * 0.5 + (pr + rp + prp) * a + (p * pr + rp * p - prp * 3.0) * b + (prp * p + p * prp) * c
}

/// Left Jacobian of SE(3).
pub fn se3_left_jacobian(xi: &Vector6<f64>) -> Matrix6<f64> {
    let rho = xi.fixed_rows::<3>(0).into_owned();
    let phi = xi.fixed_rows::<3>(3).into_owned();
    let jl = so3_left_jacobian(&phi);
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jl);
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&se3_q(&rho, &phi));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jl);
    j
}

/// Inverse of the SE(3) right Jacobian: `Log(X · Exp(δ)) ≈ Log(X) + Jr⁻¹(Log X) δ`.
pub fn se3_right_jacobian_inv(xi: &Vector6<f64>) -> Matrix6<f64> {
    // Jr(ξ) = Jl(−ξ); the inverse of [[A, Q], [0, A]] is [[A⁻¹, −A⁻¹QA⁻¹], [0, A⁻¹]].
    let rho = -xi.fixed_rows::<3>(0).into_owned();
    let phi = -xi.fixed_rows::<3>(3).into_owned();
    let a_inv = so3_right_jacobian_inv(&-phi);
    let q = se3_q(&rho, &phi);
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&a_inv);
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-a_inv * q * a_inv));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&a_inv);
    j
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{numeric_jacobian, random_se3, random_vector6};
    use nalgebra::DVector;
    use proptest::prelude::*;

    fn angle_strategy() -> impl Strategy<Value = f64> {
        // Include the series regions, the switch points and angles close to π.
        prop_oneof![
            Just(0.0),
            1e-12..1e-6f64,
            1e-5..2e-3f64,
            0.01..3.0f64,
            3.1..std::f64::consts::PI - 1e-9,
        ]
    }

    fn tangent() -> impl Strategy<Value = Vector6<f64>> {
        (
            angle_strategy(),
            prop::array::uniform3(-1.0..1.0f64),
            prop::array::uniform3(-3.0..3.0f64),
        )
            .prop_filter_map("axis", |(theta, axis, rho)| {
                let axis = Vector3::from(axis);
                (axis.norm() > 0.1).then(|| {
                    let phi = axis.normalize() * theta;
                    Vector6::new(rho[0], rho[1], rho[2], phi.x, phi.y, phi.z)
                })
            })
    }

    proptest! {
        #[test]
        fn se3_exp_log_round_trip(xi in tangent()) {
            let back = Se3::exp(&xi).log();
            prop_assert!((back - xi).norm() < 1e-9 * (1.0 + xi.norm()), "{xi} -> {back}");
        }

        #[test]
        fn so3_log_exp_round_trip(xi in tangent()) {
            let phi = xi.fixed_rows::<3>(3).into_owned();
            let q = so3_exp(&phi);
            let back = so3_exp(&so3_log(&q));
            prop_assert!(q.angle_to(&back) < 1e-12);
        }

        #[test]
        fn group_laws(seed in any::<u64>()) {
            let a = random_se3(seed);
            let b = random_se3(seed.wrapping_add(1));
            let identity = Se3::identity();
            prop_assert!(a.compose(&identity).local(&a).norm() < 1e-12);
            prop_assert!(a.compose(&a.inverse()).log().norm() < 1e-12);
            prop_assert!(a.inverse().compose(&a).log().norm() < 1e-12);
            // ⊕ and ⊖ are inverse to each other.
            prop_assert!((a.retract(&a.local(&b))).local(&b).norm() < 1e-9);
            let xi = random_vector6(seed) * 0.5;
            prop_assert!((a.local(&a.retract(&xi)) - xi).norm() < 1e-9);
            // Adjoint moves a perturbation from the right to the left.
            let lhs = a.compose(&Se3::exp(&xi));
            let rhs = Se3::exp(&(a.adjoint() * xi)).compose(&a);
            prop_assert!(lhs.local(&rhs).norm() < 1e-9);
        }

        #[test]
        fn so3_jacobians_match_differences(xi in tangent()) {
            let phi = xi.fixed_rows::<3>(3).into_owned();
            prop_assume!(phi.norm() < 3.0);
            let jr = so3_right_jacobian(&phi);
            // Jr = d Log(Exp(φ)⁻¹ Exp(φ + δ)) / dδ
            let numeric = numeric_jacobian(3, &DVector::zeros(3), |d| {
                let d = Vector3::new(d[0], d[1], d[2]);
                let v = so3_log(&(so3_exp(&phi).inverse() * so3_exp(&(phi + d))));
                DVector::from_column_slice(v.as_slice())
            });
            prop_assert!((jr - &numeric).norm() < 1e-7, "{jr} {numeric}");
            prop_assert!((jr * so3_right_jacobian_inv(&phi) - Matrix3::identity()).norm() < 1e-9);
        }

        #[test]
        fn se3_right_jacobian_inverse_matches_differences(xi in tangent()) {
            let phi = xi.fixed_rows::<3>(3).into_owned();
            prop_assume!(phi.norm() < 3.0);
            let x = Se3::exp(&xi);
            let analytic = se3_right_jacobian_inv(&xi);
            let numeric = numeric_jacobian(6, &DVector::zeros(6), |d| {
                let d = Vector6::from_column_slice(d.as_slice());
                DVector::from_column_slice(x.retract(&d).log().as_slice())
            });
            let error = (analytic - &numeric).norm();
            prop_assert!(error < 1e-6 * (1.0 + analytic.norm()), "{analytic} {numeric}");
            let jl = se3_left_jacobian(&-xi);
            prop_assert!((jl * analytic - Matrix6::identity()).norm() < 1e-8);
        }
    }
}
