//! Levenberg–Marquardt and Gauss–Newton on the sparse normal equations.
//!
//! Values change only when a step is accepted, so whatever happens (an error, a step limit, a
//! matrix that will not factor) the problem holds the last good values.

use crate::bundle::PoseViews;
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
        let analysis_time = self.analyse(problem)?;
        let system = self.system.as_mut().expect("analysed above");
        let nothing_to_do = system.dim() == 0 || problem.entries.is_empty();
        let views = problem.pose_views(&problem.values);
        let t = Instant::now();
        let initial_cost = if nothing_to_do {
            system.cost(&problem.entries, &problem.values, &views)
        } else {
            system.linearize(&problem.entries, &problem.values, &views)
        };
        let linearize_time = t.elapsed();
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
            threads: system.workers(),
            total_time: Duration::ZERO,
        };
        if nothing_to_do {
            report.total_time = start.elapsed();
            return Ok(report);
        }
        let mut run = Run {
            opts: &opts,
            start,
            cost: initial_cost,
            damping: Nielsen::new(opts.initial_lambda),
            rejections: 0,
            first_step_norm: None,
            delta: Vec::new(),
            candidate: problem.values.clone(),
            candidate_views: views.clone(),
            views,
            held: Held::Current { checked: false },
            evaluation: Evaluation::Linearise,
            linearize_time,
        };
        report.termination = Termination::MaxIterations;
        for iteration in 1..=opts.max_iterations {
            let (it, outcome) = run.iterate(iteration, problem, system);
            report.iterations.extend(it);
            match outcome {
                Outcome::Continue => {}
                Outcome::Stop(termination) => {
                    report.termination = termination;
                    break;
                }
                Outcome::Failed => {
                    report.final_cost = run.cost;
                    report.total_time = start.elapsed();
                    return Err(SolveError::LinearSolve { iteration, report });
                }
            }
        }
        report.final_cost = run.cost;
        report.total_time = start.elapsed();
        Ok(report)
    }

    /// Analyses the problem's sparsity unless the last analysis still holds (same layout
    /// version, elimination and threads); returns the time it took.
    fn analyse(&mut self, problem: &Problem) -> Result<Duration, SolveError> {
        let threads = match self.options.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        };
        let eliminate = self.options.eliminate_points;
        let layout = (problem.layout_version(), eliminate, threads);
        if self.system.as_ref().map(|s| s.layout()) == Some(layout) {
            return Ok(Duration::ZERO);
        }
        let t = Instant::now();
        self.system = Some(
            NormalEquations::analyse(problem, eliminate, threads)
                .map_err(|e| SolveError::Analysis(e.to_string()))?,
        );
        Ok(t.elapsed())
    }
}

/// What the normal equations hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Held {
    /// The linearisation at the current values; `checked` once its gradient was compared with
    /// the tolerance.
    Current { checked: bool },
    /// The linearisation of other values (a rejected candidate, or the values before a step
    /// accepted by its cost alone): the current values need theirs.
    Stale,
}

/// How a tried step is evaluated. While steps are being accepted, a candidate is linearised
/// whole: its cost comes with it, and once accepted its system is the next one. After a
/// rejection only costs are evaluated until a step is accepted again, so a streak of
/// rejections wastes one linearisation, not one per step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Evaluation {
    Linearise,
    CostOnly,
}

/// Marquardt's λ with Nielsen's update: shrunk by the gain ratio after an accepted step, grown
/// by a doubling factor after each rejection in a row.
struct Nielsen {
    lambda: f64,
    nu: f64,
}

impl Nielsen {
    fn new(lambda: f64) -> Self {
        Self { lambda, nu: 2.0 }
    }

    fn accepted(&mut self, gain_ratio: f64) {
        self.lambda *= (1.0 - (2.0 * gain_ratio - 1.0).powi(3)).max(1.0 / 3.0);
        self.lambda = self.lambda.max(1e-12);
        self.nu = 2.0;
    }

    fn rejected(&mut self) {
        self.lambda *= self.nu;
        self.nu *= 2.0;
    }
}

/// What an iteration leaves the loop to do.
enum Outcome {
    Continue,
    Stop(Termination),
    /// The normal equations could not be solved, and damping more cannot help.
    Failed,
}

/// The state of the iterations of one solve.
struct Run<'a> {
    opts: &'a Options,
    start: Instant,
    cost: f64,
    damping: Nielsen,
    rejections: usize,
    first_step_norm: Option<f64>,
    delta: Vec<f64>,
    /// Pose views go with their values: a candidate's serve its cost and, once accepted, the
    /// next linearisation.
    candidate: Values,
    candidate_views: PoseViews,
    views: PoseViews,
    held: Held,
    evaluation: Evaluation,
    /// Linearisation time not yet reported in an iteration.
    linearize_time: Duration,
}

impl Run<'_> {
    /// One iteration: the system brought to the current values, the gradient checked, a damped
    /// step solved, tried and accepted or rejected. Returns the iteration's record (none when
    /// the gradient had converged) and what to do next.
    fn iterate(
        &mut self,
        iteration: usize,
        problem: &mut Problem,
        system: &mut NormalEquations,
    ) -> (Option<Iteration>, Outcome) {
        if self.held == Held::Stale {
            let t = Instant::now();
            system.linearize(&problem.entries, &problem.values, &self.views);
            self.linearize_time += t.elapsed();
            self.held = Held::Current { checked: false };
        }
        if self.held == (Held::Current { checked: false }) {
            self.held = Held::Current { checked: true };
            if system.gradient_max() < self.opts.gradient_tolerance {
                return (None, Outcome::Stop(Termination::GradientConverged));
            }
        }
        let damping = match self.opts.method {
            Method::GaussNewton => Damping::None,
            Method::LevenbergMarquardt => Damping::Marquardt(self.damping.lambda),
        };
        let t = Instant::now();
        let solved = system.solve(damping, &mut self.delta);
        let mut it = Iteration {
            iteration,
            cost: self.cost,
            tried_cost: f64::NAN,
            lambda: match damping {
                Damping::None => 0.0,
                Damping::Marquardt(lambda) => lambda,
            },
            step_norm: f64::NAN,
            accepted: false,
            linearize_time: std::mem::take(&mut self.linearize_time),
            solve_time: t.elapsed(),
            elapsed: Duration::ZERO,
        };
        let outcome = match solved {
            Err(LinearError::NotPositiveDefinite)
                if self.opts.method == Method::LevenbergMarquardt =>
            {
                // Too little damping for an indefinite or singular H: damp more and retry.
                self.damping.rejected();
                self.rejections += 1;
                self.limits()
            }
            Err(_) => Outcome::Failed,
            Ok(()) => match self.try_step(problem, system, damping, &mut it) {
                Outcome::Continue => self.limits(),
                stop => stop,
            },
        };
        it.elapsed = self.start.elapsed();
        (Some(it), outcome)
    }

    /// Tries the solved step: its candidate values, their cost (and linearisation while steps
    /// are being accepted), then acceptance by the cost, with the convergence tests.
    fn try_step(
        &mut self,
        problem: &mut Problem,
        system: &mut NormalEquations,
        damping: Damping,
        it: &mut Iteration,
    ) -> Outcome {
        let step_norm = self.delta.iter().map(|v| v * v).sum::<f64>().sqrt();
        it.step_norm = step_norm;
        apply_step(
            &problem.values,
            system.offsets(),
            &self.delta,
            &mut self.candidate,
        );
        self.candidate_views
            .update(&self.candidate, problem.reprojections > 0);
        // The model's prediction first: linearising the candidate replaces it.
        let predicted = system.predicted_decrease(damping, &self.delta);
        let linearised = self.evaluation == Evaluation::Linearise;
        let new_cost = if linearised {
            let t = Instant::now();
            let cost = system.linearize(&problem.entries, &self.candidate, &self.candidate_views);
            it.linearize_time += t.elapsed();
            self.held = Held::Stale;
            cost
        } else {
            system.cost(&problem.entries, &self.candidate, &self.candidate_views)
        };
        it.tried_cost = new_cost;
        let actual = self.cost - new_cost;
        if !(new_cost.is_finite() && actual > 0.0) {
            if self.opts.method == Method::GaussNewton {
                return Outcome::Stop(Termination::NoProgress);
            }
            self.damping.rejected();
            self.rejections += 1;
            self.evaluation = Evaluation::CostOnly;
            return Outcome::Continue;
        }
        std::mem::swap(&mut problem.values, &mut self.candidate);
        std::mem::swap(&mut self.views, &mut self.candidate_views);
        it.accepted = true;
        it.cost = new_cost;
        self.cost = new_cost;
        self.rejections = 0;
        // The candidate's system, if it was linearised, is now the current one; else the
        // system still holds the values before the step.
        self.held = if linearised {
            Held::Current { checked: false }
        } else {
            Held::Stale
        };
        self.evaluation = Evaluation::Linearise;
        self.damping
            .accepted(actual / predicted.max(f64::MIN_POSITIVE));
        let first = *self.first_step_norm.get_or_insert(step_norm);
        if actual < self.opts.relative_cost_tolerance * (self.cost + actual) {
            Outcome::Stop(Termination::CostConverged)
        } else if step_norm < self.opts.step_tolerance * first {
            Outcome::Stop(Termination::StepConverged)
        } else {
            Outcome::Continue
        }
    }

    /// Stops on too many rejections in a row or on the time limit.
    fn limits(&self) -> Outcome {
        if self.rejections >= self.opts.max_rejections {
            Outcome::Stop(Termination::NoProgress)
        } else if self
            .opts
            .time_limit
            .is_some_and(|limit| self.start.elapsed() >= limit)
        {
            Outcome::Stop(Termination::TimeLimit)
        } else {
            Outcome::Continue
        }
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
