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
//!    with its expected normal error: [`perpend_lab::accuracy`]), **push**
//!    it (`perpend node push --preop`: write, verify, store, reset, verify,
//!    lock);
//! 3. **after**: the same fresh poses again, on the freshly reset board;
//! 4. the **floor**: what a perfectly calibrated board would show at those
//!    poses, computed host-side: the readings of the true head (`--truth`,
//!    for a simulation; without it the calibrated head stands in for it)
//!    with the reading noise the captures measured (pooled `s_mm`), fitted
//!    like the board fits them and compared with the same tracker planes;
//! 5. the **decision** (issue 45, [`perpend_lab::conformity`]): at every
//!    fresh pose the error of the board's averaged normal against the
//!    tolerance (`--tolerance-deg`, else the `--config` file's, else 0.05°)
//!    with its expanded uncertainty (k = 2, from the tracker's plane
//!    uncertainty and the pose's own reading scatter): PASS, FAIL or
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

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_core::head::Head4;
use perpend_lab::conformity::{Decision, Verdict};
use perpend_lab::plan::PlannedPose;
use perpend_lab::record::BoardStamp;

use crate::canopen::{Nmt, NodeState};
use crate::cell_robot::{abcd, check_cancel, ManualCheck, Robot};
use crate::cell_verify::{
    decision_words, drain_saw_bootup, floor, fresh_poses, head4, read_plan, reset_error, verify,
    write_csv, Reference, Sampling, Verified,
};
use crate::node::{capture, params, Node};

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
    Check(crate::cell_check::CheckArgs),
}

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
    pub m: crate::cell_verify::MeasureArgs,
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
fn clock_seed() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(1, |d| d.as_nanos() as u64 ^ (d.as_secs() << 20))
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

/// What `cell run` measured (`cell.json`).
#[derive(Debug, Clone, PartialEq)]
pub struct Figures {
    /// Mean over the fresh poses of the board's averaged normal's error
    /// before the calibration [deg].
    pub before_deg: f64,
    /// The same after it [deg].
    pub after_deg: f64,
    /// The same for the true head at the same poses [deg].
    pub floor_deg: f64,
    /// `after / floor`.
    pub ratio: f64,
    /// Where the floor's head came from (`truth` or `calibrated`).
    pub floor_head: String,
    /// Reading noise used for the floor [mm, 1σ].
    pub sigma_mm: f64,
    /// Poses captured and calibrated from.
    pub poses: usize,
    /// Verification poses.
    pub verify_poses: usize,
    /// Samples per verification pose.
    pub verify_samples: usize,
    /// The calibration's expected normal error [deg RMS] (bootstrap over
    /// the captured poses, no reading noise).
    pub expected_deg: f64,
    /// Wall time of the run [s].
    pub seconds: f64,
    /// The 95th percentile of the expected normal error [deg].
    pub expected_p95_deg: f64,
    /// The after pass decided against the tolerance.
    pub decision: Decision,
    /// Each fresh pose's error before the calibration [deg] (`None`: no
    /// plane), in the order of `decision.poses`' pose numbers.
    pub before_per_pose_deg: Vec<Option<f64>>,
}

/// Captures every planned pose into `poses`; a reset of the node in
/// between (its boot-up message) stops it.
fn capture_all(
    s: &mut Session<'_>,
    robot: &mut Robot,
    plan: &[(i64, PlannedPose)],
    poses: &Path,
) -> Result<()> {
    let a = s.args;
    if drain_saw_bootup(&mut s.node)? {
        return Err(reset_error(&s.node, "the run, before the capture"));
    }
    for (done, (k, pose)) in plan.iter().enumerate() {
        check_cancel(s.cancel, "the capture")?;
        if let Some(t) = robot.turns() {
            t.select(Some(*k));
        }
        let p = robot
            .present(&format!("pose {k}"), pose, s.cancel)
            .map_err(|e| anyhow!("{e:#} ({})", captured(done, plan.len())))?;
        std::thread::sleep(Duration::from_millis(a.m.settle_ms));
        let c = capture::Args {
            plane: abcd(&p.tracker),
            pose: *k,
            out: poses.to_path_buf(),
            samples: a.samples,
        };
        let res = capture::run(&mut s.node, &c, s.cancel);
        // A reset explains a failed capture better than its timeout does.
        if drain_saw_bootup(&mut s.node).unwrap_or(false) {
            let what = format!("the capture of pose {k} ({})", captured(done, plan.len()));
            return Err(reset_error(&s.node, &what));
        }
        res.map_err(|e| anyhow!("capturing pose {k}: {e:#} ({})", captured(done, plan.len())))?;
    }
    if let Some(t) = robot.turns() {
        t.select(None);
    }
    Ok(())
}

/// `nothing was captured` or `K of N poses captured`.
fn captured(done: usize, of: usize) -> String {
    match done {
        0 => "nothing was captured".into(),
        k => format!("{k} of {of} poses captured"),
    }
}

/// The pooled reading noise of the captures [mm, 1σ], 0 if none recorded.
fn pooled_sigma(poses: &Path) -> Result<f64> {
    let t = perpend_lab::exchange::read_poses(poses, None)?;
    let sd: Vec<f64> = t
        .rows
        .iter()
        .flat_map(|r| r.noise.sd_mm.iter().flatten().copied())
        .collect();
    if sd.is_empty() {
        return Ok(0.0);
    }
    Ok((sd.iter().map(|s| s * s).sum::<f64>() / sd.len() as f64).sqrt())
}

/// The head the floor is computed with, and where it came from.
fn floor_head(a: &RunArgs, params: &Path) -> Result<(Head4<f64>, String)> {
    match &a.truth {
        Some(p) => {
            let t = perpend_lab::exchange::read_sensors(p)?;
            Ok((
                head4(t.sensors()?, &p.display().to_string())?,
                "truth".into(),
            ))
        }
        None => {
            let f = perpend_lab::paramfile::ParamFile::read(params)?;
            let what = params.display().to_string();
            Ok((head4(f.sensors()?, &what)?, "calibrated".into()))
        }
    }
}

/// Calibrates `poses` from the nominal head into `params`.
fn calibrate(sensors: &Path, poses: &Path, params: &Path) -> Result<()> {
    use perpend_lab::calibrate as cal;
    cal::run(&cal::Args {
        sensors: sensors.to_path_buf(),
        poses: poses.to_path_buf(),
        method: cal::Method::Lsq,
        model: cal::Model::Base,
        out: Some(params.to_path_buf()),
        ekf_preset: cal::EkfPreset::Simulation,
        ekf_r: None,
        ekf_q: None,
        ekf_delta: None,
        ekf_nonlinear: false,
        ekf_joseph: false,
        keep_outliers: false,
    })
}

/// The calibration's expected normal error [deg RMS] over the captured
/// poses: the bootstrap of `perpend calibrate` ([`perpend_lab::accuracy`],
/// the paper's model refitted from the nominal head).
fn expected_deg(sensors: &Path, poses: &Path, params: &Path) -> Result<(f64, f64)> {
    use perpend_lab::accuracy::{base_refit, expected_normal_error};
    let nominal = perpend_lab::exchange::read_sensors(sensors)?
        .sensors()
        .map_err(|e| anyhow!("{}: {e}", sensors.display()))?;
    let table = perpend_lab::exchange::read_poses(poses, Some(nominal.len()))?;
    let fitted = perpend_lab::paramfile::ParamFile::read(params)?.sensors()?;
    let e = expected_normal_error(&fitted, &table, &base_refit(&nominal), 100, 1)
        .context("the calibration's expected normal error")?;
    Ok((e.rms_deg, e.p95_deg))
}

/// How far the push of the new calibration got.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PushStage {
    /// Nothing written: the board holds its previous calibration.
    NotBegun,
    /// Begun: the board may hold anything until `previous.json` is back.
    Begun,
    /// Written, stored, reset, verified.
    Verified,
}

/// One run on one node and what it changed there, to put back
/// ([`Session::restore`]).
struct Session<'a> {
    node: Node,
    args: &'a RunArgs,
    cancel: &'a AtomicBool,
    /// The heartbeat period found [ms] (0: off).
    heartbeat_ms: u64,
    /// The NMT state found (`None`: heartbeat off, unknown).
    nmt: Option<NodeState>,
    /// The residual limit 0x2300 sub 4 found [mm].
    residual: f32,
    /// Whether the run holds the residual limit raised.
    raised: bool,
    push: PushStage,
    /// The board's calibration as found (`DIR/previous.json`).
    previous: PathBuf,
    /// The before figure, once measured.
    before_deg: Option<f64>,
    /// The board's serial (0x1018 sub 4) as `0x…`, for the record.
    serial: String,
    /// Its software version (0x100A), for the record.
    firmware: String,
    /// The stamp the board carries after the push (`None`: not pushed, or
    /// pushed back).
    stamp: Option<BoardStamp>,
    /// The board's die temperature at the start and the end [°C].
    die_temp_c: [Option<f64>; 2],
    /// The tolerance and the tracker.
    reference: Reference,
    /// When the run began (ISO 8601 UTC), for the certificate.
    started_utc: String,
}

/// What [`Session::restore`] put back, and what it could not.
#[derive(Debug, Default)]
struct Restored {
    done: Vec<String>,
    problems: Vec<String>,
    /// `previous.json` was pushed back and verified.
    reverted: bool,
}

impl<'a> Session<'a> {
    /// Notes the NMT state and the residual limit, keeps the calibration
    /// in `DIR/previous.json`. Changes nothing on the board.
    fn begin(
        mut node: Node,
        args: &'a RunArgs,
        cancel: &'a AtomicBool,
        reference: Reference,
    ) -> Result<Self> {
        let started_utc = perpend_lab::record::utc_now();
        let heartbeat_ms = node.heartbeat_ms()?;
        let nmt = node.state(heartbeat_ms)?;
        let residual = node.client.read_f32(node.id, 0x2300, 4)?;
        let serial = format!("{:#010x}", node.client.read_u32(node.id, 0x1018, 4)?);
        let firmware = node.client.read_string(node.id, 0x100A, 0)?;
        let die = die_temp(&mut node);
        let previous = args.out.join("previous.json");
        params::pull(&mut node, cancel)
            .and_then(|f| f.write(&previous))
            .with_context(|| {
                format!(
                    "keeping the calibration of {} in {} before anything is changed (nothing \
                     was changed)",
                    node.name(),
                    previous.display()
                )
            })?;
        println!(
            "cell: the board's calibration kept in {} (pushed back if this run does not \
             end with a better one)",
            previous.display()
        );
        Ok(Self {
            node,
            args,
            cancel,
            heartbeat_ms,
            nmt,
            residual,
            raised: false,
            push: PushStage::NotBegun,
            previous,
            before_deg: None,
            serial,
            firmware,
            stamp: None,
            die_temp_c: [die, None],
            reference,
            started_utc,
        })
    }

    /// The verification's sampling.
    fn sampling(&self) -> Sampling {
        self.args.m.sampling()
    }

    /// The before pass with the residual limit raised, put back after it.
    fn before(&mut self, robot: &mut Robot, fresh: &[PlannedPose]) -> Result<Verified> {
        let (id, a) = (self.node.id, self.args);
        let raised = (a.before_residual_mm as f32).max(self.residual);
        // Raised from the request on: a lost answer may hide a done write.
        self.raised = true;
        self.node
            .client
            .download(id, 0x2300, 4, &raised.to_le_bytes())
            .context("raising the residual limit (0x2300 sub 4) for the before pass")?;
        let sampling = self.sampling();
        let v = verify(
            &mut self.node,
            robot,
            fresh,
            sampling,
            "before",
            self.cancel,
        )?;
        self.put_back_residual()?;
        Ok(v)
    }

    /// Writes the residual limit found back and reads it back.
    fn put_back_residual(&mut self) -> Result<()> {
        let (id, old) = (self.node.id, self.residual);
        self.node
            .client
            .download(id, 0x2300, 4, &old.to_le_bytes())?;
        let v = self.node.client.read_f32(id, 0x2300, 4)?;
        if v.to_bits() != old.to_bits() {
            bail!("it reads {v} mm after {old} mm was written");
        }
        self.raised = false;
        Ok(())
    }

    /// Pushes the new calibration (verified push, `--preop`).
    fn push_new(&mut self, params: &Path) -> Result<()> {
        self.push = PushStage::Begun;
        let push = params::PushArgs {
            file: params.to_path_buf(),
            preop: true,
            record: None,
        };
        let stamped = perpend_lab::record::record_path(params);
        let report = params::push(&mut self.node, &push, self.cancel).map_err(|e| {
            // What push says the board is left with is superseded by the
            // restore: its cause comes first.
            let left = e.to_string();
            let cause: Vec<String> = if left.starts_with("nothing was stored") {
                e.chain().skip(1).map(ToString::to_string).collect()
            } else {
                e.chain().map(ToString::to_string).collect()
            };
            anyhow!("pushing the new calibration: {}", cause.join(": "))
        })?;
        println!("{report}");
        self.push = PushStage::Verified;
        if let (Some(st), true) = (&report.stamp, stamped.exists()) {
            self.stamp = Some(BoardStamp {
                record_hash: format!("{:08x}", st.record_hash),
                stamped_record: perpend_lab::record::FileHash::of(&stamped)?,
                utc: crate::record::iso(f64::from(st.utc_s)),
                store_count: st.store_count,
            });
        }
        Ok(())
    }

    /// Reaches the node again: as it is, else over a new connection (once).
    fn relink(&mut self) -> Result<()> {
        if self.node.hello().is_ok() {
            return Ok(());
        }
        // The old connection goes first: a board (the virtual one, an
        // slcan adapter) takes one client, and our own would lock us out.
        let mut closed = crate::bus::fake::FakeBus::new(crate::bus::fake::FnPeer(
            |_: &perpend_can::Frame, _: &mut Vec<perpend_can::Frame>| {},
        ));
        closed.closed = true;
        let id = self.node.id;
        let placeholder = Node::new(crate::canopen::Client::new(Box::new(closed)), id);
        drop(std::mem::replace(&mut self.node, placeholder));
        let mut node = Node::connect(&self.args.link)?;
        node.hello()?;
        self.node = node;
        Ok(())
    }

    /// Puts back what the run changed: link, calibration (when `revert`),
    /// residual limit, lock, NMT state; each step tried even when one
    /// before it failed (the link excepted).
    fn restore(&mut self, revert: bool) -> Restored {
        let mut r = Restored::default();
        let name = self.node.name();
        if let Err(e) = self.relink() {
            r.problems.push(format!(
                "{name} cannot be reached to put back what the run changed ({e:#}); when it \
                 answers, {}",
                self.by_hand(revert)
            ));
            return r;
        }
        let id = self.node.id;
        if let Err(e) = self.node.client.nmt(id, Nmt::Preop) {
            r.problems
                .push(format!("{name}: pre-operational for the restore: {e}"));
        }
        if revert {
            self.revert(&mut r);
        }
        if self.raised {
            let old = self.residual;
            match self.put_back_residual() {
                Ok(()) => r.done.push(format!(
                    "residual limit 0x2300 sub 4 back to {old} mm (read back)"
                )),
                Err(e) => r.problems.push(format!(
                    "{name}: the residual limit 0x2300 sub 4 could not be put back to {old} mm \
                     ({e:#}); it is not stored: reset the node"
                )),
            }
        }
        self.relock(&mut r);
        self.restore_nmt(&mut r);
        r
    }

    /// Pushes `previous.json` back (the verified push).
    fn revert(&mut self, r: &mut Restored) {
        let quiet = AtomicBool::new(false);
        let push = params::PushArgs {
            file: self.previous.clone(),
            preop: true,
            record: None,
        };
        match params::push(&mut self.node, &push, &quiet) {
            Ok(_) => {
                self.push = PushStage::NotBegun;
                self.stamp = None;
                r.reverted = true;
                r.done.push(format!(
                    "the previous calibration ({}) pushed back: written, stored, reset, read \
                     back identical",
                    self.previous.display()
                ));
            }
            Err(e) => r.problems.push(format!(
                "pushing the previous calibration back failed ({e:#}): {}",
                self.by_hand(true)
            )),
        }
    }

    /// Locks calibration writes (0x2010) if they are unlocked.
    fn relock(&mut self, r: &mut Restored) {
        let id = self.node.id;
        match self.node.client.read_u32(id, 0x2010, 0) {
            Ok(0) => {}
            Ok(_) => match self.node.client.write_u32(id, 0x2010, 0, 0) {
                Ok(()) => r
                    .done
                    .push("calibration writes locked again (0x2010)".into()),
                Err(e) => r.problems.push(format!("locking 0x2010: {e}")),
            },
            Err(e) => r.problems.push(format!("reading the lock 0x2010: {e}")),
        }
    }

    /// Returns the node to the NMT state found and checks its heartbeat.
    fn restore_nmt(&mut self, r: &mut Restored) {
        let id = self.node.id;
        let (cmd, want) = match self.nmt {
            Some(NodeState::Operational) => (Some(Nmt::Start), NodeState::Operational),
            Some(NodeState::Stopped) => (Some(Nmt::Stop), NodeState::Stopped),
            _ => (None, NodeState::PreOperational),
        };
        if let Some(c) = cmd {
            if let Err(e) = self.node.client.nmt(id, c) {
                r.problems.push(format!("NMT {want} again: {e}"));
                return;
            }
        }
        if self.heartbeat_ms == 0 {
            r.done
                .push("node left pre-operational (heartbeat off: state found unknown)".into());
            return;
        }
        let wait = Duration::from_millis(self.heartbeat_ms * 3 / 2 + 200);
        match self.node.client.wait_heartbeat(id, wait) {
            Ok(Some(s)) if s == want => r.done.push(format!("node {want} as found")),
            Ok(s) => r.problems.push(format!(
                "{}: should be {want} as found, its heartbeat says {}; set it with `perpend \
                 node … nmt`",
                self.node.name(),
                s.map_or("nothing".into(), |s| s.to_string())
            )),
            Err(e) => r.problems.push(format!("checking the NMT state: {e}")),
        }
    }

    /// What to do by hand when the restore cannot.
    fn by_hand(&self, revert: bool) -> String {
        let mut s = String::from("reset it (its residual limit is not stored)");
        if revert || self.push != PushStage::NotBegun {
            s = format!(
                "push the previous calibration back: perpend node --bus {} --node-id {} push \
                 {} --preop",
                self.args.link.bus.as_deref().unwrap_or("BUS"),
                self.node.id,
                self.previous.display()
            );
        }
        s
    }
}

/// Before, capture, calibrate, push, after, floor.
fn steps(
    s: &mut Session<'_>,
    robot: &mut Robot,
    plan: &[(i64, PlannedPose)],
    started: Instant,
) -> Result<Figures> {
    let a = s.args;
    let (poses, params) = (a.out.join("poses.csv"), a.out.join("params.json"));
    // A board found operational takes no configuration writes.
    s.node.client.nmt(s.node.id, Nmt::Preop)?;
    let fresh = fresh_poses(plan, a.verify, a.seed());
    let csv = a.out.join("verify.csv");
    let before_pass = s.before(robot, &fresh)?;
    write_csv(&csv, "before", &before_pass)?;
    let before = before_pass.mean_deg();
    s.before_deg = Some(before);
    println!("cell: before calibration, normal error {before:.4}° (mean)");
    capture_all(s, robot, plan, &poses)?;
    calibrate(&a.sensors, &poses, &params)?;
    let (expected, expected_p95) = expected_deg(&a.sensors, &poses, &params)?;
    if expected > s.reference.tolerance_deg {
        bail!(
            "the new calibration's expected normal error {expected:.4}° (from its own parameter \
             uncertainty, no reading noise) exceeds the tolerance {}°: it cannot verify and was \
             not pushed; check the captures in {} (did the readings follow the planes? is the \
             plan's reach wide enough?)",
            s.reference.tolerance_deg,
            poses.display()
        );
    }
    if let Some(t) = robot.turns() {
        crate::cell_frames::after_calibration(&a.sensors, &a.out, t, expected)?;
    }
    check_cancel(s.cancel, "the calibration")?;
    s.push_new(&params)?;
    let sampling = s.sampling();
    let v = verify(&mut s.node, robot, &fresh, sampling, "after", s.cancel)?;
    write_csv(&csv, "after", &v)?;
    s.die_temp_c[1] = die_temp(&mut s.node);
    let after = v.mean_deg();
    let sigma = pooled_sigma(&poses)?;
    let (head, from) = floor_head(a, &params)?;
    let floor = floor(&head, &v.seen(), sigma, a.m.verify_samples, a.seed())?;
    Ok(Figures {
        before_deg: before,
        after_deg: after,
        floor_deg: floor,
        ratio: after / floor,
        floor_head: from,
        sigma_mm: sigma,
        poses: plan.len(),
        verify_poses: fresh.len(),
        verify_samples: a.m.verify_samples,
        expected_deg: expected,
        seconds: started.elapsed().as_secs_f64(),
        expected_p95_deg: expected_p95,
        decision: s.reference.decide(&v),
        before_per_pose_deg: before_pass.poses.iter().map(|p| p.error_deg).collect(),
    })
}

/// How a run ended (`outcome` in cell.json and the record).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// The new calibration is on the board, verified there.
    Applied,
    /// It was pushed, then the previous one was pushed back.
    Reverted,
    /// The run failed; the board holds what it held, all put back.
    FailedRestored,
    /// The run failed and something could not be put back.
    FailedUnknown,
}

impl Outcome {
    /// The word in cell.json and the record.
    pub fn word(self) -> &'static str {
        use perpend_lab::record as r;
        match self {
            Outcome::Applied => r::OUTCOME_APPLIED,
            Outcome::Reverted => r::OUTCOME_REVERTED,
            Outcome::FailedRestored => r::OUTCOME_FAILED_RESTORED,
            Outcome::FailedUnknown => r::OUTCOME_FAILED_UNKNOWN,
        }
    }
}

/// What `cell run` did (`cell.json`).
#[derive(Debug, Clone)]
pub struct Report {
    /// How it ended.
    pub outcome: Outcome,
    /// Why, in a sentence.
    pub reason: String,
    /// What stopped the run first (failed, reverted).
    pub first_cause: Option<String>,
    /// What was put back.
    pub restored: Vec<String>,
    /// What could not be put back (after the first cause).
    pub problems: Vec<String>,
    /// The before figure, when measured.
    pub before_deg: Option<f64>,
    /// The figures of a run that reached its verdict.
    pub figures: Option<Figures>,
    /// `DIR/record.json`, when the run calibrated.
    pub record: Option<PathBuf>,
}

/// The mean of after − before over the fresh poses with both, and its
/// standard uncertainty (the paired differences' scatter / √n).
fn paired_change(f: &Figures) -> Option<(f64, f64)> {
    let d: Vec<f64> = f
        .decision
        .poses
        .iter()
        .filter_map(|p| {
            let k = usize::try_from(p.pose - 1).ok()?;
            Some(p.error_deg - (*f.before_per_pose_deg.get(k)?)?)
        })
        .collect();
    perpend_lab::interim::mean_u(&d)
}

/// Why the new calibration is not applied, if it is not: the after error
/// worse than the before error beyond the uncertainty of their difference
/// (k = 2, paired over the same fresh poses), or the decision FAIL.
fn worse(f: &Figures) -> Option<String> {
    let change = paired_change(f);
    if let Some((diff, u)) = change.filter(|(d, u)| *d > 2.0 * u) {
        Some(format!(
            "after {:.4}° is worse than before {:.4}° (mean over the fresh poses; the \
             difference {diff:+.4}° exceeds its expanded uncertainty {:.4}°, k = 2)",
            f.after_deg,
            f.before_deg,
            2.0 * u
        ))
    } else if f.decision.verdict == Verdict::Fail {
        Some(decision_words(&f.decision))
    } else {
        None
    }
}

/// The verdict on a run that got its figures, and the restore it needs.
fn judge(s: &mut Session<'_>, f: Figures) -> Report {
    let keep_worse = s.args.keep_worse;
    let why = worse(&f);
    let r = s.restore(why.is_some() && !keep_worse);
    let (outcome, reason, first_cause) = match why {
        None => (
            Outcome::Applied,
            format!(
                "{}; after {:.4}° against before {:.4}° (mean{})",
                decision_words(&f.decision),
                f.after_deg,
                f.before_deg,
                paired_change(&f).map_or(String::new(), |(d, u)| format!(
                    ", change {d:+.4}° ± {:.4}° (k = 2)",
                    2.0 * u
                ))
            ),
            None,
        ),
        Some(w) if keep_worse => (
            Outcome::Applied,
            format!("{w}; the new calibration is kept (--keep-worse)"),
            None,
        ),
        Some(w) if r.reverted => (
            Outcome::Reverted,
            format!("{w}; the previous calibration was pushed back (--keep-worse keeps the new)"),
            Some(w),
        ),
        Some(w) => (
            Outcome::FailedUnknown,
            format!("{w}, and the previous calibration could not be pushed back"),
            Some(w),
        ),
    };
    Report {
        outcome,
        reason,
        first_cause,
        restored: r.done,
        problems: r.problems,
        before_deg: Some(f.before_deg),
        figures: Some(f),
        record: None,
    }
}

/// The report of a run stopped by `e`, after the restore.
fn failed(s: &mut Session<'_>, e: &anyhow::Error) -> Report {
    let revert = s.push != PushStage::NotBegun;
    let r = s.restore(revert);
    let holds = match (revert, r.reverted) {
        (false, _) if r.problems.is_empty() => "nothing was pushed: the board keeps its previous \
                                                calibration"
            .to_string(),
        (false, _) => "nothing was pushed, but not everything could be put back".into(),
        (true, true) => "the board holds its previous calibration again".into(),
        (true, false) => "the board's calibration could not be put back".into(),
    };
    let restored = r.problems.is_empty() && (!revert || r.reverted);
    Report {
        outcome: if restored {
            Outcome::FailedRestored
        } else {
            Outcome::FailedUnknown
        },
        reason: format!("the run stopped; {holds}"),
        first_cause: Some(format!("{e:#}")),
        restored: r.done,
        problems: r.problems,
        before_deg: s.before_deg,
        figures: None,
        record: None,
    }
}

/// The board's die temperature (0x200A) [°C], `None` when it has none.
fn die_temp(node: &mut Node) -> Option<f64> {
    let t = node.client.read_f32(node.id, 0x200A, 0).ok()?;
    (t > perpend_can::od::DIE_TEMP_UNKNOWN).then_some(f64::from(t))
}

/// `perpend cell run`.
///
/// # Errors
/// Only problems found before the board was touched (bad files or
/// arguments, a board or robot that does not answer, the calibration that
/// cannot be kept); every later one ends in a [`Report`] with outcome
/// `failed`, after what the run changed was put back.
pub fn run_cell(a: &RunArgs, cancel: &AtomicBool) -> Result<Report> {
    let started = Instant::now();
    if a.verify == 0 || a.m.verify_samples < 2 {
        bail!(
            "--verify must be at least 1 and --verify-samples at least 2 (their scatter is the \
             readings' share of the verification's uncertainty)"
        );
    }
    let plan = read_plan(&a.plan)?;
    let simulated = a.m.simulated();
    let reference = Reference::new(a.m.config.as_deref(), a.m.tolerance_deg, simulated)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create", a.out.display()))?;
    let poses = a.out.join("poses.csv");
    if poses.exists() {
        bail!(
            "{} exists: a cell run writes a fresh one (move it away or choose another --out)",
            poses.display()
        );
    }
    let mut robot = Robot::open(&a.m.robot, a.seed(), reference.sim_tracker())?;
    if a.reversal {
        let Robot::Sim(sim) = &mut robot else {
            bail!("--reversal: only with --robot sim:HOST:PORT for now (a manual robot cannot be told the joint angle yet)");
        };
        sim.turns = crate::cell_frames::Turns::new(crate::cell_frames::read_joints(&a.plan)?);
    }
    let mut node = Node::connect(&a.link)?;
    node.hello()?;
    let mut s = Session::begin(node, a, cancel, reference)?;
    if let Ok(f) = perpend_lab::paramfile::ParamFile::read(&s.previous) {
        robot.check_manual(ManualCheck::from_params(&f)?);
    }
    let mut report = match steps(&mut s, &mut robot, &plan, started) {
        Ok(f) => judge(&mut s, f),
        Err(e) => failed(&mut s, &e),
    };
    match write_record(a, &s, &report) {
        Ok(r) => report.record = r,
        Err(e) => report.problems.push(format!(
            "the calibration record could not be written: {e:#}"
        )),
    }
    Ok(report)
}

/// `DIR/record.json` of a run that calibrated: the calibration's record
/// (`params.record.json`, written by `perpend calibrate`) with the plan,
/// the verification file and the true head among its inputs, the
/// outcome, the board's serial, firmware and stamp, the board's previous
/// calibration (`previous.json`) as `previous`, the verification at the
/// fresh poses after the push and its decision (when the run got that
/// far), the certificate's fields and what the run did as events. Then
/// `DIR/cert.html` when the calibration is applied and verified, else
/// `DIR/report.html` (marked: no certificate). A run that stopped before it
/// calibrated has nothing to record (cell.json says why).
fn write_record(a: &RunArgs, s: &Session<'_>, report: &Report) -> Result<Option<PathBuf>> {
    use perpend_lab::record::{self as rec, FileHash, Previous, Record};
    let params = a.out.join("params.json");
    if !params.exists() {
        return Ok(None);
    }
    let beside = rec::record_path(&params);
    let mut r = if beside.exists() {
        Record::read(&beside)?
    } else {
        let file = perpend_lab::paramfile::ParamFile::read(&params)?;
        Record::new(&[&a.sensors, &a.out.join("poses.csv")], &file)?
    };
    let csv = a.out.join("verify.csv");
    for f in [
        Some(&a.plan),
        Some(&csv).filter(|c| c.exists()),
        a.truth.as_ref(),
    ]
    .into_iter()
    .flatten()
    {
        r.inputs.push(FileHash::of(f)?);
    }
    r = crate::cell_frames::into_record(r, &a.out, &params)?;
    r = r
        .with_board(&s.serial, &s.firmware)
        .with_previous(Previous::of(&s.previous)?);
    r.outcome = Some(report.outcome.word().into());
    if report.outcome == Outcome::Applied {
        r.stamp = s.stamp.clone();
    }
    if let Some(f) = &report.figures {
        r = r.with_verification(fresh_verification(f, a));
        r.decision = Some(f.decision.clone());
    }
    r.certification = Some(certification(s, &r.utc));
    if !r.is_certifiable() {
        if let Some(c) = r.certification.as_mut() {
            c.number = None;
        }
    }
    if let Some(c) = &report.first_cause {
        r.push_event(&format!("first cause: {c}"));
    }
    r.push_event(&format!(
        "perpend cell run: {}: {}",
        report.outcome.word(),
        report.reason
    ));
    for d in &report.restored {
        r.push_event(&format!("put back: {d}"));
    }
    for p in &report.problems {
        r.push_event(&format!("not put back: {p}"));
    }
    let path = a.out.join("record.json");
    r.write(&path)?;
    crate::record::write_document(&r, &a.out)?;
    Ok(Some(path))
}

/// The certificate's fields of this run: the configuration's (or what
/// stands for it), the number, the die temperatures.
fn certification(s: &Session<'_>, utc: &str) -> perpend_lab::record::Certification {
    let cfg = s.reference.config.as_ref();
    let given = |f: fn(&perpend_lab::cellconfig::CellConfig) -> &String| {
        cfg.map_or_else(
            || "not given (no --config)".to_string(),
            |c| f(&c.0).clone(),
        )
    };
    let stamp: String = utc.chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    perpend_lab::record::Certification {
        number: Some(format!(
            "PPD-{}-{stamp}",
            s.serial.trim_start_matches("0x").to_uppercase()
        )),
        operator: given(|c| &c.operator),
        approver: given(|c| &c.approver),
        site: given(|c| &c.site),
        laboratory: Some(given(|c| &c.laboratory)),
        customer: cfg.and_then(|c| c.0.customer.clone()),
        tracker: s.reference.tracker.clone(),
        die_temp_c: s.die_temp_c,
        ambient_c: cfg.and_then(|c| c.0.ambient_c),
        config: cfg.map(|c| c.1.clone()),
        performed_utc: Some([s.started_utc.clone(), perpend_lab::record::utc_now()]),
    }
}

/// The after pass as the record's verification: each fresh pose's error,
/// against the calibration's expected error, with the before figure.
fn fresh_verification(f: &Figures, a: &RunArgs) -> perpend_lab::record::Verification {
    use perpend_lab::record::{PoseError, Verification, KIND_FRESH};
    let poses = f
        .decision
        .poses
        .iter()
        .map(|p| PoseError {
            pose: p.pose,
            error_deg: p.error_deg,
        })
        .collect();
    let note = format!(
        "the board's own normal (θ1/θ2 from its TPDO, averaged over {} samples a pose, after \
         the push and reset) against the tracker's plane at {} fresh poses inside the plan's \
         reach (seed {}; planes and normals in verify.csv); before the calibration {:.4}°, the \
         floor ({} head at the measured reading noise) {:.4}°",
        f.verify_samples,
        f.verify_poses,
        a.seed(),
        f.before_deg,
        f.floor_head,
        f.floor_deg
    );
    let mut v = Verification::from_errors(KIND_FRESH, &note, poses)
        .with_expected(Some((f.expected_deg, f.expected_p95_deg)));
    v.before_mean_deg = Some(f.before_deg);
    v
}

impl Report {
    /// cell.json: the figures (if any) and the outcome.
    pub fn json(&self) -> serde_json::Value {
        let mut v = match &self.figures {
            Some(f) => f.json(),
            None => serde_json::json!({ "before_deg": self.before_deg }),
        };
        if let Some(o) = v.as_object_mut() {
            o.insert("utc".into(), perpend_lab::record::utc_now().into());
            o.insert(
                "tool_version".into(),
                perpend_lab::record::tool_version().into(),
            );
            o.insert("outcome".into(), self.outcome.word().into());
            o.insert("reason".into(), self.reason.clone().into());
            o.insert("first_cause".into(), self.first_cause.clone().into());
            o.insert("restored".into(), self.restored.clone().into());
            o.insert("restore_problems".into(), self.problems.clone().into());
            let rec = self.record.as_ref().map(|p| p.display().to_string());
            o.insert("record".into(), rec.into());
        }
        v
    }
}

impl Figures {
    /// The figures as the JSON object of `cell.json`.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "before_deg": self.before_deg,
            "after_deg": self.after_deg,
            "floor_deg": self.floor_deg,
            "ratio": self.ratio,
            "floor_head": self.floor_head,
            "sigma_mm": self.sigma_mm,
            "poses": self.poses,
            "verify_poses": self.verify_poses,
            "verify_samples": self.verify_samples,
            "expected_deg": self.expected_deg,
            "tolerance_deg": self.decision.tolerance_deg,
            "decision": self.decision.verdict.word(),
            "max_expanded_uncertainty_deg": self.decision.max_expanded_deg,
            "decide_by": self.decision.decide_by,
            "seconds": self.seconds,
        })
    }
}

/// Writes nominal.csv and truth.csv of the paper's head (Chen Table 2).
fn sim_head(a: &SimHeadArgs) -> Result<()> {
    let h = perpend_lab::sim::paper_head()?;
    std::fs::create_dir_all(&a.out)?;
    for (name, s) in [("nominal.csv", &h.nominal), ("truth.csv", &h.truth)] {
        let path = a.out.join(name);
        let table = perpend_lab::exchange::SensorTable::from_sensors(s, h.sigma_mm);
        let mut f = std::fs::File::create(&path)
            .with_context(|| format!("{}: cannot create", path.display()))?;
        perpend_lab::exchange::write_sensors(&mut f, &table, &[])?;
        println!("cell: wrote {}", path.display());
    }
    Ok(())
}

/// Set by Ctrl-C during `cell run`: the run stops at its next step and
/// puts back what it changed.
static CANCEL: AtomicBool = AtomicBool::new(false);

/// The first Ctrl-C sets [`CANCEL`], the second quits at once.
fn install_ctrlc() {
    let _ = ctrlc::set_handler(|| {
        if CANCEL.swap(true, Ordering::SeqCst) {
            eprintln!("\nperpend cell: Ctrl-C, quitting now (nothing put back)");
            std::process::exit(130);
        }
        eprintln!(
            "\nperpend cell: Ctrl-C, stopping and putting back what the run changed (Ctrl-C \
             again quits at once)"
        );
    });
}

/// Writes cell.json.
fn write_json(dir: &Path, v: &serde_json::Value) -> Result<PathBuf> {
    let json = dir.join("cell.json");
    std::fs::write(&json, crate::schema::tagged_pretty(crate::schema::CELL, v))
        .with_context(|| format!("{}: cannot write", json.display()))?;
    Ok(json)
}

/// Prints a run that reached its verdict.
fn print_figures(f: &Figures, json: &Path) {
    println!(
        "cell: normal error before {:.4}°, after {:.4}°, floor ({} head) {:.4}°: after/floor \
         {:.2}×, expected {:.4}° ({} poses captured, {} fresh poses × {} samples verified, \
         {:.1} s); figures in {}",
        f.before_deg,
        f.after_deg,
        f.floor_head,
        f.floor_deg,
        f.ratio,
        f.expected_deg,
        f.poses,
        f.verify_poses,
        f.verify_samples,
        f.seconds,
        json.display()
    );
}

/// `cell run` with its report: cell.json always, an error unless the new
/// calibration was kept.
fn run_and_report(x: &RunArgs) -> Result<()> {
    install_ctrlc();
    let report = match run_cell(x, &CANCEL) {
        Ok(r) => r,
        Err(e) => {
            // Nothing was changed on the board.
            if x.out.is_dir() {
                let v = serde_json::json!({
                    "utc": perpend_lab::record::utc_now(),
                    "tool_version": perpend_lab::record::tool_version(),
                    "outcome": perpend_lab::record::OUTCOME_FAILED_RESTORED,
                    "reason": "the run stopped before it changed anything on the board",
                    "first_cause": format!("{e:#}"),
                    "restored": [],
                    "restore_problems": [],
                });
                let _ = write_json(&x.out, &v);
            }
            return Err(e);
        }
    };
    let json = write_json(&x.out, &report.json())?;
    if let Some(f) = &report.figures {
        print_figures(f, &json);
    }
    if let Some(c) = &report.first_cause {
        println!("cell: first cause: {c}");
    }
    for d in &report.restored {
        println!("cell: put back: {d}");
    }
    if let Some(r) = &report.record {
        let doc = match r.with_file_name("cert.html").exists() {
            true => format!("certificate {}", r.with_file_name("cert.html").display()),
            false => format!(
                "{} (no certificate)",
                r.with_file_name("report.html").display()
            ),
        };
        println!(
            "cell: calibration record {} and {doc} (perpend record show|find|history)",
            r.display()
        );
    }
    println!("cell: {}: {}", report.outcome.word(), report.reason);
    match report.outcome {
        Outcome::Applied => Ok(()),
        Outcome::Reverted | Outcome::FailedRestored | Outcome::FailedUnknown => {
            let mut msg = report.first_cause.clone().unwrap_or_default();
            msg.push_str(&format!("\n  {}", report.reason));
            for p in &report.problems {
                msg.push_str(&format!("\n  also: {p}"));
            }
            msg.push_str(&format!("\n  (details in {})", json.display()));
            Err(anyhow!(msg))
        }
    }
}

/// Runs `perpend cell`.
///
/// # Errors
/// As [`run_cell`] and [`sim_head`]; a run whose calibration was not kept.
pub fn run(a: &Args) -> Result<()> {
    match &a.cmd {
        Cmd::SimHead(x) => sim_head(x),
        Cmd::Run(x) => run_and_report(&RunArgs {
            link: a.link.clone(),
            seed: Some(x.seed.unwrap_or_else(clock_seed)),
            ..x.clone()
        }),
        Cmd::Check(x) => {
            install_ctrlc();
            crate::cell_check::run_and_report(
                &crate::cell_check::CheckArgs {
                    link: a.link.clone(),
                    ..x.clone()
                },
                &CANCEL,
            )
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn fresh_poses_stay_in_the_plan_box() {
        let p = |x, y, s| PlannedPose {
            tilt_x_deg: x,
            tilt_y_deg: y,
            standoff_mm: s,
        };
        let plan = vec![(1, p(-5.0, -4.0, 26.0)), (2, p(5.0, 4.0, 30.0))];
        for q in fresh_poses(&plan, 50, 3) {
            assert!((-5.0..=5.0).contains(&q.tilt_x_deg));
            assert!((-4.0..=4.0).contains(&q.tilt_y_deg));
            assert!((26.0..=30.0).contains(&q.standoff_mm));
        }
        assert!(Robot::open("robot", 1, perpend_lab::sim::Tracker::paper()).is_err());
    }
}
