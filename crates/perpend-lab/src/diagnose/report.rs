//! The readable report of `perpend diagnose` and the comparisons of
//! measured statistics with the simulated expectation behind its first
//! section ("what the simulation gets wrong").
//!
//! Every comparison is `z = (measured − simulated mean) / spread`, the
//! spread being the predictive standard deviation over the Monte-Carlo
//! draws, floored by the sampling spread of an ideal run (RMS:
//! `rms/√(2n)`; lag-1 autocorrelation: `1/√pairs`; runs test: 1; R² of
//! `p` regressors: `√(2p)/n`). A statistic is flagged when `|z|` exceeds
//! the two-sided Student-t quantile at the diagnosis' level α split over
//! all checks (Bonferroni), with `draws − 1` degrees of freedom.

use std::fmt::Write as _;
use std::path::Path;

use super::candidates::Effect;
use super::expect::{Analysis, Expectation, Spread};
use super::select::Decision;
use super::stats;
use super::{Check, Diagnosis, Settings};

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

/// The comparisons of the measured run with the simulation.
pub fn checks(m: &Analysis, e: &Expectation, models: &[Effect], dec: &Decision) -> Vec<Check> {
    // Two-sided, Bonferroni over the checks, Student t with draws − 1
    // degrees of freedom: a flag is a finding, not one of many chances.
    let n_checks = 3 + m.insample.first().map_or(0, Vec::len) + models.len();
    let alpha = dec.alpha / (2.0 * n_checks as f64);
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

/// Plain-language statements of what the simulation gets wrong.
pub fn statements(d: &Diagnosis) -> Vec<String> {
    let mut out = Vec::new();
    let flagged: Vec<&Check> = d.checks.iter().filter(|c| c.flagged).collect();
    if flagged.is_empty() {
        out.push(
            "Nothing measured lies outside the simulated spread: the paper's model with the datasheet noise and the tracker noise reproduces these residuals."
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

fn coeff_unit(e: Effect) -> &'static [&'static str] {
    match e {
        Effect::Gain => &["gain [-]"],
        Effect::Nonlinearity => &["gain [-]", "quadratic [1/mm]", "cubic [1/mm²]"],
        Effect::Incidence => &["incidence [mm]"],
        Effect::Crosstalk => &["crosstalk [-]"],
        Effect::Thermal => &["thermal [mm/°C]"],
        Effect::Drift => &["drift [mm/s]"],
        Effect::None | Effect::Unexplained => &[],
    }
}

/// The readable report.
pub fn text(d: &Diagnosis, sensors: &Path, poses: &Path, s: &Settings) -> String {
    let mut o = String::new();
    let n_read = d.measured.insample.iter().flatten().flatten().count();
    let _ = writeln!(
        o,
        "perpend diagnose: {} + {}",
        sensors.display(),
        poses.display()
    );
    let mut cols = Vec::new();
    if d.poses.has_time() {
        cols.push("t_s");
    }
    if d.poses.has_temperature() {
        cols.push("temp_c");
    }
    let _ = writeln!(
        o,
        "run: {} poses, {} sensors, {} readings{}",
        d.poses.rows.len(),
        d.nominal.len(),
        n_read,
        if cols.is_empty() {
            String::new()
        } else {
            format!("; columns {}", cols.join(", "))
        }
    );
    let sig: Vec<String> = d.noise.sigma.iter().map(|x| format!("{x:.4}")).collect();
    let _ = writeln!(
        o,
        "noise assumed: reading σ = {} mm ({}), {}",
        sig.join(" / "),
        if s.sigma_mm.is_some() {
            "--sigma-mm"
        } else {
            "sigma_mm column"
        },
        match &d.noise.tracker {
            Some(t) => format!(
                "tracker ξ = {} mm on {} points over a {} mm patch",
                t.xi_mm, t.points, t.patch_mm
            ),
            None => "planes exact (no tracker noise)".into(),
        }
    );
    let _ = writeln!(
        o,
        "expectation: {} Monte-Carlo draws of this head (the paper's model fitted to this run, as truth) on these planes; {}-fold cross-validation by pose (seed {})",
        d.expected.draws, d.folds.k, s.seed
    );

    let _ = writeln!(o, "\nWhat the simulation gets wrong");
    let _ = writeln!(
        o,
        "  {:<44} {:>10}  {:>20}  {:>6}",
        "statistic", "measured", "simulated ± 1σ", "z"
    );
    for c in &d.checks {
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

    let _ = writeln!(
        o,
        "\nCandidates (held-out, {} folds; z* = {:.2}: family level α = {}, Bonferroni over mean and rank tests)",
        d.folds.k, d.decision.z_star, s.rule.alpha
    );
    let _ = writeln!(
        o,
        "  {:<14} {:>6}  {:>13}  {:>17}  {:>7}  {:>7}  beats base",
        "model", "params", "held-out RMS", "simulated floor", "gain z", "rank z"
    );
    for v in &d.decision.verdicts {
        let _ = writeln!(
            o,
            "  {:<14} {:>6}  {:>10.4} mm  {:>8.4} ± {:<6.4}  {:>7}  {:>7}  {}",
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
                format!("{:.1}", v.z)
            },
            if v.effect == Effect::None {
                "–".to_string()
            } else {
                format!("{:.1}", v.z_rank)
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
    for (e, why) in &d.skipped {
        let _ = writeln!(o, "  skipped: {} ({why})", e.name());
    }

    let _ = writeln!(o, "\nVerdict: {}", d.effect.name());
    for r in &d.decision.reasons {
        let _ = writeln!(o, "  {r}");
    }
    if !d.decision.ties.is_empty() {
        let t: Vec<&str> = d.decision.ties.iter().map(|e| e.name()).collect();
        let _ = writeln!(
            o,
            "  note: {} fits within one standard error as well; this run cannot tell them apart (e.g. temperature that follows time)",
            t.join(", ")
        );
    }
    if let Some(f) = d.sigma_factor {
        let sig: Vec<String> = d
            .noise
            .sigma
            .iter()
            .map(|x| format!("{:.4}", x * f))
            .collect();
        let _ = writeln!(
            o,
            "  the residuals would match a reading noise {f:.2}× the datasheet's (σ = {} mm); if the checks above show no structure (white in acquisition order, no regressor explains them), the datasheet σ is optimistic for this cell; otherwise an effect outside the catalogue is at work",
            sig.join(" / ")
        );
    }
    if let Some(f) = d.decision.explained_fraction {
        if d.effect == Effect::Unexplained {
            let _ = writeln!(
                o,
                "  the best candidate removes {:.0}% of the excess mean square over the floor",
                f * 100.0
            );
        }
    }

    if let Some((e, fits)) = &d.refit {
        let _ = writeln!(
            o,
            "\nFitted {} coefficients (all poses, ± 1σ){}",
            e.name(),
            if d.effect == Effect::Unexplained {
                " — partial explanation only"
            } else {
                ""
            }
        );
        let units = coeff_unit(*e);
        for (i, f) in fits.iter().enumerate() {
            let parts: Vec<String> = f
                .coeffs
                .iter()
                .zip(&f.sigma)
                .enumerate()
                .map(|(j, (c, s))| {
                    format!(
                        "{} {:+.4e} ± {:.1e}",
                        units.get(j).copied().unwrap_or("c"),
                        c,
                        s
                    )
                })
                .collect();
            let _ = writeln!(
                o,
                "  sensor {}: {}   (residual RMS {:.4} mm)",
                i + 1,
                parts.join(", "),
                f.rms
            );
        }
        if d.effect != Effect::Unexplained {
            let _ = writeln!(
                o,
                "  store them: perpend diagnose --sensors {} --poses {} --out params.json (parameter JSON with the extension)",
                sensors.display(),
                poses.display()
            );
        }
    }

    let _ = writeln!(o, "\nGain on held-out poses (base → extended)");
    let b: Vec<f64> = d.base_normals.iter().flatten().copied().collect();
    let x: Vec<f64> = d.ext_normals.iter().flatten().copied().collect();
    let _ = writeln!(
        o,
        "  residual RMS        {:.4} → {:.4} mm ({})   simulated floor {:.4} mm",
        d.base.heldout_rms_mm,
        d.extended.heldout_rms_mm,
        pct(d.base.heldout_rms_mm, d.extended.heldout_rms_mm),
        d.expected.rms_of(Effect::None).map_or(0.0, |s| s.mean)
    );
    if !b.is_empty() {
        let _ = writeln!(
            o,
            "  normal error mean   {:.4}° → {:.4}° ({})   simulated {:.4}°",
            stats::mean(&b),
            stats::mean(&x),
            pct(stats::mean(&b), stats::mean(&x)),
            d.expected.normal_err_deg.mean
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
    if d.ext_model == Effect::None {
        let _ = writeln!(o, "  nothing named: the extended model is the base model");
    }
    if d.ext_model == Effect::Incidence {
        let _ = writeln!(
            o,
            "  (incidence: the normal iterates the beam-to-surface angle to convergence; perpend-core's normal::plane stops after two passes, which costs accuracy when the coefficients reach millimetres)"
        );
    }
    o
}
