//! `vsgraphs-eval posegraph`: optimise a g2o pose graph and report cost per iteration.

use serde::Serialize;
use std::path::Path;
use std::time::{Duration, Instant};
use vsgraphs_optim::factors::pose::PoseError;
use vsgraphs_optim::g2o::{PoseGraph, Start};
use vsgraphs_optim::{Options, Solver};

#[derive(Debug, Serialize)]
pub struct IterationRow {
    pub iteration: usize,
    pub cost: f64,
    pub tried_cost: f64,
    pub lambda: f64,
    pub step_norm: f64,
    pub accepted: bool,
    pub linearize_ms: f64,
    pub solve_ms: f64,
    pub elapsed_ms: f64,
}

#[derive(Debug, Serialize)]
pub struct PoseGraphRun {
    pub vertices: usize,
    pub edges: usize,
    /// "quaternion" (g2o's chi2) or "log-map".
    pub error: &'static str,
    /// Where the poses started: "file", "chain" or "chordal".
    pub start: &'static str,
    /// Time to compute the start (0 for "file").
    pub start_ms: f64,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub termination: String,
    pub iterations: Vec<IterationRow>,
    pub read_ms: f64,
    pub analysis_ms: f64,
    /// The optimise call alone (analysis included), as the peers in the data README were timed.
    pub optimize_ms: f64,
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Reads `input`, starts its poses at `start`, optimises it and (when `output` is given)
/// writes the optimised graph.
pub fn run(
    input: &Path,
    output: Option<&Path>,
    error: PoseError,
    start: Start,
    options: Options,
) -> anyhow::Result<PoseGraphRun> {
    let t = Instant::now();
    let mut graph = PoseGraph::read(input)?;
    let read_ms = ms(t.elapsed());
    let t = Instant::now();
    graph.restart(start)?;
    let start_ms = ms(t.elapsed());
    let (mut problem, keys) = graph.to_problem(error)?;
    let mut solver = Solver::new(options);
    let report = solver.solve(&mut problem)?;
    if let Some(path) = output {
        graph.update(problem.values(), &keys);
        let file = std::fs::File::create(path)
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
        graph.write(std::io::BufWriter::new(file))?;
    }
    Ok(PoseGraphRun {
        vertices: graph.vertices.len(),
        edges: graph.edges.len(),
        error: match error {
            PoseError::Quaternion => "quaternion",
            PoseError::LogMap => "log-map",
        },
        start: match start {
            Start::File => "file",
            Start::Chain => "chain",
            Start::Chordal => "chordal",
        },
        start_ms,
        initial_cost: report.initial_cost,
        final_cost: report.final_cost,
        termination: format!("{:?}", report.termination),
        iterations: report
            .iterations
            .iter()
            .map(|it| IterationRow {
                iteration: it.iteration,
                cost: it.cost,
                tried_cost: it.tried_cost,
                lambda: it.lambda,
                step_norm: it.step_norm,
                accepted: it.accepted,
                linearize_ms: ms(it.linearize_time),
                solve_ms: ms(it.solve_time),
                elapsed_ms: ms(it.elapsed),
            })
            .collect(),
        read_ms,
        analysis_ms: ms(report.analysis_time),
        optimize_ms: ms(report.total_time),
    })
}

/// The readable table.
pub fn print_table(run: &PoseGraphRun) {
    println!(
        "{} vertices, {} edges, {} error; read in {:.1} ms; start {} ({:.1} ms)",
        run.vertices, run.edges, run.error, run.read_ms, run.start, run.start_ms
    );
    println!(
        "{:>4} {:>16} {:>16} {:>10} {:>10} {:>3} {:>9} {:>9} {:>10}",
        "iter", "cost", "tried", "lambda", "|step|", "ok", "lin ms", "solve ms", "total ms"
    );
    println!("{:>4} {:>16.6}", 0, run.initial_cost);
    for it in &run.iterations {
        println!(
            "{:>4} {:>16.6} {:>16.6} {:>10.2e} {:>10.3e} {:>3} {:>9.2} {:>9.2} {:>10.1}",
            it.iteration,
            it.cost,
            it.tried_cost,
            it.lambda,
            it.step_norm,
            if it.accepted { "y" } else { "n" },
            it.linearize_ms,
            it.solve_ms,
            it.elapsed_ms
        );
    }
    println!(
        "final cost {:.6} ({}) in {:.1} ms (sparsity analysis {:.1} ms)",
        run.final_cost, run.termination, run.optimize_ms, run.analysis_ms
    );
}
