//! Evaluation tools behind the `vsgraphs-eval` command: trajectory error as evo computes it
//! (APE/ATE and RPE on TUM files), semantic accuracy of building models, pose-graph
//! optimisation of g2o files, and whole simulated scenarios run through the frame pipeline and
//! scored ([`scenario`]).
//!
//! The scores need no OpenCV; `scenario` brings the pipeline (and so OpenCV) in. Nothing in the
//! server depends on this crate.

pub mod in_step;
pub mod markers;
pub mod merge_cost;
pub mod metrics;
pub mod places;
pub mod posegraph;
pub mod scenario;
pub mod score;
pub mod semantics;
