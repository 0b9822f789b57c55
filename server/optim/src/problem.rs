//! A problem: values plus weighted factors, and its cost.

use crate::bundle::{PoseViews, Reprojection};
use crate::factor::{Factor, Information, Kernel};
use crate::values::{Values, VarId};
use nalgebra::DMatrixViewMut;
use thiserror::Error;

/// Index of a factor in its [`Problem`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FactorId(pub u32);

#[derive(Debug, Error, PartialEq)]
pub enum ProblemError {
    #[error("factor names variable {0:?}, which does not exist")]
    UnknownVariable(VarId),
    #[error("factor expects variable {id:?} to be a {expected:?}, it is a {found:?}")]
    WrongKind {
        id: VarId,
        expected: crate::values::Kind,
        found: crate::values::Kind,
    },
    #[error("factor names variable {0:?} twice")]
    RepeatedVariable(VarId),
    #[error("factor has a {residual}-entry residual but a {information}x{information} information matrix")]
    InformationSize { residual: usize, information: usize },
}

#[derive(Debug)]
pub(crate) struct Entry {
    pub factor: Box<dyn Factor>,
    pub information: Information,
    pub kernel: Option<Kernel>,
    /// Column of each key's block in the factor's Jacobian.
    pub columns: Vec<usize>,
    pub total_dim: usize,
    /// The factor's data again when it is a reprojection that [`crate::bundle`] evaluates.
    pub reprojection: Option<Reprojection>,
}

/// Values and the factors between them.
#[derive(Debug, Default)]
pub struct Problem {
    pub(crate) values: Values,
    pub(crate) entries: Vec<Entry>,
    /// Changes whenever the sparsity of the normal equations may change.
    pub(crate) structure: u64,
    /// Factors with [`Entry::reprojection`]: passes over the factors then need [`PoseViews`].
    pub(crate) reprojections: usize,
}

impl Problem {
    pub fn new(values: Values) -> Self {
        Self {
            values,
            entries: Vec::new(),
            structure: 0,
            reprojections: 0,
        }
    }

    pub fn values(&self) -> &Values {
        &self.values
    }

    /// Values may be changed, fixed or freed, and added (new variables join the next solve).
    pub fn values_mut(&mut self) -> &mut Values {
        &mut self.values
    }

    /// What the layout of the normal equations depends on: the factors, the number of
    /// variables and which of them are fixed.
    pub(crate) fn layout_version(&self) -> (u64, usize, u64) {
        (
            self.structure,
            self.values.len(),
            self.values.fixed_changes(),
        )
    }

    pub fn into_values(self) -> Values {
        self.values
    }

    pub fn num_factors(&self) -> usize {
        self.entries.len()
    }

    pub fn factor(&self, id: FactorId) -> Option<&dyn Factor> {
        self.entries.get(id.0 as usize).map(|e| e.factor.as_ref())
    }

    /// Adds a factor after checking its keys against the values and its information's size.
    pub fn add(
        &mut self,
        factor: impl Factor + 'static,
        information: Information,
        kernel: Option<Kernel>,
    ) -> Result<FactorId, ProblemError> {
        let keys = factor.keys();
        let kinds = factor.kinds();
        debug_assert_eq!(keys.len(), kinds.len());
        let mut columns = Vec::with_capacity(keys.len());
        let mut total_dim = 0;
        for (i, (&id, &expected)) in keys.iter().zip(kinds).enumerate() {
            let found = self
                .values
                .variable(id)
                .ok_or(ProblemError::UnknownVariable(id))?
                .kind();
            if found != expected {
                return Err(ProblemError::WrongKind {
                    id,
                    expected,
                    found,
                });
            }
            if keys[..i].contains(&id) {
                return Err(ProblemError::RepeatedVariable(id));
            }
            columns.push(total_dim);
            total_dim += expected.dim();
        }
        if information.dim() != factor.residual_dim() {
            return Err(ProblemError::InformationSize {
                residual: factor.residual_dim(),
                information: information.dim(),
            });
        }
        let reprojection = Reprojection::of(&factor, information.isotropic_scale());
        self.reprojections += usize::from(reprojection.is_some());
        self.entries.push(Entry {
            factor: Box::new(factor),
            information,
            kernel,
            columns,
            total_dim,
            reprojection,
        });
        self.structure += 1;
        Ok(FactorId(self.entries.len() as u32 - 1))
    }

    /// Sets or removes a factor's robust kernel (e.g. once a map is optimised, loop closures
    /// get a kernel so that a false one cannot bend it). Unknown ids are ignored.
    pub fn set_kernel(&mut self, id: FactorId, kernel: Option<Kernel>) {
        if let Some(e) = self.entries.get_mut(id.0 as usize) {
            e.kernel = kernel;
        }
    }

    /// Total cost `Σ ρ(rᵀΩr)` (g2o's "chi2" when no kernel is set).
    pub fn cost(&self) -> f64 {
        self.factor_costs().iter().sum()
    }

    /// The pose views that passes over this problem's factors need at `values`.
    pub(crate) fn pose_views(&self, values: &Values) -> PoseViews {
        PoseViews::new(values, self.reprojections > 0)
    }

    /// Cost of each factor, `ρ(rᵀΩr)`, e.g. to find outliers.
    pub fn factor_costs(&self) -> Vec<f64> {
        let mut r = Vec::new();
        let views = self.pose_views(&self.values);
        self.entries
            .iter()
            .map(|e| entry_cost(e, &self.values, &views, &mut r))
            .collect()
    }
}

pub(crate) fn entry_cost(e: &Entry, values: &Values, views: &PoseViews, r: &mut Vec<f64>) -> f64 {
    if let Some(fast) = &e.reprojection {
        return fast.cost(views, values, e.kernel);
    }
    let m = e.factor.residual_dim();
    r.clear();
    r.resize(m, 0.0);
    e.factor.evaluate(values, r, None);
    let s = match e.information.isotropic_scale() {
        Some(scale) => scale * scale * r.iter().map(|v| v * v).sum::<f64>(),
        None => {
            e.information.whiten(r);
            r.iter().map(|v| v * v).sum()
        }
    };
    match e.kernel {
        Some(k) => k.evaluate(s).0,
        None => s,
    }
}

/// Scratch for linearising one factor, reused across factors.
#[derive(Default)]
pub(crate) struct Linearized {
    pub residual: Vec<f64>,
    pub jacobian: Vec<f64>,
}

impl Linearized {
    /// Evaluates `e` and leaves `√ρ'·R·r` in `residual` and `√ρ'·R·J` (column-major,
    /// `m × total_dim`) in `jacobian`. Returns the factor's cost `ρ(s)`.
    pub fn linearize(&mut self, e: &Entry, values: &Values) -> f64 {
        let m = e.factor.residual_dim();
        let n = e.total_dim;
        self.residual.clear();
        self.residual.resize(m, 0.0);
        self.jacobian.clear();
        self.jacobian.resize(m * n, 0.0);
        e.factor.evaluate(
            values,
            &mut self.residual,
            Some(DMatrixViewMut::from_slice(&mut self.jacobian, m, n)),
        );
        // Whitening by `R = s·I` is folded into the robust weight: one pass instead of two.
        let scale = e.information.isotropic_scale();
        if scale.is_none() {
            e.information.whiten(&mut self.residual);
            for col in self.jacobian.chunks_exact_mut(m) {
                e.information.whiten(col);
            }
        }
        let s = scale.map_or(1.0, |s| s * s) * self.residual.iter().map(|v| v * v).sum::<f64>();
        let (cost, weight) = match e.kernel {
            Some(k) => k.evaluate(s),
            None => (s, 1.0),
        };
        let w = scale.unwrap_or(1.0) * weight.max(0.0).sqrt();
        if w != 1.0 {
            self.residual.iter_mut().for_each(|v| *v *= w);
            self.jacobian.iter_mut().for_each(|v| *v *= w);
        }
        cost
    }
}
