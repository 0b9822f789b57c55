//! The normal equations `H δ = −g` of a problem and their damped solution.
//!
//! Variables split in two sets. *Eliminated* ones are free points (R³) of which no factor holds
//! two, such as the map points of bundle adjustment: their block of `H` is block-diagonal, so
//! they are removed by the Schur complement `S = H_rr − H_rl·H_ll⁻¹·H_lr` and recovered by back
//! substitution. The *reduced* rest (poses, planes, shared points) forms `S`, stored as the upper
//! triangle of a sparse symmetric matrix and solved by faer's sparse Cholesky.
//!
//! The layout (which variables go where, the sparsity of `S`, the fill-reducing ordering and the
//! symbolic factorisation) is analysed once and reused while the problem's structure stays the
//! same; adding a factor or fixing or freeing a variable makes the solver analyse again. Each
//! factor knows where its blocks land, so assembly is a scatter with no search.

use crate::problem::{Entry, Linearized, Problem};
use crate::values::{Kind, Values};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{LltParams, LltRegularization};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeMap;

/// Diagonal entries of `H` are raised to at least this before Marquardt damping scales them,
/// so a variable no factor constrains still gets a damped, solvable block.
const MIN_DIAGONAL: f64 = 1e-6;

/// A Schur complement of at most this many scalars is laid out dense (its Cholesky then costs
/// at most about 10 Mflop).
const DENSE_LIMIT: usize = 300;

/// Where the product of a factor's reduced key blocks `a` (rows) and `b` (columns) lands in `S`.
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

/// Where a factor's product of an eliminated key `l` with key `r` lands: the eliminated
/// variable's own block (`r == l`, `target` its index) or a coupling (`target` its index).
#[derive(Clone, Copy, Debug)]
struct ElimSlot {
    l: u8,
    r: u8,
    target: usize,
}

/// `H_rl` of one eliminated variable and one reduced neighbour: `dim × 3`, column-major.
#[derive(Clone, Copy, Debug)]
struct Coupling {
    /// Scalar offset of the reduced neighbour.
    offset: usize,
    dim: usize,
    /// Start of its entries in `w` (and `y`).
    data: usize,
}

/// Two couplings of one eliminated variable (`i`'s offset ≤ `j`'s) whose product lands in `S`.
#[derive(Clone, Copy, Debug)]
struct SchurPair {
    i: u32,
    j: u32,
    col0: usize,
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
    eliminate: bool,
    /// Scalar offset of each variable in the update vector (reduced variables first, then the
    /// eliminated ones), `usize::MAX` when fixed.
    offset: Vec<usize>,
    n_reduced: usize,
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// `H_rr` (upper triangle, by column), undamped.
    h: Vec<f64>,
    /// The damped Schur complement `S`, same pattern.
    damped: Vec<f64>,
    diag: Vec<usize>,
    /// Gradient `g = Jᵀ r` (whitened and weighted), reduced entries then eliminated ones.
    g: Vec<f64>,
    slot_start: Vec<usize>,
    slots: Vec<Slot>,
    elim_start: Vec<usize>,
    elim_slots: Vec<ElimSlot>,
    /// `H_ll` of each eliminated variable, and its damped inverse.
    v: Vec<Matrix3<f64>>,
    v_inv: Vec<Matrix3<f64>>,
    coupling_start: Vec<usize>,
    couplings: Vec<Coupling>,
    /// `H_rl` blocks, and `H_rl·H_ll⁻¹` in the same layout.
    w: Vec<f64>,
    y: Vec<f64>,
    pairs: Vec<SchurPair>,
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
    /// The problem layout and elimination setting this system was analysed for.
    pub fn layout(&self) -> ((u64, usize, u64), bool) {
        (self.layout, self.eliminate)
    }

    /// Length of the update vector.
    pub fn dim(&self) -> usize {
        self.n
    }

    /// Number of eliminated variables.
    pub fn eliminated(&self) -> usize {
        self.v.len()
    }

    /// Scalar offset of each variable in the update vector (`usize::MAX` when fixed).
    pub fn offsets(&self) -> &[usize] {
        &self.offset
    }

    /// Lays out the system of `problem` and analyses its sparsity. With `eliminate`, free points
    /// of which no factor holds two are removed by the Schur complement.
    pub fn analyse(problem: &Problem, eliminate: bool) -> Result<Self, LinearError> {
        let values = &problem.values;
        let kind_of = |id: crate::values::VarId| values.variable(id).expect("checked key").kind();
        let free = |id| !values.is_fixed(id);
        // Which variables to eliminate.
        let mut elim = vec![false; values.len()];
        if eliminate {
            for id in values.ids() {
                elim[id.index()] = free(id) && kind_of(id) == Kind::Point;
            }
            for e in &problem.entries {
                let keys = e.factor.keys();
                if keys.iter().filter(|k| elim[k.index()]).count() > 1 {
                    for k in keys {
                        elim[k.index()] = false;
                    }
                }
            }
        }
        let mut offset = vec![usize::MAX; values.len()];
        let mut n = 0;
        for id in values.ids() {
            if free(id) && !elim[id.index()] {
                offset[id.index()] = n;
                n += kind_of(id).dim();
            }
        }
        let n_reduced = n;
        let mut elim_index = vec![usize::MAX; values.len()];
        let mut num_elim = 0;
        for id in values.ids() {
            if elim[id.index()] {
                elim_index[id.index()] = num_elim;
                offset[id.index()] = n;
                n += 3;
                num_elim += 1;
            }
        }
        let is_reduced =
            |id: crate::values::VarId| offset[id.index()] != usize::MAX && !elim[id.index()];
        // Reduced neighbours of each eliminated variable: offset → dimension.
        let mut neighbours: Vec<BTreeMap<usize, usize>> = vec![BTreeMap::new(); num_elim];
        for e in &problem.entries {
            let keys = e.factor.keys();
            for &l in keys.iter().filter(|k| elim[k.index()]) {
                for &r in keys.iter().filter(|&&k| is_reduced(k)) {
                    neighbours[elim_index[l.index()]].insert(offset[r.index()], kind_of(r).dim());
                }
            }
        }
        // Block rows of each block column of S, keyed by column offset then row offset.
        let mut blocks: BTreeMap<usize, BTreeMap<usize, usize>> = BTreeMap::new();
        for id in values.ids().filter(|&id| is_reduced(id)) {
            let off = offset[id.index()];
            blocks
                .entry(off)
                .or_default()
                .insert(off, kind_of(id).dim());
        }
        // After eliminating the points of a bundle adjustment, S is dense or nearly so: a small
        // one is then laid out dense, which skips finding its pattern pair by pair.
        let dense = num_elim > 0 && n_reduced <= DENSE_LIMIT;
        if dense {
            let reduced: Vec<(usize, usize)> = blocks.iter().map(|(&o, r)| (o, r[&o])).collect();
            for (i, &(oa, da)) in reduced.iter().enumerate() {
                for &(ob, _) in &reduced[i..] {
                    blocks.entry(ob).or_default().insert(oa, da);
                }
            }
        }
        for e in problem.entries.iter().filter(|_| !dense) {
            let keys = e.factor.keys();
            for &a in keys.iter().filter(|&&k| is_reduced(k)) {
                for &b in keys.iter().filter(|&&k| is_reduced(k)) {
                    let (oa, ob) = (offset[a.index()], offset[b.index()]);
                    if oa <= ob {
                        blocks.entry(ob).or_default().insert(oa, kind_of(a).dim());
                    }
                }
            }
        }
        for nb in neighbours.iter().filter(|_| !dense) {
            for (&oa, &da) in nb {
                for &ob in nb.keys().filter(|&&ob| ob >= oa) {
                    blocks.entry(ob).or_default().insert(oa, da);
                }
            }
        }
        // Scalar CSC of the upper triangle, and each block row's prefix within its column.
        let mut col_ptr = Vec::with_capacity(n_reduced + 1);
        let mut row_idx = Vec::new();
        let mut prefix: BTreeMap<(usize, usize), usize> = BTreeMap::new();
        let mut diag = Vec::with_capacity(n_reduced);
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
        // A dense column holds every row from 0, so a block row starts at its own offset.
        let prefix_of = |row: usize, col: usize| if dense { row } else { prefix[&(row, col)] };
        // Couplings and Schur pairs of each eliminated variable.
        let mut coupling_start = Vec::with_capacity(num_elim + 1);
        let mut couplings = Vec::new();
        let mut coupling_of: Vec<BTreeMap<usize, usize>> = Vec::with_capacity(num_elim);
        let mut pairs = Vec::new();
        let mut w_len = 0;
        for nb in &neighbours {
            coupling_start.push(couplings.len());
            let first = couplings.len();
            let mut of = BTreeMap::new();
            for (&off, &dim) in nb {
                of.insert(off, couplings.len());
                couplings.push(Coupling {
                    offset: off,
                    dim,
                    data: w_len,
                });
                w_len += 3 * dim;
            }
            for i in first..couplings.len() {
                for j in i..couplings.len() {
                    let (oi, oj) = (couplings[i].offset, couplings[j].offset);
                    pairs.push(SchurPair {
                        i: i as u32,
                        j: j as u32,
                        col0: oj,
                        prefix: prefix_of(oi, oj),
                    });
                }
            }
            coupling_of.push(of);
        }
        coupling_start.push(couplings.len());
        // Per factor: its reduced slots and its eliminated slots.
        let mut slot_start = Vec::with_capacity(problem.entries.len() + 1);
        let mut slots = Vec::new();
        let mut elim_start = Vec::with_capacity(problem.entries.len() + 1);
        let mut elim_slots = Vec::new();
        for e in &problem.entries {
            slot_start.push(slots.len());
            elim_start.push(elim_slots.len());
            let keys = e.factor.keys();
            for (ia, &a) in keys.iter().enumerate() {
                for (ib, &b) in keys.iter().enumerate() {
                    let (oa, ob) = (offset[a.index()], offset[b.index()]);
                    if is_reduced(a) && is_reduced(b) && oa <= ob {
                        slots.push(Slot {
                            a: ia as u8,
                            b: ib as u8,
                            col0: ob,
                            prefix: prefix_of(oa, ob),
                        });
                    } else if elim[a.index()] && ia == ib {
                        elim_slots.push(ElimSlot {
                            l: ia as u8,
                            r: ia as u8,
                            target: elim_index[a.index()],
                        });
                    } else if elim[a.index()] && is_reduced(b) {
                        elim_slots.push(ElimSlot {
                            l: ia as u8,
                            r: ib as u8,
                            target: coupling_of[elim_index[a.index()]][&ob],
                        });
                    }
                }
            }
        }
        slot_start.push(slots.len());
        elim_start.push(elim_slots.len());
        let symbolic = {
            let pattern = SymbolicSparseColMatRef::new_checked(
                n_reduced, n_reduced, &col_ptr, None, &row_idx,
            );
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
            eliminate,
            offset,
            n_reduced,
            n,
            col_ptr,
            row_idx,
            h: vec![0.0; nnz],
            damped: vec![0.0; nnz],
            diag,
            g: vec![0.0; n],
            slot_start,
            slots,
            elim_start,
            elim_slots,
            v: vec![Matrix3::zeros(); num_elim],
            v_inv: vec![Matrix3::zeros(); num_elim],
            coupling_start,
            couplings,
            w: vec![0.0; w_len],
            y: vec![0.0; w_len],
            pairs,
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
        self.w.fill(0.0);
        self.v.fill(Matrix3::zeros());
        let mut cost = 0.0;
        let mut jtj = Vec::new();
        let mut jtr = Vec::new();
        for (fi, e) in entries.iter().enumerate() {
            cost += self.lin.linearize(e, values);
            let m = e.factor.residual_dim();
            let n = e.total_dim;
            // The factor's own JᵀJ (full, column-major) and Jᵀr, then scattered by block.
            jtj.clear();
            jtj.resize(n * n, 0.0);
            jtr.clear();
            jtr.resize(n, 0.0);
            let (jac, r) = (&self.lin.jacobian[..m * n], &self.lin.residual[..m]);
            match n {
                6 => gram::<6>(jac, r, &mut jtj, &mut jtr),
                9 => gram::<9>(jac, r, &mut jtj, &mut jtr),
                12 => gram::<12>(jac, r, &mut jtj, &mut jtr),
                _ => gram_dyn(jac, r, n, &mut jtj, &mut jtr),
            }
            let keys = e.factor.keys();
            let kinds = e.factor.kinds();
            for (ia, &a) in keys.iter().enumerate() {
                let off = self.offset[a.index()];
                if off == usize::MAX {
                    continue;
                }
                let c0 = e.columns[ia];
                for (g, x) in self.g[off..off + kinds[ia].dim()]
                    .iter_mut()
                    .zip(&jtr[c0..])
                {
                    *g += x;
                }
            }
            for slot in &self.slots[self.slot_start[fi]..self.slot_start[fi + 1]] {
                let (ia, ib) = (slot.a as usize, slot.b as usize);
                let (ca, cb) = (e.columns[ia], e.columns[ib]);
                let da = kinds[ia].dim();
                for k in 0..kinds[ib].dim() {
                    let base = self.col_ptr[slot.col0 + k] + slot.prefix;
                    let rows = if ia == ib { k + 1 } else { da };
                    let src = &jtj[(cb + k) * n + ca..(cb + k) * n + ca + rows];
                    for (h, x) in self.h[base..base + rows].iter_mut().zip(src) {
                        *h += x;
                    }
                }
            }
            for s in &self.elim_slots[self.elim_start[fi]..self.elim_start[fi + 1]] {
                let (cl, cr) = (e.columns[s.l as usize], e.columns[s.r as usize]);
                if s.l == s.r {
                    let v = &mut self.v[s.target];
                    for c in 0..3 {
                        for rr in 0..3 {
                            v[(rr, c)] += jtj[(cl + c) * n + cl + rr];
                        }
                    }
                } else {
                    let cp = self.couplings[s.target];
                    let w = &mut self.w[cp.data..cp.data + 3 * cp.dim];
                    for c in 0..3 {
                        let src = &jtj[(cl + c) * n + cr..(cl + c) * n + cr + cp.dim];
                        for (x, y) in w[c * cp.dim..(c + 1) * cp.dim].iter_mut().zip(src) {
                            *x += y;
                        }
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

    /// Solves `(H + damping) δ = −g` into `delta`, eliminating points first.
    pub fn solve(&mut self, damping: Damping, delta: &mut Vec<f64>) -> Result<(), LinearError> {
        let lambda = match damping {
            Damping::None => 0.0,
            Damping::Marquardt(lambda) => lambda,
        };
        self.damped.copy_from_slice(&self.h);
        for &i in &self.diag {
            self.damped[i] += lambda * self.h[i].max(MIN_DIAGONAL);
        }
        delta.clear();
        delta.extend(self.g.iter().map(|v| -v));
        let nr = self.n_reduced;
        // Eliminated blocks: V⁻¹, Y = W·V⁻¹, the right-hand side −g_r + Σ Y·g_l and S −= Y·Wᵀ.
        for e in 0..self.v.len() {
            let mut v = self.v[e];
            for c in 0..3 {
                v[(c, c)] += lambda * v[(c, c)].max(MIN_DIAGONAL);
            }
            let v_inv = v
                .cholesky()
                .ok_or(LinearError::NotPositiveDefinite)?
                .inverse();
            self.v_inv[e] = v_inv;
            let g_l = Vector3::from_column_slice(&self.g[nr + 3 * e..nr + 3 * e + 3]);
            for cp in &self.couplings[self.coupling_start[e]..self.coupling_start[e + 1]] {
                let d = cp.dim;
                let w = &self.w[cp.data..cp.data + 3 * d];
                let y = &mut self.y[cp.data..cp.data + 3 * d];
                for c in 0..3 {
                    for rr in 0..d {
                        y[c * d + rr] = w[rr] * v_inv[(0, c)]
                            + w[d + rr] * v_inv[(1, c)]
                            + w[2 * d + rr] * v_inv[(2, c)];
                    }
                }
                for rr in 0..d {
                    delta[cp.offset + rr] +=
                        y[rr] * g_l.x + y[d + rr] * g_l.y + y[2 * d + rr] * g_l.z;
                }
            }
        }
        schur_update(
            &self.pairs,
            &self.couplings,
            &self.y,
            &self.w,
            &self.col_ptr,
            &mut self.damped,
        );
        if nr > 0 {
            let pattern =
                SymbolicSparseColMatRef::new_checked(nr, nr, &self.col_ptr, None, &self.row_idx);
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
            let llt = LltRef::new(&self.symbolic, &self.l_values);
            let rhs = MatMut::from_column_major_slice_mut(&mut delta[..nr], nr, 1);
            llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut self.scratch));
        }
        // Back substitution: δ_l = V⁻¹(−g_l − Σ Wᵀ·δ_r).
        for e in 0..self.v.len() {
            let at = nr + 3 * e;
            let mut b = Vector3::from_column_slice(&delta[at..at + 3]);
            for cp in &self.couplings[self.coupling_start[e]..self.coupling_start[e + 1]] {
                let d = cp.dim;
                let w = &self.w[cp.data..cp.data + 3 * d];
                let dr = &delta[cp.offset..cp.offset + d];
                for c in 0..3 {
                    b[c] -= dot(&w[c * d..(c + 1) * d], dr);
                }
            }
            delta[at..at + 3].copy_from_slice((self.v_inv[e] * b).as_slice());
        }
        if delta.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(LinearError::NotPositiveDefinite)
        }
    }

    /// The decrease of the cost that the linear model predicts for `delta`.
    pub fn predicted_decrease(&self, damping: Damping, delta: &[f64]) -> f64 {
        // With cost F = |r|², the model is F + 2gᵀδ + δᵀHδ; at the damped solution this decrease
        // equals −gᵀδ + λ δᵀDδ.
        let gd = dot(&self.g, delta);
        let Damping::Marquardt(lambda) = damping else {
            return -gd;
        };
        let nr = self.n_reduced;
        let reduced: f64 = self
            .diag
            .iter()
            .zip(&delta[..nr])
            .map(|(&d, x)| self.h[d].max(MIN_DIAGONAL) * x * x)
            .sum();
        let eliminated: f64 = self
            .v
            .iter()
            .zip(delta[nr..].chunks_exact(3))
            .map(|(v, x)| {
                (0..3)
                    .map(|c| v[(c, c)].max(MIN_DIAGONAL) * x[c] * x[c])
                    .sum::<f64>()
            })
            .sum();
        -gd + lambda * (reduced + eliminated)
    }
}

/// `S −= Y_i·W_jᵀ` for every pair of couplings of every eliminated variable: the bulk of the
/// work of a bundle adjustment's solve, compiled for AVX2 too and chosen at run time.
fn schur_update(
    pairs: &[SchurPair],
    couplings: &[Coupling],
    y: &[f64],
    w: &[f64],
    col_ptr: &[usize],
    s: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has just been found to support AVX2.
        return unsafe { schur_update_avx2(pairs, couplings, y, w, col_ptr, s) };
    }
    schur_update_portable(pairs, couplings, y, w, col_ptr, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn schur_update_avx2(
    pairs: &[SchurPair],
    couplings: &[Coupling],
    y: &[f64],
    w: &[f64],
    col_ptr: &[usize],
    s: &mut [f64],
) {
    schur_update_portable(pairs, couplings, y, w, col_ptr, s)
}

#[inline(always)]
fn schur_update_portable(
    pairs: &[SchurPair],
    couplings: &[Coupling],
    y: &[f64],
    w: &[f64],
    col_ptr: &[usize],
    s: &mut [f64],
) {
    for pair in pairs {
        let ci = couplings[pair.i as usize];
        let cj = couplings[pair.j as usize];
        let (di, dj) = (ci.dim, cj.dim);
        let diagonal = pair.i == pair.j;
        if di == 6 && dj == 6 {
            // Pose–pose, the bulk of bundle adjustment: fixed-size columns.
            let y: &[f64; 18] = y[ci.data..ci.data + 18].try_into().expect("18 entries");
            let w: &[f64; 18] = w[cj.data..cj.data + 18].try_into().expect("18 entries");
            for k in 0..6 {
                let base = col_ptr[pair.col0 + k] + pair.prefix;
                let (w0, w1, w2) = (w[k], w[6 + k], w[12 + k]);
                let col: [f64; 6] =
                    std::array::from_fn(|r| y[r] * w0 + y[6 + r] * w1 + y[12 + r] * w2);
                let rows = if diagonal { k + 1 } else { 6 };
                for (o, x) in s[base..base + rows].iter_mut().zip(&col) {
                    *o -= x;
                }
            }
            continue;
        }
        let y = &y[ci.data..ci.data + 3 * di];
        let w = &w[cj.data..cj.data + 3 * dj];
        for k in 0..dj {
            let base = col_ptr[pair.col0 + k] + pair.prefix;
            let rows = if diagonal { k + 1 } else { di };
            let (w0, w1, w2) = (w[k], w[dj + k], w[2 * dj + k]);
            for (rr, o) in s[base..base + rows].iter_mut().enumerate() {
                *o -= y[rr] * w0 + y[di + rr] * w1 + y[2 * di + rr] * w2;
            }
        }
    }
}

/// `JᵀJ` (column-major `N × N`) and `Jᵀr` of a column-major `m × N` Jacobian, by rows: sized at
/// compile time so that the products unroll and vectorise.
#[inline]
fn gram<const N: usize>(jac: &[f64], r: &[f64], jtj: &mut [f64], jtr: &mut [f64]) {
    let m = r.len();
    let mut a = [[0.0; N]; N];
    let mut b = [0.0; N];
    for (row, &rv) in r.iter().enumerate() {
        let j: [f64; N] = std::array::from_fn(|c| jac[c * m + row]);
        for c in 0..N {
            b[c] += j[c] * rv;
            for i in 0..=c {
                a[c][i] += j[i] * j[c];
            }
        }
    }
    for c in 0..N {
        for i in 0..=c {
            jtj[c * N + i] = a[c][i];
            jtj[i * N + c] = a[c][i];
        }
    }
    jtr.copy_from_slice(&b);
}

fn gram_dyn(jac: &[f64], r: &[f64], n: usize, jtj: &mut [f64], jtr: &mut [f64]) {
    let m = r.len();
    let column = |i: usize| &jac[i * m..(i + 1) * m];
    for j in 0..n {
        let cj = column(j);
        jtr[j] = dot(cj, r);
        for i in 0..=j {
            let x = dot(column(i), cj);
            jtj[j * n + i] = x;
            jtj[i * n + j] = x;
        }
    }
}

#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}
