//! Stage 8 of `perpend diagnose`, the report: the readable text of a
//! [`Diagnosis`] — the run, what the simulation gets wrong (the
//! comparisons of [`super::checks`]), the candidates, the verdict, the
//! coefficients in physical units and the gain.
//!
//! Input: the `Diagnosis` (the outputs of stages 1-7); output: text. It
//! reads what the stages decided and never refits. Limits: the wording
//! follows the verdict; the figures are those of the stages, rounded.

use std::fmt::Write as _;
use std::path::Path;

use super::checks::Check;
use super::diagnosis::Diagnosis;
use super::settings::Settings;
use perpend_calib::candidates::Effect;
use perpend_calib::stats;

/// Plain-language statements of what the simulation gets wrong.
pub fn statements(d: &Diagnosis) -> Vec<String> {
    let mut out = Vec::new();
    let flagged: Vec<&Check> = d.checked.checks.iter().filter(|c| c.flagged).collect();
    if flagged.is_empty() {
        out.push(
            "Nothing measured lies outside the simulated spread: the paper's model with this run's own noise reproduces these residuals."
                .into(),
        );
        return out;
    }
    for c in &flagged {
        let s = if c.what.starts_with("held-out RMS, all") {
            let rel = (c.measured / c.expected - 1.0) * 100.0;
            if c.z > 0.0 {
                format!(
                    "The simulation underpredicts the residuals: {:.4} mm measured, {:.4} ± {:.4} mm simulated ({:+.0}%, z = {:.1}).",
                    c.measured, c.expected, c.spread, rel, c.z
                )
            } else {
                format!(
                    "The residuals are smaller than simulated: {:.4} mm measured, {:.4} ± {:.4} mm simulated ({:+.0}%): the datasheet σ or the tracker noise is pessimistic.",
                    c.measured, c.expected, c.spread, rel
                )
            }
        } else if c.what.starts_with("held-out RMS, sensor") {
            format!(
                "{}: {:.4} mm measured vs {:.4} ± {:.4} mm simulated (z = {:.1}).",
                c.what
                    .trim_end_matches(" [mm]")
                    .replace("held-out RMS, s", "S"),
                c.measured,
                c.expected,
                c.spread,
                c.z
            )
        } else if c.what.starts_with("structure") {
            format!(
                "The residuals have a smooth pattern ({} = {:.1}, simulated {:.1} ± {:.1}).",
                c.what, c.measured, c.expected, c.spread
            )
        } else if c.what.starts_with("lag-1") || c.what.starts_with("runs") {
            format!(
                "The residuals are not white in acquisition order ({} = {:.2}, simulated {:.2} ± {:.2}): something changes slowly during the run.",
                if c.what.starts_with("lag-1") {
                    "lag-1 r"
                } else {
                    "runs-test z"
                },
                c.measured,
                c.expected,
                c.spread
            )
        } else {
            format!(
                "The residuals follow a regressor the paper's model lacks: {} = {:.3}, simulated {:.3} ± {:.3} (z = {:.1}).",
                c.what, c.measured, c.expected, c.spread, c.z
            )
        };
        out.push(s);
    }
    out
}

fn pct(a: f64, b: f64) -> String {
    if a > 0.0 {
        format!("{:+.0}%", (b / a - 1.0) * 100.0)
    } else {
        "–".into()
    }
}

/// The readable report: the run and its noise, what the simulation gets
/// wrong, the candidates, the verdict, the fitted coefficients, the gain
/// on held-out poses. `out`: where `--out` stored the parameters, if it
/// did (the report then says so instead of suggesting it).
pub fn text(
    d: &Diagnosis,
    (sensors, poses): (&Path, &Path),
    out: Option<&Path>,
    s: &Settings,
) -> String {
    let mut o = String::new();
    run_section(&mut o, d, sensors, poses, s);
    checks_section(&mut o, d);
    candidates_section(&mut o, d, s);
    verdict_section(&mut o, d);
    limits_section(&mut o, d, s);
    coefficients_section(&mut o, d, (sensors, poses), out);
    gain_section(&mut o, d);
    o
}

/// The run, its noise and how the expectation was simulated.
fn run_section(o: &mut String, d: &Diagnosis, sensors: &Path, poses: &Path, s: &Settings) {
    let n_read = d.fits.measured.insample.iter().flatten().flatten().count();
    let _ = writeln!(
        o,
        "perpend diagnose: {} + {}",
        sensors.display(),
        poses.display()
    );
    let mut cols = Vec::new();
    if d.run.poses.has_time() {
        cols.push("t_s");
    }
    if d.run.poses.has_temperature() {
        cols.push("temp_c");
    }
    let _ = writeln!(
        o,
        "run: {} poses, {} sensors, {} readings{}",
        d.run.poses.rows.len(),
        d.run.nominal.len(),
        n_read,
        if cols.is_empty() {
            String::new()
        } else {
            format!("; columns {}", cols.join(", "))
        }
    );
    for line in noise_lines(d, s) {
        let _ = writeln!(o, "{line}");
    }
    let _ = writeln!(
        o,
        "expectation: {} Monte-Carlo draws of this head (the paper's model fitted to this run, as truth) on these planes; {}-fold cross-validation by pose (seed {})",
        d.decided.expected.draws, d.run.folds.k, s.seed
    );
}

/// The statistics the simulation gets wrong, and what they say.
fn checks_section(o: &mut String, d: &Diagnosis) {
    let _ = writeln!(o, "\nWhat the simulation gets wrong");
    let _ = writeln!(
        o,
        "  {:<44} {:>10}  {:>20}  {:>6}",
        "statistic", "measured", "simulated ± 1σ", "z"
    );
    for c in &d.checked.checks {
        let _ = writeln!(
            o,
            "  {:<44} {:>10.4}  {:>9.4} ± {:<8.4}  {:>6.1}{}",
            c.what,
            c.measured,
            c.expected,
            c.spread,
            c.z,
            if c.flagged { "  <" } else { "" }
        );
    }
    for st in statements(d) {
        let _ = writeln!(o, "  * {st}");
    }
}

/// Every model's held-out figures against its effect-free threshold.
fn candidates_section(o: &mut String, d: &Diagnosis, s: &Settings) {
    let _ = writeln!(
        o,
        "\nCandidates (held-out, {} folds; z* = {:.2}: family level α = {}, Bonferroni over mean and rank tests)",
        d.run.folds.k, d.decided.decision.z_star, s.rule.alpha
    );
    let _ = writeln!(
        o,
        "  {:<15} {:>6}  {:>13}  {:>17}  {:>11}  {:>11}  beats base",
        "model", "params", "held-out RMS", "simulated floor", "gain z/thr", "rank z/thr"
    );
    for v in &d.decided.decision.verdicts {
        let _ = writeln!(
            o,
            "  {:<15} {:>6}  {:>10.4} mm  {:>8.4} ± {:<6.4}  {:>11}  {:>11}  {}",
            if v.effect == Effect::None {
                "none (paper)"
            } else {
                v.effect.name()
            },
            v.n_params,
            v.rms,
            v.expected.mean,
            v.expected.predictive_sd(0.0),
            if v.effect == Effect::None {
                "–".to_string()
            } else {
                format!("{:.1} / {:.1}", v.z, v.z_threshold)
            },
            if v.effect == Effect::None {
                "–".to_string()
            } else {
                format!("{:.1} / {:.1}", v.z_rank, v.rank_threshold)
            },
            if v.effect == Effect::None {
                ""
            } else if v.beats_base {
                "yes"
            } else {
                "no"
            }
        );
    }
    if let Some(c) = &d.decided.decision.cost_named {
        let g = c.test.gain;
        let _ = writeln!(
            o,
            "  normal cost: {} lowers the held-out normal error {:.4}° → {:.4}° ({:.4} ± {:.4}° per pose), z = {:.1} / {:.1}, p = {:.1e} < α/m = {:.1e}; the paper's model costs {:.2}× the floor ({:.4}°)",
            c.effect.name(), g.base_deg, g.cand_deg, g.reduction_deg, g.se_deg, g.z, c.test.threshold, c.test.p, c.level, c.cost, c.floor_deg
        );
    }
    for (e, why) in &d.run.skipped {
        let _ = writeln!(o, "  skipped: {} ({why})", e.name());
    }
}

/// The verdict, its reasons, the forward selection's steps, warnings.
fn verdict_section(o: &mut String, d: &Diagnosis) {
    let names: Vec<&str> = d.effects().iter().map(|e| e.name()).collect();
    let _ = writeln!(
        o,
        "\nVerdict: {}",
        if names.len() > 1 {
            names.join(" + ")
        } else {
            d.decided.effect.name().to_string()
        }
    );
    for r in &d.decided.decision.reasons {
        let _ = writeln!(o, "  {r}");
    }
    if let Some(r) = perpend_calib::lags::inseparable(&d.run.poses, &d.effects()) {
        let _ = writeln!(
            o,
            "  inseparable: thermal and drift are the same pattern on this run (temperature against time r = {r:.2}): {} is the better fit, not the proven cause; {} would separate them",
            time_like(&d.effects()),
            perpend_calib::lags::SEPARATED_BY
        );
    }
    let _ = writeln!(o, "  {}", d.decided.direction.line());
    for st in &d.decided.also {
        let before: Vec<&str> = st.with[..st.with.len() - 1]
            .iter()
            .map(|e| e.name())
            .collect();
        let with = before.join(" + ");
        let test = match &st.nested {
            Some(n) => format!(
                "paired z = {:.1}, in-sample nested test p = {:.1e} (level {:.1e}, from effect-free re-simulations of the model with {with}): the run separates thermal from drift",
                st.verdict.z, n.p, n.level
            ),
            None => format!(
                "paired z = {:.1} (threshold {:.2}, from effect-free re-simulations of the model with {with})",
                st.verdict.z, st.verdict.z_threshold
            ),
        };
        let _ = writeln!(
            o,
            "  then {} on top of {with}: held-out RMS {:.4} → {:.4} mm, {test}",
            st.effect.name(),
            st.before_rms_mm,
            st.cv.rms,
        );
    }
    for e in d.effects() {
        if let Some(n) = d.acts_on(e) {
            let _ = writeln!(
                o,
                "  {} acts on {} (nested in-sample test: {})",
                e.name(),
                super::select::sensor_words(n),
                super::select::nested_words(n)
            );
        }
        match (e, d.time_constant(e)) {
            (Effect::Thermal, Some(tau)) => {
                let _ = writeln!(
                    o,
                    "  thermal acts on the sensor bodies' temperature, which lags the logged one by τ = {tau:.0} s (first-order; `--out` stores it, and the board lags its temperature alike)"
                );
            }
            (Effect::Drift, Some(tau)) => {
                let _ = writeln!(
                    o,
                    "  the drift settles with τ = {tau:.0} s (A·(1 − e^(−t/τ)), coefficients are its initial rate; folded into the zero points at the run's end)"
                );
            }
            _ => {}
        }
    }
    if !d.decided.decision.ties.is_empty() {
        let t: Vec<&str> = d.decided.decision.ties.iter().map(|e| e.name()).collect();
        let _ = writeln!(
            o,
            "  note: {} fits within one standard error as well; this run cannot tell them apart (e.g. temperature that follows time)",
            t.join(", ")
        );
    }
    for (e, why) in &d.fits.implausible {
        let _ = writeln!(
            o,
            "  {} fits outside its physical bounds ({why}): implausible, not named and never stored",
            e.name()
        );
    }
    for r in reconcile(d) {
        let _ = writeln!(o, "  {r}");
    }
    for w in &d.checked.warnings {
        let _ = writeln!(o, "  warning: {w}");
    }
    if let Some(f) = d.decided.decision.explained_fraction {
        if d.decided.effect == Effect::Unexplained {
            let _ = writeln!(
                o,
                "  the best candidate removes {:.0}% of the excess mean square over the floor",
                f * 100.0
            );
        }
    }
}

/// With a `none`: what the run could have missed, each candidate's
/// detection limit ([`super::limits`]).
fn limits_section(o: &mut String, d: &Diagnosis, s: &Settings) {
    use super::limits::{words, POWER};
    if d.limits.limits.is_empty() {
        return;
    }
    let _ = writeln!(
        o,
        "\nDetection limits (what this run could have missed: each candidate's form injected into {} effect-free re-simulations at growing sizes and judged by the decision's own test at α = {}; the smallest size named in ≥ {:.0} % of them, with the size below it that failed)",
        d.limits.draws,
        s.rule.alpha,
        100.0 * POWER
    );
    for l in &d.limits.limits {
        let e = l.effect;
        match &l.found {
            Ok(f) => {
                let _ = writeln!(
                    o,
                    "  {:<15} {} (named in {}/{}; {} failed); the paper's model there costs {:.2}× the normal-error floor, held-out RMS {:.2}× its floor",
                    e.name(),
                    words(e, f.amplitude),
                    f.detected,
                    f.draws,
                    if f.below > 0.0 {
                        super::limits::sig3(super::limits::physical(e, f.below).0)
                    } else {
                        "none smaller tried".into()
                    },
                    f.cost,
                    f.rms_ratio
                );
            }
            Err(why) => {
                let _ = writeln!(o, "  {:<15} {why}", e.name());
            }
        }
        let _ = writeln!(o, "  {:<15}   lowered by: {}", "", l.lowered_by);
    }
}

/// The named model's coefficients, fitted on all poses.
fn coefficients_section(
    o: &mut String,
    d: &Diagnosis,
    (sensors, poses): (&Path, &Path),
    out: Option<&Path>,
) {
    if let Some((e, fits)) = &d.decided.refit {
        let _ = writeln!(
            o,
            "\nFitted {} coefficients (all poses, ± 1σ){}",
            e.name(),
            if d.decided.effect == Effect::Unexplained {
                " — partial explanation only"
            } else {
                ""
            }
        );
        let span = super::load::reading_span(&d.run.poses, &d.run.refs);
        for (i, f) in fits.iter().enumerate() {
            let _ = writeln!(
                o,
                "  sensor {}: {}   (residual RMS {:.1} µm)",
                i + 1,
                physical(*e, f, span),
                1000.0 * f.rms
            );
        }
        match out {
            _ if d.decided.effect == Effect::Unexplained => {}
            Some(p) => {
                let _ = writeln!(o, "  stored in {} (--out)", p.display());
            }
            None => {
                let _ = writeln!(
                    o,
                    "  store them: perpend diagnose --sensors {} --poses {} --out params.json (parameter JSON with the extension)",
                    sensors.display(),
                    poses.display()
                );
            }
        }
    }
}

/// Base against extended model on held-out poses.
fn gain_section(o: &mut String, d: &Diagnosis) {
    let _ = writeln!(o, "\nGain on held-out poses (base → extended)");
    let b: Vec<f64> = d.scores.base_normals.iter().flatten().copied().collect();
    let x: Vec<f64> = d.scores.ext_normals.iter().flatten().copied().collect();
    let _ = writeln!(
        o,
        "  residual RMS        {:.4} → {:.4} mm ({})   simulated floor {:.4} mm",
        d.scores.base.heldout_rms_mm,
        d.scores.extended.heldout_rms_mm,
        pct(
            d.scores.base.heldout_rms_mm,
            d.scores.extended.heldout_rms_mm
        ),
        d.decided.floor_mm
    );
    if !b.is_empty() {
        let _ = writeln!(
            o,
            "  normal error mean   {:.4}° → {:.4}° ({})   simulated {:.4}°",
            stats::mean(&b),
            stats::mean(&x),
            pct(stats::mean(&b), stats::mean(&x)),
            d.decided.expected.normal_err_deg.mean
        );
        let _ = writeln!(
            o,
            "  normal error p95    {:.4}° → {:.4}°",
            stats::quantile(&b, 0.95),
            stats::quantile(&x, 0.95)
        );
        let _ = writeln!(
            o,
            "  normal error max    {:.4}° → {:.4}°",
            stats::quantile(&b, 1.0),
            stats::quantile(&x, 1.0)
        );
        let _ = writeln!(
            o,
            "  (normal error: held-out readings through perpend-core with the fold's calibrated head, against the plane normal in the file, {} poses)",
            b.len()
        );
    }
    if d.scores.ext_model == Effect::None {
        let _ = writeln!(o, "  nothing named: the extended model is the base model");
    }
}

/// The noise lines of the report: estimated against declared, the
/// tracker, the poses left out.
fn noise_lines(d: &Diagnosis, s: &Settings) -> Vec<String> {
    use perpend_calib::noise::Source;
    let e = &d.decided.estimate;
    let um = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{:.1}", 1000.0 * x))
            .collect::<Vec<_>>()
            .join(" / ")
    };
    let how = match e.source {
        Source::Residuals => "from the within-pose scatter of the residuals",
        Source::SampleScatter => {
            "from the s_i_mm / n_samples columns (at least the residuals' within-pose scatter)"
        }
        Source::ResidualRms => {
            "the residual RMS (too few readings per pose to separate plane and reading noise)"
        }
    };
    let declared = match &e.declared_mm {
        Some(v) => format!(
            "declared {} µm ({})",
            um(v),
            if s.sigma_mm.is_some() {
                "--sigma-mm"
            } else {
                "sigma_mm column"
            }
        ),
        None => "none declared".into(),
    };
    let mut out = vec![format!(
        "noise of this run: reading σ = {} µm {how}; {declared}",
        um(&e.reading_mm)
    )];
    out.push(match &e.tracker {
        Some(t) => format!(
            "  datum-plane error {:.1} µm RMS at the spots{}: tracker simulated as ξ = {:.1} µm on {} points over a {} mm patch",
            1000.0 * e.plane_mm,
            if e.plane_resolved {
                ""
            } else {
                " (not resolved above the reading noise, within two standard errors; kept as the estimate)"
            },
            1000.0 * t.xi_mm,
            t.points,
            t.patch_mm
        ),
        None => "  no datum-plane error found in the residuals: planes taken as exact".into(),
    });
    if !d.run.outliers.is_empty() {
        let p: Vec<String> = d
            .run
            .outliers
            .iter()
            .map(|o| format!("pose {} ({:.3} mm)", o.pose, o.residual_mm))
            .collect();
        out.push(format!(
            "  left out {} pose(s) that disagree with every model (tracker blunder, spatter): {}; the verdict is on the other {}",
            d.run.outliers.len(),
            p.join(", "),
            d.run.poses.rows.len()
        ));
    }
    out
}

/// Sentences that reconcile flagged statistics with the verdict, so the
/// report never says two things without saying how they fit.
fn reconcile(d: &Diagnosis) -> Vec<String> {
    let flagged: Vec<&Check> = d.checked.checks.iter().filter(|c| c.flagged).collect();
    if flagged.is_empty() || d.decided.effect == Effect::Unexplained {
        return Vec::new();
    }
    let what: Vec<&str> = flagged.iter().map(|c| c.what.as_str()).collect();
    let gain_um =
        1000.0 * (d.scores.base.heldout_rms_mm - d.scores.extended.heldout_rms_mm).max(0.0);
    vec![if d.decided.effect == Effect::None {
        format!(
            "the statistics flagged above ({}) differ from the simulation, but no candidate turns that into a better held-out prediction and no structure remains: below the level that matters for the normal",
            what.join("; ")
        )
    } else {
        format!(
            "the statistics flagged above ({}) are what {} explains: held-out RMS {:.1} µm lower with it",
            what.join("; "),
            d.decided.effect.name(),
            gain_um
        )
    }]
}

/// A fitted extension in units a metrology engineer reads: gain in %,
/// linearity as µm at the run's range ends, incidence in µm at 30°,
/// carry-over in % (and the sensor it comes from), thermal in µm/°C, drift in µm/min.
pub fn physical(e: Effect, f: &perpend_calib::candidates::SensorFit, span: f64) -> String {
    let x = &f.sensor.ext;
    let sd = |j: usize| f.sigma.get(j).copied().unwrap_or(0.0);
    let inc30 = 1.0 / (30f64.to_radians().cos()) - 1.0;
    match e {
        Effect::Gain => format!("gain {:+.3} % ± {:.3} %", 100.0 * x.gain, 100.0 * sd(0)),
        Effect::Nonlinearity => {
            let at = |s: f64| 1000.0 * (x.nonlinearity[0] * s * s + x.nonlinearity[1] * s * s * s);
            format!(
                "gain {:+.3} % ± {:.3} %, linearity error {:+.1} µm at −{span:.1} mm and {:+.1} µm at +{span:.1} mm",
                100.0 * x.gain,
                100.0 * sd(0),
                at(-span),
                at(span)
            )
        }
        Effect::LinearityTable => {
            let k = x.table.knots;
            let at: Vec<String> = k
                .iter()
                .map(|s| format!("{:+.1}", 1000.0 * x.table.value(*s)))
                .collect();
            // A table fitted with a ridge is shrunk toward a line (its 1σ
            // are those of the penalised fit).
            let ridge = if f.terms.ridge > 0.0 {
                format!(", ridge {}", f.terms.ridge)
            } else {
                String::new()
            };
            format!(
                "gain {:+.3} % ± {:.3} %, table error [{}] µm at knots [{}] mm{ridge}",
                100.0 * x.gain,
                100.0 * sd(0),
                at.join(", "),
                k.iter()
                    .map(|s| format!("{s:+.2}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }
        Effect::Incidence => perpend_calib::candidates::incidence_words(x, sd(0), inc30),
        Effect::Crosstalk => format!(
            "carry-over {:+.2} % ± {:.2} % from sensor {}",
            100.0 * x.crosstalk,
            100.0 * sd(0),
            f.source + 1
        ),
        Effect::Thermal => format!(
            "thermal {:+.2} µm/°C ± {:.2}",
            1000.0 * x.thermal,
            1000.0 * sd(0)
        ),
        Effect::Drift => format!(
            "drift {:+.3} µm/min ± {:.3}",
            60_000.0 * x.drift,
            60_000.0 * sd(0)
        ),
        Effect::None | Effect::Unexplained => String::new(),
    }
}

/// The time-like effects among `named` (thermal, drift), `+`-joined: the
/// one an `inseparable` line says fits better.
fn time_like(named: &[Effect]) -> String {
    named
        .iter()
        .filter(|e| matches!(e, Effect::Thermal | Effect::Drift))
        .map(|e| e.name())
        .collect::<Vec<_>>()
        .join(" + ")
}
