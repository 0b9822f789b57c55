//! The S-Graph optimiser: variables on manifolds (SE(3) poses, R³ points, planes), factors with
//! analytic Jacobians, robust kernels, and Levenberg–Marquardt on sparse normal equations solved
//! by faer's Cholesky. Pure maths: it must not depend on OpenCV, zenoh or tokio.
//!
//! Conventions: perturbations act on the right (`X ⊕ δ = X · Exp(δ)`); an SE(3) tangent is
//! `[ρ; φ]` (translation first); the cost is `Σ ρ(rᵀΩr)`, g2o's "chi2" without kernels.

mod bundle;
pub mod camera;
pub mod chordal;
pub mod factor;
pub mod factors;
// SIMD lanes (AVX2 + FMA intrinsics behind runtime detection).
#[allow(unsafe_code)]
mod four;
pub mod g2o;
pub mod lie;
mod normal;
mod parallel;
pub mod plane;
pub mod pose_only;
pub mod problem;
pub mod solver;
pub mod testing;
pub mod values;

pub use camera::{DepthResidual, Pinhole, VirtualStereo};
pub use factor::{Factor, Information, InformationError, Kernel};
pub use lie::Se3;
pub use plane::Plane;
pub use problem::{FactorId, Problem, ProblemError};
pub use solver::{Iteration, Method, Options, Report, SolveError, Solver, Termination};
pub use values::{Key, Kind, Values, VarId, Variable, VariableType};
