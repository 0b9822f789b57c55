//! One local bundle adjustment of the benchmark's size, for profiles. With no argument it runs
//! once on one thread (for `valgrind --tool=callgrind`, whose instruction counts are
//! reproducible where wall time is not); `local_ba THREADS RUNS` prints the fastest phases.
use std::time::Duration;
use vsgraphs_optim::testing::{bundle_scene, BundleConfig};
use vsgraphs_optim::{Options, Solver};

fn main() {
    let mut args = std::env::args().skip(1).map(|a| a.parse::<usize>());
    let threads = args.next().and_then(Result::ok).unwrap_or(1);
    let runs = args.next().and_then(Result::ok).unwrap_or(1);
    let options = Options {
        max_iterations: 5,
        threads,
        ..Options::default()
    };
    let mut best = [Duration::MAX; 4];
    let mut final_cost = 0.0;
    for _ in 0..runs {
        let mut scene = bundle_scene(&BundleConfig::default(), 1);
        let report = Solver::new(options.clone())
            .solve(&mut scene.problem)
            .expect("the scene solves");
        let phases = [
            report.analysis_time,
            report.iterations.iter().map(|i| i.linearize_time).sum(),
            report.iterations.iter().map(|i| i.solve_time).sum(),
            report.total_time,
        ];
        final_cost = report.final_cost;
        for (b, p) in best.iter_mut().zip(phases) {
            *b = (*b).min(p);
        }
    }
    println!(
        "{threads} thread(s), fastest of {runs}: analysis {:?}, linearise {:?}, solve {:?}, total {:?}; final cost {final_cost:e}",
        best[0], best[1], best[2], best[3]
    );
}
