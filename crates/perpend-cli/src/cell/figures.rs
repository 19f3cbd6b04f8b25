//! Steps 3-4 of a cell run: the figures of the before and after passes,
//! the floor (what a perfectly calibrated board would show at the same
//! fresh poses, from the true head or the calibrated one, with the reading
//! noise the captures measured) and the decision, as [`Figures`].

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use perpend_core::head::Head4;
use perpend_formats::conformity::Decision;

use super::args::RunArgs;
use super::fit::Fit;
use super::session::Session;
use super::verify::{floor, head4, Verified};

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

/// The pooled reading noise of the captures [mm, 1σ], 0 if none recorded.
fn pooled_sigma(poses: &Path) -> Result<f64> {
    let t = perpend_formats::exchange::read_poses(poses, None)?;
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
            let t = perpend_formats::exchange::read_sensors(p)?;
            Ok((
                head4(t.sensors()?, &p.display().to_string())?,
                "truth".into(),
            ))
        }
        None => {
            let f = perpend_formats::paramfile::ParamFile::read(params)?;
            let what = params.display().to_string();
            Ok((head4(f.sensors()?, &what)?, "calibrated".into()))
        }
    }
}

/// The figures of a run that got through the after pass: before and
/// after at the same fresh poses, the floor at the after pass's planes
/// with the reading noise the captures measured, the expected error and
/// the decision.
///
/// # Errors
/// The captures or the heads cannot be read.
pub fn of(
    s: &Session<'_>,
    passes: [&Verified; 2],
    fit: &Fit,
    [plan, fresh]: [usize; 2],
    started: Instant,
) -> Result<Figures> {
    let a = s.args;
    let [before, after] = passes;
    let sigma = pooled_sigma(&a.out.join("poses.csv"))?;
    let (head, from) = floor_head(a, &fit.params)?;
    let floor = floor(&head, &after.seen(), sigma, a.m.verify_samples, a.seed())?;
    Ok(Figures {
        before_deg: before.mean_deg(),
        after_deg: after.mean_deg(),
        floor_deg: floor,
        ratio: after.mean_deg() / floor,
        floor_head: from,
        sigma_mm: sigma,
        poses: plan,
        verify_poses: fresh,
        verify_samples: a.m.verify_samples,
        expected_deg: fit.expected_deg,
        seconds: started.elapsed().as_secs_f64(),
        expected_p95_deg: fit.expected_p95_deg,
        decision: s.reference.decide(after),
        before_per_pose_deg: before.poses.iter().map(|p| p.error_deg).collect(),
    })
}
