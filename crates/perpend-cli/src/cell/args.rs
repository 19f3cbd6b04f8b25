//! The options of `perpend cell run` ([`RunArgs`]) and the seed a run
//! takes from the clock when none is given.

use std::path::PathBuf;

/// Options of `cell run`.
#[derive(clap::Args, Debug, Clone)]
pub struct RunArgs {
    /// The bus and the node: `perpend cell`'s (global) link options, filled
    /// in by [`run`].
    #[arg(skip)]
    pub link: crate::node::LinkArgs,
    /// The nominal head (sensors.csv) the calibration starts from.
    #[arg(long)]
    pub sensors: PathBuf,
    /// The poses to capture (`perpend plan --out`).
    #[arg(long)]
    pub plan: PathBuf,
    /// Directory for previous.json (the board's calibration as found),
    /// poses.csv, params.json and cell.json (must not hold a poses.csv yet).
    #[arg(long)]
    pub out: PathBuf,
    /// The true head (sensors.csv) for the floor; default: the calibrated one.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Samples averaged per captured pose.
    #[arg(long, default_value_t = 50)]
    pub samples: u32,
    /// Fresh verification poses.
    #[arg(long, default_value_t = 8)]
    pub verify: usize,
    /// The robot, the sampling and the tolerance.
    #[command(flatten)]
    pub m: super::verify::MeasureArgs,
    /// Residual limit (0x2300 sub 4) during the before pass [mm]: the
    /// uncalibrated head's spots miss the plane by more than the board's
    /// default; put back afterwards.
    #[arg(long, default_value_t = 1.0)]
    pub before_residual_mm: f64,
    /// Seed of the verification poses and the simulated tracker (default:
    /// from the clock, so that every run verifies at other poses; the
    /// record's verification note names it).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Keep the new calibration even when the after pass finds it worse
    /// than the previous one or the decision is FAIL (default: push
    /// `previous.json` back and fail).
    #[arg(long)]
    pub keep_worse: bool,
    /// Estimate the cell's frame errors with the head (issue 36,
    /// docs/frames.md): the plan must turn the head about the spindle axis
    /// (`perpend plan --reversal 4`); reports each with 1σ and warns when
    /// one is above the calibration's expected error. `--robot sim:` only.
    #[arg(long)]
    pub reversal: bool,
}

impl RunArgs {
    /// The seed in force (`run` fills a missing one from the clock).
    pub fn seed(&self) -> u64 {
        self.seed.unwrap_or(1)
    }
}

/// A seed from the clock (nanoseconds since the epoch, folded).
pub(super) fn clock_seed() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(1, |d| d.as_nanos() as u64 ^ (d.as_secs() << 20))
}
