//! `perpend diagnose`: find what the paper's model misses in a calibration
//! run, name the cause, extend the model and measure the gain.
//!
//! For any run in the exchange format (`sensors.csv` + `poses.csv`),
//! [`diagnose`] is one pass through the stages below, in the order the
//! readings move, each called once, each a module with one input and one
//! output type that reads only the stages before it and the toolbox
//! (checked by `host-tests/tests/diagnose_stages.rs`):
//!
//! * **1, read and check** ([`load`](load::load)): tables + [`Settings`]
//!   → [`load::Loaded`]: the nominal head, the poses that disagree with
//!   every model left out ([`noise::reject`]), the rest re-timed with the
//!   time constants of [`lags`], the folds ([`folds_for`]), the models the
//!   run's columns allow and the declared reading noise.
//! * **2-3, nominal and candidate fits** ([`fits::fit`]): `Loaded` →
//!   [`fits::Fitted`]: the paper's model (Chen eq. 1-9) and every
//!   candidate ([`candidates`]: gain, nonlinearity, incidence, crosstalk,
//!   thermal, drift) cross-validated by pose on the measured run
//!   ([`expect::analyse`], [`cv`]); those outside their physical bounds.
//! * **4-5, noise, held-out scores against their nulls, decision**
//!   ([`decision::decide_run`]): `Loaded` + `Fitted` →
//!   [`decision::Decided`]: the reading noise estimated from the run
//!   ([`noise`]), the effect-free re-simulations at that noise
//!   ([`expect`]: the fitted head as the truth, the same planes and
//!   missing readings, seeded draws analysed like the measured run), the
//!   calibrated decision ([`select`]: paired held-out tests, Bonferroni
//!   level, minimum gain over the noise floor, one-standard-error rule;
//!   `unexplained` when no candidate reaches the floor), the forward
//!   selection of up to [`MAX_EFFECTS`] effects ([`Step`]), the direction
//!   test ([`direction`]) and the named model fitted on all poses.
//! * **6, held-out scores of the verdict** ([`scores::scores`]): the
//!   verdict + `Analysis` + `Loaded` → [`scores::Scores`]: held-out RMS
//!   and normal errors of the paper's and the named model (normals through
//!   `perpend-core` with the extension applied, as on the board).
//! * **7, checks and warnings** ([`checks::compare`]): `Loaded` +
//!   `Fitted` + `Decided` → [`Checks`]: measured statistics against their
//!   simulated spread (RMS, whiteness, structure, each candidate's R²)
//!   and the warnings (excess white noise, thermal and drift confounded).
//!
//! Their outputs side by side are the [`Diagnosis`] ([`diagnosis`]), which
//! the readers (stage 8) take without refitting: the text ([`report`]),
//! the plots ([`plot`]), `--json` ([`Diagnosis::json`]) and `--out`
//! ([`param_file`]: the named model with its extension coefficients and
//! 1σ, as the parameter JSON of [`perpend_formats::paramfile`], and the calibration
//! record). The toolbox the stages share: [`stats`], [`folds`],
//! [`settings`], [`candidates`], [`cv`], [`moments`], [`noise`], [`lags`],
//! [`expect`], [`select`], [`nested`], [`direction`].
//!
//! Limits: the expectation is only as good as the stated noise (datasheet
//! σ, tracker ξ / points / patch: pass your tracker's with `--xi-mm`,
//! `--tracker-points`, `--tracker-patch-mm`); up to [`MAX_EFFECTS`]
//! effects are named by forward selection ([`Step`]); heads of 3 to 8
//! sensors for the normal errors.
//!
//! Everything is seeded: the same files and options give the same report.

pub mod bench;
pub mod blind;
pub mod checks;
pub mod decision;
pub mod diagnosis;
pub mod direction;
pub mod expect;
pub mod fits;
pub mod insample;
pub mod limits;
pub mod load;
pub mod nested;
pub mod plot;
pub mod report;
pub mod scenario;
pub mod scores;
pub mod select;
pub mod settings;
pub mod study;

use anyhow::{anyhow, bail, Context as _, Result};
use serde::{Deserialize, Serialize};

use checks::compare;
pub use checks::{Check, Checks};
use decision::decide_run;
pub use decision::{Step, MAX_EFFECTS};
pub use diagnosis::Diagnosis;
use fits::fit;
use limits::limits;
pub use load::declared_sigma;
use load::load;
pub(crate) use load::reading_span;
use perpend_calib::candidates::{Effect, SensorFit};
use perpend_calib::folds::folds_for;
use perpend_calib::{candidates, lags, noise};
use perpend_formats::exchange::{read_poses, read_sensors, PoseTable, SensorTable};
use perpend_formats::paramfile::ParamFile;
use scores::scores;
pub use scores::Perf;
pub use settings::{
    draws_for, Args, NormalMethod, Settings, DRAWS, LIMIT_DRAWS, SMALL_RUN, SMALL_RUN_DRAWS,
};

/// One candidate in the JSON output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandidateJson {
    /// Model name (`none` = the paper's model).
    pub effect: String,
    /// Held-out residual RMS [mm].
    pub heldout_rms_mm: f64,
    /// Its simulated held-out RMS on effect-free data (the model's own
    /// floor: more parameters predict held-out poses worse) [mm].
    #[serde(default)]
    pub expected_rms_mm: f64,
    /// Parameters of the whole head.
    pub n_params: usize,
}

/// A pose left out of the diagnosis, in the JSON output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutlierJson {
    /// Pose number.
    pub pose: i64,
    /// RMS of its residuals under the model fitted on the rest [mm].
    pub residual_mm: f64,
}

/// An effect named, in the JSON output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EffectJson {
    /// Its name.
    pub effect: String,
    /// Sensors (1-based) whose coefficients differ from 0 by more than 2σ.
    pub sensors: Vec<usize>,
    /// Per sensor: the coefficients (column order of the extension's terms).
    pub coefficients: Vec<Vec<f64>>,
    /// Their 1σ.
    pub sigma: Vec<Vec<f64>>,
    /// Per sensor, in words and physical units.
    pub physical: Vec<String>,
    /// The head's time constant of a time-like effect [s]: the thermal lag
    /// of the sensor bodies, or the settling time of a drift
    /// ([`lags`]); absent when none was fitted (no lag, linear drift).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_constant_s: Option<f64>,
    /// The sensors (1-based) the effect acts on by the nested in-sample
    /// test (Holm over the sensors at α/m; every sensor when only the
    /// head's set passed, `localized` false); absent when that test did
    /// not pass (named by the held-out test alone).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acts_on: Option<ActsOnJson>,
}

/// The sensors an effect acts on, in the JSON output
/// ([`select::NestedTest`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActsOnJson {
    /// Sensors (1-based).
    pub sensors: Vec<usize>,
    /// Whether single sensors' tests found them (not the head's alone).
    pub localized: bool,
    /// p of the head's set, then of each sensor alone.
    pub p: Vec<f64>,
    /// The candidate's level α/m.
    pub level: f64,
}

/// The noise the diagnosis worked with, in the JSON output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NoiseJson {
    /// Declared reading noise per sensor [mm], if any.
    pub declared_mm: Option<Vec<f64>>,
    /// Estimated from the run [mm].
    pub estimated_mm: Vec<f64>,
    /// How: `residuals`, `sample_scatter` or `residual_rms`.
    pub source: String,
    /// RMS datum-plane error at the spots [mm] (0 when planes are taken
    /// as exact).
    pub plane_mm: f64,
    /// Whether that plane error is resolved above the reading noise (two
    /// standard errors) or given by the file's columns; an unresolved
    /// estimate is still simulated.
    #[serde(default)]
    pub plane_resolved: bool,
}

/// The `--json` output: exactly these keys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiagnoseJson {
    /// The name given: the first effect selected, `none` or `unexplained`.
    pub effect: String,
    /// Every effect selected, in order (empty for `none`; for
    /// `unexplained`, what explains part of it).
    pub effects: Vec<EffectJson>,
    /// Poses left out as disagreeing with every model.
    pub outlier_poses: Vec<OutlierJson>,
    /// The noise used.
    pub noise: NoiseJson,
    /// Candidates fitted outside their physical bounds, with the reason.
    pub implausible: Vec<(String, String)>,
    /// Warnings (excess white noise, ...).
    pub warnings: Vec<String>,
    /// Simulated held-out RMS of the base model on effect-free data [mm].
    pub expected_rms_mm: f64,
    /// Folds of the cross-validation behind every held-out figure
    /// ([`folds_for`]).
    pub folds: usize,
    /// Base model.
    pub base: Perf,
    /// Named extension (repeats `base` for none / unexplained).
    pub extended: Perf,
    /// Every model cross-validated.
    pub candidates: Vec<CandidateJson>,
    /// A direction-dependent (hysteresis-like) offset, present only when
    /// found ([`direction`]): the verdict is then `unexplained`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction_offset: Option<DirectionJson>,
    /// A candidate named by its normal cost alone, present only then
    /// ([`select`], "Normal cost").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal_cost: Option<select::NormalCostJson>,
    /// Thermal and drift cannot be told apart on this run, present only
    /// when one of them is named and the temperature follows the time
    /// ([`lags::inseparable`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inseparable: Option<InseparableJson>,
    /// With a `none`: every catalogue candidate's detection limit
    /// ([`limits`]); absent for other verdicts or `--limit-draws 0`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub detection_limits: Vec<LimitJson>,
}

/// A candidate's detection limit, in the JSON output ([`limits`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LimitJson {
    /// The candidate.
    pub effect: String,
    /// The smallest amplitude detected in ≥ 90 % of the effect-free
    /// re-simulations it was injected into, in `unit`; `null` when the run
    /// cannot show the candidate (`reason`).
    pub limit: Option<f64>,
    /// The unit of `limit` and `below` (those of the report's coefficients).
    pub unit: String,
    /// The largest amplitude tried below the limit, which failed (0: none
    /// tried), in `unit`.
    pub below: Option<f64>,
    /// The limit as the coefficient of the candidate's term (as stored;
    /// the linearity forms: peak in mm).
    pub coefficient: Option<f64>,
    /// Draws detected at the limit, of `draws`.
    pub detected: Option<usize>,
    /// Effect-free re-simulations per amplitude.
    pub draws: usize,
    /// The paper's model's held-out normal error at the limit over its
    /// effect-free floor (mean over the draws).
    pub cost: Option<f64>,
    /// The paper's model's held-out RMS at the limit over its effect-free
    /// floor (mean over the draws).
    pub rms_ratio: Option<f64>,
    /// Why there is no limit ("not detectable in this run: …").
    pub reason: Option<String>,
    /// What run would lower the limit, in words.
    pub lowered_by: String,
}

impl LimitJson {
    /// Of the stage's output.
    fn of(l: &limits::Limits) -> Vec<Self> {
        l.limits
            .iter()
            .map(|x| {
                let e = x.effect;
                let f = x.found.as_ref().ok();
                let in_unit = |a: f64| limits::physical(e, a).0;
                Self {
                    effect: e.name().into(),
                    limit: f.map(|f| in_unit(f.amplitude)),
                    unit: limits::physical(e, 1.0).1.into(),
                    below: f.map(|f| in_unit(f.below)),
                    coefficient: f.map(|f| f.amplitude),
                    detected: f.map(|f| f.detected),
                    draws: l.draws,
                    cost: f.map(|f| f.cost),
                    rms_ratio: f.map(|f| f.rms_ratio),
                    reason: x.found.as_ref().err().cloned(),
                    lowered_by: x.lowered_by.clone(),
                }
            })
            .collect()
    }
}

/// Two named time-like effects this run cannot tell apart, in the JSON
/// output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InseparableJson {
    /// The effects (`thermal`, `drift`).
    pub effects: Vec<String>,
    /// Pearson's r of the temperature and the time over the poses kept.
    pub temp_time_r: f64,
    /// The run that would separate them, in words.
    pub separated_by: String,
}

impl InseparableJson {
    /// Of a diagnosis that named `named` on `poses`; `None` when separable.
    fn of(poses: &PoseTable, named: &[Effect]) -> Option<Self> {
        lags::inseparable(poses, named).map(|r| Self {
            effects: vec![Effect::Thermal.name().into(), Effect::Drift.name().into()],
            temp_time_r: r,
            separated_by: lags::SEPARATED_BY.into(),
        })
    }
}

/// A direction-dependent offset found, in the JSON output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DirectionJson {
    /// Per sensor: `h` [mm], the reading is `−h·sign(last move)` off
    /// (`null`: too few moves).
    pub h_mm: Vec<Option<f64>>,
    /// Their 1σ [mm].
    pub sigma_mm: Vec<Option<f64>>,
    /// One-sided p against the effect-free re-simulations.
    pub p: f64,
    /// The level it beat (`α/m`).
    pub level: f64,
    /// The measurement order used: `t_s` or `file order`.
    pub order: String,
}

impl DirectionJson {
    /// Of a test that found an offset; `None` otherwise.
    fn of(t: &direction::DirectionTest) -> Option<Self> {
        match t {
            direction::DirectionTest::Tested(t) if t.found => Some(Self {
                h_mm: t.sensors.iter().map(|s| s.map(|s| s.h_mm)).collect(),
                sigma_mm: t.sensors.iter().map(|s| s.map(|s| s.sigma_mm)).collect(),
                p: t.p,
                level: t.level,
                order: t.order.name().into(),
            }),
            _ => None,
        }
    }
}

/// The `--json` output of a diagnosis (kept beside the JSON types; the
/// report's wording of each effect is [`report::physical`]).
impl Diagnosis {
    /// The `--json` object.
    pub fn json(&self) -> DiagnoseJson {
        use noise::Source;
        let span = reading_span(&self.run.poses, &self.run.refs);
        let steps = self.decided.also.iter().map(|st| {
            let own: Vec<SensorFit> = st.fits.iter().map(|f| own_columns(st.effect, f)).collect();
            (st.effect, own)
        });
        let effects = self
            .decided
            .refit
            .clone()
            .into_iter()
            .chain(steps)
            .map(|(e, fits)| EffectJson {
                effect: e.name().into(),
                sensors: fits
                    .iter()
                    .enumerate()
                    .filter(|(_, f)| {
                        f.coeffs
                            .iter()
                            .zip(&f.sigma)
                            .any(|(c, s)| c.abs() > 2.0 * s)
                    })
                    .map(|(i, _)| i + 1)
                    .collect(),
                coefficients: fits.iter().map(|f| f.coeffs.clone()).collect(),
                sigma: fits.iter().map(|f| f.sigma.clone()).collect(),
                physical: fits.iter().map(|f| report::physical(e, f, span)).collect(),
                time_constant_s: self.time_constant(e),
                acts_on: self.acts_on(e).map(|n| ActsOnJson {
                    sensors: n.acts_on.iter().map(|i| i + 1).collect(),
                    localized: n.localized,
                    p: n.p.clone(),
                    level: n.level,
                }),
            })
            .collect();
        DiagnoseJson {
            effect: self.decided.effect.name().into(),
            effects,
            outlier_poses: self
                .run
                .outliers
                .iter()
                .map(|o| OutlierJson {
                    pose: o.pose,
                    residual_mm: o.residual_mm,
                })
                .collect(),
            noise: NoiseJson {
                declared_mm: self.decided.estimate.declared_mm.clone(),
                estimated_mm: self.decided.estimate.reading_mm.clone(),
                source: match self.decided.estimate.source {
                    Source::Residuals => "residuals",
                    Source::SampleScatter => "sample_scatter",
                    Source::ResidualRms => "residual_rms",
                }
                .into(),
                plane_mm: self.decided.estimate.plane_mm,
                plane_resolved: self.decided.estimate.plane_resolved,
            },
            implausible: self
                .fits
                .implausible
                .iter()
                .map(|(e, w)| (e.name().to_string(), w.clone()))
                .collect(),
            warnings: self.checked.warnings.clone(),
            expected_rms_mm: self.decided.floor_mm,
            folds: self.run.folds.k,
            base: self.scores.base,
            extended: self.scores.extended,
            candidates: self
                .decided
                .decision
                .verdicts
                .iter()
                .map(|v| CandidateJson {
                    effect: v.effect.name().into(),
                    heldout_rms_mm: v.rms,
                    expected_rms_mm: v.expected.mean,
                    n_params: v.n_params,
                })
                .collect(),
            direction_offset: DirectionJson::of(&self.decided.direction),
            normal_cost: select::NormalCostJson::of(&self.decided.decision),
            inseparable: InseparableJson::of(&self.run.poses, &self.effects()),
            detection_limits: LimitJson::of(&self.limits),
        }
    }
}

/// The fit `f` (of several effects) reduced to the coefficients and 1σ of
/// `e`'s own terms (columns in the extension's term order).
pub fn own_columns(e: Effect, f: &SensorFit) -> SensorFit {
    use perpend_core::calib::Term;
    let cols: Vec<usize> = Term::ALL
        .into_iter()
        .filter(|t| f.terms.mask & t.bit() != 0)
        .enumerate()
        .filter(|(_, t)| e.terms().contains(t))
        .map(|(j, _)| j)
        .collect();
    let pick = |v: &[f64]| cols.iter().filter_map(|&j| v.get(j).copied()).collect();
    SensorFit {
        coeffs: pick(&f.coeffs),
        sigma: pick(&f.sigma),
        ..f.clone()
    }
}

/// Runs the diagnosis on a run read from the exchange format, in one pass
/// through the stages (docs/diagnosis.md, "How the code is laid out"),
/// each entered once: read and check ([`load`](load::load)) → nominal and
/// candidate fits ([`fits::fit`]) → noise, effect-free re-simulations and
/// decision ([`decision::decide_run`]) → held-out scores
/// ([`scores::scores`]) → checks and warnings ([`checks::compare`]).
///
/// # Errors
/// A base model that cannot be fitted (the pose set does not identify it),
/// too few poses for the folds.
pub fn diagnose(sensors: &SensorTable, all_poses: &PoseTable, s: &Settings) -> Result<Diagnosis> {
    let mut run = load(sensors, all_poses, s)?;
    let mut fits = fit(&run, s)?;
    let decided = decide_run(&run, &fits, s)?;
    let scores = scores(decided.effect, &decided.also, &fits.measured, &run, s);
    let checked = compare(&run, &fits, &decided);
    let limits = limits(&run, &fits, &decided, s);
    run.skipped.append(&mut fits.failed);
    Ok(Diagnosis {
        run,
        fits,
        decided,
        scores,
        checked,
        limits,
    })
}

/// The parameter file of the named model: every sensor as the decision
/// fitted it on all poses with the named extension (the paper's model for
/// `none` and `unexplained`), with 1σ, residual RMS and identifiability.
/// It reads the diagnosis and never refits.
///
/// # Errors
/// A named model the decision could not fit on all poses; a fit that is
/// not storable ([`candidates::storable`]) or a file that does not
/// validate.
pub fn param_file(d: &Diagnosis) -> Result<ParamFile> {
    let model = d.scores.ext_model;
    let name = if model == Effect::None {
        "base".to_string()
    } else {
        d.effects()
            .iter()
            .map(|e| e.name())
            .collect::<Vec<_>>()
            .join("+")
    };
    let mut f = ParamFile::new("lsq", &name, d.run.poses.rows.len());
    for (i, s) in d.run.nominal.iter().enumerate() {
        let fit = match (&d.decided.refit, model) {
            _ if !d.decided.also.is_empty() => d
                .decided
                .also
                .last()
                .map(|st| st.fits[i].clone())
                .ok_or_else(|| anyhow!("no fit"))?,
            (Some((e, fits)), m) if *e == m => fits[i].clone(),
            (_, Effect::None) => d.fits.measured.base_fit[i].clone(),
            _ => bail!(
                "not stored: the {} model could not be fitted on all {} poses (it was \
                 cross-validated, but the solver failed on the whole run); store the paper's \
                 model with `perpend calibrate`, or rerun with more poses",
                model.name(),
                d.run.poses.rows.len()
            ),
        };
        candidates::storable(i, d.run.nominal.len(), &fit)
            .map_err(|why| anyhow!("not stored: {why}"))?;
        let mut p = candidates::params_of(i, &fit, s);
        // Drift is removed from the estimate, never extrapolated.
        p.fold_drift(lags::run_end_s(&d.run.poses));
        f.sensors.push(p);
    }
    // The sensor bodies' lag, for the board to lag its temperature alike.
    if d.effects().contains(&Effect::Thermal) {
        f.thermal_tau_s = d.run.lags.thermal_tau_s;
    }
    f.validate()?;
    Ok(f)
}

/// Runs `perpend diagnose`.
///
/// # Errors
/// Malformed input (file, line, problem), missing reading noise, a pose set
/// that cannot identify the paper's model, I/O errors of the plots.
pub fn run(a: &Args) -> Result<()> {
    run_to(a, &mut std::io::stdout().lock())
}

/// Runs `perpend diagnose`, writing the report (or the JSON) to `out`.
///
/// # Errors
/// As [`run`]; I/O errors of `out`.
pub fn run_to(a: &Args, out: &mut dyn std::io::Write) -> Result<()> {
    let settings = Settings::from_args(a)?;
    let table = read_sensors(&a.sensors)?;
    let poses = read_poses(&a.poses, Some(table.len()))?;
    let file = a.poses.display().to_string();
    let (poses, left, total) = perpend_formats::plausible::check_run(&file, &table, poses)?;
    let mut d = diagnose(&table, &poses, &settings)?;
    let mut first = perpend_formats::plausible::left_out_lines(&file, &left, total);
    first.append(&mut d.checked.warnings);
    d.checked.warnings = first;
    if let Some(dir) = &a.plot {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        plot::write_all(&d, dir)?;
    }
    let mut record = None;
    if let Some(out) = &a.out {
        let file = param_file(&d)?;
        let previous = perpend_calib::record::Previous::of(out)?;
        file.write(out)?;
        record = Some(write_record(a, &d, &file, previous, out)?);
    }
    if a.json {
        writeln!(
            out,
            "{}",
            perpend_formats::schema::to_json(perpend_formats::schema::DIAGNOSE, &d.json())?
        )?;
    } else {
        write!(
            out,
            "{}",
            report::text(&d, (&a.sensors, &a.poses), a.out.as_deref(), &settings)
        )?;
        if let Some(dir) = &a.plot {
            writeln!(out, "\nplots written to {}", dir.display())?;
        }
        if let Some(path) = &a.out {
            writeln!(
                out,
                "parameters ({} model) written to {}",
                d.scores.ext_model.name(),
                path.display()
            )?;
        }
        if let Some(r) = &record {
            writeln!(out, "calibration record written to {}", r.display())?;
        }
    }
    Ok(())
}

/// Writes the calibration record beside `out` ([`perpend_calib::record`]): the
/// stored model's held-out normal errors of the diagnosis'
/// cross-validation are its verification.
///
/// # Errors
/// An input or `out` unreadable, I/O.
fn write_record(
    a: &Args,
    d: &Diagnosis,
    file: &ParamFile,
    previous: Option<perpend_calib::record::Previous>,
    out: &std::path::Path,
) -> Result<std::path::PathBuf> {
    use perpend_calib::record::{PoseError, Record, Verification, KIND_CROSS_VALIDATED};
    let errs = d
        .run
        .poses
        .rows
        .iter()
        .zip(&d.scores.ext_normals)
        .filter_map(|(row, e)| {
            e.map(|error_deg| PoseError {
                pose: row.pose,
                error_deg,
            })
        })
        .collect();
    let note = format!(
        "held-out normal error of every pose of the {} model: {}-fold cross-validation by pose \
         (seed {}), each pose measured by the head fitted on the other folds, against its plane \
         normal; includes the reading noise",
        file.model, d.run.folds.k, a.seed
    );
    let v = Verification::from_errors(KIND_CROSS_VALIDATED, &note, errs);
    let mut r = Record::new(&[&a.sensors, &a.poses], file)?
        .with_verification(v)
        .with_dropped(d.run.outliers.iter().map(Into::into).collect())
        .with_previous(previous);
    r.push_event(&format!("perpend diagnose wrote {}", out.display()));
    r.write_beside(out)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_calib::sim::{paper_head, simulate, SimConfig};
    use rand::SeedableRng;

    /// A run below 100 poses is cross-validated with 10 folds (at most half
    /// its poses, at least 5), a larger one with 5, and `--folds` overrides
    /// either; the fold count the diagnosis used is the one it reports. The
    /// draws follow the same split.
    #[test]
    fn runs_take_ten_folds_or_half_their_poses_below_100() {
        let head = paper_head().unwrap();
        let table =
            perpend_formats::exchange::SensorTable::from_sensors(&head.nominal, head.sigma_mm);
        let run_of = |n: usize| {
            let mut cfg = SimConfig::paper();
            cfg.poses = n;
            let mut rng = rand::rngs::StdRng::seed_from_u64(5);
            simulate(&head, &cfg, &[], &mut rng).unwrap().poses
        };
        for (n, requested, k) in [
            (30, None, 10),
            (60, None, 10),
            (120, None, 5),
            (14, None, 7),
            (30, Some(5), 5),
            (12, None, 6),
        ] {
            let poses = run_of(n);
            let s = Settings {
                folds: requested,
                draws: Some(3),
                limit_draws: 0,
                ..Settings::default()
            };
            let d = diagnose(&table, &poses, &s).unwrap();
            assert_eq!(
                (d.run.folds.k, d.run.folds.of_pose.len()),
                (k, n),
                "{n} poses"
            );
        }
        // Too few poses for the folds asked for: a clear error.
        let err = diagnose(&table, &run_of(8), &Settings::default()).unwrap_err();
        assert!(err.to_string().contains("5-fold"), "{err}");
        // ... and twice the effect-free draws, unless asked otherwise.
        assert_eq!(
            [
                draws_for(30, None),
                draws_for(60, None),
                draws_for(30, Some(5))
            ],
            [16, 8, 5]
        );
        let d = diagnose(&table, &run_of(20), &Settings::default()).unwrap();
        assert_eq!(d.decided.expected.draws, 16);
    }
}
