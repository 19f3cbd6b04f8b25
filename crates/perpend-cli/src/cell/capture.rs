//! Step 2a of a cell run: every planned pose presented by the robot and
//! captured by the board (`perpend node capture`) into `DIR/poses.csv`;
//! a boot-up of the node in between stops the run (a reset board's poses
//! are not trusted).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Result};
use perpend_calib::plan::PlannedPose;

use super::robot::{abcd, check_cancel, Robot};
use super::session::Session;
use super::verify::{drain_saw_bootup, reset_error};
use crate::node::capture;

/// Captures every planned pose into `DIR/poses.csv` and returns its
/// path; a reset of the node in between (its boot-up message) stops it.
///
/// # Errors
/// Bus, robot, Ctrl-C, a reset of the node.
pub fn run(s: &mut Session<'_>, robot: &mut Robot, plan: &[(i64, PlannedPose)]) -> Result<PathBuf> {
    let a = s.args;
    let poses = a.out.join("poses.csv");
    let poses = poses.as_path();
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
    Ok(poses.to_path_buf())
}

/// `nothing was captured` or `K of N poses captured`.
fn captured(done: usize, of: usize) -> String {
    match done {
        0 => "nothing was captured".into(),
        k => format!("{k} of {of} poses captured"),
    }
}
