//! `perpend`: simulate sensor heads, calibrate them from measured data,
//! diagnose what the model misses, benchmark, and run a virtual board.

use clap::{Parser, Subcommand};
use perpend_calib::{calibrate, measure, sim};
use perpend_cli::{board, cell, demo, eds, node, record};
use perpend_diagnosis::{bench, diagnose};

/// The conventions every command's output follows.
const CONVENTIONS: &str = "\
Conventions: TCS origin at the tool centre point, +z along the spindle feed.
The normal is a unit vector pointing towards the head. θ1 = atan2(n_y, -n_z) is
the rotation about +x, θ2 = atan2(-n_x, -n_z) about +y, θ the total angle
between spindle and normal (Tian eq. 1-5). Pitch (about x) and yaw (about y)
bring the spindle onto the normal: Rot(y, yaw)·Rot(x, pitch)·e_z = -n (Chen eq. 22).
Files: sensors.csv and poses.csv as in docs/data-format.md (`perpend calibrate --help`).";

/// The files the analysis commands read.
const FILES: &str = "\
Files (CSV, header names in any order, `#` comments, empty or NaN = missing; docs/data-format.md):
  sensors.csv  sensor, x_mm, y_mm, z_mm [mm, zero point E_i], m, n, q [beam direction],
               optional sigma_mm [mm, datasheet 1σ: a prior]
  poses.csv    pose, a, b, c, d_mm [plane a·x+b·y+c·z+d=0 in the TCS], d1_mm..dN_mm [readings, mm],
               optional t_s [s], temp_c [°C], s1_mm..sN_mm [mm, sample std], n_samples,
               plane_rms_mm [mm], plane_points";

#[derive(Parser)]
#[command(name = "perpend", version = perpend_calib::record::VERSION, about, long_about = None, after_help = CONVENTIONS)]
struct Cli {
    /// No progress bars or progress lines (drawn on stderr, and only on a terminal).
    #[arg(long, global = true)]
    quiet: bool,
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
    #[command(after_help = FILES)]
    Calibrate(calibrate::Args),
    /// Find what the model misses in a calibration run: name the effect, extend the model, measure the gain.
    #[command(after_help = FILES)]
    Diagnose(diagnose::Args),
    /// Measure every row of a readings file: normal, θ1/θ2/θ, pitch/yaw, residual (plane, sphere or cylinder).
    #[command(after_help = FILES)]
    Measure(measure::Args),
    /// Plan the fewest datum-plane poses that calibrate a head (D-optimal), with the expected accuracy.
    Plan(perpend_calib::plan::Args),
    /// Studies: `study paper` puts the paper's simulation beside its experiment.
    Study(diagnose::study::Args),
    /// Benchmarks: the paper's simulation (accuracy), calibration speed, identifiability study.
    Bench(bench::Args),
    /// Run a virtual board: the firmware's application on a simulated head,
    /// CANopen served as slcan over TCP.
    Board(board::Args),
    /// A board on a CAN bus: info, status, nmt, monitor, push/pull calibration, capture poses.
    Node(node::Args),
    /// Calibrate a cell end to end over the bus: before, capture, calibrate, push, after.
    Cell(cell::Args),
    /// Print the board's EDS (CiA 306) built into this binary (= perpend.eds).
    Eds(eds::Args),
    /// Calibration records: show one, write its certificate, follow a head's history.
    Record(record::Args),
    /// The cell's frame errors (tracker tilt, TCP) from a reversal run's files, offline.
    #[command(after_help = FILES)]
    Frames(perpend_cli::cell::frames::Args),
}

fn main() -> std::process::ExitCode {
    perpend_cli::pipe::install();
    let cli = Cli::parse();
    perpend_formats::progress::set_quiet(cli.quiet);
    let res = match cli.cmd {
        Cmd::Demo(a) => demo::run(&a),
        Cmd::Simulate(a) => sim::run(&a),
        Cmd::Calibrate(a) => calibrate::run(&a),
        Cmd::Diagnose(a) => diagnose::run(&a),
        Cmd::Measure(a) => measure::run(&a),
        Cmd::Plan(a) => perpend_calib::plan::run(&a),
        Cmd::Study(a) => diagnose::study::run(&a),
        Cmd::Bench(a) => bench::run(&a),
        Cmd::Board(a) => board::run(&a),
        Cmd::Node(a) => node::run(&a),
        Cmd::Cell(a) => cell::run(&a),
        Cmd::Eds(a) => eds::run(&a),
        Cmd::Record(a) => record::run(&a),
        Cmd::Frames(a) => perpend_cli::cell::frames::run(&a),
    };
    match res {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) if perpend_cli::pipe::is_broken_pipe(&e) => {
            std::process::ExitCode::from(perpend_cli::pipe::EXIT_BROKEN_PIPE)
        }
        Err(e) => {
            if std::env::args().any(|a| a == "--json") {
                println!("{}", error_json(&e));
            } else {
                eprintln!("error: {e:#}");
            }
            std::process::ExitCode::FAILURE
        }
    }
}

/// An error as the JSON object `--json` promises: `{"schema", "error", "file", "line"}`
/// (file and line when a data file is at fault, else null).
fn error_json(e: &anyhow::Error) -> String {
    let at = e
        .chain()
        .find_map(|c| c.downcast_ref::<perpend_formats::exchange::ExchangeError>());
    let v = serde_json::json!({
        "error": format!("{e:#}"),
        "file": at.map(|x| x.file.clone()),
        "line": at.and_then(|x| x.line),
    });
    perpend_cli::schema::tagged(perpend_cli::schema::ERROR, &v)
}
