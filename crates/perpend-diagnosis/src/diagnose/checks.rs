//! Stage 7 of `perpend diagnose`, checks and warnings: the comparisons of
//! measured statistics with the simulated expectation (what the report's
//! first section, "what the simulation gets wrong", states) and the
//! warnings for the user (excess white noise, a confounded time axis).
//!
//! Every comparison is `z = (measured − simulated mean) / spread`, the
//! spread being the predictive standard deviation over the Monte-Carlo
//! draws, floored by the sampling spread of an ideal run (RMS:
//! `rms/√(2n)`; lag-1 autocorrelation: `1/√pairs`; runs test: 1; R² of
//! `p` regressors: `√(2p)/n`). A statistic is flagged when `|z|` exceeds
//! the two-sided Student-t quantile at the diagnosis' level α split over
//! all checks (Bonferroni), with `draws − 1` degrees of freedom.
//!
//! Input: the outputs of stages 1-5 (`Loaded`, `Fitted`, `Decided`);
//! output: [`Checks`]. Reads those stages only and refits nothing: the
//! statistics are the measured [`Analysis`] and the [`Expectation`] the
//! decision simulated. Limits: the flags are only as good as the
//! simulated spread (as many draws as the decision ran).

use super::decision::{named, Decided};
use super::expect::{Analysis, Expectation, Spread};
use super::fits::Fitted;
use super::load::Loaded;
use perpend_calib::candidates::Effect;
use perpend_calib::lags;
use perpend_calib::noise::{self, NoiseEstimate};
use perpend_calib::stats;
use perpend_formats::exchange::PoseTable;

/// A comparison of a measured statistic with its simulated expectation.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    /// What is compared.
    pub what: String,
    /// Measured value.
    pub measured: f64,
    /// Simulated mean.
    pub expected: f64,
    /// Simulated predictive spread (1σ).
    pub spread: f64,
    /// `(measured − expected) / spread`.
    pub z: f64,
    /// Outside the simulated spread at the diagnosis' level.
    pub flagged: bool,
}

/// The output of stage 7: what the report compares and warns about.
#[derive(Debug, Clone, Default)]
pub struct Checks {
    /// Comparisons of the measured run with the simulation.
    pub checks: Vec<Check>,
    /// Warnings for the user (excess white noise, ...).
    pub warnings: Vec<String>,
}

/// Stage 7 on the loaded run `l`, its fits `f` and the decision `d`: the
/// comparisons ([`comparisons`]) and the warnings about the noise and
/// the time axis.
pub(super) fn compare(l: &Loaded, f: &Fitted, d: &Decided) -> Checks {
    let checks = comparisons(&f.measured, &d.expected, &f.fitted, d.decision.alpha);
    let mut warnings = noise_warnings(&d.estimate, d.effect);
    warnings.extend(time_warning(&l.poses, &named(d.effect, &d.also)));
    Checks { checks, warnings }
}

fn check(what: String, measured: f64, exp: Spread, floor: f64, t: f64) -> Check {
    let spread = exp.predictive_sd(floor);
    let z = if spread > 0.0 {
        (measured - exp.mean) / spread
    } else {
        0.0
    };
    Check {
        what,
        measured,
        expected: exp.mean,
        spread,
        z,
        flagged: z.abs() > t,
    }
}

/// The comparisons of the measured run `m` with the simulation `e`, for
/// the models fitted, at the decision's level.
fn comparisons(m: &Analysis, e: &Expectation, models: &[Effect], level: f64) -> Vec<Check> {
    // Two-sided, Bonferroni over the checks, Student t with draws − 1
    // degrees of freedom: a flag is a finding, not one of many chances.
    let n_checks = 3 + m.insample.first().map_or(0, Vec::len) + models.len() + noise::AXES.len();
    let alpha = level / (2.0 * n_checks as f64);
    let t = stats::t_quantile(1.0 - alpha, (e.draws.max(2) - 1) as f64);
    let mut out = Vec::new();
    if let (Some(b), Some(s)) = (m.cv_of(Effect::None), e.rms_of(Effect::None)) {
        out.push(check(
            "held-out RMS, all sensors [mm]".into(),
            b.rms,
            s,
            s.mean / (2.0 * b.n.max(1) as f64).sqrt(),
            t,
        ));
        for (i, (r, s)) in b.rms_sensor.iter().zip(&e.rms_sensor).enumerate() {
            let n = b.resid.iter().filter(|row| row[i].is_some()).count();
            out.push(check(
                format!("held-out RMS, sensor {} [mm]", i + 1),
                *r,
                *s,
                s.mean / (2.0 * n.max(1) as f64).sqrt(),
                t,
            ));
        }
    }
    let pairs = m.lag1.1.max(1) as f64;
    out.push(check(
        "lag-1 autocorrelation (acquisition order)".into(),
        m.lag1.0,
        e.lag1,
        1.0 / pairs.sqrt(),
        t,
    ));
    out.push(check(
        "runs test z (acquisition order)".into(),
        m.runs_z,
        e.runs_z,
        1.0,
        t,
    ));
    if let Some(z) = m.structure_of(Effect::None) {
        for (x, v) in z.iter().take(noise::AXES.len()).enumerate() {
            if let (Some(v), Some(sp)) = (v, e.structure_of(Effect::None).get(x)) {
                out.push(check(
                    format!("structure z along {}", noise::AXES[x]),
                    *v,
                    *sp,
                    1.0,
                    t,
                ));
            }
        }
    }
    let n = m.insample.iter().flatten().flatten().count().max(1) as f64;
    for &eff in models.iter().filter(|x| **x != Effect::None) {
        if let (Some(r), Some(s)) = (m.r2_of(eff), e.r2_of(eff)) {
            let p = eff.terms().len() as f64;
            out.push(check(
                format!("R² of residual on {} regressor", eff.name()),
                r,
                s,
                (2.0 * p).sqrt() / n,
                t,
            ));
        }
    }
    out
}

/// Warnings about the noise: excess white noise over the declared value.
fn noise_warnings(est: &NoiseEstimate, effect: Effect) -> Vec<String> {
    let mut w = Vec::new();
    if let Some(decl) = &est.declared_mm {
        let d = stats::mean(decl);
        let e = stats::mean(&est.reading_mm);
        if e > 1.5 * d && effect == Effect::None {
            w.push(format!(
                "the residuals carry no structure but their noise, {:.1} µm, is {:.1}× the declared {:.1} µm: white excess noise (sensor, electronics or vibration), not a model effect",
                1000.0 * e,
                e / d,
                1000.0 * d
            ));
        } else if e > 1.5 * d {
            w.push(format!(
                "the run's reading noise, {:.1} µm, is {:.1}× the declared {:.1} µm",
                1000.0 * e,
                e / d,
                1000.0 * d
            ));
        }
        for (i, (&d, &e)) in decl.iter().zip(&est.reading_mm).enumerate() {
            let who = format!("sensor {}", i + 1);
            let how = "estimated from the run";
            w.extend(perpend_formats::plausible::sigma_warning(
                &who, d, e, how, true,
            ));
        }
    }
    w
}

/// A warning when a time-like effect (thermal, drift) is named on a run
/// whose temperature follows its time (a warm-up that only rises): the run
/// cannot tell one from the other; which is named is the better fit of
/// this run's pattern, not evidence for its cause.
fn time_warning(poses: &PoseTable, named: &[Effect]) -> Option<String> {
    lags::inseparable(poses, named).map(|r| {
        format!(
            "thermal and drift are confounded in this run: the temperature follows the time (r = {r:.2}), so the run cannot tell a temperature coefficient from a drift in time; the correction fits this run, but would extrapolate differently. A run in which the temperature falls or is held (a cool-down, a second warm-up after a pause) separates them"
        )
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_calib::sim::{paper_head, simulate, SimConfig, TempProfile};
    use rand::SeedableRng;

    fn run(swing_c: f64) -> PoseTable {
        let head = paper_head().unwrap();
        let mut cfg = SimConfig::paper();
        cfg.dt_s = Some(30.0);
        cfg.temp = Some(TempProfile {
            start_c: 21.0,
            rate_c_per_s: 0.003,
            swing_c,
            period_s: 300.0,
        });
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        simulate(&head, &cfg, &[], &mut rng).unwrap().poses
    }

    /// A warm-up (temperature following time) makes thermal and drift the
    /// same pattern: named, either one is flagged; a temperature that swings
    /// separates them, and nothing is said; nor when neither is named.
    #[test]
    fn thermal_and_drift_are_flagged_only_when_the_run_confounds_them() {
        let warm = run(0.0);
        assert!(time_warning(&warm, &[Effect::Thermal]).is_some());
        assert!(time_warning(&warm, &[Effect::Gain, Effect::Drift]).is_some());
        assert!(time_warning(&warm, &[Effect::Gain]).is_none());
        let swing = run(3.0);
        assert!(time_warning(&swing, &[Effect::Thermal]).is_none());
    }
}
