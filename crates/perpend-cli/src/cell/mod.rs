//! `perpend cell`: the cell calibration script, end to end over the bus.
//!
//! ```text
//! perpend cell run --bus BUS --node-id N --sensors nominal.csv --plan plan.csv \
//!                  --robot sim:127.0.0.1:PORT|manual --out DIR [--truth truth.csv]
//! perpend cell sim-head --out DIR      nominal.csv + truth.csv of the paper's head
//! ```
//!
//! `run`, in this order, stopping at the first problem:
//! 0. **keep**: the NMT state (from the heartbeat), the residual limit
//!    (0x2300 sub 4) and the board's calibration (`perpend node pull`, into
//!    `DIR/previous.json`) are noted; the node goes pre-operational;
//! 1. **before**: at `--verify` fresh random poses inside the plan's reach
//!    (not the planned ones), the robot presents the datum plane, the
//!    tracker measures it, and the board's own normal, from θ1/θ2 of the
//!    TPDO that maps 0x2002 sub 1 and 2 (one frame: one sample), is compared
//!    with the tracker's plane over `--verify-samples` SYNCs (samples whose
//!    status says "no plane" are left out and counted). The uncalibrated
//!    head's spots miss the plane by more than the board's residual limit,
//!    so for this pass only the limit is raised (`--before-residual-mm`,
//!    0x2300 sub 4) and put back afterwards;
//! 2. **capture** every planned pose (`perpend node capture`, into
//!    `DIR/poses.csv`; a boot-up message of the node in between stops the
//!    run: a reset board's poses are not trusted), **calibrate** (`perpend
//!    calibrate`, least squares, the paper's model, into `DIR/params.json`,
//!    with its expected normal error: [`perpend_calib::accuracy`]), **push**
//!    it (`perpend node push --preop`: write, verify, store, reset, verify,
//!    lock);
//! 3. **after**: the same fresh poses again, on the freshly reset board;
//! 4. the **floor**: what a perfectly calibrated board would show at those
//!    poses, computed host-side: the readings of the true head (`--truth`,
//!    for a simulation; without it the calibrated head stands in for it)
//!    with the reading noise the captures measured (pooled `s_mm`), fitted
//!    like the board fits them and compared with the same tracker planes;
//! 5. the **decision** (issue 45, [`perpend_formats::conformity`]): at every
//!    fresh pose the error of the board's averaged normal against the
//!    tolerance (`--tolerance-deg`, else the `--config` file's, else 0.05°)
//!    with its expanded uncertainty (from the tracker's plane uncertainty
//!    and the pose's own reading scatter; k from its degrees of freedom): PASS, FAIL or
//!    INCONCLUSIVE with what would decide it. The new calibration is
//!    applied unless the decision is FAIL or the after error is worse than
//!    the before error; then `previous.json` is pushed back (the same
//!    verified push) and the run fails, unless `--keep-worse`. The record's
//!    outcome, the certificate's verdict and cell.json say the same.
//!
//! Fail safe: whatever stops the run (an error, end of input, Ctrl-C), what
//! it changed is put back before it reports, in this order: the link (one
//! reconnection if the bus went away), the calibration (`previous.json`
//! pushed back once the push had begun, so the board holds the previous
//! calibration or the new verified one, never a mix), the residual limit
//! (written and read back), the lock (0x2010), the NMT state found at the
//! start. The report names the first cause first, then any restore problem.
//! `DIR/cell.json` holds the figures and `outcome` (`applied`, `reverted`,
//! `failed, restored`, `failed, board state unknown`), `reason`,
//! `first_cause` and `restored`; `DIR/record.json` the same outcome, and
//! `DIR/cert.html` is written only for an applied calibration (else
//! `DIR/report.html`, marked as no certificate).
//!
//! Robots: `sim:HOST:PORT` moves the virtual board's plane through its
//! world channel (`perpend board --world`) and simulates the tracker
//! (Chen §5: 20 points, ξ = 0.02 mm); `manual` prints each pose and reads
//! the tracker's plane `A,B,C,D` from standard input after the operator
//! moved the robot (a line it cannot read is asked again, with why; the
//! end of input stops the run safely). The bus part is the same for both,
//! so the script runs unchanged against a real board with `--bus
//! socketcan:can0 --robot manual`.
//!
//! Limits: the board must be alone in running SYNC (the script sends it);
//! a heartbeat-less board is left pre-operational (its state is unknown);
//! when the bus cannot be reached again, the report says what to push.

pub mod args;
pub mod capture;
pub mod check;
pub mod figures;
pub mod fit;
pub mod frames;
pub mod judge;
pub mod record;
pub mod robot;
pub mod run;
pub mod session;
pub mod verify;

use std::path::PathBuf;

use anyhow::{Context as _, Result};

pub use args::RunArgs;
pub use figures::Figures;
pub use judge::{Outcome, Report};
pub use run::run_cell;

/// Arguments of `perpend cell`. The link's options are global: they may
/// stand before or after the subcommand (`perpend cell --bus B --node-id 5
/// run …` and `perpend cell run --bus B --node-id 5 …` are the same).
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The bus and the node (for `run`).
    #[command(flatten)]
    pub link: crate::node::LinkArgs,
    /// What to do.
    #[command(subcommand)]
    pub cmd: Cmd,
}

/// The subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum Cmd {
    /// Before, capture, calibrate, push, after: the whole cell calibration.
    Run(RunArgs),
    /// Write the paper's simulated head: nominal.csv and truth.csv.
    SimHead(SimHeadArgs),
    /// Interim check: the stored calibration at a few fresh poses against
    /// the last record and the tolerance.
    Check(check::CheckArgs),
}

/// Options of `cell sim-head`.
#[derive(clap::Args, Debug)]
pub struct SimHeadArgs {
    /// Directory to write nominal.csv and truth.csv into.
    #[arg(long)]
    pub out: PathBuf,
    /// `perpend cell`'s global link options, which sim-head does not read:
    /// kept out of its help and refused after its name.
    #[command(flatten)]
    pub no_link: crate::node::NoLink,
}

/// Writes nominal.csv and truth.csv of the paper's head (Chen Table 2).
fn sim_head(a: &SimHeadArgs) -> Result<()> {
    let h = perpend_calib::sim::paper_head()?;
    std::fs::create_dir_all(&a.out)?;
    for (name, s) in [("nominal.csv", &h.nominal), ("truth.csv", &h.truth)] {
        let path = a.out.join(name);
        let table = perpend_formats::exchange::SensorTable::from_sensors(s, h.sigma_mm);
        let mut f = std::fs::File::create(&path)
            .with_context(|| format!("{}: cannot create", path.display()))?;
        perpend_formats::exchange::write_sensors(&mut f, &table, &[])?;
        println!("cell: wrote {}", path.display());
    }
    Ok(())
}

/// Runs `perpend cell`.
///
/// # Errors
/// As [`run_cell`] and [`sim_head`]; a run whose calibration was not kept.
pub fn run(a: &Args) -> Result<()> {
    match &a.cmd {
        Cmd::SimHead(x) => sim_head(x),
        Cmd::Run(x) => run::run_and_report(&RunArgs {
            link: a.link.clone(),
            seed: Some(x.seed.unwrap_or_else(args::clock_seed)),
            ..x.clone()
        }),
        Cmd::Check(x) => {
            robot::install_ctrlc();
            check::run_and_report(
                &check::CheckArgs {
                    link: a.link.clone(),
                    ..x.clone()
                },
                &robot::CANCEL,
            )
        }
    }
}
