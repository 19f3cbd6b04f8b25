//! The conformity decision of a verification against a tolerance, with the
//! verification's own measurement uncertainty (issue 45).
//!
//! **Measurand.** The calibrated board's systematic normal error at each
//! verified pose: the angle between the board's normal, averaged over the
//! pose's samples (the mean of the sample normals, then normalised), and
//! the datum plane's true normal. The tolerance is a maximum permissible
//! error (MPE) on that angle at every verified pose.
//!
//! **Uncertainty** (GUM, JCGM 100:2008 §5.1.2, first order): the measured
//! angle `e = |d|`, `d` the 2-D error vector, has per-axis standard
//! uncertainty `u = √(u_t² + u_r²)` from
//! - `u_t`, the tracker's: the 1σ per axis of the normal it fits to its
//!   points (type B, from the tracker's point noise ξ, point count N and
//!   patch side L: `ξ/√(N·L²/12)` for points spread uniformly over the
//!   patch, or as the cell configuration states it);
//! - `u_r`, the board's readings': the scatter of the pose's sample
//!   normals per axis over √samples (type A, from the pose itself).
//!
//! The sensitivity of `|d|` to `d` is 1 along `d`, so `u(e) = u`.
//! Expanded uncertainty `U = k·u` for about 95 % coverage of the error's
//! component along its own direction, which is what decides near the
//! tolerance whenever the error there is much larger than `u` (the
//! tolerances of a cell, 0.02-0.1°, against u ≈ 0.006-0.015°). As a
//! radius around an error near zero, 2u covers only 86 % of a 2-D normal
//! spread, but there the norm is also biased upwards (by up to 1.25 u),
//! which makes PASS harder, never easier.
//!
//! **Coverage factor** (JCGM 100:2008 G.4, G.6.4). `u_r` is estimated
//! from the pose's own `n` samples, with `ν_r = n − 1` degrees of freedom
//! (the per-axis variance is pooled over both axes, which would give
//! `2(n − 1)` for an isotropic scatter; `n − 1` does not assume it);
//! `u_t` is a type B figure taken as exact (`ν_t = ∞`). The effective
//! degrees of freedom follow Welch–Satterthwaite (eq. G.2b),
//! `ν_eff = u⁴ / (u_r⁴ / ν_r)`, and `k = t_95.45(ν_eff)`, Student's t of
//! Table G.2 (ν_eff truncated to the integer below it up to 20, as G.6.4
//! directs; linear in 1/ν between the table's rows above that). So `k` is
//! 2 when the tracker dominates or the pose has many samples, 2.05 at
//! ν_eff = 50, 2.87 at 4 and 13.97 at 1: a pose verified with 2 samples
//! is not given the coverage of 20.
//!
//! **Decision rule** (ISO 14253-1:2017 §5, ILAC-G8:09/2019 §4.2.3,
//! guarded acceptance and rejection with guard band `w = U`): a pose
//! conforms (PASS) when `e + U ≤ T`, does not (FAIL) when `e − U > T`, and
//! is INCONCLUSIVE in between. The verification PASSes when every pose
//! does, FAILs when any pose does, and is INCONCLUSIVE otherwise.
//!
//! **What would decide it.** Only the readings' share shrinks with more
//! samples: an inconclusive pose is decided with `m'` samples when
//! `k·√(u_t² + u_r²·m/m') < |T − e|`; when the tracker's share alone is
//! too large, no sample count decides it (the tracker must measure the
//! plane with more points or less noise). More poses do not decide an MPE
//! verification: each pose is a test of its own.
//!
//! Limits: the poses are the cell run's fresh poses, a sample of the
//! plan's reach; the statement holds at those poses. The readings' share
//! assumes independent samples (the board's noise is white at the SYNC
//! rate in the virtual board; a real board's drift within a pose is not in
//! `u_r`).

use serde::{Deserialize, Serialize};

/// Coverage factor of the expanded uncertainty with infinite degrees of
/// freedom (the normal distribution's 95.45 %).
pub const K: f64 = 2.0;

/// The decision rule as stated in records and certificates.
pub const RULE: &str = "ISO 14253-1:2017 guarded acceptance and rejection (ILAC-G8:09/2019 \
    §4.2.3), guard band = expanded uncertainty U = k·u, k = Student's t for 95.45 % coverage \
    at the Welch–Satterthwaite effective degrees of freedom (JCGM 100:2008 G.4, Table G.2; \
    k = 2 with many samples), applied at every verified pose to the tolerance as a maximum \
    permissible normal error";

/// Student's t for 95.45 % two-sided coverage, ν = 1 … 20 (JCGM 100:2008
/// Table G.2, to three decimals: the quantile of t computed again by
/// numerical integration of its density agrees with the table's two).
/// A table rather than `perpend_calib::stats::t_quantile`: that
/// Cornish-Fisher series sits a floor above this crate and is 25 % low
/// at ν = 1 (10.4 for 13.97), where a verification with 2 samples lands.
const T_9545: [f64; 20] = [
    13.968, 4.527, 3.307, 2.869, 2.649, 2.517, 2.429, 2.366, 2.320, 2.284, 2.255, 2.231, 2.212,
    2.195, 2.181, 2.169, 2.158, 2.149, 2.140, 2.133,
];

/// The table's rows above ν = 20: (ν, t); ν = ∞ gives [`K`].
const T_9545_TAIL: [(f64, f64); 8] = [
    (20.0, 2.133),
    (25.0, 2.105),
    (30.0, 2.087),
    (35.0, 2.074),
    (40.0, 2.064),
    (45.0, 2.057),
    (50.0, 2.051),
    (100.0, 2.025),
];

/// The coverage factor for `nu` effective degrees of freedom (module
/// header): Table G.2's t at ν truncated to an integer up to 20, linear in
/// 1/ν above (to [`K`] at ν = ∞); ν below 1 is taken as 1, NaN as 1.
pub fn coverage_factor(nu: f64) -> f64 {
    if nu.is_nan() || nu < 20.0 {
        let i = if nu.is_nan() {
            1.0
        } else {
            nu.floor().clamp(1.0, 20.0)
        };
        return T_9545[i as usize - 1];
    }
    let inv = 1.0 / nu;
    let mut upper = (f64::INFINITY, K);
    for &(n, t) in T_9545_TAIL.iter().rev() {
        if nu >= n {
            let (n_hi, t_hi) = upper;
            let w = (1.0 / n - inv) / (1.0 / n - 1.0 / n_hi);
            return t + w * (t_hi - t);
        }
        upper = (n, t);
    }
    T_9545_TAIL[0].1
}

/// The Welch–Satterthwaite effective degrees of freedom of `√(ut² + ur²)`
/// with `ut` exact and `ur` from `samples` samples (`ν = samples − 1`);
/// infinite when the readings' share is zero.
pub fn effective_dof(ut: f64, ur: f64, samples: usize) -> f64 {
    let nu_r = samples.saturating_sub(1).max(1) as f64;
    let u2 = ut * ut + ur * ur;
    if ur <= 0.0 {
        return f64::INFINITY;
    }
    u2 * u2 / (ur.powi(4) / nu_r)
}

/// Largest sample count ever suggested.
const MAX_SAMPLES: f64 = 1.0e6;

/// The verdict of a pose or of a verification.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Verdict {
    /// Conformance proven: the result plus its expanded uncertainty is
    /// within the tolerance.
    #[serde(rename = "PASS")]
    Pass,
    /// Non-conformance proven: the result minus its expanded uncertainty
    /// is beyond the tolerance.
    #[serde(rename = "FAIL")]
    Fail,
    /// Neither: the uncertainty straddles the tolerance.
    #[serde(rename = "INCONCLUSIVE")]
    Inconclusive,
}

impl Verdict {
    /// `PASS`, `FAIL` or `INCONCLUSIVE`.
    pub fn word(self) -> &'static str {
        match self {
            Verdict::Pass => "PASS",
            Verdict::Fail => "FAIL",
            Verdict::Inconclusive => "INCONCLUSIVE",
        }
    }
}

/// One verified pose as measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measured {
    /// Pose number.
    pub pose: i64,
    /// The normal error of the board's averaged normal [deg].
    pub error_deg: f64,
    /// The readings' standard uncertainty per axis of that normal [deg]
    /// (sample scatter / √samples).
    pub readings_u_deg: f64,
    /// Samples averaged.
    pub samples: usize,
}

/// One pose's decision as recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseDecision {
    /// Pose number.
    pub pose: i64,
    /// Normal error of the board's averaged normal [deg].
    pub error_deg: f64,
    /// Combined standard uncertainty [deg] (tracker ⊕ readings).
    pub u_deg: f64,
    /// Coverage factor of this pose (from its effective degrees of
    /// freedom; records written before it was stored used 2).
    #[serde(default = "k_default")]
    pub k: f64,
    /// Welch–Satterthwaite effective degrees of freedom (`null`: infinite,
    /// or a record written before it was stored).
    #[serde(default)]
    pub nu_eff: Option<f64>,
    /// Expanded uncertainty `k·u` [deg].
    pub expanded_deg: f64,
    /// The readings' share of `u` [deg].
    pub readings_u_deg: f64,
    /// Samples averaged.
    pub samples: usize,
    /// PASS, FAIL or INCONCLUSIVE.
    pub verdict: Verdict,
}

/// A verification's decision against its tolerance (the record's
/// `decision`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Decision {
    /// The tolerance: maximum permissible normal error [deg].
    pub tolerance_deg: f64,
    /// The decision rule in words ([`RULE`]).
    pub rule: String,
    /// The largest coverage factor of a pose (2 with many samples).
    pub k: f64,
    /// The tracker's standard uncertainty per axis of a plane normal [deg].
    pub tracker_u_deg: f64,
    /// Where that figure comes from.
    pub tracker_u_source: String,
    /// Per pose.
    pub poses: Vec<PoseDecision>,
    /// The verification's verdict.
    pub verdict: Verdict,
    /// The largest expanded uncertainty of a pose [deg].
    pub max_expanded_deg: f64,
    /// What would decide an INCONCLUSIVE verification (`null` otherwise).
    pub decide_by: Option<String>,
    /// Samples per pose that would decide it (`null`: none would, or it
    /// is decided).
    pub samples_needed: Option<usize>,
}

fn k_default() -> f64 {
    K
}

/// The tracker's standard uncertainty per axis of a fitted plane normal
/// [rad]: `N` points with noise `ξ` (1σ per coordinate, mm) spread
/// uniformly over a square patch of side `L` mm (variance `L²/12` per
/// axis): `ξ/√(N·L²/12)`. `None` for fewer than 3 points or a
/// non-positive patch.
pub fn tracker_u_rad(xi_mm: f64, points: usize, patch_mm: f64) -> Option<f64> {
    let ok = points >= 3 && patch_mm > 0.0 && xi_mm >= 0.0 && xi_mm.is_finite();
    ok.then(|| xi_mm / (points as f64 * patch_mm * patch_mm / 12.0).sqrt())
}

/// The decision of the `measured` poses against `tolerance_deg`, with the
/// tracker's share `tracker_u_deg` (per axis) from `source`.
pub fn decide(
    measured: &[Measured],
    tolerance_deg: f64,
    tracker_u_deg: f64,
    source: &str,
) -> Decision {
    let poses: Vec<PoseDecision> = measured
        .iter()
        .map(|m| pose_decision(m, tolerance_deg, tracker_u_deg))
        .collect();
    let verdict = if poses.is_empty() {
        Verdict::Inconclusive
    } else if poses.iter().any(|p| p.verdict == Verdict::Fail) {
        Verdict::Fail
    } else if poses.iter().all(|p| p.verdict == Verdict::Pass) {
        Verdict::Pass
    } else {
        Verdict::Inconclusive
    };
    let (decide_by, samples_needed) = match verdict {
        Verdict::Inconclusive => what_decides(measured, &poses, tolerance_deg, tracker_u_deg),
        _ => (None, None),
    };
    Decision {
        tolerance_deg,
        rule: RULE.into(),
        k: poses.iter().map(|p| p.k).fold(K, f64::max),
        tracker_u_deg,
        tracker_u_source: source.into(),
        max_expanded_deg: poses.iter().map(|p| p.expanded_deg).fold(0.0, f64::max),
        poses,
        verdict,
        decide_by,
        samples_needed,
    }
}

fn pose_decision(m: &Measured, t: f64, ut: f64) -> PoseDecision {
    let u = ut.hypot(m.readings_u_deg);
    let nu = effective_dof(ut, m.readings_u_deg, m.samples);
    let k = coverage_factor(nu);
    let big_u = k * u;
    let verdict = if m.error_deg + big_u <= t {
        Verdict::Pass
    } else if m.error_deg - big_u > t {
        Verdict::Fail
    } else {
        Verdict::Inconclusive
    };
    PoseDecision {
        pose: m.pose,
        error_deg: m.error_deg,
        u_deg: u,
        k,
        nu_eff: nu.is_finite().then_some(nu),
        expanded_deg: big_u,
        readings_u_deg: m.readings_u_deg,
        samples: m.samples,
        verdict,
    }
}

/// Samples that would decide pose `m` against `t` (the smallest count
/// whose `U`, with the readings' share `u_r·√(n/n')` and the coverage
/// factor of its own degrees of freedom, is inside the margin): `None`
/// when the tracker's share alone is too large.
fn samples_to_decide(m: &Measured, t: f64, ut: f64) -> Option<usize> {
    let margin = (t - m.error_deg).abs();
    if K * ut >= margin {
        return None;
    }
    let ur2m = m.readings_u_deg.powi(2) * m.samples.max(1) as f64;
    let decides = |n: f64| {
        let ur = (ur2m / n).sqrt();
        coverage_factor(effective_dof(ut, ur, n as usize)) * ut.hypot(ur) < margin
    };
    // U falls as n grows (both u and k do): double, then halve the gap.
    let mut hi = 2.0;
    while !decides(hi) {
        hi *= 2.0;
        if hi > MAX_SAMPLES {
            return None;
        }
    }
    let mut lo = hi / 2.0;
    while hi - lo > 1.0 {
        let mid = ((lo + hi) / 2.0).floor();
        if decides(mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some(hi as usize)
}

/// What would decide an inconclusive verification, in words, and the
/// samples per pose it takes.
fn what_decides(
    measured: &[Measured],
    poses: &[PoseDecision],
    t: f64,
    ut: f64,
) -> (Option<String>, Option<usize>) {
    let open: Vec<(&Measured, &PoseDecision)> = measured
        .iter()
        .zip(poses)
        .filter(|(_, p)| p.verdict == Verdict::Inconclusive)
        .collect();
    let names: Vec<String> = open.iter().map(|(m, _)| m.pose.to_string()).collect();
    let needs: Vec<Option<usize>> = open
        .iter()
        .map(|(m, _)| samples_to_decide(m, t, ut))
        .collect();
    let worst = open
        .iter()
        .map(|(_, p)| p)
        .max_by(|a, b| a.expanded_deg.total_cmp(&b.expanded_deg));
    let head = match worst {
        Some(p) => format!(
            "pose{} {} undecided (e.g. pose {}: {:.4}° ± {:.4}° against {t}°)",
            if names.len() == 1 { "" } else { "s" },
            names.join(", "),
            p.pose,
            p.error_deg,
            p.expanded_deg
        ),
        None => return (Some("no pose was verified".into()), None),
    };
    if needs.iter().any(Option::is_none) {
        let floor = K * ut;
        return (
            Some(format!(
                "{head}: no sample count decides it, the tracker's share alone (U = {floor:.4}°) \
                 is too large for the margin: measure the datum plane with more tracker points \
                 or a quieter tracker, then verify again"
            )),
            None,
        );
    }
    let n = needs.into_iter().flatten().max().unwrap_or(1);
    (
        Some(format!(
            "{head}: verify again with at least {n} samples per pose (--verify-samples {n}); \
             more poses do not decide it, each pose is a test of its own"
        )),
        Some(n),
    )
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn m(pose: i64, e: f64, ur: f64) -> Measured {
        Measured {
            pose,
            error_deg: e,
            readings_u_deg: ur,
            samples: 20,
        }
    }

    #[test]
    fn guard_bands_split_pass_fail_and_inconclusive() {
        // u = √(0.003² + 0.004²) = 0.005; ν_eff = 0.005⁴·19/0.004⁴ = 46.4,
        // k = 2.055 (between Table G.2's 2.057 at 45 and 2.051 at 50),
        // U = 0.0103.
        let d = decide(&[m(1, 0.039, 0.004)], 0.05, 0.003, "test");
        assert_eq!(d.verdict, Verdict::Pass);
        let p = &d.poses[0];
        assert!((p.nu_eff.unwrap() - 19.0 * 625.0 / 256.0).abs() < 1e-9);
        assert!((2.051..2.057).contains(&p.k), "{}", p.k);
        assert!((p.expanded_deg - p.k * 0.005).abs() < 1e-12);
        assert_eq!(d.k, p.k);
        let d = decide(&[m(1, 0.041, 0.004)], 0.05, 0.003, "test");
        assert_eq!(d.verdict, Verdict::Inconclusive);
        let d = decide(&[m(1, 0.059, 0.004)], 0.05, 0.003, "test");
        assert_eq!(d.verdict, Verdict::Inconclusive);
        let d = decide(&[m(1, 0.061, 0.004)], 0.05, 0.003, "test");
        assert_eq!(d.verdict, Verdict::Fail);
        assert_eq!(d.decide_by, None);
        // One failing pose fails the verification, one open pose leaves it open.
        let d = decide(&[m(1, 0.01, 0.001), m(2, 0.07, 0.001)], 0.05, 0.003, "t");
        assert_eq!(d.verdict, Verdict::Fail);
        let d = decide(&[m(1, 0.01, 0.001), m(2, 0.045, 0.004)], 0.05, 0.003, "t");
        assert_eq!(d.verdict, Verdict::Inconclusive);
        assert_eq!(decide(&[], 0.05, 0.003, "t").verdict, Verdict::Inconclusive);
    }

    #[test]
    fn the_samples_named_decide_the_pose_and_fewer_do_not() {
        let p = m(3, 0.035, 0.008);
        let (t, ut) = (0.05, 0.002);
        let d = decide(&[p], t, ut, "t");
        assert_eq!(d.verdict, Verdict::Inconclusive);
        let n = d.samples_needed.unwrap();
        assert!(d
            .decide_by
            .as_ref()
            .unwrap()
            .contains(&format!("{n} samples")));
        // The readings' share with n samples: u_r·√(20/n).
        let with = |k: usize| Measured {
            readings_u_deg: p.readings_u_deg * (20.0 / k as f64).sqrt(),
            samples: k,
            ..p
        };
        assert_eq!(decide(&[with(n)], t, ut, "t").verdict, Verdict::Pass);
        assert_eq!(
            decide(&[with(n - 1)], t, ut, "t").verdict,
            Verdict::Inconclusive
        );
    }

    #[test]
    fn the_coverage_factor_is_table_g2_s_t() {
        // JCGM 100:2008 Table G.2, p = 95.45 %.
        for (nu, t) in [
            (1.0, 13.97),
            (2.0, 4.53),
            (3.0, 3.31),
            (4.0, 2.87),
            (5.0, 2.65),
            (10.0, 2.28),
            (20.0, 2.13),
            (30.0, 2.09),
            (50.0, 2.05),
            (100.0, 2.025),
        ] {
            assert!((coverage_factor(nu) - t).abs() <= 0.005, "ν {nu}");
        }
        // Truncated to the integer below (G.6.4), never below 1.
        assert_eq!(coverage_factor(4.9), coverage_factor(4.0));
        assert_eq!(coverage_factor(0.3), coverage_factor(1.0));
        assert_eq!(coverage_factor(f64::NAN), coverage_factor(1.0));
        assert_eq!(coverage_factor(f64::INFINITY), K);
        assert!((coverage_factor(1e9) - K).abs() < 1e-6);
        // Falls as ν grows, continuously above 20.
        let mut last = f64::INFINITY;
        for i in 1..4000 {
            let k = coverage_factor(i as f64 * 0.25);
            assert!(k <= last && k >= K, "ν {}", i as f64 * 0.25);
            last = k;
        }
        assert!((coverage_factor(24.999) - coverage_factor(25.0)).abs() < 1e-3);
    }

    #[test]
    fn two_samples_are_not_given_the_coverage_of_twenty() {
        // The readings dominate and the pose has 2 samples: ν_eff ≈ 1.
        // With k = 2 this pose would PASS (0.02 + 2·0.0102 ≤ 0.05).
        let p = Measured {
            pose: 1,
            error_deg: 0.02,
            readings_u_deg: 0.01,
            samples: 2,
        };
        let d = decide(&[p], 0.05, 0.002, "t");
        assert!(d.poses[0].k > 10.0, "{}", d.poses[0].k);
        assert_eq!(d.verdict, Verdict::Inconclusive);
        // What would decide it: more samples, counted with their own k.
        let n = d.samples_needed.unwrap();
        let with = |k: usize| Measured {
            readings_u_deg: p.readings_u_deg * (2.0 / k as f64).sqrt(),
            samples: k,
            ..p
        };
        assert_eq!(decide(&[with(n)], 0.05, 0.002, "t").verdict, Verdict::Pass);
        assert_eq!(
            decide(&[with(n - 1)], 0.05, 0.002, "t").verdict,
            Verdict::Inconclusive
        );
        // Many samples, tracker dominant: k = 2 again.
        let d = decide(&[m(1, 0.01, 0.0001)], 0.05, 0.003, "t");
        assert!((d.poses[0].k - K).abs() < 1e-3, "{}", d.poses[0].k);
    }

    #[test]
    fn records_without_k_per_pose_read_as_k_2() {
        let json = r#"{"pose":1,"error_deg":0.01,"u_deg":0.005,"expanded_deg":0.01,
            "readings_u_deg":0.004,"samples":20,"verdict":"PASS"}"#;
        let p: PoseDecision = serde_json::from_str(json).unwrap();
        assert_eq!((p.k, p.nu_eff), (K, None));
    }

    #[test]
    fn a_tracker_too_coarse_for_the_margin_is_named() {
        let d = decide(&[m(1, 0.045, 0.001)], 0.05, 0.004, "t");
        assert_eq!(d.verdict, Verdict::Inconclusive);
        assert_eq!(d.samples_needed, None);
        assert!(d.decide_by.unwrap().contains("tracker"));
    }

    #[test]
    fn the_tracker_share_follows_points_and_patch() {
        // Chen §5: 20 points, ξ = 0.02 mm, 150 mm patch: about 1.0e-4 rad.
        let u = tracker_u_rad(0.02, 20, 150.0).unwrap();
        assert!((u - 0.02 / (20.0f64 * 150.0 * 150.0 / 12.0).sqrt()).abs() < 1e-15);
        assert!((0.9e-4..1.1e-4).contains(&u), "{u}");
        assert_eq!(tracker_u_rad(0.02, 2, 150.0), None);
        assert_eq!(tracker_u_rad(0.02, 20, 0.0), None);
    }
}
