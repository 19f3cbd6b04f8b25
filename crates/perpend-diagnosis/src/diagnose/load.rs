//! Stage 1 of `perpend diagnose`, read and check: the nominal head of the
//! sensor table, the poses that disagree with every model left out
//! ([`perpend_calib::noise::reject`]), the rest re-timed with the time constants
//! chosen on them ([`perpend_calib::lags`]), the folds ([`perpend_calib::folds`]) and the
//! models the run's columns allow ([`available_models`]).
//!
//! Input: the tables and [`Settings`]; output: `Loaded`. Reads no later
//! stage. Limits: a head whose sensor count differs from the poses'
//! reading columns, or fewer than two poses per fold, is refused.

use anyhow::{anyhow, bail, Result};
use perpend_core::calib::LsqConfig;
use perpend_core::head::Sensor;

use super::expect::Plan;
use super::settings::Settings;
use perpend_calib::candidates::{available, available_models, Effect, Refs};
use perpend_calib::folds::{folds_for, Folds};
use perpend_calib::lags;
use perpend_calib::noise::{self, Outlier};
use perpend_formats::exchange::{PoseTable, SensorTable};

/// The run as the diagnosis sees it (stage "load → bad poses"): the
/// nominal head, the poses kept (re-timed), the folds and the models the
/// run's columns allow.
#[derive(Debug, Clone)]
pub struct Loaded {
    /// The nominal head (the sensor table).
    pub nominal: Vec<Sensor<f64>>,
    /// Poses left out as disagreeing with every model.
    pub outliers: Vec<Outlier>,
    /// The run without the outlying poses, re-timed with `lags`.
    pub poses: PoseTable,
    /// The time constants of the time-like candidates ([`lags`]).
    pub lags: lags::Lags,
    /// The candidates' term references.
    pub refs: Refs,
    /// The folds of every cross-validation.
    pub folds: Folds,
    /// The paper's model first, then every candidate the run allows.
    pub models: Vec<Effect>,
    /// Candidates not tested and why.
    pub skipped: Skipped,
    /// The declared reading noise per sensor ([`declared_sigma`]).
    pub declared: Option<Vec<f64>>,
}

impl Loaded {
    /// The plan of the cross-validations of `models` on this run.
    pub(super) fn plan<'a>(&'a self, models: &'a [Effect], s: &'a Settings) -> Plan<'a> {
        Plan {
            nominal: &self.nominal,
            refs: &self.refs,
            folds: &self.folds,
            models,
            lsq: &s.lsq,
            method: s.method,
        }
    }
}

/// Models left out of the diagnosis, each with why.
pub(super) type Skipped = Vec<(Effect, String)>;

/// Reads the head, rejects the bad poses ([`noise::reject`]), re-times the
/// rest ([`retimed`]), chooses the folds ([`folds_for`]) and the
/// candidates the run's columns allow ([`available`]).
///
/// # Errors
/// A head that does not match the poses' reading columns, too few poses
/// for the folds.
pub(super) fn load(sensors: &SensorTable, all_poses: &PoseTable, s: &Settings) -> Result<Loaded> {
    let nominal = sensors
        .sensors()
        .map_err(|e| anyhow!("nominal head: {e}"))?;
    if all_poses.n_sensors != nominal.len() {
        bail!(
            "the poses have {} reading columns, the head {} sensors",
            all_poses.n_sensors,
            nominal.len()
        );
    }
    let outliers = noise::reject(&nominal, all_poses, &s.lsq, &available_models(all_poses));
    let (poses, lags) = retimed(&nominal, all_poses, &outliers, &s.lsq);
    let n = poses.rows.len();
    let k = folds_for(n, s.folds);
    if n < 2 * k {
        bail!(
            "{n} poses are too few for {k}-fold cross-validation (need at least {})",
            2 * k
        );
    }
    let mut models = vec![Effect::None];
    let mut skipped = Vec::new();
    for e in Effect::CATALOG {
        match available(e, &poses) {
            Ok(()) => models.push(e),
            Err(why) => skipped.push((e, why)),
        }
    }
    Ok(Loaded {
        declared: declared_sigma(sensors, s.sigma_mm),
        nominal,
        outliers,
        refs: Refs::of(&poses),
        folds: Folds::new(n, k, s.seed),
        poses,
        lags,
        models,
        skipped,
    })
}

/// The run without `outliers`, re-timed with the time constants chosen on
/// it ([`lags`]; the lag filters every pose's temperature, the outliers'
/// included).
fn retimed(
    nominal: &[Sensor<f64>],
    all: &PoseTable,
    outliers: &[Outlier],
    lsq: &LsqConfig<f64>,
) -> (PoseTable, lags::Lags) {
    let kept = noise::without(all, outliers);
    let lags = lags::select(nominal, &kept, &[Effect::Thermal, Effect::Drift], lsq);
    (noise::without(&lags::apply(all, &lags), outliers), lags)
}

/// The largest `|d − d_ref|` of the run [mm] (for the plausibility bounds).
pub(crate) fn reading_span(poses: &PoseTable, refs: &Refs) -> f64 {
    poses
        .rows
        .iter()
        .flat_map(|r| {
            r.readings
                .iter()
                .enumerate()
                .filter_map(|(i, d)| Some((d.as_ref()? - refs.d_ref.get(i)?).abs()))
        })
        .fold(0.0, f64::max)
}

/// The declared reading noise of each sensor: the override or the
/// `sigma_mm` column; `None` when neither gives a positive value for every
/// sensor (the diagnosis then relies on its own estimate alone).
pub fn declared_sigma(sensors: &SensorTable, sigma_mm: Option<f64>) -> Option<Vec<f64>> {
    if let Some(s) = sigma_mm {
        return Some(vec![s; sensors.len()]);
    }
    sensors
        .rows
        .iter()
        .map(|r| r.sigma_mm.filter(|s| *s > 0.0))
        .collect()
}
