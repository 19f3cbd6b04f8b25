//! Simulator of calibration and verification runs (Chen §5 steps 1-10),
//! writing the exchange format, and `perpend simulate`.
//!
//! A run is a sequence of poses of a sensor head against a plane:
//!
//! 1. **Heads** ([`SimHead`]): nominal and true parameters of each sensor —
//!    the paper's simulated head (Chen Table 2), its experimental head
//!    (Table 6, the estimated errors taken as the truth) and random heads
//!    around a nominal cone head with errors of the paper's size.
//! 2. **Poses** ([`PoseSpread`]): the true plane of each pose, tilted about
//!    the TCS x and y axes by angles drawn uniformly in a range around a
//!    centre tilt, at a standoff (where it crosses the spindle axis) drawn
//!    uniformly in a range. Tilt angles are Tian's θ1 (about x) and θ2
//!    (about y) of [`perpend_core::angles::Deviation`].
//! 3. **Tracker** ([`Tracker`]): the plane equation a laser tracker would
//!    report: `points` points uniform on a square patch of side `patch_mm`
//!    centred where the spindle axis meets the plane, each coordinate
//!    perturbed by N(0, ξ), fitted by total least squares (Chen §5 step 1).
//!    Drawn anew for every pose.
//! 4. **Readings**: the true head's distances (Chen eq. 1-3), then any
//!    [`Effect`]s (systematic errors of the sensors: issue 5 injects gain,
//!    non-linearity, incidence, crosstalk, thermal, drift, or effects outside
//!    that catalogue through this trait), then reading noise N(0, ζ)
//!    (step 4), the sensors' measuring range and random dropouts.
//!    Optional time stamps and a head-temperature profile fill `t_s` /
//!    `temp_c`.
//! 5. **Curved datum surfaces** (issue 14): readings of a sphere or
//!    cylinder ([`perpend_core::surface::CurvedSurface`], beam-surface
//!    intersection) with the same noise, range and dropouts
//!    ([`curved_readings`]); a Tian-style head ([`tian_style_head`]).
//!
//! Everything is drawn from one seeded [`StdRng`], so a seed reproduces a
//! run exactly.
//!
//! The paper's simulated head looks along −z (its Table 2 has q = −0.866)
//! while our TCS has +z along the feed: it is presented rotated 180° about
//! x, `(x, y, z) → (x, −y, −z)`, applied to zero points, directions, their
//! errors and to the Table 1 plane. Angles between normals are invariant.

use std::path::PathBuf;

use anyhow::{bail, Context as _, Result};
use nalgebra::{Matrix3, SVector, Vector3};
use perpend_core::ext::{Context, Extension, Incidence};
use perpend_core::geometry::{tangent_basis, Plane};
use perpend_core::head::Sensor;
use perpend_core::model::distance;
use perpend_core::surface::CurvedSurface;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// One planned pose: how the robot presents the datum plane
/// (`perpend plan`, `crate::plan`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PlannedPose {
    /// Tilt about TCS x (θ1) [deg].
    pub tilt_x_deg: f64,
    /// Tilt about TCS y (θ2) [deg].
    pub tilt_y_deg: f64,
    /// Where the plane crosses the spindle axis [mm].
    pub standoff_mm: f64,
}

impl PlannedPose {
    /// The plane in the TCS.
    pub fn plane(&self) -> Plane<f64> {
        plane_from_tilts(
            self.tilt_x_deg.to_radians(),
            self.tilt_y_deg.to_radians(),
            self.standoff_mm,
        )
    }
}
use rand_distr::StandardNormal;

use perpend_formats::exchange::{PoseRow, PoseTable, SensorTable};

/// A sensor head to simulate: what the drawings say and what was built.
#[derive(Debug, Clone, PartialEq)]
pub struct SimHead {
    /// Short name (`paper`, `experiment`, `random`, …).
    pub name: String,
    /// Nominal sensors (written to `sensors.csv`).
    pub nominal: Vec<Sensor<f64>>,
    /// True sensors (generate the readings).
    pub truth: Vec<Sensor<f64>>,
    /// Datasheet repeatability written to `sensors.csv`, if any.
    pub sigma_mm: Option<f64>,
    /// A standoff [mm, z where the plane crosses the spindle axis] at which
    /// the readings are mid-range.
    pub standoff_mm: f64,
}

/// `(x, y, z) → (x, −y, −z)`: the paper's −z-looking TCS to ours.
fn rot_x180(v: [f64; 3]) -> Vector3<f64> {
    Vector3::new(v[0], -v[1], -v[2])
}

fn sensor(zero: Vector3<f64>, dir: Vector3<f64>) -> Result<Sensor<f64>> {
    Sensor::new(zero, dir).map_err(|e| anyhow::anyhow!("head definition: {e}"))
}

/// Builds a head from nominal `[x, y, z, m, n, q]` rows and their errors.
fn head_from_table(
    name: &str,
    nominal: &[[f64; 6]],
    errors: &[[f64; 6]],
    map: fn([f64; 3]) -> Vector3<f64>,
    standoff_mm: f64,
) -> Result<SimHead> {
    let mut nom = Vec::new();
    let mut tru = Vec::new();
    for (n, e) in nominal.iter().zip(errors) {
        let z = map([n[0], n[1], n[2]]);
        let u = map([n[3], n[4], n[5]]);
        let dz = map([e[0], e[1], e[2]]);
        let du = map([e[3], e[4], e[5]]);
        nom.push(sensor(z, u)?);
        tru.push(sensor(z + dz, u + du)?);
    }
    Ok(SimHead {
        name: name.into(),
        nominal: nom,
        truth: tru,
        sigma_mm: None,
        standoff_mm,
    })
}

/// An effect-free run of the paper head for the time-like checks: 60 poses
/// 30 s apart, the temperature column held at 21 °C (a caller writes its
/// own warm-up or drift into the readings).
///
/// # Errors
/// Those of [`paper_head`] and [`simulate`].
pub fn timed_paper_run(seed: u64) -> Result<(SimHead, PoseTable)> {
    let head = paper_head()?;
    let mut cfg = SimConfig::paper();
    cfg.poses = 60;
    cfg.dt_s = Some(30.0);
    cfg.temp = Some(TempProfile {
        start_c: 21.0,
        rate_c_per_s: 0.0,
        swing_c: 0.0,
        period_s: 300.0,
    });
    let run = simulate(&head, &cfg, &[], &mut StdRng::seed_from_u64(seed))?.poses;
    Ok((head, run))
}

/// Chen Table 2: the simulated head (nominal + parameter errors), rotated
/// into our +z-feed TCS. Standoff: [`PAPER_STANDOFF_MM`] (the Table 1 plane
/// crosses the axis at z = 34.1218 / 0.9515 = 35.861 mm).
///
/// # Errors
/// None in practice (the table is valid); kept fallible like all heads.
pub fn paper_head() -> Result<SimHead> {
    let nominal = [
        [50.0, 0.0, 0.0, -0.5, 0.0, -0.8660],
        [0.0, 50.0, 0.0, 0.0, -0.5, -0.8660],
        [-50.0, 0.0, 0.0, 0.5, 0.0, -0.8660],
        [0.0, -50.0, 0.0, 0.0, 0.5, -0.8660],
    ];
    let errors = [
        [1.3, 0.9, 1.1, 0.0445, 0.0506, -0.0228],
        [1.3, -1.4, 1.6, -0.0634, 0.0479, -0.0237],
        [1.3, -1.2, 1.2, -0.0507, -0.0365, -0.0266],
        [1.5, 1.1, 1.4, 0.0339, -0.0682, -0.0353],
    ];
    let mut h = head_from_table("paper", &nominal, &errors, rot_x180, PAPER_STANDOFF_MM)?;
    h.sigma_mm = Some(0.01);
    Ok(h)
}

/// Chen Table 6: the experimental head, its estimated errors taken as the
/// truth. It already looks along +z. Standoff 0: the readings are ~40 mm
/// when the plane passes through the TCP.
///
/// # Errors
/// None in practice.
pub fn experiment_head() -> Result<SimHead> {
    let a = 36.4655;
    let (m, q) = (0.3536, 0.8660);
    let nominal = [
        [-a, a, -35.0, m, -m, q],
        [a, a, -35.0, -m, -m, q],
        [a, -a, -35.0, -m, m, q],
        [-a, -a, -35.0, m, m, q],
    ];
    let errors = [
        [0.4838, -0.2460, 0.1723, 0.0047, -0.0065, -0.0047],
        [-0.2906, -0.4338, -0.2393, -0.0048, -0.0012, -0.0026],
        [0.9513, 0.5488, 0.1860, -0.0278, -0.0201, -0.0039],
        [0.5558, -0.8081, 0.1186, 0.0229, -0.0182, -0.0026],
    ];
    let mut h = head_from_table("experiment", &nominal, &errors, Vector3::from, 0.0)?;
    h.sigma_mm = Some(0.003);
    Ok(h)
}

/// The nominal cone head of the random heads: four sensors on a 50 mm
/// circle in z = 0, beams 30° off the axis towards it, looking along +z
/// (the paper's Table 2 geometry in our frame), numbered counter-clockwise
/// from +x.
///
/// # Errors
/// None in practice.
pub fn cone_nominal() -> Result<Vec<Sensor<f64>>> {
    let h = perpend_core::head::Head4::cone(50.0, 30f64.to_radians(), 0.0, 0.0)
        .map_err(|e| anyhow::anyhow!("cone head: {e}"))?;
    Ok(h.sensors.to_vec())
}

/// `nominal` with zero-point errors uniform in ±`zero_err_mm` per axis and
/// beam tilts uniform in ±`dir_err_rad` about each tangent axis.
fn perturbed(
    nominal: &[Sensor<f64>],
    rng: &mut StdRng,
    zero_err_mm: f64,
    dir_err_rad: f64,
    what: &str,
) -> Result<Vec<Sensor<f64>>> {
    nominal
        .iter()
        .map(|s| {
            let mut u = || rng.gen_range(-1.0..=1.0);
            let d = SVector::<f64, 5>::from([
                zero_err_mm * u(),
                zero_err_mm * u(),
                zero_err_mm * u(),
                dir_err_rad * u(),
                dir_err_rad * u(),
            ]);
            s.retract(&d).map_err(|e| anyhow::anyhow!("{what}: {e}"))
        })
        .collect()
}

/// A random head: the nominal cone head with zero-point errors uniform in
/// ±`zero_err_mm` per axis and beam tilts uniform in ±`dir_err_rad` about
/// each tangent axis (the paper's Table 2 errors are up to 1.6 mm and
/// 0.07 rad).
///
/// # Errors
/// None in practice.
pub fn random_head(rng: &mut StdRng, zero_err_mm: f64, dir_err_rad: f64) -> Result<SimHead> {
    let nominal = cone_nominal()?;
    let truth = perturbed(&nominal, rng, zero_err_mm, dir_err_rad, "random head")?;
    Ok(SimHead {
        name: "random".into(),
        nominal,
        truth,
        sigma_mm: Some(0.01),
        standoff_mm: 35.0,
    })
}

/// Standoff [mm] of the Tian-style head ([`tian_style_head`]): where the
/// surface crosses the spindle axis, 60 mm from the zero points (issue 14).
pub const TIAN_STANDOFF_MM: f64 = 60.0;

/// A Tian-style head (Tian Fig. 3-4 with the proportions of issue 14):
/// four sensors on a 45 mm circle in z = 0, beams 25° off the axis towards
/// it, looking along +z, numbered counter-clockwise from +x, standoff
/// [`TIAN_STANDOFF_MM`] (the spots lie on a 17 mm circle there); the true
/// head has zero-point errors uniform in ±`zero_err_mm` per axis and beam
/// tilts uniform in ±`dir_err_rad` about each tangent axis.
///
/// # Errors
/// None in practice.
pub fn tian_style_head(rng: &mut StdRng, zero_err_mm: f64, dir_err_rad: f64) -> Result<SimHead> {
    let h = perpend_core::head::Head4::cone(45.0, 25f64.to_radians(), 0.0, 0.0)
        .map_err(|e| anyhow::anyhow!("cone head: {e}"))?;
    let nominal = h.sensors.to_vec();
    let truth = perturbed(&nominal, rng, zero_err_mm, dir_err_rad, "Tian-style head")?;
    Ok(SimHead {
        name: "tian".into(),
        nominal,
        truth,
        sigma_mm: Some(0.01),
        standoff_mm: TIAN_STANDOFF_MM,
    })
}

/// How the poses of a run are spread (all ranges full width, uniform).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseSpread {
    /// Centre tilt about TCS x (θ1) [deg].
    pub center_tilt_x_deg: f64,
    /// Centre tilt about TCS y (θ2) [deg].
    pub center_tilt_y_deg: f64,
    /// Full range of the tilt about x [deg].
    pub tilt_x_range_deg: f64,
    /// Full range of the tilt about y [deg].
    pub tilt_y_range_deg: f64,
    /// Centre standoff: z [mm] where the plane crosses the spindle axis.
    pub standoff_mm: f64,
    /// Full range of the standoff [mm].
    pub standoff_range_mm: f64,
}

/// Full tilt range [deg] about x and about y of the paper reproduction
/// ([`PoseSpread::paper`]), tuned so that the uncalibrated error matches
/// Chen Table 4's "before" row (1.34° mean, 0.18° std, 1.68° max of 20).
pub const PAPER_TILT_RANGE_DEG: f64 = 10.0;
/// Full standoff range [mm] of the paper reproduction.
pub const PAPER_STANDOFF_RANGE_MM: f64 = 3.0;
/// Centre standoff [mm] of the paper reproduction (where the plane crosses
/// the spindle axis). The Table 1 plane itself crosses at 35.86 mm, where
/// the uncalibrated error is 1.61° whatever the spread: the paper's mean of
/// 1.34° needs the planes ~8 mm closer (the error grows by ~0.05°/mm).
pub const PAPER_STANDOFF_MM: f64 = 28.0;

impl PoseSpread {
    /// The paper's simulation: the orientation of the Table 1 plane
    /// (θ1 = 17.89°, θ2 = −1.04° in our frame) at [`PAPER_STANDOFF_MM`],
    /// with the spread tuned to reproduce Table 4's "before" row (the paper
    /// states neither): tilts ±[`PAPER_TILT_RANGE_DEG`]/2 about both axes,
    /// standoff ±[`PAPER_STANDOFF_RANGE_MM`]/2. Used for the calibration
    /// poses and the test planes alike.
    pub fn paper() -> Self {
        // Table 1 plane rotated into our frame: (0.0173, 0.3071, −0.9515).
        let (a, b, c) = (0.0173f64, 0.3071f64, -0.9515f64);
        Self {
            center_tilt_x_deg: b.atan2(-c).to_degrees(),
            center_tilt_y_deg: (-a).atan2(-c).to_degrees(),
            tilt_x_range_deg: PAPER_TILT_RANGE_DEG,
            tilt_y_range_deg: PAPER_TILT_RANGE_DEG,
            standoff_mm: PAPER_STANDOFF_MM,
            standoff_range_mm: PAPER_STANDOFF_RANGE_MM,
        }
    }

    /// A robot cell's calibration poses around the perpendicular: ±10°
    /// about both axes, ±5 mm standoff around `standoff_mm`.
    pub fn cell(standoff_mm: f64) -> Self {
        Self {
            center_tilt_x_deg: 0.0,
            center_tilt_y_deg: 0.0,
            tilt_x_range_deg: 20.0,
            tilt_y_range_deg: 20.0,
            standoff_mm,
            standoff_range_mm: 10.0,
        }
    }

    /// Draws one true plane.
    pub fn draw(&self, rng: &mut StdRng) -> Plane<f64> {
        let mut u = || rng.gen_range(-0.5..=0.5);
        let tx = (self.center_tilt_x_deg + self.tilt_x_range_deg * u()).to_radians();
        let ty = (self.center_tilt_y_deg + self.tilt_y_range_deg * u()).to_radians();
        let s = self.standoff_mm + self.standoff_range_mm * u();
        plane_from_tilts(tx, ty, s)
    }
}

/// The plane with Tian's deviation angles θ1 = `tx`, θ2 = `ty` [rad] (its
/// normal towards the head is `normalise(−tan ty, tan tx, −1)`) crossing the
/// spindle axis at z = `standoff`.
pub fn plane_from_tilts(tx: f64, ty: f64, standoff: f64) -> Plane<f64> {
    let n = Vector3::new(-ty.tan(), tx.tan(), -1.0).normalize();
    Plane {
        n,
        d: -n.z * standoff,
    }
}

/// The laser tracker's plane measurement (Chen §5 step 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tracker {
    /// Point noise ξ (1σ per coordinate) [mm].
    pub xi_mm: f64,
    /// Points measured per plane.
    pub points: usize,
    /// Side of the square patch the points are spread over [mm].
    pub patch_mm: f64,
}

impl Tracker {
    /// Chen §5 step 1: 20 points, ξ = 0.02 mm; a 150 mm patch, consistent
    /// with Table 1's fitted-vs-theoretical difference (~1e-4 in B and C,
    /// 0.007 mm in D).
    pub fn paper() -> Self {
        Self {
            xi_mm: 0.02,
            points: 20,
            patch_mm: 150.0,
        }
    }

    /// The plane fitted to `points` noisy points of `truth` (total least
    /// squares), oriented like `truth`.
    pub fn measure(&self, truth: &Plane<f64>, rng: &mut StdRng) -> Plane<f64> {
        if self.points < 3 {
            return *truth;
        }
        let n = truth.n;
        // Centre: where the spindle axis meets the plane (or the foot of
        // the origin if the plane contains the axis direction).
        let centre = if n.z.abs() > 1e-6 {
            Vector3::new(0.0, 0.0, -truth.d / n.z)
        } else {
            -n * truth.d
        };
        let (e1, e2) = tangent_basis(&n);
        let pts: Vec<Vector3<f64>> = (0..self.points)
            .map(|_| {
                let u = rng.gen_range(-0.5..=0.5) * self.patch_mm;
                let v = rng.gen_range(-0.5..=0.5) * self.patch_mm;
                let noise = Vector3::from_fn(|_, _| self.xi_mm * gauss(rng));
                centre + e1 * u + e2 * v + noise
            })
            .collect();
        let c = pts.iter().fold(Vector3::zeros(), |a, p| a + p) / pts.len() as f64;
        let mut m = Matrix3::zeros();
        for p in &pts {
            let q = p - c;
            m += q * q.transpose();
        }
        let eig = m.symmetric_eigen();
        let imin = eig.eigenvalues.imin();
        let mut fitted = eig.eigenvectors.column(imin).into_owned();
        if fitted.dot(&n) < 0.0 {
            fitted = -fitted;
        }
        Plane {
            n: fitted,
            d: -fitted.dot(&c),
        }
    }
}

/// One standard normal draw.
pub fn gauss(rng: &mut StdRng) -> f64 {
    rng.sample::<f64, _>(StandardNormal)
}

/// What an [`Effect`] may look at: the truth of one pose.
#[derive(Debug, Clone, Copy)]
pub struct PoseTruth<'a> {
    /// Pose index (0-based).
    pub pose: usize,
    /// The true plane.
    pub plane: &'a Plane<f64>,
    /// The true sensors.
    pub head: &'a [Sensor<f64>],
    /// True geometric distances (`None` where the beam misses the plane).
    pub distances: &'a [Option<f64>],
    /// Acquisition time [s], if simulated.
    pub t_s: Option<f64>,
    /// Head temperature [°C], if simulated.
    pub temp_c: Option<f64>,
}

/// A systematic error of the readings, applied to the noise-free readings
/// of a pose before the reading noise is added.
pub trait Effect {
    /// Short name for file comments.
    fn name(&self) -> String;
    /// Changes `readings` (initially the true distances) for one pose.
    fn apply(&self, truth: &PoseTruth<'_>, readings: &mut [Option<f64>], rng: &mut StdRng);
}

/// Readings that a head with per-sensor [`Extension`] coefficients
/// produces: the reading `r` with `ext.correct(r, …) = true distance`
/// (solved by fixed-point iteration; the board's correction then recovers
/// the distance exactly up to the first-order inversion of `ext`).
#[derive(Debug, Clone, PartialEq)]
pub struct ExtensionEffect {
    /// One extension per sensor (missing = identity).
    pub ext: Vec<Extension<f64>>,
}

impl Effect for ExtensionEffect {
    fn name(&self) -> String {
        "extension".into()
    }

    fn apply(&self, truth: &PoseTruth<'_>, readings: &mut [Option<f64>], _rng: &mut StdRng) {
        let n = readings.len();
        let ctx = Context {
            temp_c: truth.temp_c,
            t_s: truth.t_s,
        };
        // the beam's angles to the surface, azimuth included (the spot
        // terms of `perpend_core::ext`, "Incidence")
        let cosg: Vec<Incidence<f64>> = truth
            .head
            .iter()
            .map(|s| Incidence::of(&truth.plane.n, &s.dir))
            .collect();
        let base: Vec<Option<f64>> = truth.distances.to_vec();
        let mut cur: Vec<Option<f64>> = base.clone();
        for _ in 0..8 {
            let prev = cur.clone();
            for i in 0..n {
                let (Some(d), Some(_)) = (base[i], prev[i]) else {
                    continue;
                };
                let Some(e) = self.ext.get(i) else {
                    continue;
                };
                let p = prev[(i + n - 1) % n];
                // The reading model of `perpend_core::ext`: the excess is a
                // function of the true distance and the previous channel's
                // reading (iterated because the channels form a ring).
                cur[i] = Some(d + e.excess(d, p, cosg[i], &ctx));
            }
        }
        readings.copy_from_slice(&cur);
    }
}

/// Head temperature over the run: `start + rate·t + swing·sin(2πt/period)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TempProfile {
    /// Temperature at t = 0 [°C].
    pub start_c: f64,
    /// Linear rate [°C/s].
    pub rate_c_per_s: f64,
    /// Amplitude of a periodic swing [°C].
    pub swing_c: f64,
    /// Period of the swing [s].
    pub period_s: f64,
}

impl TempProfile {
    /// Temperature at time `t` [s].
    pub fn at(&self, t: f64) -> f64 {
        let periodic = if self.period_s > 0.0 {
            self.swing_c * (2.0 * std::f64::consts::PI * t / self.period_s).sin()
        } else {
            0.0
        };
        self.start_c + self.rate_c_per_s * t + periodic
    }
}

/// Everything about a simulated run except the head.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimConfig {
    /// Number of poses.
    pub poses: usize,
    /// Pose spread.
    pub spread: PoseSpread,
    /// Tracker model (`None`: the true plane is written).
    pub tracker: Option<Tracker>,
    /// Reading noise ζ (1σ) [mm].
    pub zeta_mm: f64,
    /// Measuring range `(min, max)` [mm]: readings outside are missing.
    pub range_mm: Option<(f64, f64)>,
    /// Probability that a reading is missing (fault, dropout).
    pub dropout: f64,
    /// Time between poses [s]: fills `t_s` when set.
    pub dt_s: Option<f64>,
    /// Head temperature: fills `temp_c` when set (needs `dt_s`, else t = pose index).
    pub temp: Option<TempProfile>,
}

impl SimConfig {
    /// The paper's calibration run (Chen §5 steps 1-7): 100 poses of the
    /// paper spread, tracker ξ = 0.02 mm, ζ = 0.01 mm.
    pub fn paper() -> Self {
        Self {
            poses: 100,
            spread: PoseSpread::paper(),
            tracker: Some(Tracker::paper()),
            zeta_mm: 0.01,
            range_mm: None,
            dropout: 0.0,
            dt_s: None,
            temp: None,
        }
    }
}

/// A simulated run: the exchange-format tables and the hidden truth.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// `sensors.csv` (nominal head).
    pub sensors: SensorTable,
    /// `poses.csv` (tracker planes, readings).
    pub poses: PoseTable,
    /// True plane of each pose.
    pub true_planes: Vec<Plane<f64>>,
    /// True sensors.
    pub truth: Vec<Sensor<f64>>,
}

/// Adds a linearity error of a shape no candidate of the diagnosis has to
/// every reading of `poses`: one sine period over each sensor's range of
/// readings in the run, `amp[i]·sin(π·u)` with `u` from −1 at its smallest
/// reading to +1 at its largest (the S-curve a triangulation sensor's
/// residual linearity often is). For tests of the linearity table.
pub fn add_sine_linearity(poses: &mut perpend_formats::exchange::PoseTable, amp: &[f64]) {
    let range = |i: usize| {
        let v = poses
            .rows
            .iter()
            .filter_map(|r| r.readings.get(i).copied().flatten());
        v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), d| {
            (a.min(d), b.max(d))
        })
    };
    let ranges: Vec<(f64, f64)> = (0..amp.len()).map(range).collect();
    for row in &mut poses.rows {
        for ((d, a), (lo, hi)) in row.readings.iter_mut().zip(amp).zip(&ranges) {
            if let Some(d) = d.as_mut() {
                if hi > lo {
                    let u = 2.0 * (*d - lo) / (hi - lo) - 1.0;
                    *d += a * (std::f64::consts::PI * u).sin();
                }
            }
        }
    }
}

/// True distances of `head` on `plane` (`None` where the beam misses).
pub fn true_distances(head: &[Sensor<f64>], plane: &Plane<f64>) -> Vec<Option<f64>> {
    head.iter()
        .enumerate()
        .map(|(i, s)| distance(s, plane, i).ok())
        .collect()
}

/// When a pose is acquired: its index, time and head temperature.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Moment {
    /// Pose index (0-based).
    pub pose: usize,
    /// Acquisition time [s].
    pub t_s: Option<f64>,
    /// Head temperature [°C].
    pub temp_c: Option<f64>,
}

/// Noisy readings of `plane` by the true head at `when`: effects, noise ζ,
/// measuring range, dropouts (`None` = missing).
pub fn readings(
    head: &SimHead,
    cfg: &SimConfig,
    effects: &[&dyn Effect],
    plane: &Plane<f64>,
    when: Moment,
    rng: &mut StdRng,
) -> Vec<Option<f64>> {
    let dist = true_distances(&head.truth, plane);
    let mut r = dist.clone();
    let truth = PoseTruth {
        pose: when.pose,
        plane,
        head: &head.truth,
        distances: &dist,
        t_s: when.t_s,
        temp_c: when.temp_c,
    };
    for e in effects {
        e.apply(&truth, &mut r, rng);
    }
    perturb(cfg, &mut r, rng);
    r
}

/// Reading noise ζ, measuring range and dropouts of `cfg` applied to
/// distances (`None` stays missing).
fn perturb(cfg: &SimConfig, r: &mut [Option<f64>], rng: &mut StdRng) {
    for x in r.iter_mut() {
        let noise = cfg.zeta_mm * gauss(rng);
        let drop = cfg.dropout > 0.0 && rng.gen_bool(cfg.dropout.clamp(0.0, 1.0));
        *x = match *x {
            Some(v) if !drop => {
                let v = v + noise;
                let in_range = cfg.range_mm.is_none_or(|(lo, hi)| v >= lo && v <= hi);
                (in_range && v >= 0.0).then_some(v)
            }
            _ => None,
        };
    }
}

/// True distances of `head` on a curved datum surface (beam-surface
/// intersection, [`CurvedSurface::distance`]; `None` where the beam misses).
pub fn curved_distances(head: &[Sensor<f64>], surface: &CurvedSurface<f64>) -> Vec<Option<f64>> {
    head.iter()
        .enumerate()
        .map(|(i, s)| surface.distance(s, i).ok())
        .collect()
}

/// Noisy readings of a curved datum surface (sphere or cylinder, issue 14)
/// by the true head: the geometric distances, then noise ζ, measuring
/// range and dropouts as [`readings`] (no [`Effect`]s: they are written
/// for planes).
pub fn curved_readings(
    head: &SimHead,
    cfg: &SimConfig,
    surface: &CurvedSurface<f64>,
    rng: &mut StdRng,
) -> Vec<Option<f64>> {
    let mut r = curved_distances(&head.truth, surface);
    perturb(cfg, &mut r, rng);
    r
}

/// Simulates a run of `cfg.poses` poses of `head` (poses with fewer than
/// three valid readings are drawn again, up to 100 times each).
///
/// # Errors
/// When a pose with three valid readings cannot be drawn (the spread does
/// not fit the head or its range).
pub fn simulate(
    head: &SimHead,
    cfg: &SimConfig,
    effects: &[&dyn Effect],
    rng: &mut StdRng,
) -> Result<Dataset> {
    let n = head.truth.len();
    let mut rows = Vec::with_capacity(cfg.poses);
    let mut planes = Vec::with_capacity(cfg.poses);
    for k in 0..cfg.poses {
        let t_s = cfg.dt_s.map(|dt| dt * k as f64);
        let temp_c = cfg.temp.map(|p| p.at(t_s.unwrap_or(k as f64)));
        let mut attempt = 0;
        let (plane, r) = loop {
            let plane = cfg.spread.draw(rng);
            let when = Moment {
                pose: k,
                t_s,
                temp_c,
            };
            let r = readings(head, cfg, effects, &plane, when, rng);
            if r.iter().filter(|x| x.is_some()).count() >= 3 {
                break (plane, r);
            }
            attempt += 1;
            if attempt >= 100 {
                bail!(
                    "pose {}: no plane of the spread gives three valid readings",
                    k + 1
                );
            }
        };
        let measured = match &cfg.tracker {
            Some(t) => t.measure(&plane, rng),
            None => plane,
        };
        rows.push(PoseRow {
            line: 0,
            pose: k as i64 + 1,
            abcd: [measured.n.x, measured.n.y, measured.n.z, measured.d],
            plane: measured,
            readings: r,
            t_s,
            temp_c,
            noise: Default::default(),
        });
        planes.push(plane);
    }
    Ok(Dataset {
        sensors: SensorTable::from_sensors(&head.nominal, head.sigma_mm),
        poses: PoseTable { n_sensors: n, rows },
        true_planes: planes,
        truth: head.truth.clone(),
    })
}

/// Which head `perpend simulate` uses.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadKind {
    /// Chen Table 2 (simulated head), rotated into the +z-feed TCS.
    Paper,
    /// Chen Table 6 (experimental head).
    Experiment,
    /// The nominal cone head with random errors of the paper's size.
    Random,
}

/// Arguments of `perpend simulate`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output directory for sensors.csv and poses.csv.
    #[arg(long, default_value = "sim")]
    pub out: PathBuf,
    /// Head to simulate.
    #[arg(long, value_enum, default_value_t = HeadKind::Paper)]
    pub head: HeadKind,
    /// Random seed (the same seed reproduces the same files).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of poses.
    #[arg(long, default_value_t = 100)]
    pub poses: usize,
    /// Centre tilt about x [deg] (default: the paper's Table 1 plane for
    /// the paper head, 0 otherwise).
    #[arg(long, allow_hyphen_values = true)]
    pub center_tilt_x: Option<f64>,
    /// Centre tilt about y [deg] (default as --center-tilt-x).
    #[arg(long, allow_hyphen_values = true)]
    pub center_tilt_y: Option<f64>,
    /// Full tilt range about x [deg].
    #[arg(long, default_value_t = PAPER_TILT_RANGE_DEG)]
    pub tilt_x_range: f64,
    /// Full tilt range about y [deg].
    #[arg(long, default_value_t = PAPER_TILT_RANGE_DEG)]
    pub tilt_y_range: f64,
    /// Centre standoff [mm] (default: mid-range for the head).
    #[arg(long, allow_hyphen_values = true)]
    pub standoff: Option<f64>,
    /// Full standoff range [mm].
    #[arg(long, default_value_t = PAPER_STANDOFF_RANGE_MM)]
    pub standoff_range: f64,
    /// Tracker point noise ξ [mm] (0: write the true planes).
    #[arg(long, default_value_t = 0.02)]
    pub xi: f64,
    /// Tracker points per plane.
    #[arg(long, default_value_t = 20)]
    pub tracker_points: usize,
    /// Side of the tracker's square patch [mm].
    #[arg(long, default_value_t = 150.0)]
    pub patch: f64,
    /// Reading noise ζ [mm].
    #[arg(long, default_value_t = 0.01)]
    pub zeta: f64,
    /// Probability of a missing reading.
    #[arg(long, default_value_t = 0.0)]
    pub dropout: f64,
    /// Time between poses [s]: writes a t_s column.
    #[arg(long)]
    pub dt: Option<f64>,
    /// Head temperature at the start [°C]: writes a temp_c column.
    #[arg(long, allow_hyphen_values = true)]
    pub temp_start: Option<f64>,
    /// Temperature rate [°C/s] (with --temp-start).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub temp_rate: f64,
    /// Write the true head as a parameter JSON here (for comparisons).
    #[arg(long)]
    pub truth: Option<PathBuf>,
}

/// Builds the head, spread and configuration from the arguments.
///
/// # Errors
/// Invalid values.
pub fn setup(a: &Args, rng: &mut StdRng) -> Result<(SimHead, SimConfig)> {
    let head = match a.head {
        HeadKind::Paper => paper_head()?,
        HeadKind::Experiment => experiment_head()?,
        HeadKind::Random => random_head(rng, 1.5, 0.07)?,
    };
    let base = match a.head {
        HeadKind::Paper => PoseSpread::paper(),
        _ => PoseSpread::cell(head.standoff_mm),
    };
    let spread = PoseSpread {
        center_tilt_x_deg: a.center_tilt_x.unwrap_or(base.center_tilt_x_deg),
        center_tilt_y_deg: a.center_tilt_y.unwrap_or(base.center_tilt_y_deg),
        tilt_x_range_deg: a.tilt_x_range,
        tilt_y_range_deg: a.tilt_y_range,
        standoff_mm: a.standoff.unwrap_or(base.standoff_mm),
        standoff_range_mm: a.standoff_range,
    };
    for (v, name) in [
        (a.tilt_x_range, "--tilt-x-range"),
        (a.tilt_y_range, "--tilt-y-range"),
        (a.standoff_range, "--standoff-range"),
        (a.xi, "--xi"),
        (a.zeta, "--zeta"),
        (a.patch, "--patch"),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            bail!("{name} must be a non-negative number, got {v}");
        }
    }
    if !(0.0..=1.0).contains(&a.dropout) {
        bail!("--dropout must be in [0, 1], got {}", a.dropout);
    }
    if a.poses == 0 {
        bail!("--poses must be at least 1");
    }
    let tracker = (a.xi > 0.0).then_some(Tracker {
        xi_mm: a.xi,
        points: a.tracker_points,
        patch_mm: a.patch,
    });
    let temp = a.temp_start.map(|s| TempProfile {
        start_c: s,
        rate_c_per_s: a.temp_rate,
        swing_c: 0.0,
        period_s: 0.0,
    });
    let cfg = SimConfig {
        poses: a.poses,
        spread,
        tracker,
        zeta_mm: a.zeta,
        range_mm: None,
        dropout: a.dropout,
        dt_s: a.dt,
        temp,
    };
    Ok((head, cfg))
}

/// Runs `perpend simulate`.
///
/// # Errors
/// Invalid arguments, I/O errors.
pub fn run(a: &Args) -> Result<()> {
    let mut rng = StdRng::seed_from_u64(a.seed);
    let (mut head, cfg) = setup(a, &mut rng)?;
    // The datasheet σ written is the reading noise actually simulated, so
    // that a diagnosis of clean simulated data expects what it gets.
    head.sigma_mm = (a.zeta > 0.0).then_some(a.zeta);
    let data = simulate(&head, &cfg, &[], &mut rng)?;
    let s = &cfg.spread;
    let comments = vec![
        format!(
            "perpend simulate --head {} --seed {} --poses {}",
            head.name, a.seed, cfg.poses
        ),
        format!(
            "tilt about x {:.3}° ± {:.3}°, about y {:.3}° ± {:.3}°, standoff {:.3} ± {:.3} mm",
            s.center_tilt_x_deg,
            s.tilt_x_range_deg / 2.0,
            s.center_tilt_y_deg,
            s.tilt_y_range_deg / 2.0,
            s.standoff_mm,
            s.standoff_range_mm / 2.0
        ),
        format!(
            "tracker xi = {} mm ({} points, {} mm patch), reading noise zeta = {} mm",
            a.xi, a.tracker_points, a.patch, a.zeta
        ),
    ];
    perpend_formats::exchange::write_dataset(&a.out, &data.sensors, &data.poses, &comments)?;
    if let Some(p) = &a.truth {
        let pf = perpend_formats::paramfile::ParamFile::truth(&head.truth, &head.nominal);
        pf.write(p)
            .with_context(|| format!("cannot write {}", p.display()))?;
    }
    println!(
        "wrote {} and {} ({} poses, {} sensors, head {})",
        a.out.join("sensors.csv").display(),
        a.out.join("poses.csv").display(),
        cfg.poses,
        head.nominal.len(),
        head.name
    );
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_core::surface::Shape;

    #[test]
    fn curved_readings_put_the_spots_on_the_surface() {
        let mut rng = StdRng::seed_from_u64(4);
        let head = tian_style_head(&mut rng, 1.0, 0.02).unwrap();
        let n = Vector3::new(0.1, -0.05, -1.0);
        let p = Vector3::new(0.0, 0.0, TIAN_STANDOFF_MM);
        let cfg = SimConfig {
            zeta_mm: 0.0,
            tracker: None,
            ..SimConfig::paper()
        };
        for shape in [
            Shape::Sphere { radius: 300.0 },
            Shape::Sphere { radius: -300.0 },
            Shape::Cylinder {
                radius: 400.0,
                axis: Vector3::new(1.0, 1.0, 0.0),
            },
            Shape::Cylinder {
                radius: -400.0,
                axis: Vector3::new(0.0, 1.0, 0.0),
            },
        ] {
            let s = CurvedSurface::through(p, n, &shape).unwrap();
            let r = curved_readings(&head, &cfg, &s, &mut rng);
            for (d, sensor) in r.iter().zip(&head.truth) {
                let q = sensor.spot(d.unwrap());
                // on the surface: its distance from the centre (or axis) is |R|
                let mut v = q - s.centre;
                if let Some(a) = s.axis {
                    v -= a * a.dot(&v);
                }
                assert!((v.norm() - s.radius.abs()).abs() < 1e-9, "{shape:?}");
                // the facing side: the normal there opposes the beam
                assert!(s.normal_at(&q).unwrap().dot(&sensor.dir) < 0.0);
            }
        }
        // noise ζ is added as for planes
        let noisy = SimConfig {
            zeta_mm: 0.01,
            ..cfg
        };
        let s = CurvedSurface::through(p, n, &Shape::Sphere { radius: 500.0 }).unwrap();
        let exact = curved_distances(&head.truth, &s);
        let r = curved_readings(&head, &noisy, &s, &mut rng);
        let dev: f64 = r
            .iter()
            .zip(&exact)
            .map(|(a, b)| (a.unwrap() - b.unwrap()).abs())
            .sum();
        assert!(dev > 0.0 && dev < 0.2, "{dev}");
    }
}
