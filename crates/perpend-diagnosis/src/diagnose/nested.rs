//! The second of two time-like effects (thermal beside drift): a nested
//! in-sample test, calibrated on effect-free re-simulations of the model
//! with the effect named before it.
//!
//! A linear drift and a warm-up that reaches its plateau share the time
//! axis but part ways once the temperature holds (issue 35, item 3). The
//! forward selection's held-out test ([`super::decision`]) compares the
//! per-pose held-out losses of the model before and after the partner;
//! each pose's loss difference carries the cross term of the noise with
//! the partner's small share, and the test misses a partner that the run
//! resolves (a tied thermal of half the visible noise beside a drift:
//! paired z 1.5-2.3 against thresholds near 3, where the in-sample
//! statistic below is 5-8 null spreads out). On a run that separates
//! the two ([`perpend_calib::lags::separable`]) the partner is judged like a nested
//! model (the F statistic's numerator, summed over the sensors):
//!
//! `T = Σᵢ (RSSᵢ(before) − RSSᵢ(before + c)) / (RSSᵢ(before + c)/νᵢ)`
//!
//! (`νᵢ` the residual degrees of freedom), on all poses. Its null is the
//! same `T` on [`NULL_DRAWS`] effect-free re-simulations
//! ([`super::expect::null_table`]: the model before it fitted to the run
//! as the truth's geometry, the same planes, times and temperatures, the
//! reading and tracker noise estimated from the run; seeds as
//! [`super::expect::expect`]), fitted with the same two models: a
//! time-like effect already in the data is a linear term of both models
//! and leaves the residuals, and so `T`, alone. `z` of `∛T` against the
//! draws (Wilson-Hilferty), `p` its Student tail with draws − 1 degrees
//! of freedom, compared with the step's family level `α/m`.
//!
//! Limits: in-sample, so a partner is also asked to lower the held-out
//! RMS (its paired z above its effect-free mean) before it is named
//! ([`super::decision`]); only the time-like partner of a time-like effect
//! is tested this way, on runs whose temperature does not follow the time.

use perpend_core::calib::{LsqConfig, Regressors};
use perpend_core::head::Sensor;

use super::expect::{null_draw, NoiseModel, Spread};
use perpend_calib::candidates::{fit, Effect, Refs};
use perpend_calib::stats::t_tail;
use perpend_formats::exchange::PoseTable;

/// Effect-free re-simulations behind the null of `T`.
pub const NULL_DRAWS: usize = 48;

/// The time-like partner not yet among `with` when one of thermal and
/// drift is: the effect this module tests.
pub fn partner(with: &[Effect]) -> Option<Effect> {
    let has = |e: Effect| with.contains(&e);
    match (has(Effect::Thermal), has(Effect::Drift)) {
        (true, false) => Some(Effect::Drift),
        (false, true) => Some(Effect::Thermal),
        _ => None,
    }
}

/// The test's outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct Nested {
    /// The (first) effect tested.
    pub effect: Effect,
    /// `T` on the run.
    pub stat: f64,
    /// `T` over the effect-free re-simulations.
    pub null: Spread,
    /// One-sided p of `T` against that null.
    pub p: f64,
    /// The level `p` is compared with (`α/m`).
    pub level: f64,
}

impl Nested {
    /// `p` below the level.
    pub fn found(&self) -> bool {
        self.p < self.level
    }
}

/// What the statistic and its null need.
pub struct NestedPlan<'a> {
    /// The nominal head the fits start from.
    pub nominal: &'a [Sensor<f64>],
    /// Term references with the effects named before (`extra`).
    pub refs: &'a Refs,
    /// The geometry of the model before, taken as the truth.
    pub truth: &'a [Sensor<f64>],
    /// The noise estimated from the run (the model before it).
    pub noise: &'a NoiseModel,
    /// Solver settings.
    pub lsq: &'a LsqConfig<f64>,
    /// The diagnosis's seed.
    pub seed: u64,
}

/// `T` of the effects `added` on `poses` (module docs); `None` when a
/// sensor cannot be fitted with either model.
fn stat(plan: &NestedPlan<'_>, poses: &PoseTable, added: &[Effect]) -> Option<f64> {
    let (c, rest) = added.split_first()?;
    let after_refs = Refs {
        extra: plan.refs.extra.iter().chain(rest).copied().collect(),
        ..plan.refs.clone()
    };
    let mut t = 0.0;
    for (i, s) in plan.nominal.iter().enumerate() {
        let before = fit(s, i, poses, plan.refs.terms(Effect::None, i), plan.lsq).ok()?;
        let after = fit(s, i, poses, after_refs.terms(*c, i), plan.lsq).ok()?;
        let rss = |f: &perpend_calib::candidates::SensorFit| f.rms * f.rms * f.used as f64;
        let nu = after.used.saturating_sub(5 + after.terms.count()).max(1) as f64;
        let scale = rss(&after) / nu;
        if scale > 0.0 {
            t += (rss(&before) - rss(&after)).max(0.0) / scale;
        }
    }
    Some(t)
}

/// The nested test of the effects `added` together on top of the model of
/// `plan.refs` (module docs) at `level`; `None` when the run or too many
/// draws cannot be fitted, or nothing is added.
pub fn judge(
    plan: &NestedPlan<'_>,
    poses: &PoseTable,
    added: &[Effect],
    level: f64,
) -> Option<Nested> {
    let effect = *added.first()?;
    let t = stat(plan, poses, added)?;
    let nulls: Vec<f64> = (0..NULL_DRAWS)
        .filter_map(|j| {
            let table = null_draw(plan.truth, poses, plan.noise, plan.seed, j);
            stat(plan, &table, added)
        })
        .collect();
    let null = Spread::of(&nulls);
    if null.n < NULL_DRAWS / 2 {
        return None;
    }
    // T is χ²-like: its cube root is nearly normal (Wilson and Hilferty).
    let root = Spread::of(&nulls.iter().map(|x| x.cbrt()).collect::<Vec<_>>());
    let z = (t.cbrt() - root.mean) / root.predictive_sd(1e-12);
    Some(Nested {
        effect,
        stat: t,
        null,
        p: t_tail(z, (null.n - 1) as f64),
        level,
    })
}
