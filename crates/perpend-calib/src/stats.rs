//! Small statistics used by the diagnosis: means and spreads, normal and
//! Student-t quantiles, Pearson correlation, the lag-1 autocorrelation and
//! the Wald-Wolfowitz runs test of a residual sequence, and the pooled
//! fraction of residual variance a set of regressors explains.
//!
//! Limits: the quantile functions are approximations (normal: Acklam's
//! rational approximation, relative error < 1.2e-9; Student t:
//! Cornish-Fisher expansion to order ν⁻³, better than 1% for ν ≥ 3; the
//! normal tail: the Chebyshev fit of erfc in Numerical Recipes §6.2,
//! relative error < 1.2e-7), ample for decision thresholds and p-values.

/// Mean of `v` (0 for an empty slice).
pub fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// Sample standard deviation (n − 1; 0 for fewer than two values).
pub fn sd(v: &[f64]) -> f64 {
    let n = v.len();
    if n < 2 {
        return 0.0;
    }
    let m = mean(v);
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1) as f64).sqrt()
}

/// Root mean square (0 for an empty slice).
pub fn rms(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    }
}

/// The `q`-quantile of `v` (linear interpolation; 0 for an empty slice).
pub fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return 0.0;
    }
    s.sort_by(f64::total_cmp);
    let pos = q.clamp(0.0, 1.0) * (s.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    let f = pos - lo as f64;
    s[lo] * (1.0 - f) + s[hi] * f
}

/// Quantile function of the standard normal distribution (Acklam).
/// `p` outside (0, 1) is clamped to [1e-300, 1 − 1e-16].
pub fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let p = p.clamp(1e-300, 1.0 - 1e-16);
    let plow = 0.02425;
    if p < plow {
        let q = (-2.0 * p.ln()).sqrt();
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    } else if p <= 1.0 - plow {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    } else {
        let q = (-2.0 * (1.0 - p).ln()).sqrt();
        -(((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    }
}

/// Upper tail `P(Z > z)` of the standard normal distribution, through the
/// Chebyshev fit of `erfc` (Numerical Recipes §6.2, relative error
/// < 1.2e-7 everywhere); the inverse of [`normal_quantile`] on its upper
/// side.
pub fn normal_upper_tail(z: f64) -> f64 {
    let x = z / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * x.abs());
    const C: [f64; 10] = [
        -1.265_512_23,
        1.000_023_68,
        0.374_091_96,
        0.096_784_18,
        -0.186_288_06,
        0.278_868_07,
        -1.135_203_98,
        1.488_515_87,
        -0.822_152_23,
        0.170_872_77,
    ];
    let poly = C.iter().rev().fold(0.0, |acc, c| acc * t + c);
    let erfc = t * (-x * x + poly).exp();
    let erfc = if x >= 0.0 { erfc } else { 2.0 - erfc };
    0.5 * erfc
}

/// Quantile of Student's t with `nu` degrees of freedom (Cornish-Fisher
/// expansion about the normal quantile; `nu = ∞` gives the normal).
pub fn t_quantile(p: f64, nu: f64) -> f64 {
    let z = normal_quantile(p);
    if !nu.is_finite() || nu <= 0.0 {
        return z;
    }
    let z2 = z * z;
    let g1 = (z2 + 1.0) * z / 4.0;
    let g2 = ((5.0 * z2 + 16.0) * z2 + 3.0) * z / 96.0;
    let g3 = (((3.0 * z2 + 19.0) * z2 + 17.0) * z2 - 15.0) * z / 384.0;
    z + g1 / nu + g2 / (nu * nu) + g3 / (nu * nu * nu)
}

/// Pearson correlation of paired samples (0 when either is constant).
pub fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len().min(y.len());
    if n < 2 {
        return 0.0;
    }
    let (mx, my) = (mean(&x[..n]), mean(&y[..n]));
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for i in 0..n {
        let (a, b) = (x[i] - mx, y[i] - my);
        sxy += a * b;
        sxx += a * a;
        syy += b * b;
    }
    if sxx > 0.0 && syy > 0.0 {
        sxy / (sxx * syy).sqrt()
    } else {
        0.0
    }
}

/// Lag-1 autocorrelation pooled over several sequences (each centred on
/// its own mean; `None` entries break the chain): returns `(r1, pairs)`.
/// For white noise `r1 ≈ 0 ± 1/√pairs`.
pub fn lag1(seqs: &[Vec<Option<f64>>]) -> (f64, usize) {
    let (mut num, mut den, mut pairs) = (0.0, 0.0, 0usize);
    for s in seqs {
        let vals: Vec<f64> = s.iter().flatten().copied().collect();
        if vals.len() < 3 {
            continue;
        }
        let m = mean(&vals);
        den += vals.iter().map(|x| (x - m) * (x - m)).sum::<f64>();
        for w in s.windows(2) {
            if let (Some(a), Some(b)) = (w[0], w[1]) {
                num += (a - m) * (b - m);
                pairs += 1;
            }
        }
    }
    if den > 0.0 {
        (num / den, pairs)
    } else {
        (0.0, pairs)
    }
}

/// Wald-Wolfowitz runs test on the signs of a sequence (about its median;
/// `None` and values equal to the median are skipped): the z statistic,
/// negative when there are fewer runs than chance (positively correlated
/// residuals, a slow pattern). 0 when undefined.
pub fn runs_z(seq: &[Option<f64>]) -> f64 {
    let vals: Vec<f64> = seq.iter().flatten().copied().collect();
    if vals.len() < 4 {
        return 0.0;
    }
    let med = quantile(&vals, 0.5);
    let signs: Vec<bool> = vals
        .iter()
        .filter(|&&v| v != med)
        .map(|&v| v > med)
        .collect();
    let n1 = signs.iter().filter(|&&s| s).count() as f64;
    let n2 = signs.len() as f64 - n1;
    let n = n1 + n2;
    if n1 < 1.0 || n2 < 1.0 {
        return 0.0;
    }
    let runs = 1.0 + signs.windows(2).filter(|w| w[0] != w[1]).count() as f64;
    let mu = 2.0 * n1 * n2 / n + 1.0;
    let var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0));
    if var > 0.0 {
        (runs - mu) / var.sqrt()
    } else {
        0.0
    }
}

/// Wilcoxon signed-rank test of paired differences `d` against a median
/// of 0 (zeros dropped, average ranks for ties, normal approximation with
/// the tie-corrected variance): the z statistic, positive when the
/// differences are mostly positive. 0 with fewer than two non-zero values.
pub fn signed_rank_z(d: &[f64]) -> f64 {
    let mut v: Vec<f64> = d
        .iter()
        .copied()
        .filter(|x| *x != 0.0 && x.is_finite())
        .collect();
    let n = v.len();
    if n < 2 {
        return 0.0;
    }
    v.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
    let mut w_plus = 0.0;
    let mut tie_corr = 0.0;
    let mut i = 0;
    while i < n {
        let mut j = i + 1;
        while j < n && v[j].abs() == v[i].abs() {
            j += 1;
        }
        // ranks i+1 ..= j share their average
        let rank = (i + 1 + j) as f64 / 2.0;
        let t = (j - i) as f64;
        tie_corr += t * t * t - t;
        for x in &v[i..j] {
            if *x > 0.0 {
                w_plus += rank;
            }
        }
        i = j;
    }
    let nf = n as f64;
    let mu = nf * (nf + 1.0) / 4.0;
    let var = nf * (nf + 1.0) * (2.0 * nf + 1.0) / 24.0 - tie_corr / 48.0;
    if var > 0.0 {
        (w_plus - mu) / var.sqrt()
    } else {
        0.0
    }
}

/// Fraction of the variance of `y` explained by a least-squares fit on the
/// columns `xs` plus an intercept (R²). 0 when the columns are degenerate.
pub fn r_squared(y: &[f64], xs: &[Vec<f64>]) -> f64 {
    let (expl, total) = explained(y, xs);
    if total > 0.0 {
        expl / total
    } else {
        0.0
    }
}

/// `(explained, total)` sums of squares of `y` about its mean for the
/// least-squares fit on the columns `xs` plus an intercept (columns
/// standardised, solved by SVD so that dependent columns are harmless).
pub fn explained(y: &[f64], xs: &[Vec<f64>]) -> (f64, f64) {
    let n = y.len();
    let p = xs.len();
    if n <= p + 1 || p == 0 || xs.iter().any(|c| c.len() != n) {
        return (0.0, 0.0);
    }
    let my = mean(y);
    let total: f64 = y.iter().map(|v| (v - my) * (v - my)).sum();
    let x = nalgebra::DMatrix::from_fn(n, p, |k, j| {
        let c = &xs[j];
        let m = mean(c);
        let s = sd(c);
        if s > 0.0 {
            (c[k] - m) / s
        } else {
            0.0
        }
    });
    let yc = nalgebra::DVector::from_fn(n, |k, _| y[k] - my);
    let Ok(b) = x
        .clone()
        .svd(true, true)
        .solve(&yc, 1e-9 * (n as f64).sqrt())
    else {
        return (0.0, total);
    };
    let fit = &x * b;
    (fit.norm_squared().min(total), total)
}

/// Smallest p reported (the re-simulations' spread says nothing finer).
pub const P_MIN: f64 = 1e-16;

/// One-sided tail `P(t_ν > z)` of Student's t, by inverting
/// [`t_quantile`] (bisection on `log p`), at least [`P_MIN`].
pub fn t_tail(z: f64, nu: f64) -> f64 {
    if z <= 0.0 {
        return 0.5;
    }
    let (mut lo, mut hi) = (P_MIN.ln(), 0.5f64.ln());
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if t_quantile(1.0 - mid.exp(), nu) > z {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi.exp()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// The upper tail against tabulated values and as the inverse of the
    /// quantile function (both sides).
    #[test]
    fn normal_upper_tail_golden() {
        assert_relative_eq!(normal_upper_tail(0.0), 0.5, max_relative = 1e-7);
        assert_relative_eq!(normal_upper_tail(1.959_963_985), 0.025, max_relative = 1e-6);
        assert_relative_eq!(normal_upper_tail(-1.0), 0.841_344_746, max_relative = 1e-6);
        assert_relative_eq!(normal_upper_tail(3.090_232_306), 1e-3, max_relative = 1e-6);
        for p in [1e-6, 1e-3, 0.02, 0.3, 0.7, 0.99] {
            let z = normal_quantile(1.0 - p);
            assert_relative_eq!(normal_upper_tail(z), p, max_relative = 1e-5);
        }
    }

    #[test]
    fn normal_and_t_quantiles_golden() {
        assert_relative_eq!(normal_quantile(0.5), 0.0, epsilon = 1e-12);
        assert_relative_eq!(normal_quantile(0.975), 1.959_963_985, epsilon = 1e-8);
        assert_relative_eq!(normal_quantile(0.01), -2.326_347_874, epsilon = 1e-8);
        assert_relative_eq!(normal_quantile(1.0 - 1e-4), 3.719_016_485, epsilon = 1e-7);
        // t tables: t_{0.99, 7} = 2.998, t_{0.975, 10} = 2.228, t_{0.99, 30} = 2.457
        assert_relative_eq!(t_quantile(0.99, 7.0), 2.998, epsilon = 0.03);
        assert_relative_eq!(t_quantile(0.975, 10.0), 2.228, epsilon = 0.005);
        assert_relative_eq!(t_quantile(0.99, 30.0), 2.457, epsilon = 0.002);
    }

    #[test]
    fn moments_golden() {
        let v = [1.0, 2.0, 3.0, 4.0];
        assert_relative_eq!(mean(&v), 2.5);
        assert_relative_eq!(sd(&v), (5.0f64 / 3.0).sqrt());
        assert_relative_eq!(rms(&v), 7.5f64.sqrt());
        assert_relative_eq!(quantile(&v, 0.5), 2.5);
        assert_relative_eq!(quantile(&v, 1.0), 4.0);
    }

    #[test]
    fn correlation_and_r2_golden() {
        let x: Vec<f64> = (0..20).map(|i| i as f64).collect();
        let y: Vec<f64> = x.iter().map(|v| 3.0 * v + 1.0).collect();
        assert_relative_eq!(pearson(&x, &y), 1.0, epsilon = 1e-12);
        assert_relative_eq!(
            r_squared(&y, std::slice::from_ref(&x)),
            1.0,
            epsilon = 1e-12
        );
        // y = x² on symmetric x: uncorrelated with x, explained by x².
        let xs: Vec<f64> = (-10..=10).map(|i| i as f64).collect();
        let y2: Vec<f64> = xs.iter().map(|v| v * v).collect();
        let x2: Vec<f64> = xs.iter().map(|v| v * v).collect();
        assert_relative_eq!(pearson(&xs, &y2), 0.0, epsilon = 1e-12);
        assert_relative_eq!(
            r_squared(&y2, std::slice::from_ref(&xs)),
            0.0,
            epsilon = 1e-12
        );
        assert_relative_eq!(r_squared(&y2, &[xs.clone(), x2]), 1.0, epsilon = 1e-9);
    }

    #[test]
    fn signed_rank_golden() {
        // d = 1..=10 all positive: W+ = 55, mu = 27.5, var = 96.25.
        let d: Vec<f64> = (1..=10).map(|i| i as f64).collect();
        assert_relative_eq!(signed_rank_z(&d), 27.5 / 96.25f64.sqrt(), epsilon = 1e-12);
        // symmetric: z = 0
        let s: Vec<f64> = (1..=10).flat_map(|i| [i as f64, -(i as f64)]).collect();
        assert_relative_eq!(signed_rank_z(&s), 0.0, epsilon = 1e-12);
        // a few huge negatives do not outweigh many positives in rank
        let mut m: Vec<f64> = (1..=30).map(|i| i as f64 * 0.01).collect();
        m.extend([-100.0, -200.0]);
        assert!(signed_rank_z(&m) > 3.0);
    }

    #[test]
    fn lag1_and_runs_detect_a_slow_pattern() {
        // Alternating signs: r1 = -1 (minus end effects), many runs.
        let alt: Vec<Option<f64>> = (0..40)
            .map(|i| Some(if i % 2 == 0 { 1.0 } else { -1.0 }))
            .collect();
        let (r, pairs) = lag1(std::slice::from_ref(&alt));
        assert_eq!(pairs, 39);
        assert_relative_eq!(r, -39.0 / 40.0, epsilon = 1e-12);
        assert!(runs_z(&alt) > 5.0);
        // Two blocks: one run each, far fewer runs than chance.
        let blocks: Vec<Option<f64>> = (0..40)
            .map(|i| Some(if i < 20 { 1.0 } else { -1.0 }))
            .collect();
        assert!(runs_z(&blocks) < -5.0);
        // Missing values break the chain.
        let gap = vec![Some(1.0), None, Some(-1.0), Some(1.0)];
        assert_eq!(lag1(&[gap]).1, 1);
    }

    #[test]
    fn t_tail_inverts_the_quantile() {
        for (p, nu) in [(0.05, 10.0), (1e-3, 40.0), (1e-6, 47.0)] {
            let z = t_quantile(1.0 - p, nu);
            let back = t_tail(z, nu);
            assert!((back / p - 1.0).abs() < 1e-6, "{p} → {z} → {back}");
        }
        assert!((t_tail(-1.0, 5.0) - 0.5).abs() < 1e-12);
    }
}
