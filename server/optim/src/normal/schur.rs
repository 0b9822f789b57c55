//! Elimination of the points: `V⁻¹`, `Y = W·V⁻¹`, the reduced right-hand side, the Schur
//! complement `S −= Y·Wᵀ`, and the back substitution that recovers the points' steps.
//!
//! The Schur products are the bulk of a bundle adjustment's solve. They are compiled for AVX2
//! and FMA too and chosen at run time; both builds round alike because every product is an
//! `f64::mul_add`.

use super::{Coupling, LinearError, SchurPair, Share, Structure, MIN_DIAGONAL};
#[cfg(target_arch = "x86_64")]
use crate::four::{avx2_fma, Avx};
use crate::four::{Four, Portable};
use nalgebra::{Matrix3, Vector3};

/// What elimination reads, shared by every thread.
pub(super) struct Input<'a> {
    pub v: &'a [Matrix3<f64>],
    pub w: &'a [f64],
    pub g: &'a [f64],
}

/// Eliminates the share's variables: writes their `V⁻¹` and `Y` (the share's slices), adds
/// `Σ Y·g_l` to `rhs` (the reduced right-hand side) and subtracts `Σ Y·Wᵀ` from `s`.
#[allow(clippy::too_many_arguments)]
pub(super) fn eliminate(
    st: &Structure,
    share: &Share,
    lambda: f64,
    input: Input<'_>,
    v_inv: &mut [Matrix3<f64>],
    y: &mut [f64],
    rhs: &mut [f64],
    s: &mut [f64],
) -> Result<(), LinearError> {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has just been found to support AVX2 and FMA.
        return unsafe { eliminate_avx2(st, share, lambda, input, v_inv, y, rhs, s) };
    }
    eliminate_portable(st, share, lambda, input, v_inv, y, rhs, s)
}

/// [`eliminate`] compiled for AVX2: `Y`'s products then take four lanes at a time. Rust does
/// not fuse a multiply and an add by itself, so the bits are those of the portable build.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn eliminate_avx2(
    st: &Structure,
    share: &Share,
    lambda: f64,
    input: Input<'_>,
    v_inv: &mut [Matrix3<f64>],
    y: &mut [f64],
    rhs: &mut [f64],
    s: &mut [f64],
) -> Result<(), LinearError> {
    eliminate_portable(st, share, lambda, input, v_inv, y, rhs, s)
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn eliminate_portable(
    st: &Structure,
    share: &Share,
    lambda: f64,
    input: Input<'_>,
    v_inv: &mut [Matrix3<f64>],
    y: &mut [f64],
    rhs: &mut [f64],
    s: &mut [f64],
) -> Result<(), LinearError> {
    let base = share.data.start;
    #[cfg(target_arch = "x86_64")]
    if let (Some(poses), false) = (st.pose_blocks, stores_y(st)) {
        // Bundle adjustment: each point's `Y` is formed and used at once, never stored.
        // SAFETY: the CPU has just been found to support AVX2 and FMA.
        return unsafe { pose_blocks::eliminate(st, share, poses, lambda, input, v_inv, rhs, s) };
    }
    for (e, v_inv) in share.elim.clone().zip(v_inv.iter_mut()) {
        let couplings = &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]];
        let y = couplings
            .first()
            .map_or(&mut [][..], |c| &mut y[c.data - base..]);
        *v_inv = eliminate_one::<Portable>(st.n_reduced, e, lambda, &input, couplings, y, rhs)?;
    }
    if st.dense {
        schur_update_dense(st, share, y, input.w, s);
    } else {
        let pairs = &st.pairs[share.pairs.clone()];
        schur_update(pairs, &st.couplings, y, base, input.w, &st.col_ptr, s);
    }
    Ok(())
}

/// Eliminates variable `e` (its `couplings`, contiguous in `w` and `y`, the first at the start
/// of `y`): writes their `Y = W·V⁻¹`, adds `Σ Y·g_l` to `rhs` and returns its damped `V⁻¹`.
/// A pose's `Y` takes four rows at a time in lanes; the products and sums are the scalar
/// ones, so every lane type gives the same bits.
#[inline(always)]
fn eliminate_one<F: Four>(
    n_reduced: usize,
    e: usize,
    lambda: f64,
    input: &Input<'_>,
    couplings: &[Coupling],
    y: &mut [f64],
    rhs: &mut [f64],
) -> Result<Matrix3<f64>, LinearError> {
    let mut v = input.v[e];
    for c in 0..3 {
        v[(c, c)] += lambda * v[(c, c)].max(MIN_DIAGONAL);
    }
    let v_inv = v
        .cholesky()
        .ok_or(LinearError::NotPositiveDefinite)?
        .inverse();
    let g_l = Vector3::from_column_slice(&input.g[n_reduced + 3 * e..n_reduced + 3 * e + 3]);
    let Some(first) = couplings.first() else {
        return Ok(v_inv);
    };
    let vi: [[F; 3]; 3] = std::array::from_fn(|c| std::array::from_fn(|r| F::splat(v_inv[(r, c)])));
    let gv = [F::splat(g_l.x), F::splat(g_l.y), F::splat(g_l.z)];
    let head = |x: &[f64]| F::from_array([x[0], x[1], x[2], x[3]]);
    for cp in couplings {
        let d = cp.dim;
        let at = cp.data - first.data;
        let w = &input.w[cp.data..cp.data + 3 * d];
        let y = &mut y[at..at + 3 * d];
        if d == 6 {
            // A pose, as in bundle adjustment: rows 0–3 and rows 2–5 in lanes (rows 2 and 3
            // twice, the same numbers both times).
            let w: &[f64; 18] = w.try_into().expect("6 × 3");
            let y: &mut [f64; 18] = y.try_into().expect("6 × 3");
            let rhs: &mut [f64; 6] = (&mut rhs[cp.offset..cp.offset + 6])
                .try_into()
                .expect("6 rows");
            let mut r = [head(&rhs[0..]), head(&rhs[2..])];
            for (half, r) in [0, 2].into_iter().zip(&mut r) {
                let (w0, w1, w2) = (
                    head(&w[half..]),
                    head(&w[6 + half..]),
                    head(&w[12 + half..]),
                );
                let mut yc = [F::splat(0.0); 3];
                for (c, yc) in yc.iter_mut().enumerate() {
                    *yc = w0 * vi[c][0] + w1 * vi[c][1] + w2 * vi[c][2];
                    y[6 * c + half..6 * c + half + 4].copy_from_slice(&yc.to_array());
                }
                *r = *r + (yc[0] * gv[0] + yc[1] * gv[1] + yc[2] * gv[2]);
            }
            rhs[0..4].copy_from_slice(&r[0].to_array());
            rhs[2..6].copy_from_slice(&r[1].to_array());
            continue;
        }
        for c in 0..3 {
            for rr in 0..d {
                y[c * d + rr] = w[rr] * v_inv[(0, c)]
                    + w[d + rr] * v_inv[(1, c)]
                    + w[2 * d + rr] * v_inv[(2, c)];
            }
        }
        for rr in 0..d {
            rhs[cp.offset + rr] += y[rr] * g_l.x + y[d + rr] * g_l.y + y[2 * d + rr] * g_l.z;
        }
    }
    Ok(v_inv)
}

/// Whether [`eliminate`] stores `Y` (of `w`'s size): everywhere but in bundle adjustment
/// (every reduced variable a pose) on a CPU with AVX2 and FMA, where each point's `Y` is used
/// as it is formed.
pub(super) fn stores_y(st: &Structure) -> bool {
    #[cfg(target_arch = "x86_64")]
    if st.pose_blocks.is_some() && avx2_fma() {
        return false;
    }
    true
}

/// `δ_l = V⁻¹(−g_l − Σ Wᵀ·δ_r)` for the share's variables; `delta_l` holds `−g_l` on entry.
pub(super) fn back_substitute(
    st: &Structure,
    share: &Share,
    v_inv: &[Matrix3<f64>],
    w: &[f64],
    delta_r: &[f64],
    delta_l: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has just been found to support AVX2 and FMA.
        return unsafe { back_substitute_avx2(st, share, v_inv, w, delta_r, delta_l) };
    }
    back_substitute_with::<Portable>(st, share, v_inv, w, delta_r, delta_l)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn back_substitute_avx2(
    st: &Structure,
    share: &Share,
    v_inv: &[Matrix3<f64>],
    w: &[f64],
    delta_r: &[f64],
    delta_l: &mut [f64],
) {
    back_substitute_with::<Avx>(st, share, v_inv, w, delta_r, delta_l)
}

/// [`back_substitute`]: a pose's `W_cᵀ·δ` (c = 0, 1, 2) is summed over the variable's
/// couplings as four-lane products of the columns' first four rows plus the last two, and
/// reduced once per variable.
#[inline(always)]
fn back_substitute_with<F: Four>(
    st: &Structure,
    share: &Share,
    v_inv: &[Matrix3<f64>],
    w: &[f64],
    delta_r: &[f64],
    delta_l: &mut [f64],
) {
    let load4 = |x: &[f64]| F::from_array([x[0], x[1], x[2], x[3]]);
    for (e, out) in share.elim.clone().zip(delta_l.chunks_exact_mut(3)) {
        let mut b = Vector3::from_column_slice(out);
        let mut head = [F::splat(0.0); 3];
        let mut tail = [0.0; 3];
        for cp in &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]] {
            let d = cp.dim;
            let w = &w[cp.data..cp.data + 3 * d];
            let dr = &delta_r[cp.offset..cp.offset + d];
            if d == 6 {
                let w: &[f64; 18] = w.try_into().expect("6 × 3");
                let dr: &[f64; 6] = dr.try_into().expect("6 entries");
                let dr_head = load4(dr);
                for c in 0..3 {
                    head[c] = load4(&w[6 * c..]).mul_add(dr_head, head[c]);
                    tail[c] = w[6 * c + 5].mul_add(dr[5], w[6 * c + 4].mul_add(dr[4], tail[c]));
                }
                continue;
            }
            for c in 0..3 {
                b[c] -= super::dot(&w[c * d..(c + 1) * d], dr);
            }
        }
        for c in 0..3 {
            b[c] -= head[c].sum() + tail[c];
        }
        out.copy_from_slice((v_inv[e] * b).as_slice());
    }
}

/// `S −= Y_i·W_jᵀ` for every pair of couplings of every eliminated variable when `S` is
/// sparse (`y` starts at entry `base` of the full layout).
fn schur_update(
    pairs: &[SchurPair],
    couplings: &[Coupling],
    y: &[f64],
    base: usize,
    w: &[f64],
    col_ptr: &[usize],
    s: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has just been found to support AVX2 and FMA.
        return unsafe { schur_update_avx2(pairs, couplings, y, base, w, col_ptr, s) };
    }
    schur_update_portable(pairs, couplings, y, base, w, col_ptr, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn schur_update_avx2(
    pairs: &[SchurPair],
    couplings: &[Coupling],
    y: &[f64],
    base: usize,
    w: &[f64],
    col_ptr: &[usize],
    s: &mut [f64],
) {
    schur_update_portable(pairs, couplings, y, base, w, col_ptr, s)
}

#[inline(always)]
fn schur_update_portable(
    pairs: &[SchurPair],
    couplings: &[Coupling],
    y: &[f64],
    base: usize,
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
            // Pose–pose, the bulk of bundle adjustment: fixed-size columns, each entry updated
            // by three fused multiply–adds.
            let y: &[f64; 18] = y[ci.data - base..ci.data - base + 18]
                .try_into()
                .expect("18 entries");
            let w: &[f64; 18] = w[cj.data..cj.data + 18].try_into().expect("18 entries");
            for k in 0..6 {
                let at = col_ptr[pair.col0 + k] + pair.prefix;
                let (w0, w1, w2) = (w[k], w[6 + k], w[12 + k]);
                if diagonal {
                    subtract_product_dyn(&mut s[at..at + k + 1], y, [w0, w1, w2]);
                } else {
                    // A whole column of six, fixed in size so that it vectorises.
                    let dst: &mut [f64; 6] = (&mut s[at..at + 6]).try_into().expect("6 rows");
                    subtract_product(dst, y, [w0, w1, w2]);
                }
            }
            continue;
        }
        let y = &y[ci.data - base..ci.data - base + 3 * di];
        let w = &w[cj.data..cj.data + 3 * dj];
        for k in 0..dj {
            let at = col_ptr[pair.col0 + k] + pair.prefix;
            let rows = if diagonal { k + 1 } else { di };
            subtract_product_dyn(&mut s[at..at + rows], y, [w[k], w[dj + k], w[2 * dj + k]]);
        }
    }
}

/// `S −= Y·Wᵀ` over the share's eliminated variables when `S` is dense (the usual local bundle
/// adjustment): column by column of each coupling `j`, the three entries of `W_j` in that
/// column are loaded once and every coupling `i` before `j` updates its rows with them.
fn schur_update_dense(st: &Structure, share: &Share, y: &[f64], w: &[f64], s: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has just been found to support AVX2 and FMA.
        return unsafe { schur_update_dense_avx2(st, share, y, w, s) };
    }
    schur_update_dense_portable(st, share, y, w, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn schur_update_dense_avx2(
    st: &Structure,
    share: &Share,
    y: &[f64],
    w: &[f64],
    s: &mut [f64],
) {
    schur_update_dense_portable(st, share, y, w, s)
}

#[inline(always)]
fn schur_update_dense_portable(st: &Structure, share: &Share, y: &[f64], w: &[f64], s: &mut [f64]) {
    let base = share.data.start;
    for e in share.elim.clone() {
        let couplings = &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]];
        let Some(first) = couplings.first() else {
            continue;
        };
        // The couplings of one variable are contiguous in `y` and `w`.
        let len: usize = couplings.iter().map(|c| 3 * c.dim).sum();
        let (ye, we) = (&y[first.data - base..][..len], &w[first.data..][..len]);
        if couplings.iter().all(|c| c.dim == 6) {
            poses_only(
                couplings,
                ye.as_chunks().0,
                we.as_chunks().0,
                &st.col_ptr,
                s,
            );
            continue;
        }
        let mut at_j = 0;
        for (jx, cj) in couplings.iter().enumerate() {
            let dj = cj.dim;
            let wj = &we[at_j..at_j + 3 * dj];
            for k in 0..dj {
                let c = cj.offset + k;
                let column = &mut s[st.col_ptr[c]..st.col_ptr[c + 1]];
                let wk = [wj[k], wj[dj + k], wj[2 * dj + k]];
                let mut at_i = 0;
                for ci in &couplings[..jx] {
                    let yi = &ye[at_i..at_i + 3 * ci.dim];
                    subtract_product_dyn(&mut column[ci.offset..ci.offset + ci.dim], yi, wk);
                    at_i += 3 * ci.dim;
                }
                // The diagonal block: its upper triangle, rows up to this column.
                let yj = &ye[at_j..at_j + 3 * dj];
                subtract_product_dyn(&mut column[cj.offset..=c], yj, wk);
            }
            at_j += 3 * dj;
        }
    }
}

/// [`schur_update_dense`] for a variable all of whose neighbours are poses (a map point):
/// every block is `6 × 6`.
#[inline(always)]
fn poses_only(
    couplings: &[Coupling],
    y: &[[f64; 18]],
    w: &[[f64; 18]],
    col_ptr: &[usize],
    s: &mut [f64],
) {
    for (jx, (cj, wj)) in couplings.iter().zip(w).enumerate() {
        // Where the six columns of block column `j` start; block row `i` is at `i`'s offset.
        let starts: [usize; 6] = std::array::from_fn(|k| col_ptr[cj.offset + k]);
        let wk: [[f64; 3]; 6] = std::array::from_fn(|k| [wj[k], wj[6 + k], wj[12 + k]]);
        // What makes every block row above the diagonal fall inside `s`, checked once per
        // block column rather than once per row: the columns start in order, the last one
        // reaches the diagonal block, and the couplings (sorted by offset) do not overlap, so
        // for `i` before `j`, `start + i.offset + 6 ≤ starts[5] + j.offset ≤ s.len()`.
        assert!(starts.is_sorted() && starts[5] + cj.offset + 6 <= s.len());
        assert!(jx == 0 || couplings[jx - 1].offset + 6 <= cj.offset);
        let s_ptr = s.as_mut_ptr();
        for (ci, yi) in couplings[..jx].iter().zip(y) {
            // One block: `Y_i` stays in registers for its six columns.
            for (start, wk) in starts.iter().zip(&wk) {
                // SAFETY: in bounds by the asserts above; no other reference into `s` is
                // alive while `rows` is.
                let rows = unsafe { &mut *s_ptr.add(start + ci.offset).cast::<[f64; 6]>() };
                subtract_product(rows, yi, *wk);
            }
        }
        // The diagonal block: its upper triangle, rows up to each column, each column's
        // length fixed at compile time so that it vectorises.
        let yj = &y[jx];
        let at: [usize; 6] = std::array::from_fn(|k| starts[k] + cj.offset);
        subtract_product_upper::<1>(&mut s[at[0]..], yj, wk[0]);
        subtract_product_upper::<2>(&mut s[at[1]..], yj, wk[1]);
        subtract_product_upper::<3>(&mut s[at[2]..], yj, wk[2]);
        subtract_product_upper::<4>(&mut s[at[3]..], yj, wk[3]);
        subtract_product_upper::<5>(&mut s[at[4]..], yj, wk[4]);
        subtract_product_upper::<6>(&mut s[at[5]..], yj, wk[5]);
    }
}

/// `rows −= (Y·w)[..R]` for a `6 × 3` column-major `Y` (`R < 6`: a column of a diagonal
/// block, upper triangle only), by fused multiply–adds.
#[inline(always)]
fn subtract_product<const R: usize>(rows: &mut [f64; R], y: &[f64; 18], w: [f64; 3]) {
    for (r, o) in rows.iter_mut().enumerate() {
        *o = (-y[12 + r]).mul_add(w[2], (-y[6 + r]).mul_add(w[1], (-y[r]).mul_add(w[0], *o)));
    }
}

/// [`subtract_product`] on the first `R` entries of `rows`.
#[inline(always)]
fn subtract_product_upper<const R: usize>(rows: &mut [f64], y: &[f64; 18], w: [f64; 3]) {
    subtract_product::<R>((&mut rows[..R]).try_into().expect("R rows"), y, w);
}

/// `rows −= Y[..rows]·w` for a `d × 3` column-major `Y` of which the first rows are used.
#[inline(always)]
fn subtract_product_dyn(rows: &mut [f64], y: &[f64], w: [f64; 3]) {
    let d = y.len() / 3;
    for (r, o) in rows.iter_mut().enumerate() {
        *o = (-y[2 * d + r]).mul_add(w[2], (-y[d + r]).mul_add(w[1], (-y[r]).mul_add(w[0], *o)));
    }
}

/// The dense Schur update of a bundle adjustment, where every reduced variable is a pose. `S`
/// is copied into 6 × 6 blocks of nine 2 × 2 tiles, one four-lane vector each: a tile's
/// `Y_i` operand is two rows of a column of `Y_i` loaded twice over, its `W_j` operand two
/// entries each repeated, so `W_j`'s nine operand vectors stay in registers while the blocks
/// of every `i ≤ j` are updated, and `Y_i`'s are single loads. Each entry gets the same three
/// fused multiply–adds in the same order as in [`poses_only`], so the bits do not depend on the
/// CPU.
#[cfg(target_arch = "x86_64")]
mod pose_blocks {
    use super::{Coupling, Input, LinearError, Share, Structure};
    use crate::four::Avx;
    use nalgebra::Matrix3;
    use std::arch::x86_64::*;

    /// Where entry `(r, k)` of a block lies among its 36: tile `(r/2, k/2)` at
    /// `4·(3·(k/2) + r/2)`, lanes `(r even, k even), (r odd, k even), (r even, k odd), (odd, odd)`.
    fn within(r: usize, k: usize) -> usize {
        4 * (3 * (k / 2) + r / 2) + 2 * (k % 2) + r % 2
    }

    /// Calls `visit(packed, block)` for every entry of `S`'s upper triangle: its index in the
    /// packed columns and in the block layout, where block `(bi, bj)` (`bi ≤ bj`) starts at
    /// `(bj·poses + bi)·36`. A diagonal block's lower half is not visited.
    fn for_each_entry(st: &Structure, poses: usize, mut visit: impl FnMut(usize, usize)) {
        for bj in 0..poses {
            for k in 0..6 {
                let column = st.col_ptr[6 * bj + k];
                for bi in 0..=bj {
                    let rows = if bi == bj { k + 1 } else { 6 };
                    let block = (bj * poses + bi) * 36;
                    for r in 0..rows {
                        visit(column + 6 * bi + r, block + within(r, k));
                    }
                }
            }
        }
    }

    /// Eliminates the share's points as [`super::eliminate`] does, each point's `Y` formed in
    /// a scratch buffer and used at once for its Schur products (bundle adjustment's `Y` is
    /// megabytes: writing it and reading it back cost more than forming it).
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn eliminate(
        st: &Structure,
        share: &Share,
        poses: usize,
        lambda: f64,
        input: Input<'_>,
        v_inv: &mut [Matrix3<f64>],
        rhs: &mut [f64],
        s: &mut [f64],
    ) -> Result<(), LinearError> {
        let mut blocks = vec![0.0; poses * poses * 36];
        for_each_entry(st, poses, |packed, block| blocks[block] = s[packed]);
        let (mut y, mut starts) = (Vec::new(), Vec::new());
        for (e, v_inv) in share.elim.clone().zip(v_inv.iter_mut()) {
            let couplings = &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]];
            y.resize(18 * couplings.len(), 0.0);
            *v_inv = super::eliminate_one::<Avx>(
                st.n_reduced,
                e,
                lambda,
                &input,
                couplings,
                &mut y,
                rhs,
            )?;
            // Each coupling's pose index, times 36: where its blocks start in a block column.
            starts.clear();
            starts.extend(couplings.iter().map(|c| c.offset / 6 * 36));
            update(&mut blocks, poses, couplings, &starts, &y, input.w);
        }
        for_each_entry(st, poses, |packed, block| s[packed] = blocks[block]);
        Ok(())
    }

    /// `S −= Y·Wᵀ` for one point's couplings (all poses), whose `Y` blocks are `y` in order,
    /// whose `W` blocks are in `w`, and whose poses' indices times 36 are `starts`.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn update(
        blocks: &mut [f64],
        poses: usize,
        couplings: &[Coupling],
        starts: &[usize],
        y: &[f64],
        w: &[f64],
    ) {
        let m = couplings.len();
        // What keeps every access below in bounds, checked once per point: the couplings'
        // poses (and so their blocks) exist, and `y` holds a block per coupling.
        assert!(starts.len() == m && y.len() == 18 * m);
        assert!(starts.iter().all(|&b| b + 36 <= 36 * poses));
        assert!(blocks.len() == 36 * poses * poses);
        let (blocks, y) = (blocks.as_mut_ptr(), y.as_ptr());
        for (jx, cj) in couplings.iter().enumerate() {
            let wj: &[f64; 18] = w[cj.data..cj.data + 18].try_into().expect("6 × 3");
            // Column pair q of W_j: (w[2q], w[2q], w[2q + 1], w[2q + 1]) of each product m.
            let mut wv = [[_mm256_setzero_pd(); 3]; 3];
            for (q, wv) in wv.iter_mut().enumerate() {
                for (m, v) in wv.iter_mut().enumerate() {
                    let pair = _mm_loadu_pd(wj[6 * m + 2 * q..].as_ptr());
                    *v = _mm256_permute4x64_pd::<0b01_01_00_00>(_mm256_castpd128_pd256(pair));
                }
            }
            let column = blocks.add(starts[jx] * poses);
            for (ix, &start) in starts[..=jx].iter().enumerate() {
                // SAFETY: block (i, j) lies within `blocks` and Y_i within `y` (asserts above).
                let b = column.add(start);
                let yi = y.add(18 * ix);
                for p in 0..3 {
                    // Row pair p of Y_i, twice: (y[2p], y[2p + 1], y[2p], y[2p + 1]).
                    let yv: [__m256d; 3] = std::array::from_fn(|m| {
                        _mm256_broadcast_pd(&*yi.add(6 * m + 2 * p).cast::<__m128d>())
                    });
                    for (q, wv) in wv.iter().enumerate() {
                        let tile = b.add(4 * (3 * q + p));
                        let mut v = _mm256_loadu_pd(tile);
                        v = _mm256_fnmadd_pd(yv[0], wv[0], v);
                        v = _mm256_fnmadd_pd(yv[1], wv[1], v);
                        v = _mm256_fnmadd_pd(yv[2], wv[2], v);
                        _mm256_storeu_pd(tile, v);
                    }
                }
            }
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::normal::NormalEquations;
    use crate::testing::{bundle_scene, BundleConfig, Rng};
    use nalgebra::Matrix3;

    #[test]
    fn pose_blocks_give_the_bits_of_the_column_by_column_elimination() {
        if !avx2_fma() {
            return;
        }
        let config = BundleConfig {
            keyframes: 7,
            points: 150,
            observations_per_point: 5,
            ..BundleConfig::default()
        };
        let scene = bundle_scene(&config, 11);
        let system = NormalEquations::analyse(&scene.problem, true, 1).unwrap();
        let st = &system.st;
        let poses = st.pose_blocks.expect("a bundle adjustment has pose blocks");
        assert_eq!(poses, 7 - config.fixed_keyframes);
        let share = &st.shares[0];
        let mut rng = Rng::new(4);
        let mut random = |n: usize| -> Vec<f64> { (0..n).map(|_| rng.normal()).collect() };
        let (w, g) = (random(system.w.len()), random(system.g.len()));
        // Positive definite point blocks: A·Aᵀ + I.
        let v: Vec<Matrix3<f64>> = random(9 * system.v.len())
            .chunks_exact(9)
            .map(|a| {
                let a = Matrix3::from_column_slice(a);
                a * a.transpose() + Matrix3::identity()
            })
            .collect();
        let (start_s, start_rhs) = (random(system.h.len()), random(st.n_reduced));
        let input = || Input {
            v: &v,
            w: &w,
            g: &g,
        };
        let lambda = 1e-3;
        // Column by column, `Y` stored first.
        let (mut s_expected, mut rhs_expected) = (start_s.clone(), start_rhs.clone());
        let mut y = vec![0.0; w.len()];
        let mut v_expected = vec![Matrix3::zeros(); v.len()];
        for (e, v_inv) in share.elim.clone().zip(&mut v_expected) {
            let couplings = &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]];
            let y = couplings.first().map_or(&mut [][..], |c| &mut y[c.data..]);
            let (input, rhs) = (input(), &mut rhs_expected);
            *v_inv = eliminate_one::<Portable>(st.n_reduced, e, lambda, &input, couplings, y, rhs)
                .unwrap();
        }
        schur_update_dense_portable(st, share, &y, &w, &mut s_expected);
        // In pose blocks, each point's `Y` used at once.
        let (mut s_blocks, mut rhs_blocks) = (start_s.clone(), start_rhs.clone());
        let mut v_blocks = vec![Matrix3::zeros(); v.len()];
        // SAFETY: the CPU supports AVX2 and FMA (checked above).
        unsafe {
            let (v_inv, rhs, s) = (&mut v_blocks, &mut rhs_blocks, &mut s_blocks);
            pose_blocks::eliminate(st, share, poses, lambda, input(), v_inv, rhs, s).unwrap()
        };
        assert_ne!(s_expected, start_s);
        let bits = |x: &[f64]| -> Vec<u64> { x.iter().map(|v| v.to_bits()).collect() };
        assert_eq!(bits(&s_blocks), bits(&s_expected), "S differs");
        assert_eq!(
            bits(&rhs_blocks),
            bits(&rhs_expected),
            "the right-hand side differs"
        );
        assert_eq!(v_blocks, v_expected);
    }
}
