//! `vsgraphs-eval`: evaluation tools.

use clap::{Parser, Subcommand, ValueEnum};
use std::path::PathBuf;
use vsgraphs_eval::posegraph;
use vsgraphs_sgraph::factors::pose::PoseError;
use vsgraphs_sgraph::{Method, Options};

#[derive(Parser)]
#[command(name = "vsgraphs-eval", version, about = "vsgraphs evaluation tools")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum ErrorArg {
    /// g2o's error [t; vec(q)]: the cost is g2o's chi2.
    Quaternion,
    /// Log(Z⁻¹ Xi⁻¹ Xj), as GTSAM and factrs minimise.
    LogMap,
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    /// Levenberg–Marquardt.
    Lm,
    /// Gauss–Newton.
    Gn,
}

#[derive(Subcommand)]
enum Command {
    /// Optimise a g2o pose graph (VERTEX_SE3:QUAT / EDGE_SE3:QUAT) and print cost per iteration.
    Posegraph {
        input: PathBuf,
        /// Write the optimised graph here (g2o format).
        #[arg(long, short)]
        output: Option<PathBuf>,
        #[arg(long, value_enum, default_value = "quaternion")]
        error: ErrorArg,
        #[arg(long, value_enum, default_value = "lm")]
        method: MethodArg,
        #[arg(long, default_value_t = 100)]
        max_iterations: usize,
        /// Print JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Posegraph {
            input,
            output,
            error,
            method,
            max_iterations,
            json,
        } => {
            let options = Options {
                method: match method {
                    MethodArg::Lm => Method::LevenbergMarquardt,
                    MethodArg::Gn => Method::GaussNewton,
                },
                max_iterations,
                ..Options::default()
            };
            let error = match error {
                ErrorArg::Quaternion => PoseError::Quaternion,
                ErrorArg::LogMap => PoseError::LogMap,
            };
            let run = posegraph::run(&input, output.as_deref(), error, options)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&run)?);
            } else {
                posegraph::print_table(&run);
            }
        }
    }
    Ok(())
}
