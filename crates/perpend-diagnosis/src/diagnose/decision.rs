//! Stages 4 and 5 of `perpend diagnose`, held-out scores against their
//! nulls and the decision: the noise estimated from the full model's
//! residuals ([`perpend_calib::noise`]), the effect-free re-simulations at that
//! noise ([`super::expect`]), the calibrated decision ([`super::select`]),
//! then the forward selection of further effects on top of the first
//! ([`Step`], at most [`MAX_EFFECTS`]).
//!
//! Input: the loaded run (`Loaded`) and the measured [`Analysis`] of
//! stages 2-3; output: the noise, the expectation, the [`Decision`] and the
//! effects named with their steps. Reads stages 0-3 only. Limits: a
//! forward step whose model the solver cannot fit ends the selection.

use anyhow::{anyhow, bail, Result};
use perpend_core::head::Sensor;

use super::direction::{self, DirectionTest, NullPlan};
use super::expect::{analyse, expect, Analysis, Expectation, NoiseModel, Plan};
use super::fits::{implausible_fits, Fitted};
use super::load::Loaded;
use super::nested::{self, Nested, NestedPlan};
use super::select::{self, decide, Decision};
use super::settings::{draws_for, Settings};
use perpend_calib::candidates::available_models;
use perpend_calib::candidates::{self, Effect, Refs, SensorFit};
use perpend_calib::cv;
use perpend_calib::lags;
use perpend_calib::noise::{self, NoiseEstimate};
use perpend_formats::exchange::PoseTable;

/// Most effects named together.
pub const MAX_EFFECTS: usize = 3;

/// Noise → expectation → decision, with the noise estimated from the
/// residuals of the full model fitted on all poses (of the paper's model
/// when not even one candidate fits).
#[allow(clippy::too_many_arguments)]
fn settle(
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    refs: &Refs,
    plan: &Plan,
    measured: &Analysis,
    declared: Option<Vec<f64>>,
    s: &Settings,
    implausible: &[Effect],
) -> Result<(NoiseEstimate, NoiseModel, Expectation, Decision)> {
    let (fits, resid) = noise::full_residuals(nominal, poses, refs, plan.models, &s.lsq)
        .unwrap_or_else(|| (measured.base_fit.clone(), measured.insample.clone()));
    let estimate = noise::estimate(nominal, poses, &fits, &resid, declared, s.tracker);
    let truth: Vec<Sensor<f64>> = measured.base_fit.iter().map(|f| f.sensor).collect();
    let noise = NoiseModel {
        sigma: estimate.reading_mm.clone(),
        tracker: estimate.tracker,
    };
    let draws = draws_for(poses.rows.len(), s.draws);
    let expected = expect(&truth, poses, &noise, plan, draws, s.seed);
    if expected.draws < 2 {
        bail!("the simulated expectation failed: the base model could not be fitted on the simulated runs");
    }
    let decision = decide(measured, &expected, nominal.len(), &s.rule, implausible);
    Ok((estimate, noise, expected, decision))
}

/// Stage "decision", second half: the effect named first, and the forward
/// selection on top of it. A winner that leaves structure may be one of
/// two effects: the forward selection looks for the other before
/// `unexplained` stands, and names both when it finds it (the reason is
/// added to `decision`).
///
/// # Errors
/// Those of [`forward`].
fn name_effects(
    decision: &mut Decision,
    l: &Loaded,
    f: &Fitted,
    noise: &NoiseModel,
    s: &Settings,
) -> Result<(Effect, Vec<Step>)> {
    let declared = l.declared.clone();
    let mut effect = decision.effect;
    let first = match (effect, decision.winner) {
        (Effect::Unexplained, Some(w)) => w,
        (e, _) => e,
    };
    let also = match first {
        Effect::None | Effect::Unexplained => {
            return Ok(time_pair(decision, l, f, noise, s)?.unwrap_or((effect, Vec::new())));
        }
        e => forward(e, l, declared, s)?,
    };
    if let (Effect::Unexplained, Some(st)) = (effect, also.last()) {
        decision.reasons.push(format!(
            "with {} added the residuals are explained: {} are named together",
            st.effect.name(),
            st.with
                .iter()
                .map(|e| e.name())
                .collect::<Vec<_>>()
                .join(" + ")
        ));
        effect = first;
    }
    Ok((effect, also))
}

/// Thermal and drift named together where neither alone beats the base
/// model (`decision` names nothing): on a run that separates them
/// ([`lags::separable`]) the two can cancel over the warm-up and show only
/// together. The pair is judged by the nested in-sample test against the
/// paper's model ([`nested`], at the decision's family level `α/m`), the
/// better of the two alone is then taken first and the other must be
/// named on top of it by the forward step, and the pair must lower the
/// held-out RMS of the paper's model. `None` otherwise.
///
/// # Errors
/// Those of [`next_step`].
fn time_pair(
    decision: &mut Decision,
    l: &Loaded,
    f: &Fitted,
    noise: &NoiseModel,
    s: &Settings,
) -> Result<Option<(Effect, Vec<Step>)>> {
    let cv = |e: Effect| f.measured.cv_of(e).map(|c| c.rms);
    let (Some(base), Some(th), Some(dr)) =
        (cv(Effect::None), cv(Effect::Thermal), cv(Effect::Drift))
    else {
        return Ok(None);
    };
    if decision.winner.is_some() || !lags::separable(&l.poses) {
        return Ok(None);
    }
    let (a, b) = if th <= dr {
        (Effect::Thermal, Effect::Drift)
    } else {
        (Effect::Drift, Effect::Thermal)
    };
    let truth: Vec<Sensor<f64>> = f.measured.base_fit.iter().map(|x| x.sensor).collect();
    let plan = NestedPlan {
        nominal: &l.nominal,
        refs: &l.refs,
        truth: &truth,
        noise,
        lsq: &s.lsq,
        seed: s.seed,
    };
    let m = decision.verdicts.len().saturating_sub(1).max(1);
    let Some(test) = nested::judge(&plan, &l.poses, &[a, b], s.rule.alpha / m as f64) else {
        return Ok(None);
    };
    if !test.found() {
        return Ok(None);
    }
    let Some(step) = next_step(&[a], l, &l.declared, s)? else {
        return Ok(None);
    };
    if step.effect != b || step.cv.rms >= base {
        return Ok(None);
    }
    decision.reasons.push(format!(
        "but {} and {} together explain the residuals where neither alone does (they cancel in part over the warm-up): in-sample p = {:.1e} against effect-free re-simulations (level {:.1e}), held-out RMS {base:.4} → {:.4} mm",
        a.name(),
        b.name(),
        test.p,
        test.level,
        step.cv.rms
    ));
    decision.effect = a;
    decision.winner = Some(a);
    Ok(Some((a, vec![step])))
}

/// A further effect of the forward selection: named by the same
/// calibrated decision as the first, with the effects before it added to
/// every model (the paper's model included) and the noise and the
/// effect-free re-simulations taken from that model.
#[derive(Debug, Clone)]
pub struct Step {
    /// The effect added.
    pub effect: Effect,
    /// Every effect selected up to and including this one.
    pub with: Vec<Effect>,
    /// Its evaluation against the model before it.
    pub verdict: select::Verdict,
    /// Held-out RMS of the model before it [mm].
    pub before_rms_mm: f64,
    /// Held-out cross-validation of the model with it.
    pub cv: cv::CvResult,
    /// All poses fitted with every effect up to this one.
    pub fits: Vec<SensorFit>,
    /// The nested in-sample test that named it, when the held-out test
    /// alone did not ([`nested`]: the time-like partner of a time-like
    /// effect).
    pub nested: Option<Nested>,
}

/// Forward selection after `first` was named (module docs): adds the
/// candidate that the calibrated decision names on top of the effects
/// selected so far ([`next_step`]), refits, repeats; stops when nothing
/// more is named or after [`MAX_EFFECTS`] effects.
///
/// # Errors
/// A winner without a verdict (an internal inconsistency).
fn forward(
    first: Effect,
    l: &Loaded,
    declared: Option<Vec<f64>>,
    s: &Settings,
) -> Result<Vec<Step>> {
    let mut with = vec![first];
    let mut steps = Vec::new();
    while with.len() < MAX_EFFECTS {
        let Some(step) = next_step(&with, l, &declared, s)? else {
            break;
        };
        with.push(step.effect);
        steps.push(step);
    }
    Ok(steps)
}

/// One round of [`forward`]: the candidates not yet selected (nor excluded
/// by one that is) decided on top of `with`, as the first effect was
/// (noise from the full model, effect-free re-simulations). `None` when
/// nothing more is named, or when a model the solver cannot fit on this
/// run (more terms than the pose set identifies) ends the selection: what
/// was named so far stands.
///
/// # Errors
/// A winner without a verdict (an internal inconsistency).
fn next_step(
    with: &[Effect],
    l: &Loaded,
    declared: &Option<Vec<f64>>,
    s: &Settings,
) -> Result<Option<Step>> {
    let (nominal, poses) = (&l.nominal, &l.poses);
    let r = Refs {
        extra: with.to_vec(),
        ..l.refs.clone()
    };
    let models: Vec<Effect> = available_models(poses)
        .into_iter()
        .filter(|e| !(with.contains(e) || with.iter().any(|w| e.excluded_by(*w))))
        .collect();
    if models.len() < 2 {
        return Ok(None);
    }
    let plan = Plan {
        nominal,
        refs: &r,
        folds: &l.folds,
        models: &models,
        lsq: &s.lsq,
        method: s.method,
    };
    let Ok(measured) = analyse(poses, &plan, false) else {
        return Ok(None);
    };
    let fitted: Vec<Effect> = measured
        .cv
        .iter()
        .filter(|(_, x)| x.is_ok())
        .map(|(e, _)| *e)
        .collect();
    let plan = Plan {
        models: &fitted,
        ..plan
    };
    let bad: Vec<Effect> = implausible_fits(nominal, poses, &r, &fitted, &s.lsq)
        .into_iter()
        .map(|(e, _)| e)
        .collect();
    let settled = settle(
        nominal,
        poses,
        &r,
        &plan,
        &measured,
        declared.clone(),
        s,
        &bad,
    );
    let Ok((_, noise, expected, d)) = settled else {
        return Ok(None);
    };
    let held_out = d
        .winner
        .filter(|w| d.effect == *w)
        .filter(|w| nested_on_top(*w, with, l, &measured, &expected, &d, s));
    let nested = match held_out {
        Some(_) => None,
        None => nested_partner(with, l, &r, &measured, &noise, &expected, &d, s),
    };
    let Some(e) = held_out.or(nested.as_ref().map(|n| n.effect)) else {
        return Ok(None);
    };
    let Some(cv) = measured.cv_of(e) else {
        return Ok(None);
    };
    let Ok(fits) = candidates::fit_all(nominal, poses, &r, e, &s.lsq) else {
        return Ok(None);
    };
    let mut with = with.to_vec();
    with.push(e);
    Ok(Some(Step {
        effect: e,
        with,
        verdict: d
            .verdicts
            .iter()
            .find(|v| v.effect == e)
            .cloned()
            .ok_or_else(|| anyhow!("no verdict"))?,
        before_rms_mm: measured.cv_of(Effect::None).map_or(0.0, |b| b.rms),
        cv: cv.clone(),
        fits,
        nested,
    }))
}

/// Whether winner `w` of a forward step may be named on top of `with`:
/// always when the held-out test named it; when only the nested test did
/// ([`select`], "Nested test"), after the forms of `with` passed their
/// lack-of-fit check ([`select::lack_of_fit`]: a settling drift fitted as
/// a line leaves curvature in time that a thermal term would take), and a
/// time-like partner of a time-like effect only on a run that separates
/// them ([`lags::separable`]).
fn nested_on_top(
    w: Effect,
    with: &[Effect],
    l: &Loaded,
    measured: &Analysis,
    expected: &Expectation,
    d: &Decision,
    s: &Settings,
) -> bool {
    let Some(v) = d.verdicts.iter().find(|v| v.effect == w) else {
        return false;
    };
    if v.residual {
        return true;
    }
    let time_pair = nested::partner(with) == Some(w);
    select::lack_of_fit(with, measured, expected, s.rule.alpha).is_none()
        && (!time_pair || lags::separable(&l.poses))
}

/// The time-like partner of a time-like effect in `with`, named by the
/// nested in-sample test ([`nested`]) when the held-out test of the step
/// (`d`) named nothing: on a run that separates thermal from drift
/// ([`lags::separable`]), with `p` below the step's family level and a
/// held-out gain (paired z above its effect-free mean, plausible
/// coefficients, lower held-out mean square).
#[allow(clippy::too_many_arguments)]
fn nested_partner(
    with: &[Effect],
    l: &Loaded,
    r: &Refs,
    measured: &Analysis,
    noise: &NoiseModel,
    expected: &Expectation,
    d: &Decision,
    s: &Settings,
) -> Option<Nested> {
    let c = nested::partner(with)?;
    let v = d.verdicts.iter().find(|v| v.effect == c)?;
    let null_mean = expected.gain_z_of(c).map_or(0.0, |z| z.mean);
    if !(lags::separable(&l.poses) && v.plausible && v.gain_mse > 0.0 && v.z > null_mean) {
        return None;
    }
    let truth: Vec<Sensor<f64>> = measured.base_fit.iter().map(|f| f.sensor).collect();
    let plan = NestedPlan {
        nominal: &l.nominal,
        refs: r,
        truth: &truth,
        noise,
        lsq: &s.lsq,
        seed: s.seed,
    };
    let m = d.verdicts.len().saturating_sub(1).max(1);
    nested::judge(&plan, &l.poses, &[c], s.rule.alpha / m as f64).filter(Nested::found)
}

/// The effects named: the verdict `effect` and those the forward
/// selection added (`also`); none for `none` and `unexplained`.
pub(super) fn named(effect: Effect, also: &[Step]) -> Vec<Effect> {
    match effect {
        Effect::None | Effect::Unexplained => Vec::new(),
        e => std::iter::once(e)
            .chain(also.iter().map(|st| st.effect))
            .collect(),
    }
}

/// The output of stages 4-5: the noise, the effect-free expectation and
/// the verdict with the effects named.
#[derive(Debug, Clone)]
pub struct Decided {
    /// The run's own noise.
    pub estimate: NoiseEstimate,
    /// The noise the expectation was simulated with.
    pub noise: NoiseModel,
    /// The effect-free re-simulations.
    pub expected: Expectation,
    /// The calibrated decision.
    pub decision: Decision,
    /// The name given.
    pub effect: Effect,
    /// Further effects selected on top of `effect`.
    pub also: Vec<Step>,
    /// Simulated held-out RMS of the paper's model on effect-free data at
    /// the noise from the full model (the floor reported) [mm].
    pub floor_mm: f64,
    /// The test for direction-dependent offsets ([`direction`]).
    pub direction: DirectionTest,
    /// The named effect (for `unexplained`, the partial winner) fitted on
    /// all poses, with coefficients and 1σ: what is reported and stored
    /// (`None` for `none`, or when it cannot be fitted on all poses).
    pub refit: Option<(Effect, Vec<SensorFit>)>,
}

/// Stages 4-5 on the fitted run: the noise from the full model (every
/// candidate at once: an effect not yet named is not counted as noise),
/// the decision ([`settle`]) and the forward selection ([`name_effects`]).
///
/// # Errors
/// Those of [`settle`] and [`name_effects`].
pub(super) fn decide_run(l: &Loaded, f: &Fitted, s: &Settings) -> Result<Decided> {
    // Models that failed on the measured data are not simulated either.
    let plan = l.plan(&f.fitted, s);
    let bad: Vec<Effect> = f.implausible.iter().map(|(e, _)| *e).collect();
    let (estimate, noise, expected, mut decision) = settle(
        &l.nominal,
        &l.poses,
        &l.refs,
        &plan,
        &f.measured,
        l.declared.clone(),
        s,
        &bad,
    )?;
    let (mut effect, also) = name_effects(&mut decision, l, f, &noise, s)?;
    let floor_mm = expected.rms_of(Effect::None).map_or(0.0, |x| x.mean);
    let direction = direction_test(l, f, &noise, s, decision.verdicts.len());
    if effect == Effect::None && direction.found() {
        // Nothing in the catalogue: the run is `unexplained`, nothing named.
        effect = Effect::Unexplained;
        decision.effect = Effect::Unexplained;
        decision.winner = None;
    }
    let refit = refit(effect, decision.winner, l, s);
    Ok(Decided {
        estimate,
        noise,
        expected,
        decision,
        effect,
        also,
        floor_mm,
        direction,
        refit,
    })
}

/// The effect named (or, for `unexplained`, the partial `winner`) fitted
/// on all poses: the coefficients reported and stored. `None` for `none`
/// or when the solver cannot fit it on all poses (the parameter file then
/// refuses, [`super::param_file`]).
fn refit(
    effect: Effect,
    winner: Option<Effect>,
    l: &Loaded,
    s: &Settings,
) -> Option<(Effect, Vec<SensorFit>)> {
    let model = match effect {
        Effect::None => None,
        Effect::Unexplained => winner,
        e => Some(e),
    }?;
    candidates::fit_all(&l.nominal, &l.poses, &l.refs, model, &s.lsq)
        .ok()
        .map(|f| (model, f))
}

/// The direction test ([`direction::judge`]) on the nominal fit, its null
/// from effect-free re-simulations at the run's noise `noise`, at the
/// family level `α/m` (`m`: the candidates and this test, `tests`).
fn direction_test(
    l: &Loaded,
    f: &Fitted,
    noise: &NoiseModel,
    s: &Settings,
    tests: usize,
) -> DirectionTest {
    let geom: Vec<Sensor<f64>> = f.measured.base_fit.iter().map(|x| x.sensor).collect();
    let plan = NullPlan {
        truth: &geom,
        nominal: &l.nominal,
        refs: &l.refs,
        noise,
        lsq: &s.lsq,
        seed: s.seed,
    };
    let level = s.rule.alpha / tests.max(1) as f64;
    direction::judge(&l.poses, &geom, &f.measured.insample, &plan, level)
}
