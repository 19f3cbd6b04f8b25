//! `perpend bench`: the paper's simulation (Chen §5, Table 4) over many
//! seeds, the calibration speed on the host, and the identifiability
//! sensitivity study behind [`perpend_core::calib::Thresholds`].
//!
//! **accuracy** — Chen §5 steps 1-10 per seed: the Table 2 head, 100
//! calibration poses of the Table 1 plane spread by
//! [`PoseSpread::paper`] (tracker ξ = 0.02 mm on 20 points, reading noise
//! ζ = 0.01 mm), then 20 test planes from the same spread read with noise ζ.
//! The normal of every test plane is computed from the same readings with
//! the nominal head (`before`), the EKF's head (`ekf`, Chen eq. 10-16 with
//! the §5 step 7 values), the least-squares head (`lsq`) and the true head
//! (`floor`: what perfect calibration achieves), always with Chen's
//! micro-plane normal (eq. 18-19, averaged cross products), and compared
//! with the plane's true normal. Statistics pool all seeds × planes
//! (std with n − 1).
//!
//! **speed** — median wall time of calibrating all four sensors from 100
//! poses, LM and EKF, over repeated runs.
//!
//! **curvature** — micro-plane against the curved model on spheres and
//! cylinders, and the alignment loop: [`perpend_calib::curvature`].
//!
//! **ident** — how the identifiability and the calibrated normal error
//! depend on the calibration pose spread (tilt range about x and y,
//! standoff range), for choosing the thresholds.

use std::time::Instant;

use anyhow::{anyhow, bail, Result};
use nalgebra::Vector3;
use perpend_core::calib::{
    ekf_sensor, fit_sensor_base, EkfConfig, EkfFit, Innovation, LsqConfig, Thresholds,
};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::{Head4, Sensor};
use perpend_core::normal::{plane, Method};
use rand::rngs::StdRng;
use rand::SeedableRng;
use serde::Serialize;

use perpend_calib::calibrate::{angle_deg, residual_rms};
use perpend_calib::sim::{
    paper_head, readings, simulate, Dataset, Moment, PoseSpread, SimConfig, SimHead,
    PAPER_STANDOFF_RANGE_MM, PAPER_TILT_RANGE_DEG,
};
use perpend_formats::exchange::PoseTable;

/// Arguments of `perpend bench`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to measure.
    #[command(subcommand)]
    pub what: Bench,
}

/// The benchmarks.
#[derive(clap::Subcommand, Debug)]
pub enum Bench {
    /// The paper's simulation (Chen §5, Table 4) over K seeds.
    Accuracy(AccuracyArgs),
    /// Host calibration time for 100 poses (LM and EKF).
    Speed(SpeedArgs),
    /// Sensitivity of identifiability and accuracy to the pose spread.
    Ident(IdentArgs),
    /// The diagnosis on runs from the independent generator
    /// (`host-tests/blind`, no shared code), scored against their hidden
    /// truth over the grid of regimes: false positives, singles and pairs
    /// named, blunders found, extended RMS over the same-draw floor.
    Diagnose(crate::diagnose::blind::Args),
    /// Self-consistency of the diagnosis on perpend's own simulator
    /// (effects injected through the candidates' own terms): confusion
    /// matrix and detection rate against effect size; not the benchmark of
    /// record (`bench diagnose` is).
    DiagnoseSelf(crate::diagnose::bench::Args),
    /// Planned (D-optimal) against random calibration poses, 8-100 poses.
    Plan(perpend_calib::plan::BenchArgs),
    /// Curved skins (issue 14): micro-plane against the sphere/cylinder
    /// model and the noise floor, and the alignment loop.
    Curvature(perpend_calib::curvature::Args),
    /// Frame errors of the cell (issue 36): normal error with and without
    /// reversal about the spindle axis, against the floor.
    Frames(perpend_calib::frames::bench::Args),
}

/// Arguments of `perpend bench accuracy`.
#[derive(clap::Args, Debug)]
pub struct AccuracyArgs {
    /// Number of seeds (runs of the whole simulation).
    #[arg(long, default_value_t = 10)]
    pub seeds: u64,
    /// First seed.
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Print one JSON object {before, ekf, lsq, floor}.
    #[arg(long)]
    pub json: bool,
    /// Full tilt range of the poses about x and y [deg].
    #[arg(long, default_value_t = PAPER_TILT_RANGE_DEG)]
    pub tilt_range: f64,
    /// Full standoff range of the poses [mm].
    #[arg(long, default_value_t = PAPER_STANDOFF_RANGE_MM)]
    pub standoff_range: f64,
    /// Calibration poses per seed.
    #[arg(long, default_value_t = 100)]
    pub poses: usize,
    /// Test planes per seed.
    #[arg(long, default_value_t = 20)]
    pub test_planes: usize,
    /// EKF with the nonlinear innovation instead of the paper's.
    #[arg(long)]
    pub ekf_nonlinear: bool,
}

/// Max / mean / std of angular errors [deg].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// Largest error.
    pub max_deg: f64,
    /// Mean error.
    pub mean_deg: f64,
    /// Sample standard deviation.
    pub std_deg: f64,
}

impl Stats {
    /// Statistics of `v` (zeros for an empty slice).
    pub fn of(v: &[f64]) -> Self {
        let n = v.len();
        if n == 0 {
            return Self {
                max_deg: 0.0,
                mean_deg: 0.0,
                std_deg: 0.0,
            };
        }
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = if n > 1 {
            v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1) as f64
        } else {
            0.0
        };
        Self {
            max_deg: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            mean_deg: mean,
            std_deg: var.sqrt(),
        }
    }
}

/// Settings of the accuracy benchmark.
#[derive(Debug, Clone)]
pub struct AccuracyConfig {
    /// Seeds, one simulation each.
    pub seeds: Vec<u64>,
    /// Calibration run.
    pub cal: SimConfig,
    /// Test planes per seed (noise `cal.zeta_mm`).
    pub test_planes: usize,
    /// Spread of the test planes.
    pub test_spread: PoseSpread,
    /// EKF settings.
    pub ekf: EkfConfig<f64>,
    /// LSQ settings.
    pub lsq: LsqConfig<f64>,
}

impl AccuracyConfig {
    /// The paper's simulation over `seeds`.
    pub fn paper(seeds: Vec<u64>) -> Self {
        Self {
            seeds,
            cal: SimConfig::paper(),
            test_planes: 20,
            test_spread: PoseSpread::paper(),
            ekf: EkfConfig::chen_simulation(),
            lsq: LsqConfig::default(),
        }
    }
}

/// All errors of the accuracy benchmark.
#[derive(Debug, Clone, Default)]
pub struct AccuracyErrors {
    /// Nominal head.
    pub before: Vec<f64>,
    /// EKF head.
    pub ekf: Vec<f64>,
    /// Least-squares head.
    pub lsq: Vec<f64>,
    /// True head.
    pub floor: Vec<f64>,
    /// EKF readings used until the stop, per sensor, per (converged) seed.
    pub ekf_used: Vec<[usize; 4]>,
    /// Seeds whose EKF diverged on some sensor (excluded from `ekf`).
    pub ekf_diverged: Vec<u64>,
}

/// Residual RMS [mm] above which an EKF run counts as diverged: 10 ζ of the
/// paper's simulation (converged runs stay below 0.05 mm, diverged ones
/// are at 0.5-10 mm).
pub const EKF_DIVERGED_RMS_MM: f64 = 0.1;

fn head4(s: &[Sensor<f64>]) -> Result<Head4<f64>> {
    let arr: [Sensor<f64>; 4] = s
        .to_vec()
        .try_into()
        .map_err(|_| anyhow!("the benchmark needs a four-sensor head"))?;
    Ok(Head4::new(arr))
}

/// Chen eq. 18-19 normal error [deg] of `head` on `readings` of `truth`.
fn normal_error(head: &Head4<f64>, r: &[Option<f64>], truth: &Plane<f64>) -> Result<f64> {
    let r4: [Option<f64>; 4] = [r[0], r[1], r[2], r[3]];
    let fit = plane(head, &r4, &Context::default(), Method::Chen)
        .map_err(|e| anyhow!("normal of a test plane: {e}"))?;
    // The true normal towards the head (the head sits on the -z side).
    let n_true: Vector3<f64> = if truth.n.z < 0.0 { truth.n } else { -truth.n };
    Ok(angle_deg(&fit.normal, &n_true))
}

/// The paper's EKF on sensor `i` of `poses`, or `None` when it diverged:
/// it failed, rejected readings (the beam missed the plane at its
/// estimate) or its residual RMS over the run exceeds
/// [`EKF_DIVERGED_RMS_MM`]. The one divergence rule of the benches and of
/// `perpend study paper`.
pub fn ekf_accepted(
    nominal: &Sensor<f64>,
    i: usize,
    poses: &PoseTable,
    cfg: EkfConfig<f64>,
) -> Option<EkfFit<f64>> {
    ekf_sensor(nominal, i, poses, cfg).ok().filter(|f| {
        f.rejected == 0
            && residual_rms(&f.sensor, i, poses).is_some_and(|r| r < EKF_DIVERGED_RMS_MM)
    })
}

/// Both calibrations of one simulated run.
#[derive(Debug, Clone)]
pub struct Calibrated {
    /// EKF head (`None` where the filter diverged, see
    /// [`EKF_DIVERGED_RMS_MM`]).
    pub ekf: Vec<Option<Sensor<f64>>>,
    /// EKF readings used until the stop, per sensor.
    pub ekf_used: Vec<usize>,
    /// Least-squares head.
    pub lsq: Vec<Sensor<f64>>,
}

/// Calibrates with both methods. An EKF run that rejected readings (the
/// beam missed the plane at its estimate) or whose residual RMS over the
/// run exceeds [`EKF_DIVERGED_RMS_MM`] is reported as diverged (`None`).
///
/// # Errors
/// LSQ failures (a pose set that cannot identify the head).
pub fn calibrate_both(
    head: &SimHead,
    data: &Dataset,
    ekf: EkfConfig<f64>,
    lsq: &LsqConfig<f64>,
) -> Result<Calibrated> {
    let mut out = Calibrated {
        ekf: Vec::new(),
        ekf_used: Vec::new(),
        lsq: Vec::new(),
    };
    for (i, s) in head.nominal.iter().enumerate() {
        let f = ekf_accepted(s, i, &data.poses, ekf);
        out.ekf_used.push(f.as_ref().map_or(0, |f| f.used));
        out.ekf.push(f.map(|f| f.sensor));
        let g = fit_sensor_base(s, i, &data.poses, lsq).map_err(|e| anyhow!("LSQ: {e}"))?;
        out.lsq.push(g.sensor);
    }
    Ok(out)
}

/// Runs the paper's simulation for every seed.
///
/// # Errors
/// Simulation or calibration failures.
pub fn accuracy(cfg: &AccuracyConfig) -> Result<AccuracyErrors> {
    let head = paper_head()?;
    let mut out = AccuracyErrors::default();
    let nominal = head4(&head.nominal)?;
    let truth = head4(&head.truth)?;
    let bar = perpend_formats::progress::Progress::new(cfg.seeds.len() as u64, "accuracy: seeds");
    for &seed in &cfg.seeds {
        bar.inc();
        let mut rng = StdRng::seed_from_u64(seed);
        let data = simulate(&head, &cfg.cal, &[], &mut rng)?;
        let c = calibrate_both(&head, &data, cfg.ekf, &cfg.lsq)?;
        let lsq = head4(&c.lsq)?;
        let ekf = match c.ekf.iter().copied().collect::<Option<Vec<_>>>() {
            Some(e) => {
                let u = &c.ekf_used;
                out.ekf_used.push([u[0], u[1], u[2], u[3]]);
                Some(head4(&e)?)
            }
            None => {
                out.ekf_diverged.push(seed);
                None
            }
        };
        let mut test_cfg = cfg.cal;
        test_cfg.dropout = 0.0;
        for t in 0..cfg.test_planes {
            let p = cfg.test_spread.draw(&mut rng);
            let r = test_readings(&head, &test_cfg, &p, t, &mut rng);
            if r.iter().any(Option::is_none) {
                bail!(
                    "seed {seed}: test plane {} is out of the sensors' reach",
                    t + 1
                );
            }
            out.before.push(normal_error(&nominal, &r, &p)?);
            if let Some(h) = &ekf {
                out.ekf.push(normal_error(h, &r, &p)?);
            }
            out.lsq.push(normal_error(&lsq, &r, &p)?);
            out.floor.push(normal_error(&truth, &r, &p)?);
        }
    }
    Ok(out)
}

/// The text report of `perpend bench accuracy`: the rows against Chen
/// Table 4, the EKF's readings used against Table 3, LSQ over the floor.
fn print_accuracy(
    a: &AccuracyArgs,
    cfg: &AccuracyConfig,
    errs: &AccuracyErrors,
    [b, e, l, f]: [&Stats; 4],
    diverged: &str,
) {
    let s = &cfg.cal.spread;
    println!(
        "Chen §5 simulation: {} seeds × {} test planes, {} calibration poses each",
        a.seeds, cfg.test_planes, cfg.cal.poses
    );
    println!(
        "pose spread: tilt {:.2}° ± {:.1}° about x, {:.2}° ± {:.1}° about y, standoff {:.2} ± {:.1} mm",
        s.center_tilt_x_deg,
        s.tilt_x_range_deg / 2.0,
        s.center_tilt_y_deg,
        s.tilt_y_range_deg / 2.0,
        s.standoff_mm,
        s.standoff_range_mm / 2.0
    );
    println!("normal: Chen eq. 18-19 (averaged cross products) for every row");
    println!();
    println!("                      this run                     |  Chen Table 4");
    println!("                      max [°]   mean [°]   std [°]  |  max [°]   mean [°]   std [°]");
    let row = |name: &str, s: &Stats, paper: Option<(f64, f64, f64)>| {
        let p = paper.map_or(
            "        –          –         –".to_string(),
            |(x, m, d)| format!("{x:>8.4}   {m:>8.4}  {d:>8.4}"),
        );
        println!(
            "{name:<20} {:>8.4}   {:>8.4}  {:>8.4}  | {p}",
            s.max_deg, s.mean_deg, s.std_deg
        );
    };
    row("before", b, Some((1.6801, 1.3387, 0.1841)));
    let ekf_name = if a.ekf_nonlinear {
        "EKF (nonlinear inn.)"
    } else {
        "EKF (Chen eq. 10-16)"
    };
    row(ekf_name, e, Some((0.0511, 0.0412, 0.0057)));
    row("LSQ (5-DOF LM)", l, None);
    row("floor (true head)", f, None);
    println!("(paper's method 1, nonlinear LS of [19]: 0.4278 / 0.2446 / 0.1024)");
    let n = errs.ekf_used.len().max(1) as f64;
    let used: Vec<String> = (0..4)
        .map(|i| {
            format!(
                "L{} {:.1}",
                i + 1,
                errs.ekf_used.iter().map(|u| u[i] as f64).sum::<f64>() / n
            )
        })
        .collect();
    println!();
    println!(
        "EKF readings used until the stop (mean over seeds): {}  (Chen Table 3: 75 86 91 81)",
        used.join(", ")
    );
    println!("{diverged}");
    println!(
        "lsq / floor: mean {:.3}, max {:.3}   (done when ≤ 1.10 and ≤ 1.25)",
        l.mean_deg / f.mean_deg,
        l.max_deg / f.max_deg
    );
}

fn run_accuracy(a: &AccuracyArgs) -> Result<()> {
    if a.seeds == 0 {
        bail!("--seeds must be at least 1");
    }
    let mut cfg = AccuracyConfig::paper((a.first_seed..a.first_seed + a.seeds).collect());
    cfg.cal.spread.tilt_x_range_deg = a.tilt_range;
    cfg.cal.spread.tilt_y_range_deg = a.tilt_range;
    cfg.cal.spread.standoff_range_mm = a.standoff_range;
    cfg.cal.poses = a.poses;
    cfg.test_planes = a.test_planes;
    if a.ekf_nonlinear {
        cfg.ekf.innovation = Innovation::Nonlinear;
    }
    let errs = accuracy(&cfg)?;
    let (b, e, l, f) = (
        Stats::of(&errs.before),
        Stats::of(&errs.ekf),
        Stats::of(&errs.lsq),
        Stats::of(&errs.floor),
    );
    let diverged = format!(
        "EKF diverged (rejected readings or residual RMS > {EKF_DIVERGED_RMS_MM} mm) in {} of {} seeds{}; those seeds are excluded from the ekf row",
        errs.ekf_diverged.len(),
        a.seeds,
        if errs.ekf_diverged.is_empty() {
            String::new()
        } else {
            format!(" ({:?})", errs.ekf_diverged)
        }
    );
    if a.json {
        let v = serde_json::json!({ "before": b, "ekf": e, "lsq": l, "floor": f });
        println!(
            "{}",
            perpend_formats::schema::to_json(perpend_formats::schema::BENCH_ACCURACY, &v)?
        );
        if !errs.ekf_diverged.is_empty() {
            eprintln!("note: {diverged}");
        }
        return Ok(());
    }
    print_accuracy(a, &cfg, &errs, [&b, &e, &l, &f], &diverged);
    Ok(())
}

/// Arguments of `perpend bench speed`.
#[derive(clap::Args, Debug)]
pub struct SpeedArgs {
    /// Repetitions (the median is reported).
    #[arg(long, default_value_t = 201)]
    pub runs: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// Timing results [µs].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpeedReport {
    /// Poses per calibration.
    pub poses: usize,
    /// Sensors calibrated per run.
    pub sensors: usize,
    /// Repetitions.
    pub runs: usize,
    /// Median time of the LM calibration of all sensors [µs].
    pub lsq_us: f64,
    /// Median time of the EKF (f64) over the run of all sensors [µs].
    pub ekf_us: f64,
    /// Same with the EKF in f32 [µs].
    pub ekf_f32_us: f64,
    /// Mean time of one f32 EKF update [ns].
    pub ekf_f32_update_ns: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Measures the calibration times.
///
/// # Errors
/// Simulation or calibration failures.
pub fn speed(runs: usize) -> Result<SpeedReport> {
    let head = paper_head()?;
    let mut rng = StdRng::seed_from_u64(1);
    let data = simulate(&head, &SimConfig::paper(), &[], &mut rng)?;
    let lsq_cfg = LsqConfig::default();
    let ekf_cfg = EkfConfig::chen_simulation();
    let runs = runs.max(1);
    // f32 copy of the run for the board's arithmetic.
    let poses32: Vec<perpend_core::calib::CalPose<f32, 4>> = data
        .poses
        .rows
        .iter()
        .map(|r| perpend_core::calib::CalPose {
            plane: Plane {
                n: r.plane.n.cast(),
                d: r.plane.d as f32,
            },
            readings: [0, 1, 2, 3].map(|i| r.readings[i].map(|x| x as f32)),
            ctx: Context::default(),
        })
        .collect();
    let nominal32: Vec<Sensor<f32>> = head.nominal.iter().map(Sensor::cast).collect();
    let ekf32 = EkfConfig::<f32>::chen_simulation();
    let (mut tl, mut te, mut te32) = (Vec::new(), Vec::new(), Vec::new());
    let mut updates = 0usize;
    for _ in 0..runs {
        let t = Instant::now();
        for (i, s) in head.nominal.iter().enumerate() {
            let f = fit_sensor_base(s, i, &data.poses, &lsq_cfg).map_err(|e| anyhow!("{e}"))?;
            std::hint::black_box(f);
        }
        tl.push(t.elapsed().as_secs_f64() * 1e6);
        let t = Instant::now();
        for (i, s) in head.nominal.iter().enumerate() {
            let f = ekf_sensor(s, i, &data.poses, ekf_cfg).map_err(|e| anyhow!("{e}"))?;
            std::hint::black_box(f);
        }
        te.push(t.elapsed().as_secs_f64() * 1e6);
        let t = Instant::now();
        updates = 0;
        for (i, s) in nominal32.iter().enumerate() {
            let f = ekf_sensor(s, i, poses32.as_slice(), ekf32).map_err(|e| anyhow!("{e}"))?;
            updates += f.used;
            std::hint::black_box(f);
        }
        te32.push(t.elapsed().as_secs_f64() * 1e6);
    }
    let ekf_f32_us = median(te32);
    Ok(SpeedReport {
        poses: data.poses.rows.len(),
        sensors: head.nominal.len(),
        runs,
        lsq_us: median(tl),
        ekf_us: median(te),
        ekf_f32_us,
        ekf_f32_update_ns: ekf_f32_us * 1e3 / updates.max(1) as f64,
    })
}

fn run_speed(a: &SpeedArgs) -> Result<()> {
    let r = speed(a.runs)?;
    if a.json {
        println!(
            "{}",
            perpend_formats::schema::to_json(perpend_formats::schema::BENCH_SPEED, &r)?
        );
    } else {
        println!(
            "calibration of {} sensors from {} poses, median of {} runs{}:",
            r.sensors,
            r.poses,
            r.runs,
            if cfg!(debug_assertions) {
                " (debug build: use --release for real figures)"
            } else {
                ""
            }
        );
        println!("  LM (f64)          {:>10.1} µs", r.lsq_us);
        println!("  EKF (f64)         {:>10.1} µs", r.ekf_us);
        println!(
            "  EKF (f32)         {:>10.1} µs  ({:.0} ns per update)",
            r.ekf_f32_us, r.ekf_f32_update_ns
        );
    }
    Ok(())
}

/// Arguments of `perpend bench ident`.
#[derive(clap::Args, Debug)]
pub struct IdentArgs {
    /// Seeds per pose spread.
    #[arg(long, default_value_t = 5)]
    pub seeds: u64,
}

/// One row of the sensitivity study.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IdentRow {
    /// Tilt range about x of the calibration poses [deg].
    pub tilt_x: f64,
    /// Tilt range about y [deg].
    pub tilt_y: f64,
    /// Standoff range [mm].
    pub standoff: f64,
    /// Largest condition number over sensors and seeds.
    pub condition: f64,
    /// Smallest per-sensor reading range over sensors and seeds [mm].
    pub reading_range_mm: f64,
    /// Median over sensors/seeds of the largest 1σ of the across-beam
    /// zero-point components [mm].
    pub sigma_zero_mm: f64,
    /// Median of the largest 1σ of the direction tilts [mrad].
    pub sigma_dir_mrad: f64,
    /// Mean normal error with the LSQ head / with the true head, on test
    /// planes from the paper spread.
    pub ratio: f64,
}

/// Runs the calibration for one spread (identifiability not enforced) and
/// evaluates it on test planes of the paper spread.
///
/// # Errors
/// Simulation failures.
pub fn ident_row(tilt_x: f64, tilt_y: f64, standoff: f64, seeds: u64) -> Result<IdentRow> {
    let head = paper_head()?;
    let mut cal = SimConfig::paper();
    cal.spread.tilt_x_range_deg = tilt_x;
    cal.spread.tilt_y_range_deg = tilt_y;
    cal.spread.standoff_range_mm = standoff;
    let lsq = LsqConfig {
        thresholds: Thresholds {
            max_condition: f64::INFINITY,
            ..Thresholds::default()
        },
        ..LsqConfig::default()
    };
    let test = PoseSpread::paper();
    let truth = head4(&head.truth)?;
    let (mut kmax, mut sz, mut sd) = (0f64, Vec::new(), Vec::new());
    let mut rmin = f64::INFINITY;
    let (mut el, mut ef) = (0.0, 0.0);
    for seed in 1..=seeds {
        let mut rng = StdRng::seed_from_u64(seed);
        let data = simulate(&head, &cal, &[], &mut rng)?;
        let mut fitted = Vec::new();
        for (i, s) in head.nominal.iter().enumerate() {
            match fit_sensor_base(s, i, &data.poses, &lsq) {
                Ok(f) => {
                    kmax = kmax.max(f.diagnostic.condition);
                    rmin = rmin.min(f.diagnostic.standoff_range_mm);
                    // Across-beam zero point: σ projected on the tangent
                    // basis of the beam.
                    let (e1, e2) = f.sensor.basis();
                    let c = f.cov.fixed_view::<3, 3>(0, 0);
                    let s1 = (e1.transpose() * c * e1)[0].sqrt();
                    let s2 = (e2.transpose() * c * e2)[0].sqrt();
                    sz.push(s1.max(s2));
                    sd.push(f.sigma[3].max(f.sigma[4]) * 1e3);
                    fitted.push(f.sensor);
                }
                Err(e) => {
                    kmax = f64::INFINITY;
                    fitted.push(*s);
                    let _ = e;
                    sz.push(f64::INFINITY);
                    sd.push(f64::INFINITY);
                }
            }
        }
        let h = head4(&fitted)?;
        for t in 0..20 {
            let p = test.draw(&mut rng);
            let r = test_readings(&head, &cal, &p, t, &mut rng);
            if r.iter().any(Option::is_none) {
                continue;
            }
            el += normal_error(&h, &r, &p)?;
            ef += normal_error(&truth, &r, &p)?;
        }
    }
    Ok(IdentRow {
        tilt_x,
        tilt_y,
        standoff,
        condition: kmax,
        reading_range_mm: rmin,
        sigma_zero_mm: median(sz),
        sigma_dir_mrad: median(sd),
        ratio: el / ef,
    })
}

fn run_ident(a: &IdentArgs) -> Result<()> {
    println!("identifiability vs calibration pose spread (paper head, ζ = 0.01 mm, ξ = 0.02 mm, 100 poses, {} seeds)", a.seeds);
    println!("test planes: paper spread; ratio = mean normal error LSQ head / true head");
    println!();
    println!("tilt x [°]  tilt y [°]  standoff [mm]  min reading range [mm]  max condition  σ zero⊥ [mm]  σ dir [mrad]  ratio");
    let mut grid: Vec<(f64, f64, f64)> = Vec::new();
    for t in [0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0] {
        grid.push((t, t, PAPER_STANDOFF_RANGE_MM));
    }
    for t in [0.0, 0.4, 1.0, 3.0] {
        grid.push((t, PAPER_TILT_RANGE_DEG, PAPER_STANDOFF_RANGE_MM));
    }
    for s in [0.0, 1.0, 2.0, 3.0, 5.0, 10.0] {
        grid.push((PAPER_TILT_RANGE_DEG, PAPER_TILT_RANGE_DEG, s));
    }
    for s in [0.0, 1.0, 2.0, 3.0, 5.0] {
        grid.push((3.0, 3.0, s));
    }
    for (tx, ty, s) in grid {
        let r = ident_row(tx, ty, s, a.seeds)?;
        println!(
            "{:>10.1}  {:>10.1}  {:>13.1}  {:>22.1}  {:>13.2e}  {:>12.4}  {:>12.3}  {:>5.3}",
            r.tilt_x,
            r.tilt_y,
            r.standoff,
            r.reading_range_mm,
            r.condition,
            r.sigma_zero_mm,
            r.sigma_dir_mrad,
            r.ratio
        );
    }
    Ok(())
}

/// Runs `perpend bench`.
///
/// # Errors
/// Those of the benchmarks.
pub fn run(a: &Args) -> Result<()> {
    match &a.what {
        Bench::Accuracy(x) => run_accuracy(x),
        Bench::Speed(x) => run_speed(x),
        Bench::Ident(x) => run_ident(x),
        Bench::Diagnose(x) => crate::diagnose::blind::run(x),
        Bench::DiagnoseSelf(x) => crate::diagnose::bench::run(x),
        Bench::Plan(x) => perpend_calib::plan::run_bench(x),
        Bench::Curvature(x) => perpend_calib::curvature::run(x),
        Bench::Frames(x) => perpend_calib::frames::bench::run(x),
    }
}

/// Readings of test plane `t` (no effects), drawn like any pose.
fn test_readings(
    head: &SimHead,
    cfg: &SimConfig,
    plane: &Plane<f64>,
    t: usize,
    rng: &mut StdRng,
) -> Vec<Option<f64>> {
    readings(
        head,
        cfg,
        &[],
        plane,
        Moment {
            pose: t,
            ..Moment::default()
        },
        rng,
    )
}
