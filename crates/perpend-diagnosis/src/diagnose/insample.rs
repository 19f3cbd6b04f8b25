//! The nested in-sample statistic of every candidate against the paper's
//! model (issue 46 item 2), per sensor and over the head: what the
//! decision's nested test ([`super::select`], "Nested test") compares with
//! the same statistic on the run's effect-free re-simulations.
//!
//! For sensor `i`, the paper's model (with the effects selected before,
//! [`perpend_calib::candidates::Refs::extra`]) and the candidate are fitted on
//! all poses; the candidate's extra columns `qᵢ` buy the drop
//! `ΔRSSᵢ = RSSᵢ(base) − RSSᵢ(c)` of the residual sum of squares, and
//!
//! `Tᵢ = ΔRSSᵢ / (RSSᵢ(c)/νᵢ)`,  `νᵢ = readingsᵢ − 5 − columnsᵢ(c)`
//!
//! is `qᵢ` times an F statistic (Fisher; the likelihood-ratio test of a
//! linear model's nested columns under Gaussian noise). Over a set `S` of
//! sensors `T_S = Σ_{i∈S} Tᵢ` is referred to `F(q_S + k, Σνᵢ)` (`k` = 1
//! for a time-like candidate, whose time constant was chosen on this run
//! and is not chosen again on the re-simulations, [`chosen_params`]) and
//! turned into a normal z by Paulson's cube-root approximation
//! ([`paulson_z`]), so that every set's statistic is on one scale. The
//! sets ([`sets`]): every sensor at once (index 0), then each sensor
//! alone (index `i + 1`): an effect confined to one sensor is diluted by
//! the other three in the head's statistic, not in its own.
//!
//! The columns and crosstalk source of each sensor are those its
//! cross-validation used (the first fold's fit: the table's knots and
//! ridge, the incidence form and the carry-over source are chosen once on
//! the whole table, [`perpend_calib::cv::cross_validate`]), so the choice is made
//! the same way on the measured run and on each re-simulation.
//!
//! Limits: the F reference holds for a linear model under Gaussian noise;
//! the Gauss-Newton fits are linear near the solution, and what the
//! references miss (the tracker's plane error shared by the sensors of a
//! pose, the choices above, a ridge) is carried by the null the decision
//! calibrates on. In-sample: the decision also asks the candidate to
//! predict held-out readings of the sensors it acts on better
//! ([`heldout_gain`]).

use perpend_core::calib::{LsqConfig, Regressors};

use perpend_core::head::Sensor;

use perpend_calib::candidates::{fit, fit_from, Effect, Refs, SensorFit};
use perpend_calib::cv::{CvResult, BASE_PARAMS};
use perpend_formats::exchange::PoseTable;

/// One model's in-sample fit of one sensor, as far as the test needs it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rss {
    /// Residual sum of squares [mm²].
    pub rss: f64,
    /// Extension columns fitted.
    pub columns: usize,
    /// Readings fitted.
    pub used: usize,
}

impl Rss {
    /// Of a fit on all poses.
    pub fn of(f: &SensorFit) -> Self {
        Self {
            rss: f.rms * f.rms * f.used as f64,
            columns: f.terms.count(),
            used: f.used,
        }
    }

    /// Residual degrees of freedom (at least 1).
    fn nu(&self) -> f64 {
        self.used.saturating_sub(BASE_PARAMS + self.columns).max(1) as f64
    }
}

/// Each sensor of the model cross-validated as `cv`, fitted on all of
/// `poses` with the columns and carry-over source its folds used, the
/// Gauss-Newton started from the first fold's geometry (the same minimum
/// as from the nominal head, in fewer steps: this runs on every
/// re-simulation); `None` where it cannot be fitted.
pub fn refit(cv: &CvResult, poses: &PoseTable, lsq: &LsqConfig<f64>) -> Vec<Option<Rss>> {
    let Some(head) = cv.heads.first() else {
        return Vec::new();
    };
    head.iter()
        .enumerate()
        .map(|(i, f)| {
            fit_from(&f.sensor, i, poses, f.terms, f.source, lsq)
                .ok()
                .map(|x| Rss::of(&x))
        })
        .collect()
}

/// The paper's model (with [`Refs::extra`]) fitted on all of `poses`,
/// sensor by sensor; `None` when a sensor cannot be fitted.
pub fn base_rss(
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    refs: &Refs,
    lsq: &LsqConfig<f64>,
) -> Option<Vec<Rss>> {
    nominal
        .iter()
        .enumerate()
        .map(|(i, s)| {
            fit(s, i, poses, refs.terms(Effect::None, i), lsq)
                .ok()
                .map(|f| Rss::of(&f))
        })
        .collect()
}

/// The sets of sensors tested (module docs): every sensor at once, then
/// each alone.
pub fn sets(n: usize) -> Vec<Vec<usize>> {
    std::iter::once((0..n).collect())
        .chain((0..n).map(|i| vec![i]))
        .collect()
}

/// Parameters chosen on the run and not again on its re-simulations: the
/// thermal lag and the settling time ([`perpend_calib::lags`]), one per head.
pub fn chosen_params(e: Effect) -> usize {
    usize::from(matches!(e, Effect::Thermal | Effect::Drift))
}

/// Paulson's normal approximation of the upper tail of `F(d1, d2)` at `f`:
/// `z = ((1 − 2/(9d₂))·f^⅓ − (1 − 2/(9d₁))) / √(2/(9d₁) + f^⅔·2/(9d₂))`.
pub fn paulson_z(f: f64, d1: f64, d2: f64) -> f64 {
    let (a, b) = (2.0 / (9.0 * d1), 2.0 / (9.0 * d2));
    let c = f.max(0.0).cbrt();
    ((1.0 - b) * c - (1.0 - a)) / (a + c * c * b).sqrt()
}

/// `z` of `T_S` (module docs) of candidate `e` over the sensors `set`;
/// `None` when a sensor of the set has no fit or the candidate adds no
/// column there.
pub fn set_z(e: Effect, base: &[Rss], cand: &[Option<Rss>], set: &[usize]) -> Option<f64> {
    let (mut t, mut q, mut nu) = (0.0, 0usize, 0.0);
    for &i in set {
        let (b, c) = (base.get(i)?, (*cand.get(i)?)?);
        let qi = c.columns.checked_sub(b.columns).filter(|q| *q > 0)?;
        let scale = c.rss / c.nu();
        if !(scale > 0.0) {
            return None;
        }
        t += (b.rss - c.rss).max(0.0) / scale;
        q += qi;
        nu += c.nu();
    }
    let d1 = (q + chosen_params(e)) as f64;
    (q > 0).then(|| paulson_z(t / d1, d1, nu))
}

/// `z` of every set of [`sets`] (index 0 the head, `i + 1` sensor `i`).
pub fn zs(e: Effect, base: &[Rss], cand: &[Option<Rss>]) -> Vec<Option<f64>> {
    sets(base.len())
        .iter()
        .map(|s| set_z(e, base, cand, s))
        .collect()
}

/// Held-out mean-square gain per reading of `cand` over `base` on the
/// sensors `set` [mm²] (the poses both predict), from the folds' held-out
/// residuals: the cross-validation guard of the nested test.
pub fn heldout_gain(base: &CvResult, cand: &CvResult, set: &[usize]) -> f64 {
    let (mut d, mut n) = (0.0, 0usize);
    for (rb, rc) in base.resid.iter().zip(&cand.resid) {
        for &i in set {
            if let (Some(Some(b)), Some(Some(c))) = (rb.get(i), rc.get(i)) {
                d += b * b - c * c;
                n += 1;
            }
        }
    }
    if n > 0 {
        d / n as f64
    } else {
        0.0
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// Paulson's approximation against tabulated F quantiles: the upper
    /// 1 % point of F(1, 50) is 7.17, of F(4, 200) 3.41, of F(2, 60) 4.98
    /// (z = 2.326 there), and the median of F(4, 200) about 0.84 (z ≈ 0).
    #[test]
    fn paulson_matches_tabulated_quantiles() {
        for (f, d1, d2) in [(7.17, 1.0, 50.0), (3.41, 4.0, 200.0), (4.98, 2.0, 60.0)] {
            let z = paulson_z(f, d1, d2);
            assert!((z - 2.326).abs() < 0.06, "F({d1}, {d2}) at {f}: z {z}");
        }
        assert!(paulson_z(0.84, 4.0, 200.0).abs() < 0.05);
    }

    /// The head's set sums the sensors; a sensor alone sees only itself;
    /// a candidate that adds no column is not tested.
    #[test]
    fn sets_sum_their_sensors() {
        let base = vec![
            Rss {
                rss: 1.2,
                columns: 0,
                used: 60,
            };
            4
        ];
        let mut cand = vec![
            Some(Rss {
                rss: 1.0,
                columns: 1,
                used: 60,
            });
            4
        ];
        cand[3] = Some(Rss {
            rss: 1.2,
            columns: 1,
            used: 60,
        });
        let z = zs(Effect::Gain, &base, &cand);
        assert_eq!(sets(4).len(), 5);
        assert_eq!(z.len(), 5);
        // sensors 1-3: T = 0.2/(1.0/54) = 10.8 of F(1, 54), z ≈ 2.9;
        // sensor 4 gains nothing: its own z is far below the others'
        assert!(z[4].unwrap() < 0.0, "{z:?}");
        assert!((2.7..3.1).contains(&z[1].unwrap()), "{z:?}");
        // the head pools three strong sensors and one null one: more
        // evidence than any one of them
        assert!(z[0].unwrap() > z[1].unwrap() + 1.0, "{z:?}");
        assert!(set_z(
            Effect::Gain,
            &base,
            &base.iter().map(|b| Some(*b)).collect::<Vec<_>>(),
            &[0]
        )
        .is_none());
    }
}
