//! Pose-only optimisation: one camera pose against fixed map points, as tracking solves it every
//! frame. The normal matrix is 6×6, so it is solved densely here rather than through the sparse
//! [`Problem`](crate::Problem) machinery, whose bookkeeping would cost more than the solve; the
//! residuals and Jacobians are those of [`StereoProjectionFactor`] and [`ProjectionFactor`]
//! (a test checks both paths reach the same pose).
//!
//! Robustness follows ORB-SLAM's scheme: a few rounds of Levenberg–Marquardt with a Huber kernel,
//! after each round every observation is classified by its χ² against the 95 % threshold of its
//! dimension, outliers are left out of the next round (but re-classified, so they can return),
//! and the last round runs without the kernel on the inliers only.
//!
//! [`StereoProjectionFactor`]: crate::factors::projection::StereoProjectionFactor
//! [`ProjectionFactor`]: crate::factors::projection::ProjectionFactor

use crate::bundle::{gauss_newton_terms, pose_gradient};
use crate::camera::{Pinhole, VirtualStereo};
use crate::factors::projection::{pixel_residual, CameraFromWorld};
use crate::lie::Se3;
use nalgebra::{Matrix6, Vector2, Vector3, Vector6};

/// χ² 95 % quantiles for 2 and 3 degrees of freedom.
pub const CHI2_2D: f64 = 5.991;
pub const CHI2_3D: f64 = 7.815;

/// What a keypoint measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Measurement {
    /// `(u, v)`: a keypoint without depth.
    Mono(Vector2<f64>),
    /// `(u, v, u_r)`: a keypoint with depth, `u_r = u − bf/z`.
    Stereo(Vector3<f64>),
}

/// A fixed world point seen by the camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseObservation {
    pub point_in_world: Vector3<f64>,
    pub measured: Measurement,
    /// `1/σ²` of every pixel coordinate (ORB-SLAM: the inverse of the keypoint's level scale²).
    pub information: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct PoseOnlyOptions {
    /// Classification rounds; the last one runs without the robust kernel.
    pub rounds: usize,
    pub iterations_per_round: usize,
    /// Stop a round when the step is below this (tangent norm).
    pub step_tolerance: f64,
}

impl Default for PoseOnlyOptions {
    fn default() -> Self {
        Self {
            rounds: 4,
            iterations_per_round: 10,
            step_tolerance: 1e-6,
        }
    }
}

/// The optimised pose and which observations it explains.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseOnlyResult {
    pub world_from_camera: Se3,
    /// One flag per observation: its χ² at the final pose is within the threshold.
    pub inliers: Vec<bool>,
    pub inlier_count: usize,
    /// Sum of the inliers' χ² at the final pose.
    pub inlier_chi2: f64,
}

/// Residual `r` of one observation (rows beyond its dimension are zero) and the point in the
/// camera.
fn residual(
    camera: &Pinhole,
    stereo: VirtualStereo,
    view: &CameraFromWorld,
    observation: &PoseObservation,
) -> (Vector3<f64>, Vector3<f64>) {
    let p_c = view.transform(&observation.point_in_world);
    let (depth, measured) = match observation.measured {
        Measurement::Mono(m) => (None, [m.x, m.y, 0.0]),
        Measurement::Stereo(m) => (Some(stereo), [m.x, m.y, m.z]),
    };
    let r = pixel_residual(camera, depth, &measured, &p_c);
    (Vector3::from(r), p_c)
}

/// χ² of one observation at a pose.
pub fn chi2(
    camera: &Pinhole,
    stereo: VirtualStereo,
    world_from_camera: &Se3,
    o: &PoseObservation,
) -> f64 {
    chi2_in(camera, stereo, &CameraFromWorld::new(world_from_camera), o)
}

fn chi2_in(
    camera: &Pinhole,
    stereo: VirtualStereo,
    view: &CameraFromWorld,
    o: &PoseObservation,
) -> f64 {
    residual(camera, stereo, view, o).0.norm_squared() * o.information
}

fn threshold(o: &PoseObservation) -> f64 {
    match o.measured {
        Measurement::Mono(_) => CHI2_2D,
        Measurement::Stereo(_) => CHI2_3D,
    }
}

/// Robust cost of the included observations.
fn cost(
    camera: &Pinhole,
    stereo: VirtualStereo,
    pose: &Se3,
    observations: &[PoseObservation],
    included: &[bool],
    robust: bool,
) -> f64 {
    let view = CameraFromWorld::new(pose);
    observations
        .iter()
        .zip(included)
        .filter(|(_, &inc)| inc)
        .map(|(o, _)| {
            let s = chi2_in(camera, stereo, &view, o);
            let d2 = threshold(o);
            if robust && s > d2 {
                2.0 * (d2 * s).sqrt() - d2
            } else {
                s
            }
        })
        .sum()
}

/// Optimises `initial` against the observations; an empty or hopeless set returns the initial
/// pose with no inliers.
pub fn optimise_pose(
    initial: &Se3,
    camera: &Pinhole,
    stereo: VirtualStereo,
    observations: &[PoseObservation],
    options: &PoseOnlyOptions,
) -> PoseOnlyResult {
    let mut pose = *initial;
    let mut included = vec![true; observations.len()];
    let rounds = options.rounds.max(1);
    for round in 0..rounds {
        let robust = round + 1 < rounds;
        levenberg_marquardt(
            &mut pose,
            camera,
            stereo,
            observations,
            &included,
            robust,
            options,
        );
        let view = CameraFromWorld::new(&pose);
        for (o, inc) in observations.iter().zip(included.iter_mut()) {
            *inc = chi2_in(camera, stereo, &view, o) <= threshold(o);
        }
        if included.iter().filter(|&&i| i).count() < 3 {
            break;
        }
    }
    let mut inlier_chi2 = 0.0;
    let view = CameraFromWorld::new(&pose);
    for (o, inc) in observations.iter().zip(included.iter_mut()) {
        let s = chi2_in(camera, stereo, &view, o);
        *inc = s <= threshold(o);
        if *inc {
            inlier_chi2 += s;
        }
    }
    PoseOnlyResult {
        world_from_camera: pose,
        inlier_count: included.iter().filter(|&&i| i).count(),
        inliers: included,
        inlier_chi2,
    }
}

fn levenberg_marquardt(
    pose: &mut Se3,
    camera: &Pinhole,
    stereo: VirtualStereo,
    observations: &[PoseObservation],
    included: &[bool],
    robust: bool,
    options: &PoseOnlyOptions,
) {
    let mut current = cost(camera, stereo, pose, observations, included, robust);
    let mut lambda = 1e-5;
    for _ in 0..options.iterations_per_round {
        let mut h = Matrix6::<f64>::zeros();
        let mut g = Vector6::<f64>::zeros();
        let view = CameraFromWorld::new(pose);
        for (o, _) in observations.iter().zip(included).filter(|(_, &i)| i) {
            let (r, p_c) = residual(camera, stereo, &view, o);
            let s = r.norm_squared() * o.information;
            let d2 = threshold(o);
            // Huber's weight ρ'(s): 1 inside the threshold, √(d²/s) beyond.
            let weight = if robust && s > d2 {
                (d2 / s).sqrt()
            } else {
                1.0
            } * o.information;
            // `JᵀJ` and `Jᵀr` from the Jacobian's structure, as bundle adjustment forms them.
            let depth = matches!(o.measured, Measurement::Stereo(_)).then_some(stereo);
            let (gram, jtr) = gauss_newton_terms(camera, depth, &p_c, &[r.x, r.y, r.z], weight);
            let p = [p_c.x, p_c.y, p_c.z];
            for (c, column) in gram.pose_block(&p).iter().enumerate() {
                for (rr, x) in column.iter().enumerate() {
                    h[(rr, c)] += x;
                }
            }
            for (gi, x) in g.iter_mut().zip(pose_gradient(&jtr, &p)) {
                *gi += x;
            }
        }
        let mut accepted = false;
        for _ in 0..10 {
            let mut damped = h;
            for i in 0..6 {
                damped[(i, i)] += lambda * h[(i, i)].max(1e-6);
            }
            let Some(chol) = damped.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = -chol.solve(&g);
            let candidate = pose.retract(&step);
            let tried = cost(camera, stereo, &candidate, observations, included, robust);
            if tried.is_finite() && tried <= current {
                *pose = candidate;
                current = tried;
                lambda = (lambda / 10.0).max(1e-12);
                accepted = true;
                if step.norm() < options.step_tolerance {
                    return;
                }
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factor::{Information, Kernel};
    use crate::factors::projection::{ProjectionFactor, StereoProjectionFactor};
    use crate::{Options, Problem, Solver, Values};
    use nalgebra::UnitQuaternion;

    const CAMERA: Pinhole = Pinhole {
        fx: 600.0,
        fy: 600.0,
        cx: 320.0,
        cy: 240.0,
    };
    const BF: f64 = 48.0;

    /// A deterministic scatter of points in front of a camera at `truth`, and what it measures.
    fn scene(truth: &Se3, n: usize, outliers: usize) -> Vec<PoseObservation> {
        let mut state = 12345u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|i| {
                let p_c = Vector3::new(
                    (uniform() - 0.5) * 4.0,
                    (uniform() - 0.5) * 3.0,
                    1.0 + uniform() * 4.0,
                );
                let p_w = truth.transform_point(&p_c);
                let uv = CAMERA.project(&p_c);
                let mut noise = Vector3::new(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5);
                if i < outliers {
                    noise *= 80.0;
                } else {
                    noise *= 0.5;
                }
                let measured = if i % 3 == 0 {
                    Measurement::Mono(Vector2::new(uv.x + noise.x, uv.y + noise.y))
                } else {
                    Measurement::Stereo(Vector3::new(
                        uv.x + noise.x,
                        uv.y + noise.y,
                        uv.x - BF / p_c.z + noise.z,
                    ))
                };
                PoseObservation {
                    point_in_world: p_w,
                    measured,
                    information: 1.0,
                }
            })
            .collect()
    }

    fn truth() -> Se3 {
        Se3::new(
            UnitQuaternion::from_euler_angles(0.1, -0.3, 0.7),
            Vector3::new(1.0, -2.0, 0.5),
        )
    }

    #[test]
    fn recovers_the_pose_and_finds_the_outliers() {
        let truth = truth();
        let observations = scene(&truth, 300, 30);
        let start = truth.retract(&Vector6::new(0.05, -0.04, 0.03, 0.02, -0.03, 0.01));
        let result = optimise_pose(
            &start,
            &CAMERA,
            VirtualStereo::disparity(BF),
            &observations,
            &PoseOnlyOptions::default(),
        );
        let error = truth.local(&result.world_from_camera);
        assert!(error.fixed_rows::<3>(0).norm() < 5e-3, "{error}");
        assert!(error.fixed_rows::<3>(3).norm() < 1e-3, "{error}");
        // Every gross outlier is rejected; nearly every good observation kept.
        assert!(result.inliers[..30].iter().all(|&i| !i));
        assert!(result.inlier_count >= 265, "{}", result.inlier_count);
    }

    #[test]
    fn agrees_with_the_sparse_solver_on_the_same_factors() {
        for stereo in [VirtualStereo::disparity(BF), VirtualStereo::right_image(BF)] {
            agrees_with_the_sparse_solver(stereo);
        }
    }

    fn agrees_with_the_sparse_solver(stereo: VirtualStereo) {
        let truth = truth();
        let observations = scene(&truth, 120, 0);
        let start = truth.retract(&Vector6::new(0.02, 0.01, -0.02, 0.01, 0.0, -0.01));
        let dense = optimise_pose(
            &start,
            &CAMERA,
            stereo,
            &observations,
            &PoseOnlyOptions {
                rounds: 1,
                iterations_per_round: 50,
                step_tolerance: 1e-14,
            },
        );
        let mut values = Values::new();
        let pose = values.add(start);
        let mut problem_points = Vec::new();
        for o in &observations {
            let p = values.add(o.point_in_world);
            values.set_fixed(p.id, true);
            problem_points.push(p);
        }
        let mut problem = Problem::new(values);
        for (o, &p) in observations.iter().zip(&problem_points) {
            match o.measured {
                Measurement::Mono(m) => problem
                    .add(
                        ProjectionFactor::new(pose, p, CAMERA, m),
                        Information::isotropic(2, 1.0).unwrap(),
                        None::<Kernel>,
                    )
                    .unwrap(),
                Measurement::Stereo(m) => problem
                    .add(
                        StereoProjectionFactor::new(pose, p, CAMERA, BF, m)
                            .with_residual(stereo.residual),
                        Information::isotropic(3, 1.0).unwrap(),
                        None,
                    )
                    .unwrap(),
            };
        }
        Solver::new(Options {
            max_iterations: 50,
            ..Options::default()
        })
        .solve(&mut problem)
        .unwrap();
        let sparse = *problem.values().get(pose);
        let difference = sparse.local(&dense.world_from_camera);
        assert!(difference.norm() < 1e-9, "{stereo:?}: {difference}");
    }

    #[test]
    fn nothing_to_explain_leaves_the_pose_alone() {
        let start = truth();
        let result = optimise_pose(
            &start,
            &CAMERA,
            VirtualStereo::disparity(BF),
            &[],
            &PoseOnlyOptions::default(),
        );
        assert_eq!(result.world_from_camera, start);
        assert_eq!(result.inlier_count, 0);
    }
}
