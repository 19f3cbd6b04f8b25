//! Step 5 of a cell run: keep or revert ([`judge`]) by the decision and the
//! paired before/after change, or what a stopped run left ([`failed`]),
//! as a [`Report`] with its [`Outcome`] and first cause.

use std::path::PathBuf;

use perpend_formats::conformity::{coverage_factor, Verdict};

use super::figures::Figures;
use super::session::{PushStage, Session};
use super::verify::decision_words;

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
        use perpend_calib::record as r;
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

impl Report {
    /// cell.json: the figures (if any) and the outcome.
    pub fn json(&self) -> serde_json::Value {
        let mut v = match &self.figures {
            Some(f) => f.json(),
            None => serde_json::json!({ "before_deg": self.before_deg }),
        };
        if let Some(o) = v.as_object_mut() {
            o.insert("utc".into(), perpend_calib::record::utc_now().into());
            o.insert(
                "tool_version".into(),
                perpend_calib::record::tool_version().into(),
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

/// The mean of after − before over the fresh poses with both, and its
/// expanded uncertainty: the paired differences' scatter / √n times the
/// coverage factor of their n − 1 degrees of freedom (Student's t for
/// 95.45 %, JCGM 100:2008 Table G.2: 2.43 for 8 poses, 2 for many).
pub(super) fn paired_change(f: &Figures) -> Option<(f64, f64)> {
    let d: Vec<f64> = f
        .decision
        .poses
        .iter()
        .filter_map(|p| {
            let k = usize::try_from(p.pose - 1).ok()?;
            Some(p.error_deg - (*f.before_per_pose_deg.get(k)?)?)
        })
        .collect();
    let k = coverage_factor(d.len().saturating_sub(1) as f64);
    perpend_calib::interim::mean_u(&d).map(|(m, u)| (m, k * u))
}

/// Why the new calibration is not applied, if it is not: the after error
/// worse than the before error beyond the expanded uncertainty of their
/// difference (paired over the same fresh poses), or the decision FAIL.
pub(super) fn worse(f: &Figures) -> Option<String> {
    let change = paired_change(f);
    if let Some((diff, big_u)) = change.filter(|(d, big_u)| d > big_u) {
        Some(format!(
            "after {:.4}° is worse than before {:.4}° (mean over the fresh poses; the \
             difference {diff:+.4}° exceeds its expanded uncertainty {big_u:.4}°)",
            f.after_deg, f.before_deg,
        ))
    } else if f.decision.verdict == Verdict::Fail {
        Some(decision_words(&f.decision))
    } else {
        None
    }
}

/// The verdict on a run that got its figures, and the restore it needs.
pub(super) fn judge(s: &mut Session<'_>, f: Figures) -> Report {
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
                paired_change(&f).map_or(String::new(), |(d, big_u)| format!(
                    ", change {d:+.4}° ± {big_u:.4}° (U)"
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
pub(super) fn failed(s: &mut Session<'_>, e: &anyhow::Error) -> Report {
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
