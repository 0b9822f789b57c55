//! The normal equations `H δ = −g` of a problem, stored as the upper triangle of a sparse
//! symmetric matrix, and their damped solution by faer's sparse Cholesky.
//!
//! The sparsity comes from which free variables share a factor. It is analysed once (block
//! layout, fill-reducing ordering and symbolic factorisation) and reused for as long as the
//! problem's structure stays the same; when a factor is added or a variable is fixed or freed the
//! analysis is redone. Each factor knows where its blocks land in the value array, so assembly is
//! a scatter with no search.

use crate::problem::{Entry, Linearized, Problem};
use crate::values::Values;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{LltParams, LltRegularization};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};
use std::collections::BTreeMap;

/// Where the product of a factor's key blocks `a` (rows) and `b` (columns) lands.
#[derive(Clone, Copy, Debug)]
struct Slot {
    /// Key indices in the factor.
    a: u8,
    b: u8,
    /// First scalar column of block column `b`.
    col0: usize,
    /// Position of block row `a`'s first row within each column of block column `b`.
    prefix: usize,
}

/// Damping applied to the normal equations.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Damping {
    /// Gauss–Newton: none.
    None,
    /// `H + λ·diag(H)` (Marquardt), with diagonal entries clamped from below.
    Marquardt(f64),
}

pub(crate) struct NormalEquations {
    layout: (u64, usize, u64),
    /// Scalar offset of each variable, `usize::MAX` when fixed.
    offset: Vec<usize>,
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Undamped `H` (upper triangle, by column).
    h: Vec<f64>,
    damped: Vec<f64>,
    diag: Vec<usize>,
    /// Gradient `g = Jᵀ r` (whitened and weighted).
    pub g: Vec<f64>,
    slot_start: Vec<usize>,
    slots: Vec<Slot>,
    symbolic: SymbolicCholesky<usize>,
    l_values: Vec<f64>,
    scratch: MemBuffer,
    lin: Linearized,
}

#[derive(Debug, thiserror::Error)]
pub(crate) enum LinearError {
    #[error("the damped normal equations are not positive definite")]
    NotPositiveDefinite,
    #[error("sparse analysis failed: {0}")]
    Analysis(String),
}

impl NormalEquations {
    /// The problem layout this system was analysed for.
    pub fn layout(&self) -> (u64, usize, u64) {
        self.layout
    }

    pub fn dim(&self) -> usize {
        self.n
    }

    /// Scalar offset of each variable in the update vector (`usize::MAX` when fixed).
    pub fn offsets(&self) -> &[usize] {
        &self.offset
    }

    /// Lays out the system of `problem` and analyses its sparsity.
    pub fn analyse(problem: &Problem) -> Result<Self, LinearError> {
        let values = &problem.values;
        let mut offset = vec![usize::MAX; values.len()];
        let mut n = 0;
        for id in values.ids() {
            if !values.is_fixed(id) {
                offset[id.index()] = n;
                n += values.variable(id).expect("id from ids()").kind().dim();
            }
        }
        let dim_of =
            |id: crate::values::VarId| values.variable(id).expect("checked key").kind().dim();
        // Block rows of each block column, keyed by column offset then row offset.
        let mut blocks: BTreeMap<usize, BTreeMap<usize, usize>> = BTreeMap::new();
        for id in values.ids() {
            let off = offset[id.index()];
            if off != usize::MAX {
                let d = dim_of(id);
                blocks.entry(off).or_default().insert(off, d);
            }
        }
        for e in &problem.entries {
            let keys = e.factor.keys();
            for &a in keys {
                for &b in keys {
                    let (oa, ob) = (offset[a.index()], offset[b.index()]);
                    if oa == usize::MAX || ob == usize::MAX || oa > ob {
                        continue;
                    }
                    blocks.entry(ob).or_default().insert(oa, dim_of(a));
                }
            }
        }
        // Scalar CSC of the upper triangle, and each block row's prefix within its column.
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let mut prefix: BTreeMap<(usize, usize), usize> = BTreeMap::new();
        let mut diag = Vec::with_capacity(n);
        col_ptr.push(0);
        for (&col_off, rows) in &blocks {
            let col_dim = rows[&col_off];
            let mut p = 0;
            for (&row_off, &row_dim) in rows {
                prefix.insert((row_off, col_off), p);
                p += row_dim;
            }
            for k in 0..col_dim {
                for (&row_off, &row_dim) in rows {
                    let count = if row_off == col_off { k + 1 } else { row_dim };
                    row_idx.extend(row_off..row_off + count);
                }
                diag.push(row_idx.len() - 1);
                col_ptr.push(row_idx.len());
            }
        }
        let mut slot_start = Vec::with_capacity(problem.entries.len() + 1);
        let mut slots = Vec::new();
        for e in &problem.entries {
            slot_start.push(slots.len());
            let keys = e.factor.keys();
            for (ia, &a) in keys.iter().enumerate() {
                for (ib, &b) in keys.iter().enumerate() {
                    let (oa, ob) = (offset[a.index()], offset[b.index()]);
                    if oa == usize::MAX || ob == usize::MAX || oa > ob {
                        continue;
                    }
                    slots.push(Slot {
                        a: ia as u8,
                        b: ib as u8,
                        col0: ob,
                        prefix: prefix[&(oa, ob)],
                    });
                }
            }
        }
        slot_start.push(slots.len());
        let symbolic = {
            let pattern = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
            factorize_symbolic_cholesky(
                pattern,
                Side::Upper,
                SymmetricOrdering::Amd,
                CholeskySymbolicParams::default(),
            )
            .map_err(|e| LinearError::Analysis(format!("{e:?}")))?
        };
        let scratch = MemBuffer::try_new(
            symbolic
                .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
                .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq)),
        )
        .map_err(|_| LinearError::Analysis("out of memory".into()))?;
        let nnz = row_idx.len();
        Ok(Self {
            layout: problem.layout_version(),
            offset,
            n,
            col_ptr,
            row_idx,
            h: vec![0.0; nnz],
            damped: vec![0.0; nnz],
            diag,
            g: vec![0.0; n],
            slot_start,
            slots,
            l_values: vec![0.0; symbolic.len_val()],
            symbolic,
            scratch,
            lin: Linearized::default(),
        })
    }

    /// Evaluates every factor at `values`, fills `H` and `g`, and returns the cost.
    pub fn linearize(&mut self, entries: &[Entry], values: &Values) -> f64 {
        self.h.fill(0.0);
        self.g.fill(0.0);
        let mut cost = 0.0;
        for (fi, e) in entries.iter().enumerate() {
            cost += self.lin.linearize(e, values);
            let m = e.factor.residual_dim();
            let jac = &self.lin.jacobian;
            let r = &self.lin.residual;
            let keys = e.factor.keys();
            for (ia, &a) in keys.iter().enumerate() {
                let off = self.offset[a.index()];
                if off == usize::MAX {
                    continue;
                }
                let c0 = e.columns[ia];
                for i in 0..e.factor.kinds()[ia].dim() {
                    let col = &jac[(c0 + i) * m..(c0 + i + 1) * m];
                    self.g[off + i] += dot(col, r);
                }
            }
            for slot in &self.slots[self.slot_start[fi]..self.slot_start[fi + 1]] {
                let (ia, ib) = (slot.a as usize, slot.b as usize);
                let (ca, cb) = (e.columns[ia], e.columns[ib]);
                let da = e.factor.kinds()[ia].dim();
                let db = e.factor.kinds()[ib].dim();
                for k in 0..db {
                    let colb = &jac[(cb + k) * m..(cb + k + 1) * m];
                    let base = self.col_ptr[slot.col0 + k] + slot.prefix;
                    let rows = if ia == ib { k + 1 } else { da };
                    for rr in 0..rows {
                        let cola = &jac[(ca + rr) * m..(ca + rr + 1) * m];
                        self.h[base + rr] += dot(cola, colb);
                    }
                }
            }
        }
        cost
    }

    /// Largest absolute entry of the gradient.
    pub fn gradient_max(&self) -> f64 {
        self.g.iter().fold(0.0, |m, v| m.max(v.abs()))
    }

    /// Solves `(H + damping) δ = −g` into `delta`.
    pub fn solve(&mut self, damping: Damping, delta: &mut Vec<f64>) -> Result<(), LinearError> {
        self.damped.copy_from_slice(&self.h);
        if let Damping::Marquardt(lambda) = damping {
            for &i in &self.diag {
                self.damped[i] += lambda * self.h[i].max(1e-6);
            }
        }
        let pattern = SymbolicSparseColMatRef::new_checked(
            self.n,
            self.n,
            &self.col_ptr,
            None,
            &self.row_idx,
        );
        let matrix = SparseColMatRef::new(pattern, &self.damped);
        let stack = MemStack::new(&mut self.scratch);
        self.symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.l_values,
                matrix,
                Side::Upper,
                LltRegularization::default(),
                Par::Seq,
                stack,
                Spec::<LltParams, f64>::default(),
            )
            .map_err(|_| LinearError::NotPositiveDefinite)?;
        delta.clear();
        delta.extend(self.g.iter().map(|v| -v));
        let llt = LltRef::new(&self.symbolic, &self.l_values);
        let rhs = MatMut::from_column_major_slice_mut(delta.as_mut_slice(), self.n, 1);
        llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut self.scratch));
        if delta.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(LinearError::NotPositiveDefinite)
        }
    }

    /// `δᵀ diag-damping δ` and `gᵀδ` for the predicted cost decrease.
    pub fn predicted_decrease(&self, damping: Damping, delta: &[f64]) -> f64 {
        // With cost F = |r|², the model is F + 2gᵀδ + δᵀHδ; at the damped solution this decrease
        // equals −gᵀδ + λ δᵀDδ.
        let gd = dot(&self.g, delta);
        let damp = match damping {
            Damping::None => 0.0,
            Damping::Marquardt(lambda) => self
                .diag
                .iter()
                .enumerate()
                .map(|(i, &d)| lambda * self.h[d].max(1e-6) * delta[i] * delta[i])
                .sum(),
        };
        -gd + damp
    }
}

#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}
