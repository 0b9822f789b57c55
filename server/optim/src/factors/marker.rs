//! A keyframe's observation of a marker: its four corners reprojected (8-D), given the marker's
//! pose and side length, and with the depth image, each corner's depth too (12-D, the depth in
//! the form keypoints use). ARCHITECTURE.md says why this replaces the paper's 6-D pose residual.

use crate::camera::{DepthResidual, Pinhole, VirtualStereo, MIN_DEPTH};
use crate::factor::Factor;
use crate::factors::projection::{pixel_residual, point_in_camera_jacobian};
use crate::lie::{hat, Se3};
use crate::values::{Key, Kind, Values, VarId};
use nalgebra::{DMatrixViewMut, Matrix3x6, Vector2, Vector3};

/// Corners of a square marker of side `side` in its own frame (z out of the face), in the order
/// ArUco reports them: top-left, top-right, bottom-right, bottom-left.
pub fn marker_corners(side: f64) -> [Vector3<f64>; 4] {
    let h = side / 2.0;
    [
        Vector3::new(-h, h, 0.0),
        Vector3::new(h, h, 0.0),
        Vector3::new(h, -h, 0.0),
        Vector3::new(-h, -h, 0.0),
    ]
}

/// `r = [π(T⁻¹·M·c_k) − z_k]_{k=1..4}` for keyframe `T = world_from_camera` and marker
/// `M = world_from_marker`; with depths ([`Self::with_depths`]) each corner's entry is a
/// keypoint's `[u, v, r_z]`.
#[derive(Clone, Debug)]
pub struct MarkerCornersFactor {
    keys: [VarId; 2],
    pub camera: Pinhole,
    corners: [Vector3<f64>; 4],
    /// Detected corners (undistorted pixels), in [`marker_corners`] order.
    pub measured: [Vector2<f64>; 4],
    /// The virtual stereo rig and each corner's measured right-image coordinate.
    depth: Option<(VirtualStereo, [f64; 4])>,
}

impl MarkerCornersFactor {
    pub fn new(
        world_from_camera: Key<Se3>,
        world_from_marker: Key<Se3>,
        camera: Pinhole,
        side: f64,
        measured: [Vector2<f64>; 4],
    ) -> Self {
        Self {
            keys: [world_from_camera.id, world_from_marker.id],
            camera,
            corners: marker_corners(side),
            measured,
            depth: None,
        }
    }

    /// Adds each corner's measured depth (camera z, metres) through `stereo`.
    pub fn with_depths(mut self, stereo: VirtualStereo, depths: [f64; 4]) -> Self {
        let right = std::array::from_fn(|k| self.measured[k].x - stereo.bf / depths[k]);
        self.depth = Some((stereo, right));
        self
    }

    /// Entries per corner: 2 (pixels) or 3 (pixels and depth).
    fn per_corner(&self) -> usize {
        if self.depth.is_some() {
            3
        } else {
            2
        }
    }
}

impl Factor for MarkerCornersFactor {
    fn keys(&self) -> &[VarId] {
        &self.keys
    }

    fn kinds(&self) -> &[Kind] {
        &[Kind::Pose, Kind::Pose]
    }

    fn residual_dim(&self) -> usize {
        4 * self.per_corner()
    }

    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        mut jacobian: Option<DMatrixViewMut<'_, f64>>,
    ) {
        let t = values.at::<Se3>(self.keys[0]);
        let m = values.at::<Se3>(self.keys[1]);
        let camera_from_world = t.rotation.to_rotation_matrix().into_inner().transpose();
        let world_from_marker = m.rotation.to_rotation_matrix().into_inner();
        let camera_from_marker = camera_from_world * world_from_marker;
        let n = self.per_corner();
        for (k, c) in self.corners.iter().enumerate() {
            let p_w = world_from_marker * c + m.translation;
            let p_c = camera_from_world * (p_w - t.translation);
            let row = n * k;
            let measured = [
                self.measured[k].x,
                self.measured[k].y,
                self.depth.map_or(0.0, |(_, right)| right[k]),
            ];
            let stereo = self.depth.map(|(stereo, _)| stereo);
            let r = pixel_residual(&self.camera, stereo, &measured, &p_c);
            residual[row..row + n].copy_from_slice(&r[..n]);
            if let Some(jac) = jacobian.as_mut() {
                // ∂r/∂p_c: the projection's rows, and the depth's row as the keypoints' factor.
                let d_uv = self.camera.project_jacobian(&p_c);
                let mut dg = nalgebra::Matrix3::zeros();
                dg.fixed_view_mut::<2, 3>(0, 0).copy_from(&d_uv);
                if let Some(stereo) = stereo {
                    if stereo.residual == DepthResidual::RightImage {
                        dg.fixed_view_mut::<1, 3>(2, 0).copy_from(&d_uv.row(0));
                    }
                    if p_c.z >= MIN_DEPTH {
                        dg[(2, 2)] += stereo.bf / (p_c.z * p_c.z);
                    }
                }
                // M·Exp([ρ; φ])·c ≈ M·c + R_M·ρ − R_M·[c]×·φ.
                let mut d_marker = Matrix3x6::zeros();
                d_marker
                    .fixed_view_mut::<3, 3>(0, 0)
                    .copy_from(&camera_from_marker);
                d_marker
                    .fixed_view_mut::<3, 3>(0, 3)
                    .copy_from(&(-camera_from_marker * hat(c)));
                let d_pose = dg * point_in_camera_jacobian(&p_c);
                let d_marker = dg * d_marker;
                for i in 0..n {
                    for j in 0..6 {
                        jac[(row + i, j)] = d_pose[(i, j)];
                        jac[(row + i, 6 + j)] = d_marker[(i, j)];
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{jacobian_error, random_se3, Rng};
    use nalgebra::UnitQuaternion;
    use proptest::prelude::*;

    fn camera() -> Pinhole {
        Pinhole::new(605.86, 606.27, 325.02, 244.76)
    }

    /// A marker `distance` metres in front of a random camera, turned by up to `tilt` radians.
    fn scene(seed: u64, distance: f64, tilt: f64) -> (Values, Key<Se3>, Key<Se3>) {
        let mut rng = Rng::new(seed);
        let t = random_se3(seed);
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let turn =
            UnitQuaternion::from_scaled_axis(rng.vector3(1.0).normalize() * rng.range(0.0, tilt));
        let camera_from_marker = Se3::new(
            turn * facing,
            Vector3::new(rng.range(-0.3, 0.3), rng.range(-0.2, 0.2), distance),
        );
        let mut values = Values::new();
        let kf = values.add(t);
        let marker = values.add(t.compose(&camera_from_marker));
        (values, kf, marker)
    }

    proptest! {
        #[test]
        fn jacobians_match_differences(seed in any::<u64>(), distance in prop::sample::select(vec![0.3, 1.0, 6.0]), tilt in prop::sample::select(vec![0.0, 0.6, 1.45])) {
            let (values, kf, marker) = scene(seed, distance, tilt);
            let measured = [Vector2::new(300.0, 200.0), Vector2::new(330.0, 201.0), Vector2::new(331.0, 230.0), Vector2::new(299.0, 229.0)];
            let f = MarkerCornersFactor::new(kf, marker, camera(), 0.08, measured);
            let err = jacobian_error(&f, &values);
            prop_assert!(err < 1e-6, "{err}");
            for form in [VirtualStereo::disparity(40.0), VirtualStereo::right_image(40.0)] {
                let f = MarkerCornersFactor::new(kf, marker, camera(), 0.08, measured)
                    .with_depths(form, [distance * 0.9, distance, distance * 1.1, distance]);
                let err = jacobian_error(&f, &values);
                prop_assert!(err < 1e-6, "{form:?}: {err}");
            }
        }
    }

    /// An 8 cm marker 1 m ahead of a camera at the origin, facing it (its z towards the
    /// camera), and where the pinhole puts its corners: the top-left corner (−4, +4) cm in the
    /// marker frame is (−4, −4) cm in the camera frame, up and left.
    fn facing_marker_ahead() -> (Values, Key<Se3>, Key<Se3>, [Vector2<f64>; 4]) {
        let mut values = Values::new();
        let kf = values.add(Se3::identity());
        let facing = UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0);
        let marker = values.add(Se3::new(facing, Vector3::new(0.0, 0.0, 1.0)));
        let cam = camera();
        let (dx, dy) = (cam.fx * 0.04, cam.fy * 0.04);
        let measured = [
            Vector2::new(cam.cx - dx, cam.cy - dy),
            Vector2::new(cam.cx + dx, cam.cy - dy),
            Vector2::new(cam.cx + dx, cam.cy + dy),
            Vector2::new(cam.cx - dx, cam.cy + dy),
        ];
        (values, kf, marker, measured)
    }

    #[test]
    fn a_corner_depth_off_by_one_pixel_of_disparity_gives_a_residual_of_one() {
        // Every corner of the facing marker is at depth 1 m (its face is square to the camera).
        let (values, kf, marker, measured) = facing_marker_ahead();
        let cam = camera();
        let bf = 40.0;
        // Disparity bf/z: 40 px at 1 m; 41 px at the depth that the third corner reports.
        let depths = [1.0, 1.0, bf / 41.0, 1.0];
        let f = MarkerCornersFactor::new(kf, marker, cam, 0.08, measured)
            .with_depths(VirtualStereo::disparity(bf), depths);
        assert_eq!(f.residual_dim(), 12);
        let mut r = [9.0; 12];
        f.evaluate(&values, &mut r, None);
        for (i, v) in r.iter().enumerate() {
            let expected = if i == 8 { 1.0 } else { 0.0 };
            assert!((v - expected).abs() < 1e-9, "entry {i}: {r:?}");
        }
    }

    #[test]
    fn corners_of_a_facing_marker_land_where_the_pinhole_puts_them() {
        let (values, kf, marker, measured) = facing_marker_ahead();
        let cam = camera();
        let f = MarkerCornersFactor::new(kf, marker, cam, 0.08, measured);
        let mut r = [1.0; 8];
        f.evaluate(&values, &mut r, None);
        assert!(r.iter().all(|v| v.abs() < 1e-9), "{r:?}");
    }
}
