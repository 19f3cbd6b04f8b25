//! Stage 7b of `perpend diagnose`, detection limits: with a `none`, what
//! the run could have missed. For every candidate of the catalogue, the
//! smallest amplitude this run would detect with 90 % probability at the
//! diagnosis's α, in the units the report gives a named effect, as the
//! normal-error cost × the floor it has there, and what run would lower it.
//!
//! How: the candidate's own form ([`pattern`]: its regressor on every
//! sensor, the same size on each, alternate signs; the linearity forms as
//! a bow and an S over each sensor's readings) is added at amplitude `a`
//! to `n` effect-free re-simulations of the run ([`super::expect::null_draw`]
//! at the run's noise, seeds after the expectation's), and each is judged
//! by the decision's own test of that candidate against the paper's
//! model ([`detected`], through the one rule the decision uses,
//! [`super::select::test`]: paired held-out z or signed-rank z beyond the
//! thresholds the run's decision used with the minimum gain over the
//! floor, the nested in-sample test against the run's effect-free
//! spreads, or the normal-cost test), on the run's folds and references. A pass at
//! `a` is at least ⌈0.9·n⌉ of the `n` draws detected (8 of 8 with the
//! default `n` = 8), the same draws at every `a` (common random numbers).
//! The search ([`search`]) walks a grid of steps of 2^¼ from below where
//! the part the paper's model cannot absorb ([`visible_per_unit`], held
//! out, noise-free) is 0.7× the noise, upwards until a pass: a failing
//! amplitude stops at its first misses and is cheap, so about one passing
//! amplitude costs all `n` draws. The limit is that amplitude; the one
//! below it failed. Monte-Carlo precision: the grid's 2^¼ (19 %), and
//! with `n` draws a pass at a true power of 0.9 happens with probability
//! 0.9ⁿ (0.43 at 8; 0.27 at a power of 0.85, 0.66 at 0.95): a lucky pass
//! below the 90 % point is possible, more often the limit lies above it
//! (docs/diagnosis.md, "Detection limits", measures it on the
//! independent generator).
//!
//! Limits: the limit is of the candidate's test against the paper's
//! model, the first step of the decision; the structure checks that
//! follow it (a winner whose residuals keep structure) and competition
//! between candidates are not simulated, nor the plausibility bound (the
//! search never goes beyond it). The injected form is the candidate's:
//! an effect of another shape is seen as well as its projection on it.
//! Computed only when the verdict is `none`; [`Settings::limit_draws`]
//! draws (0: not computed).

use perpend_core::head::Sensor;

use super::decision::Decided;
use super::expect::{null_draw, null_table, NoiseModel};
use super::fits::Fitted;
use super::insample;
use super::load::{reading_span, Loaded};
use super::select::{self, Bar, Shown, Verdict};
use super::settings::Settings;
use perpend_calib::candidates::{regressor, Effect, Refs};
use perpend_calib::cv::{cross_validate, normal_errors, paired_normals, CvResult};
use perpend_calib::lags;
use perpend_calib::stats;
use perpend_formats::exchange::PoseTable;

/// Detected share a pass needs.
pub const POWER: f64 = 0.9;
/// Seed offset of the injected draws: past the expectation's, the
/// direction test's and the nested test's draws.
const DRAW_OFFSET: usize = 5000;

/// The detection limit of one candidate.
#[derive(Debug, Clone, PartialEq)]
pub struct Limit {
    /// The candidate.
    pub effect: Effect,
    /// The limit, or why the run cannot show the candidate.
    pub found: Result<Found, String>,
    /// What run would lower it, in words.
    pub lowered_by: String,
}

/// A limit found by the search (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Found {
    /// The smallest amplitude that passed (coefficient units of the
    /// candidate's term; the linearity forms: peak [mm]).
    pub amplitude: f64,
    /// The largest amplitude tried below it that failed (0: none tried).
    pub below: f64,
    /// Draws detected at the limit, of `draws`.
    pub detected: usize,
    /// Draws run at the limit.
    pub draws: usize,
    /// Mean over the draws of the paper's model's mean held-out normal
    /// error over its effect-free expectation, at the limit.
    pub cost: f64,
    /// Mean over the draws of the paper's model's held-out RMS over its
    /// effect-free expectation, at the limit.
    pub rms_ratio: f64,
}

/// The output of the stage: one entry per catalogue candidate (empty when
/// not computed).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Limits {
    /// Per candidate, catalogue order.
    pub limits: Vec<Limit>,
    /// Effect-free draws per amplitude.
    pub draws: usize,
}

/// What an evaluation needs from the run.
struct Ctx<'a> {
    l: &'a Loaded,
    s: &'a Settings,
    truth: Vec<Sensor<f64>>,
    tables: Vec<PoseTable>,
    /// Half-span of each sensor's readings about `d_ref` [mm].
    span: Vec<f64>,
    floor_rms: f64,
    floor_deg: f64,
}

/// Stage 7b (module docs): the detection limit of every catalogue
/// candidate when the verdict is `none`; empty otherwise or with
/// `limit_draws` 0.
pub(super) fn limits(l: &Loaded, f: &Fitted, d: &Decided, s: &Settings) -> Limits {
    let n = s.limit_draws;
    if d.effect != Effect::None || n == 0 {
        return Limits::default();
    }
    let truth: Vec<Sensor<f64>> = f.measured.base_fit.iter().map(|x| x.sensor).collect();
    let tables = (0..n)
        .map(|j| null_draw(&truth, &l.poses, &d.noise, s.seed, DRAW_OFFSET + j))
        .collect();
    let base_exp = d.expected.rms_of(Effect::None).unwrap_or_default();
    let ctx = Ctx {
        l,
        s,
        span: half_spans(&l.poses, &l.refs),
        truth,
        tables,
        floor_rms: base_exp.mean,
        floor_deg: d.expected.normal_err_deg.mean,
    };
    let sigma = stats::rms(&d.noise.sigma);
    let limits = Effect::CATALOG
        .into_iter()
        .map(|e| Limit {
            effect: e,
            found: limit_of(e, &ctx, f, d, sigma),
            lowered_by: lowered_by(e, l),
        })
        .collect();
    Limits { limits, draws: n }
}

/// The search of one candidate (module docs), or why there is none.
fn limit_of(e: Effect, c: &Ctx<'_>, f: &Fitted, d: &Decided, sigma: f64) -> Result<Found, String> {
    if let Some((_, why)) = c.l.skipped.iter().find(|(x, _)| *x == e) {
        return Err(format!("not detectable in this run: {why}"));
    }
    let v = d
        .decision
        .verdicts
        .iter()
        .find(|v| v.effect == e)
        .ok_or_else(|| {
            let why = f
                .failed
                .iter()
                .find(|(x, _)| *x == e)
                .map_or("it could not be cross-validated", |(_, w)| w.as_str());
            format!("not detectable in this run: {why}")
        })?;
    let bound = bound(e);
    let per_unit = visible_per_unit(e, c, bound / 100.0);
    if !(per_unit * bound > 1e-3 * sigma) {
        return Err(format!(
            "not detectable in this run: the paper's model absorbs its form on this pose set (what is left of it at the physical bound, {}, is below a thousandth of the noise)",
            words(e, bound)
        ));
    }
    let need = ((POWER * c.tables.len() as f64).ceil() as usize).max(1);
    let pass = |a: f64| evaluate(e, a, c, v, need);
    let (lo, hi) = search(&pass, START * sigma / per_unit, bound, need);
    let Some((h, hp)) = hi else {
        return Err(format!(
            "not detectable within the physical bound: injected at {} into {} effect-free re-simulations, the decision names it in fewer than {need} of them",
            words(e, bound),
            c.tables.len()
        ));
    };
    Ok(Found {
        amplitude: h,
        below: lo,
        detected: hp.hits,
        draws: hp.tried,
        cost: stats::mean(&hp.cost),
        rms_ratio: stats::mean(&hp.rms),
    })
}

/// Where the search starts: the amplitude whose held-out part the paper's
/// model leaves on noise-free data is this many times the noise, times
/// [`STEP`]⁻² (the limits of the golden runs lie at 0.7-1.2 of the noise).
const START: f64 = 1.0;
/// The search's step factor, 2^¼: the limit's resolution.
const STEP: f64 = 1.189_207_115_002_721;
/// Most steps of the search (2^¼ each: a range of 2⁸ about the start).
const MAX_STEPS: usize = 32;

/// The smallest amplitude on the grid `start·STEP^k` (k from −2) at
/// which `pass` reaches `need` draws, at most `bound`, and the amplitude
/// one step below it that failed (0 when none was tried). Upwards from
/// below the start: a failing pass stops at its first misses and is
/// cheap, a passing one runs every draw, so the search meets one passing
/// pass unless the start itself passes (then it steps down until one
/// fails).
fn search(
    pass: &dyn Fn(f64) -> Pass,
    start: f64,
    bound: f64,
    need: usize,
) -> (f64, Option<(f64, Pass)>) {
    let mut a = (start / (STEP * STEP)).min(bound);
    let p = pass(a);
    if p.hits >= need {
        let mut hi = (a, p);
        for _ in 0..MAX_STEPS {
            let down = hi.0 / STEP;
            let p = pass(down);
            if p.hits < need {
                return (down, Some(hi));
            }
            hi = (down, p);
        }
        return (0.0, Some(hi));
    }
    for _ in 0..MAX_STEPS {
        if a >= bound {
            break;
        }
        let up = (a * STEP).min(bound);
        let p = pass(up);
        if p.hits >= need {
            return (a, Some((up, p)));
        }
        a = up;
    }
    (a, None)
}

/// The candidate's physical bound ([`perpend_calib::candidates::plausible`]) in
/// the amplitude's units.
fn bound(e: Effect) -> f64 {
    match e {
        Effect::Gain | Effect::Thermal => 0.1,
        Effect::Nonlinearity | Effect::LinearityTable => 1.0,
        Effect::Incidence => perpend_calib::candidates::INCIDENCE_BOUND_MM,
        Effect::Crosstalk => 0.45,
        Effect::Drift => 5.0 / 3600.0,
        Effect::None | Effect::Unexplained => 0.0,
    }
}

/// Half-span of each sensor's readings about its `d_ref` [mm] (at least
/// 1 µm).
fn half_spans(poses: &PoseTable, refs: &Refs) -> Vec<f64> {
    (0..poses.n_sensors)
        .map(|i| {
            let d0 = refs.d_ref.get(i).copied().unwrap_or(0.0);
            poses
                .rows
                .iter()
                .filter_map(|r| Some((r.readings.get(i).copied().flatten()? - d0).abs()))
                .fold(1e-3, f64::max)
        })
        .collect()
}

/// The candidate's form per unit amplitude for sensor `i` in pose `k` of
/// `table` (module docs): its regressor with the sign `(−1)^i` (the
/// carry-over positive on every channel); the polynomial a bow
/// `(u/s)²`, the table an S `sin(πu/s)`, `u = d − d_ref`, `s` the
/// sensor's half-span.
fn pattern(e: Effect, c: &Ctx<'_>, table: &PoseTable, k: usize, i: usize) -> Option<f64> {
    let sign = if i.is_multiple_of(2) { 1.0 } else { -1.0 };
    let s = c.span.get(i).copied().unwrap_or(1.0);
    let x = regressor(e, &c.l.refs, table, k, i, c.truth.get(i)?)?;
    Some(match e {
        Effect::Nonlinearity => sign * (x / s).powi(2),
        Effect::LinearityTable => sign * (std::f64::consts::PI * x / s).sin(),
        Effect::Crosstalk => x,
        _ => sign * x,
    })
}

/// `table` with candidate `e` added at amplitude `a` (regressors from the
/// table as drawn).
fn inject(e: Effect, a: f64, c: &Ctx<'_>, table: &PoseTable) -> PoseTable {
    let mut out = table.clone();
    for (k, row) in out.rows.iter_mut().enumerate() {
        for (i, r) in row.readings.iter_mut().enumerate() {
            if let (Some(d), Some(p)) = (*r, pattern(e, c, table, k, i)) {
                *r = Some(d + a * p);
            }
        }
    }
    out
}

/// Held-out RMS the paper's model leaves of `e`'s form per unit amplitude,
/// on the run's planes without noise (probed at `probe`).
fn visible_per_unit(e: Effect, c: &Ctx<'_>, probe: f64) -> f64 {
    use rand::SeedableRng;
    let quiet = NoiseModel {
        sigma: vec![0.0; c.truth.len()],
        tracker: None,
    };
    let mut rng = rand::rngs::StdRng::seed_from_u64(c.s.seed);
    let clean = null_table(&c.truth, &c.l.poses, &quiet, &mut rng);
    let t = inject(e, probe, c, &clean);
    cv_of(Effect::None, c, &t).map_or(0.0, |b| b.rms / probe)
}

fn cv_of(e: Effect, c: &Ctx<'_>, t: &PoseTable) -> Option<CvResult> {
    cross_validate(e, &c.l.nominal, t, &c.l.refs, &c.l.folds, &c.s.lsq).ok()
}

/// The draws judged at one amplitude.
#[derive(Debug, Clone, Default)]
struct Pass {
    hits: usize,
    tried: usize,
    cost: Vec<f64>,
    rms: Vec<f64>,
}

/// The draws at amplitude `a`, judged one by one ([`detected`]); stops as
/// soon as `need` detections can no longer be reached.
fn evaluate(e: Effect, a: f64, c: &Ctx<'_>, v: &Verdict, need: usize) -> Pass {
    let n = c.tables.len();
    let mut p = Pass::default();
    for t in &c.tables {
        if p.tried - p.hits > n - need {
            break;
        }
        p.tried += 1;
        let t = inject(e, a, c, t);
        if let Some((hit, cost, rms)) = detected(e, c, &t, v) {
            p.hits += usize::from(hit);
            p.cost.push(cost);
            p.rms.push(rms);
        }
    }
    p
}

/// The decision's test of `e` against the paper's model on table `t`
/// (one rule with the decision: [`super::select::test`], the held-out
/// test, the nested test and the normal-cost test) with the thresholds of
/// the run's verdict `v`: whether it passes, the paper's model's
/// normal-error cost and its held-out RMS over the floor. The injected
/// form is within its physical bound by construction (the search stops
/// there), so the bar is taken as plausible.
fn detected(e: Effect, c: &Ctx<'_>, t: &PoseTable, v: &Verdict) -> Option<(bool, f64, f64)> {
    let b = cv_of(Effect::None, c, t)?;
    let x = cv_of(e, c, t)?;
    let nested = nested_of(e, c, t, &x);
    let nb = normal_errors(&b, t, &c.l.folds, c.s.method);
    let nx = normal_errors(&x, t, &c.l.folds, c.s.method);
    let g = paired_normals(&nb, &nx);
    let bar = Bar {
        plausible: true,
        ..v.bar.clone()
    };
    let shown = Shown {
        base: &b,
        cand: &x,
        nested: &nested,
        normal_z: (g.poses > 0).then_some(g.z),
    };
    let o = select::test(&shown, &bar);
    let base: Vec<f64> = nb.iter().flatten().copied().collect();
    let cost = if c.floor_deg > 0.0 {
        stats::mean(&base) / c.floor_deg
    } else {
        f64::NAN
    };
    let rms = if c.floor_rms > 0.0 {
        b.rms / c.floor_rms
    } else {
        f64::NAN
    };
    Some((o.beats_base() || o.normal, cost, rms))
}

/// The nested z per set of sensors of `e` (cross-validated as `x`) on
/// table `t` ([`super::insample`]); empty when the paper's model cannot
/// be fitted on it.
fn nested_of(e: Effect, c: &Ctx<'_>, t: &PoseTable, x: &CvResult) -> Vec<Option<f64>> {
    insample::base_rss(&c.l.nominal, t, &c.l.refs, &c.s.lsq).map_or_else(Vec::new, |b| {
        insample::zs(e, &b, &insample::refit(x, t, &c.s.lsq))
    })
}

/// An amplitude of `e` in the units the report gives a named effect
/// ([`super::report::physical`]): `(value, unit)`.
pub fn physical(e: Effect, a: f64) -> (f64, &'static str) {
    let inc30 = 1.0 / 30f64.to_radians().cos() - 1.0;
    match e {
        Effect::Gain => (100.0 * a, "%"),
        Effect::Nonlinearity => (1000.0 * a, "µm at the run's range ends (bow)"),
        Effect::LinearityTable => (1000.0 * a, "µm peak over the run's readings (S)"),
        Effect::Incidence => (1000.0 * a * inc30, "µm at 30° incidence"),
        Effect::Crosstalk => (100.0 * a, "% carry-over"),
        Effect::Thermal => (1000.0 * a, "µm/°C"),
        Effect::Drift => (60_000.0 * a, "µm/min"),
        Effect::None | Effect::Unexplained => (a, ""),
    }
}

/// An amplitude in words (value and unit).
pub fn words(e: Effect, a: f64) -> String {
    let (v, u) = physical(e, a);
    format!("{} {u}", sig3(v))
}

/// Three significant figures.
pub fn sig3(v: f64) -> String {
    let m = v.abs();
    if m >= 100.0 {
        format!("{v:.0}")
    } else if m >= 10.0 {
        format!("{v:.1}")
    } else if m >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// What run would lower the limit of `e`, from the spread of its regressor
/// on this run.
fn lowered_by(e: Effect, l: &Loaded) -> String {
    let p = &l.poses;
    let n = p.rows.len();
    let more = format!(
        "more poses (the limit falls about as 1/√poses: {} instead of {n} halves it)",
        4 * n
    );
    let range = |v: Vec<f64>| {
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if v.is_empty() {
            0.0
        } else {
            hi - lo
        }
    };
    let temps = range(p.rows.iter().filter_map(|r| r.temp_c).collect());
    let times = range(p.rows.iter().filter_map(|r| r.t_s).collect());
    match e {
        Effect::Gain | Effect::Nonlinearity | Effect::LinearityTable => format!(
            "readings spread wider over the sensors' range (±{:.2} mm about the mean here: vary the standoff), or {more}",
            reading_span(p, &l.refs)
        ),
        Effect::Incidence => format!(
            "a larger tilt range (the bias grows as 1/cos γ − 1 ≈ γ²/2: twice the tilt lowers the limit about fourfold), or {more}"
        ),
        Effect::Crosstalk => format!(
            "larger steps between the channels converted in turn (a larger tilt range), or {more}"
        ),
        Effect::Thermal if temps > 0.0 && !lags::separable(p) => format!(
            "a temperature change that does not follow the time ({temps:.1} °C here, along the time: {}), a larger one, or {more}",
            lags::SEPARATED_BY
        ),
        Effect::Thermal if temps > 0.0 => {
            format!("a larger temperature change during the run ({temps:.1} °C here), or {more}")
        }
        Effect::Thermal => {
            "a temperature change during the run, logged per pose (temp_c)".into()
        }
        Effect::Drift if times > 0.0 => format!(
            "a longer run ({:.0} min here) with the poses in random order in time, or {more}",
            times / 60.0
        ),
        Effect::Drift => "the time of every pose logged (t_s) over a run of some minutes".into(),
        Effect::None | Effect::Unexplained => String::new(),
    }
}
