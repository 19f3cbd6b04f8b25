//! K-fold cross-validation by pose: held-out residuals and held-out normal
//! errors of a candidate model.
//!
//! The poses are dealt into `k` folds by a seeded shuffle (the same seed
//! and pose count give the same folds). For each fold every sensor is
//! fitted on the other folds' poses ([`crate::candidates::fit`]) and the
//! held-out readings are predicted: the held-out residual of a reading is
//! `d − f(E, u; plane) − Σ c_j x_j` (Chen eq. 1-3 plus the extension terms).
//! The held-out normal error of a pose is the angle between the normal the
//! fold's calibrated head measures from the pose's readings through
//! [`perpend_core::normal::plane`] (Chen eq. 17 spots with the extension
//! corrections of [`perpend_core::ext`], then the micro-plane) and the
//! normal of the pose's plane as given in the file.
//!
//! [`paired_normals`] compares two models' held-out normal errors pose by
//! pose (the normal-cost test of `perpend_diagnosis::diagnose::select`).
//!
//! Limits: a pose is predicted only by the fold that holds it out, so each
//! reading gets exactly one held-out residual; poses with fewer than three
//! readings have no normal error; heads of 3 to 8 sensors.

use nalgebra::Vector3;
use perpend_core::calib::{LsqConfig, Poses};
use perpend_core::head::{Head, Sensor};
use perpend_core::normal::{plane, Method};

use crate::candidates::{line_angle_deg, predict, Effect, Refs, SensorFit, Subset};
pub use crate::folds::Folds;
use crate::stats;
use perpend_formats::exchange::PoseTable;

/// Cross-validation result of one model.
#[derive(Debug, Clone, PartialEq)]
pub struct CvResult {
    /// The model.
    pub effect: Effect,
    /// Held-out residual `[pose][sensor]` [mm] (`None`: no reading).
    pub resid: Vec<Vec<Option<f64>>>,
    /// Fitted sensors of each fold (with extensions).
    pub heads: Vec<Vec<SensorFit>>,
    /// Held-out residual RMS over all readings [mm].
    pub rms: f64,
    /// Held-out residual RMS per sensor [mm].
    pub rms_sensor: Vec<f64>,
    /// Sum of squared held-out residuals of each pose [mm²].
    pub pose_loss: Vec<f64>,
    /// Number of held-out residuals.
    pub n: usize,
}

/// Parameters of the paper's model per sensor (zero point and beam
/// direction, Chen eq. 1-3).
pub const BASE_PARAMS: usize = 5;

impl CvResult {
    /// Parameters of the whole head as fitted: per sensor the paper's
    /// [`BASE_PARAMS`] and the extension terms its fits carry (those of the
    /// effects already selected included). Per sensor, not per model: the
    /// incidence candidate fits one coefficient where the symmetric form
    /// was chosen and two where the spot form was
    /// ([`crate::candidates::Refs::with_incidence_choice`]). Every fold fits
    /// the same terms, so the first is counted; `None` without fits.
    pub fn fitted_params(&self) -> Option<usize> {
        let head = self.heads.first().filter(|h| !h.is_empty())?;
        Some(
            head.iter()
                .map(|s| BASE_PARAMS + s.terms.mask.count_ones() as usize)
                .sum(),
        )
    }
}

/// The per-pose held-out loss differences `base − cand` [mm²].
fn loss_differences(base: &CvResult, cand: &CvResult) -> Vec<f64> {
    base.pose_loss
        .iter()
        .zip(&cand.pose_loss)
        .map(|(a, b)| a - b)
        .collect()
}

/// Wilcoxon signed-rank z of the per-pose loss differences `base − cand`.
pub fn paired_rank(base: &CvResult, cand: &CvResult) -> f64 {
    let d = loss_differences(base, cand);
    stats::signed_rank_z(&d)
}

/// Paired comparison of two models' per-pose held-out losses: returns
/// `(mean gain per reading [mm²], z, standard error of the mean gain per
/// pose)`.
pub fn paired(base: &CvResult, cand: &CvResult) -> (f64, f64, f64) {
    let d = loss_differences(base, cand);
    let k = d.len().max(1) as f64;
    let m = stats::mean(&d);
    let se = stats::sd(&d) / k.sqrt();
    let z = if se > 0.0 { m / se } else { 0.0 };
    (d.iter().sum::<f64>() / base.n.max(1) as f64, z, se)
}

/// A paired comparison of two models' held-out normal errors
/// ([`paired_normals`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct NormalGain {
    /// Mean held-out normal error of the base model over the paired
    /// poses [deg].
    pub base_deg: f64,
    /// The same of the candidate [deg].
    pub cand_deg: f64,
    /// Mean reduction `base − cand` per pose [deg].
    pub reduction_deg: f64,
    /// Its standard error `sd/√K` [deg].
    pub se_deg: f64,
    /// `reduction / se` (0 when the poses agree exactly).
    pub z: f64,
    /// Poses with a normal under both models (`K`).
    pub poses: usize,
}

/// Paired comparison of held-out normal errors per pose, `base` against
/// `cand` (both from [`normal_errors`] on the same folds): the mean of
/// `D_k = e_base(k) − e_cand(k)` over the poses where both models measure
/// a normal, its standard error and z. Fewer than 3 such poses: all 0.
pub fn paired_normals(base: &[Option<f64>], cand: &[Option<f64>]) -> NormalGain {
    let pairs: Vec<(f64, f64)> = base
        .iter()
        .zip(cand)
        .filter_map(|(b, c)| Some(((*b)?, (*c)?)))
        .collect();
    if pairs.len() < 3 {
        return NormalGain::default();
    }
    let d: Vec<f64> = pairs.iter().map(|(b, c)| b - c).collect();
    let k = d.len() as f64;
    let reduction_deg = stats::mean(&d);
    let se_deg = stats::sd(&d) / k.sqrt();
    let b: Vec<f64> = pairs.iter().map(|p| p.0).collect();
    let c: Vec<f64> = pairs.iter().map(|p| p.1).collect();
    NormalGain {
        base_deg: stats::mean(&b),
        cand_deg: stats::mean(&c),
        reduction_deg,
        se_deg,
        z: if se_deg > 0.0 {
            reduction_deg / se_deg
        } else {
            0.0
        },
        poses: d.len(),
    }
}

/// Cross-validates `effect` on `poses`.
///
/// # Errors
/// A sensor that cannot be fitted on some fold's training poses (message
/// names the fold and the sensor).
pub fn cross_validate(
    effect: Effect,
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    refs: &Refs,
    folds: &Folds,
    cfg: &LsqConfig<f64>,
) -> Result<CvResult, String> {
    let n_poses = poses.rows.len();
    let ns = nominal.len();
    let mut resid = vec![vec![None; ns]; n_poses];
    let mut heads = Vec::with_capacity(folds.k);
    // Table knots and crosstalk sources are picked once on the whole table
    // (the null re-simulations pick theirs the same way).
    let refs = &refs.with_table_choice(nominal, poses, effect, cfg);
    let src = crate::candidates::sources(nominal, poses, refs, effect, cfg);
    for f in 0..folds.k {
        let train = folds.train(f);
        let sub = Subset {
            all: poses,
            idx: &train,
        };
        let mut fitted = Vec::with_capacity(ns);
        for (i, s) in nominal.iter().enumerate() {
            let sf = crate::candidates::fit_from(s, i, &sub, refs.terms(effect, i), src[i], cfg)
                .map_err(|e| format!("fold {} of {}, sensor {}: {e}", f + 1, folds.k, i + 1))?;
            fitted.push(sf);
        }
        for k in folds.test(f) {
            for (i, sf) in fitted.iter().enumerate() {
                if let (Some(d), Some(p)) = (poses.reading(k, i), predict(sf, poses, k, i)) {
                    resid[k][i] = Some(d - p);
                }
            }
        }
        heads.push(fitted);
    }
    Ok(summarise(effect, resid, heads, ns))
}

fn summarise(
    effect: Effect,
    resid: Vec<Vec<Option<f64>>>,
    heads: Vec<Vec<SensorFit>>,
    ns: usize,
) -> CvResult {
    let pose_loss: Vec<f64> = resid
        .iter()
        .map(|r| r.iter().flatten().map(|e| e * e).sum())
        .collect();
    let all: Vec<f64> = resid.iter().flatten().flatten().copied().collect();
    let rms_sensor = (0..ns)
        .map(|i| {
            let v: Vec<f64> = resid.iter().filter_map(|r| r[i]).collect();
            crate::stats::rms(&v)
        })
        .collect();
    CvResult {
        effect,
        rms: crate::stats::rms(&all),
        n: all.len(),
        rms_sensor,
        pose_loss,
        resid,
        heads,
    }
}

/// The micro-plane normal that `sensors` measure from `readings` (any head
/// of 3 to 8 sensors), through [`perpend_core::normal::plane`].
///
/// With an incidence correction the angle γ of each beam to the surface
/// comes from a previous plane; `plane` does two passes (the first without
/// the correction). With incidence coefficients of a few mm that leaves γ
/// unconverged (on a seeded run with `c ≈ 2 mm` the true head's normal
/// error is 0.0150° after two passes, 0.0105° after three, where it
/// stays), so further passes of [`perpend_core::normal::spots`] and
/// [`perpend_core::normal::fit`] follow until the normal stops moving
/// (at most 6 passes in all; a no-op for heads without incidence).
///
/// # Errors
/// Unsupported sensor count, too few readings, degenerate spots.
pub fn measure_normal(
    sensors: &[Sensor<f64>],
    readings: &[Option<f64>],
    ctx: &perpend_core::ext::Context<f64>,
    method: Method,
) -> Result<Vector3<f64>, String> {
    fn go<const N: usize>(
        s: &[Sensor<f64>],
        r: &[Option<f64>],
        ctx: &perpend_core::ext::Context<f64>,
        method: Method,
    ) -> Result<Vector3<f64>, String> {
        let arr: [Sensor<f64>; N] = core::array::from_fn(|i| s.get(i).copied().unwrap_or(s[0]));
        let rr: [Option<f64>; N] = core::array::from_fn(|i| r.get(i).copied().flatten());
        let head = Head::new(arr);
        // perpend-core iterates the incidence angle to its fixed point, as
        // the board does.
        plane(&head, &rr, ctx, method)
            .map(|p| p.normal)
            .map_err(|e| e.to_string())
    }
    if sensors.is_empty() || readings.len() != sensors.len() {
        return Err("readings and sensors differ in number".into());
    }
    match sensors.len() {
        3 => go::<3>(sensors, readings, ctx, method),
        4 => go::<4>(sensors, readings, ctx, method),
        5 => go::<5>(sensors, readings, ctx, method),
        6 => go::<6>(sensors, readings, ctx, method),
        7 => go::<7>(sensors, readings, ctx, method),
        8 => go::<8>(sensors, readings, ctx, method),
        n => Err(format!(
            "normals need a head of 3 to 8 sensors, this one has {n}"
        )),
    }
}

/// The sensors of `fits` and the readings as `perpend-core` takes them: a
/// carry-over from a channel other than the previous one (which is all the
/// core applies) is removed from the reading here, `f = (d − c·d_src)/(1 − c)`,
/// and left out of the sensor's extension.
fn rewired_head(
    fits: &[SensorFit],
    readings: &[Option<f64>],
) -> (Vec<Sensor<f64>>, Vec<Option<f64>>) {
    let n = fits.len();
    fits.iter()
        .enumerate()
        .map(|(i, f)| {
            let d = readings.get(i).copied().flatten();
            let c = f.sensor.ext.crosstalk;
            if c == 0.0 || f.source == crate::candidates::previous(i, n) {
                return (f.sensor, d);
            }
            let mut s = f.sensor;
            s.ext.crosstalk = 0.0;
            let src = readings.get(f.source).copied().flatten();
            let d = match (d, src) {
                (Some(d), Some(p)) => Some((d - c * p) / (1.0 - c)),
                (d, _) => d,
            };
            (s, d)
        })
        .unzip()
}

/// Held-out normal error [deg] of every pose (`None` where the normal
/// cannot be measured): the head of the fold that holds the pose out,
/// against the pose's plane normal.
pub fn normal_errors(
    cv: &CvResult,
    poses: &PoseTable,
    folds: &Folds,
    method: Method,
) -> Vec<Option<f64>> {
    poses
        .rows
        .iter()
        .enumerate()
        .map(|(k, row)| {
            let (h, r) = rewired_head(cv.heads.get(folds.of_pose[k])?, &row.readings);
            let n = measure_normal(&h, &r, &poses.context(k), method).ok()?;
            Some(line_angle_deg(&n, &row.plane.n))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pairing skips a pose either model has no normal for; the mean,
    /// the standard error and z are those of the differences; fewer than 3
    /// pairs give nothing.
    #[test]
    fn paired_normals_pairs_poses_both_measured() {
        let base = [Some(0.05), Some(0.04), None, Some(0.06), Some(0.05)];
        let cand = [Some(0.03), Some(0.03), Some(0.01), None, Some(0.02)];
        let g = paired_normals(&base, &cand);
        assert_eq!(g.poses, 3);
        // differences 0.02, 0.01, 0.03
        assert!((g.reduction_deg - 0.02).abs() < 1e-12, "{g:?}");
        assert!((g.se_deg - 0.01 / 3f64.sqrt()).abs() < 1e-12, "{g:?}");
        assert!((g.z - 0.02 / g.se_deg).abs() < 1e-9, "{g:?}");
        // means over the 3 paired poses only
        assert!((g.base_deg - 0.14 / 3.0).abs() < 1e-12, "{g:?}");
        assert!((g.cand_deg - 0.08 / 3.0).abs() < 1e-12, "{g:?}");
        let g = paired_normals(&base[..2], &cand[..2]);
        assert_eq!(g, NormalGain::default());
    }

    #[test]
    fn folds_are_deterministic_and_balanced() {
        let a = Folds::new(103, 5, 7);
        let b = Folds::new(103, 5, 7);
        assert_eq!(a, b);
        let c = Folds::new(103, 5, 8);
        assert_ne!(a, c);
        for f in 0..5 {
            let n = a.test(f).len();
            assert!(n == 20 || n == 21, "fold {f}: {n}");
            assert_eq!(a.train(f).len() + n, 103);
        }
        // every pose held out exactly once
        let mut seen = vec![0; 103];
        for f in 0..5 {
            for p in a.test(f) {
                seen[p] += 1;
            }
        }
        assert!(seen.iter().all(|&s| s == 1));
    }
}
