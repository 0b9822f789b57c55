//! Laying out the normal equations of a problem: which variables are eliminated, the sparsity
//! of `S`, where each factor's blocks land, how the work is shared among threads, and the
//! symbolic Cholesky factorisation.

use super::observations::{Observations, Observed};
use super::{
    Coupling, ElimSlot, LinearError, NormalEquations, Private, SchurPair, Scratch, Share, Slot,
    Structure, DENSE_LIMIT, PARALLEL_MIN_FACTORS,
};
use crate::problem::Problem;
use crate::values::{Kind, Values, VarId};
use faer::dyn_stack::MemBuffer;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::SymbolicSparseColMatRef;
use faer::{Par, Side};
use nalgebra::Matrix3;
use std::collections::BTreeMap;

impl NormalEquations {
    /// Lays out the system of `problem` and analyses its sparsity. With `eliminate`, free points
    /// of which no factor holds two are removed by the Schur complement. Problems large enough
    /// are split into `threads` shares.
    pub fn analyse(
        problem: &Problem,
        eliminate: bool,
        threads: usize,
    ) -> Result<Self, LinearError> {
        Self::analyse_with(problem, eliminate, threads, true)
    }

    /// [`Self::analyse`], with reprojections assembled four at a time (`four_lanes`) or one at
    /// a time (to compare both). The phases, in order: which variables are eliminated and where
    /// every variable lands ([`Ordering`]), each eliminated variable's reduced neighbours, the
    /// block pattern of `S` and its scalar layout ([`Pattern`]), the couplings and Schur pairs
    /// ([`Couplings`]), where each factor's blocks go ([`FactorSlots`]), the shares of the work,
    /// and the symbolic Cholesky factorisation.
    pub(super) fn analyse_with(
        problem: &Problem,
        eliminate: bool,
        threads: usize,
        four_lanes: bool,
    ) -> Result<Self, LinearError> {
        let values = &problem.values;
        let entries = &problem.entries;
        let order = Ordering::new(problem, eliminate);
        let elim_of: Vec<Option<VarId>> = entries
            .iter()
            .map(|e| {
                e.factor
                    .keys()
                    .iter()
                    .copied()
                    .find(|k| order.elim[k.index()])
            })
            .collect();
        let neighbours = Neighbours::new(problem, &order, &elim_of);
        let dense = order.num_elim > 0 && order.n_reduced <= DENSE_LIMIT;
        let pattern = Pattern::new(problem, &order, &neighbours, dense);
        let pose_blocks = (dense
            && values
                .ids()
                .filter(|&id| order.is_reduced(id))
                .all(|id| kind_of(values, id) == Kind::Pose))
        .then_some(order.n_reduced / 6);
        let couplings = Couplings::new(&neighbours, &pattern);
        let slots = FactorSlots::new(problem, &order, &pattern, &couplings, four_lanes);
        // Whether each coupling gets exactly one factor (as a reprojection in bundle
        // adjustment): assembly then stores `W` instead of adding to a zeroed copy.
        let w_single = slots.writers.iter().all(|&c| c == 1);
        let elim_of: Vec<Option<usize>> = elim_of
            .iter()
            .map(|l| l.map(|l| order.elim_index[l.index()]))
            .collect();
        let workers = if entries.len() >= PARALLEL_MIN_FACTORS {
            threads.max(1)
        } else {
            1
        };
        let mut shares = share_out(
            &elim_of,
            &couplings.start,
            &couplings.couplings,
            &couplings.pair_start,
            couplings.w_len,
            workers,
        );
        // Where a pose's own block starts in each of its six columns.
        let diagonal = |pose: usize| {
            std::array::from_fn(|k| pattern.col_ptr[pose + k] + pattern.prefix_of(pose, pose))
        };
        for share in &mut shares {
            let mut mine = Vec::new();
            share.factors.retain(|&fi| {
                let o = slots.observed[fi as usize];
                if o.elim == Observed::NONE.elim {
                    return true;
                }
                mine.push((fi, o));
                false
            });
            share.observations = Observations::new(
                share,
                &mine,
                entries,
                &couplings.couplings,
                (&order.offset, &diagonal),
            );
        }
        let symbolic = symbolic_cholesky(&order, &pattern, dense)?;
        let memory = MemBuffer::try_new(
            symbolic
                .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
                .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq)),
        )
        .map_err(|_| LinearError::Analysis("out of memory".into()))?;
        let nnz = pattern.row_idx.len();
        let n_reduced = order.n_reduced;
        let helpers = (1..shares.len())
            .map(|_| Private {
                h: vec![0.0; nnz],
                g_r: vec![0.0; n_reduced],
                s: vec![0.0; nnz],
                rhs: vec![0.0; n_reduced],
                scratch: Scratch::default(),
            })
            .collect();
        let (num_elim, n, w_len) = (order.num_elim, order.n, couplings.w_len);
        Ok(Self {
            layout: problem.layout_version(),
            eliminate,
            threads,
            st: Structure {
                offset: order.offset,
                n_reduced,
                n,
                dense,
                pose_blocks,
                w_single,
                col_ptr: pattern.col_ptr,
                row_idx: pattern.row_idx,
                diag: pattern.diag,
                slot_start: slots.slot_start,
                slots: slots.slots,
                elim_start: slots.elim_start,
                elim_slots: slots.elim_slots,
                coupling_start: couplings.start,
                couplings: couplings.couplings,
                pairs: couplings.pairs,
                shares,
            },
            h: vec![0.0; nnz],
            damped: vec![0.0; nnz],
            g: vec![0.0; n],
            v: vec![Matrix3::zeros(); num_elim],
            v_inv: vec![Matrix3::zeros(); num_elim],
            w: vec![0.0; w_len],
            y: Vec::new(),
            l_values: vec![0.0; symbolic.len_val()],
            symbolic,
            memory,
            scratch: Scratch::default(),
            helpers,
        })
    }
}

/// Which variables are eliminated, and where each variable's unknowns land: the reduced ones
/// first (in id order), then 3 per eliminated point. A fixed variable has no place.
struct Ordering {
    elim: Vec<bool>,
    offset: Vec<usize>,
    /// Unknowns of the reduced system, and of the whole.
    n_reduced: usize,
    n: usize,
    /// Each eliminated variable's index among them.
    elim_index: Vec<usize>,
    num_elim: usize,
}

impl Ordering {
    /// With `eliminate`, free points of which no factor holds two are eliminated.
    fn new(problem: &Problem, eliminate: bool) -> Self {
        let values = &problem.values;
        let kind_of = |id: VarId| kind_of(values, id);
        let free = |id| !values.is_fixed(id);
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
        Self {
            elim,
            offset,
            n_reduced,
            n,
            elim_index,
            num_elim,
        }
    }

    fn is_reduced(&self, id: VarId) -> bool {
        self.offset[id.index()] != usize::MAX && !self.elim[id.index()]
    }
}

/// The kind of a variable the problem holds.
fn kind_of(values: &Values, id: VarId) -> Kind {
    values.variable(id).expect("checked key").kind()
}

/// Each eliminated variable's reduced neighbours `(offset, dimension)`, sorted by offset and
/// without repeats, all in one array: a vector per point would be thousands of small
/// allocations.
struct Neighbours {
    start: Vec<usize>,
    flat: Vec<(usize, usize)>,
}

impl Neighbours {
    /// `elim_of` is each factor's eliminated variable, if any.
    fn new(problem: &Problem, order: &Ordering, elim_of: &[Option<VarId>]) -> Self {
        let values = &problem.values;
        let entries = &problem.entries;
        let num_elim = order.num_elim;
        // Each variable's run counted first, then filled, then sorted and deduplicated in place.
        let mut start = vec![0usize; num_elim + 1];
        for (e, l) in entries.iter().zip(elim_of) {
            if let Some(l) = l {
                start[order.elim_index[l.index()] + 1] += e
                    .factor
                    .keys()
                    .iter()
                    .filter(|&&k| order.is_reduced(k))
                    .count();
            }
        }
        for i in 0..num_elim {
            start[i + 1] += start[i];
        }
        let mut flat = vec![(0usize, 0usize); start[num_elim]];
        let mut next = start.clone();
        for (e, l) in entries.iter().zip(elim_of) {
            if let Some(l) = l {
                let at = &mut next[order.elim_index[l.index()]];
                for &r in e.factor.keys().iter().filter(|&&k| order.is_reduced(k)) {
                    flat[*at] = (order.offset[r.index()], kind_of(values, r).dim());
                    *at += 1;
                }
            }
        }
        let mut kept = 0;
        for i in 0..num_elim {
            let run = &mut flat[start[i]..start[i + 1]];
            run.sort_unstable();
            let mut len = 0;
            for j in 0..run.len() {
                if len == 0 || run[j] != run[len - 1] {
                    run[len] = run[j];
                    len += 1;
                }
            }
            flat.copy_within(start[i]..start[i] + len, kept);
            start[i] = kept;
            kept += len;
        }
        start[num_elim] = kept;
        flat.truncate(kept);
        Self { start, flat }
    }

    fn iter(&self) -> impl Iterator<Item = &[(usize, usize)]> {
        self.start.windows(2).map(|w| &self.flat[w[0]..w[1]])
    }
}

/// The pattern of `S`'s upper triangle: block rows of each block column, then the scalar
/// compressed columns and each block row's prefix within its column.
struct Pattern {
    dense: bool,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Position of each scalar column's diagonal entry.
    diag: Vec<usize>,
    /// `(row offset, column offset)` of a block → its first row's position in each column of
    /// the block column (a dense pattern needs none: a block row starts at its own offset).
    prefix: BTreeMap<(usize, usize), usize>,
}

impl Pattern {
    /// After eliminating the points of a bundle adjustment, `S` is dense or nearly so: a small
    /// one (`dense`) is then laid out dense, which skips finding its pattern pair by pair.
    fn new(problem: &Problem, order: &Ordering, neighbours: &Neighbours, dense: bool) -> Self {
        let values = &problem.values;
        // Block rows of each block column of S, keyed by column offset then row offset.
        let mut blocks: BTreeMap<usize, BTreeMap<usize, usize>> = BTreeMap::new();
        for id in values.ids().filter(|&id| order.is_reduced(id)) {
            let off = order.offset[id.index()];
            blocks
                .entry(off)
                .or_default()
                .insert(off, kind_of(values, id).dim());
        }
        if dense {
            let reduced: Vec<(usize, usize)> = blocks.iter().map(|(&o, r)| (o, r[&o])).collect();
            for (i, &(oa, da)) in reduced.iter().enumerate() {
                for &(ob, _) in &reduced[i..] {
                    blocks.entry(ob).or_default().insert(oa, da);
                }
            }
        } else {
            for e in &problem.entries {
                let keys = e.factor.keys();
                for &a in keys.iter().filter(|&&k| order.is_reduced(k)) {
                    for &b in keys.iter().filter(|&&k| order.is_reduced(k)) {
                        let (oa, ob) = (order.offset[a.index()], order.offset[b.index()]);
                        if oa <= ob {
                            blocks
                                .entry(ob)
                                .or_default()
                                .insert(oa, kind_of(values, a).dim());
                        }
                    }
                }
            }
            for nb in neighbours.iter() {
                for (i, &(oa, da)) in nb.iter().enumerate() {
                    for &(ob, _) in &nb[i..] {
                        blocks.entry(ob).or_default().insert(oa, da);
                    }
                }
            }
        }
        let mut col_ptr = Vec::with_capacity(order.n_reduced + 1);
        let mut row_idx = Vec::new();
        let mut prefix: BTreeMap<(usize, usize), usize> = BTreeMap::new();
        let mut diag = Vec::with_capacity(order.n_reduced);
        col_ptr.push(0);
        for (&col_off, rows) in &blocks {
            let col_dim = rows[&col_off];
            let mut p = 0;
            for (&row_off, &row_dim) in rows {
                if !dense {
                    prefix.insert((row_off, col_off), p);
                }
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
        Self {
            dense,
            col_ptr,
            row_idx,
            diag,
            prefix,
        }
    }

    /// Where block row `row` starts within each column of block column `col`.
    fn prefix_of(&self, row: usize, col: usize) -> usize {
        if self.dense {
            row
        } else {
            self.prefix[&(row, col)]
        }
    }
}

/// The couplings (`H_rl` blocks) of each eliminated variable with its reduced neighbours, where
/// their entries go in `w`, and the Schur pairs their products land in (none for a dense `S`,
/// which is updated point by point).
struct Couplings {
    start: Vec<usize>,
    couplings: Vec<Coupling>,
    pair_start: Vec<usize>,
    pairs: Vec<SchurPair>,
    w_len: usize,
}

impl Couplings {
    fn new(neighbours: &Neighbours, pattern: &Pattern) -> Self {
        let mut start = Vec::new();
        let mut couplings = Vec::new();
        let mut pair_start = Vec::new();
        let mut pairs = Vec::new();
        let mut w_len = 0;
        for nb in neighbours.iter() {
            start.push(couplings.len());
            pair_start.push(pairs.len());
            let first = couplings.len();
            for &(off, dim) in nb {
                couplings.push(Coupling {
                    offset: off,
                    dim,
                    data: w_len,
                });
                w_len += 3 * dim;
            }
            for i in (first..couplings.len()).filter(|_| !pattern.dense) {
                for j in i..couplings.len() {
                    let (oi, oj) = (couplings[i].offset, couplings[j].offset);
                    pairs.push(SchurPair {
                        i: i as u32,
                        j: j as u32,
                        col0: oj,
                        prefix: pattern.prefix_of(oi, oj),
                    });
                }
            }
        }
        start.push(couplings.len());
        pair_start.push(pairs.len());
        Self {
            start,
            couplings,
            pair_start,
            pairs,
            w_len,
        }
    }

    /// The coupling of eliminated variable `e` with the reduced variable at `offset`.
    fn of(&self, e: usize, offset: usize) -> usize {
        let range = self.start[e]..self.start[e + 1];
        let found = self.couplings[range.clone()].binary_search_by_key(&offset, |c| c.offset);
        range.start + found.expect("every neighbour has a coupling")
    }
}

/// Where each factor's blocks go. Reprojections of eliminated points with a kernel the
/// four-lane path knows go there (`observed`: their point and coupling); the other factors get
/// slots in `S` (reduced pairs) and in `V`/`W` (eliminated ones). `writers` counts the factors
/// writing each coupling.
struct FactorSlots {
    observed: Vec<Observed>,
    slot_start: Vec<usize>,
    slots: Vec<Slot>,
    elim_start: Vec<usize>,
    elim_slots: Vec<ElimSlot>,
    writers: Vec<u32>,
}

impl FactorSlots {
    fn new(
        problem: &Problem,
        order: &Ordering,
        pattern: &Pattern,
        couplings: &Couplings,
        four_lanes: bool,
    ) -> Self {
        let entries = &problem.entries;
        let (elim, offset) = (&order.elim, &order.offset);
        let mut observed = vec![Observed::NONE; entries.len()];
        let mut slot_start = Vec::with_capacity(entries.len() + 1);
        let mut slots = Vec::new();
        let mut elim_start = Vec::with_capacity(entries.len() + 1);
        let mut elim_slots = Vec::new();
        let mut writers = vec![0u32; couplings.couplings.len()];
        for (e, observed) in entries.iter().zip(&mut observed) {
            slot_start.push(slots.len());
            elim_start.push(elim_slots.len());
            let fast = e
                .reprojection
                .as_ref()
                .filter(|f| four_lanes && elim[f.point.index()] && Observations::accepts(e.kernel));
            if let Some(fast) = fast {
                let point = order.elim_index[fast.point.index()];
                let coupling = order.is_reduced(fast.pose).then(|| {
                    let c = couplings.of(point, offset[fast.pose.index()]);
                    writers[c] += 1;
                    c as u32
                });
                *observed = Observed {
                    elim: point as u32,
                    coupling: coupling.unwrap_or(Observed::NONE.coupling),
                };
                continue;
            }
            let keys = e.factor.keys();
            for (ia, &a) in keys.iter().enumerate() {
                for (ib, &b) in keys.iter().enumerate() {
                    let (oa, ob) = (offset[a.index()], offset[b.index()]);
                    if order.is_reduced(a) && order.is_reduced(b) && oa <= ob {
                        slots.push(Slot {
                            a: ia as u8,
                            b: ib as u8,
                            col0: ob,
                            prefix: pattern.prefix_of(oa, ob),
                        });
                    } else if elim[a.index()] && ia == ib {
                        elim_slots.push(ElimSlot {
                            l: ia as u8,
                            r: ia as u8,
                            target: order.elim_index[a.index()],
                        });
                    } else if elim[a.index()] && order.is_reduced(b) {
                        let target = couplings.of(order.elim_index[a.index()], ob);
                        writers[target] += 1;
                        elim_slots.push(ElimSlot {
                            l: ia as u8,
                            r: ib as u8,
                            target,
                        });
                    }
                }
            }
        }
        slot_start.push(slots.len());
        elim_start.push(elim_slots.len());
        Self {
            observed,
            slot_start,
            slots,
            elim_start,
            elim_slots,
            writers,
        }
    }
}

/// The symbolic Cholesky factorisation of `S` (AMD ordering). A dense `S` is one supernode:
/// its dense kernels beat the simplicial column-by-column factorisation that faer's heuristic
/// picks for it (5× fewer instructions at 108 unknowns).
fn symbolic_cholesky(
    order: &Ordering,
    pattern: &Pattern,
    dense: bool,
) -> Result<faer::sparse::linalg::cholesky::SymbolicCholesky<usize>, LinearError> {
    let n = order.n_reduced;
    let structure =
        SymbolicSparseColMatRef::new_checked(n, n, &pattern.col_ptr, None, &pattern.row_idx);
    let params = CholeskySymbolicParams {
        supernodal_flop_ratio_threshold: if dense {
            SupernodalThreshold::FORCE_SUPERNODAL
        } else {
            SupernodalThreshold::AUTO
        },
        ..Default::default()
    };
    factorize_symbolic_cholesky(structure, Side::Upper, SymmetricOrdering::Amd, params)
        .map_err(|e| LinearError::Analysis(format!("{e:?}")))
}

/// Splits the factors into `workers` shares of about equal size. Eliminated variables are cut
/// into contiguous ranges, each factor holding one goes with it, and the other factors go to
/// whichever share has the fewest so far.
fn share_out(
    elim_of: &[Option<usize>],
    coupling_start: &[usize],
    couplings: &[Coupling],
    pair_start: &[usize],
    w_len: usize,
    workers: usize,
) -> Vec<Share> {
    let num_elim = coupling_start.len() - 1;
    let mut count = vec![0usize; num_elim];
    for e in elim_of.iter().flatten() {
        count[*e] += 1;
    }
    let total: usize = count.iter().sum();
    // Share t takes eliminated variables bounds[t]..bounds[t + 1].
    let mut bounds = vec![0];
    let mut sum = 0;
    for (e, c) in count.iter().enumerate() {
        if bounds.len() < workers && sum * workers >= total * bounds.len() && sum > 0 {
            bounds.push(e);
        }
        sum += c;
    }
    while bounds.len() <= workers {
        bounds.push(num_elim);
    }
    let data_at = |e: usize| couplings.get(coupling_start[e]).map_or(w_len, |c| c.data);
    let mut shares: Vec<Share> = bounds
        .windows(2)
        .map(|b| Share {
            factors: Vec::new(),
            observations: Observations::default(),
            elim: b[0]..b[1],
            data: data_at(b[0])..data_at(b[1]),
            pairs: pair_start[b[0]]..pair_start[b[1]],
        })
        .collect();
    let share_of = |e: usize| bounds[1..].partition_point(|&b| b <= e);
    let mut load: Vec<usize> = shares
        .iter()
        .map(|s| count[s.elim.clone()].iter().sum())
        .collect();
    for (fi, e) in elim_of.iter().enumerate() {
        let t = match e {
            Some(e) => share_of(*e),
            None => {
                let t = (0..workers)
                    .min_by_key(|&t| load[t])
                    .expect("at least one worker");
                load[t] += 1;
                t
            }
        };
        shares[t].factors.push(fi as u32);
    }
    shares
}
