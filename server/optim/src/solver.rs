//! Levenberg–Marquardt and Gauss–Newton on the sparse normal equations.
//!
//! Values change only when a step is accepted, so whatever happens (an error, a step limit, a
//! matrix that will not factor) the problem holds the last good values.

use crate::normal::{Damping, LinearError, NormalEquations};
use crate::problem::Problem;
use crate::values::Values;
use std::time::{Duration, Instant};
use thiserror::Error;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    LevenbergMarquardt,
    GaussNewton,
}

/// Solver settings; the defaults suit both tracking-sized and building-sized problems.
#[derive(Clone, Debug)]
pub struct Options {
    pub method: Method,
    pub max_iterations: usize,
    /// Initial λ of the Marquardt damping `H + λ·diag(H)`.
    pub initial_lambda: f64,
    /// Converged when an accepted step lowers the cost by less than this fraction.
    pub relative_cost_tolerance: f64,
    /// Converged when the largest gradient entry is below this.
    pub gradient_tolerance: f64,
    /// Converged when `|δ| < step_tolerance · (|δ| of the first step)`.
    pub step_tolerance: f64,
    /// Gives up after this many rejected steps in a row.
    pub max_rejections: usize,
    /// Stops (with the best values so far) once this much time has passed.
    pub time_limit: Option<Duration>,
    /// Removes free points that no factor shares with another point (bundle adjustment's map
    /// points) by the Schur complement before the sparse Cholesky.
    pub eliminate_points: bool,
    /// Threads for large problems (0: one per core). Results are identical from run to run
    /// for a given count, but differ in the last bits between counts.
    pub threads: usize,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            method: Method::LevenbergMarquardt,
            max_iterations: 100,
            initial_lambda: 1e-5,
            relative_cost_tolerance: 1e-10,
            gradient_tolerance: 1e-12,
            step_tolerance: 1e-12,
            max_rejections: 12,
            time_limit: None,
            eliminate_points: true,
            threads: 0,
        }
    }
}

/// One iteration of the solver.
#[derive(Clone, Debug)]
pub struct Iteration {
    pub iteration: usize,
    /// Cost after the iteration (the new cost if the step was accepted, else the old one).
    pub cost: f64,
    /// Cost of the tried step.
    pub tried_cost: f64,
    pub lambda: f64,
    pub step_norm: f64,
    pub accepted: bool,
    /// Time spent linearising (evaluating factors, assembling `H` and `g`) in this iteration:
    /// the tried step's values while steps are accepted (the first iteration also counts the
    /// start), the current values again after a rejection.
    pub linearize_time: Duration,
    /// Time to factor and solve.
    pub solve_time: Duration,
    /// Time since the solve began.
    pub elapsed: Duration,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// The cost stopped decreasing by more than the relative tolerance.
    CostConverged,
    GradientConverged,
    StepConverged,
    MaxIterations,
    TimeLimit,
    /// Too many rejected steps in a row: no step lowers the cost (at the solver's precision).
    NoProgress,
    /// Nothing to optimise: every variable is fixed or there are no factors.
    NothingToDo,
}

#[derive(Clone, Debug)]
pub struct Report {
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: Vec<Iteration>,
    pub termination: Termination,
    /// Time spent analysing sparsity (zero when the previous analysis was reused).
    pub analysis_time: Duration,
    /// Points removed by the Schur complement, and the size of the system left to factor.
    pub eliminated_points: usize,
    pub reduced_dim: usize,
    /// Threads that worked on the problem (1 for small ones).
    pub threads: usize,
    pub total_time: Duration,
}

#[derive(Debug, Error)]
pub enum SolveError {
    #[error("the cost is not finite at the initial values ({0})")]
    NonFiniteInitialCost(f64),
    #[error("sparsity analysis failed: {0}")]
    Analysis(String),
    #[error("the normal equations could not be solved at iteration {iteration}")]
    LinearSolve { iteration: usize, report: Report },
}

/// A reusable solver: it keeps the sparsity analysis between calls while the problem's
/// structure is unchanged (e.g. successive local bundle adjustments of one window).
#[derive(Default)]
pub struct Solver {
    pub options: Options,
    system: Option<NormalEquations>,
}

impl Solver {
    pub fn new(options: Options) -> Self {
        Self {
            options,
            system: None,
        }
    }

    /// Optimises the problem's values in place.
    pub fn solve(&mut self, problem: &mut Problem) -> Result<Report, SolveError> {
        let start = Instant::now();
        let opts = self.options.clone();
        let mut analysis_time = Duration::ZERO;
        let threads = match opts.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        };
        let layout = (problem.layout_version(), opts.eliminate_points, threads);
        if self.system.as_ref().map(|s| s.layout()) != Some(layout) {
            let t = Instant::now();
            self.system = Some(
                NormalEquations::analyse(problem, opts.eliminate_points, threads)
                    .map_err(|e| SolveError::Analysis(e.to_string()))?,
            );
            analysis_time = t.elapsed();
        }
        let system = self.system.as_mut().expect("analysed above");
        let entries = &problem.entries;
        let workers = system.workers();
        // Pose views go with their values: a candidate's serve its cost and, once accepted,
        // the next linearisation.
        let mut views = problem.pose_views(&problem.values);
        // The system holds the linearisation at the current values (`current`), whose gradient
        // is still to be checked (`unchecked`). A candidate is linearised whole while steps
        // are being accepted (its cost comes with it, and once accepted its system is the next
        // one); after a rejection only its cost is evaluated until a step is accepted again,
        // so a streak of rejections costs one linearisation too many, not one per step.
        let nothing_to_do = system.dim() == 0 || entries.is_empty();
        let t = Instant::now();
        let initial_cost = if nothing_to_do {
            system.cost(entries, &problem.values, &views)
        } else {
            system.linearize(entries, &problem.values, &views)
        };
        let mut linearize_time = t.elapsed();
        if !initial_cost.is_finite() {
            return Err(SolveError::NonFiniteInitialCost(initial_cost));
        }
        let mut report = Report {
            initial_cost,
            final_cost: initial_cost,
            iterations: Vec::new(),
            termination: Termination::NothingToDo,
            analysis_time,
            eliminated_points: system.eliminated(),
            reduced_dim: system.dim() - 3 * system.eliminated(),
            threads: workers,
            total_time: Duration::ZERO,
        };
        if nothing_to_do {
            report.total_time = start.elapsed();
            return Ok(report);
        }
        let mut cost = initial_cost;
        let mut lambda = opts.initial_lambda;
        let mut nu = 2.0;
        let mut rejections = 0;
        let mut first_step_norm = None;
        let mut delta = Vec::new();
        let mut candidate = problem.values.clone();
        let mut candidate_views = views.clone();
        let need_views = problem.reprojections > 0;
        let (mut current, mut unchecked, mut optimistic) = (true, true, true);
        report.termination = Termination::MaxIterations;
        for iteration in 1..=opts.max_iterations {
            if !current {
                let t = Instant::now();
                system.linearize(entries, &problem.values, &views);
                linearize_time += t.elapsed();
                (current, unchecked) = (true, true);
            }
            if unchecked {
                unchecked = false;
                if system.gradient_max() < opts.gradient_tolerance {
                    report.termination = Termination::GradientConverged;
                    break;
                }
            }
            let damping = match opts.method {
                Method::GaussNewton => Damping::None,
                Method::LevenbergMarquardt => Damping::Marquardt(lambda),
            };
            let t = Instant::now();
            let solved = system.solve(damping, &mut delta);
            let solve_time = t.elapsed();
            let mut it = Iteration {
                iteration,
                cost,
                tried_cost: f64::NAN,
                lambda: match damping {
                    Damping::None => 0.0,
                    Damping::Marquardt(lambda) => lambda,
                },
                step_norm: f64::NAN,
                accepted: false,
                linearize_time,
                solve_time,
                elapsed: Duration::ZERO,
            };
            linearize_time = Duration::ZERO;
            match solved {
                Err(LinearError::NotPositiveDefinite)
                    if opts.method == Method::LevenbergMarquardt =>
                {
                    // Too little damping for an indefinite or singular H: damp more and retry.
                    lambda *= nu;
                    nu *= 2.0;
                    rejections += 1;
                }
                Err(_) => {
                    it.elapsed = start.elapsed();
                    report.iterations.push(it);
                    report.final_cost = cost;
                    report.total_time = start.elapsed();
                    return Err(SolveError::LinearSolve { iteration, report });
                }
                Ok(()) => {
                    let step_norm = delta.iter().map(|v| v * v).sum::<f64>().sqrt();
                    it.step_norm = step_norm;
                    apply_step(&problem.values, system.offsets(), &delta, &mut candidate);
                    candidate_views.update(&candidate, need_views);
                    // The model's prediction first: linearising the candidate replaces it.
                    let predicted = system.predicted_decrease(damping, &delta);
                    let new_cost = if optimistic {
                        let t = Instant::now();
                        let c = system.linearize(entries, &candidate, &candidate_views);
                        it.linearize_time += t.elapsed();
                        current = false;
                        c
                    } else {
                        system.cost(entries, &candidate, &candidate_views)
                    };
                    it.tried_cost = new_cost;
                    let actual = cost - new_cost;
                    if new_cost.is_finite() && actual > 0.0 {
                        std::mem::swap(&mut problem.values, &mut candidate);
                        std::mem::swap(&mut views, &mut candidate_views);
                        it.accepted = true;
                        it.cost = new_cost;
                        cost = new_cost;
                        rejections = 0;
                        // The candidate's system, if it was linearised, is now the current one.
                        (current, unchecked) = (optimistic, optimistic);
                        optimistic = true;
                        let rho = actual / predicted.max(f64::MIN_POSITIVE);
                        lambda *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                        lambda = lambda.max(1e-12);
                        nu = 2.0;
                        let first = *first_step_norm.get_or_insert(step_norm);
                        let converged = if actual < opts.relative_cost_tolerance * (cost + actual) {
                            Some(Termination::CostConverged)
                        } else if step_norm < opts.step_tolerance * first {
                            Some(Termination::StepConverged)
                        } else {
                            None
                        };
                        if let Some(reason) = converged {
                            it.elapsed = start.elapsed();
                            report.iterations.push(it);
                            report.termination = reason;
                            break;
                        }
                    } else {
                        if opts.method == Method::GaussNewton {
                            it.elapsed = start.elapsed();
                            report.iterations.push(it);
                            report.termination = Termination::NoProgress;
                            break;
                        }
                        lambda *= nu;
                        nu *= 2.0;
                        rejections += 1;
                        optimistic = false;
                    }
                }
            }
            it.elapsed = start.elapsed();
            report.iterations.push(it);
            if rejections >= opts.max_rejections {
                report.termination = Termination::NoProgress;
                break;
            }
            if opts
                .time_limit
                .is_some_and(|limit| start.elapsed() >= limit)
            {
                report.termination = Termination::TimeLimit;
                break;
            }
        }
        report.final_cost = cost;
        report.total_time = start.elapsed();
        Ok(report)
    }
}

/// `candidate = values ⊕ δ` for the free variables.
fn apply_step(values: &Values, offsets: &[usize], delta: &[f64], candidate: &mut Values) {
    for id in values.ids() {
        let off = offsets[id.index()];
        let v = values.variable(id).expect("id from ids()");
        *candidate.variable_mut(id) = if off == usize::MAX {
            *v
        } else {
            v.retract(&delta[off..off + v.kind().dim()])
        };
    }
}
