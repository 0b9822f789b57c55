//! Bundle adjustment's bulk, a keyframe seeing a map point through a pinhole (RGB-D or
//! monocular), without dynamic dispatch: cost passes and the normal-equation blocks of these
//! factors are computed here from a copy of the factor's data, with each pose's rotation matrix
//! formed once per set of values instead of once per observation.
//!
//! The blocks come from the Jacobian's structure, not from the Jacobian. With
//! `p_c = R_cw·(p_w − t)` the residual `r = g(p_c) − m` has `J = D·[P | R_cw]`, where
//! `D = ∂g/∂p_c` and `P = [−I, [p_c]×]` is the pose's right perturbation
//! ([`crate::factors::projection`]). With `G = w²·DᵀD` and `h = w²·Dᵀr` (`w²` the isotropic
//! information times the kernel's weight):
//!
//! - pose block `AᵀA = Pᵀ·G·P`, coupling `AᵀB = Pᵀ·G·R_cw`, point block `BᵀB = R_cwᵀ·G·R_cw`;
//! - gradients `Aᵀr = Pᵀ·h` and `Bᵀr = R_cwᵀ·h`;
//!
//! and `Pᵀ·x = [−x; x × p_c]`. That is about half the arithmetic of forming the 3 × 9 Jacobian
//! and its products, and no factor is called through a `dyn` pointer. A test checks the blocks
//! against the factors' own Jacobians. The normal equations evaluate most of these factors
//! four at a time with the same formulas (`normal::observations`); this one-at-a-time form
//! serves the rest, and pose-only optimisation shares its Gauss–Newton terms.

use crate::camera::{DepthResidual, Pinhole, VirtualStereo, MIN_DEPTH};
use crate::factor::{Factor, Kernel};
use crate::factors::projection::{
    pixel_residual, CameraFromWorld, ProjectionFactor, StereoProjectionFactor,
};
use crate::values::{Values, VarId, Variable};
use nalgebra::{Matrix3, Vector3};
use std::any::Any;

/// A reprojection factor's data, copied when it joins a problem with isotropic information.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Reprojection {
    pub pose: VarId,
    pub point: VarId,
    camera: Pinhole,
    /// RGB-D `(u, v, u_r)`, `None` for `(u, v)`.
    stereo: Option<VirtualStereo>,
    /// Measured pixels; the third is 0 without depth.
    measured: [f64; 3],
    /// `s` of the information `R = s·I`.
    scale: f64,
}

impl Reprojection {
    /// The fast form of `factor` if it is a reprojection factor whose information is `s·I`.
    pub fn of(factor: &dyn Any, isotropic_scale: Option<f64>) -> Option<Self> {
        let scale = isotropic_scale?;
        if let Some(f) = factor.downcast_ref::<StereoProjectionFactor>() {
            let [pose, point] = [f.keys()[0], f.keys()[1]];
            return Some(Self {
                pose,
                point,
                camera: f.camera,
                stereo: Some(f.stereo),
                measured: [f.measured.x, f.measured.y, f.measured.z],
                scale,
            });
        }
        let f = factor.downcast_ref::<ProjectionFactor>()?;
        let [pose, point] = [f.keys()[0], f.keys()[1]];
        Some(Self {
            pose,
            point,
            camera: f.camera,
            stereo: None,
            measured: [f.measured.x, f.measured.y, 0.0],
            scale,
        })
    }

    /// The residual (the third entry 0 without depth) and the point in the camera, by the
    /// factors' own function, so costs have the same bits on both paths.
    #[inline(always)]
    fn residual(&self, view: &CameraFromWorld, values: &Values) -> ([f64; 3], Vector3<f64>) {
        let p_c = view.transform(values.at::<Vector3<f64>>(self.point));
        (
            pixel_residual(&self.camera, self.stereo, &self.measured, &p_c),
            p_c,
        )
    }

    /// Measured `(u, v, u_r)`; the third is 0 without depth.
    pub fn measured(&self) -> [f64; 3] {
        self.measured
    }

    /// `s` of the information `s·I`.
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// The virtual stereo pair of RGB-D, `None` for monocular.
    pub fn stereo(&self) -> Option<VirtualStereo> {
        self.stereo
    }

    pub fn camera(&self) -> &Pinhole {
        &self.camera
    }

    /// `s = rᵀΩr`.
    #[inline(always)]
    fn chi2(&self, r: &[f64; 3]) -> f64 {
        self.scale * self.scale * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    }

    /// `ρ(s)`.
    #[inline]
    pub fn cost(&self, views: &PoseViews, values: &Values, kernel: Option<Kernel>) -> f64 {
        let (r, _) = self.residual(views.get(self.pose), values);
        let s = self.chi2(&r);
        kernel.map_or(s, |k| k.evaluate(s).0)
    }

    /// Writes every entry of the blocks this factor adds to the normal equations (weighted by
    /// `ρ'`) to `out`, and returns `ρ(s)`.
    #[inline(always)]
    pub fn blocks(
        &self,
        views: &PoseViews,
        values: &Values,
        kernel: Option<Kernel>,
        out: &mut PosePointBlocks,
    ) -> f64 {
        let view = views.get(self.pose);
        let (r, p) = self.residual(view, values);
        let s = self.chi2(&r);
        let (cost, weight) = kernel.map_or((s, 1.0), |k| k.evaluate(s));
        let w2 = self.scale * self.scale * weight.max(0.0);
        let (g, h) = gauss_newton_terms(&self.camera, self.stereo, &p, &r, w2);
        let [g00, g02, g11, g12, g22] = [g.g00, g.g02, g.g11, g.g12, g.g22];
        let rot = &view.rotation;
        let p = [p.x, p.y, p.z];
        // G·R_cw by column; the point block Rᵀ·(G·R) and the coupling Pᵀ·(G·R).
        let mut gr = [[0.0; 3]; 3];
        for (c, gr) in gr.iter_mut().enumerate() {
            let (r0, r1, r2) = (rot[(0, c)], rot[(1, c)], rot[(2, c)]);
            *gr = [
                g00 * r0 + g02 * r2,
                g11 * r1 + g12 * r2,
                g02 * r0 + g12 * r1 + g22 * r2,
            ];
            let x = cross(gr, &p);
            out.coupling[c] = [-gr[0], -gr[1], -gr[2], x[0], x[1], x[2]];
        }
        for (c, gr) in gr.iter().enumerate() {
            for i in 0..=c {
                let m = rot[(0, i)] * gr[0] + rot[(1, i)] * gr[1] + rot[(2, i)] * gr[2];
                out.point[c][i] = m;
                out.point[i][c] = m;
            }
        }
        out.pose = g.pose_block(&p);
        out.g_pose = pose_gradient(&h, &p);
        out.g_point =
            std::array::from_fn(|i| rot[(0, i)] * h[0] + rot[(1, i)] * h[1] + rot[(2, i)] * h[2]);
        cost
    }
}

/// `G = w²·DᵀD` of a pinhole residual, `D = ∂(u, v[, r_z])/∂p_c` ([`pixel_residual`]):
/// symmetric, and `G01 = 0` because `u` and the depth's entry do not depend on `y`, nor `v` on
/// `x`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Gram3 {
    g00: f64,
    g02: f64,
    g11: f64,
    g12: f64,
    g22: f64,
}

/// `G = w²·DᵀD` and `h = w²·Dᵀr` for the residual `r` (its third entry 0 without depth) of a
/// point `p_c` seen by `camera`; `stereo` is `Some` for RGB-D `(u, v, u_r)`.
#[inline(always)]
pub(crate) fn gauss_newton_terms(
    camera: &Pinhole,
    stereo: Option<VirtualStereo>,
    p_c: &Vector3<f64>,
    r: &[f64; 3],
    w2: f64,
) -> (Gram3, [f64; 3]) {
    // D's entries: u's row [a, 0, b], v's [0, c, d] and, with depth, the disparity's
    // [0, 0, e] or the right image's [a, 0, b + e]; the depth column is zero where the depth
    // is clamped (as `Pinhole::project_jacobian`).
    let clamped = p_c.z < MIN_DEPTH;
    let iz = 1.0 / p_c.z.max(MIN_DEPTH);
    let (a, c) = (camera.fx * iz, camera.fy * iz);
    let (b, d) = if clamped {
        (0.0, 0.0)
    } else {
        (-a * p_c.x * iz, -c * p_c.y * iz)
    };
    let (mut g00, mut g02, g11, g12, mut g22) = (a * a, a * b, c * c, c * d, b * b + d * d);
    let (mut h0, h1, mut h2) = (a * r[0], c * r[1], b * r[0] + d * r[1]);
    if let Some(stereo) = stereo {
        let disparity = if clamped { 0.0 } else { stereo.bf * iz * iz };
        let e = match stereo.residual {
            DepthResidual::Disparity => disparity,
            DepthResidual::RightImage => {
                let e = if clamped { b } else { b + disparity };
                g00 += a * a;
                g02 += a * e;
                h0 += a * r[2];
                e
            }
        };
        g22 += e * e;
        h2 += e * r[2];
    }
    let g = Gram3 {
        g00: g00 * w2,
        g02: g02 * w2,
        g11: g11 * w2,
        g12: g12 * w2,
        g22: g22 * w2,
    };
    (g, [h0 * w2, h1 * w2, h2 * w2])
}

impl Gram3 {
    /// The pose's block `Pᵀ·G·P = [[G, −G·[p]×], [·, [p]×ᵀ·G·[p]×]]` by column, `p` the point
    /// in the camera; column j of `G·[p]×` is `n_j = G·(p × e_j)`.
    #[inline(always)]
    pub fn pose_block(&self, p: &[f64; 3]) -> [[f64; 6]; 6] {
        let Self {
            g00,
            g02,
            g11,
            g12,
            g22,
        } = *self;
        let (px, py, pz) = (p[0], p[1], p[2]);
        let n = [
            [-g02 * py, g11 * pz - g12 * py, g12 * pz - g22 * py],
            [g02 * px - g00 * pz, g12 * px, g22 * px - g02 * pz],
            [g00 * py, -g11 * px, g02 * py - g12 * px],
        ];
        let g = [[g00, 0.0, g02], [0.0, g11, g12], [g02, g12, g22]];
        let mut out = [[0.0; 6]; 6];
        for j in 0..3 {
            let x = cross(&n[j], p);
            out[j] = [g[j][0], g[j][1], g[j][2], -n[0][j], -n[1][j], -n[2][j]];
            out[3 + j] = [-n[j][0], -n[j][1], -n[j][2], x[0], x[1], x[2]];
        }
        out
    }
}

/// The pose's gradient `Pᵀ·h = [−h; h × p]`.
#[inline(always)]
pub(crate) fn pose_gradient(h: &[f64; 3], p: &[f64; 3]) -> [f64; 6] {
    let x = cross(h, p);
    [-h[0], -h[1], -h[2], x[0], x[1], x[2]]
}

#[inline(always)]
fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The blocks of `JᵀJ` and `Jᵀr` that a pose–point factor contributes, with `J = [A | B]`
/// (`A` the pose's six columns, `B` the point's three): `AᵀA`, `AᵀB`, `BᵀB`, `Aᵀr`, `Bᵀr`,
/// each by column.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct PosePointBlocks {
    pub pose: [[f64; 6]; 6],
    pub coupling: [[f64; 6]; 3],
    pub point: [[f64; 3]; 3],
    pub g_pose: [f64; 6],
    pub g_point: [f64; 3],
}

/// Every pose variable as its camera sees the world, for one set of values; empty for a problem
/// without reprojection factors.
#[derive(Clone, Debug, Default)]
pub(crate) struct PoseViews(Vec<CameraFromWorld>);

impl PoseViews {
    pub fn new(values: &Values, needed: bool) -> Self {
        let mut views = Self::default();
        views.update(values, needed);
        views
    }

    /// Recomputes the views for `values` (nothing when not `needed`).
    pub fn update(&mut self, values: &Values, needed: bool) {
        self.0.clear();
        if !needed {
            return;
        }
        let unused = CameraFromWorld {
            rotation: Matrix3::identity(),
            centre: Vector3::zeros(),
        };
        self.0
            .extend(values.ids().map(|id| match values.variable(id) {
                Some(Variable::Pose(t)) => CameraFromWorld::new(t),
                _ => unused,
            }));
    }

    #[inline(always)]
    pub fn get(&self, pose: VarId) -> &CameraFromWorld {
        &self.0[pose.index()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factor::Information;
    use crate::problem::{Entry, Linearized};
    use crate::testing::{random_se3, Rng};
    use crate::values::Key;
    use crate::Se3;

    /// The blocks formed from a factor's own whitened, weighted Jacobian, as the general path does.
    fn blocks_from_jacobian(e: &Entry, values: &Values) -> (f64, PosePointBlocks) {
        let mut lin = Linearized::default();
        let cost = lin.linearize(e, values);
        let m = e.factor.residual_dim();
        let j = |row: usize, col: usize| lin.jacobian[col * m + row];
        let mut out = PosePointBlocks::default();
        for k in 0..m {
            let r = lin.residual[k];
            for c in 0..9 {
                for i in 0..9 {
                    let x = j(k, i) * j(k, c);
                    match (i < 6, c < 6) {
                        (true, true) => out.pose[c][i] += x,
                        (true, false) => out.coupling[c - 6][i] += x,
                        (false, false) => out.point[c - 6][i - 6] += x,
                        (false, true) => {}
                    }
                }
                if c < 6 {
                    out.g_pose[c] += j(k, c) * r;
                } else {
                    out.g_point[c - 6] += j(k, c) * r;
                }
            }
        }
        (cost, out)
    }

    fn max_relative_difference(a: &PosePointBlocks, b: &PosePointBlocks) -> f64 {
        let flat = |x: &PosePointBlocks| -> Vec<f64> {
            x.pose
                .iter()
                .flatten()
                .chain(x.coupling.iter().flatten())
                .chain(x.point.iter().flatten())
                .chain(&x.g_pose)
                .chain(&x.g_point)
                .copied()
                .collect()
        };
        let (a, b) = (flat(a), flat(b));
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-300);
        a.iter()
            .zip(&b)
            .fold(0.0, |m, (x, y)| m.max((x - y).abs() / scale))
    }

    #[test]
    fn blocks_equal_those_of_the_factors_own_jacobians() {
        let camera = Pinhole::new(605.86, 606.27, 325.02, 244.76);
        let mut rng = Rng::new(7);
        let mut checked = 0;
        for seed in 0..200u64 {
            let t = random_se3(seed);
            // Near and far points, in view and off to the side, one behind the camera
            // (its depth is clamped).
            let depth = [0.3, 1.5, 6.0, 30.0, -0.5][seed as usize % 5];
            let p_c = Vector3::new(rng.range(-0.6, 0.6), rng.range(-0.5, 0.5), 1.0) * depth;
            let mut values = Values::new();
            let pose: Key<Se3> = values.add(t);
            let point = values.add(t.transform_point(&p_c));
            let measured = Vector3::new(rng.range(0.0, 640.0), rng.range(0.0, 480.0), 0.0);
            let measured = measured + Vector3::new(0.0, 0.0, measured.x - rng.range(0.0, 40.0));
            let sigma = [1.0, 1.2, 1.44, 2.07][seed as usize % 4];
            let kernel = [
                None,
                Some(Kernel::Huber(7.815f64.sqrt())),
                Some(Kernel::Huber(0.1)),
                Some(Kernel::Cauchy(1.0)),
            ][seed as usize % 4];
            let form =
                [DepthResidual::Disparity, DepthResidual::RightImage][(seed / 4) as usize % 2];
            let stereo = StereoProjectionFactor::new(pose, point, camera, 30.3, measured)
                .with_residual(form);
            let mono = ProjectionFactor::new(pose, point, camera, measured.xy());
            let factors: [(Box<dyn Factor>, &dyn Any, usize); 2] = [
                (Box::new(stereo.clone()), &stereo, 3),
                (Box::new(mono.clone()), &mono, 2),
            ];
            for (factor, any, dim) in factors {
                let information = Information::isotropic(dim, sigma).unwrap();
                let fast = Reprojection::of(any, information.isotropic_scale()).unwrap();
                let entry = Entry {
                    factor,
                    information,
                    kernel,
                    columns: vec![0, 6],
                    total_dim: 9,
                    reprojection: Some(fast),
                };
                let views = PoseViews::new(&values, true);
                let mut blocks = PosePointBlocks::default();
                let cost = fast.blocks(&views, &values, kernel, &mut blocks);
                let (expected_cost, expected) = blocks_from_jacobian(&entry, &values);
                assert_eq!(cost, expected_cost, "seed {seed}, dim {dim}");
                assert_eq!(fast.cost(&views, &values, kernel), expected_cost);
                let diff = max_relative_difference(&blocks, &expected);
                assert!(diff < 1e-12, "seed {seed}, dim {dim}: {diff:e}");
                checked += 1;
            }
        }
        assert_eq!(checked, 400);
    }

    #[test]
    fn only_reprojection_factors_with_isotropic_information_take_the_fast_path() {
        let mut values = Values::new();
        let pose = values.add(Se3::identity());
        let point = values.add(Vector3::new(0.0, 0.0, 2.0));
        let camera = Pinhole::new(500.0, 500.0, 320.0, 240.0);
        let stereo = StereoProjectionFactor::new(pose, point, camera, 40.0, Vector3::zeros());
        assert!(Reprojection::of(&stereo, Some(1.0)).is_some());
        assert!(Reprojection::of(&stereo, None).is_none());
        let prior = crate::factors::PriorFactor::new(pose, Se3::identity());
        assert!(Reprojection::of(&prior, Some(1.0)).is_none());
    }
}
