//! Assembly of `H` and `g`: each factor is linearised, its `JᵀJ` and `Jᵀr` formed, and the
//! blocks scattered to the places the analysis gave them.

use super::{Scratch, Share, Structure};
use crate::bundle::{PosePointBlocks, PoseViews};
use crate::problem::Entry;
use crate::values::Kind;
use crate::values::Values;
use nalgebra::Matrix3;

/// Where one share's sums go: `H_rr` and `g_r` in full (private to the thread), and the share's
/// own slices of `g_l`, `V` and `W`.
pub(super) struct Accumulators<'a> {
    pub h: &'a mut [f64],
    pub g_r: &'a mut [f64],
    pub g_l: &'a mut [f64],
    pub v: &'a mut [Matrix3<f64>],
    pub w: &'a mut [f64],
}

/// Linearises the share's factors into `out` and returns their cost. The arithmetic is the
/// same on every path (Rust never fuses a multiply and an add by itself), so the AVX2 build
/// only changes the speed.
pub(super) fn assemble(
    st: &Structure,
    share: &Share,
    entries: &[Entry],
    (values, views): (&Values, &PoseViews),
    out: Accumulators<'_>,
    scratch: &mut Scratch,
) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has just been found to support AVX2.
        return unsafe { assemble_avx2(st, share, entries, (values, views), out, scratch) };
    }
    assemble_portable(st, share, entries, (values, views), out, scratch)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn assemble_avx2(
    st: &Structure,
    share: &Share,
    entries: &[Entry],
    (values, views): (&Values, &PoseViews),
    out: Accumulators<'_>,
    scratch: &mut Scratch,
) -> f64 {
    assemble_portable(st, share, entries, (values, views), out, scratch)
}

#[inline(always)]
fn assemble_portable(
    st: &Structure,
    share: &Share,
    entries: &[Entry],
    (values, views): (&Values, &PoseViews),
    mut out: Accumulators<'_>,
    scratch: &mut Scratch,
) -> f64 {
    let nr = st.n_reduced;
    let g_l_start = nr + 3 * share.elim.start;
    let Scratch {
        lin,
        jtj,
        jtr,
        pose_sums,
        pose_parts,
    } = scratch;
    // With pose blocks, a pose's own block is summed whole here (vectorised) and its upper
    // triangle added to `H` once at the end.
    pose_sums.clear();
    pose_sums.resize(st.pose_blocks.unwrap_or(0), [0.0; 36]);
    let mut cost = share
        .observations
        .assemble((values, views), &mut out, st.w_single, pose_parts);
    for &fi in &share.factors {
        let fi = fi as usize;
        let e = &entries[fi];
        // A reprojection onto an eliminated point that the four-lane path does not take (a
        // kernel other than Huber): its blocks straight from `bundle`, written to their places.
        if let Some(fast) = &e.reprojection {
            let point = st.offset[fast.point.index()];
            if point != usize::MAX && point >= nr {
                // On the stack, so that the compiler may keep parts of it in registers.
                let mut b = PosePointBlocks::default();
                cost += fast.blocks(views, values, e.kernel, &mut b);
                let pose = st.offset[fast.pose.index()];
                scatter(st, share, (fi, pose), &b, point, &mut out, pose_sums);
                continue;
            }
        }
        cost += lin.linearize(e, values);
        let keys = e.factor.keys();
        let kinds = e.factor.kinds();
        let m = e.factor.residual_dim();
        let n = e.total_dim;
        let (jac, r) = (&lin.jacobian[..m * n], &lin.residual[..m]);
        // Another pose–point factor onto an eliminated point: only the blocks that are kept
        // are formed, sizes known at compile time.
        if n == 9 && (m == 2 || m == 3) && kinds == [Kind::Pose, Kind::Point] {
            let point = st.offset[keys[1].index()];
            if point != usize::MAX && point >= nr {
                let b = if m == 3 {
                    pose_point_blocks::<3>(jac, r)
                } else {
                    pose_point_blocks::<2>(jac, r)
                };
                let pose = st.offset[keys[0].index()];
                scatter(st, share, (fi, pose), &b, point, &mut out, pose_sums);
                continue;
            }
        }
        // Anything else: the factor's own JᵀJ (full, column-major) and Jᵀr, then scattered by
        // block. Both are overwritten in full below.
        let Accumulators { h, g_r, g_l, v, w } = &mut out;
        let slots = &st.slots[st.slot_start[fi]..st.slot_start[fi + 1]];
        let elim_slots = &st.elim_slots[st.elim_start[fi]..st.elim_start[fi + 1]];
        jtj.resize(n * n, 0.0);
        jtr.resize(n, 0.0);
        // The shapes of the other common factors: relative pose and prior, marker corners.
        match (m, n) {
            (6, 12) => gram::<6, 12>(jac, r, jtj, jtr),
            (6, 6) => gram::<6, 6>(jac, r, jtj, jtr),
            (8, 12) => gram::<8, 12>(jac, r, jtj, jtr),
            _ => gram_dyn(jac, r, n, jtj, jtr),
        }
        for (ia, &a) in keys.iter().enumerate() {
            let off = st.offset[a.index()];
            if off == usize::MAX {
                continue;
            }
            let dim = kinds[ia].dim();
            let g = if off < nr {
                &mut g_r[off..off + dim]
            } else {
                &mut g_l[off - g_l_start..off - g_l_start + dim]
            };
            for (g, x) in g.iter_mut().zip(&jtr[e.columns[ia]..]) {
                *g += x;
            }
        }
        for slot in slots {
            let (ia, ib) = (slot.a as usize, slot.b as usize);
            let (ca, cb) = (e.columns[ia], e.columns[ib]);
            let da = kinds[ia].dim();
            for k in 0..kinds[ib].dim() {
                let base = st.col_ptr[slot.col0 + k] + slot.prefix;
                let rows = if ia == ib { k + 1 } else { da };
                let src = &jtj[(cb + k) * n + ca..(cb + k) * n + ca + rows];
                for (h, x) in h[base..base + rows].iter_mut().zip(src) {
                    *h += x;
                }
            }
        }
        for s in elim_slots {
            let (cl, cr) = (e.columns[s.l as usize], e.columns[s.r as usize]);
            if s.l == s.r {
                let v = &mut v[s.target - share.elim.start];
                for c in 0..3 {
                    for rr in 0..3 {
                        v[(rr, c)] += jtj[(cl + c) * n + cl + rr];
                    }
                }
            } else {
                let cp = st.couplings[s.target];
                let at = cp.data - share.data.start;
                let w = &mut w[at..at + 3 * cp.dim];
                for c in 0..3 {
                    let src = &jtj[(cl + c) * n + cr..(cl + c) * n + cr + cp.dim];
                    let dst = &mut w[c * cp.dim..(c + 1) * cp.dim];
                    if st.w_single {
                        dst.copy_from_slice(src);
                    } else {
                        add(dst, src);
                    }
                }
            }
        }
    }
    for (i, sum) in pose_sums.iter().enumerate() {
        // A dense column holds every row from 0: the block's rows start at its offset.
        for k in 0..6 {
            let base = st.col_ptr[6 * i + k] + 6 * i;
            add(&mut out.h[base..base + k + 1], &sum[6 * k..6 * k + k + 1]);
        }
    }
    cost
}

/// `JᵀJ` (column-major `N × N`) and `Jᵀr` of a column-major `M × N` Jacobian, sized at compile
/// time: the rows stay in registers and each column of the square is formed whole and stored
/// once (twice the products of one triangle, but they vectorise).
#[inline(always)]
fn gram<const M: usize, const N: usize>(jac: &[f64], r: &[f64], jtj: &mut [f64], jtr: &mut [f64]) {
    let rows: [[f64; N]; M] = std::array::from_fn(|k| std::array::from_fn(|c| jac[c * M + k]));
    let r: [f64; M] = r.try_into().expect("M residuals");
    for (c, (dst, b)) in jtj.chunks_exact_mut(N).zip(jtr.iter_mut()).enumerate() {
        let mut col = [0.0; N];
        let mut g = 0.0;
        for k in 0..M {
            let s = rows[k][c];
            for (x, y) in col.iter_mut().zip(&rows[k]) {
                *x += y * s;
            }
            g += s * r[k];
        }
        dst.copy_from_slice(&col);
        *b = g;
    }
}

fn gram_dyn(jac: &[f64], r: &[f64], n: usize, jtj: &mut [f64], jtr: &mut [f64]) {
    let m = r.len();
    let column = |i: usize| &jac[i * m..(i + 1) * m];
    for j in 0..n {
        let cj = column(j);
        jtr[j] = super::dot(cj, r);
        for i in 0..=j {
            let x = super::dot(column(i), cj);
            jtj[j * n + i] = x;
            jtj[i * n + j] = x;
        }
    }
}

#[inline(always)]
fn add(sum: &mut [f64], part: &[f64]) {
    for (s, p) in sum.iter_mut().zip(part) {
        *s += p;
    }
}

/// [`PosePointBlocks`] of a column-major `M × 9` Jacobian: each row is read once into
/// registers, and every sum runs over the `M` rows in the same order as [`gram`]'s.
#[inline(always)]
fn pose_point_blocks<const M: usize>(jac: &[f64], r: &[f64]) -> PosePointBlocks {
    let jac: &[f64] = &jac[..9 * M];
    let a: [[f64; 6]; M] = std::array::from_fn(|k| std::array::from_fn(|c| jac[c * M + k]));
    let b: [[f64; 3]; M] = std::array::from_fn(|k| std::array::from_fn(|c| jac[(6 + c) * M + k]));
    let r: &[f64; M] = r.try_into().expect("M residuals");
    let mut out = PosePointBlocks::default();
    for ((a, b), &r) in a.iter().zip(&b).zip(r) {
        for (col, &ac) in out.pose.iter_mut().zip(a) {
            for (o, &ai) in col.iter_mut().zip(a) {
                *o += ai * ac;
            }
        }
        for ((coupling, point), &bc) in out.coupling.iter_mut().zip(&mut out.point).zip(b) {
            for (o, &ai) in coupling.iter_mut().zip(a) {
                *o += ai * bc;
            }
            for (o, &bi) in point.iter_mut().zip(b) {
                *o += bi * bc;
            }
        }
        for (o, &ai) in out.g_pose.iter_mut().zip(a) {
            *o += ai * r;
        }
        for (o, &bi) in out.g_point.iter_mut().zip(b) {
            *o += bi * r;
        }
    }
    out
}

/// Adds a pose–point factor's blocks (factor `fi`, its pose and point at scalar offsets `pose`
/// and `point`) to their places: `g`, the pose's upper triangle in `H_rr` (or its whole block
/// to `pose_sums` when `S` has pose blocks), the point's `V` and the coupling in `W`.
#[inline(always)]
fn scatter(
    st: &Structure,
    share: &Share,
    (fi, pose): (usize, usize),
    b: &PosePointBlocks,
    point: usize,
    out: &mut Accumulators<'_>,
    pose_sums: &mut [[f64; 36]],
) {
    let Accumulators { h, g_r, g_l, v, w } = out;
    if pose != usize::MAX {
        add(&mut g_r[pose..pose + 6], &b.g_pose);
        if !pose_sums.is_empty() {
            let sum = &mut pose_sums[pose / 6];
            for (s, x) in sum.iter_mut().zip(b.pose.as_flattened()) {
                *s += x;
            }
        }
    }
    let p = point - st.n_reduced - 3 * share.elim.start;
    add(&mut g_l[p..p + 3], &b.g_point);
    let slots = if pose_sums.is_empty() {
        &st.slots[st.slot_start[fi]..st.slot_start[fi + 1]]
    } else {
        &[]
    };
    for slot in slots {
        // The pose's own block: the upper triangle of its 6 × 6, by column.
        for (k, col) in b.pose.iter().enumerate() {
            let base = st.col_ptr[slot.col0 + k] + slot.prefix;
            add(&mut h[base..base + k + 1], &col[..k + 1]);
        }
    }
    for s in &st.elim_slots[st.elim_start[fi]..st.elim_start[fi + 1]] {
        if s.r == 1 {
            let v = &mut v[s.target - share.elim.start];
            for (c, col) in b.point.iter().enumerate() {
                for (rr, x) in col.iter().enumerate() {
                    v[(rr, c)] += x;
                }
            }
        } else {
            let at = st.couplings[s.target].data - share.data.start;
            let w: &mut [f64; 18] = (&mut w[at..at + 18]).try_into().expect("6 × 3");
            for (c, col) in b.coupling.iter().enumerate() {
                if st.w_single {
                    w[6 * c..6 * c + 6].copy_from_slice(col);
                } else {
                    add(&mut w[6 * c..6 * c + 6], col);
                }
            }
        }
    }
}
