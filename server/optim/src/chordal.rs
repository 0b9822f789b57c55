//! Starting points for pose graphs whose poses may be far from right: a loop closed after a long
//! drift, poses chained from odometry. Least squares on SE(3) from such a start stops in a local
//! minimum (Gauss–Newton, Levenberg–Marquardt and every solver built on them do), because the
//! cost is not convex in the rotations.
//!
//! The chordal relaxation (Martinec & Pajdla 2007; the initialisation Carlone et al., ICRA 2015,
//! found best) drops the rotations' constraints: each rotation is a free 3 × 3 matrix, each
//! relative rotation asks `R_j ≈ R_i · R_ij` in the Frobenius norm, which is linear, so one
//! sparse least-squares solve gives its global optimum. Each matrix is then projected onto
//! SO(3), and with the rotations known the translations are linear too. Neither step needs a
//! starting guess: only the anchored poses (the gauge) are read.

use crate::lie::Se3;
use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use thiserror::Error;

/// One relative-pose measurement between poses `from` and `to` (indices into the poses).
#[derive(Clone, Debug)]
pub struct Relative {
    pub from: usize,
    pub to: usize,
    /// Measured `from_from_to`.
    pub measured: Se3,
    /// Weight of the chordal rotation error (an isotropic stand-in for the rotation
    /// information; only the ratios between edges matter).
    pub rotation_weight: f64,
    /// Information of the translation error in the measurement's frame (`to`'s axes as `from`
    /// sees them), as g2o and [`crate::factors::pose::BetweenFactor`] express it.
    pub translation_information: Matrix3<f64>,
}

#[derive(Debug, Error, PartialEq)]
pub enum ChordalError {
    #[error("no pose is anchored: one fixed pose sets the frame")]
    NoAnchor,
    #[error("edge {edge} names pose {pose}, but there are {poses} poses")]
    BadIndex {
        edge: usize,
        pose: usize,
        poses: usize,
    },
    #[error("edge {edge} joins pose {pose} to itself")]
    SelfLoop { edge: usize, pose: usize },
    #[error("edge {edge} has a weight that is not positive and finite")]
    BadWeight { edge: usize },
    #[error("pose {pose} is joined to no anchored pose by the edges")]
    Disconnected { pose: usize },
    #[error("the {what} system cannot be solved: {message}")]
    Solve { what: &'static str, message: String },
}

/// The poses that solve the chordal relaxation, then the translations, with `anchored` poses
/// kept as `poses` has them (the others' values are not read).
pub fn initialise(
    poses: &[Se3],
    anchored: &[bool],
    edges: &[Relative],
) -> Result<Vec<Se3>, ChordalError> {
    // A pose no edge joins to an anchor would make the systems singular: say which.
    chain(poses, anchored, edges)?;
    let free = FreeIndex::new(anchored);
    let rotations = rotations(poses, anchored, &free, edges)?;
    let translations = translations(poses, anchored, &free, edges, &rotations)?;
    Ok((0..poses.len())
        .map(|i| {
            if anchored[i] {
                return poses[i];
            }
            let r = Rotation3::from_matrix_unchecked(rotations[i]);
            Se3::new(UnitQuaternion::from_rotation_matrix(&r), translations[i])
        })
        .collect())
}

/// Poses chained from the anchored ones along the edges in the order they come, as
/// compounding odometry does: each edge places its unplaced end from its placed one, and the
/// edges are swept again until nothing more is placed. With a graph's odometry edges first,
/// every pose is the product of the odometry before it. It is what [`initialise`] is
/// compared against.
pub fn chain(
    poses: &[Se3],
    anchored: &[bool],
    edges: &[Relative],
) -> Result<Vec<Se3>, ChordalError> {
    let n = poses.len();
    check(n, anchored, edges)?;
    let mut out: Vec<Option<Se3>> = (0..n).map(|i| anchored[i].then_some(poses[i])).collect();
    let mut placed_any = true;
    while placed_any {
        placed_any = false;
        for e in edges {
            let placed = match (out[e.from], out[e.to]) {
                (Some(from), None) => Some((e.to, from.compose(&e.measured))),
                (None, Some(to)) => Some((e.from, to.compose(&e.measured.inverse()))),
                _ => None,
            };
            if let Some((pose, at)) = placed {
                out[pose] = Some(at);
                placed_any = true;
            }
        }
    }
    out.into_iter()
        .enumerate()
        .map(|(pose, p)| p.ok_or(ChordalError::Disconnected { pose }))
        .collect()
}

fn check(n: usize, anchored: &[bool], edges: &[Relative]) -> Result<(), ChordalError> {
    assert_eq!(anchored.len(), n, "one anchored flag per pose");
    if !anchored.iter().any(|&a| a) {
        return Err(ChordalError::NoAnchor);
    }
    for (edge, e) in edges.iter().enumerate() {
        for pose in [e.from, e.to] {
            if pose >= n {
                return Err(ChordalError::BadIndex {
                    edge,
                    pose,
                    poses: n,
                });
            }
        }
        if e.from == e.to {
            return Err(ChordalError::SelfLoop { edge, pose: e.from });
        }
        let info_ok = e.translation_information.iter().all(|v| v.is_finite())
            && e.translation_information.trace() > 0.0;
        if !(e.rotation_weight.is_finite() && e.rotation_weight > 0.0 && info_ok) {
            return Err(ChordalError::BadWeight { edge });
        }
    }
    Ok(())
}

/// Each free pose's column block in the linear systems (anchored poses have none).
struct FreeIndex {
    block: Vec<Option<usize>>,
    count: usize,
}

impl FreeIndex {
    fn new(anchored: &[bool]) -> Self {
        let mut count = 0;
        let block = anchored
            .iter()
            .map(|&a| {
                (!a).then(|| {
                    count += 1;
                    count - 1
                })
            })
            .collect();
        Self { block, count }
    }
}

/// Linear least squares in 3-vectors, one per pose, with residuals `x_to − M·x_from − c`
/// weighted by `W`, and `m` right-hand sides solved at once (one per column of `c` and of the
/// anchored values). The normal equations are sparse with 3 × 3 blocks.
struct BlockSystem {
    triplets: Vec<Triplet<usize, usize, f64>>,
    rhs: Mat<f64>,
}

impl BlockSystem {
    fn new(free: usize, columns: usize) -> Self {
        Self {
            triplets: Vec::new(),
            rhs: Mat::zeros(3 * free, columns),
        }
    }

    fn add_block(&mut self, row: usize, col: usize, block: &Matrix3<f64>) {
        for r in 0..3 {
            for c in 0..3 {
                // Only the lower triangle is factorised.
                if 3 * row + r >= 3 * col + c {
                    self.triplets
                        .push(Triplet::new(3 * row + r, 3 * col + c, block[(r, c)]));
                }
            }
        }
    }

    fn add_rhs(&mut self, row: usize, column: usize, v: &Vector3<f64>) {
        for r in 0..3 {
            self.rhs[(3 * row + r, column)] += v[r];
        }
    }

    /// One residual `x_to − M·x_from − c` (each column of `c` one right-hand side); `known`
    /// gives an anchored pose's vector per column.
    #[allow(clippy::too_many_arguments)]
    fn add(
        &mut self,
        free: &FreeIndex,
        from: usize,
        to: usize,
        m: &Matrix3<f64>,
        w: &Matrix3<f64>,
        c: &[Vector3<f64>],
        known: &dyn Fn(usize, usize) -> Vector3<f64>,
    ) {
        let (bf, bt) = (free.block[from], free.block[to]);
        // Jacobians: −M for `from`, I for `to`.
        if let Some(t) = bt {
            self.add_block(t, t, w);
        }
        if let Some(f) = bf {
            self.add_block(f, f, &(m.transpose() * w * m));
        }
        if let (Some(f), Some(t)) = (bf, bt) {
            let off = -(w * m); // rows of `to`, columns of `from`
            if t > f {
                self.add_block(t, f, &off);
            } else {
                self.add_block(f, t, &off.transpose());
            }
        }
        for (k, ck) in c.iter().enumerate() {
            // Residual with the anchored side moved to the right: x_to − M·x_from = c.
            let mut target = *ck;
            if bf.is_none() {
                target += m * known(from, k);
            }
            if bt.is_none() {
                target -= known(to, k);
            }
            let wc = w * target;
            if let Some(t) = bt {
                self.add_rhs(t, k, &wc);
            }
            if let Some(f) = bf {
                self.add_rhs(f, k, &(-(m.transpose() * wc)));
            }
        }
    }

    fn solve(self, what: &'static str, size: usize) -> Result<Mat<f64>, ChordalError> {
        let failed = |message: String| ChordalError::Solve { what, message };
        let mut rhs = self.rhs;
        if size == 0 {
            return Ok(rhs);
        }
        let matrix = SparseColMat::<usize, f64>::try_new_from_triplets(size, size, &self.triplets)
            .map_err(|e| failed(format!("{e:?}")))?;
        let llt = matrix
            .sp_cholesky(Side::Lower)
            .map_err(|e| failed(format!("{e:?}")))?;
        llt.solve_in_place(rhs.as_mut());
        if rhs.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
            return Err(failed("the solution is not finite".into()));
        }
        Ok(rhs)
    }
}

/// Rotations: row `k` of every rotation is unknown `x`, and `R_to = R_from · R_ij` reads
/// `x_to = R_ijᵀ · x_from` for each row, so the three rows share one matrix and are three
/// right-hand sides. The solution is projected onto SO(3).
fn rotations(
    poses: &[Se3],
    anchored: &[bool],
    free: &FreeIndex,
    edges: &[Relative],
) -> Result<Vec<Matrix3<f64>>, ChordalError> {
    let matrices: Vec<Matrix3<f64>> = poses
        .iter()
        .map(|p| *p.rotation.to_rotation_matrix().matrix())
        .collect();
    let mut system = BlockSystem::new(free.count, 3);
    let zero = [Vector3::zeros(); 3];
    let known = |pose: usize, row: usize| matrices[pose].row(row).transpose();
    for e in edges {
        let r_ij = e.measured.rotation.to_rotation_matrix();
        let w = Matrix3::identity() * e.rotation_weight;
        system.add(
            free,
            e.from,
            e.to,
            &r_ij.matrix().transpose(),
            &w,
            &zero,
            &known,
        );
    }
    let solution = system.solve("rotation", 3 * free.count)?;
    Ok((0..poses.len())
        .map(|i| match free.block[i] {
            None => {
                debug_assert!(anchored[i]);
                matrices[i]
            }
            Some(b) => {
                let mut m = Matrix3::zeros();
                for row in 0..3 {
                    for col in 0..3 {
                        m[(row, col)] = solution[(3 * b + col, row)];
                    }
                }
                nearest_rotation(&m)
            }
        })
        .collect())
}

/// Translations with the rotations known: `t_to − t_from = R_from · t_ij`, each weighted by
/// its information turned into the world's axes.
fn translations(
    poses: &[Se3],
    anchored: &[bool],
    free: &FreeIndex,
    edges: &[Relative],
    rotations: &[Matrix3<f64>],
) -> Result<Vec<Vector3<f64>>, ChordalError> {
    let mut system = BlockSystem::new(free.count, 1);
    let known = |pose: usize, _: usize| poses[pose].translation;
    for e in edges {
        let r_from = rotations[e.from];
        // The error is expressed in the measured pose's axes: R_from · R_ij.
        let axes = r_from * e.measured.rotation.to_rotation_matrix().matrix();
        let w = axes * e.translation_information * axes.transpose();
        let w = (w + w.transpose()) * 0.5;
        let c = [r_from * e.measured.translation];
        system.add(free, e.from, e.to, &Matrix3::identity(), &w, &c, &known);
    }
    let solution = system.solve("translation", 3 * free.count)?;
    Ok((0..poses.len())
        .map(|i| match free.block[i] {
            None => {
                debug_assert!(anchored[i]);
                poses[i].translation
            }
            Some(b) => Vector3::new(
                solution[(3 * b, 0)],
                solution[(3 * b + 1, 0)],
                solution[(3 * b + 2, 0)],
            ),
        })
        .collect())
}

/// The rotation nearest `m` in the Frobenius norm: `U · diag(1, 1, det(U·Vᵀ)) · Vᵀ`.
fn nearest_rotation(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Matrix3::identity();
    };
    let mut d = Matrix3::identity();
    d[(2, 2)] = (u * v_t).determinant().signum();
    u * d * v_t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::random_se3;

    fn exact(truth: &[Se3], pairs: &[(usize, usize)]) -> Vec<Relative> {
        pairs
            .iter()
            .map(|&(from, to)| Relative {
                from,
                to,
                measured: truth[from].inverse().compose(&truth[to]),
                rotation_weight: 1.0 + from as f64,
                translation_information: Matrix3::from_diagonal(&Vector3::new(1.0, 4.0, 9.0)),
            })
            .collect()
    }

    fn assert_near(a: &Se3, b: &Se3) {
        let d = a.inverse().compose(b).log();
        assert!(d.norm() < 1e-9, "{a:?} vs {b:?}");
    }

    #[test]
    fn exact_measurements_give_the_poses_from_any_rotations() {
        // Rotations of every size (up to π), a loop and a chord.
        let truth: Vec<Se3> = (0..6).map(|k| random_se3(40 + k)).collect();
        let edges = exact(
            &truth,
            &[(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4)],
        );
        let mut anchored = vec![false; 6];
        anchored[0] = true;
        // Only the anchored pose is read: the rest start anywhere.
        let mut poses = vec![Se3::identity(); 6];
        poses[0] = truth[0];
        for start in [
            initialise(&poses, &anchored, &edges),
            chain(&poses, &anchored, &edges),
        ] {
            for (got, want) in start.unwrap().iter().zip(&truth) {
                assert_near(got, want);
            }
        }
    }

    #[test]
    fn two_anchors_stay_where_they_are() {
        let truth: Vec<Se3> = (0..4).map(|k| random_se3(50 + k)).collect();
        let edges = exact(&truth, &[(0, 1), (1, 2), (2, 3)]);
        let anchored = [true, false, false, true];
        let got = initialise(&truth, &anchored, &edges).unwrap();
        assert_eq!(got[0], truth[0]);
        assert_eq!(got[3], truth[3]);
        assert_near(&got[1], &truth[1]);
        assert_near(&got[2], &truth[2]);
    }

    #[test]
    fn what_cannot_be_solved_is_named() {
        let truth: Vec<Se3> = (0..4).map(|k| random_se3(60 + k)).collect();
        let anchored = [true, false, false, false];
        let edges = exact(&truth, &[(0, 1), (2, 3)]);
        assert_eq!(
            initialise(&truth, &anchored, &edges),
            Err(ChordalError::Disconnected { pose: 2 })
        );
        assert_eq!(
            initialise(&truth, &[false; 4], &edges),
            Err(ChordalError::NoAnchor)
        );
        let mut bad = exact(&truth, &[(0, 1), (1, 2), (2, 3)]);
        bad[1].to = 7;
        assert_eq!(
            initialise(&truth, &anchored, &bad),
            Err(ChordalError::BadIndex {
                edge: 1,
                pose: 7,
                poses: 4
            })
        );
        bad[1].to = 1;
        assert_eq!(
            chain(&truth, &anchored, &bad),
            Err(ChordalError::SelfLoop { edge: 1, pose: 1 })
        );
        bad[1].to = 2;
        bad[2].rotation_weight = f64::NAN;
        let message = initialise(&truth, &anchored, &bad).unwrap_err().to_string();
        assert!(message.contains("edge 2"), "{message}");
    }
}
