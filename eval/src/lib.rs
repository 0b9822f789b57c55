//! Evaluation tools behind the `vsgraphs-eval` command: pose-graph optimisation of g2o files
//! (and, with the simulator, trajectory and semantic scoring).

pub mod posegraph;
