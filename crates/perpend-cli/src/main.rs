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
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let res = match cli.cmd {
        Cmd::Demo(a) => demo::run(&a),
    };
    match res {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
