//! The rigid transform between two sets of matched 3-D points (Kabsch), which relocalisation
//! and map merging both fit.

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use vsgraphs_optim::Se3;

/// The rigid transform taking the second point of each pair onto the first, in the least
/// squares sense; `None` when the points are collinear (or fewer than three distinct).
pub fn rigid_fit(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<Se3> {
    if pairs.is_empty() {
        return None;
    }
    let n = pairs.len() as f64;
    let mean_to = pairs.iter().map(|p| p.0).sum::<Vector3<f64>>() / n;
    let mean_from = pairs.iter().map(|p| p.1).sum::<Vector3<f64>>() / n;
    let mut cross = Matrix3::zeros();
    for (to, from) in pairs {
        cross += (to - mean_to) * (from - mean_from).transpose();
    }
    let svd = cross.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    // Degenerate (collinear) samples have two vanishing singular values.
    if svd.singular_values[1] < 1e-9 * svd.singular_values[0].max(1e-12) {
        return None;
    }
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let rotation = UnitQuaternion::from_matrix(&(u * d * v_t));
    let translation = mean_to - rotation * mean_from;
    Some(Se3::new(rotation, translation))
}

/// A pair of matched points, `(to, from)`: the first where the transform should put the second.
pub type Pair = (Vector3<f64>, Vector3<f64>);

/// RANSAC over three-point rigid fits: of `samples` fits, the one `is_inlier` accepts most
/// pairs under, with those pairs; `None` when no sample gave a fit. Deterministic for a seed.
pub fn ransac_rigid(
    pairs: &[Pair],
    seed: u64,
    samples: usize,
    is_inlier: impl Fn(&Se3, &Pair) -> bool,
) -> Option<(Se3, Vec<usize>)> {
    if pairs.len() < 3 {
        return None;
    }
    let mut state = seed | 1;
    let mut next = |n: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % n as u64) as usize
    };
    let mut best: Option<(Se3, Vec<usize>)> = None;
    for _ in 0..samples {
        let (a, b, c) = (next(pairs.len()), next(pairs.len()), next(pairs.len()));
        if a == b || b == c || a == c {
            continue;
        }
        let Some(pose) = rigid_fit(&[pairs[a], pairs[b], pairs[c]]) else {
            continue;
        };
        let inliers: Vec<usize> = (0..pairs.len())
            .filter(|&i| is_inlier(&pose, &pairs[i]))
            .collect();
        if best.as_ref().is_none_or(|(_, b)| inliers.len() > b.len()) {
            best = Some((pose, inliers));
        }
    }
    best
}
