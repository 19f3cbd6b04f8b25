//! Sampling distributions of a table's statistics (parametric bootstrap
//! over seeds: each seed is one simulated experiment of 20 test points) and
//! the probability of a measured value under them.
//!
//! **Per statistic.** The two-sided tail probability of the measured value
//! `x` among `N` simulated values: `p = min(1, 2·min(k≤, k≥)/(N + 1))` with
//! `k≤ = 1 + #{s ≤ x}` and `k≥ = 1 + #{s ≥ x}` (the +1 counts the measured
//! experiment itself, so `p ≥ 2/(N + 1)`: the smallest probability `N`
//! seeds can state).
//!
//! **A row.** Its three statistics (max, mean, std) are judged together
//! by Bonferroni: `p_row = min(1, 3·min(p_max, p_mean, p_std))`, which
//! holds whatever their correlation (conservative).
//!
//! Limits: `N` seeds resolve probabilities down to ~`1/N`; below that the
//! report says "< 1/(N+1)".

use serde::Serialize;

use super::model::Stat3;
use perpend_calib::stats;

/// A statistic's simulated distribution against the measured value.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Versus {
    /// Measured value.
    pub measured: f64,
    /// 2.5th percentile of the simulated values.
    pub lo: f64,
    /// Median.
    pub median: f64,
    /// 97.5th percentile.
    pub hi: f64,
    /// Two-sided tail probability of the measured value.
    pub p: f64,
}

/// All three statistics of a table row, and the joint probability.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RowVersus {
    /// Simulated experiments (converged seeds).
    pub n: usize,
    /// Largest of the 20 errors.
    pub max: Versus,
    /// Mean of the 20 errors.
    pub mean: Versus,
    /// Std of the 20 errors.
    pub std: Versus,
    /// The row's probability (Bonferroni over the three statistics).
    pub row_p: f64,
}

/// Two-sided tail probability of `x` among `sim` (module docs).
pub fn two_sided(sim: &[f64], x: f64) -> f64 {
    if sim.is_empty() {
        // Nothing simulated (every EKF diverged) reproduces a measured row.
        return 0.0;
    }
    let n = sim.len() as f64;
    let le = 1.0 + sim.iter().filter(|s| **s <= x).count() as f64;
    let ge = 1.0 + sim.iter().filter(|s| **s >= x).count() as f64;
    (2.0 * le.min(ge) / (n + 1.0)).min(1.0)
}

/// The distribution of `sim` against `x`.
pub fn versus(sim: &[f64], x: f64) -> Versus {
    Versus {
        measured: x,
        lo: stats::quantile(sim, 0.025),
        median: stats::quantile(sim, 0.5),
        hi: stats::quantile(sim, 0.975),
        p: two_sided(sim, x),
    }
}

/// A simulated row against the measured `(max, mean, std)`.
pub fn row_versus(sim: &[Stat3], measured: Stat3) -> RowVersus {
    let col = |f: fn(&Stat3) -> f64| -> Vec<f64> { sim.iter().map(f).collect() };
    let mut r = RowVersus {
        n: sim.len(),
        max: versus(&col(|s| s.max), measured.max),
        mean: versus(&col(|s| s.mean), measured.mean),
        std: versus(&col(|s| s.std), measured.std),
        row_p: 0.0,
    };
    r.row_p = (3.0 * r.max.p.min(r.mean.p).min(r.std.p)).min(1.0);
    r
}

/// Significance level of the verdicts.
pub const ALPHA: f64 = 0.05;

/// The verdict a probability supports, given the smallest probability the
/// seeds can state (`floor`).
pub fn verdict(p: f64, floor: f64) -> &'static str {
    if p >= ALPHA {
        "agrees"
    } else if floor >= ALPHA {
        "too few seeds"
    } else {
        "disagrees"
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn two_sided_is_one_at_the_median_and_floors_at_two_over_n_plus_one() {
        let sim: Vec<f64> = (0..99).map(f64::from).collect();
        approx::assert_relative_eq!(two_sided(&sim, 49.0), 1.0);
        approx::assert_relative_eq!(two_sided(&sim, 1e6), 2.0 / 100.0);
        approx::assert_relative_eq!(two_sided(&sim, -1.0), 2.0 / 100.0);
        // 10 of 99 at or below 9: p = 2·11/100.
        approx::assert_relative_eq!(two_sided(&sim, 9.0), 0.22);
    }

    #[test]
    fn row_probability_is_bonferroni_of_the_three() {
        let sim: Vec<Stat3> = (0..99)
            .map(|k| {
                let x = f64::from(k);
                Stat3 {
                    max: x,
                    mean: x,
                    std: x,
                }
            })
            .collect();
        let r = row_versus(
            &sim,
            Stat3 {
                max: 49.0,
                mean: 9.0,
                std: 1e6,
            },
        );
        approx::assert_relative_eq!(r.max.p, 1.0);
        approx::assert_relative_eq!(r.row_p, 3.0 * 2.0 / 100.0);
        assert_eq!(verdict(r.row_p, 0.02), "agrees");
        assert_eq!(verdict(0.01, 0.005), "disagrees");
        assert_eq!(verdict(0.06, 0.06), "agrees");
        assert_eq!(verdict(0.04, 0.06), "too few seeds");
    }
}
