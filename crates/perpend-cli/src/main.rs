//! `perpend`: simulate sensor heads, calibrate them from measured data,
//! diagnose what the model misses, benchmark, and run a virtual board.

use clap::{Parser, Subcommand};
use perpend_cli::{board, demo};
use perpend_lab::{bench, calibrate, diagnose, sim};

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
    /// Find what the model misses in a calibration run: name the effect, extend the model, measure the gain.
    Diagnose(diagnose::Args),
    /// Studies: `study paper` puts the paper's simulation beside its experiment.
    Study(diagnose::study::Args),
    /// Benchmarks: the paper's simulation (accuracy), calibration speed, identifiability study.
    Bench(bench::Args),
    /// Run a virtual board: the firmware's application on a simulated head,
    /// CANopen served as slcan over TCP.
    Board(board::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let res = match cli.cmd {
        Cmd::Demo(a) => demo::run(&a),
        Cmd::Simulate(a) => sim::run(&a),
        Cmd::Calibrate(a) => calibrate::run(&a),
        Cmd::Diagnose(a) => diagnose::run(&a),
        Cmd::Study(a) => diagnose::study::run(&a),
        Cmd::Bench(a) => bench::run(&a),
        Cmd::Board(a) => board::run(&a),
    };
    match res {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
