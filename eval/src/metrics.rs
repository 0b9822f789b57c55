//! Trajectory error as the `evo` tools compute it: timestamp association, Umeyama alignment,
//! absolute pose error (APE, "ATE") and relative pose error (RPE), and their statistics.
//!
//! The rules follow evo 1.38 so that the numbers agree with `evo_ape` / `evo_rpe` (checked to
//! 1e-6 on the TUM fr1/xyz files in `../shared/data/trajectories`):
//! - association starts from the trajectory with fewer poses and takes, for each of its stamps,
//!   the nearest stamp of the other within `max_diff` (ties to the earlier one);
//! - alignment moves the estimate onto the reference: `p ↦ s·R·p + t` by Umeyama's method;
//! - statistics are over the per-pose errors; `std` is the population standard deviation and
//!   the median of an even count is the mean of the middle two.

use nalgebra::{Isometry3, Matrix3, Rotation3, UnitQuaternion, Vector3};
use serde::Serialize;
use thiserror::Error;
use vsgraphs_datasets::Trajectory;

#[derive(Debug, Error, PartialEq)]
pub enum MetricsError {
    #[error("no timestamps match within {max_diff} s (offset {offset} s)")]
    NoMatches { max_diff: f64, offset: f64 },
    #[error("alignment needs at least 3 non-collinear positions; the covariance has rank {rank}")]
    Degenerate { rank: usize },
    #[error("RPE with delta {delta} needs more than {delta} matched poses, there are {poses}")]
    TooShortForDelta { delta: usize, poses: usize },
    #[error("delta must be at least 1")]
    ZeroDelta,
}

/// How the estimate is aligned to the reference before comparing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    None,
    /// Rotation and translation (`evo -a`).
    Se3,
    /// Rotation, translation and scale (`evo -as`), for monocular estimates.
    Sim3,
}

/// Which part of the pose error is measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Relation {
    /// Norm of the translation error, metres (`evo -r trans_part`, the default).
    Translation,
    /// Angle of the rotation error, degrees (`evo -r angle_deg`).
    AngleDeg,
}

/// `p ↦ scale·rotation·p + translation`.
#[derive(Clone, Copy, Debug)]
pub struct Similarity {
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
    pub scale: f64,
}

impl Similarity {
    pub fn identity() -> Self {
        Self {
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// The pose moved by this transform: its position mapped, its rotation turned.
    pub fn apply(&self, pose: &Isometry3<f64>) -> Isometry3<f64> {
        // Umeyama's R is orthonormal to rounding, so the closed-form conversion suffices (the
        // iterative `from_matrix` would only repeat it).
        let r =
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(self.rotation));
        Isometry3::from_parts(
            (self.scale * (self.rotation * pose.translation.vector) + self.translation).into(),
            r * pose.rotation,
        )
    }
}

/// Statistics of a set of errors, with evo's names.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stats {
    pub rmse: f64,
    pub mean: f64,
    pub median: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
    pub sse: f64,
    pub count: usize,
}

impl Stats {
    /// Statistics of `errors`, which must not be empty.
    pub fn of(errors: &[f64]) -> Self {
        let n = errors.len();
        assert!(n > 0, "statistics of no errors");
        let nf = n as f64;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let mean = errors.iter().sum::<f64>() / nf;
        let var = errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / nf;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let median = if n % 2 == 1 {
            sorted[n / 2]
        } else {
            0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
        };
        Self {
            rmse: (sse / nf).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[n - 1],
            sse,
            count: n,
        }
    }
}

/// Index pairs `(reference, estimate)` of poses whose stamps match within `max_diff` seconds,
/// after adding `offset` to the estimate's stamps.
pub fn associate(
    reference: &[f64],
    estimate: &[f64],
    max_diff: f64,
    offset: f64,
) -> Result<Vec<(usize, usize)>, MetricsError> {
    let estimate: Vec<f64> = estimate.iter().map(|t| t + offset).collect();
    // Start from the shorter list so that none of its poses is lost (the estimate on a tie).
    let estimate_is_short = estimate.len() <= reference.len();
    let (short, long) = if estimate_is_short {
        (&estimate[..], reference)
    } else {
        (reference, &estimate[..])
    };
    let pairs: Vec<(usize, usize)> = nearest_stamps(short, long, max_diff)
        .into_iter()
        .map(|(s, l)| if estimate_is_short { (l, s) } else { (s, l) })
        .collect();
    if pairs.is_empty() {
        return Err(MetricsError::NoMatches { max_diff, offset });
    }
    Ok(pairs)
}

/// For each stamp of `short`, the index of the nearest stamp of `long` within `max_diff`.
fn nearest_stamps(short: &[f64], long: &[f64], max_diff: f64) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    if long.is_empty() {
        return out;
    }
    if long.windows(2).any(|w| w[1] < w[0]) {
        // Unsorted: a linear search per stamp, the first of equally near ones.
        for (i, &t) in short.iter().enumerate() {
            let (j, d) = long.iter().map(|&u| (u - t).abs()).enumerate().fold(
                (0, f64::INFINITY),
                |best, (j, d)| if d < best.1 { (j, d) } else { best },
            );
            if d <= max_diff {
                out.push((i, j));
            }
        }
        return out;
    }
    let last = long.len() - 1;
    for (i, &t) in short.iter().enumerate() {
        if t < long[0] - max_diff || t > long[last] + max_diff {
            continue;
        }
        // First stamp after t, and the one before it.
        let upper = long.partition_point(|&u| u <= t).min(last);
        let above = long[upper] - t;
        let below = if upper > 0 {
            t - long[upper - 1]
        } else {
            f64::INFINITY
        };
        if above <= max_diff && above < below {
            out.push((i, upper));
        } else if below <= max_diff && below <= above {
            out.push((i, upper - 1));
        }
    }
    out
}

/// The similarity that best maps `from` onto `to` in least squares (Umeyama 1991); with
/// `with_scale` false the scale is 1.
pub fn umeyama(
    from: &[Vector3<f64>],
    to: &[Vector3<f64>],
    with_scale: bool,
) -> Result<Similarity, MetricsError> {
    assert_eq!(from.len(), to.len(), "point sets of equal size");
    let n = from.len() as f64;
    let mean = |p: &[Vector3<f64>]| p.iter().sum::<Vector3<f64>>() / n;
    let (mean_from, mean_to) = (mean(from), mean(to));
    let var_from = from
        .iter()
        .map(|p| (p - mean_from).norm_squared())
        .sum::<f64>()
        / n;
    let cov = from
        .iter()
        .zip(to)
        .map(|(f, t)| (t - mean_to) * (f - mean_from).transpose())
        .sum::<Matrix3<f64>>()
        / n;
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u.expect("asked for U"), svd.v_t.expect("asked for Vᵀ"));
    let d = svd.singular_values;
    let rank = d.iter().filter(|&&x| x > f64::EPSILON).count();
    if rank < 2 {
        return Err(MetricsError::Degenerate { rank });
    }
    // A reflection is turned into a rotation by flipping the axis of the smallest singular value.
    let mut s = Vector3::repeat(1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s[d.imin()] = -1.0;
    }
    let rotation = u * Matrix3::from_diagonal(&s) * v_t;
    let scale = if with_scale {
        d.dot(&s) / var_from
    } else {
        1.0
    };
    Ok(Similarity {
        rotation,
        translation: mean_to - scale * rotation * mean_from,
        scale,
    })
}

/// Options shared by APE and RPE.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Compare {
    pub alignment: Alignment,
    pub relation: Relation,
    /// Largest stamp difference for a match, seconds (evo: 0.01).
    pub max_diff: f64,
    /// Added to the estimate's stamps before matching, seconds.
    pub offset: f64,
}

impl Default for Compare {
    fn default() -> Self {
        Self {
            alignment: Alignment::Se3,
            relation: Relation::Translation,
            max_diff: 0.01,
            offset: 0.0,
        }
    }
}

/// The matched, aligned pair of trajectories both scores start from.
#[derive(Clone, Debug)]
pub struct Matched {
    pub reference: Vec<Isometry3<f64>>,
    /// The estimate after alignment.
    pub estimate: Vec<Isometry3<f64>>,
    pub stamps: Vec<f64>,
    pub alignment: Similarity,
    /// Poses in each input, for "matched N of M".
    pub reference_poses: usize,
    pub estimate_poses: usize,
}

pub fn match_and_align(
    reference: &Trajectory,
    estimate: &Trajectory,
    options: &Compare,
) -> Result<Matched, MetricsError> {
    let pairs = associate(
        &reference.stamps,
        &estimate.stamps,
        options.max_diff,
        options.offset,
    )?;
    let ref_poses: Vec<Isometry3<f64>> = pairs.iter().map(|&(r, _)| reference.poses[r]).collect();
    let est_poses: Vec<Isometry3<f64>> = pairs.iter().map(|&(_, e)| estimate.poses[e]).collect();
    let alignment = match options.alignment {
        Alignment::None => Similarity::identity(),
        Alignment::Se3 | Alignment::Sim3 => {
            let positions =
                |p: &[Isometry3<f64>]| p.iter().map(|x| x.translation.vector).collect::<Vec<_>>();
            umeyama(
                &positions(&est_poses),
                &positions(&ref_poses),
                options.alignment == Alignment::Sim3,
            )?
        }
    };
    Ok(Matched {
        estimate: est_poses.iter().map(|p| alignment.apply(p)).collect(),
        reference: ref_poses,
        stamps: pairs.iter().map(|&(r, _)| reference.stamps[r]).collect(),
        alignment,
        reference_poses: reference.len(),
        estimate_poses: estimate.len(),
    })
}

/// The error of one pose difference `E` under `relation`.
fn error_of(e: &Isometry3<f64>, relation: Relation) -> f64 {
    match relation {
        Relation::Translation => e.translation.vector.norm(),
        Relation::AngleDeg => e.rotation.angle().to_degrees(),
    }
}

/// A score: per-pose errors with their stamps, and their statistics.
#[derive(Clone, Debug, Serialize)]
pub struct Score {
    pub stats: Stats,
    #[serde(skip)]
    pub errors: Vec<f64>,
    #[serde(skip)]
    pub stamps: Vec<f64>,
}

/// Absolute pose error: for translation, `|t_est − t_ref|` after alignment; for rotation, the
/// angle of `R_refᵀ·R_est`.
pub fn ape(matched: &Matched, relation: Relation) -> Score {
    let errors: Vec<f64> = matched
        .reference
        .iter()
        .zip(&matched.estimate)
        .map(|(r, e)| match relation {
            Relation::Translation => (e.translation.vector - r.translation.vector).norm(),
            Relation::AngleDeg => error_of(&(r.inverse() * e), relation),
        })
        .collect();
    Score {
        stats: Stats::of(&errors),
        errors,
        stamps: matched.stamps.clone(),
    }
}

/// Relative pose error over pose pairs `delta` apart (in matched poses): consecutive pairs
/// `(0, δ), (δ, 2δ), …` or, with `all_pairs`, every `(i, i + δ)`. The error of a pair is that of
/// `(Q_i⁻¹Q_j)⁻¹(P_i⁻¹P_j)`, the reference `Q` and the estimate `P`.
pub fn rpe(
    matched: &Matched,
    relation: Relation,
    delta: usize,
    all_pairs: bool,
) -> Result<Score, MetricsError> {
    if delta == 0 {
        return Err(MetricsError::ZeroDelta);
    }
    let n = matched.reference.len();
    if n <= delta {
        return Err(MetricsError::TooShortForDelta { delta, poses: n });
    }
    let step = if all_pairs { 1 } else { delta };
    let (q, p) = (&matched.reference, &matched.estimate);
    let (errors, stamps) = (0..n - delta)
        .step_by(step)
        .map(|i| {
            let j = i + delta;
            let e = (q[i].inverse() * q[j]).inverse() * (p[i].inverse() * p[j]);
            (error_of(&e, relation), matched.stamps[j])
        })
        .unzip::<_, _, Vec<f64>, Vec<f64>>();
    Ok(Score {
        stats: Stats::of(&errors),
        errors,
        stamps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Translation3;

    #[test]
    fn statistics_by_hand() {
        let s = Stats::of(&[3.0, 1.0, 4.0, 2.0]);
        assert_eq!((s.min, s.max, s.median, s.mean), (1.0, 4.0, 2.5, 2.5));
        assert_eq!(s.sse, 30.0);
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15);
        assert_eq!(Stats::of(&[5.0, 1.0, 3.0]).median, 3.0);
    }

    #[test]
    fn association_takes_the_nearest_stamp_within_the_limit() {
        let reference = [0.0, 0.25, 0.5, 0.75, 1.0];
        // 0.2 is nearest 0.25; 0.625 is a tie, which goes to the earlier; 1.9 is too far.
        let estimate = [0.2, 0.625, 1.9];
        let pairs = associate(&reference, &estimate, 0.13, 0.0).unwrap();
        assert_eq!(pairs, vec![(1, 0), (2, 1)]);
        // The offset is added to the estimate's stamps.
        let pairs = associate(&reference, &[-0.5], 0.01, 0.75).unwrap();
        assert_eq!(pairs, vec![(1, 0)]);
        assert!(associate(&reference, &[5.0], 0.01, 0.0).is_err());
        // Unsorted stamps are matched by a linear search.
        let pairs = associate(&[0.3, 0.1, 0.2], &[0.1, 0.2, 0.301], 0.01, 0.0).unwrap();
        assert_eq!(pairs, vec![(1, 0), (2, 1), (0, 2)]);
    }

    fn points() -> Vec<Vector3<f64>> {
        (0..20)
            .map(|i| {
                let t = i as f64 * 0.3;
                Vector3::new(t.cos() * 2.0, t.sin(), 0.1 * t * t)
            })
            .collect()
    }

    #[test]
    fn umeyama_recovers_a_known_similarity() {
        let rotation = UnitQuaternion::from_euler_angles(0.3, -1.2, 2.5);
        let truth = Similarity {
            rotation: *rotation.to_rotation_matrix().matrix(),
            translation: Vector3::new(1.0, -2.0, 3.0),
            scale: 1.7,
        };
        let from = points();
        let to: Vec<_> = from
            .iter()
            .map(|p| truth.scale * (truth.rotation * p) + truth.translation)
            .collect();
        let found = umeyama(&from, &to, true).unwrap();
        assert!((found.rotation - truth.rotation).norm() < 1e-9);
        assert!((found.translation - truth.translation).norm() < 1e-9);
        assert!((found.scale - truth.scale).abs() < 1e-9);
        let rigid = umeyama(&from, &to, false).unwrap();
        assert_eq!(rigid.scale, 1.0);
        assert!((rigid.rotation - truth.rotation).norm() < 1e-9);
        // Points on a line cannot fix a rotation.
        let line: Vec<_> = (0..5).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(matches!(
            umeyama(&line, &line, false),
            Err(MetricsError::Degenerate { .. })
        ));
    }

    #[test]
    fn a_rigidly_moved_estimate_has_no_error_once_aligned() {
        let mut reference = Trajectory::default();
        let mut estimate = Trajectory::default();
        let moved = Isometry3::from_parts(
            Translation3::new(5.0, 1.0, -1.0),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 1.0),
        );
        for (i, p) in points().iter().enumerate() {
            let pose = Isometry3::from_parts(
                (*p).into(),
                UnitQuaternion::from_euler_angles(0.0, 0.0, i as f64 * 0.1),
            );
            reference.push(i as f64, pose);
            estimate.push(i as f64 + 0.004, moved * pose);
        }
        let matched = match_and_align(&reference, &estimate, &Compare::default()).unwrap();
        assert_eq!(matched.stamps.len(), 20);
        assert!(ape(&matched, Relation::Translation).stats.max < 1e-9);
        assert!(ape(&matched, Relation::AngleDeg).stats.max < 1e-6);
        // RPE needs no alignment for a rigid motion.
        let unaligned = Compare {
            alignment: Alignment::None,
            ..Compare::default()
        };
        let matched = match_and_align(&reference, &estimate, &unaligned).unwrap();
        assert!(ape(&matched, Relation::Translation).stats.min > 1.0);
        let rpe = rpe(&matched, Relation::Translation, 3, false).unwrap();
        assert_eq!(rpe.stats.count, 6); // pairs (0,3) … (15,18)
        assert!(rpe.stats.max < 1e-9);
    }
}
