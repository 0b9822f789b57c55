//! Helpers for checking factors and manifolds: central differences and deterministic randomness.
//! Public so that integration tests and benchmarks of other crates can use them too.

mod building;

pub use building::{building_scene, BuildingConfig, BuildingScene};

use crate::factor::Factor;
use crate::lie::Se3;
use crate::values::Values;
use nalgebra::{DMatrix, DMatrixViewMut, DVector, Vector2, Vector3, Vector6};

/// A file of the shared test data (`../shared/data` beside the repository, or
/// `VSGRAPHS_TEST_DATA`); `None`, with a message saying why the caller skips, when absent.
pub fn shared_data(relative: &str) -> Option<std::path::PathBuf> {
    let dir = std::env::var_os("VSGRAPHS_TEST_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data")
        });
    let path = dir.join(relative);
    if path.exists() {
        Some(path)
    } else {
        eprintln!(
            "skipped: {} is absent (set VSGRAPHS_TEST_DATA)",
            path.display()
        );
        None
    }
}

/// A small deterministic generator (SplitMix64), so tests need no `rand` and repeat exactly.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u = self.uniform().max(1e-300);
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }

    pub fn vector3(&mut self, scale: f64) -> Vector3<f64> {
        Vector3::new(self.normal(), self.normal(), self.normal()) * scale
    }
}

/// A random tangent vector with entries in [-1, 1).
pub fn random_vector6(seed: u64) -> Vector6<f64> {
    let mut rng = Rng::new(seed);
    Vector6::from_fn(|_, _| rng.range(-1.0, 1.0))
}

/// An RGB-D keypoint as a sensor gives it, `(u, v, u_r)`: the pixel and the disparity `bf/z`
/// each with noise of `sigma` pixels, and `u_r` the noisy `u` less the noisy disparity (not an
/// independent right-image measurement: an RGB-D camera has no second image).
pub fn rgbd_measurement(
    uv: &Vector2<f64>,
    disparity: f64,
    rng: &mut Rng,
    sigma: f64,
) -> Vector3<f64> {
    let noise = rng.vector3(sigma);
    let (u, v) = (uv.x + noise.x, uv.y + noise.y);
    Vector3::new(u, v, u - (disparity + noise.z))
}

/// A random pose: translation within ±5 m, any rotation (angle up to π).
pub fn random_se3(seed: u64) -> Se3 {
    let mut rng = Rng::new(seed ^ 0x5EED);
    let axis = rng.vector3(1.0).normalize();
    let angle = rng.range(0.0, std::f64::consts::PI);
    Se3::new(
        nalgebra::UnitQuaternion::from_scaled_axis(axis * angle),
        Vector3::new(
            rng.range(-5.0, 5.0),
            rng.range(-5.0, 5.0),
            rng.range(-5.0, 5.0),
        ),
    )
}

/// Central-difference Jacobian of `f` at `x`.
pub fn numeric_jacobian(
    n: usize,
    x: &DVector<f64>,
    f: impl Fn(&DVector<f64>) -> DVector<f64>,
) -> DMatrix<f64> {
    let h = 1e-6;
    let m = f(x).len();
    let mut j = DMatrix::zeros(m, n);
    for c in 0..n {
        let mut plus = x.clone();
        plus[c] += h;
        let mut minus = x.clone();
        minus[c] -= h;
        let d = (f(&plus) - f(&minus)) / (2.0 * h);
        j.set_column(c, &d);
    }
    j
}

/// The factor's analytic Jacobian and the central-difference one, perturbing each variable
/// by `⊕` (as the solver does).
pub fn factor_jacobians(factor: &dyn Factor, values: &Values) -> (DMatrix<f64>, DMatrix<f64>) {
    let m = factor.residual_dim();
    let dims: Vec<usize> = factor.kinds().iter().map(|k| k.dim()).collect();
    let n: usize = dims.iter().sum();
    let mut r = vec![0.0; m];
    let mut analytic = DMatrix::zeros(m, n);
    factor.evaluate(values, &mut r, Some(DMatrixViewMut::from(&mut analytic)));
    let mut numeric = DMatrix::zeros(m, n);
    let h = 1e-6;
    let mut col = 0;
    for (k, &id) in factor.keys().iter().enumerate() {
        for i in 0..dims[k] {
            let eval = |sign: f64| {
                let mut perturbed = values.clone();
                let mut delta = vec![0.0; dims[k]];
                delta[i] = sign * h;
                let v = perturbed.variable_mut(id);
                *v = v.retract(&delta);
                let mut out = vec![0.0; m];
                factor.evaluate(&perturbed, &mut out, None);
                DVector::from_vec(out)
            };
            let d = (eval(1.0) - eval(-1.0)) / (2.0 * h);
            numeric.set_column(col, &d);
            col += 1;
        }
    }
    (analytic, numeric)
}

/// Relative error `‖A − N‖ / ‖N‖` of a factor's Jacobian (absolute when `N` is tiny).
pub fn jacobian_error(factor: &dyn Factor, values: &Values) -> f64 {
    let (a, n) = factor_jacobians(factor, values);
    (&a - &n).norm() / n.norm().max(1e-3)
}

/// Settings of a synthetic RGB-D bundle adjustment ([`bundle_scene`]).
#[derive(Clone, Debug)]
pub struct BundleConfig {
    pub keyframes: usize,
    pub points: usize,
    /// Keyframes that observe each point (fewer when fewer see it).
    pub observations_per_point: usize,
    /// Noise of u, v and u_r, pixels.
    pub pixel_sigma: f64,
    /// Noise of the initial keyframe positions (m) and angles (rad), and of the points (m).
    pub position_noise: f64,
    pub angle_noise: f64,
    pub point_noise: f64,
    /// The first keyframes are exact and held fixed (the gauge, as a local window's edge is).
    pub fixed_keyframes: usize,
}

impl Default for BundleConfig {
    /// The local-BA size of the optimiser's goals: 20 keyframes, 3,000 points, 30,000
    /// observations.
    fn default() -> Self {
        Self {
            keyframes: 20,
            points: 3000,
            observations_per_point: 10,
            pixel_sigma: 1.0,
            position_noise: 0.02,
            angle_noise: 0.01,
            point_noise: 0.05,
            fixed_keyframes: 2,
        }
    }
}

/// A synthetic bundle adjustment: ground truth, and a problem started from noisy values.
pub struct BundleScene {
    pub problem: crate::Problem,
    pub keyframes: Vec<crate::Key<Se3>>,
    pub points: Vec<crate::Key<Vector3<f64>>>,
    pub true_keyframes: Vec<Se3>,
    pub true_points: Vec<Vector3<f64>>,
    pub observations: usize,
}

/// A camera sliding sideways past points 2.5–6 m ahead, with a D435's intrinsics and
/// RGB-D stereo observations (u, v, u_r) under a Huber kernel, as ORB-SLAM's local BA sets them.
pub fn bundle_scene(config: &BundleConfig, seed: u64) -> BundleScene {
    use crate::factors::StereoProjectionFactor;
    use crate::{Information, Kernel, Pinhole, Problem};
    let camera = Pinhole::new(605.86, 606.27, 325.02, 244.76);
    let bf = camera.fx * 0.05;
    let mut rng = Rng::new(seed);
    let true_keyframes: Vec<Se3> = (0..config.keyframes)
        .map(|i| {
            let yaw = 0.05 * (i as f64 * 0.7).sin();
            Se3::new(
                nalgebra::UnitQuaternion::from_euler_angles(0.02 * rng.normal(), yaw, 0.0),
                Vector3::new(0.1 * i as f64, 0.05 * rng.normal(), 0.05 * rng.normal()),
            )
        })
        .collect();
    let span = 0.1 * config.keyframes as f64;
    let true_points: Vec<Vector3<f64>> = (0..config.points)
        .map(|_| {
            Vector3::new(
                rng.range(-0.3, span + 0.3),
                rng.range(-1.2, 1.2),
                rng.range(2.5, 6.0),
            )
        })
        .collect();
    let mut values = Values::new();
    let keyframes: Vec<_> = true_keyframes
        .iter()
        .enumerate()
        .map(|(i, t)| {
            if i < config.fixed_keyframes {
                let k = values.add(*t);
                values.set_fixed(k.id, true);
                k
            } else {
                let mut xi = Vector6::zeros();
                xi.fixed_rows_mut::<3>(0)
                    .copy_from(&rng.vector3(config.position_noise));
                xi.fixed_rows_mut::<3>(3)
                    .copy_from(&rng.vector3(config.angle_noise));
                values.add(t.retract(&xi))
            }
        })
        .collect();
    let points: Vec<_> = true_points
        .iter()
        .map(|p| values.add(p + rng.vector3(config.point_noise)))
        .collect();
    let mut problem = Problem::new(values);
    let info = Information::isotropic(3, config.pixel_sigma).expect("positive sigma");
    let kernel = Some(Kernel::Huber(7.815f64.sqrt()));
    let mut observations = 0;
    for (pk, p) in points.iter().zip(&true_points) {
        let mut seen = vec![false; config.keyframes];
        let mut count = 0;
        for _ in 0..10 * config.observations_per_point {
            if count == config.observations_per_point {
                break;
            }
            let k = (rng.next_u64() % config.keyframes as u64) as usize;
            let p_c = true_keyframes[k].inverse().transform_point(p);
            let uv = camera.project(&p_c);
            if seen[k] || !(0.0..640.0).contains(&uv.x) || !(0.0..480.0).contains(&uv.y) {
                continue;
            }
            seen[k] = true;
            count += 1;
            let measured = rgbd_measurement(&uv, bf / p_c.z, &mut rng, config.pixel_sigma);
            problem
                .add(
                    StereoProjectionFactor::new(keyframes[k], *pk, camera, bf, measured),
                    info.clone(),
                    kernel,
                )
                .expect("keys of this problem");
            observations += 1;
        }
    }
    BundleScene {
        problem,
        keyframes,
        points,
        true_keyframes,
        true_points,
        observations,
    }
}
