//! The rigid transform between two sets of matched 3-D points (Kabsch), which relocalisation
//! and map merging both fit.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use vsgraphs_optim::Se3;

/// The rigid transform taking the second point of each pair onto the first, in the least
/// squares sense; `None` when the points are collinear (or fewer than three distinct).
pub fn rigid_fit(pairs: &[(Vector3<f64>, Vector3<f64>)]) -> Option<Se3> {
    if pairs.is_empty()
        || pairs
            .iter()
            .any(|(to, from)| !to.iter().chain(from.iter()).all(|x| x.is_finite()))
    {
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
    // `u · d · vᵀ` is a rotation by construction: taken as it is (nalgebra's `from_matrix`
    // iterates toward the nearest rotation without a bound, and never ends on some samples
    // RANSAC draws from wrong matches).
    let rotation =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(u * d * v_t));
    let translation = mean_to - rotation * mean_from;
    Some(Se3::new(rotation, translation))
}

/// A pair of matched points, `(to, from)`: the first where the transform should put the second.
pub type Pair = (Vector3<f64>, Vector3<f64>);

/// Whether `pose` puts a pair's camera point (`from`, depth along z) on its match: within 5 cm
/// plus 2 % of its depth, the growth of RGB-D depth noise with range.
pub fn agrees(pose: &Se3, (to, from): &Pair) -> bool {
    (pose.transform_point(from) - to).norm() < 0.05 + 0.02 * from.z
}

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

#[cfg(test)]
mod tests {
    use super::*;

    /// Points spread over a few metres, and where `pose` takes them.
    fn pairs(pose: &Se3) -> Vec<Pair> {
        (0..12)
            .map(|i| {
                let i = f64::from(i);
                let from = Vector3::new((i * 0.37).sin() * 2.0, (i * 0.91).cos(), 1.0 + i * 0.3);
                (pose.transform_point(&from), from)
            })
            .collect()
    }

    #[test]
    fn the_fit_recovers_any_turn_even_a_half_turn() {
        for angle in [
            0.0,
            0.3,
            2.0,
            std::f64::consts::PI - 1e-9,
            std::f64::consts::PI,
        ] {
            let pose = Se3::new(
                UnitQuaternion::from_axis_angle(
                    &nalgebra::Unit::new_normalize(Vector3::new(0.3, -1.0, 0.2)),
                    angle,
                ),
                Vector3::new(0.5, -0.2, 1.0),
            );
            let fit = rigid_fit(&pairs(&pose)).expect("a fit");
            assert!(
                fit.local(&pose).norm() < 1e-9,
                "{angle}: {:?}",
                fit.local(&pose)
            );
        }
    }

    #[test]
    fn points_that_are_not_numbers_give_no_fit() {
        let mut pairs = pairs(&Se3::identity());
        pairs[3].0.x = f64::NAN;
        assert_eq!(rigid_fit(&pairs), None);
        pairs[3].0.x = f64::INFINITY;
        assert_eq!(rigid_fit(&pairs), None);
    }
}
