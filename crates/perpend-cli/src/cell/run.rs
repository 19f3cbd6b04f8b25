//! `perpend cell run` as a sequence of steps ([`run_cell`]): keep what the
//! board holds ([`super::session`]), the before pass, capture
//! ([`super::capture`]), calibrate ([`super::fit`]), push, the after pass
//! and the floor ([`super::figures`]), keep or revert ([`super::judge`]),
//! the record ([`super::record`]); then the report on the console and in
//! `DIR/cell.json`.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_calib::plan::PlannedPose;

use super::args::RunArgs;
use super::figures::{self, Figures};
use super::judge::{failed, judge, Outcome, Report};
use super::record::write_record;
use super::robot::{check_cancel, ManualCheck, Robot};
use super::robot::{install_ctrlc, CANCEL};
use super::session::Session;
use super::verify::{fresh_poses, read_plan, Reference};
use super::{capture, fit};
use crate::canopen::Nmt;
use crate::node::Node;

/// Before, capture, calibrate, push, after, floor: each step takes what
/// the one before left.
fn steps(
    s: &mut Session<'_>,
    robot: &mut Robot,
    plan: &[(i64, PlannedPose)],
    started: Instant,
) -> Result<Figures> {
    let a = s.args;
    // A board found operational takes no configuration writes.
    s.node.client.nmt(s.node.id, Nmt::Preop)?;
    let fresh = fresh_poses(plan, a.verify, a.seed());
    let before = s.before(robot, &fresh)?;
    let poses = capture::run(s, robot, plan)?;
    let fit = fit::run(&a.sensors, &poses, &a.out, s.reference.tolerance_deg)?;
    if let Some(t) = robot.turns() {
        super::frames::after_calibration(&a.sensors, &a.out, t, fit.expected_deg)?;
    }
    check_cancel(s.cancel, "the calibration")?;
    s.push_new(&fit.params)?;
    let after = s.after(robot, &fresh)?;
    figures::of(
        s,
        [&before, &after],
        &fit,
        [plan.len(), fresh.len()],
        started,
    )
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
        sim.turns = super::frames::Turns::new(super::frames::read_joints(&a.plan)?);
    }
    let mut node = Node::connect(&a.link)?;
    node.hello()?;
    let mut s = Session::begin(node, a, cancel, reference)?;
    if let Ok(f) = perpend_formats::paramfile::ParamFile::read(&s.previous) {
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
pub(super) fn run_and_report(x: &RunArgs) -> Result<()> {
    install_ctrlc();
    let report = match run_cell(x, &CANCEL) {
        Ok(r) => r,
        Err(e) => {
            // Nothing was changed on the board.
            if x.out.is_dir() {
                let v = serde_json::json!({
                    "utc": perpend_calib::record::utc_now(),
                    "tool_version": perpend_calib::record::tool_version(),
                    "outcome": perpend_calib::record::OUTCOME_FAILED_RESTORED,
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
    // --keep-worse: the operator chose to keep what is not shown good.
    let undecided = report
        .figures
        .as_ref()
        .map(|f| &f.decision)
        .filter(|d| d.verdict != perpend_formats::conformity::Verdict::Pass && !x.keep_worse);
    match report.outcome {
        // Applied (not worse than before) but not shown in tolerance: no
        // certificate, and a script reading the exit code must not take
        // it for a pass.
        Outcome::Applied if undecided.is_some() => Err(anyhow!(
            "the calibration is applied (not worse than before) but its verification is {}, \
             not PASS: no certificate ({}); {}",
            undecided.map_or("", |d| d.verdict.word()),
            json.with_file_name("report.html").display(),
            undecided
                .and_then(|d| d.decide_by.clone())
                .unwrap_or_else(|| "see the decision in record.json".into())
        )),
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
