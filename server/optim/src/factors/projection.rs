//! Reprojection of map points into keyframes: RGB-D (u, v and the depth as a disparity against
//! the virtual right-image u_r that ORB-SLAM measures for RGB-D) and monocular (u, v).
//!
//! A keyframe variable is `world_from_camera`. Under its right perturbation `T·Exp([ρ; φ])` a
//! world point seen from the camera, `p_c = Tᵀ·p_w`, moves by `−ρ + [p_c]×φ`.

use crate::camera::{DepthResidual, Pinhole, VirtualStereo, MIN_DEPTH};
use crate::factor::Factor;
use crate::lie::{hat, Se3};
use crate::values::{Key, Kind, Values, VarId};
use nalgebra::{DMatrixViewMut, Matrix3, Matrix3x6, Vector2, Vector3};

/// A keyframe `T = world_from_camera` as its camera sees the world, `p_c = R_cw·(p − t)`, with
/// the rotation matrix formed once: callers that project many points keep one per pose.
#[derive(Clone, Copy, Debug)]
pub(crate) struct CameraFromWorld {
    /// `R_cw`.
    pub rotation: Matrix3<f64>,
    /// The camera centre in the world, `t`.
    pub centre: Vector3<f64>,
}

impl CameraFromWorld {
    pub fn new(world_from_camera: &Se3) -> Self {
        Self {
            rotation: world_from_camera
                .rotation
                .to_rotation_matrix()
                .into_inner()
                .transpose(),
            centre: world_from_camera.translation,
        }
    }

    #[inline(always)]
    pub fn transform(&self, p_w: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * (p_w - self.centre)
    }
}

/// The residual of a point `p_c` in the camera against a keypoint measured at `(u, v)` with,
/// for RGB-D (`stereo`), the virtual right-image coordinate `u_r = u − bf/z` of its depth:
/// `[u − u_m, v − v_m, r_z]`, where `r_z` is the disparity's `bf/z_m − bf/z` or the right
/// image's `u − bf/z − u_r,m` ([`DepthResidual`]), and 0 without depth. The one residual of
/// every reprojection path (the factors here, `bundle`'s and the normal equations' fast paths,
/// pose-only tracking).
#[inline(always)]
pub(crate) fn pixel_residual(
    camera: &Pinhole,
    stereo: Option<VirtualStereo>,
    measured: &[f64; 3],
    p_c: &Vector3<f64>,
) -> [f64; 3] {
    let uv = camera.project(p_c);
    let depth = match stereo {
        Some(s) => {
            let disparity = s.bf / p_c.z.max(MIN_DEPTH);
            match s.residual {
                DepthResidual::Disparity => (measured[0] - measured[2]) - disparity,
                DepthResidual::RightImage => uv.x - disparity - measured[2],
            }
        }
        None => 0.0,
    };
    [uv.x - measured[0], uv.y - measured[1], depth]
}

/// `∂p_c/∂δ` for the camera pose: `[−I, [p_c]×]`.
pub(crate) fn point_in_camera_jacobian(p_c: &Vector3<f64>) -> Matrix3x6<f64> {
    let mut j = Matrix3x6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-Matrix3::identity()));
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&hat(p_c));
    j
}

/// Writes `∂r/∂δ_pose` and `∂r/∂δ_point` for a residual `r = g(p_c)` with `∂g/∂p_c = dg`.
fn write_jacobian<const M: usize>(
    jac: &mut DMatrixViewMut<'_, f64>,
    dg: &nalgebra::SMatrix<f64, M, 3>,
    p_c: &Vector3<f64>,
    camera_from_world: &Matrix3<f64>,
) {
    jac.fixed_view_mut::<M, 6>(0, 0)
        .copy_from(&(dg * point_in_camera_jacobian(p_c)));
    jac.fixed_view_mut::<M, 3>(0, 6)
        .copy_from(&(dg * camera_from_world));
}

/// A keypoint with depth, measured as ORB-SLAM does, `(u, v, u_r)` with `u_r = u − bf/z` (`bf`
/// the focal length times the virtual stereo baseline, ORB-SLAM's `mbf`); its residual is
/// [`pixel_residual`]'s, the depth as a disparity unless [`Self::with_residual`] says otherwise.
#[derive(Clone, Debug)]
pub struct StereoProjectionFactor {
    keys: [VarId; 2],
    pub camera: Pinhole,
    pub stereo: VirtualStereo,
    /// Measured `(u, v, u_r)`, pixels.
    pub measured: Vector3<f64>,
}

impl StereoProjectionFactor {
    pub fn new(
        world_from_camera: Key<Se3>,
        point: Key<Vector3<f64>>,
        camera: Pinhole,
        bf: f64,
        measured: Vector3<f64>,
    ) -> Self {
        Self {
            keys: [world_from_camera.id, point.id],
            camera,
            stereo: VirtualStereo::disparity(bf),
            measured,
        }
    }

    /// The same factor with its depth entering as `residual`.
    pub fn with_residual(mut self, residual: DepthResidual) -> Self {
        self.stereo.residual = residual;
        self
    }
}

impl Factor for StereoProjectionFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose, Kind::Point]
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
        let t = values.at::<Se3>(self.keys[0]);
        let p_w = values.at::<Vector3<f64>>(self.keys[1]);
        let view = CameraFromWorld::new(t);
        let p_c = view.transform(p_w);
        let m = &self.measured;
        residual.copy_from_slice(&pixel_residual(
            &self.camera,
            Some(self.stereo),
            &[m.x, m.y, m.z],
            &p_c,
        ));
        let z = p_c.z.max(MIN_DEPTH);
        if let Some(mut jac) = jacobian {
            let d_uv = self.camera.project_jacobian(&p_c);
            let mut dg = nalgebra::Matrix3::zeros();
            dg.fixed_view_mut::<2, 3>(0, 0).copy_from(&d_uv);
            if self.stereo.residual == DepthResidual::RightImage {
                dg.fixed_view_mut::<1, 3>(2, 0).copy_from(&d_uv.row(0));
            }
            if p_c.z >= MIN_DEPTH {
                dg[(2, 2)] += self.stereo.bf / (z * z);
            }
            write_jacobian::<3>(&mut jac, &dg, &p_c, &view.rotation);
        }
    }
}

/// `r = π(T⁻¹·p) − measured`: a keypoint without depth.
#[derive(Clone, Debug)]
pub struct ProjectionFactor {
    keys: [VarId; 2],
    pub camera: Pinhole,
    /// Measured `(u, v)`, pixels.
    pub measured: Vector2<f64>,
}

impl ProjectionFactor {
    pub fn new(
        world_from_camera: Key<Se3>,
        point: Key<Vector3<f64>>,
        camera: Pinhole,
        measured: Vector2<f64>,
    ) -> Self {
        Self {
            keys: [world_from_camera.id, point.id],
            camera,
            measured,
        }
    }
}

impl Factor for ProjectionFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose, Kind::Point]
    }

    fn residual_dim(&self) -> usize {
        2
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let t = values.at::<Se3>(self.keys[0]);
        let p_w = values.at::<Vector3<f64>>(self.keys[1]);
        let view = CameraFromWorld::new(t);
        let p_c = view.transform(p_w);
        let m = &self.measured;
        let r = pixel_residual(&self.camera, None, &[m.x, m.y, 0.0], &p_c);
        residual.copy_from_slice(&r[..2]);
        if let Some(mut jac) = jacobian {
            let dg = self.camera.project_jacobian(&p_c);
            write_jacobian::<2>(&mut jac, &dg, &p_c, &view.rotation);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{jacobian_error, random_se3, Rng};
    use proptest::prelude::*;

    pub(crate) fn d435() -> Pinhole {
        Pinhole::new(605.86, 606.27, 325.02, 244.76)
    }

    /// A camera and a point in front of it at `depth` metres, seen near the image's edge or centre.
    fn scene(seed: u64, depth: f64) -> (Values, Key<Se3>, Key<Vector3<f64>>) {
        let mut rng = Rng::new(seed);
        let t = random_se3(seed);
        let p_c = Vector3::new(
            rng.range(-0.5, 0.5) * depth,
            rng.range(-0.4, 0.4) * depth,
            depth,
        );
        let mut values = Values::new();
        let pose = values.add(t);
        let point = values.add(t.transform_point(&p_c));
        (values, pose, point)
    }

    proptest! {
        #[test]
        fn stereo_projection_jacobians_match_differences(seed in any::<u64>(), depth in prop::sample::select(vec![0.05, 0.5, 3.0, 40.0])) {
            let (values, pose, point) = scene(seed, depth);
            for form in [DepthResidual::Disparity, DepthResidual::RightImage] {
                let f = StereoProjectionFactor::new(pose, point, d435(), 40.0, Vector3::new(300.0, 200.0, 290.0))
                    .with_residual(form);
                let err = jacobian_error(&f, &values);
                prop_assert!(err < 1e-6, "{form:?}: {err}");
            }
        }

        #[test]
        fn projection_jacobians_match_differences(seed in any::<u64>(), depth in prop::sample::select(vec![0.05, 0.5, 3.0, 40.0])) {
            let (values, pose, point) = scene(seed, depth);
            let f = ProjectionFactor::new(pose, point, d435(), Vector2::new(10.0, 470.0));
            let err = jacobian_error(&f, &values);
            prop_assert!(err < 1e-6, "{err}");
        }
    }

    #[test]
    fn residuals_vanish_at_the_truth_and_depth_enters_by_its_form() {
        let camera = d435();
        let mut values = Values::new();
        let pose = values.add(Se3::identity());
        let point = values.add(Vector3::new(0.2, -0.1, 2.0));
        let residual = |measured: Vector3<f64>, form: DepthResidual| {
            let f = StereoProjectionFactor::new(pose, point, camera, 40.0, measured)
                .with_residual(form);
            let mut r = [0.0; 3];
            f.evaluate(&values, &mut r, None);
            r
        };
        // Computed by hand: u = 605.86·0.1 + 325.02, v = 606.27·(−0.05) + 244.76, u_r = u − 40/2.
        for form in [DepthResidual::Disparity, DepthResidual::RightImage] {
            let r = residual(Vector3::new(385.606, 214.4465, 365.606), form);
            assert!(r.iter().all(|v| v.abs() < 1e-9), "{form:?}: {r:?}");
        }
        // The keypoint 1 px to the left, its depth unchanged (u_r moves with u): the disparity
        // sees it in u's entry alone, the right image in its own as well.
        let shifted = Vector3::new(384.606, 214.4465, 364.606);
        for (form, third) in [
            (DepthResidual::Disparity, 0.0),
            (DepthResidual::RightImage, 1.0),
        ] {
            let r = residual(shifted, form);
            assert!(
                (r[0] - 1.0).abs() < 1e-9 && r[1].abs() < 1e-9 && (r[2] - third).abs() < 1e-9,
                "{form:?}: {r:?}"
            );
        }
        // Measured at 2.5 m instead of 2 m (bf/z 16 px instead of 20): only the third entry,
        // in both forms.
        for form in [DepthResidual::Disparity, DepthResidual::RightImage] {
            let r = residual(Vector3::new(385.606, 214.4465, 369.606), form);
            assert!(
                r[0].abs() < 1e-9 && r[1].abs() < 1e-9 && (r[2] + 4.0).abs() < 1e-9,
                "{form:?}: {r:?}"
            );
        }
    }

    #[test]
    fn a_point_behind_the_camera_gives_a_finite_residual() {
        let mut values = Values::new();
        let pose = values.add(Se3::identity());
        let point = values.add(Vector3::new(0.2, -0.1, -2.0));
        let f = StereoProjectionFactor::new(
            pose,
            point,
            d435(),
            40.0,
            Vector3::new(300.0, 200.0, 290.0),
        );
        let (analytic, _) = crate::testing::factor_jacobians(&f, &values);
        let mut r = [0.0; 3];
        f.evaluate(&values, &mut r, None);
        assert!(r.iter().all(|v| v.is_finite()) && r[0].abs() > 1e4);
        assert!(analytic.iter().all(|v| v.is_finite()));
    }
}
