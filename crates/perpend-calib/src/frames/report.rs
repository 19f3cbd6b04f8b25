//! The frame errors of a calibration run as the cell reports and records
//! them (issues 36, 46): each identifiable one as estimate ± 1σ in µrad /
//! µm whatever its precision, whether it is significant and whether the
//! precision is good enough for the calibration, and warnings that name
//! the frame and the fix.
//!
//! Rules ([`super::estimate`] decides the first three):
//!
//! * **significant**: |estimate| > 2σ ([`super::SIGNIFICANT_Z`]);
//! * **resolved**: 1σ ≤ half the calibration's expected normal error
//!   ([`super::RESOLVE_SHARE`]; 30 µrad when that error is not given). It
//!   describes the precision and never withholds the value;
//! * the head is corrected for every frame error that is resolved or
//!   beyond 3σ ([`super::CORRECT_Z`]);
//! * a significant tracker tilt whose angle exceeds the calibration's
//!   expected normal error is a **warning** with the fix, at any noise:
//!   re-register the tracker against the robot base (the head was
//!   calibrated against the corrected planes);
//! * a tracker tilt neither significant nor resolved is a warning saying
//!   what would resolve it: more poses at this noise (1σ falls as
//!   1/√poses), or turning the head about the spindle axis if it did not
//!   turn; a tilt below 2σ is absorbed by the head meanwhile.
//!
//! The TCP tilt and offset are never identifiable from plane readings
//! ([`super`]): a note ([`TCP_NOTE`]) says how to check them.

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
    /// Estimate (`null`: not identifiable with these poses; records
    /// before issue 46 also wrote `null` for an unresolved one).
    pub value: Option<f64>,
    /// 1σ (`null`: not identifiable with these poses).
    pub sigma: Option<f64>,
    /// Estimated and 1σ within the calibration's tolerance (module header).
    pub resolved: bool,
    /// Estimated and beyond 2σ (before issue 46: resolved and beyond 2σ).
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
/// the calibration's `expected_deg` normal error (infinite: not known, no
/// warning of size).
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
            FrameEstimate {
                name: FRAME_NAMES[j].into(),
                unit: if is_angle(j) { "µrad" } else { "µm" }.into(),
                value: fit.sigma[j].map(|_| k * fit.frames[j]),
                sigma: fit.sigma[j].or(fit.ident.frames[j].sigma).map(|s| k * s),
                resolved: fit.resolved[j],
                significant: fit.significant[j],
            }
        })
        .collect();
    let advice = Advice {
        expected_deg,
        limit_urad: 1e6 * fit.tolerance.angle_rad,
        turned: angles.len() > 1,
        poses: joints.len(),
        corrected: [fit.corrected[0], fit.corrected[1]],
    };
    let warnings = warnings(&errors, &advice);
    FrameEstimates {
        joint_angles_deg: angles,
        rank: fit.ident.rank,
        params: fit.ident.params,
        condition: fit.ident.condition,
        errors,
        warnings,
    }
}

/// What the warnings are weighed against.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Advice {
    /// The calibration's expected normal error [deg] (infinite: not known).
    pub expected_deg: f64,
    /// 1σ [µrad] up to which a tilt is resolved.
    pub limit_urad: f64,
    /// The run used more than one joint angle (then an unresolved tilt
    /// needs more poses or less noise, not a turn).
    pub turned: bool,
    /// Poses of the run.
    pub poses: usize,
    /// Whether the head was corrected for the tracker tilt x, y.
    pub corrected: [bool; 2],
}

/// The warnings of the tracker tilts of `errors` (module header).
pub(crate) fn warnings(errors: &[FrameEstimate], a: &Advice) -> Vec<String> {
    let mut w = Vec::new();
    for (e, &corrected) in errors.iter().zip(&a.corrected) {
        let deg = e.value.map_or(0.0, |v| (v * 1e-6).to_degrees());
        if e.significant && deg.abs() > a.expected_deg {
            let (v, s) = (e.value.unwrap_or(0.0), e.sigma.unwrap_or(0.0));
            let head = if corrected {
                "the head was calibrated against the corrected planes"
            } else {
                "the head is not corrected for it: below 3σ the correction would add about its 1σ to every normal"
            };
            w.push(format!(
                "{} = {v:.0} ± {s:.0} µrad ({deg:.4}°, {:.1}σ) is above the calibration's expected normal error ({:.4}°): the tracker's frame is off against the robot base: re-register the tracker ({head})",
                e.name,
                v.abs() / s.max(f64::MIN_POSITIVE),
                a.expected_deg
            ));
        } else if !e.resolved && !e.significant {
            w.push(if a.turned {
                unresolved_turned(e, a)
            } else {
                unresolved_still(e)
            });
        }
    }
    w
}

/// The estimate as text: `v ± s µrad` (or that there is none).
fn value_text(e: &FrameEstimate) -> String {
    match (e.value, e.sigma) {
        (Some(v), Some(s)) => format!("{v:.0} ± {s:.0} µrad"),
        (None, Some(s)) => format!("not estimated (1σ {s:.0} µrad)"),
        _ => "not identifiable".into(),
    }
}

/// An unresolved tracker tilt of a run that did not turn the head.
fn unresolved_still(e: &FrameEstimate) -> String {
    format!(
        "{} is not resolved by these poses ({}): a tracker tilt below 2σ is absorbed by the head: turn the head about the spindle axis (perpend plan --reversal 4)",
        e.name,
        value_text(e)
    )
}

/// An unresolved tracker tilt of a run that did turn the head: 1σ falls as
/// noise/√poses, so the poses it would take at this noise.
fn unresolved_turned(e: &FrameEstimate, a: &Advice) -> String {
    let limit = a.limit_urad;
    match e.sigma {
        Some(s) => {
            let need = (a.poses as f64 * (s / limit).powi(2)).ceil();
            format!(
                "{} = {} is within 2σ of 0 but not resolved although the head turned (resolved at 1σ ≤ {limit:.0} µrad): the noise is too large for {} poses: about {need:.0} poses at this noise, or a quieter tracker, would resolve it; a tilt below 2σ ({:.0} µrad) is absorbed by the head meanwhile",
                e.name,
                value_text(e),
                a.poses,
                2.0 * s
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
            (None, Some(s)) => format!("not estimated (1σ {s:.1} {})", e.unit),
            _ => "not identifiable".into(),
        };
        let precision = if e.resolved {
            "resolved"
        } else {
            "not resolved"
        };
        let state = match (e.value.is_some(), e.significant) {
            (false, _) => precision.to_string(),
            (true, true) => format!("{precision}, significant"),
            (true, false) => format!("{precision}, within 2σ of 0"),
        };
        out.push(format!("  {:<15} {v} ({state})", e.name));
    }
    out.extend(f.warnings.iter().map(|w| format!("warning: {w}")));
    out.push(format!("note: {TCP_NOTE}"));
    out
}
