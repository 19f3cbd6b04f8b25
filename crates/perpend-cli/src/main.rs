//! `perpend`: simulate sensor heads, calibrate them from measured data,
//! diagnose what the model misses, benchmark, and run a virtual board.

use clap::{Parser, Subcommand};
use perpend_cli::*;

#[derive(Parser)]
#[command(name = "perpend", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Measure a simulated plane with an ideal head: normal, θ1/θ2, attitude.
    Demo(demo::Args),
    /// Simulate a calibration run (Chen §5): write sensors.csv and poses.csv.
    Simulate(sim::Args),
    /// Calibrate a head from sensors.csv + poses.csv (least squares or the paper's EKF).
    Calibrate(calibrate::Args),
    /// Benchmarks: the paper's simulation (accuracy), calibration speed, identifiability study.
    Bench(bench::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let res = match cli.cmd {
        Cmd::Demo(a) => demo::run(&a),
        Cmd::Simulate(a) => sim::run(&a),
        Cmd::Calibrate(a) => calibrate::run(&a),
        Cmd::Bench(a) => bench::run(&a),
    };
    match res {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
