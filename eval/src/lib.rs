//! Evaluation tools behind the `vsgraphs-eval` command: trajectory error as evo computes it
//! (APE/ATE and RPE on TUM files), semantic accuracy of building models, and pose-graph
//! optimisation of g2o files.

pub mod metrics;
pub mod posegraph;
pub mod score;
pub mod semantics;
pub mod trajectory;
