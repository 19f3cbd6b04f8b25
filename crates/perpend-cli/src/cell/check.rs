//! `perpend cell check`: the interim check between two calibrations
//! (issue 45). The board's stored calibration, unchanged, is measured at
//! a few fresh poses inside the plan's reach exactly as the cell run
//! verifies ([`super::verify`]), decided against the tolerance with
//! the verification's own expanded uncertainty
//! ([`perpend_formats::conformity`]) and compared with the last calibration
//! record's fresh-pose mean; a `perpend.check/1` record
//! ([`perpend_calib::interim`]) is written for `perpend record history`.
//!
//! The answer: `in tolerance`, `inconclusive` (with the samples that
//! would decide it) or `recalibrate now`. A board whose serial is not the
//! record's is refused; a board whose stamp is not the record's is
//! checked, and the record says its calibration changed since.
//!
//! Nothing is written to the board: the check only starts it
//! (operational, for its TPDOs) and puts its NMT state back as found,
//! also when the check stops.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_calib::interim::{self, Against, CheckRecord};
use perpend_calib::record::{utc_now, FileHash, Record};

use super::robot::{ManualCheck, Robot};
use super::verify::{fresh_poses, read_plan, verify, write_csv, Reference};
use crate::canopen::{Nmt, NodeState};
use crate::node::{params, Node};

/// Options of `cell check`.
#[derive(clap::Args, Debug, Clone)]
pub struct CheckArgs {
    /// The bus and the node: `perpend cell`'s (global) link options.
    #[arg(skip)]
    pub link: crate::node::LinkArgs,
    /// The last calibration record of this head (a cell run's record.json).
    #[arg(long)]
    pub record: PathBuf,
    /// The plan whose reach the fresh poses are drawn in (`perpend plan`).
    #[arg(long)]
    pub plan: PathBuf,
    /// The check record to write (`perpend.check/1`); its poses go beside
    /// it as `<name>.verify.csv`.
    #[arg(long)]
    pub out: PathBuf,
    /// Fresh poses.
    #[arg(long, default_value_t = 4)]
    pub verify: usize,
    /// Seed of the fresh poses and the simulated tracker.
    #[arg(long, default_value_t = 2)]
    pub seed: u64,
    /// The robot, the sampling and the tolerance.
    #[command(flatten)]
    pub m: super::verify::MeasureArgs,
}

/// What the last record verified, to compare with.
fn against(path: &Path) -> Result<(Record, Against)> {
    let r = Record::read(path)?;
    let d = r.decision.as_ref().ok_or_else(|| {
        anyhow!(
            "{}: the record has no decided fresh-pose verification (a cell run's record.json \
             has one)",
            path.display()
        )
    })?;
    let e: Vec<f64> = d.poses.iter().map(|p| p.error_deg).collect();
    let (mean, u) = interim::mean_u(&e).ok_or_else(|| anyhow!("{}: no pose", path.display()))?;
    let a = Against {
        record: FileHash::of(path)?,
        utc: r.utc.clone(),
        stamp: r.stamp.as_ref().map(|s| s.record_hash.clone()),
        mean_deg: mean,
        mean_u_deg: u,
    };
    Ok((r, a))
}

/// The NMT state found (from the heartbeat), to put back.
fn nmt_found(node: &mut Node) -> Result<(u64, Option<NodeState>)> {
    let hb = node.heartbeat_ms()?;
    Ok((hb, node.state(hb)?))
}

/// Puts the NMT state found back (a node found pre-operational, or
/// without heartbeat, is left pre-operational).
fn put_back(node: &mut Node, found: Option<NodeState>) -> Result<()> {
    let cmd = match found {
        Some(NodeState::Operational) => Nmt::Start,
        Some(NodeState::Stopped) => Nmt::Stop,
        _ => Nmt::Preop,
    };
    node.client.nmt(node.id, cmd)?;
    Ok(())
}

/// `perpend cell check`: the check record written, and its verdict.
///
/// # Errors
/// Bad files or arguments, a board of another head, bus or robot errors
/// (the NMT state found is put back first).
pub fn run_check(a: &CheckArgs, cancel: &AtomicBool) -> Result<CheckRecord> {
    if a.verify == 0 || a.m.verify_samples < 2 {
        bail!("--verify must be at least 1 and --verify-samples at least 2");
    }
    if a.out.exists() {
        bail!("{} exists: a check writes a new record", a.out.display());
    }
    let (last, against) = against(&a.record)?;
    let tol =
        a.m.tolerance_deg
            .or(last.decision.as_ref().map(|d| d.tolerance_deg));
    let mut reference = Reference::new(a.m.config.as_deref(), tol, a.m.simulated())?;
    // Without a configuration, the tracker the record names (and its
    // uncertainty) stands, not a default.
    if let (None, Some(c)) = (&a.m.config, last.certification.as_ref()) {
        if let Some(u) = perpend_formats::conformity::tracker_u_rad(
            c.tracker.xi_mm,
            c.tracker.points,
            c.tracker.patch_mm,
        ) {
            reference.tracker = c.tracker.clone();
            reference.tracker_u_deg = u.to_degrees();
            reference.source = format!(
                "tracker {} (serial {}) as the record {} names it",
                c.tracker.model,
                c.tracker.serial,
                a.record.display()
            );
        }
    }
    let plan = read_plan(&a.plan)?;
    let mut robot = Robot::open(&a.m.robot, a.seed, reference.sim_tracker())?;
    let mut node = Node::connect(&a.link)?;
    node.hello()?;
    let serial = format!("{:#010x}", node.client.read_u32(node.id, 0x1018, 4)?);
    if last.head_serial.as_deref() != Some(serial.as_str()) {
        bail!(
            "{} is head {serial}, {} is a record of head {}: check a board against its own \
             record",
            node.name(),
            a.record.display(),
            last.head_serial.as_deref().unwrap_or("without serial")
        );
    }
    let firmware = node.client.read_string(node.id, 0x100A, 0)?;
    let stamp = params::read_stamp(&mut node)?.map(|s| format!("{:08x}", s.record_hash));
    if let Ok(f) = params::pull(&mut node, cancel) {
        robot.check_manual(ManualCheck::from_params(&f)?);
    }
    let (_, found) = nmt_found(&mut node)?;
    let fresh = fresh_poses(&plan, a.verify, a.seed);
    let pass = verify(
        &mut node,
        &mut robot,
        &fresh,
        a.m.sampling(),
        "check",
        cancel,
    );
    let back = put_back(&mut node, found);
    let v = pass?;
    back.context("putting the NMT state found back")?;
    let csv = verify_csv(&a.out);
    write_csv(&csv, "check", &v)?;
    let mut inputs = vec![FileHash::of(&a.plan)?, FileHash::of(&csv)?];
    if let Some((_, f)) = &reference.config {
        inputs.push(f.clone());
    }
    let rec = record(&reference, &v, against, inputs, [serial, firmware], stamp)?;
    rec.write(&a.out)?;
    Ok(rec)
}

/// `check.json` → `check.verify.csv`.
fn verify_csv(out: &Path) -> PathBuf {
    let stem = out
        .file_stem()
        .map_or_else(|| "check".into(), |s| s.to_string_lossy().into_owned());
    out.with_file_name(format!("{stem}.verify.csv"))
}

/// The check record of the pass `v`.
fn record(
    reference: &Reference,
    v: &super::verify::Verified,
    against: Against,
    inputs: Vec<FileHash>,
    [serial, firmware]: [String; 2],
    board_stamp: Option<String>,
) -> Result<CheckRecord> {
    let decision = reference.decide(v);
    let e: Vec<f64> = decision.poses.iter().map(|p| p.error_deg).collect();
    let (mean, u) = interim::mean_u(&e).ok_or_else(|| anyhow!("check: no pose had a plane"))?;
    let change = interim::change(mean, u, &against);
    let verdict = interim::verdict_words(decision.verdict);
    let reason = format!(
        "{verdict}: {}; mean {:.4}° ± {:.4}° against the record's {:.4}° ± {:.4}° ({:+.4}° ± \
         {:.4}°, {})",
        super::verify::decision_words(&decision),
        mean,
        u,
        against.mean_deg,
        against.mean_u_deg,
        change.diff_deg,
        change.u_deg,
        if change.significant {
            "a significant change"
        } else {
            "no significant change"
        }
    );
    // A board whose calibration is not the record's is said first: the
    // comparison below is then of another calibration than the record's.
    let mut events = Vec::new();
    if board_stamp != against.stamp {
        events.push(format!(
            "{} the board carries stamp {}, the record stamped {}: its calibration changed \
             since that record, the comparison is with another calibration",
            utc_now(),
            board_stamp.as_deref().unwrap_or("none"),
            against.stamp.as_deref().unwrap_or("none")
        ));
    }
    events.push(format!("{} perpend cell check: {reason}", utc_now()));
    Ok(CheckRecord {
        schema: interim::SCHEMA.into(),
        utc: utc_now(),
        tool_version: perpend_calib::record::tool_version(),
        head_serial: serial,
        firmware,
        board_stamp,
        inputs,
        against: Some(against),
        mean_deg: mean,
        mean_u_deg: u,
        decision,
        change: Some(change),
        verdict: verdict.into(),
        reason,
        events,
    })
}

/// `cell check` with its report: the record always, an error when the
/// board must be recalibrated.
///
/// # Errors
/// As [`run_check`]; `recalibrate now`.
pub fn run_and_report(a: &CheckArgs, cancel: &AtomicBool) -> Result<()> {
    let r = run_check(a, cancel)?;
    println!("check: record {} ({})", a.out.display(), r.verdict);
    for e in &r.events {
        println!("check: {}", e.split_once(' ').map_or(e.as_str(), |x| x.1));
    }
    if r.verdict == interim::verdict_words(perpend_formats::conformity::Verdict::Fail) {
        bail!(
            "{}: recalibrate now (perpend cell run); the record is {}",
            r.reason,
            a.out.display()
        );
    }
    Ok(())
}
