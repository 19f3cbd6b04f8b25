//! The frame errors of a calibration run as the cell reports and records
//! them (issue 36): each with its 1σ in µrad / µm, whether the poses
//! resolve it, and warnings that name the frame and the fix.
//!
//! Rules: a resolved error is **significant** when it exceeds 2σ; a
//! significant one whose effect on the normal (the angle itself for
//! tilts) exceeds the calibration's expected normal error is a warning
//! (tracker: re-register the tracker against the robot base; the head was
//! calibrated against the corrected planes). An unresolved tracker tilt is
//! a warning to turn the head about the spindle axis. The TCP tilt and
//! offset are never identifiable from plane readings ([`super`]): a note
//! ([`TCP_NOTE`]) says how to check them.

use serde::{Deserialize, Serialize};

use super::{is_angle, FrameFit, FRAME_NAMES, N_FRAME};

/// One frame error as recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameEstimate {
    /// Which frame error (`tracker tilt x`, …).
    pub name: String,
    /// `µrad` or `µm`.
    pub unit: String,
    /// Estimate (`null`: not estimated).
    pub value: Option<f64>,
    /// 1σ (`null`: not identifiable with these poses).
    pub sigma: Option<f64>,
    /// Identifiable and 1σ within the resolution limit.
    pub resolved: bool,
    /// Resolved and beyond 2σ.
    pub significant: bool,
}

/// The frame errors of a run (the record's optional `frames`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameEstimates {
    /// Joint angles about the spindle axis the run used [deg].
    pub joint_angles_deg: Vec<f64>,
    /// Rank and parameter count of the joint Jacobian.
    pub rank: usize,
    /// Parameters (5 per sensor + 6).
    pub params: usize,
    /// Condition number of its identifiable part.
    pub condition: f64,
    /// Per frame error.
    pub errors: Vec<FrameEstimate>,
    /// Warnings (frame and fix).
    pub warnings: Vec<String>,
}

/// The record of `fit` from poses at `joints` (deg), with warnings against
/// the calibration's `expected_deg` normal error.
pub fn summarise(fit: &FrameFit, joints: &[f64], expected_deg: f64) -> FrameEstimates {
    let mut angles: Vec<f64> = Vec::new();
    for j in joints {
        if !angles.iter().any(|a| (a - j).abs() < 1e-6) {
            angles.push(*j);
        }
    }
    let errors: Vec<FrameEstimate> = (0..N_FRAME)
        .map(|j| {
            let k = if is_angle(j) { 1e6 } else { 1e3 };
            let value = fit.sigma[j].map(|_| k * fit.frames[j]);
            let sigma = fit.sigma[j].or(fit.ident.frames[j].sigma).map(|s| k * s);
            let resolved = fit.sigma[j].is_some();
            FrameEstimate {
                name: FRAME_NAMES[j].into(),
                unit: if is_angle(j) { "µrad" } else { "µm" }.into(),
                value,
                sigma,
                resolved,
                significant: resolved && value.zip(sigma).is_some_and(|(v, s)| v.abs() > 2.0 * s),
            }
        })
        .collect();
    let warnings = warnings(&errors, expected_deg, angles.len() > 1, joints.len());
    FrameEstimates {
        joint_angles_deg: angles,
        rank: fit.ident.rank,
        params: fit.ident.params,
        condition: fit.ident.condition,
        errors,
        warnings,
    }
}

/// The warnings of `errors`; `turned`: the run used more than one joint
/// angle (then an unresolved tilt needs more poses or less noise, not a
/// turn), `poses`: how many.
pub(crate) fn warnings(
    errors: &[FrameEstimate],
    expected_deg: f64,
    turned: bool,
    poses: usize,
) -> Vec<String> {
    let mut w = Vec::new();
    for e in errors.iter().take(2) {
        let deg = e.value.map_or(0.0, |v| (v * 1e-6).to_degrees());
        if e.significant && deg.abs() > expected_deg {
            w.push(format!(
                "{} = {:.0} ± {:.0} µrad ({deg:.4}°) is above the calibration's expected normal error ({expected_deg:.4}°): the tracker's frame is off against the robot base: re-register the tracker (the head was calibrated against the corrected planes)",
                e.name,
                e.value.unwrap_or(0.0),
                e.sigma.unwrap_or(0.0)
            ));
        }
        if !e.resolved && turned {
            w.push(unresolved_turned(e, poses));
        } else if !e.resolved {
            w.push(format!(
                "{} is not resolved by these poses (1σ {}): a tracker tilt would be absorbed by the head: turn the head about the spindle axis (perpend plan --reversal 4)",
                e.name,
                e.sigma.map_or("unbounded".into(), |s| format!("{s:.0} µrad"))
            ));
        }
    }
    w
}

/// An unresolved tracker tilt of a run that did turn the head: 1σ falls as
/// noise/√poses, so the poses it would take at this noise.
fn unresolved_turned(e: &FrameEstimate, poses: usize) -> String {
    let limit = super::RESOLVE_RAD * 1e6;
    match e.sigma {
        Some(s) => {
            let need = (poses as f64 * (s / limit).powi(2)).ceil();
            format!(
                "{} is not resolved although the head turned (1σ {s:.0} µrad, resolved below {limit:.0}): the noise of readings and tracker is too large for {poses} poses: about {need:.0} poses at this noise, or a quieter tracker; a tilt of that size is absorbed by the head meanwhile",
                e.name
            )
        }
        None => format!(
            "{} is not identifiable from these poses although the head turned: turn it to at least 3 angles spread over 180° or more (perpend plan --reversal 4)",
            e.name
        ),
    }
}

/// What no plane reading can tell (printed under every frame report).
pub const TCP_NOTE: &str = "TCP tilt and offset are not identifiable from plane readings (the head turns with them): if the drilled holes lean, re-teach the TCP and check it with a spindle-held target traced over the reversal";

/// The report as text lines.
pub fn lines(f: &FrameEstimates) -> Vec<String> {
    let mut out = vec![format!(
        "frames: joint angles {:?}°, rank {}/{}, condition {:.0}",
        f.joint_angles_deg, f.rank, f.params, f.condition
    )];
    for e in &f.errors {
        let v = match (e.value, e.sigma) {
            (Some(v), Some(s)) => format!("{v:.1} ± {s:.1} {}", e.unit),
            (None, Some(s)) => format!("not estimated (1σ would be {s:.1} {})", e.unit),
            _ => "not identifiable".into(),
        };
        let state = match (e.resolved, e.significant) {
            (true, true) => "resolved, significant",
            (true, false) => "resolved, within 2σ of 0",
            _ => "not resolved",
        };
        out.push(format!("  {:<15} {v} ({state})", e.name));
    }
    out.extend(f.warnings.iter().map(|w| format!("warning: {w}")));
    out.push(format!("note: {TCP_NOTE}"));
    out
}
