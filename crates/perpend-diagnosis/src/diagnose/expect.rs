//! What the residuals *should* look like: the same analysis on Monte-Carlo
//! runs of the simulator for this head and this pose set.
//!
//! Each draw re-creates the run with the paper's model only: the head is
//! the base fit of the measured run taken as the truth (Chen eq. 1-3), the
//! poses are the measured run's planes taken as the true planes, a reading
//! exists where the measured run has one, reading noise is N(0, σ_i) with
//! the datasheet σ (`sigma_mm`), and the plane written for the pose is what
//! the laser tracker would report ([`Tracker::measure`], Chen §5 step 1),
//! drawn anew. Time and temperature are copied. The draws go through
//! exactly the analysis of the measured run ([`analyse`]): the spread of a
//! statistic over the draws is its sampling spread for this pose set, which
//! is what the measured statistic is compared against.
//!
//! Limits: the expectation is only as good as σ and the tracker model; an
//! optimistic datasheet σ shows up as residuals "above expectation".

use perpend_core::calib::{LsqConfig, Regressors};
use perpend_core::head::Sensor;
use perpend_core::model::distance;
use perpend_core::normal::Method;
use rand::rngs::StdRng;

use super::insample::{self, Rss};
use perpend_calib::candidates::{fit, Effect, Refs, SensorFit};
use perpend_calib::cv::{cross_validate, normal_errors, CvResult, Folds};
use perpend_calib::sim::{gauss, Tracker};
use perpend_calib::stats;
use perpend_formats::exchange::{PoseRow, PoseTable};

/// The measurement noise the expectation assumes.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseModel {
    /// Reading noise 1σ of each sensor [mm].
    pub sigma: Vec<f64>,
    /// The tracker's plane measurement (`None`: planes exact).
    pub tracker: Option<Tracker>,
}

/// The `j`-th effect-free re-simulation of a diagnosis seeded `seed`
/// ([`null_table`] on its own seeded stream): the expectation, the
/// direction test and the nested test draw the same runs.
pub fn null_draw(
    truth: &[Sensor<f64>],
    poses: &PoseTable,
    noise: &NoiseModel,
    seed: u64,
    j: usize,
) -> PoseTable {
    use rand::SeedableRng;
    let mut rng = StdRng::seed_from_u64(
        seed.wrapping_add(j as u64)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15),
    );
    null_table(truth, poses, noise, &mut rng)
}

/// A run re-created with the paper's model: `truth` reads the planes of
/// `poses` with noise `noise` where `poses` has a reading.
pub fn null_table(
    truth: &[Sensor<f64>],
    poses: &PoseTable,
    noise: &NoiseModel,
    rng: &mut StdRng,
) -> PoseTable {
    let rows = poses
        .rows
        .iter()
        .map(|row| {
            let readings: Vec<Option<f64>> = row
                .readings
                .iter()
                .enumerate()
                .map(|(i, r)| {
                    let s = noise.sigma.get(i).copied().unwrap_or(0.0);
                    let e = s * gauss(rng);
                    let d = distance(truth.get(i)?, &row.plane, i).ok()?;
                    r.and(Some(d + e)).filter(|v| *v >= 0.0)
                })
                .collect();
            let plane = match &noise.tracker {
                Some(t) => t.measure(&row.plane, rng),
                None => row.plane,
            };
            PoseRow {
                line: row.line,
                pose: row.pose,
                abcd: [plane.n.x, plane.n.y, plane.n.z, plane.d],
                plane,
                readings,
                t_s: row.t_s,
                temp_c: row.temp_c,
                noise: Default::default(),
            }
        })
        .collect();
    PoseTable {
        n_sensors: poses.n_sensors,
        rows,
    }
}

/// Everything computed on one run (measured or simulated).
#[derive(Debug, Clone)]
pub struct Analysis {
    /// Cross-validation of each model (`Effect::None` first), or why it
    /// could not be fitted.
    pub cv: Vec<(Effect, Result<CvResult, String>)>,
    /// The base model fitted on all poses.
    pub base_fit: Vec<SensorFit>,
    /// In-sample residuals of the base fit `[pose][sensor]` [mm].
    pub insample: Vec<Vec<Option<f64>>>,
    /// Pooled lag-1 autocorrelation of the in-sample residuals in
    /// acquisition order, and the number of pairs.
    pub lag1: (f64, usize),
    /// Runs test z pooled over sensors (`Σ z_i / √N`).
    pub runs_z: f64,
    /// Fraction of the in-sample residual variance each candidate's
    /// regressors explain (pooled over sensors).
    pub r2: Vec<(Effect, f64)>,
    /// Held-out normal errors of the base model [deg] (simulated runs
    /// only when asked).
    pub base_normal: Vec<Option<f64>>,
    /// Held-out normal errors of each candidate [deg], same folds, same
    /// poses (only when asked, like `base_normal`): the normal-cost test
    /// of [`super::select`].
    pub normals: Vec<(Effect, Vec<Option<f64>>)>,
    /// Structure z of each model's held-out residuals along each axis of
    /// [`perpend_calib::noise::AXES`] (keys from the base fit's geometry).
    pub structure: Vec<(Effect, Vec<Option<f64>>)>,
    /// Nested in-sample z of each candidate against the base model per
    /// set of sensors ([`super::insample::zs`]: the head, then each
    /// sensor alone).
    pub nested: Vec<(Effect, Vec<Option<f64>>)>,
}

impl Analysis {
    /// The cross-validation of `e`, if it succeeded.
    pub fn cv_of(&self, e: Effect) -> Option<&CvResult> {
        self.cv
            .iter()
            .find(|(x, _)| *x == e)
            .and_then(|(_, r)| r.as_ref().ok())
    }

    /// Pooled R² of candidate `e`.
    pub fn r2_of(&self, e: Effect) -> Option<f64> {
        self.r2.iter().find(|(x, _)| *x == e).map(|(_, r)| *r)
    }

    /// Held-out normal errors of model `e` per pose (`Effect::None`: the
    /// base model's); `None` when they were not computed.
    pub fn normals_of(&self, e: Effect) -> Option<&[Option<f64>]> {
        if e == Effect::None {
            return (!self.base_normal.is_empty()).then_some(self.base_normal.as_slice());
        }
        self.normals
            .iter()
            .find(|(x, _)| *x == e)
            .map(|(_, v)| v.as_slice())
    }

    /// The paired normal-error comparison of candidate `e` with the base
    /// model ([`perpend_calib::cv::paired_normals`]), when both were computed.
    pub fn normal_gain_of(&self, e: Effect) -> Option<perpend_calib::cv::NormalGain> {
        let b = self.normals_of(Effect::None)?;
        Some(perpend_calib::cv::paired_normals(b, self.normals_of(e)?))
    }

    /// Structure z per axis of model `e`'s held-out residuals.
    pub fn structure_of(&self, e: Effect) -> Option<&[Option<f64>]> {
        self.structure
            .iter()
            .find(|(x, _)| *x == e)
            .map(|(_, v)| v.as_slice())
    }

    /// Nested in-sample z per set of sensors of candidate `e`.
    pub fn nested_of(&self, e: Effect) -> Option<&[Option<f64>]> {
        self.nested
            .iter()
            .find(|(x, _)| *x == e)
            .map(|(_, v)| v.as_slice())
    }
}

/// Settings shared by the measured and simulated analyses.
#[derive(Debug, Clone)]
pub struct Plan<'a> {
    /// Nominal head.
    pub nominal: &'a [Sensor<f64>],
    /// Term references (from the measured run).
    pub refs: &'a Refs,
    /// Folds.
    pub folds: &'a Folds,
    /// Models to cross-validate (`Effect::None` first).
    pub models: &'a [Effect],
    /// Solver settings.
    pub lsq: &'a LsqConfig<f64>,
    /// Normal method for held-out normal errors.
    pub method: Method,
}

/// The share of the paper's model's in-sample residual variance that the
/// regressors of candidate `e` explain, pooled over the sensors.
fn explained_share(
    e: Effect,
    plan: &Plan<'_>,
    poses: &PoseTable,
    insample: &[Vec<Option<f64>>],
    base_fit: &[SensorFit],
) -> f64 {
    let (mut ex, mut tot) = (0.0, 0.0);
    for (i, fit) in base_fit.iter().enumerate() {
        let terms = plan.refs.terms(e, i);
        let m = terms.count();
        let mut ys = Vec::new();
        let mut xs = vec![Vec::new(); m];
        for (k, row) in insample.iter().enumerate() {
            let Some(r) = row[i] else { continue };
            let mut x = [0.0; 8];
            terms.fill(poses, k, i, &fit.sensor, &mut x[..m]);
            ys.push(r);
            for j in 0..m {
                xs[j].push(x[j]);
            }
        }
        let (a, b) = stats::explained(&ys, &xs);
        ex += a;
        tot += b;
    }
    if tot > 0.0 {
        ex / tot
    } else {
        0.0
    }
}

/// Runs the analysis on `poses`: the paper's model fitted on all poses, its
/// in-sample residuals' whiteness and the share each candidate's regressors
/// explain, every model cross-validated, the held-out normal errors of
/// every model (with `normals`) and the residuals' structure.
///
/// # Errors
/// When the base model cannot be fitted on all poses.
pub fn analyse(poses: &PoseTable, plan: &Plan<'_>, normals: bool) -> Result<Analysis, String> {
    let base_fit: Vec<SensorFit> = plan
        .nominal
        .iter()
        .enumerate()
        .map(|(i, s)| {
            fit(s, i, poses, plan.refs.terms(Effect::None, i), plan.lsq)
                .map_err(|e| format!("base model, sensor {}: {e}", i + 1))
        })
        .collect::<Result<_, _>>()?;
    let ns = plan.nominal.len();
    let insample = perpend_calib::noise::residuals_of(&base_fit, poses);
    let per_sensor: Vec<Vec<Option<f64>>> = (0..ns)
        .map(|i| insample.iter().map(|r| r[i]).collect())
        .collect();
    let lag1 = stats::lag1(&per_sensor);
    let runs_z = per_sensor.iter().map(|s| stats::runs_z(s)).sum::<f64>() / (ns as f64).sqrt();
    let r2 = plan
        .models
        .iter()
        .filter(|e| **e != Effect::None)
        .map(|&e| (e, explained_share(e, plan, poses, &insample, &base_fit)))
        .collect();
    let cv: Vec<(Effect, Result<CvResult, String>)> = plan
        .models
        .iter()
        .map(|&e| {
            (
                e,
                cross_validate(e, plan.nominal, poses, plan.refs, plan.folds, plan.lsq),
            )
        })
        .collect();
    let base_normal = match (normals, cv.first()) {
        (true, Some((_, Ok(b)))) => normal_errors(b, poses, plan.folds, plan.method),
        _ => Vec::new(),
    };
    let normals = match normals && !base_normal.is_empty() {
        true => candidate_normals(&cv, poses, plan),
        false => Vec::new(),
    };
    let nested = nested_zs(&cv, &base_fit, poses, plan);
    let geom: Vec<Sensor<f64>> = base_fit.iter().map(|f| f.sensor).collect();
    let sources = carry_sources(&cv);
    let structure = cv
        .iter()
        .filter_map(|(e, r)| {
            Some((
                *e,
                perpend_calib::noise::structure(&geom, poses, &sources, &r.as_ref().ok()?.resid),
            ))
        })
        .collect();
    Ok(Analysis {
        cv,
        base_fit,
        insample,
        lag1,
        runs_z,
        r2,
        base_normal,
        normals,
        structure,
        nested,
    })
}

/// The nested in-sample z of every candidate that could be
/// cross-validated against the base model fitted on all poses
/// (`base_fit`), per set of sensors ([`super::insample`]).
fn nested_zs(
    cv: &[(Effect, Result<CvResult, String>)],
    base_fit: &[SensorFit],
    poses: &PoseTable,
    plan: &Plan<'_>,
) -> Vec<(Effect, Vec<Option<f64>>)> {
    let base: Vec<Rss> = base_fit.iter().map(Rss::of).collect();
    cv.iter()
        .filter(|(e, _)| *e != Effect::None)
        .filter_map(|(e, r)| {
            let c = r.as_ref().ok()?;
            let cand = insample::refit(c, poses, plan.lsq);
            Some((*e, insample::zs(*e, &base, &cand)))
        })
        .collect()
}

/// The channel each sensor's carry-over reads, as the crosstalk candidate
/// chose it on this table ([`perpend_calib::candidates::sources`]; empty without
/// that candidate: the previous channel in sensor order).
fn carry_sources(cv: &[(Effect, Result<CvResult, String>)]) -> Vec<usize> {
    cv.iter()
        .find(|(e, _)| *e == Effect::Crosstalk)
        .and_then(|(_, r)| r.as_ref().ok()?.heads.first())
        .map(|h| h.iter().map(|s| s.source).collect())
        .unwrap_or_default()
}

/// Held-out normal errors of every candidate that could be
/// cross-validated (the base model's are computed apart).
fn candidate_normals(
    cv: &[(Effect, Result<CvResult, String>)],
    poses: &PoseTable,
    plan: &Plan<'_>,
) -> Vec<(Effect, Vec<Option<f64>>)> {
    cv.iter()
        .filter(|(e, _)| *e != Effect::None)
        .filter_map(|(e, r)| {
            let c = r.as_ref().ok()?;
            Some((*e, normal_errors(c, poses, plan.folds, plan.method)))
        })
        .collect()
}

/// Mean and sample spread of a statistic over the draws.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Spread {
    /// Mean over the draws.
    pub mean: f64,
    /// Sample standard deviation over the draws.
    pub sd: f64,
    /// Number of draws that produced the statistic.
    pub n: usize,
}

impl Spread {
    /// Of the values `v`.
    pub fn of(v: &[f64]) -> Self {
        Self {
            mean: stats::mean(v),
            sd: stats::sd(v),
            n: v.len(),
        }
    }

    /// Standard deviation of a *new* observation around `mean` (prediction
    /// spread `sd·√(1 + 1/n)`), at least `floor`.
    pub fn predictive_sd(&self, floor: f64) -> f64 {
        let n = self.n.max(1) as f64;
        (self.sd * (1.0 + 1.0 / n).sqrt()).max(floor)
    }
}

/// The simulated expectation of every statistic.
#[derive(Debug, Clone, Default)]
pub struct Expectation {
    /// Draws run.
    pub draws: usize,
    /// Held-out RMS of each model [mm].
    pub rms: Vec<(Effect, Spread)>,
    /// Held-out RMS of the base model per sensor [mm].
    pub rms_sensor: Vec<Spread>,
    /// Lag-1 autocorrelation.
    pub lag1: Spread,
    /// Runs test z.
    pub runs_z: Spread,
    /// R² of each candidate's regressors.
    pub r2: Vec<(Effect, Spread)>,
    /// Held-out normal error of the base model, mean over poses [deg].
    pub normal_err_deg: Spread,
    /// Paired z of each candidate's held-out gain over the base model on
    /// effect-free data: what the candidate "gains" from noise alone.
    pub gain_z: Vec<(Effect, Spread)>,
    /// Signed-rank z of the same per-pose gains on effect-free data.
    pub rank_z: Vec<(Effect, Spread)>,
    /// Paired z of each candidate's held-out normal-error reduction over
    /// the base model on effect-free data ([`perpend_calib::cv::paired_normals`]:
    /// the normals against the planes as the simulated tracker reports
    /// them, like the measured run's).
    pub normal_z: Vec<(Effect, Spread)>,
    /// Structure z of each model's held-out residuals per axis: what a
    /// model that captures the run leaves (cross-validation's own fold
    /// errors are smooth in the geometry, more so with more parameters).
    pub structure: Vec<(Effect, Vec<Spread>)>,
    /// Nested in-sample z of each candidate per set of sensors
    /// ([`super::insample`]) on effect-free data: the null of the
    /// decision's nested test.
    pub nested_z: Vec<(Effect, Vec<Spread>)>,
}

impl Expectation {
    /// Held-out RMS spread of model `e`.
    pub fn rms_of(&self, e: Effect) -> Option<Spread> {
        self.rms.iter().find(|(x, _)| *x == e).map(|(_, s)| *s)
    }

    /// R² spread of candidate `e`.
    pub fn r2_of(&self, e: Effect) -> Option<Spread> {
        self.r2.iter().find(|(x, _)| *x == e).map(|(_, s)| *s)
    }

    /// Structure spreads per axis of model `e`.
    pub fn structure_of(&self, e: Effect) -> &[Spread] {
        self.structure
            .iter()
            .find(|(x, _)| *x == e)
            .map_or(&[], |(_, v)| v.as_slice())
    }

    /// Null spread of candidate `e`'s paired gain z.
    pub fn gain_z_of(&self, e: Effect) -> Option<Spread> {
        self.gain_z.iter().find(|(x, _)| *x == e).map(|(_, s)| *s)
    }

    /// Null spread of candidate `e`'s normal-error reduction z.
    pub fn normal_z_of(&self, e: Effect) -> Option<Spread> {
        self.normal_z.iter().find(|(x, _)| *x == e).map(|(_, s)| *s)
    }

    /// Null spreads of candidate `e`'s nested z per set of sensors
    /// (empty when not simulated).
    pub fn nested_z_of(&self, e: Effect) -> &[Spread] {
        self.nested_z
            .iter()
            .find(|(x, _)| *x == e)
            .map_or(&[], |(_, v)| v.as_slice())
    }

    /// Null spread of candidate `e`'s signed-rank z.
    pub fn rank_z_of(&self, e: Effect) -> Option<Spread> {
        self.rank_z.iter().find(|(x, _)| *x == e).map(|(_, s)| *s)
    }
}

/// Runs `draws` Monte-Carlo draws of the run with the base fit `truth` and
/// collects the expectation. Draw `j` uses the seed `seed + j` (so the
/// result is reproducible and independent of the measured data's values).
pub fn expect(
    truth: &[Sensor<f64>],
    poses: &PoseTable,
    noise: &NoiseModel,
    plan: &Plan<'_>,
    draws: usize,
    seed: u64,
) -> Expectation {
    let mut analyses = Vec::with_capacity(draws);
    for j in 0..draws {
        let table = null_draw(truth, poses, noise, seed, j);
        if let Ok(a) = analyse(&table, plan, true) {
            analyses.push(a);
        }
    }
    summarise(&analyses, plan)
}

/// Each model's held-out RMS, and the base model's per sensor, over the
/// draws.
fn rms_spreads(analyses: &[Analysis], plan: &Plan<'_>) -> (Vec<(Effect, Spread)>, Vec<Spread>) {
    let rms = plan
        .models
        .iter()
        .map(|&e| {
            let v: Vec<f64> = analyses
                .iter()
                .filter_map(|a| a.cv_of(e))
                .map(|c| c.rms)
                .collect();
            (e, Spread::of(&v))
        })
        .collect();
    let rms_sensor = (0..plan.nominal.len())
        .map(|i| {
            let v: Vec<f64> = analyses
                .iter()
                .filter_map(|a| a.cv_of(Effect::None))
                .map(|c| c.rms_sensor[i])
                .collect();
            Spread::of(&v)
        })
        .collect();
    (rms, rms_sensor)
}

/// Each model's structure z per axis over the draws.
fn structure_spreads(analyses: &[Analysis], plan: &Plan<'_>) -> Vec<(Effect, Vec<Spread>)> {
    plan.models
        .iter()
        .map(|&e| {
            let per_axis = (0..=perpend_calib::noise::STEP_AXIS)
                .map(|x| {
                    let v: Vec<f64> = analyses
                        .iter()
                        .filter_map(|a| a.structure_of(e)?.get(x).copied().flatten())
                        .collect();
                    Spread::of(&v)
                })
                .collect();
            (e, per_axis)
        })
        .collect()
}

/// The spread over the draws of a per-candidate statistic `stat` (the
/// draws where it has a value), for every candidate of `plan`.
fn per_candidate(
    analyses: &[Analysis],
    plan: &Plan<'_>,
    stat: &dyn Fn(&Analysis, Effect) -> Option<f64>,
) -> Vec<(Effect, Spread)> {
    plan.models
        .iter()
        .filter(|e| **e != Effect::None)
        .map(|&e| {
            let v: Vec<f64> = analyses.iter().filter_map(|a| stat(a, e)).collect();
            (e, Spread::of(&v))
        })
        .collect()
}

/// The spreads of every statistic over the draws' analyses.
fn summarise(analyses: &[Analysis], plan: &Plan<'_>) -> Expectation {
    let (rms, rms_sensor) = rms_spreads(analyses, plan);
    let r2 = per_candidate(analyses, plan, &|a, e| a.r2_of(e));
    let lag: Vec<f64> = analyses.iter().map(|a| a.lag1.0).collect();
    let runs: Vec<f64> = analyses.iter().map(|a| a.runs_z).collect();
    let nerr: Vec<f64> = analyses
        .iter()
        .map(|a| {
            let v: Vec<f64> = a.base_normal.iter().flatten().copied().collect();
            stats::mean(&v)
        })
        .collect();
    let null_of = |stat: &dyn Fn(&CvResult, &CvResult) -> f64| {
        per_candidate(analyses, plan, &|a, e| {
            Some(stat(a.cv_of(Effect::None)?, a.cv_of(e)?))
        })
    };
    Expectation {
        draws: analyses.len(),
        rms,
        rms_sensor,
        lag1: Spread::of(&lag),
        runs_z: Spread::of(&runs),
        r2,
        normal_err_deg: Spread::of(&nerr),
        gain_z: null_of(&|b, c| perpend_calib::cv::paired(b, c).1),
        rank_z: null_of(&perpend_calib::cv::paired_rank),
        // the draws where both models measured normals
        normal_z: per_candidate(analyses, plan, &|a, e| {
            a.normal_gain_of(e).filter(|g| g.poses > 0).map(|g| g.z)
        }),
        structure: structure_spreads(analyses, plan),
        nested_z: nested_spreads(analyses, plan),
    }
}

/// Each candidate's nested z per set of sensors over the draws.
fn nested_spreads(analyses: &[Analysis], plan: &Plan<'_>) -> Vec<(Effect, Vec<Spread>)> {
    let sets = insample::sets(plan.nominal.len()).len();
    plan.models
        .iter()
        .filter(|e| **e != Effect::None)
        .map(|&e| {
            let per_set = (0..sets)
                .map(|x| {
                    let v: Vec<f64> = analyses
                        .iter()
                        .filter_map(|a| a.nested_of(e)?.get(x).copied().flatten())
                        .collect();
                    Spread::of(&v)
                })
                .collect();
            (e, per_set)
        })
        .collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_calib::sim::{paper_head, simulate, SimConfig};
    use rand::SeedableRng;

    #[test]
    fn null_table_keeps_planes_and_missing_readings() {
        let head = paper_head().unwrap();
        let mut cfg = SimConfig::paper();
        cfg.poses = 20;
        cfg.dropout = 0.1;
        let data = simulate(&head, &cfg, &[], &mut StdRng::seed_from_u64(3)).unwrap();
        let noise = NoiseModel {
            sigma: vec![0.0; 4],
            tracker: None,
        };
        let t = null_table(
            &head.truth,
            &data.poses,
            &noise,
            &mut StdRng::seed_from_u64(4),
        );
        assert_eq!(t.rows.len(), 20);
        for (a, b) in t.rows.iter().zip(&data.poses.rows) {
            assert_eq!(a.plane, b.plane);
            for (i, (x, y)) in a.readings.iter().zip(&b.readings).enumerate() {
                assert_eq!(x.is_some(), y.is_some());
                if let Some(x) = x {
                    // noise-free: exactly the true head's distance
                    let d = distance(&head.truth[i], &b.plane, i).unwrap();
                    approx::assert_relative_eq!(*x, d, epsilon = 1e-12);
                }
            }
        }
    }

    #[test]
    fn predictive_spread_golden() {
        let s = Spread::of(&[1.0, 2.0, 3.0, 4.0]);
        approx::assert_relative_eq!(s.mean, 2.5);
        approx::assert_relative_eq!(
            s.predictive_sd(0.0),
            (5.0f64 / 3.0).sqrt() * 1.25f64.sqrt(),
            epsilon = 1e-12
        );
        approx::assert_relative_eq!(s.predictive_sd(10.0), 10.0);
    }
}
