//! The simulated experiment of `perpend study paper`: one seed is one
//! experiment (a calibration run of 100 poses, then 20 test points), with
//! the unknowns of Chen's experiment as explicit conditions.
//!
//! **Calibration.** The true head reads planes of the calibration spread
//! ([`PoseSpread::paper`] for Table 4, a ±10°, ±5 mm cell around the
//! perpendicular for Table 8) with reading noise ζ; the recorded plane is
//! the tracker's fit of 20 points with noise ξ (Chen §5 step 1), rotated
//! by the per-pose TCS error when that cause is on (Chen §6 measures the
//! TCS at every pose). Sensor causes act on the readings through
//! `perpend_core::ext` coefficients with a seeded per-sensor pattern; the
//! datum-plane form error raises the surface under each spot (three plane
//! waves of 200-600 mm wavelength, the head at a random place of a
//! 500 mm plate at every pose) while the tracker records the mean plane.
//! The head is calibrated with the paper's EKF
//! ([`crate::bench::ekf_accepted`], the benches' divergence rule).
//!
//! **Tests.** Planes within ±`test_tilt/2` of the perpendicular, ±5 mm
//! around a test standoff (on the same datum plate, as in Chen §6); the normal by Chen
//! eq. 18-19 through `perpend_core::normal::plane` (the board's code); the
//! error is the angle to the true mean plane plus, per test point, the
//! robot's reorientation error and the TCS error of the tracker's
//! spindle-axis measurement (independent 2-D Gaussians).
//!
//! Limits: the calibration spread, the timing and temperature profile of
//! the run and the plate size are assumptions (the paper states none);
//! the closed attitude loop of Chen §4.2 is not simulated, only its
//! residual (the robot term).

use anyhow::{anyhow, Result};
use nalgebra::Vector3;
use perpend_core::calib::EkfConfig;
use perpend_core::ext::{Context, Extension};
use perpend_core::geometry::{tangent_basis, Plane};
use perpend_core::head::Sensor;
use perpend_core::normal::Method;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::bench::ekf_accepted;
use crate::diagnose::scenario::{AdcCrosstalk, Ripple};
use perpend_calib::candidates::Effect;
use perpend_calib::cv::measure_normal;
use perpend_calib::sim::{
    experiment_head, gauss, paper_head, plane_from_tilts, readings, simulate, Effect as SimEffect,
    ExtensionEffect, Moment, PoseSpread, PoseTruth, SimConfig, SimHead, TempProfile, Tracker,
};
use perpend_calib::stats;

/// A candidate cause of the gap between simulation and experiment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// A catalogue effect of the diagnosis (sensor or front end).
    Sensor(Effect),
    /// Periodic linearity error (outside the catalogue).
    Ripple,
    /// Error of the tracker's TCS measurement at each pose [deg, 1σ per
    /// axis]: rotates the recorded plane in calibration, tilts the measured
    /// spindle axis in the tests.
    Tcs,
    /// Form error of the datum plate [mm RMS height].
    Form,
    /// The robot's reorientation error in the verification [deg, 1σ per
    /// axis].
    Robot,
}

impl Serialize for Cause {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(name(*self))
    }
}

/// Name of a cause.
pub fn name(c: Cause) -> &'static str {
    match c {
        Cause::Sensor(e) => e.name(),
        Cause::Ripple => "ripple",
        Cause::Tcs => "TCS error per pose",
        Cause::Form => "datum form error",
        Cause::Robot => "robot reorientation error",
    }
}

/// Max, mean and sample std of one experiment's test errors [deg].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct Stat3 {
    /// Largest error.
    pub max: f64,
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation.
    pub std: f64,
}

impl Stat3 {
    /// The statistics of `v`.
    pub fn of(v: &[f64]) -> Self {
        Self {
            max: v.iter().copied().fold(0.0, f64::max),
            mean: stats::mean(v),
            std: stats::sd(v),
        }
    }

    /// As an array (max, mean, std).
    pub fn arr(&self) -> [f64; 3] {
        [self.max, self.mean, self.std]
    }
}

/// The conditions of one simulated experiment.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Conditions {
    /// Reading noise ζ (1σ) [mm].
    pub zeta_mm: f64,
    /// Tracker point noise ξ (1σ per coordinate) [mm].
    pub xi_mm: f64,
    /// Full range of the test attitudes about both axes [deg] (Table 8
    /// setup only; Table 4 uses the paper spread).
    pub test_tilt_deg: f64,
    /// Offset of the test standoff centre from the calibration runs' [mm]
    /// (Table 8 setup only).
    pub test_standoff_mm: f64,
    /// Causes switched on, each at its magnitude.
    pub causes: Vec<(Cause, f64)>,
}

impl Conditions {
    /// The magnitude of `which` (0 when off).
    pub fn magnitude(&self, which: Cause) -> f64 {
        self.causes
            .iter()
            .filter(|(c, _)| *c == which)
            .map(|(_, m)| *m)
            .sum()
    }

    /// These conditions with `cause` at `m` added.
    pub fn with(&self, cause: Cause, m: f64) -> Self {
        let mut c = self.clone();
        c.causes.push((cause, m));
        c
    }
}

/// Which procedure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Chen §5 (Table 4).
    Paper,
    /// Chen §6 (Table 8).
    Experiment,
}

/// One simulated procedure (Chen §5 steps 1-10 or its experimental
/// counterpart).
#[derive(Debug, Clone)]
pub struct Setup {
    /// Which.
    pub kind: Kind,
    /// The head.
    pub head: SimHead,
    /// The calibration run (ζ and ξ are replaced by the conditions').
    pub cal: SimConfig,
    /// Test points per experiment.
    pub test_planes: usize,
    /// The paper's filter settings.
    pub ekf: EkfConfig<f64>,
    /// Per-sensor pattern of the injected sensor effects.
    pub pattern: Vec<f64>,
    /// Second pattern (cubic sign, ripple periods/phases).
    pub pattern2: Vec<f64>,
}

/// Seeded per-sensor pattern: sign times a factor in [0.5, 1.5].
fn pattern(n: usize, seed: u64) -> Vec<f64> {
    let mut r = StdRng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let s = if r.gen_bool(0.5) { 1.0 } else { -1.0 };
            s * r.gen_range(0.5..=1.5)
        })
        .collect()
}

impl Setup {
    /// Chen §5: Table 2 head, Table 1 plane spread, 100 poses, 20 test
    /// planes, the §5 filter (Q = 10⁻¹⁰·I, R = 8·10⁻⁵).
    ///
    /// # Errors
    /// None in practice.
    pub fn paper() -> Result<Self> {
        let head = paper_head()?;
        let n = head.truth.len();
        Ok(Self {
            kind: Kind::Paper,
            head,
            cal: SimConfig::paper(),
            test_planes: 20,
            ekf: EkfConfig::chen_simulation(),
            pattern: pattern(n, 0x51D7),
            pattern2: pattern(n, 0x51D8),
        })
    }

    /// Chen §6 as simulated here: Table 6 head (its estimates taken as the
    /// truth), the §6 filter (Q = 10⁻¹²·I, R = 9·10⁻⁶), 100 poses of a
    /// ±10°/±5 mm cell, one every 30 s, the head warming 2 °C over the run
    /// with a ±0.5 °C swing of 20 min (assumptions).
    ///
    /// # Errors
    /// None in practice.
    pub fn experiment() -> Result<Self> {
        let head = experiment_head()?;
        let n = head.truth.len();
        let cal = SimConfig {
            poses: 100,
            spread: PoseSpread::cell(head.standoff_mm),
            tracker: Some(Tracker {
                xi_mm: 0.015,
                points: 20,
                patch_mm: 150.0,
            }),
            zeta_mm: 0.003,
            range_mm: None,
            dropout: 0.0,
            dt_s: Some(30.0),
            temp: Some(TempProfile {
                start_c: 22.0,
                rate_c_per_s: 2.0 / 3000.0,
                swing_c: 0.5,
                period_s: 1200.0,
            }),
        };
        Ok(Self {
            kind: Kind::Experiment,
            head,
            cal,
            test_planes: 20,
            ekf: EkfConfig::chen_experiment(),
            pattern: pattern(n, 0x51D7),
            pattern2: pattern(n, 0x51D8),
        })
    }

    /// Where the test planes come from under `c`.
    pub fn test_spread(&self, c: &Conditions) -> PoseSpread {
        match self.kind {
            Kind::Paper => PoseSpread::paper(),
            Kind::Experiment => PoseSpread {
                tilt_x_range_deg: c.test_tilt_deg,
                tilt_y_range_deg: c.test_tilt_deg,
                standoff_mm: self.cal.spread.standoff_mm + c.test_standoff_mm,
                ..self.cal.spread
            },
        }
    }

    /// The reading extensions that inject the sensor causes of `c`.
    fn extension(&self, c: &Conditions) -> Vec<Extension<f64>> {
        let sp = self.cal.spread;
        let centre = plane_from_tilts(
            sp.center_tilt_x_deg.to_radians(),
            sp.center_tilt_y_deg.to_radians(),
            sp.standoff_mm,
        );
        let temp_ref = self.cal.temp.map_or(20.0, |t| t.start_c);
        self.head
            .truth
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let mut e = Extension::identity();
                e.d_ref = perpend_core::model::distance(s, &centre, i).unwrap_or(40.0);
                e.temp_ref = temp_ref;
                for &(cause, m) in &c.causes {
                    self.set_coefficient(&mut e, i, cause, m);
                }
                e
            })
            .collect()
    }

    fn set_coefficient(&self, e: &mut Extension<f64>, i: usize, cause: Cause, m: f64) {
        let c = m * self.pattern[i];
        match cause {
            Cause::Sensor(Effect::Gain) => e.gain = c,
            Cause::Sensor(Effect::Nonlinearity) => {
                // Half quadratic, half cubic, each reaching m/2 at ±25 mm
                // (half the assumed 50 mm measuring range).
                e.nonlinearity = [0.5 * c / 625.0, 0.5 * m * self.pattern2[i] / 15625.0];
            }
            Cause::Sensor(Effect::Incidence) => e.incidence = c,
            Cause::Sensor(Effect::Crosstalk) => e.crosstalk = c.abs(),
            Cause::Sensor(Effect::Thermal) => e.thermal = c,
            Cause::Sensor(Effect::Drift) => e.drift = c,
            _ => {}
        }
    }

    fn ripple(&self, m: f64) -> Ripple {
        Ripple {
            amp: self.pattern.iter().map(|p| m * p.abs()).collect(),
            period: self
                .pattern2
                .iter()
                .map(|p| 1.5 + 1.5 * (p.abs() - 0.5))
                .collect(),
            phase: self.pattern2.iter().map(|p| p * 2.0).collect(),
        }
    }
}

/// Form error of the datum plate: three plane waves (wavelength 200-600
/// mm, random directions and phases, drawn per experiment) with RMS
/// height `rms_mm`; the head sits at a random place of a 500 mm plate at
/// every pose (drawn from the pose index and the experiment's seed).
struct Form {
    waves: [(f64, f64, f64); 3],
    amp: f64,
    seed: u64,
}

/// Side of the datum plate the poses and tests are spread over [mm]
/// (assumption: the paper gives no size).
pub const PLATE_MM: f64 = 500.0;

impl Form {
    fn new(rms_mm: f64, seed: u64) -> Self {
        let mut r = StdRng::seed_from_u64(seed ^ 0xF0_F0F0);
        let waves = core::array::from_fn(|_| {
            let lambda = r.gen_range(200.0..=600.0);
            let dir: f64 = r.gen_range(0.0..std::f64::consts::TAU);
            let k = std::f64::consts::TAU / lambda;
            let ph: f64 = r.gen_range(0.0..std::f64::consts::TAU);
            (k * dir.cos(), k * dir.sin(), ph)
        });
        // Three unit-amplitude waves have RMS sqrt(3/2).
        Self {
            waves,
            amp: rms_mm / 1.5f64.sqrt(),
            seed,
        }
    }

    fn height(&self, u: f64, v: f64) -> f64 {
        self.waves
            .iter()
            .map(|(kx, ky, ph)| (kx * u + ky * v + ph).cos())
            .sum::<f64>()
            * self.amp
    }
}

impl SimEffect for Form {
    fn name(&self) -> String {
        "datum form".into()
    }

    fn apply(&self, t: &PoseTruth<'_>, r: &mut [Option<f64>], _rng: &mut StdRng) {
        let mut at = StdRng::seed_from_u64(self.seed ^ (t.pose as u64).wrapping_mul(0x9E37_79B9));
        let (u0, v0) = (
            PLATE_MM * at.gen_range(-0.5..=0.5),
            PLATE_MM * at.gen_range(-0.5..=0.5),
        );
        let (e1, e2) = tangent_basis(&t.plane.n);
        for (i, x) in r.iter_mut().enumerate() {
            let (Some(v), Some(d), Some(s)) = (*x, t.distances[i], t.head.get(i)) else {
                continue;
            };
            let spot = s.zero + s.dir * d;
            let h = self.height(u0 + spot.dot(&e1), v0 + spot.dot(&e2));
            // A surface raised towards the head by h shortens the beam.
            let cos = t.plane.n.dot(&s.dir).abs().max(0.1);
            *x = Some(v - h / cos);
        }
    }
}

/// The simulator effects of `c` for one experiment. The reading noise is
/// drawn inside an [`AdcCrosstalk`] effect in the experiment (crosstalk
/// needs the noise before the carry-over, as an ADC makes it).
struct Injected {
    ext: ExtensionEffect,
    ripple: Option<Ripple>,
    form: Option<Form>,
    adc: Option<AdcCrosstalk>,
    cal: SimConfig,
}

impl Injected {
    fn new(setup: &Setup, c: &Conditions, seed: u64) -> Self {
        let mut ext = setup.extension(c);
        let mut cal = setup.cal;
        cal.zeta_mm = c.zeta_mm;
        if let Some(t) = cal.tracker.as_mut() {
            t.xi_mm = c.xi_mm;
        }
        let adc = (setup.kind == Kind::Experiment).then(|| AdcCrosstalk {
            c: ext.iter().map(|e| e.crosstalk).collect(),
            sigma: c.zeta_mm,
        });
        if adc.is_some() {
            cal.zeta_mm = 0.0;
            ext.iter_mut().for_each(|e| e.crosstalk = 0.0);
        }
        let ripple = c.magnitude(Cause::Ripple);
        let form = c.magnitude(Cause::Form);
        Self {
            ext: ExtensionEffect { ext },
            ripple: (ripple > 0.0).then(|| setup.ripple(ripple)),
            form: (form > 0.0).then(|| Form::new(form, seed)),
            adc,
            cal,
        }
    }

    fn effects(&self) -> Vec<&dyn SimEffect> {
        let mut v: Vec<&dyn SimEffect> = vec![&self.ext];
        if let Some(r) = &self.ripple {
            v.push(r);
        }
        if let Some(f) = &self.form {
            v.push(f);
        }
        // The noise (and any carry-over) last: what the sensors output is
        // what the ADC samples.
        if let Some(a) = &self.adc {
            v.push(a);
        }
        v
    }
}

/// Error vector [deg] of a measured normal against the true plane, in the
/// plane's tangent basis.
fn error_vec(n_meas: &Vector3<f64>, truth: &Plane<f64>) -> [f64; 2] {
    let mut n = *n_meas;
    let t = if truth.n.z < 0.0 { truth.n } else { -truth.n };
    if n.dot(&t) < 0.0 {
        n = -n;
    }
    let (e1, e2) = tangent_basis(&t);
    let v = n - t * n.dot(&t);
    [
        v.dot(&e1).asin().to_degrees(),
        v.dot(&e2).asin().to_degrees(),
    ]
}

/// Rotates each recorded plane of `data` about the TCS origin by a
/// Gaussian angle (1σ `sd_deg` about x and y): the per-pose TCS error.
fn tcs_error(poses: &mut perpend_formats::exchange::PoseTable, sd_deg: f64, seed: u64) {
    if sd_deg <= 0.0 {
        return;
    }
    let mut r = StdRng::seed_from_u64(seed ^ 0x7C5_0000);
    for row in poses.rows.iter_mut() {
        let w = Vector3::new(gauss(&mut r), gauss(&mut r), 0.0) * sd_deg.to_radians();
        let n = (row.plane.n + w.cross(&row.plane.n)).normalize();
        row.plane = Plane { n, d: row.plane.d };
        row.abcd = [n.x, n.y, n.z, row.plane.d];
    }
}

/// One experiment's rows: the nominal head, the paper's EKF (`None` when
/// it diverged on some sensor) and the true head, each over the same test
/// readings with its own draws of the verification errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// Nominal head.
    pub before: Stat3,
    /// The paper's EKF.
    pub ekf: Option<Stat3>,
    /// True head (the floor).
    pub floor: Stat3,
}

/// Runs one experiment under `c` with `seed`.
///
/// # Errors
/// Simulation failures or a test plane out of the sensors' reach.
pub fn experiment(setup: &Setup, c: &Conditions, seed: u64) -> Result<Outcome> {
    let inj = Injected::new(setup, c, seed);
    let effects = inj.effects();
    let mut rng = StdRng::seed_from_u64(seed);
    let head = &setup.head;
    let mut data = simulate(head, &inj.cal, &effects, &mut rng)?;
    let tcs = c.magnitude(Cause::Tcs);
    tcs_error(&mut data.poses, tcs, seed);
    let ekf: Option<Vec<Sensor<f64>>> = head
        .nominal
        .iter()
        .enumerate()
        .map(|(i, s)| ekf_accepted(s, i, &data.poses, setup.ekf).map(|f| f.sensor))
        .collect();
    let heads: [Option<&[Sensor<f64>]>; 3] =
        [Some(&head.nominal), ekf.as_deref(), Some(&head.truth)];
    let sd = (c.magnitude(Cause::Robot).powi(2) + tcs.powi(2)).sqrt();
    let mut verify = StdRng::seed_from_u64(seed ^ 0xA77_17DE);
    let spread = setup.test_spread(c);
    let mut errs: [Vec<f64>; 3] = Default::default();
    for t in 0..setup.test_planes {
        let p = spread.draw(&mut rng);
        let k = setup.cal.poses + t;
        let t_s = setup.cal.dt_s.map(|dt| dt * k as f64);
        let when = Moment {
            pose: k,
            t_s,
            temp_c: setup.cal.temp.map(|tp| tp.at(t_s.unwrap_or(k as f64))),
        };
        let r = readings(head, &inj.cal, &effects, &p, when, &mut rng);
        for (h, e) in heads.iter().zip(errs.iter_mut()) {
            let extra = [sd * gauss(&mut verify), sd * gauss(&mut verify)];
            let Some(h) = h else { continue };
            let n = measure_normal(h, &r, &Context::default(), Method::Chen)
                .map_err(|x| anyhow!("seed {seed}, test point {}: {x}", t + 1))?;
            let v = error_vec(&n, &p);
            e.push((v[0] + extra[0]).hypot(v[1] + extra[1]));
        }
    }
    Ok(Outcome {
        before: Stat3::of(&errs[0]),
        ekf: ekf.is_some().then(|| Stat3::of(&errs[1])),
        floor: Stat3::of(&errs[2]),
    })
}

/// The experiments of `seeds` under `c`.
///
/// # Errors
/// Those of [`experiment`].
pub fn experiments(setup: &Setup, c: &Conditions, seeds: &[u64]) -> Result<Vec<Outcome>> {
    seeds.iter().map(|&s| experiment(setup, c, s)).collect()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn paper_setup_orders_before_calibrated_and_floor() {
        let s = Setup::paper().unwrap();
        let c = Conditions {
            zeta_mm: 0.01,
            xi_mm: 0.02,
            test_tilt_deg: 0.0,
            test_standoff_mm: 0.0,
            causes: Vec::new(),
        };
        let o = experiments(&s, &c, &[1, 2, 3]).unwrap();
        for x in &o {
            let e = x.ekf.unwrap();
            assert!(x.before.mean > 10.0 * e.mean, "{x:?}");
            assert!(x.floor.mean < e.mean, "{x:?}");
            // Table 4's before row is reproduced by the paper spread.
            approx::assert_relative_eq!(x.before.mean, 1.3387, max_relative = 0.1);
        }
    }

    #[test]
    fn verification_error_adds_to_every_row_and_form_error_to_the_floor() {
        let s = Setup::experiment().unwrap();
        let c = Conditions {
            zeta_mm: 0.0,
            xi_mm: 0.0,
            test_tilt_deg: 2.0,
            test_standoff_mm: 0.0,
            causes: Vec::new(),
        };
        let clean = experiment(&s, &c, 7).unwrap();
        assert!(clean.floor.mean < 1e-6, "{clean:?}");
        let robot = experiment(&s, &c.with(Cause::Robot, 0.1), 7).unwrap();
        // A 0.1° 1σ per-axis tilt: Rayleigh mean 0.125°, 20 draws.
        assert!((0.07..0.2).contains(&robot.floor.mean), "{robot:?}");
        let form = experiment(&s, &c.with(Cause::Form, 0.01), 7).unwrap();
        assert!(form.floor.mean > 1e-3, "{form:?}");
    }
}
