//! Relative-pose (odometry, loop closure, pose graph) and pose-prior factors.

use crate::factor::Factor;
use crate::lie::{se3_right_jacobian_inv, Se3};
use crate::values::{Key, Kind, Values, VarId};
use nalgebra::{DMatrixViewMut, Matrix3, Matrix6, Vector6};

/// How the error pose `E` of a relative-pose factor becomes a 6-vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseError {
    /// `[t; vec(q)]` with `q.w ≥ 0`, as g2o's EDGE_SE3:QUAT: its "chi2" is then comparable.
    /// The rotation part is about half the angle, so this weighs rotation 4× less than `LogMap`.
    Quaternion,
    /// `Log(E) = [ρ; φ]`, as GTSAM and factrs do.
    LogMap,
}

/// `r = f(Z⁻¹ · Xi⁻¹ · Xj)`: pose `j` seen from pose `i` should be the measurement `Z`.
#[derive(Clone, Debug)]
pub struct BetweenFactor {
    keys: [VarId; 2],
    /// Measured `i_from_j`.
    pub measured: Se3,
    pub error: PoseError,
}

impl BetweenFactor {
    pub fn new(i: Key<Se3>, j: Key<Se3>, i_from_j: Se3, error: PoseError) -> Self {
        Self {
            keys: [i.id, j.id],
            measured: i_from_j,
            error,
        }
    }
}

/// `r = f(E)` and `∂r/∂ξ` for a right perturbation `E · Exp(ξ)`.
fn error_and_jacobian(e: &Se3, kind: PoseError) -> (Vector6<f64>, Matrix6<f64>) {
    match kind {
        PoseError::Quaternion => {
            let q = e.rotation.quaternion();
            let (w, v) = if q.w < 0.0 {
                (-q.w, -q.vector())
            } else {
                (q.w, q.vector().into_owned())
            };
            let r = Vector6::new(
                e.translation.x,
                e.translation.y,
                e.translation.z,
                v.x,
                v.y,
                v.z,
            );
            let mut j = Matrix6::zeros();
            j.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(e.rotation.to_rotation_matrix().matrix());
            // vec(q ⊗ [1, φ/2]) = vec(q) + ½(w·I + [v]×) φ
            j.fixed_view_mut::<3, 3>(3, 3)
                .copy_from(&((Matrix3::identity() * w + crate::lie::hat(&v)) * 0.5));
            (r, j)
        }
        PoseError::LogMap => {
            let r = e.log();
            (r, se3_right_jacobian_inv(&r))
        }
    }
}

impl Factor for BetweenFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose, Kind::Pose]
    }

    fn residual_dim(&self) -> usize {
        6
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let xi = values.at::<Se3>(self.keys[0]);
        let xj = values.at::<Se3>(self.keys[1]);
        let i_from_j = xi.inverse().compose(xj);
        let e = self.measured.inverse().compose(&i_from_j);
        let (r, de) = error_and_jacobian(&e, self.error);
        residual.copy_from_slice(r.as_slice());
        if let Some(mut jac) = jacobian {
            // E(δi, δj) = Z⁻¹ Exp(−δi) Xi⁻¹ Xj Exp(δj) ≈ E · Exp(δj − Ad(Xj⁻¹ Xi) δi)
            let ad = i_from_j.inverse().adjoint();
            jac.fixed_view_mut::<6, 6>(0, 0).copy_from(&(-de * ad));
            jac.fixed_view_mut::<6, 6>(0, 6).copy_from(&de);
        }
    }
}

/// `r = Log(Z⁻¹ · X)`: a pose should be where a prior says (e.g. to anchor a map).
#[derive(Clone, Debug)]
pub struct PriorFactor {
    keys: [VarId; 1],
    pub prior: Se3,
}

impl PriorFactor {
    pub fn new(key: Key<Se3>, prior: Se3) -> Self {
        Self {
            keys: [key.id],
            prior,
        }
    }
}

impl Factor for PriorFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose]
    }

    fn residual_dim(&self) -> usize {
        6
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let x = values.at::<Se3>(self.keys[0]);
        let r = self.prior.local(x);
        residual.copy_from_slice(r.as_slice());
        if let Some(mut jac) = jacobian {
            jac.fixed_view_mut::<6, 6>(0, 0)
                .copy_from(&se3_right_jacobian_inv(&r));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{jacobian_error, random_se3, random_vector6};
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn between_jacobians_match_differences(seed in any::<u64>(), near in any::<bool>()) {
            for error in [PoseError::Quaternion, PoseError::LogMap] {
                let mut values = Values::new();
                let xi = random_se3(seed);
                // Near-degenerate: the measurement almost equal to the relative pose (E ≈ I),
                // where the log map's series expansions take over.
                let xj = if near { xi.retract(&(random_vector6(seed) * 1e-3)) } else { random_se3(seed + 7) };
                let z = if near { xi.inverse().compose(&xj).retract(&(random_vector6(seed + 3) * 1e-7)) } else { random_se3(seed + 11) };
                let i = values.add(xi);
                let j = values.add(xj);
                let factor = BetweenFactor::new(i, j, z, error);
                // The log map jumps at a rotation of π (see the prior's test).
                let e = z.inverse().compose(&xi.inverse().compose(&xj));
                if error == PoseError::LogMap && e.log().fixed_rows::<3>(3).norm() > std::f64::consts::PI - 1e-2 {
                    continue;
                }
                let err = jacobian_error(&factor, &values);
                prop_assert!(err < 1e-6, "{error:?}: {err}");
            }
        }

        #[test]
        fn prior_jacobian_matches_differences(seed in any::<u64>()) {
            let mut values = Values::new();
            let x = values.add(random_se3(seed));
            let factor = PriorFactor::new(x, random_se3(seed + 1));
            // The log map jumps at a rotation of π, where no derivative exists and central
            // differences straddle the jump (seed 9394925336661579529: 3e-5 rad from π).
            let r = factor.prior.local(values.get(x));
            prop_assume!(r.fixed_rows::<3>(3).norm() < std::f64::consts::PI - 1e-2);
            prop_assert!(jacobian_error(&factor, &values) < 1e-6);
        }
    }

    #[test]
    fn zero_residual_when_the_measurement_is_exact() {
        let mut values = Values::new();
        let a = random_se3(1);
        let b = random_se3(2);
        let i = values.add(a);
        let j = values.add(b);
        for error in [PoseError::Quaternion, PoseError::LogMap] {
            let f = BetweenFactor::new(i, j, a.inverse().compose(&b), error);
            let mut r = [1.0; 6];
            f.evaluate(&values, &mut r, None);
            assert!(r.iter().all(|v| v.abs() < 1e-12), "{r:?}");
        }
    }
}
