//! Helpers for checking factors and manifolds: central differences and deterministic randomness.
//! Public so that integration tests and benchmarks of other crates can use them too.

use crate::factor::Factor;
use crate::lie::Se3;
use crate::values::Values;
use nalgebra::{DMatrix, DMatrixViewMut, DVector, Vector3, Vector6};

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
