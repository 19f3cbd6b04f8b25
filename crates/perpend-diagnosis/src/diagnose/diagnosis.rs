//! The output of the pass of `perpend diagnose`: the outputs of its stages
//! side by side, in the order the data move (docs/diagnosis.md, "How the
//! code is laid out"). The report ([`super::report`]), the plots,
//! `--json` and `--out` read it; none of them refits.
//!
//! Input: the outputs of stages 1-7; output: `Diagnosis`. Holds no
//! computation of its own but the names of the effects and their time
//! constants, read from the decision and the loaded run.

use super::checks::Checks;
use super::decision::{named, Decided};
use super::fits::Fitted;
use super::limits::Limits;
use super::load::Loaded;
use super::scores::Scores;
use perpend_calib::candidates::Effect;

/// Everything a diagnosis found: the output of each stage, in the order
/// the data move. The report, the plots, `--json` and `--out` read it;
/// none of them refits.
#[derive(Debug, Clone)]
pub struct Diagnosis {
    /// Stage 1, read and check: the head, the poses kept (re-timed with
    /// the time constants of [`perpend_calib::lags`]), the outliers left out, the
    /// folds, the term references and the candidates skipped with the
    /// reason.
    pub run: Loaded,
    /// Stages 2-3, the nominal and candidate fits: the measured
    /// [`super::expect::Analysis`] and the candidates fitted outside their
    /// physical bounds.
    pub fits: Fitted,
    /// Stages 4-5, noise, held-out scores against their nulls and the
    /// decision: the noise, the effect-free expectation, the
    /// [`super::select::Decision`], the effects named, the direction test
    /// and the named model fitted on all poses.
    pub decided: Decided,
    /// Stage 6, held-out scores of the verdict.
    pub scores: Scores,
    /// Stage 7, the comparisons of the measured run with the simulation
    /// and the warnings for the user.
    pub checked: Checks,
    /// Stage 7b, with a `none`: each candidate's detection limit
    /// ([`super::limits`]).
    pub limits: Limits,
}

impl Diagnosis {
    /// Every effect named, in the order selected (empty for `none` and
    /// `unexplained`).
    pub fn effects(&self) -> Vec<Effect> {
        named(self.decided.effect, &self.decided.also)
    }

    /// The nested test of effect `e` as it was selected (the first's
    /// verdict, or the forward step's), when one of its sets passed:
    /// the sensors it acts on ([`super::select::NestedTest::acts_on`]).
    pub fn acts_on(&self, e: Effect) -> Option<&super::select::NestedTest> {
        let first = self
            .decided
            .decision
            .verdicts
            .iter()
            .find(|v| v.effect == e && self.decided.decision.winner == Some(e));
        let step = self.decided.also.iter().find(|st| st.effect == e);
        step.map(|st| &st.verdict)
            .or(first)?
            .nested
            .as_ref()
            .filter(|n| n.significant)
    }

    /// The fitted time constant of `e` [s]
    /// ([`super::EffectJson::time_constant_s`]).
    pub fn time_constant(&self, e: Effect) -> Option<f64> {
        match e {
            Effect::Thermal => Some(self.run.lags.thermal_tau_s).filter(|t| *t > 0.0),
            Effect::Drift => Some(self.run.lags.drift_tau_s).filter(|t| t.is_finite()),
            _ => None,
        }
    }
}
