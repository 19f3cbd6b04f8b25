//! Simulated runs with a hidden effect, for the self-consistency tests
//! and `perpend bench diagnose-self` (effects injected through perpend's
//! own terms; the independent generator is `host-tests/blind/gen.py`).
//!
//! A [`Scenario`] fixes everything about a run: the seed, the hidden
//! effect (none, one of the catalogue, or the out-of-catalogue
//! [`Ripple`]), its magnitude, the pose count and the reading noise. The
//! run itself comes from the simulator ([`perpend_calib::sim::simulate`]): a random
//! head (the paper's error sizes), poses spread like a robot cell's
//! calibration (±10° about both axes, ±5 mm standoff), the paper's tracker
//! and reading noise σ, time stamps every 6 s and a head temperature that
//! warms up and swings. The catalogue effects are injected with
//! [`ExtensionEffect`] (the same [`Extension`] the board corrects) —
//! except crosstalk, injected by [`AdcCrosstalk`] so that the carry-over
//! includes the previous channel's noise as in a real ADC — with a
//! different coefficient on every sensor: `k · s_i`, where `s_i` is a
//! random sign times a factor in [0.5, 1.5].
//!
//! **Magnitude.** Much of an effect can be absorbed by the zero point and
//! beam direction (incidence almost entirely: `1/cos γ` differs from the
//! z zero point's regressor only at second order in the tilt). So the
//! magnitude is defined by what the paper's model *cannot* absorb: `k` is
//! chosen so that the RMS of the base model's residuals on a noise-free
//! run of the same head and spread with the effect equals `magnitude · σ`.
//! Magnitude 1 is an unexplainable part as large as the reading noise.
//!
//! The effects do not draw from the random generator while they act, so
//! the same scenario without its effect ([`Generated::clean`]) has exactly
//! the same planes and noise: its base held-out RMS is the noise floor the
//! bench measures the effect size against.

use std::f64::consts::PI;
use std::path::Path;

use anyhow::{anyhow, Result};
use perpend_core::calib::{LsqConfig, Poses};
use perpend_core::ext::Extension;
use perpend_core::model::distance;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use perpend_calib::candidates::{fit, predict, Effect as DiagEffect, Refs};
use perpend_calib::sim::{
    plane_from_tilts, random_head, simulate, Dataset, Effect as SimEffect, ExtensionEffect,
    PoseSpread, PoseTruth, SimConfig, SimHead, TempProfile, Tracker,
};
use perpend_formats::exchange::write_dataset;

/// The effect hidden in a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Hidden {
    /// No effect: the paper's model is the truth.
    None,
    /// Per-sensor gain error.
    Gain,
    /// Per-sensor quadratic + cubic linearity error.
    Nonlinearity,
    /// Incidence bias.
    Incidence,
    /// Sample-and-hold carry-over.
    Crosstalk,
    /// Drift with temperature.
    Thermal,
    /// Drift with time.
    Drift,
    /// Out of the catalogue: a periodic linearity error (ripple) of each
    /// sensor, `A_i sin(2π d / P_i + φ_i)` with periods of 1.5-3 mm.
    Ripple,
}

impl Hidden {
    /// Every kind, clean data first.
    pub const ALL: [Hidden; 8] = [
        Hidden::None,
        Hidden::Gain,
        Hidden::Nonlinearity,
        Hidden::Incidence,
        Hidden::Crosstalk,
        Hidden::Thermal,
        Hidden::Drift,
        Hidden::Ripple,
    ];

    /// Name (the catalogue's, `ripple` for the out-of-catalogue effect).
    pub const fn name(self) -> &'static str {
        match self {
            Hidden::None => "none",
            Hidden::Gain => "gain",
            Hidden::Nonlinearity => "nonlinearity",
            Hidden::Incidence => "incidence",
            Hidden::Crosstalk => "crosstalk",
            Hidden::Thermal => "thermal",
            Hidden::Drift => "drift",
            Hidden::Ripple => "ripple",
        }
    }

    /// The name a correct diagnosis gives.
    pub const fn correct_verdict(self) -> &'static str {
        match self {
            Hidden::Ripple => "unexplained",
            h => h.name(),
        }
    }

    /// Whether the effect is in the diagnosis' catalogue.
    pub const fn in_catalog(self) -> bool {
        !matches!(self, Hidden::None | Hidden::Ripple)
    }

    /// The coefficient scale the effect's pattern is built with before it
    /// is normalised to its visible size (a small value, so that the
    /// normalisation works in the linear regime of the effect).
    fn base_coeff(self) -> f64 {
        match self {
            Hidden::None => 0.0,
            Hidden::Gain => 1e-3,
            Hidden::Nonlinearity => 1e-3,
            Hidden::Incidence => 1e-2,
            Hidden::Crosstalk => 1e-3,
            Hidden::Thermal => 1e-3,
            Hidden::Drift => 1e-5,
            Hidden::Ripple => 1e-3,
        }
    }
}

/// Everything that defines a simulated run with a hidden effect.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scenario {
    /// Seed of the head, the poses, the noise and the effect's pattern.
    pub seed: u64,
    /// The hidden effect.
    pub hidden: Hidden,
    /// Magnitude: the RMS of the part of the effect the paper's model
    /// cannot absorb, in units of σ (module docs).
    pub magnitude: f64,
    /// Poses of the run.
    pub poses: usize,
    /// Reading noise σ [mm] (written as `sigma_mm`).
    pub sigma_mm: f64,
    /// Write the `t_s` column.
    pub with_time: bool,
    /// Write the `temp_c` column.
    pub with_temp: bool,
}

impl Scenario {
    /// A scenario picked by `seed`: the effect is `kinds[seed mod len]`,
    /// the magnitude log-uniform in 1.5-4 σ (0 for none: large enough that
    /// the base model's held-out RMS rises by roughly 50% or more), the
    /// reading noise log-uniform in 0.004-0.02 mm, and the head, poses,
    /// noise and effect pattern from the seed.
    pub fn draw(seed: u64, kinds: &[Hidden], poses: usize) -> Self {
        let mut rng = StdRng::seed_from_u64(seed ^ 0x5CE7_A810);
        let hidden = kinds
            .get((seed % kinds.len().max(1) as u64) as usize)
            .copied()
            .unwrap_or(Hidden::None);
        let m = 1.5 * (4.0f64 / 1.5).powf(rng.gen_range(0.0..=1.0));
        let magnitude = if hidden == Hidden::None { 0.0 } else { m };
        let sigma_mm = 0.004 * 5f64.powf(rng.gen_range(0.0..=1.0));
        Self {
            seed,
            hidden,
            magnitude,
            poses,
            sigma_mm,
            with_time: true,
            with_temp: true,
        }
    }
}

/// The out-of-catalogue effect: a periodic linearity error per sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct Ripple {
    /// Amplitude of each sensor [mm].
    pub amp: Vec<f64>,
    /// Period of each sensor [mm of reading].
    pub period: Vec<f64>,
    /// Phase of each sensor [rad].
    pub phase: Vec<f64>,
}

impl SimEffect for Ripple {
    fn name(&self) -> String {
        "ripple".into()
    }

    fn apply(&self, _truth: &PoseTruth<'_>, readings: &mut [Option<f64>], _rng: &mut StdRng) {
        for (i, r) in readings.iter_mut().enumerate() {
            if let (Some(d), Some(a), Some(p), Some(f)) =
                (*r, self.amp.get(i), self.period.get(i), self.phase.get(i))
            {
                *r = Some(d + a * (2.0 * PI * d / p + f).sin());
            }
        }
    }
}

/// Crosstalk as an ADC front end produces it: the sensors' noise is in
/// the analog signal, so the carry-over of the previously converted
/// channel includes that channel's noise. Each scan: `v_i = d_i + σ·N(0,1)`,
/// then `r_i = v_i + c_i·(r_{i−1} − r_i)` (the first channel takes the
/// last one's conversion; solved by fixed-point iteration). This is the
/// reading model of [`Extension::excess`]'s crosstalk term with the noise
/// where the physics puts it; the simulator's reading noise must then be 0.
#[derive(Debug, Clone, PartialEq)]
pub struct AdcCrosstalk {
    /// Carry-over fraction of each channel.
    pub c: Vec<f64>,
    /// Analog noise 1σ [mm].
    pub sigma: f64,
}

impl SimEffect for AdcCrosstalk {
    fn name(&self) -> String {
        "adc-crosstalk".into()
    }

    fn apply(&self, _truth: &PoseTruth<'_>, readings: &mut [Option<f64>], rng: &mut StdRng) {
        let n = readings.len();
        let v: Vec<Option<f64>> = readings
            .iter()
            .map(|r| {
                let e = self.sigma * perpend_calib::sim::gauss(rng);
                r.map(|d| d + e)
            })
            .collect();
        let mut r = v.clone();
        for _ in 0..40 {
            for i in 0..n {
                let c = self.c.get(i).copied().unwrap_or(0.0);
                if let (Some(vi), Some(p)) = (v[i], r[(i + n - 1) % n]) {
                    r[i] = Some((vi + c * p) / (1.0 + c));
                }
            }
        }
        readings.copy_from_slice(&r);
    }
}

/// A generated run and its clean twin.
#[derive(Debug, Clone)]
pub struct Generated {
    /// The run with the hidden effect.
    pub data: Dataset,
    /// The same run without it (same planes, same noise).
    pub clean: Dataset,
    /// The head.
    pub head: SimHead,
    /// The injected per-sensor extension (identity for none / ripple).
    pub ext: Vec<Extension<f64>>,
}

/// The temperature profile of the scenarios: 22 °C warming by 2 °C over
/// ~10 minutes with a ±1.5 °C swing of period 4 minutes (the swing keeps
/// temperature and time apart, as on a real cell).
pub fn temp_profile() -> TempProfile {
    TempProfile {
        start_c: 22.0,
        rate_c_per_s: 2.0 / 600.0,
        swing_c: 1.5,
        period_s: 240.0,
    }
}

/// The effect's per-sensor pattern and shape parameters, drawn once per
/// scenario from their own generator.
#[derive(Debug, Clone, PartialEq)]
struct Pattern {
    sign_factor: Vec<f64>,
    second: Vec<f64>,
    mix: Vec<f64>,
    period: Vec<f64>,
    phase: Vec<f64>,
}

impl Pattern {
    fn draw(n: usize, seed: u64) -> Self {
        let mut r = StdRng::seed_from_u64(seed.wrapping_mul(0x2545_F491_4F6C_DD1D) ^ 0x00EF_FEC7);
        let mut sf = || {
            let s = if r.gen_bool(0.5) { 1.0 } else { -1.0 };
            s * r.gen_range(0.5..=1.5)
        };
        let sign_factor: Vec<f64> = (0..n).map(|_| sf()).collect();
        let second: Vec<f64> = (0..n).map(|_| sf()).collect();
        let mix = (0..n).map(|_| r.gen_range(0.2..=0.8)).collect();
        let period = (0..n).map(|_| r.gen_range(1.5..=3.0)).collect();
        let phase = (0..n).map(|_| r.gen_range(0.0..2.0 * PI)).collect();
        Self {
            sign_factor,
            second,
            mix,
            period,
            phase,
        }
    }
}

/// The injected extension of `hidden` at coefficient scale `k`.
fn extensions(
    hidden: Hidden,
    k: f64,
    p: &Pattern,
    d_mid: &[f64],
    temp_ref: f64,
) -> Vec<Extension<f64>> {
    d_mid
        .iter()
        .enumerate()
        .map(|(i, &d_ref)| {
            let mut e = Extension::identity();
            e.d_ref = d_ref;
            e.temp_ref = temp_ref;
            let c = k * p.sign_factor[i];
            match hidden {
                Hidden::Gain => e.gain = c,
                Hidden::Nonlinearity => {
                    // A sensor-specific mix of a quadratic and a cubic
                    // (per mm of reading offset, comparable sizes over ±8 mm).
                    e.nonlinearity = [
                        c * p.mix[i] / 8.0,
                        k * p.second[i] * (1.0 - p.mix[i]) / 64.0,
                    ];
                }
                Hidden::Incidence => e.incidence = c,
                Hidden::Crosstalk => e.crosstalk = c.abs(),
                Hidden::Thermal => e.thermal = c,
                Hidden::Drift => e.drift = c,
                Hidden::None | Hidden::Ripple => {}
            }
            e
        })
        .collect()
}

fn ripple(k: f64, p: &Pattern) -> Ripple {
    Ripple {
        amp: p.sign_factor.iter().map(|s| k * s.abs()).collect(),
        period: p.period.clone(),
        phase: p.phase.clone(),
    }
}

fn effect_of<'a>(
    hidden: Hidden,
    ext: &'a ExtensionEffect,
    rip: &'a Ripple,
    xt: &'a AdcCrosstalk,
) -> Vec<&'a dyn SimEffect> {
    match hidden {
        Hidden::None => vec![],
        Hidden::Ripple => vec![rip],
        Hidden::Crosstalk => vec![xt],
        _ => vec![ext],
    }
}

fn adc(hidden: Hidden, ext: &[Extension<f64>], sigma: f64) -> AdcCrosstalk {
    AdcCrosstalk {
        c: ext
            .iter()
            .map(|e| {
                if hidden == Hidden::Crosstalk {
                    e.crosstalk
                } else {
                    0.0
                }
            })
            .collect(),
        sigma,
    }
}

/// RMS of the base model's in-sample residuals on a noise-free run (exact
/// planes, no reading noise) of `head` with `effects`: the part of the
/// effects the paper's model cannot absorb.
///
/// # Errors
/// Simulation failures, a base model that cannot be fitted.
pub fn visible_rms(
    head: &SimHead,
    cfg: &SimConfig,
    effects: &[&dyn SimEffect],
    seed: u64,
) -> Result<f64> {
    let quiet = SimConfig {
        zeta_mm: 0.0,
        tracker: None,
        ..*cfg
    };
    let data = simulate(
        head,
        &quiet,
        effects,
        &mut StdRng::seed_from_u64(seed ^ 0x0715_1B1E),
    )?;
    let refs = Refs::of(&data.poses);
    let mut res = Vec::new();
    for (i, s) in head.nominal.iter().enumerate() {
        let f = fit(
            s,
            i,
            &data.poses,
            refs.terms(DiagEffect::None, i),
            &LsqConfig::default(),
        )
        .map_err(|e| anyhow!("visible size, sensor {}: {e}", i + 1))?;
        for k in 0..data.poses.rows.len() {
            if let (Some(d), Some(p)) = (data.poses.reading(k, i), predict(&f, &data.poses, k, i)) {
                res.push(d - p);
            }
        }
    }
    Ok(perpend_calib::stats::rms(&res))
}

/// Simulates the scenario.
///
/// # Errors
/// Simulator failures.
pub fn generate(sc: &Scenario) -> Result<Generated> {
    let mut rng = StdRng::seed_from_u64(sc.seed);
    let mut head = random_head(&mut rng, 1.5, 0.07)?;
    head.sigma_mm = Some(sc.sigma_mm);
    let n = head.truth.len();
    // The effect's pattern comes from its own generator so that the run's
    // draws are the same with and without it.
    let pat = Pattern::draw(n, sc.seed);
    let centre = plane_from_tilts(0.0, 0.0, head.standoff_mm);
    let d_mid: Vec<f64> = head
        .truth
        .iter()
        .enumerate()
        .map(|(i, s)| distance(s, &centre, i).unwrap_or(head.standoff_mm))
        .collect();
    let prof = temp_profile();
    let cfg = SimConfig {
        poses: sc.poses,
        spread: PoseSpread::cell(head.standoff_mm),
        tracker: Some(Tracker::paper()),
        zeta_mm: sc.sigma_mm,
        range_mm: None,
        dropout: 0.0,
        dt_s: Some(6.0),
        temp: Some(prof),
    };
    // Normalise the coefficient scale to the visible size magnitude · σ.
    let k = if sc.hidden == Hidden::None || !(sc.magnitude > 0.0) {
        0.0
    } else {
        let k0 = sc.hidden.base_coeff();
        let e0 = ExtensionEffect {
            ext: extensions(sc.hidden, k0, &pat, &d_mid, prof.start_c),
        };
        let r0 = ripple(k0, &pat);
        let x0 = adc(sc.hidden, &e0.ext, 0.0);
        let v0 = visible_rms(&head, &cfg, &effect_of(sc.hidden, &e0, &r0, &x0), sc.seed)?;
        if v0 > 0.0 {
            k0 * sc.magnitude * sc.sigma_mm / v0
        } else {
            0.0
        }
    };
    let ext = extensions(sc.hidden, k, &pat, &d_mid, prof.start_c);
    let ext_effect = ExtensionEffect { ext: ext.clone() };
    let rip = ripple(k, &pat);
    // Crosstalk carries the noise over too: the noise is drawn inside the
    // effect (module docs of AdcCrosstalk), and the clean twin draws it the
    // same way with no carry-over.
    let (cfg, xt, xt0) = if sc.hidden == Hidden::Crosstalk {
        (
            SimConfig {
                zeta_mm: 0.0,
                ..cfg
            },
            adc(sc.hidden, &ext, sc.sigma_mm),
            adc(Hidden::None, &ext, sc.sigma_mm),
        )
    } else {
        (
            cfg,
            adc(Hidden::None, &ext, 0.0),
            adc(Hidden::None, &ext, 0.0),
        )
    };
    let effects = effect_of(sc.hidden, &ext_effect, &rip, &xt);
    let clean_effects: Vec<&dyn SimEffect> = if sc.hidden == Hidden::Crosstalk {
        vec![&xt0]
    } else {
        vec![]
    };
    let mut data = simulate(&head, &cfg, &effects, &mut rng.clone())?;
    let mut clean = simulate(&head, &cfg, &clean_effects, &mut rng)?;
    for d in [&mut data, &mut clean] {
        for r in d.poses.rows.iter_mut() {
            if !sc.with_time {
                r.t_s = None;
            }
            if !sc.with_temp {
                r.temp_c = None;
            }
        }
    }
    Ok(Generated {
        data,
        clean,
        head,
        ext,
    })
}

/// Writes a run as `sensors.csv` / `poses.csv` into `dir`, with comments
/// that say nothing about the hidden effect.
///
/// # Errors
/// I/O errors.
pub fn write(data: &Dataset, dir: &Path) -> Result<()> {
    write_dataset(
        dir,
        &data.sensors,
        &data.poses,
        &["simulated calibration run (perpend scenario)".to_string()],
    )
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_run_and_a_clean_twin() {
        let sc = Scenario {
            seed: 11,
            hidden: Hidden::Gain,
            magnitude: 2.0,
            poses: 30,
            sigma_mm: 0.01,
            with_time: true,
            with_temp: false,
        };
        let a = generate(&sc).unwrap();
        let b = generate(&sc).unwrap();
        assert_eq!(a.data.poses, b.data.poses);
        // the twin has the same planes and differs only by the effect
        assert_eq!(a.data.true_planes, a.clean.true_planes);
        assert_ne!(
            a.data.poses.rows[0].readings,
            a.clean.poses.rows[0].readings
        );
        assert!(a
            .data
            .poses
            .rows
            .iter()
            .all(|r| r.temp_c.is_none() && r.t_s.is_some()));
        assert!(a.ext.iter().all(|e| e.gain != 0.0));
    }

    #[test]
    fn magnitude_is_the_visible_size_in_sigma() {
        for (h, seed) in [
            (Hidden::Gain, 1),
            (Hidden::Incidence, 2),
            (Hidden::Ripple, 3),
        ] {
            let sc = Scenario {
                seed,
                hidden: h,
                magnitude: 2.0,
                poses: 60,
                sigma_mm: 0.01,
                with_time: true,
                with_temp: true,
            };
            let g = generate(&sc).unwrap();
            let cfg = SimConfig {
                poses: 60,
                spread: PoseSpread::cell(g.head.standoff_mm),
                tracker: None,
                zeta_mm: 0.0,
                range_mm: None,
                dropout: 0.0,
                dt_s: Some(6.0),
                temp: Some(temp_profile()),
            };
            let e = ExtensionEffect { ext: g.ext.clone() };
            let pat = Pattern::draw(4, seed);
            let k = g
                .ext
                .iter()
                .map(|x| x.gain.abs() + x.incidence.abs())
                .sum::<f64>();
            let rip = ripple(if h == Hidden::Ripple { 1.0 } else { 0.0 }, &pat);
            let eff: Vec<&dyn SimEffect> = if h == Hidden::Ripple {
                vec![]
            } else {
                vec![&e]
            };
            if h != Hidden::Ripple {
                assert!(k > 0.0);
                let v = visible_rms(&g.head, &cfg, &eff, seed).unwrap();
                // the same size on the normalisation's own draw: 2σ
                approx::assert_relative_eq!(v, 0.02, max_relative = 0.05);
            } else {
                assert!(rip.amp.iter().all(|a| *a > 0.0));
            }
        }
    }
}
