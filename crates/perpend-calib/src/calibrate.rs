//! `perpend calibrate`: calibrate a sensor head from a calibration run in
//! the exchange format, with batch least squares (default) or the paper's
//! EKF, print per-sensor corrections with 1σ, residual RMS and
//! identifiability, and write the parameter JSON ([`perpend_formats::paramfile`]).
//!
//! Malformed input is an error naming the file, line and problem; a pose
//! set that cannot identify a sensor's parameters is an error naming what
//! it lacks. Either way nothing is written and the exit code is non-zero.

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::{bail, Result};
use nalgebra::Vector3;
use perpend_core::calib::{
    assess, ekf_sensor, CovarianceUpdate, Diagnostic, EkfConfig, EkfFit, Innovation, LsqConfig,
    Poses, Status,
};
use perpend_core::head::Sensor;
use perpend_core::model::distance;

use crate::candidates::{self, Effect, Refs};
pub use crate::lags::run_end_s;
use perpend_formats::exchange::{read_poses, read_sensors, PoseTable};
use perpend_formats::paramfile::{Identifiability, ParamFile, SensorParams, Triples};

/// Estimator.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Batch Gauss-Newton / Levenberg-Marquardt, 5 parameters per sensor.
    Lsq,
    /// The paper's EKF (Chen eq. 10-16), 6 states per sensor.
    Ekf,
}

/// The reading model to fit: the paper's, or the paper's plus one
/// extension of [`perpend_core::ext`] (what `perpend diagnose` names).
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    /// Zero point + beam direction (Chen §3.1).
    Base,
    /// + per-sensor scale error of the analog chain.
    Gain,
    /// + per-sensor gain, quadratic and cubic linearity error.
    Nonlinearity,
    /// + per-sensor gain and a linearity table (natural spline, 5 knots).
    #[value(name = "linearity_table")]
    LinearityTable,
    /// + bias with the beam's incidence angle on the surface.
    Incidence,
    /// + carry-over from the previously converted channel.
    Crosstalk,
    /// + drift with the head temperature (`temp_c`).
    Thermal,
    /// + drift with time (`t_s`).
    Drift,
}

impl Model {
    /// The diagnosis' name of the model.
    pub fn effect(self) -> Effect {
        match self {
            Model::Base => Effect::None,
            Model::Gain => Effect::Gain,
            Model::Nonlinearity => Effect::Nonlinearity,
            Model::LinearityTable => Effect::LinearityTable,
            Model::Incidence => Effect::Incidence,
            Model::Crosstalk => Effect::Crosstalk,
            Model::Thermal => Effect::Thermal,
            Model::Drift => Effect::Drift,
        }
    }
}

/// Noise settings of the EKF, as printed in the paper.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum EkfPreset {
    /// §5 step 7: Q = 1e-10·I, R = 8e-5.
    Simulation,
    /// §6: Q = 1e-12·I, R = 9e-6.
    Experiment,
    /// §3.2 text: Q = 1e-10·I, R = 1e-4.
    Section3,
}

impl EkfPreset {
    /// The configuration of the preset.
    pub fn config(self) -> EkfConfig<f64> {
        match self {
            EkfPreset::Simulation => EkfConfig::chen_simulation(),
            EkfPreset::Experiment => EkfConfig::chen_experiment(),
            EkfPreset::Section3 => EkfConfig::chen_section3(),
        }
    }
}

/// `poses` (the run without the outliers of `all`) re-timed for `model`:
/// a thermal lag or a settling drift with the time constant the diagnosis
/// would choose ([`crate::lags`]), the lag filtering every pose's
/// temperature, the outliers' included. The lag goes to `file`, the choice
/// to `report`.
fn retime(
    model: Effect,
    nominal: &[perpend_core::head::Sensor<f64>],
    (all, outliers): (&PoseTable, &[crate::noise::Outlier]),
    poses: &PoseTable,
    report: &mut String,
    file: &mut ParamFile,
) -> PoseTable {
    use crate::{lags, noise};
    if !matches!(model, Effect::Thermal | Effect::Drift) {
        return poses.clone();
    }
    let chosen = lags::select(nominal, poses, &[model], &LsqConfig::default());
    lag_lines(model, &chosen, report);
    if model == Effect::Thermal {
        file.thermal_tau_s = chosen.thermal_tau_s;
    }
    noise::without(&lags::apply(all, &chosen), outliers)
}

/// Reports the time constant of a thermal lag or a settling drift.
fn lag_lines(model: Effect, lags: &crate::lags::Lags, report: &mut String) {
    if model == Effect::Thermal && lags.thermal_tau_s > 0.0 {
        let _ = writeln!(
            report,
            "thermal lag: the sensor bodies follow the logged temperature with τ = {:.0} s",
            lags.thermal_tau_s
        );
    }
    if model == Effect::Drift && lags.drift_tau_s.is_finite() {
        let _ = writeln!(
            report,
            "drift settles with τ = {:.0} s (coefficients: its initial rate; what it still has to come after the run is neither folded nor applied)",
            lags.drift_tau_s
        );
    }
}

/// Refuses a model whose fit the board could not reproduce in use
/// (issue 11 item 8), with the reason: the thermal term is applied with
/// the temperature the board measures (its die sensor), so every pose of
/// the log needs that temperature in `temp_c` (`perpend node capture`
/// records it); drift needs `t_s` on every pose to be separated from the
/// geometry, and is then folded into the zero points at the run's end,
/// never applied in use ([`SensorParams::fold_drift`]).
///
/// # Errors
/// The model and what the log lacks.
fn board_can_apply(model: Effect, poses: &PoseTable) -> Result<()> {
    let missing = |f: fn(&perpend_formats::exchange::PoseRow) -> bool| {
        poses.rows.iter().filter(|r| !f(r)).map(|r| r.line).next()
    };
    match model {
        Effect::Thermal => {
            if let Some(line) = missing(|r| r.temp_c.is_some()) {
                bail!(
                    "--model thermal: pose on line {line} has no temp_c; the board corrects with the \
                     temperature it measures (die sensor), so every pose needs that temperature \
                     (perpend node capture records it)"
                );
            }
        }
        Effect::Drift => {
            if let Some(line) = missing(|r| r.t_s.is_some()) {
                bail!(
                    "--model drift: pose on line {line} has no t_s; drift is separated from the \
                     geometry by the time of each pose (and folded into the zero points at the \
                     run's end: the board never extrapolates it)"
                );
            }
        }
        _ => {}
    }
    Ok(())
}

/// Folds the sensor's drift into its zero point at the run's end
/// ([`SensorParams::fold_drift`]) and says so in the report.
fn fold_drift(p: &mut SensorParams, t_end_s: f64, report: &mut String) {
    let rate = p.ext.drift_mm_per_s;
    let c = p.fold_drift(t_end_s);
    let _ = writeln!(
        report,
        "  drift {:+.2} µm/min (initial rate): the zero point is referred to the run's end \
         ({:+.4} mm along the beam, the drift accumulated over the run); the board applies no \
         drift (it is never extrapolated)",
        rate * 6e4,
        -c
    );
}

/// Arguments of `perpend calibrate`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The nominal head (sensors.csv).
    #[arg(long)]
    pub sensors: PathBuf,
    /// The calibration run (poses.csv).
    #[arg(long)]
    pub poses: PathBuf,
    /// Estimator.
    #[arg(long, value_enum, default_value_t = Method::Lsq)]
    pub method: Method,
    /// Reading model: the paper's (`base`) or with one extension, whose
    /// coefficients the parameter file carries and the board applies
    /// (least squares only).
    #[arg(long, value_enum, default_value_t = Model::Base)]
    pub model: Model,
    /// Write the calibrated parameters (JSON) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// EKF noise preset.
    #[arg(long, value_enum, default_value_t = EkfPreset::Simulation)]
    pub ekf_preset: EkfPreset,
    /// EKF: override R [mm²].
    #[arg(long)]
    pub ekf_r: Option<f64>,
    /// EKF: override the diagonal of Q.
    #[arg(long)]
    pub ekf_q: Option<f64>,
    /// EKF: override the stopping threshold δ.
    #[arg(long)]
    pub ekf_delta: Option<f64>,
    /// EKF: use the nonlinear innovation d_meas − f(Φ̂) instead of the
    /// paper's linearised one.
    #[arg(long)]
    pub ekf_nonlinear: bool,
    /// EKF: Joseph-form covariance update instead of eq. 15.
    #[arg(long)]
    pub ekf_joseph: bool,
    /// Keep every pose: do not leave out poses that disagree with every
    /// model (tracker blunders), which are otherwise reported and dropped.
    #[arg(long)]
    pub keep_outliers: bool,
}

/// The EKF configuration from the arguments.
pub fn ekf_config(a: &Args) -> EkfConfig<f64> {
    let mut c = a.ekf_preset.config();
    if let Some(r) = a.ekf_r {
        c.r = r;
    }
    if let Some(q) = a.ekf_q {
        c.q = nalgebra::SVector::<f64, 6>::from_element(q);
    }
    if let Some(d) = a.ekf_delta {
        c.delta = d;
    }
    if a.ekf_nonlinear {
        c.innovation = Innovation::Nonlinear;
    }
    if a.ekf_joseph {
        c.covariance = CovarianceUpdate::Joseph;
    }
    c
}

/// Residual RMS [mm] of `sensor` (index `idx`) over the run.
pub fn residual_rms(sensor: &Sensor<f64>, idx: usize, poses: &PoseTable) -> Option<f64> {
    let mut ss = 0.0;
    let mut m = 0usize;
    for k in 0..poses.len() {
        if let Some(d) = poses.reading(k, idx) {
            if let Ok(f) = distance(sensor, &poses.plane(k), idx) {
                ss += (d - f) * (d - f);
                m += 1;
            }
        }
    }
    (m > 0).then(|| (ss / m as f64).sqrt())
}

fn ident_json(d: &Diagnostic<f64>) -> Identifiability {
    Identifiability::from(d)
}

/// The paper's EKF on every sensor.
pub fn run_ekf(
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    cfg: EkfConfig<f64>,
) -> Vec<perpend_core::Result<EkfFit<f64>>> {
    nominal
        .iter()
        .enumerate()
        .map(|(i, s)| ekf_sensor(s, i, poses, cfg))
        .collect()
}

/// Parameters of an EKF fit for the JSON file (1σ from the filter's `P`).
pub fn ekf_params(
    idx: usize,
    fit: &EkfFit<f64>,
    nominal: &Sensor<f64>,
    poses: &PoseTable,
    diag: Option<&Diagnostic<f64>>,
) -> SensorParams {
    let mut p = SensorParams::from_sensor(idx + 1, &fit.sensor, Some(nominal));
    let sd = |i: usize| fit.covariance[(i, i)].max(0.0).sqrt();
    p.sigma = Some(Triples {
        zero_mm: [sd(0), sd(1), sd(2)],
        dir: [sd(3), sd(4), sd(5)],
    });
    p.residual_rms_mm = residual_rms(&fit.sensor, idx, poses);
    p.readings = fit.used;
    p.identifiability = diag.map(ident_json);
    p
}

/// The beam direction's correction as two tilts [mrad] in the nominal
/// beam's tangent basis ([`perpend_core::geometry::tangent_basis`]: α
/// around the cone, β towards or away from the axis, the units `plan`
/// prints), with their 1σ from the components' 1σ `sd` (no covariance).
fn tilts_mrad(nominal: &Vector3<f64>, fitted: &Vector3<f64>, sd: [f64; 3]) -> [(f64, f64); 2] {
    let u = nominal.normalize();
    let f = fitted.normalize();
    let (e1, e2) = perpend_core::geometry::tangent_basis(&u);
    let sigma = |e: &Vector3<f64>| (0..3).map(|j| (e[j] * sd[j]).powi(2)).sum::<f64>().sqrt();
    [
        (1000.0 * f.dot(&e1), 1000.0 * sigma(&e1)),
        (1000.0 * f.dot(&e2), 1000.0 * sigma(&e2)),
    ]
}

fn fmt_sensor_table(
    out: &mut String,
    nominal: &Sensor<f64>,
    fitted: &Sensor<f64>,
    sigma: ([f64; 3], [f64; 3]),
) {
    let [(a, sa), (b, sb)] = tilts_mrad(&nominal.dir, &fitted.dir, sigma.1);
    let rows = [
        ("x", "mm", nominal.zero.x, fitted.zero.x, sigma.0[0]),
        ("y", "mm", nominal.zero.y, fitted.zero.y, sigma.0[1]),
        ("z", "mm", nominal.zero.z, fitted.zero.z, sigma.0[2]),
        ("α", "mrad", 0.0, a, sa),
        ("β", "mrad", 0.0, b, sb),
    ];
    let _ = writeln!(
        out,
        "              nominal    calibrated    correction        1σ"
    );
    for (name, unit, n, f, s) in rows {
        let _ = writeln!(
            out,
            "  {:<8}  {n:>10.4}  {f:>12.6}  {:>+12.6}  {s:>9.6}",
            format!("{name} [{unit}]"),
            f - n
        );
    }
    let _ = writeln!(
        out,
        "  (α, β: tilts of the beam direction around the cone and towards the axis, {:.3} mrad in all; the components m, n, q are in the parameter file)",
        1000.0 * angle_deg(&nominal.dir, &fitted.dir).to_radians()
    );
}

/// The same rejection as `perpend diagnose`: poses that disagree with the
/// paper's model and every candidate are left out (none with
/// `--keep-outliers`) and named in `report`.
fn reject_outliers(
    a: &Args,
    nominal: &[Sensor<f64>],
    all_poses: &PoseTable,
    report: &mut String,
) -> Vec<crate::noise::Outlier> {
    if a.keep_outliers {
        return Vec::new();
    }
    let outliers = crate::noise::reject(
        nominal,
        all_poses,
        &LsqConfig::default(),
        &crate::candidates::available_models(all_poses),
    );
    if !outliers.is_empty() {
        let p: Vec<String> = outliers
            .iter()
            .map(|o| format!("pose {} ({:.3} mm RMS)", o.pose, o.residual_mm))
            .collect();
        let _ = writeln!(
            report,
            "left out {} of {} poses that disagree with every model (tracker blunder, spatter; --keep-outliers keeps them): {}",
            outliers.len(),
            all_poses.rows.len(),
            p.join(", ")
        );
    }
    outliers
}

/// What one calibration produced: the report, the parameter file, and the
/// sensors that failed (nothing is written then).
struct Outcome {
    report: String,
    file: ParamFile,
    failures: Vec<String>,
    /// The expected normal error (RMS, 95 %) [deg], when computed.
    expected: Option<(f64, f64)>,
    /// Held-out normal errors (pose, deg), when asked for (`--out`, lsq).
    heldout: Option<Vec<crate::record::PoseError>>,
}

/// Least squares with `model` on every sensor (the run re-timed for a
/// thermal lag or a settling drift), then the expected accuracy.
fn calibrate_lsq(
    model: Effect,
    nominal: &[Sensor<f64>],
    all: (&PoseTable, &[crate::noise::Outlier]),
    poses: &PoseTable,
    o: &mut Outcome,
    verify: bool,
) {
    let poses = retime(model, nominal, all, poses, &mut o.report, &mut o.file);
    // The table's knots and ridge as the diagnosis chooses them.
    let refs = Refs::of(&poses).with_table_choice(nominal, &poses, model, &LsqConfig::default());
    if model != Effect::None {
        let _ = writeln!(
            o.report,
            "model: zero point + beam direction + {} ({})",
            model.name(),
            model.regressor_label()
        );
    }
    let mut geometry = Vec::new();
    for (i, s) in nominal.iter().enumerate() {
        let _ = writeln!(o.report);
        match candidates::fit(s, i, &poses, refs.terms(model, i), &LsqConfig::default()) {
            Ok(fit) => {
                lsq_sensor_lines(&mut o.report, i, s, &fit);
                let mut p = candidates::params_of(i, &fit, s);
                if model == Effect::Drift {
                    fold_drift(&mut p, run_end_s(&poses), &mut o.report);
                }
                o.file.sensors.push(p);
                geometry.push(fit.sensor);
            }
            Err(e) => {
                let _ = writeln!(o.report, "sensor {}: FAILED", i + 1);
                let _ = writeln!(o.report, "  {e}");
                o.failures.push(with_sensor(i, &e.to_string()));
            }
        }
    }
    if o.failures.is_empty() {
        o.expected = expected_accuracy(&mut o.report, &geometry, nominal, (&poses, &refs), model);
        if verify {
            o.heldout = heldout_errors(model, nominal, &poses, &mut o.report);
        }
    }
}

/// `why` prefixed by "sensor N: " unless it already names the sensor so
/// (the identifiability diagnostic does): never "sensor 2: sensor 2:".
pub fn with_sensor(i: usize, why: &str) -> String {
    let name = format!("sensor {}: ", i + 1);
    if why.starts_with(&name) {
        why.to_string()
    } else {
        name + why
    }
}

/// Held-out normal errors of every pose by k-fold cross-validation by pose
/// (the folds `perpend diagnose` uses, [`crate::folds::folds_for`],
/// seed 1): each pose measured by the head fitted with `model` on the other
/// folds, against the pose's plane normal. `None` (and a line in the
/// report) when a fold cannot be fitted.
fn heldout_errors(
    model: Effect,
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    report: &mut String,
) -> Option<Vec<crate::record::PoseError>> {
    use crate::cv;
    let folds = cv::Folds::new(
        poses.rows.len(),
        crate::folds::folds_for(poses.rows.len(), None),
        1,
    );
    let refs = Refs::of(poses);
    let cfg = LsqConfig::default();
    match cv::cross_validate(model, nominal, poses, &refs, &folds, &cfg) {
        Ok(r) => {
            let m = perpend_core::normal::Method::LeastSquares;
            let errs = cv::normal_errors(&r, poses, &folds, m);
            Some(
                poses
                    .rows
                    .iter()
                    .zip(errs)
                    .filter_map(|(row, e)| {
                        e.map(|error_deg| crate::record::PoseError {
                            pose: row.pose,
                            error_deg,
                        })
                    })
                    .collect(),
            )
        }
        Err(e) => {
            let _ = writeln!(report, "held-out verification: not computed ({e})");
            None
        }
    }
}

/// The report of one sensor's least-squares fit: geometry against the
/// nominal, the extension's coefficients, the ridge, the identifiability.
fn lsq_sensor_lines(
    report: &mut String,
    i: usize,
    nominal: &Sensor<f64>,
    fit: &candidates::SensorFit,
) {
    let _ = writeln!(
        report,
        "sensor {}: {} readings, residual RMS {:.4} mm",
        i + 1,
        fit.used,
        fit.rms
    );
    fmt_sensor_table(
        report,
        nominal,
        &fit.sensor,
        (fit.sigma_zero, fit.sigma_dir),
    );
    for (j, (c, sd)) in fit.coeffs.iter().zip(&fit.sigma).enumerate() {
        let _ = writeln!(
            report,
            "  {:<12} {c:>+14.6e}  1σ {sd:.2e}",
            perpend_core::calib::Regressors::<f64>::name(&fit.terms, j)
        );
    }
    if fit.terms.ridge > 0.0 {
        let _ = writeln!(
            report,
            "  table ridge {} (chosen by held-out error: table and gain shrunk toward the paper's model; their 1σ are the penalised fit's)",
            fit.terms.ridge
        );
    }
    let _ = writeln!(report, "  {}", fit.diagnostic);
}

/// The paper's EKF on every sensor; a sensor the pose set cannot identify
/// fails before the filter's figures are believed.
///
/// # Errors
/// Settings the filter cannot run with.
fn calibrate_ekf(
    a: &Args,
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    o: &mut Outcome,
) -> Result<()> {
    let cfg = ekf_config(a);
    cfg.validate()
        .map_err(|e| anyhow::anyhow!("EKF settings: {e}"))?;
    let _ = writeln!(
        o.report,
        "EKF: Q = {:e}·I, R = {:e}, P0 = I, X0 = 0, δ = {:e}, {:?} innovation, {:?} covariance update",
        cfg.q[0], cfg.r, cfg.delta, cfg.innovation, cfg.covariance
    );
    for (i, r) in run_ekf(nominal, poses, cfg).iter().enumerate() {
        let _ = writeln!(o.report);
        let diag = assess(&nominal[i], i, poses, &Default::default()).ok();
        if let Some(d) = diag.filter(|d| d.status == Status::NotIdentifiable) {
            let _ = writeln!(o.report, "sensor {}: FAILED", i + 1);
            let _ = writeln!(o.report, "  {d}");
            o.failures.push(d.to_string());
            continue;
        }
        match r {
            Ok(fit) => {
                ekf_sensor_lines(&mut o.report, i, &nominal[i], fit, poses, diag.as_ref());
                o.file
                    .sensors
                    .push(ekf_params(i, fit, &nominal[i], poses, diag.as_ref()));
            }
            Err(e) => {
                let _ = writeln!(o.report, "sensor {}: FAILED: {e}", i + 1);
                o.failures.push(with_sensor(i, &e.to_string()));
            }
        }
    }
    Ok(())
}

/// The report of one sensor's EKF fit: readings used until the stop,
/// geometry against the nominal with the filter's own `P`, and what that
/// `P` is not.
fn ekf_sensor_lines(
    report: &mut String,
    i: usize,
    nominal: &Sensor<f64>,
    fit: &EkfFit<f64>,
    poses: &PoseTable,
    diag: Option<&Diagnostic<f64>>,
) {
    let rms = residual_rms(&fit.sensor, i, poses).unwrap_or(f64::NAN);
    let _ = writeln!(
        report,
        "sensor {}: {} of {} readings used until the stop ({}), residual RMS {:.4} mm",
        i + 1,
        fit.used,
        fit.available,
        if fit.converged {
            "stopping rule met"
        } else {
            "stopping rule not met: all readings used"
        },
        rms
    );
    let sd = |j: usize| fit.covariance[(j, j)].max(0.0).sqrt();
    fmt_sensor_table(
        report,
        nominal,
        &fit.sensor,
        ([sd(0), sd(1), sd(2)], [sd(3), sd(4), sd(5)]),
    );
    let _ = writeln!(
        report,
        "  (1σ column: the filter's internal covariance P, m, n, q before normalisation;\n   \
         not a confidence: the paper's filter stops early and its P does not cover the\n   \
         estimate's actual error; `--method lsq` gives 1σ and an expected accuracy to plan with)"
    );
    if let Some(d) = diag {
        let _ = writeln!(report, "  {d}");
    }
}

/// The declared `sigma_mm` of each sensor against its residual RMS (an
/// upper bound of its noise: a declared value 5× above it is a mistake of
/// units, [`perpend_formats::plausible::sigma_warning`]).
pub fn sigma_warnings(
    table: &perpend_formats::exchange::SensorTable,
    file: &ParamFile,
) -> Vec<String> {
    table
        .rows
        .iter()
        .zip(&file.sensors)
        .filter_map(|(row, p)| {
            perpend_formats::plausible::sigma_warning(
                &format!("sensor {}", row.sensor),
                row.sigma_mm?,
                p.residual_rms_mm?,
                "the calibration's residual RMS",
                true,
            )
        })
        .collect()
}

/// Runs `perpend calibrate`: bad poses → the run's model checked against
/// what the board applies → least squares or the EKF per sensor → report
/// → parameter file (only when every sensor calibrated).
///
/// # Errors
/// Malformed input, unidentifiable pose sets, estimator failures, I/O.
pub fn run(a: &Args) -> Result<()> {
    let table = read_sensors(&a.sensors)?;
    let all_poses = read_poses(&a.poses, Some(table.len()))?;
    let nominal = table
        .sensors()
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.sensors.display()))?;
    let (all_poses, left, total) =
        perpend_formats::plausible::check_run(&a.poses.display().to_string(), &table, all_poses)?;
    let mut report = String::new();
    for l in
        perpend_formats::plausible::left_out_lines(&a.poses.display().to_string(), &left, total)
    {
        let _ = writeln!(report, "{l}");
    }
    let outliers = reject_outliers(a, &nominal, &all_poses, &mut report);
    let poses = crate::noise::without(&all_poses, &outliers);
    let method = match a.method {
        Method::Lsq => "lsq",
        Method::Ekf => "ekf",
    };
    if a.model != Model::Base && a.method != Method::Lsq {
        bail!(
            "--model {:?}: extensions are fitted by least squares (--method lsq)",
            a.model
        );
    }
    let model = a.model.effect();
    board_can_apply(model, &poses)?;
    let name = if model == Effect::None {
        "base"
    } else {
        model.name()
    };
    let _ = writeln!(
        report,
        "calibration of {} sensors from {} poses ({}), method {}",
        nominal.len(),
        poses.len(),
        a.poses.display(),
        match a.method {
            Method::Lsq => "batch least squares (Levenberg-Marquardt, 5 parameters per sensor)",
            Method::Ekf => "EKF (Chen eq. 10-16, 6 states per sensor)",
        }
    );
    let mut o = Outcome {
        report,
        file: ParamFile::new(method, name, poses.len()),
        failures: Vec::new(),
        expected: None,
        heldout: None,
    };
    let verify = a.out.is_some();
    match a.method {
        Method::Lsq => calibrate_lsq(
            model,
            &nominal,
            (&all_poses, &outliers),
            &poses,
            &mut o,
            verify,
        ),
        Method::Ekf => calibrate_ekf(a, &nominal, &poses, &mut o)?,
    }
    for w in sigma_warnings(&table, &o.file) {
        let _ = writeln!(o.report, "\nwarning: {w}");
    }
    print!("{}", o.report);
    if !o.failures.is_empty() {
        bail!(
            "calibration failed for {} of {} sensors; no parameters written:\n  {}",
            o.failures.len(),
            nominal.len(),
            o.failures.join("\n  ")
        );
    }
    if let Some(out) = &a.out {
        o.file.validate()?;
        let previous = crate::record::Previous::of(out)?;
        o.file.write(out)?;
        println!("\nwrote {}", out.display());
        let rec = write_record(a, &o, &outliers, previous, out)?;
        println!("wrote {}", rec.display());
    }
    Ok(())
}

/// Writes the calibration record beside `out` ([`crate::record`]): inputs
/// and their hashes, the parameters as written, the poses left out, the
/// held-out verification (or "expected only"), what `out` replaced.
///
/// # Errors
/// An input or `out` unreadable, I/O.
fn write_record(
    a: &Args,
    o: &Outcome,
    outliers: &[crate::noise::Outlier],
    previous: Option<crate::record::Previous>,
    out: &std::path::Path,
) -> Result<PathBuf> {
    use crate::record::{Record, Verification, KIND_CROSS_VALIDATED};
    let v = match &o.heldout {
        Some(errs) => Verification::from_errors(
            KIND_CROSS_VALIDATED,
            &format!(
                "held-out normal error of every pose: {}-fold cross-validation by pose (seed 1), \
                 each pose measured by the head fitted on the other folds, against its plane \
                 normal; includes the reading noise",
                crate::folds::folds_for(o.file.poses, None)
            ),
            errs.clone(),
        ),
        None => Verification::expected_only(match a.method {
            Method::Ekf => "the EKF gives no held-out verification nor an expected accuracy",
            Method::Lsq => "the held-out verification could not be computed (see the report)",
        }),
    };
    let mut r = Record::new(&[&a.sensors, &a.poses], &o.file)?
        .with_verification(v.with_expected(o.expected))
        .with_dropped(outliers.iter().map(Into::into).collect())
        .with_previous(previous);
    r.push_event(&format!("perpend calibrate wrote {}", out.display()));
    r.write_beside(out)
}

/// Appends the expected angular accuracy of the calibrated head over the
/// run's poses ([`crate::accuracy`]) to the report: pose resamples refitted
/// with the same model and references `refs` as the calibration (mean
/// reading, mean temperature, the table's knots and ridge: the run's, as
/// the stored calibration's are).
fn expected_accuracy(
    report: &mut String,
    fitted: &[Sensor<f64>],
    nominal: &[Sensor<f64>],
    (poses, refs): (&PoseTable, &Refs),
    model: Effect,
) -> Option<(f64, f64)> {
    const DRAWS: usize = 100;
    let refit = |sub: &candidates::Subset<'_>| -> Option<Vec<Sensor<f64>>> {
        nominal
            .iter()
            .enumerate()
            .map(|(i, s)| {
                candidates::fit(s, i, sub, refs.terms(model, i), &LsqConfig::default())
                    .ok()
                    .map(|f| f.sensor)
            })
            .collect()
    };
    let _ = writeln!(report);
    match crate::accuracy::expected_normal_error(fitted, poses, &refit, DRAWS, 1) {
        Ok(e) => {
            let _ = writeln!(
                report,
                "expected normal error from the calibration's uncertainty over this run's {} poses: \
                 {:.4}° RMS (1σ), {:.4}° at 95 %\n  (bootstrap over poses, {} refits; the reading \
                 noise at measurement time adds to this)",
                e.poses, e.rms_deg, e.p95_deg, e.draws
            );
            Some((e.rms_deg, e.p95_deg))
        }
        Err(e) => {
            let _ = writeln!(report, "expected normal error: not computed ({e})");
            None
        }
    }
}

/// Angle [deg] between two unit vectors, accurate near 0.
pub fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A beam tilted by 2 mrad along e1 and −1 mrad along e2 prints as
    /// α = 2, β = −1 mrad; the 1σ of a component along e1 carries over.
    #[test]
    fn beam_corrections_are_tilts_in_mrad() {
        let u = Vector3::new(-0.5, 0.0, 0.866).normalize();
        let (e1, e2) = perpend_core::geometry::tangent_basis(&u);
        let f = u + 0.002 * e1 - 0.001 * e2;
        let [(a, _), (b, _)] = tilts_mrad(&u, &f, [0.0; 3]);
        assert!((a - 2.0).abs() < 1e-2 && (b + 1.0).abs() < 1e-2, "{a} {b}");
        let [(_, sa), _] = tilts_mrad(&u, &u, [0.001, 0.001, 0.001]);
        assert!((sa - 1.0).abs() < 1e-9, "{sa}");
        assert_eq!(with_sensor(1, "sensor 2: weak"), "sensor 2: weak");
        assert_eq!(with_sensor(1, "weak"), "sensor 2: weak");
    }
}
