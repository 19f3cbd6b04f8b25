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
//! Expanded uncertainty `U = k·u`, `k = 2`: about 95 % coverage of the
//! error's component along its own direction, which is what decides near
//! the tolerance whenever the error there is much larger than `u` (the
//! tolerances of a cell, 0.02-0.1°, against u ≈ 0.006-0.015°). As a
//! radius around an error near zero, 2u covers only 86 % of a 2-D normal
//! spread, but there the norm is also biased upwards (by up to 1.25 u),
//! which makes PASS harder, never easier.
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

/// Coverage factor of the expanded uncertainty.
pub const K: f64 = 2.0;

/// The decision rule as stated in records and certificates.
pub const RULE: &str = "ISO 14253-1:2017 guarded acceptance and rejection (ILAC-G8:09/2019 \
    §4.2.3), guard band = expanded uncertainty U (k = 2), applied at every verified pose to \
    the tolerance as a maximum permissible normal error";

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
    /// Coverage factor.
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
        k: K,
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
    let big_u = K * u;
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
        expanded_deg: big_u,
        readings_u_deg: m.readings_u_deg,
        samples: m.samples,
        verdict,
    }
}

/// Samples that would decide pose `m` against `t`: `None` when the
/// tracker's share alone is too large.
fn samples_to_decide(m: &Measured, t: f64, ut: f64) -> Option<usize> {
    let allowed = (t - m.error_deg).abs() / K;
    let room = allowed * allowed - ut * ut;
    if room <= 0.0 {
        return None;
    }
    let ur2m = m.readings_u_deg.powi(2) * m.samples.max(1) as f64;
    let need = (ur2m / room).floor() + 1.0;
    (need <= MAX_SAMPLES).then_some(need.max(1.0) as usize)
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
        // u = √(0.003² + 0.004²) = 0.005, U = 0.010.
        let d = decide(&[m(1, 0.039, 0.004)], 0.05, 0.003, "test");
        assert_eq!(d.verdict, Verdict::Pass);
        assert!((d.poses[0].expanded_deg - 0.010).abs() < 1e-12);
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
