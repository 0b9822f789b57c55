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
//!
//! Large problems are assembled and eliminated on several threads, each with a fixed [`Share`]
//! of the work: since a factor holds at most one eliminated variable, giving each thread the
//! factors of a contiguous range of eliminated variables keeps their blocks of `V`, `W` and
//! `g_l` disjoint, and only `H_rr`, `g_r` and `S` need a private copy per thread, summed after.

mod analyse;
// These call the four-lane kernels compiled for AVX2 + FMA, after runtime detection.
#[allow(unsafe_code)]
mod assemble;
#[allow(unsafe_code)]
mod observations;
#[allow(unsafe_code)]
mod schur;

use crate::bundle::PoseViews;
use crate::parallel::{run, split_lengths};
use crate::problem::{entry_cost, Entry, Linearized};
use crate::values::Values;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{LltParams, LltRegularization};
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};
use nalgebra::Matrix3;
use std::ops::Range;

/// Diagonal entries of `H` are raised to at least this before Marquardt damping scales them,
/// so a variable no factor constrains still gets a damped, solvable block.
const MIN_DIAGONAL: f64 = 1e-6;

/// A Schur complement of at most this many scalars is laid out dense (its Cholesky then costs
/// at most about 10 Mflop).
const DENSE_LIMIT: usize = 300;

/// Problems with fewer factors are solved on one thread: below this, starting threads costs
/// more than it saves (pose-only tracking has a few hundred).
const PARALLEL_MIN_FACTORS: usize = 4000;

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

/// One thread's part of the work: its factors and the eliminated variables they hold, with
/// those variables' couplings, entries of `w`/`y`, and Schur pairs.
#[derive(Clone, Debug, Default)]
struct Share {
    /// Factors assembled one by one.
    factors: Vec<u32>,
    /// Reprojections assembled four at a time.
    observations: observations::Observations,
    elim: Range<usize>,
    data: Range<usize>,
    pairs: Range<usize>,
}

/// What the analysis decides; read by every thread.
struct Structure {
    /// Scalar offset of each variable in the update vector (reduced variables first, then the
    /// eliminated ones), `usize::MAX` when fixed.
    offset: Vec<usize>,
    n_reduced: usize,
    n: usize,
    /// `S` is laid out dense: column `c` holds rows `0..=c`.
    dense: bool,
    /// `Some(number of poses)` when `S` is dense and every reduced variable is a pose (bundle
    /// adjustment): the Schur update then works on 6 × 6 blocks.
    pose_blocks: Option<usize>,
    /// Every coupling's `W` comes from exactly one factor, which stores it.
    w_single: bool,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    diag: Vec<usize>,
    slot_start: Vec<usize>,
    slots: Vec<Slot>,
    elim_start: Vec<usize>,
    elim_slots: Vec<ElimSlot>,
    coupling_start: Vec<usize>,
    couplings: Vec<Coupling>,
    /// Empty when `S` is dense.
    pairs: Vec<SchurPair>,
    shares: Vec<Share>,
}

/// Scratch for evaluating one factor at a time.
#[derive(Default)]
struct Scratch {
    lin: Linearized,
    jtj: Vec<f64>,
    jtr: Vec<f64>,
    /// Each pose's own block while assembling with pose blocks.
    pose_sums: Vec<[f64; 36]>,
    /// What observations add to each pose's own block.
    pose_parts: Vec<observations::PoseParts>,
}

/// A helper thread's private sums: `H_rr` and `g_r` while assembling, `S` and the reduced
/// right-hand side while eliminating.
#[derive(Default)]
struct Private {
    h: Vec<f64>,
    g_r: Vec<f64>,
    s: Vec<f64>,
    rhs: Vec<f64>,
    scratch: Scratch,
}

/// Damping applied to the normal equations.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Damping {
    /// Gauss–Newton: none.
    None,
    /// `H + λ·diag(H)` (Marquardt), with diagonal entries clamped from below.
    Marquardt(f64),
}

impl Damping {
    fn lambda(self) -> f64 {
        match self {
            Damping::None => 0.0,
            Damping::Marquardt(lambda) => lambda,
        }
    }
}

pub(crate) struct NormalEquations {
    layout: (u64, usize, u64),
    eliminate: bool,
    threads: usize,
    st: Structure,
    /// `H_rr` (upper triangle, by column), undamped.
    h: Vec<f64>,
    /// The damped Schur complement `S`, same pattern.
    damped: Vec<f64>,
    /// Gradient `g = Jᵀ r` (whitened and weighted), reduced entries then eliminated ones.
    g: Vec<f64>,
    /// `H_ll` of each eliminated variable, and its damped inverse.
    v: Vec<Matrix3<f64>>,
    v_inv: Vec<Matrix3<f64>>,
    /// `H_rl` blocks.
    w: Vec<f64>,
    /// `H_rl·H_ll⁻¹` in `w`'s layout; empty where it is not stored ([`schur::stores_y`]).
    y: Vec<f64>,
    symbolic: SymbolicCholesky<usize>,
    l_values: Vec<f64>,
    memory: MemBuffer,
    scratch: Scratch,
    /// One per share after the first.
    helpers: Vec<Private>,
}

#[derive(Debug, thiserror::Error)]
pub(crate) enum LinearError {
    #[error("the damped normal equations are not positive definite")]
    NotPositiveDefinite,
    #[error("sparse analysis failed: {0}")]
    Analysis(String),
}

impl NormalEquations {
    /// The problem layout, elimination setting and thread count this system was analysed for.
    pub fn layout(&self) -> ((u64, usize, u64), bool, usize) {
        (self.layout, self.eliminate, self.threads)
    }

    /// Length of the update vector.
    pub fn dim(&self) -> usize {
        self.st.n
    }

    /// Number of eliminated variables.
    pub fn eliminated(&self) -> usize {
        self.v.len()
    }

    /// Threads that work on this system (1 for small problems).
    pub fn workers(&self) -> usize {
        self.st.shares.len()
    }

    /// Scalar offset of each variable in the update vector (`usize::MAX` when fixed).
    pub fn offsets(&self) -> &[usize] {
        &self.st.offset
    }

    /// Evaluates every factor at `values` (whose pose views are `views`), fills `H` and `g`, and
    /// returns the cost.
    pub fn linearize(&mut self, entries: &[Entry], values: &Values, views: &PoseViews) -> f64 {
        let st = &self.st;
        self.h.fill(0.0);
        self.g.fill(0.0);
        if !st.w_single {
            self.w.fill(0.0);
        }
        self.v.fill(Matrix3::zeros());
        for p in &mut self.helpers {
            p.h.fill(0.0);
            p.g_r.fill(0.0);
        }
        let (g_r, g_l) = self.g.split_at_mut(st.n_reduced);
        let g_l = split_lengths(g_l, st.shares.iter().map(|s| 3 * s.elim.len()));
        let v = split_lengths(&mut self.v, st.shares.iter().map(|s| s.elim.len()));
        let w = split_lengths(&mut self.w, st.shares.iter().map(|s| s.data.len()));
        let sums = std::iter::once((&mut self.h[..], g_r, &mut self.scratch)).chain(
            self.helpers
                .iter_mut()
                .map(|p| (&mut p.h[..], &mut p.g_r[..], &mut p.scratch)),
        );
        let jobs: Vec<_> = st
            .shares
            .iter()
            .zip(sums)
            .zip(g_l.into_iter().zip(v).zip(w))
            .map(|((share, (h, g_r, scratch)), ((g_l, v), w))| {
                let out = assemble::Accumulators { h, g_r, g_l, v, w };
                (share, out, scratch)
            })
            .collect();
        let costs = run(jobs, |(share, out, scratch)| {
            assemble::assemble(st, share, entries, (values, views), out, scratch)
        });
        for p in &self.helpers {
            add(&mut self.h, &p.h);
            add(&mut self.g[..st.n_reduced], &p.g_r);
        }
        costs.iter().sum()
    }

    /// `Σ ρ(rᵀΩr)` of every factor at `values` (whose pose views are `views`), share by share
    /// as assembly sums it.
    pub fn cost(&self, entries: &[Entry], values: &Values, views: &PoseViews) -> f64 {
        let costs = run(self.st.shares.iter().collect(), |share| {
            let mut r = Vec::new();
            let others: f64 = share
                .factors
                .iter()
                .map(|&fi| entry_cost(&entries[fi as usize], values, views, &mut r))
                .sum();
            share.observations.cost(values, views) + others
        });
        costs.iter().sum()
    }

    /// Largest absolute entry of the gradient.
    pub fn gradient_max(&self) -> f64 {
        self.g.iter().fold(0.0, |m, v| m.max(v.abs()))
    }

    /// Solves `(H + damping) δ = −g` into `delta`, eliminating points first.
    pub fn solve(&mut self, damping: Damping, delta: &mut Vec<f64>) -> Result<(), LinearError> {
        let lambda = damping.lambda();
        let st = &self.st;
        let nr = st.n_reduced;
        self.damped.copy_from_slice(&self.h);
        for &i in &st.diag {
            self.damped[i] += lambda * self.h[i].max(MIN_DIAGONAL);
        }
        delta.clear();
        delta.extend(self.g.iter().map(|v| -v));
        // Eliminated blocks: V⁻¹, Y = W·V⁻¹, the right-hand side −g_r + Σ Y·g_l and S −= Y·Wᵀ.
        if !self.v.is_empty() {
            for p in &mut self.helpers {
                p.s.fill(0.0);
                p.rhs.fill(0.0);
            }
            let v_inv = split_lengths(&mut self.v_inv, st.shares.iter().map(|s| s.elim.len()));
            // `Y` is stored only where it is not formed point by point and used at once.
            let stores_y = schur::stores_y(st);
            if stores_y && self.y.len() != self.w.len() {
                self.y.resize(self.w.len(), 0.0);
            }
            let y_len = |s: &Share| if stores_y { s.data.len() } else { 0 };
            let y = split_lengths(&mut self.y, st.shares.iter().map(y_len));
            let sums = std::iter::once((&mut self.damped[..], &mut delta[..nr])).chain(
                self.helpers
                    .iter_mut()
                    .map(|p| (&mut p.s[..], &mut p.rhs[..])),
            );
            let jobs: Vec<_> = st
                .shares
                .iter()
                .zip(v_inv.into_iter().zip(y))
                .zip(sums)
                .collect();
            let (v, w, g) = (&self.v, &self.w, &self.g);
            let results = run(jobs, |((share, (v_inv, y)), (s, rhs))| {
                let input = schur::Input { v, w, g };
                schur::eliminate(st, share, lambda, input, v_inv, y, rhs, s)
            });
            results.into_iter().collect::<Result<(), _>>()?;
            for p in &self.helpers {
                add(&mut self.damped, &p.s);
                add(&mut delta[..nr], &p.rhs);
            }
        }
        if nr > 0 {
            let pattern =
                SymbolicSparseColMatRef::new_checked(nr, nr, &st.col_ptr, None, &st.row_idx);
            let matrix = SparseColMatRef::new(pattern, &self.damped);
            self.symbolic
                .factorize_numeric_llt::<f64>(
                    &mut self.l_values,
                    matrix,
                    Side::Upper,
                    LltRegularization::default(),
                    Par::Seq,
                    MemStack::new(&mut self.memory),
                    Spec::<LltParams, f64>::default(),
                )
                .map_err(|_| LinearError::NotPositiveDefinite)?;
            let llt = LltRef::new(&self.symbolic, &self.l_values);
            let rhs = MatMut::from_column_major_slice_mut(&mut delta[..nr], nr, 1);
            llt.solve_in_place_with_conj(Conj::No, rhs, Par::Seq, MemStack::new(&mut self.memory));
        }
        if !self.v.is_empty() {
            let (delta_r, delta_l) = delta.split_at_mut(nr);
            let delta_l = split_lengths(delta_l, st.shares.iter().map(|s| 3 * s.elim.len()));
            let (v_inv, w) = (&self.v_inv, &self.w);
            let delta_r = &*delta_r;
            run(
                st.shares.iter().zip(delta_l).collect(),
                |(share, delta_l)| schur::back_substitute(st, share, v_inv, w, delta_r, delta_l),
            );
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
        let nr = self.st.n_reduced;
        let reduced: f64 = self
            .st
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

fn add(sum: &mut [f64], part: &[f64]) {
    for (s, p) in sum.iter_mut().zip(part) {
        *s += p;
    }
}

#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}
