//! Which effect to name: held-out prediction error with a parsimony rule,
//! judged against the simulated noise floor.
//!
//! For every candidate `c` the per-pose held-out losses
//! `L(k) = Σ_i e_ki²` of the base model and of `c` are paired
//! (`D_k = L_base(k) − L_c(k)`), and the candidate's gain is tested with the
//! paired z statistic `z_c = mean(D) / (sd(D)/√K)` (K poses): the
//! fold-to-fold and pose-to-pose spread of the gain sets the scale, and the
//! held-out error already charges each extra parameter its over-fitting
//! cost. A candidate **clearly beats the base model** when
//!
//! 1. `z_c > z*` **or** the Wilcoxon signed-rank z of the same `D_k`
//!    exceeds `z*`, the one-sided normal quantile at the family level `α`
//!    split over the `2m` tests of the `m` candidates (Bonferroni,
//!    `z* = Φ⁻¹(1 − α/2m)`), so that on data without an effect all
//!    candidates together are named wrongly with probability ≤ `α`. The
//!    mean test has the power when a few poses carry the effect; the rank
//!    test when the base model fails badly on a few poses and the squared
//!    losses are too heavy-tailed for the mean; and
//! 2. the held-out mean square error drops by at least `ε = 2%` of the
//!    simulated noise floor's (an effect below that changes nothing a user
//!    can measure).
//!
//! Among the candidates that clearly beat the base model the one with the
//! lowest held-out error wins, unless one with fewer parameters is within
//! one standard error of it (the one-standard-error rule: prefer the
//! simpler model when the data cannot tell them apart).
//!
//! The winner **explains** the data when its held-out RMS is not clearly
//! above what the simulation predicts for that model on effect-free data:
//! `rms_c ≤ μ_c + t·s_c`, with `μ_c, s_c` the mean and predictive spread
//! of the model's held-out RMS over the Monte-Carlo draws and `t` the
//! Student-t quantile at level `α` with `draws − 1` degrees of freedom. The
//! same test on the base model says whether the residuals are **above
//! expectation** at all. The verdict:
//!
//! * a winner that explains the data → its name;
//! * a winner that does not, or no winner while the base model is above
//!   expectation → `unexplained`;
//! * otherwise → `none`.

use super::candidates::Effect;
use super::cv::CvResult;
use super::expect::{Analysis, Expectation, Spread};
use super::stats;

/// Decision thresholds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rule {
    /// Family-wise false-naming level α.
    pub alpha: f64,
    /// Smallest relative drop of the held-out mean square error, in units
    /// of the simulated floor's mean square.
    pub min_gain: f64,
}

impl Default for Rule {
    fn default() -> Self {
        Self {
            alpha: 0.01,
            min_gain: 0.02,
        }
    }
}

/// The evaluation of one candidate.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    /// The candidate.
    pub effect: Effect,
    /// Held-out RMS [mm].
    pub rms: f64,
    /// Parameters of the whole head (5 per sensor + the extension's).
    pub n_params: usize,
    /// Paired z of its gain over the base model (mean of `D_k`).
    pub z: f64,
    /// Wilcoxon signed-rank z of the same differences.
    pub z_rank: f64,
    /// Drop of the held-out mean square error [mm²].
    pub gain_mse: f64,
    /// Whether it clearly beats the base model.
    pub beats_base: bool,
    /// Simulated held-out RMS of this model on effect-free data.
    pub expected: Spread,
}

/// The outcome of the selection.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// The name given.
    pub effect: Effect,
    /// The best candidate that clearly beats the base model, if any (for
    /// `unexplained`: the one that explains part of the excess).
    pub winner: Option<Effect>,
    /// Candidates indistinguishable from the winner (within one standard
    /// error, same parameter count).
    pub ties: Vec<Effect>,
    /// Every candidate's evaluation (base first).
    pub verdicts: Vec<Verdict>,
    /// z of the base model's held-out RMS against its expectation.
    pub base_excess_z: f64,
    /// Whether the base model's residuals are above expectation.
    pub above: bool,
    /// Threshold on the candidates' z.
    pub z_star: f64,
    /// Threshold (t quantile) on the RMS excess.
    pub t_star: f64,
    /// The family level α used.
    pub alpha: f64,
    /// Fraction of the base model's excess mean square over the floor that
    /// the winner removes (0..1; for a named effect close to 1).
    pub explained_fraction: Option<f64>,
    /// Reasons, in words.
    pub reasons: Vec<String>,
}

/// Wilcoxon signed-rank z of the per-pose loss differences `base − cand`.
pub fn paired_rank(base: &CvResult, cand: &CvResult) -> f64 {
    let d: Vec<f64> = base
        .pose_loss
        .iter()
        .zip(&cand.pose_loss)
        .map(|(a, b)| a - b)
        .collect();
    stats::signed_rank_z(&d)
}

/// Paired comparison of two models' per-pose held-out losses: returns
/// `(mean gain per reading [mm²], z, standard error of the mean gain per
/// pose)`.
pub fn paired(base: &CvResult, cand: &CvResult) -> (f64, f64, f64) {
    let d: Vec<f64> = base
        .pose_loss
        .iter()
        .zip(&cand.pose_loss)
        .map(|(a, b)| a - b)
        .collect();
    let k = d.len().max(1) as f64;
    let m = stats::mean(&d);
    let se = stats::sd(&d) / k.sqrt();
    let z = if se > 0.0 { m / se } else { 0.0 };
    (d.iter().sum::<f64>() / base.n.max(1) as f64, z, se)
}

/// Floor of the predictive spread of an RMS over `n` readings
/// (`rms/√(2n)`: independent Gaussian residuals).
fn rms_floor(mean: f64, n: usize) -> f64 {
    mean / (2.0 * n.max(1) as f64).sqrt()
}

/// Decides.
pub fn decide(measured: &Analysis, exp: &Expectation, n_sensors: usize, rule: &Rule) -> Decision {
    let mut reasons = Vec::new();
    let base = measured.cv_of(Effect::None);
    let draws = exp.draws.max(2);
    let t_star = stats::t_quantile(1.0 - rule.alpha, (draws - 1) as f64);
    let base_exp = exp.rms_of(Effect::None).unwrap_or_default();
    let (base_rms, base_n) = base.map_or((0.0, 0), |b| (b.rms, b.n));
    let s0 = base_exp.predictive_sd(rms_floor(base_exp.mean, base_n));
    let base_excess_z = if s0 > 0.0 {
        (base_rms - base_exp.mean) / s0
    } else {
        0.0
    };
    let above = base_excess_z > t_star;
    let cands: Vec<&CvResult> = measured
        .cv
        .iter()
        .filter(|(e, _)| *e != Effect::None)
        .filter_map(|(_, r)| r.as_ref().ok())
        .collect();
    let m = cands.len().max(1);
    let z_star = stats::normal_quantile(1.0 - rule.alpha / (2 * m) as f64);
    let floor_ms = base_exp.mean * base_exp.mean;
    let mut verdicts = Vec::new();
    if let Some(b) = base {
        verdicts.push(Verdict {
            effect: Effect::None,
            rms: b.rms,
            n_params: 5 * n_sensors,
            z: 0.0,
            z_rank: 0.0,
            gain_mse: 0.0,
            beats_base: false,
            expected: base_exp,
        });
    }
    for c in &cands {
        let (gain, z, _) = base.map_or((0.0, 0.0, 0.0), |b| paired(b, c));
        let z_rank = base.map_or(0.0, |b| paired_rank(b, c));
        let beats = (z > z_star || z_rank > z_star) && gain >= rule.min_gain * floor_ms;
        verdicts.push(Verdict {
            effect: c.effect,
            rms: c.rms,
            n_params: (5 + c.effect.terms().len()) * n_sensors,
            z,
            z_rank,
            gain_mse: gain,
            beats_base: beats,
            expected: exp.rms_of(c.effect).unwrap_or_default(),
        });
    }
    // Best among those that beat the base model, then the 1-SE rule.
    let winners: Vec<&Verdict> = verdicts.iter().filter(|v| v.beats_base).collect();
    let best = winners
        .iter()
        .min_by(|a, b| a.rms.total_cmp(&b.rms))
        .copied();
    let mut ties = Vec::new();
    let winner = best.map(|b| {
        let cv_of = |e: Effect| cands.iter().find(|c| c.effect == e).copied();
        let simpler = winners
            .iter()
            .filter(|v| v.n_params < b.n_params)
            .filter(|v| match (cv_of(v.effect), cv_of(b.effect)) {
                (Some(cv), Some(cb)) => {
                    // g: how much worse v is than b per reading; within
                    // one standard error?
                    let (g, _, se) = paired(cv, cb);
                    let se_per_reading = se * cv.pose_loss.len() as f64 / cv.n.max(1) as f64;
                    g <= se_per_reading
                }
                _ => false,
            })
            .min_by(|a, b| a.rms.total_cmp(&b.rms));
        let chosen = simpler.copied().unwrap_or(b);
        if !std::ptr::eq(chosen, b) {
            reasons.push(format!(
                "{} ({} parameters) is within one standard error of {} ({} parameters): the simpler model is named",
                chosen.effect.name(),
                chosen.n_params,
                b.effect.name(),
                b.n_params
            ));
        }
        for v in &winners {
            if v.effect == chosen.effect || v.n_params != chosen.n_params {
                continue;
            }
            if let (Some(cv), Some(cc)) = (cv_of(v.effect), cv_of(chosen.effect)) {
                let (g, _, se) = paired(cv, cc);
                let se_per_reading = se * cv.pose_loss.len() as f64 / cv.n.max(1) as f64;
                if g <= se_per_reading {
                    ties.push(v.effect);
                }
            }
        }
        chosen.clone()
    });
    let mut explained_fraction = None;
    let effect = match &winner {
        Some(w) => {
            let sc = w.expected.predictive_sd(rms_floor(w.expected.mean, base_n));
            let excess_z = if sc > 0.0 {
                (w.rms - w.expected.mean) / sc
            } else {
                0.0
            };
            let ex0 = base_rms * base_rms - floor_ms;
            if ex0 > 0.0 {
                explained_fraction =
                    Some(((base_rms * base_rms - w.rms * w.rms) / ex0).clamp(0.0, 1.0));
            }
            reasons.push(format!(
                "{} beats the base model: held-out RMS {:.4} → {:.4} mm, paired z = {:.1}, signed-rank z = {:.1} (threshold {:.2})",
                w.effect.name(),
                base_rms,
                w.rms,
                w.z,
                w.z_rank,
                z_star
            ));
            if excess_z > t_star {
                reasons.push(format!(
                    "but its held-out RMS {:.4} mm stays above the simulated {:.4} ± {:.4} mm (z = {:.1} > {:.2}): it explains only part of the excess",
                    w.rms, w.expected.mean, sc, excess_z, t_star
                ));
                Effect::Unexplained
            } else {
                reasons.push(format!(
                    "with it the held-out RMS {:.4} mm matches the simulated {:.4} ± {:.4} mm (z = {:.1})",
                    w.rms, w.expected.mean, sc, excess_z
                ));
                w.effect
            }
        }
        None if above => {
            reasons.push(format!(
                "the base model's held-out RMS {:.4} mm is above the simulated {:.4} ± {:.4} mm (z = {:.1} > {:.2}) and no candidate beats it clearly (z* = {:.2})",
                base_rms, base_exp.mean, s0, base_excess_z, t_star, z_star
            ));
            Effect::Unexplained
        }
        None => {
            reasons.push(format!(
                "the base model's held-out RMS {:.4} mm is consistent with the simulated {:.4} ± {:.4} mm (z = {:.1}) and no candidate beats it clearly (z* = {:.2})",
                base_rms, base_exp.mean, s0, base_excess_z, z_star
            ));
            Effect::None
        }
    };
    Decision {
        effect,
        winner: winner.map(|w| w.effect),
        ties,
        verdicts,
        base_excess_z,
        above,
        z_star,
        t_star,
        alpha: rule.alpha,
        explained_fraction,
        reasons,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::diagnose::expect::{Analysis, Expectation, Spread};

    fn cv(effect: Effect, losses: &[f64]) -> CvResult {
        let n = losses.len() * 4;
        let rms = (losses.iter().sum::<f64>() / n as f64).sqrt();
        CvResult {
            effect,
            resid: vec![vec![None; 4]; losses.len()],
            heads: vec![],
            rms,
            rms_sensor: vec![rms; 4],
            pose_loss: losses.to_vec(),
            n,
        }
    }

    fn analysis(cvs: Vec<CvResult>) -> Analysis {
        Analysis {
            cv: cvs.into_iter().map(|c| (c.effect, Ok(c))).collect(),
            base_fit: vec![],
            insample: vec![],
            lag1: (0.0, 0),
            runs_z: 0.0,
            r2: vec![],
            base_normal: vec![],
        }
    }

    fn expectation(models: &[(Effect, f64)]) -> Expectation {
        Expectation {
            draws: 8,
            rms: models
                .iter()
                .map(|&(e, m)| {
                    (
                        e,
                        Spread {
                            mean: m,
                            sd: 0.02 * m,
                            n: 8,
                        },
                    )
                })
                .collect(),
            ..Expectation::default()
        }
    }

    /// Per-pose losses around `level` (4 readings per pose), deterministic
    /// pseudo-noise.
    fn losses(level: f64, k: usize, seed: u64) -> Vec<f64> {
        (0..k)
            .map(|i| {
                let u = ((i as u64 * 2654435761 + seed * 97) % 1000) as f64 / 1000.0;
                4.0 * level * level * (0.5 + u)
            })
            .collect()
    }

    #[test]
    fn clean_data_is_none() {
        let base = cv(Effect::None, &losses(0.01, 100, 1));
        // a candidate that only over-fits: slightly worse everywhere
        let g: Vec<f64> = base.pose_loss.iter().map(|l| l * 1.01).collect();
        let a = analysis(vec![base.clone(), cv(Effect::Gain, &g)]);
        let e = expectation(&[(Effect::None, base.rms), (Effect::Gain, base.rms)]);
        let d = decide(&a, &e, 4, &Rule::default());
        assert_eq!(d.effect, Effect::None);
        assert!(!d.above);
        assert_eq!(d.verdicts.len(), 2);
        assert!(!d.verdicts[1].beats_base);
    }

    #[test]
    fn a_candidate_that_reaches_the_floor_is_named() {
        let floor = 0.01;
        let base = cv(Effect::None, &losses(0.02, 100, 1));
        let good = cv(Effect::Thermal, &losses(floor, 100, 2));
        let a = analysis(vec![base, good]);
        let e = expectation(&[(Effect::None, floor), (Effect::Thermal, floor)]);
        let d = decide(&a, &e, 4, &Rule::default());
        assert_eq!(d.effect, Effect::Thermal);
        assert!(d.above);
        assert!(d.verdicts[1].z > d.z_star);
        assert!(d.explained_fraction.unwrap() > 0.9);
    }

    #[test]
    fn a_partial_explanation_is_unexplained() {
        let floor = 0.01;
        let base = cv(Effect::None, &losses(0.03, 100, 1));
        let half = cv(Effect::Gain, &losses(0.02, 100, 2));
        let a = analysis(vec![base, half]);
        let e = expectation(&[(Effect::None, floor), (Effect::Gain, floor)]);
        let d = decide(&a, &e, 4, &Rule::default());
        assert_eq!(d.effect, Effect::Unexplained);
        assert_eq!(d.winner, Some(Effect::Gain));
    }

    #[test]
    fn excess_without_a_candidate_is_unexplained() {
        let floor = 0.01;
        let base = cv(Effect::None, &losses(0.02, 100, 1));
        let g: Vec<f64> = base.pose_loss.iter().map(|l| l * 1.01).collect();
        let a = analysis(vec![base, cv(Effect::Drift, &g)]);
        let e = expectation(&[(Effect::None, floor), (Effect::Drift, floor)]);
        let d = decide(&a, &e, 4, &Rule::default());
        assert_eq!(d.effect, Effect::Unexplained);
        assert_eq!(d.winner, None);
    }

    #[test]
    fn the_simpler_of_two_equal_models_is_named() {
        let floor = 0.01;
        let base = cv(Effect::None, &losses(0.02, 100, 1));
        let gain = cv(Effect::Gain, &losses(floor, 100, 2));
        // nonlinearity (more parameters) marginally better on average, by
        // far less than the pose-to-pose spread of the difference
        let nl: Vec<f64> = gain
            .pose_loss
            .iter()
            .enumerate()
            .map(|(i, l)| l * (0.999 + 0.05 * (i as f64 * 1.7).sin()))
            .collect();
        assert!(nl.iter().sum::<f64>() < gain.pose_loss.iter().sum::<f64>());
        let a = analysis(vec![base, gain, cv(Effect::Nonlinearity, &nl)]);
        let e = expectation(&[
            (Effect::None, floor),
            (Effect::Gain, floor),
            (Effect::Nonlinearity, floor),
        ]);
        let d = decide(&a, &e, 4, &Rule::default());
        assert_eq!(d.effect, Effect::Gain);
        assert_eq!(d.verdicts[2].n_params, 32);
    }
}
