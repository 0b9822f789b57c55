//! Elimination of the points: `V⁻¹`, `Y = W·V⁻¹`, the reduced right-hand side, the Schur
//! complement `S −= Y·Wᵀ`, and the back substitution that recovers the points' steps.

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
    let pairs = &st.pairs[share.pairs.clone()];
    schur_update(pairs, &st.couplings, y, base, input.w, &st.col_ptr, s);
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
            for c in 0..3 {
                b[c] -= super::dot(&w[c * d..(c + 1) * d], dr);
            }
        }
        out.copy_from_slice((v_inv[e] * b).as_slice());
    }
}

/// `S −= Y_i·W_jᵀ` for every pair of couplings of every eliminated variable (`y` starts at
/// entry `base` of the full layout): the bulk of the
/// work of a bundle adjustment's solve, compiled for AVX2 too and chosen at run time.
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
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has just been found to support AVX2.
        return unsafe { schur_update_avx2(pairs, couplings, y, base, w, col_ptr, s) };
    }
    schur_update_portable(pairs, couplings, y, base, w, col_ptr, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
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
            // Pose–pose, the bulk of bundle adjustment: fixed-size columns.
            let y: &[f64; 18] = y[ci.data - base..ci.data - base + 18]
                .try_into()
                .expect("18 entries");
            let w: &[f64; 18] = w[cj.data..cj.data + 18].try_into().expect("18 entries");
            for k in 0..6 {
                let at = col_ptr[pair.col0 + k] + pair.prefix;
                let (w0, w1, w2) = (w[k], w[6 + k], w[12 + k]);
                let col: [f64; 6] =
                    std::array::from_fn(|r| y[r] * w0 + y[6 + r] * w1 + y[12 + r] * w2);
                if diagonal {
                    for (o, x) in s[at..at + k + 1].iter_mut().zip(&col) {
                        *o -= x;
                    }
                } else {
                    // A whole column of six, fixed in size so that it vectorises.
                    let dst: &mut [f64; 6] = (&mut s[at..at + 6]).try_into().expect("6 rows");
                    for (o, x) in dst.iter_mut().zip(&col) {
                        *o -= x;
                    }
                }
            }
            continue;
        }
        let y = &y[ci.data - base..ci.data - base + 3 * di];
        let w = &w[cj.data..cj.data + 3 * dj];
        for k in 0..dj {
            let at = col_ptr[pair.col0 + k] + pair.prefix;
            let rows = if diagonal { k + 1 } else { di };
            let (w0, w1, w2) = (w[k], w[dj + k], w[2 * dj + k]);
            for (rr, o) in s[at..at + rows].iter_mut().enumerate() {
                *o -= y[rr] * w0 + y[di + rr] * w1 + y[2 * di + rr] * w2;
            }
        }
    }
}
