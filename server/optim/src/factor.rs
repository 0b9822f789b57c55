//! What a factor is: residual and analytic Jacobians over a few variables, an information
//! matrix and an optional robust kernel.

use crate::values::{Kind, Values, VarId};
use nalgebra::{DMatrix, DMatrixViewMut};
use thiserror::Error;

/// A residual over a few variables with analytic Jacobians.
///
/// Jacobians are taken with respect to the right perturbation `δ` of each variable
/// (`X ⊕ δ`, see [`crate::values::Variable::retract`]).
pub trait Factor: Send + Sync + std::fmt::Debug {
    /// Variables the residual depends on, in the order of the Jacobian's column blocks.
    fn keys(&self) -> &[VarId];

    /// Kinds of [`Factor::keys`], checked against the values when the factor is added.
    fn kinds(&self) -> &[Kind];

    /// Length of the residual.
    fn residual_dim(&self) -> usize;

    /// Writes the (unweighted) residual and, when asked, the Jacobian `∂r/∂δ`: a
    /// `residual_dim × Σ dim(keys)` matrix whose column blocks follow [`Factor::keys`].
    fn evaluate(
        &self,
        values: &Values,
        residual: &mut [f64],
        jacobian: Option<DMatrixViewMut<'_, f64>>,
    );
}

#[derive(Debug, Error, PartialEq)]
pub enum InformationError {
    #[error("information matrix is {rows}x{cols}, the residual has {dim} entries")]
    WrongSize {
        rows: usize,
        cols: usize,
        dim: usize,
    },
    #[error("information matrix is not symmetric (largest asymmetry {0:e})")]
    NotSymmetric(f64),
    #[error("information matrix has a non-finite entry")]
    NotFinite,
    #[error("information matrix is not positive definite (smallest eigenvalue {0:e})")]
    NotPositiveDefinite(f64),
}

/// The inverse covariance `Ω` of a residual, kept as its upper Cholesky factor `Ω = RᵀR`.
///
/// Policy: a matrix that is not symmetric positive definite is refused with an error when it
/// is made ([`Information::new`]). A caller that knows its matrix is only nearly PSD may ask for
/// [`Information::clamped`], which raises eigenvalues to a floor and says so. Nothing is
/// repaired silently.
#[derive(Clone, Debug, PartialEq)]
pub struct Information {
    form: Form,
}

#[derive(Clone, Debug, PartialEq)]
enum Form {
    /// `R = s·I` (the usual pixel noise): whitening is one multiplication that linearisation
    /// folds into the robust weight, and nothing is allocated (a local BA makes tens of
    /// thousands).
    Isotropic { dim: usize, scale: f64 },
    General {
        sqrt: DMatrix<f64>,
        /// True when `R` is diagonal, so whitening is a scaling.
        diagonal: bool,
    },
}

impl Information {
    pub fn new(omega: DMatrix<f64>) -> Result<Self, InformationError> {
        let n = omega.nrows();
        if omega.ncols() != n {
            return Err(InformationError::WrongSize {
                rows: n,
                cols: omega.ncols(),
                dim: n,
            });
        }
        if omega.iter().any(|v| !v.is_finite()) {
            return Err(InformationError::NotFinite);
        }
        let scale = omega.amax().max(f64::MIN_POSITIVE);
        let asymmetry = (&omega - omega.transpose()).amax();
        if asymmetry > 1e-9 * scale {
            return Err(InformationError::NotSymmetric(asymmetry));
        }
        match omega.clone().cholesky() {
            Some(chol) => {
                let sqrt = chol.l().transpose();
                let diagonal = (0..n).all(|c| (0..c).all(|r| sqrt[(r, c)] == 0.0));
                let form = if diagonal && n > 0 && (1..n).all(|i| sqrt[(i, i)] == sqrt[(0, 0)]) {
                    Form::Isotropic {
                        dim: n,
                        scale: sqrt[(0, 0)],
                    }
                } else {
                    Form::General { sqrt, diagonal }
                };
                Ok(Self { form })
            }
            None => Err(InformationError::NotPositiveDefinite(
                omega.symmetric_eigenvalues().min(),
            )),
        }
    }

    /// Like [`Information::new`], but eigenvalues below `floor` are raised to it. Returns the
    /// information and how many eigenvalues were raised.
    pub fn clamped(omega: DMatrix<f64>, floor: f64) -> Result<(Self, usize), InformationError> {
        if omega.iter().any(|v| !v.is_finite()) {
            return Err(InformationError::NotFinite);
        }
        let sym = (&omega + omega.transpose()) * 0.5;
        let mut eig = sym.symmetric_eigen();
        let mut raised = 0;
        for v in eig.eigenvalues.iter_mut() {
            if *v < floor {
                *v = floor;
                raised += 1;
            }
        }
        Ok((Self::new(eig.recompose())?, raised))
    }

    /// `Ω = I / σ²` for a residual of `dim` entries.
    pub fn isotropic(dim: usize, sigma: f64) -> Result<Self, InformationError> {
        // Built directly, no factorisation; the bits are those `new` gives for `I / σ²`.
        let omega = 1.0 / (sigma * sigma);
        if !omega.is_finite() {
            return Err(InformationError::NotFinite);
        }
        if omega <= 0.0 {
            return Err(InformationError::NotPositiveDefinite(omega));
        }
        let form = if dim == 0 {
            Form::General {
                sqrt: DMatrix::zeros(0, 0),
                diagonal: true,
            }
        } else {
            Form::Isotropic {
                dim,
                scale: omega.sqrt(),
            }
        };
        Ok(Self { form })
    }

    /// `Ω = diag(1/σᵢ²)`.
    pub fn from_sigmas(sigmas: &[f64]) -> Result<Self, InformationError> {
        let diag =
            nalgebra::DVector::from_iterator(sigmas.len(), sigmas.iter().map(|s| 1.0 / (s * s)));
        Self::new(DMatrix::from_diagonal(&diag))
    }

    pub fn dim(&self) -> usize {
        match &self.form {
            Form::Isotropic { dim, .. } => *dim,
            Form::General { sqrt, .. } => sqrt.nrows(),
        }
    }

    /// `s` when `R = s·I`.
    pub fn isotropic_scale(&self) -> Option<f64> {
        match self.form {
            Form::Isotropic { scale, .. } => Some(scale),
            Form::General { .. } => None,
        }
    }

    /// Upper-triangular `R` with `Ω = RᵀR`.
    pub fn sqrt(&self) -> DMatrix<f64> {
        match &self.form {
            Form::Isotropic { dim, scale } => DMatrix::from_diagonal_element(*dim, *dim, *scale),
            Form::General { sqrt, .. } => sqrt.clone(),
        }
    }

    /// `v ← R·v`, the whitened residual (or Jacobian column).
    #[inline]
    pub fn whiten(&self, v: &mut [f64]) {
        debug_assert_eq!(v.len(), self.dim());
        match &self.form {
            Form::Isotropic { scale, .. } => v.iter_mut().for_each(|x| *x *= scale),
            Form::General { sqrt, diagonal } => {
                let m = v.len();
                let r = sqrt.as_slice(); // column-major
                if *diagonal {
                    for (i, x) in v.iter_mut().enumerate() {
                        *x *= r[i * m + i];
                    }
                } else {
                    // Row i of an upper-triangular R reads only entries ≥ i, so in place is
                    // safe.
                    for i in 0..m {
                        v[i] = (i..m).map(|k| r[k * m + i] * v[k]).sum();
                    }
                }
            }
        }
    }

    pub fn matrix(&self) -> DMatrix<f64> {
        let sqrt = self.sqrt();
        sqrt.transpose() * &sqrt
    }
}

/// Robust kernels `ρ(s)` of the squared whitened residual `s = rᵀΩr`; all have `ρ(s) ≈ s` near 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kernel {
    /// Quadratic up to `|r| = δ`, linear beyond.
    Huber(f64),
    /// `c² ln(1 + s/c²)`: outliers keep a slowly growing cost.
    Cauchy(f64),
    /// `c² s / (c² + s)`: bounded cost, so gross outliers stop pulling at all.
    GemanMcClure(f64),
}

impl Kernel {
    /// `(ρ(s), ρ'(s))`.
    pub fn evaluate(&self, s: f64) -> (f64, f64) {
        match *self {
            Kernel::Huber(delta) => {
                let d2 = delta * delta;
                if s <= d2 {
                    (s, 1.0)
                } else {
                    let r = s.sqrt();
                    (2.0 * delta * r - d2, delta / r)
                }
            }
            Kernel::Cauchy(c) => {
                let c2 = c * c;
                (c2 * (s / c2).ln_1p(), 1.0 / (1.0 + s / c2))
            }
            Kernel::GemanMcClure(c) => {
                let c2 = c * c;
                let q = c2 + s;
                (c2 * s / q, c2 * c2 / (q * q))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn information_policy() {
        let good = DMatrix::from_row_slice(2, 2, &[4.0, 1.0, 1.0, 3.0]);
        let info = Information::new(good.clone()).unwrap();
        assert!((info.matrix() - good).amax() < 1e-12);
        let indefinite = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]);
        match Information::new(indefinite.clone()) {
            Err(InformationError::NotPositiveDefinite(min)) => assert!((min + 1.0).abs() < 1e-12),
            other => panic!("{other:?}"),
        }
        let (clamped, raised) = Information::clamped(indefinite, 1e-6).unwrap();
        assert_eq!(raised, 1);
        assert!(clamped.matrix().symmetric_eigenvalues().min() > 0.0);
        let asym = DMatrix::from_row_slice(2, 2, &[1.0, 0.5, 0.0, 1.0]);
        assert!(matches!(
            Information::new(asym),
            Err(InformationError::NotSymmetric(_))
        ));
        let nan = DMatrix::from_row_slice(1, 1, &[f64::NAN]);
        assert_eq!(Information::new(nan), Err(InformationError::NotFinite));
        assert!(Information::isotropic(3, 0.0).is_err());
    }

    #[test]
    fn isotropic_information_is_what_the_general_path_makes_of_the_same_matrix() {
        for dim in [1, 2, 3, 6, 8] {
            for sigma in [1.0, 0.5, 1.2f64.powi(7), 0.013, 3.7] {
                let direct = Information::isotropic(dim, sigma).unwrap();
                let general = Information::new(DMatrix::identity(dim, dim) / (sigma * sigma));
                assert_eq!(Ok(direct), general, "dim {dim}, sigma {sigma}");
            }
        }
        for bad in [0.0, f64::NAN, f64::INFINITY, 1e-200] {
            assert!(Information::isotropic(3, bad).is_err(), "sigma {bad}");
        }
    }

    #[test]
    fn kernels_are_quadratic_near_zero_and_derivatives_match() {
        for kernel in [
            Kernel::Huber(1.3),
            Kernel::Cauchy(0.7),
            Kernel::GemanMcClure(2.0),
        ] {
            let (rho, w) = kernel.evaluate(1e-8);
            assert!(
                (rho - 1e-8).abs() < 1e-12 && (w - 1.0).abs() < 1e-6,
                "{kernel:?}"
            );
            for s in [0.01, 0.5, 1.69, 3.0, 50.0] {
                let h = 1e-6 * s;
                let numeric = (kernel.evaluate(s + h).0 - kernel.evaluate(s - h).0) / (2.0 * h);
                assert!(
                    (numeric - kernel.evaluate(s).1).abs() < 1e-6,
                    "{kernel:?} at {s}"
                );
            }
        }
        // Gross outliers: Geman–McClure's cost is bounded by c².
        assert!(Kernel::GemanMcClure(2.0).evaluate(1e12).0 < 4.0);
    }
}
