//! Elimination of the points: `V⁻¹`, `Y = W·V⁻¹`, the reduced right-hand side, the Schur
//! complement `S −= Y·Wᵀ`, and the back substitution that recovers the points' steps.
//!
//! The Schur products are the bulk of a bundle adjustment's solve. They are compiled for AVX2
//! and FMA too and chosen at run time; both builds round alike because every product is an
//! `f64::mul_add`.

use super::{Coupling, LinearError, SchurPair, Share, Structure, MIN_DIAGONAL};
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
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
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
    let nr = st.n_reduced;
    let base = share.data.start;
    for (e, v_inv) in share.elim.clone().zip(v_inv.iter_mut()) {
        let mut v = input.v[e];
        for c in 0..3 {
            v[(c, c)] += lambda * v[(c, c)].max(MIN_DIAGONAL);
        }
        *v_inv = v
            .cholesky()
            .ok_or(LinearError::NotPositiveDefinite)?
            .inverse();
        let g_l = Vector3::from_column_slice(&input.g[nr + 3 * e..nr + 3 * e + 3]);
        for cp in &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]] {
            let d = cp.dim;
            let w = &input.w[cp.data..cp.data + 3 * d];
            let y = &mut y[cp.data - base..cp.data - base + 3 * d];
            if d == 6 {
                // A pose, as in bundle adjustment: fixed sizes, so that it vectorises.
                let w: &[f64; 18] = w.try_into().expect("6 × 3");
                let y: &mut [f64; 18] = y.try_into().expect("6 × 3");
                let rhs: &mut [f64; 6] = (&mut rhs[cp.offset..cp.offset + 6])
                    .try_into()
                    .expect("6 rows");
                for c in 0..3 {
                    for rr in 0..6 {
                        y[c * 6 + rr] = w[rr] * v_inv[(0, c)]
                            + w[6 + rr] * v_inv[(1, c)]
                            + w[12 + rr] * v_inv[(2, c)];
                    }
                }
                for rr in 0..6 {
                    rhs[rr] += y[rr] * g_l.x + y[6 + rr] * g_l.y + y[12 + rr] * g_l.z;
                }
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
    }
    if st.dense {
        schur_update_dense(st, share, y, input.w, s);
    } else {
        let pairs = &st.pairs[share.pairs.clone()];
        schur_update(pairs, &st.couplings, y, base, input.w, &st.col_ptr, s);
    }
    Ok(())
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
    for (e, out) in share.elim.clone().zip(delta_l.chunks_exact_mut(3)) {
        let mut b = Vector3::from_column_slice(out);
        for cp in &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]] {
            let d = cp.dim;
            let w = &w[cp.data..cp.data + 3 * d];
            let dr = &delta_r[cp.offset..cp.offset + d];
            if d == 6 {
                let w: &[f64; 18] = w.try_into().expect("6 × 3");
                let dr: &[f64; 6] = dr.try_into().expect("6 entries");
                for c in 0..3 {
                    b[c] -= dot6(&w[6 * c..6 * c + 6], dr);
                }
                continue;
            }
            for c in 0..3 {
                b[c] -= super::dot(&w[c * d..(c + 1) * d], dr);
            }
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

#[inline(always)]
fn dot6(a: &[f64], b: &[f64; 6]) -> f64 {
    let a: &[f64; 6] = a.try_into().expect("6 entries");
    (0..6).map(|i| a[i] * b[i]).sum()
}

/// `S −= Y·Wᵀ` over the share's eliminated variables when `S` is dense (the usual local bundle
/// adjustment): column by column of each coupling `j`, the three entries of `W_j` in that
/// column are loaded once and every coupling `i` before `j` updates its rows with them.
fn schur_update_dense(st: &Structure, share: &Share, y: &[f64], w: &[f64], s: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        if let Some(poses) = st.pose_blocks {
            // SAFETY: the CPU has just been found to support AVX2 and FMA.
            return unsafe { pose_blocks::update(st, share, poses, y, w, s) };
        }
        // SAFETY: as above.
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

/// The dense Schur update of a bundle adjustment, where every reduced variable is a pose: `S`
/// is copied into 6 × 6 blocks of 36 contiguous entries (column-major), and each block
/// `S_ij −= Y_i·W_jᵀ` is nine vectors of four, each updated by three fused multiply–adds
/// with no lane wasted (a column of six would take a vector of four and one of two). Each
/// entry gets the same three fused operations in the same order as in [`poses_only`], so the
/// bits do not depend on the CPU.
#[cfg(target_arch = "x86_64")]
mod pose_blocks {
    use super::{Share, Structure};
    use std::arch::x86_64::*;

    /// Calls `visit(packed, block)` for every entry of `S`'s upper triangle: its index in the
    /// packed columns and in the block layout, where block `(bi, bj)` (`bi ≤ bj`) starts at
    /// `(bj·poses + bi)·36`, column-major. A diagonal block's lower half is not visited.
    fn for_each_entry(st: &Structure, poses: usize, mut visit: impl FnMut(usize, usize)) {
        for bj in 0..poses {
            for k in 0..6 {
                let column = st.col_ptr[6 * bj + k];
                for bi in 0..=bj {
                    let rows = if bi == bj { k + 1 } else { 6 };
                    let block = (bj * poses + bi) * 36 + 6 * k;
                    for r in 0..rows {
                        visit(column + 6 * bi + r, block + r);
                    }
                }
            }
        }
    }

    /// Vector t of a block holds its entries 4t..4t+4, of columns ⌊(4t+q)/6⌋: W_j's entries
    /// of those columns, for each of the three products m.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn w_vectors(wj: &[f64; 18]) -> [[__m256d; 3]; 9] {
        let mut wv = [[_mm256_setzero_pd(); 3]; 9];
        for m in 0..3 {
            let b: [__m256d; 6] = std::array::from_fn(|k| _mm256_set1_pd(wj[6 * m + k]));
            for (g, pair) in b.chunks_exact(2).enumerate() {
                wv[3 * g][m] = pair[0];
                wv[3 * g + 1][m] = _mm256_blend_pd::<0b1100>(pair[0], pair[1]);
                wv[3 * g + 2][m] = pair[1];
            }
        }
        wv
    }

    /// `S −= Σ Y·Wᵀ` over the share's points, `S` packed as [`super::schur_update_dense`]'s.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn update(
        st: &Structure,
        share: &Share,
        poses: usize,
        y: &[f64],
        w: &[f64],
        s: &mut [f64],
    ) {
        let mut blocks = vec![0.0; poses * poses * 36];
        for_each_entry(st, poses, |packed, block| blocks[block] = s[packed]);
        let base = share.data.start;
        // Per coupling of one point: its block index and W's vectors (see `w_vectors`).
        let mut columns: Vec<(usize, [[__m256d; 3]; 9])> = Vec::new();
        for e in share.elim.clone() {
            let couplings = &st.couplings[st.coupling_start[e]..st.coupling_start[e + 1]];
            columns.clear();
            columns.extend(couplings.iter().map(|c| {
                let wj: &[f64; 18] = w[c.data..c.data + 18].try_into().expect("6 × 3");
                (c.offset / 6, w_vectors(wj))
            }));
            for (ix, ci) in couplings.iter().enumerate() {
                let yi: &[f64; 18] = y[ci.data - base..ci.data - base + 18]
                    .try_into()
                    .expect("6 × 3");
                // The rows of vector t cycle with t mod 3: 0–3, then 4, 5, 0, 1, then 2–5.
                let mut yv = [[_mm256_setzero_pd(); 3]; 3];
                for m in 0..3 {
                    let low = _mm256_loadu_pd(yi[6 * m..6 * m + 4].as_ptr());
                    let high = _mm256_loadu_pd(yi[6 * m + 2..6 * m + 6].as_ptr());
                    yv[0][m] = low;
                    yv[1][m] = _mm256_permute2f128_pd::<0x21>(high, low);
                    yv[2][m] = high;
                }
                let bi = columns[ix].0;
                for (bj, wv) in &columns[ix..] {
                    let at = (bj * poses + bi) * 36;
                    let block: &mut [f64; 36] = (&mut blocks[at..at + 36])
                        .try_into()
                        .expect("a 6 × 6 block");
                    let p = block.as_mut_ptr();
                    // Nine vectors, unrolled: t = 3g + u.
                    for g in 0..3 {
                        for u in 0..3 {
                            let (wv, yv, q) = (&wv[3 * g + u], &yv[u], p.add(12 * g + 4 * u));
                            let mut v = _mm256_loadu_pd(q);
                            v = _mm256_fnmadd_pd(yv[0], wv[0], v);
                            v = _mm256_fnmadd_pd(yv[1], wv[1], v);
                            v = _mm256_fnmadd_pd(yv[2], wv[2], v);
                            _mm256_storeu_pd(q, v);
                        }
                    }
                }
            }
        }
        for_each_entry(st, poses, |packed, block| s[packed] = blocks[block]);
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::normal::NormalEquations;
    use crate::testing::{bundle_scene, BundleConfig, Rng};

    #[test]
    fn pose_blocks_give_the_bits_of_the_column_by_column_update() {
        if !(std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma"))
        {
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
        let (y, w) = (random(system.w.len()), random(system.w.len()));
        let start = random(system.h.len());
        let mut expected = start.clone();
        schur_update_dense_portable(st, share, &y, &w, &mut expected);
        let mut blocks = start.clone();
        // SAFETY: the CPU supports AVX2 and FMA (checked above).
        unsafe { pose_blocks::update(st, share, poses, &y, &w, &mut blocks) };
        assert_ne!(expected, start);
        let same = expected
            .iter()
            .zip(&blocks)
            .all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "the two updates differ");
    }
}
