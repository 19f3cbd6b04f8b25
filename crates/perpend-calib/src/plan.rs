//! Pose planning: the fewest datum-plane poses that identify a head.
//!
//! Chen §5 calibrates from 100 random poses of the datum plane; each is a
//! robot move and a laser-tracker shot. Each sensor's 5 parameters (zero
//! point, beam direction in its tangent plane) are fitted separately by
//! least squares, so the information pose `k` gives about sensor `i` is
//! `J_ik J_ikᵀ`, `J_ik` the gradient of the reading (Chen eq. 7-9 in the
//! 5-DOF form, [`perpend_core::model::jacobian`]) at the nominal head. The
//! plan maximises the D-criterion of the head,
//! `Σ_i log det(Σ_k J_ik J_ikᵀ)` (the volume of every sensor's confidence
//! ellipsoid, independent of the units of the parameters), over a grid of
//! reachable poses: tilt about x and about y within ±`tilt_max` of the
//! centre orientation (the rectangle a robot programmer sets, the same as
//! [`PoseSpread`]) on 7 levels each, and the standoff on 3 levels of its
//! range. Greedy selection of distinct poses, then Fedorov exchange passes
//! until no swap raises the criterion. Only poses where every beam meets
//! the plane in front of the sensor are candidates.
//!
//! The expected accuracy is measured, not propagated: the plan is
//! simulated `draws` times with the nominal head as truth, the reading
//! noise and the tracker (the tracker's plane error is shared by the
//! sensors of a pose, which a per-sensor covariance would miss, see
//! [`crate::accuracy`]), calibrated by least squares, and each calibrated
//! head measures test planes of the same spread; the parameters' 1σ are
//! the spread of the fits and the normal error is compared with what the
//! true head achieves on the same readings (the floor).
//!
//! Refusals: the paper's model has `DOF` = 5 parameters per sensor and a
//! pose gives one reading per sensor, so no plan of fewer than `DOF + 1`
//! poses (the least-squares fit wants one reading more than its unknowns)
//! calibrates; the minimum of a reach ([`min_poses`]) is the smallest
//! count whose D-optimal design every sensor's estimator accepts (full
//! rank, scaled condition within [`Thresholds::max_condition`], judged by
//! [`assess`] on the planned poses). `perpend plan` refuses fewer poses,
//! refuses a plan of which any simulated calibration fails, and warns when
//! the declared reading noise is not a laser sensor's ([`SIGMA_PLAUSIBLE_MM`]).
//!
//! Limits: the design is local (the gradients at the nominal head: a head
//! whose errors are far larger than the paper's changes them little); it
//! plans for the paper's model, not for an extension (a thermal or drift
//! term wants time and temperature spread, which a pose plan cannot give);
//! the grid is the reachable set, so a robot that reaches only part of the
//! rectangle needs a smaller `tilt_max`.

use anyhow::{anyhow, bail, Result};
use nalgebra::{SMatrix, Vector3};
use perpend_core::calib::{assess, fit_sensor_base, LsqConfig, Status, Thresholds};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::{Head4, Sensor, DOF};
use perpend_core::model::{distance, jacobian};
use perpend_core::normal::{plane, Method};
use rand::rngs::StdRng;
use rand::SeedableRng;
use serde::Serialize;

use crate::calibrate::angle_deg;
use crate::sim::{readings, Moment, PoseSpread, SimConfig, SimHead};
use perpend_formats::exchange::{PoseRow, PoseTable};

type Info = SMatrix<f64, DOF, DOF>;

/// One planned pose (defined beside the simulator that presents it, so
/// that `frames::plan` can use it without importing this module).
pub use crate::sim::PlannedPose;

/// The reachable poses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reach {
    /// Centre orientation (θ1, θ2) [deg].
    pub center_deg: (f64, f64),
    /// Half-range of each tilt about the centre [deg].
    pub tilt_max_deg: f64,
    /// Standoff range [mm].
    pub standoff_mm: (f64, f64),
}

impl Reach {
    /// The reach of a [`PoseSpread`] (the same rectangle).
    pub fn of(s: &PoseSpread) -> Self {
        Self {
            center_deg: (s.center_tilt_x_deg, s.center_tilt_y_deg),
            tilt_max_deg: 0.5 * s.tilt_x_range_deg.min(s.tilt_y_range_deg),
            standoff_mm: (
                s.standoff_mm - 0.5 * s.standoff_range_mm,
                s.standoff_mm + 0.5 * s.standoff_range_mm,
            ),
        }
    }

    /// The candidate grid: 7 × 7 tilts × 3 standoffs, keeping the poses
    /// every sensor of `head` sees.
    pub fn grid(&self, head: &[Sensor<f64>]) -> Vec<PlannedPose> {
        let lv = |lo: f64, hi: f64, n: usize| -> Vec<f64> {
            (0..n)
                .map(|j| lo + (hi - lo) * j as f64 / (n - 1) as f64)
                .collect()
        };
        let t = self.tilt_max_deg;
        let (cx, cy) = self.center_deg;
        let mut out = Vec::new();
        for tx in lv(cx - t, cx + t, 7) {
            for ty in lv(cy - t, cy + t, 7) {
                for s in lv(self.standoff_mm.0, self.standoff_mm.1, 3) {
                    let p = PlannedPose {
                        tilt_x_deg: tx,
                        tilt_y_deg: ty,
                        standoff_mm: s,
                    };
                    let pl = p.plane();
                    if head
                        .iter()
                        .enumerate()
                        .all(|(i, x)| distance(x, &pl, i).is_ok())
                    {
                        out.push(p);
                    }
                }
            }
        }
        out
    }
}

/// Information `J Jᵀ` of each sensor of `head` from pose `p`.
fn info(head: &[Sensor<f64>], p: &PlannedPose) -> Option<Vec<Info>> {
    let pl = p.plane();
    head.iter()
        .enumerate()
        .map(|(i, s)| jacobian(s, &pl, i).ok().map(|(_, j)| j * j.transpose()))
        .collect()
}

/// `Σ_i log det(M_i)` (−∞ when a sensor is not identified).
fn criterion(m: &[Info]) -> f64 {
    m.iter()
        .map(|x| {
            let d = x.determinant();
            if d > 0.0 {
                d.ln()
            } else {
                f64::NEG_INFINITY
            }
        })
        .sum()
}

fn sum(infos: &[Vec<Info>], pick: &[usize], n_sensors: usize, ridge: f64) -> Vec<Info> {
    let mut m = vec![Info::identity() * ridge; n_sensors];
    for &k in pick {
        for (acc, x) in m.iter_mut().zip(&infos[k]) {
            *acc += x;
        }
    }
    m
}

/// The D-optimal choice of `n` distinct poses of `reach` for `head`
/// (module docs).
///
/// # Errors
/// Fewer reachable poses than asked, or not more poses than parameters
/// per sensor ([`min_poses`] gives the count that identifies the head).
pub fn plan(head: &[Sensor<f64>], reach: &Reach, n: usize) -> Result<Vec<PlannedPose>> {
    if n <= DOF {
        bail!(
            "{n} poses cannot identify {DOF} parameters per sensor: plan at least {} \
             (8 or more in practice)",
            DOF + 1
        );
    }
    let cands = reach.grid(head);
    let infos: Vec<Vec<Info>> = cands.iter().filter_map(|p| info(head, p)).collect();
    if infos.len() < n {
        bail!(
            "only {} reachable poses in ±{}° and {:.1}-{:.1} mm: ask for fewer or widen the reach",
            infos.len(),
            reach.tilt_max_deg,
            reach.standoff_mm.0,
            reach.standoff_mm.1
        );
    }
    let ns = head.len();
    // Greedy, with a small ridge so that the first poses can be compared.
    let mut pick: Vec<usize> = Vec::with_capacity(n);
    while pick.len() < n {
        let best = (0..infos.len())
            .filter(|k| !pick.contains(k))
            .map(|k| {
                let mut t = pick.clone();
                t.push(k);
                (k, criterion(&sum(&infos, &t, ns, 1e-9)))
            })
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(k, _)| k)
            .ok_or_else(|| anyhow!("no candidate left"))?;
        pick.push(best);
    }
    exchange(&infos, &mut pick, ns);
    Ok(pick.into_iter().map(|k| cands[k]).collect())
}

/// Fedorov exchange: swap a chosen pose for an unused one while that
/// raises the criterion (at most 20 passes).
fn exchange(infos: &[Vec<Info>], pick: &mut [usize], ns: usize) {
    let mut best = criterion(&sum(infos, pick, ns, 0.0));
    for _ in 0..20 {
        let mut improved = false;
        for j in 0..pick.len() {
            for k in 0..infos.len() {
                if pick.contains(&k) {
                    continue;
                }
                let old = pick[j];
                pick[j] = k;
                let c = criterion(&sum(infos, pick, ns, 0.0));
                if c > best + 1e-9 {
                    best = c;
                    improved = true;
                } else {
                    pick[j] = old;
                }
            }
        }
        if !improved {
            break;
        }
    }
}

/// Reading noise (1σ) [mm] a laser triangulation sensor can declare: from
/// 0.1 µm (the best confocal sensors) to 0.1 mm (the coarsest
/// triangulation sensors over a 100 mm range). Outside, the value is most
/// likely in another unit (10 typed for 10 µm).
pub const SIGMA_PLAUSIBLE_MM: (f64, f64) = (1e-4, 0.1);

/// The warning for a declared reading noise `sigma_mm` outside
/// [`SIGMA_PLAUSIBLE_MM`], `source` naming where it was declared.
pub fn sigma_warning(sigma_mm: f64, source: &str) -> Option<String> {
    let (lo, hi) = SIGMA_PLAUSIBLE_MM;
    if (lo..=hi).contains(&sigma_mm) {
        return None;
    }
    let hint = if sigma_mm > hi {
        format!(
            "micrometres typed into a millimetre column? {sigma_mm} µm = {} mm",
            sigma_mm / 1000.0
        )
    } else {
        "metres or a typo?".to_string()
    };
    Some(format!(
        "declared reading noise σ = {sigma_mm} mm ({source}) is not a laser sensor's ({lo}-{hi} mm): \
         {hint}; the expected figures below assume it"
    ))
}

/// The smallest number of poses of `reach` whose D-optimal plan every
/// sensor of `head` can be calibrated from, and the worst sensor's scaled
/// condition number there (module docs). Searched from `DOF + 1` up to
/// `cap` poses.
///
/// # Errors
/// No count up to `cap` (or up to the reachable poses) identifies the head:
/// the reach is too narrow.
pub fn min_poses(head: &[Sensor<f64>], reach: &Reach, cap: usize) -> Result<(usize, f64)> {
    let th = Thresholds::<f64>::default();
    let reachable = reach.grid(head).len();
    let mut last = f64::INFINITY;
    for n in DOF + 1..=cap.min(reachable) {
        let planes: Vec<Plane<f64>> = plan(head, reach, n)?
            .iter()
            .map(PlannedPose::plane)
            .collect();
        let table = exact_table(head, &planes);
        let mut worst = 0.0_f64;
        let mut ok = true;
        for (i, s) in head.iter().enumerate() {
            match assess(s, i, &table, &th) {
                Ok(d) if d.status != Status::NotIdentifiable => worst = worst.max(d.condition),
                Ok(d) => {
                    ok = false;
                    worst = worst.max(d.condition);
                }
                Err(_) => ok = false,
            }
        }
        if ok {
            return Ok((n, worst));
        }
        last = worst;
    }
    bail!(
        "no plan of up to {} poses in ±{}° and {:.1}-{:.1} mm identifies every sensor \
         (condition {last:.1e}, limit {:.0e}): widen --tilt-max or --standoff",
        cap.min(reachable),
        reach.tilt_max_deg,
        reach.standoff_mm.0,
        reach.standoff_mm.1,
        th.max_condition
    )
}

/// Noise-free readings of `head` on `planes` (what [`assess`] judges).
fn exact_table(head: &[Sensor<f64>], planes: &[Plane<f64>]) -> PoseTable {
    let sim = SimHead {
        name: "nominal".into(),
        nominal: head.to_vec(),
        truth: head.to_vec(),
        sigma_mm: None,
        standoff_mm: 0.0,
    };
    let mut cfg = SimConfig::paper();
    cfg.zeta_mm = 0.0;
    cfg.tracker = None;
    cfg.dropout = 0.0;
    cfg.range_mm = None;
    simulate_on(&sim, &cfg, planes, &mut StdRng::seed_from_u64(0))
}

/// What a plan is expected to give, from simulated calibrations.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Expected {
    /// Simulated calibrations that succeeded / were run.
    pub ok: usize,
    /// Simulated calibrations run.
    pub draws: usize,
    /// Per sensor: 1σ of the zero point [mm] (x, y, z).
    pub sigma_zero_mm: Vec<[f64; 3]>,
    /// Per sensor: 1σ of the beam direction [mrad] (its tangent angles).
    pub sigma_dir_mrad: Vec<f64>,
    /// Mean normal error on test planes after calibration [deg].
    pub lsq_mean_deg: f64,
    /// 95th percentile of it [deg].
    pub lsq_p95_deg: f64,
    /// The same with the true head (the floor) [deg].
    pub floor_mean_deg: f64,
}

/// Simulated calibration run of `truth` on the planes `planes`.
pub fn simulate_on(
    head: &SimHead,
    cfg: &SimConfig,
    planes: &[Plane<f64>],
    rng: &mut StdRng,
) -> PoseTable {
    let rows = planes
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let r = readings(
                head,
                cfg,
                &[],
                p,
                Moment {
                    pose: k,
                    ..Moment::default()
                },
                rng,
            );
            let measured = cfg.tracker.map_or(*p, |t| t.measure(p, rng));
            PoseRow {
                line: 0,
                pose: k as i64 + 1,
                abcd: [measured.n.x, measured.n.y, measured.n.z, measured.d],
                plane: measured,
                readings: r,
                t_s: None,
                temp_c: None,
                noise: Default::default(),
            }
        })
        .collect();
    PoseTable {
        n_sensors: head.truth.len(),
        rows,
    }
}

fn head4(s: &[Sensor<f64>]) -> Result<Head4<f64>> {
    let a: [Sensor<f64>; 4] = s
        .to_vec()
        .try_into()
        .map_err(|_| anyhow!("planning evaluates four-sensor heads"))?;
    Ok(Head4::new(a))
}

/// Normal error [deg] of `h` on readings `r` of `truth` (Chen eq. 18-19).
fn normal_err(h: &Head4<f64>, r: &[Option<f64>], truth: &Plane<f64>) -> Option<f64> {
    let r4 = [*r.first()?, *r.get(1)?, *r.get(2)?, *r.get(3)?];
    let fit = plane(h, &r4, &Context::default(), Method::Chen).ok()?;
    let n: Vector3<f64> = if truth.n.z < 0.0 { truth.n } else { -truth.n };
    Some(angle_deg(&fit.normal, &n))
}

/// Simulates `draws` calibrations of `head` on `planes` (noise and tracker
/// of `cfg`), each evaluated on 20 test planes drawn from `test`.
/// `seeds`: (calibration noise, test planes and their noise): the same
/// test seed gives the same test planes whatever the plan, so plans are
/// compared on the same readings.
///
/// # Errors
/// A head that is not four sensors.
pub fn evaluate(
    head: &SimHead,
    cfg: &SimConfig,
    planes: &[Plane<f64>],
    test: &PoseSpread,
    draws: usize,
    seeds: (u64, u64),
    lsq: &LsqConfig<f64>,
) -> Result<Expected> {
    let truth4 = head4(&head.truth)?;
    let ns = head.truth.len();
    let (mut lsq_err, mut floor_err) = (Vec::new(), Vec::new());
    let mut dz: Vec<Vec<[f64; 3]>> = vec![Vec::new(); ns];
    let mut da: Vec<Vec<f64>> = vec![Vec::new(); ns];
    let mut ok = 0;
    for d in 0..draws {
        let mut rng = StdRng::seed_from_u64(seeds.0.wrapping_mul(1000).wrapping_add(d as u64));
        let table = simulate_on(head, cfg, planes, &mut rng);
        let fits: Option<Vec<Sensor<f64>>> = head
            .nominal
            .iter()
            .enumerate()
            .map(|(i, s)| fit_sensor_base(s, i, &table, lsq).ok().map(|f| f.sensor))
            .collect();
        let Some(fits) = fits else { continue };
        ok += 1;
        for (i, (f, t)) in fits.iter().zip(&head.truth).enumerate() {
            let e = f.zero - t.zero;
            dz[i].push([e.x, e.y, e.z]);
            da[i].push(angle_deg(&f.dir, &t.dir).to_radians() * 1000.0);
        }
        let cal = head4(&fits)?;
        let mut tcfg = *cfg;
        tcfg.dropout = 0.0;
        let mut rng = StdRng::seed_from_u64(seeds.1.wrapping_mul(1000).wrapping_add(d as u64));
        for t in 0..20 {
            let p = test.draw(&mut rng);
            let r = readings(
                head,
                &tcfg,
                &[],
                &p,
                Moment {
                    pose: t,
                    ..Moment::default()
                },
                &mut rng,
            );
            if let (Some(a), Some(b)) = (normal_err(&cal, &r, &p), normal_err(&truth4, &r, &p)) {
                lsq_err.push(a);
                floor_err.push(b);
            }
        }
    }
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    Ok(Expected {
        ok,
        draws,
        sigma_zero_mm: dz
            .iter()
            .map(|v| {
                let c = |j: usize| rms(&v.iter().map(|x| x[j]).collect::<Vec<_>>());
                [c(0), c(1), c(2)]
            })
            .collect(),
        sigma_dir_mrad: da.iter().map(|v| rms(v)).collect(),
        lsq_mean_deg: crate::stats::mean(&lsq_err),
        lsq_p95_deg: crate::stats::quantile(&lsq_err, 0.95),
        floor_mean_deg: crate::stats::mean(&floor_err),
    })
}

/// One row of `perpend bench plan`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BenchRow {
    /// Calibration poses.
    pub poses: usize,
    /// Mean normal error after least-squares calibration [deg].
    pub lsq_mean_deg: f64,
    /// Mean normal error of the true head on the same readings [deg].
    pub floor_mean_deg: f64,
    /// Calibrations that failed (pose set not identifying the head).
    pub failed: usize,
}

/// `perpend bench plan --json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BenchPlan {
    /// D-optimal poses of the paper's spread.
    pub planned: Vec<BenchRow>,
    /// Random poses of the same spread (Chen §5).
    pub random: Vec<BenchRow>,
    /// The smallest planned pose count whose error is within 1.10× the
    /// floor of 100 random poses, if any.
    pub planned_poses_to_goal: Option<usize>,
}

/// Pose counts of the bench.
pub const BENCH_COUNTS: [usize; 7] = [8, 12, 16, 20, 30, 50, 100];

/// The paper's simulation (Table 2 head, ζ = 0.01 mm, tracker ξ = 0.02 mm,
/// 20 test planes per seed) calibrated from planned and from random poses
/// of [`PoseSpread::paper`], `seeds` seeds each.
///
/// # Errors
/// Planning or simulation failures.
pub fn bench(seeds: usize) -> Result<BenchPlan> {
    let head = crate::sim::paper_head()?;
    let cfg = SimConfig::paper();
    let spread = PoseSpread::paper();
    let lsq = LsqConfig::default();
    let reach = Reach::of(&spread);
    let bar =
        perpend_formats::progress::Progress::new((2 * BENCH_COUNTS.len()) as u64, "bench plan");
    let row = |n: usize, planes_of: &dyn Fn(u64) -> Result<Vec<Plane<f64>>>| -> Result<BenchRow> {
        bar.inc();
        let (mut l, mut f, mut failed) = (Vec::new(), Vec::new(), 0);
        for s in 0..seeds as u64 {
            let e = evaluate(
                &head,
                &cfg,
                &planes_of(s)?,
                &spread,
                1,
                (7919 * s + n as u64, s),
                &lsq,
            )?;
            failed += e.draws - e.ok;
            if e.ok > 0 {
                l.push(e.lsq_mean_deg);
                f.push(e.floor_mean_deg);
            }
        }
        Ok(BenchRow {
            poses: n,
            lsq_mean_deg: crate::stats::mean(&l),
            floor_mean_deg: crate::stats::mean(&f),
            failed,
        })
    };
    let mut planned = Vec::new();
    let mut random = Vec::new();
    for n in BENCH_COUNTS {
        let p: Vec<Plane<f64>> = plan(&head.nominal, &reach, n)?
            .iter()
            .map(PlannedPose::plane)
            .collect();
        planned.push(row(n, &|_| Ok(p.clone()))?);
        random.push(row(n, &|s| {
            let mut rng = StdRng::seed_from_u64(104_729 * s + n as u64);
            Ok((0..n).map(|_| spread.draw(&mut rng)).collect())
        })?);
    }
    let floor100 = random.last().map_or(0.0, |r| r.floor_mean_deg);
    let planned_poses_to_goal = planned
        .iter()
        .find(|r| r.failed == 0 && r.lsq_mean_deg <= 1.10 * floor100)
        .map(|r| r.poses);
    Ok(BenchPlan {
        planned,
        random,
        planned_poses_to_goal,
    })
}

/// Arguments of `perpend plan`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The nominal head (sensors.csv; its `sigma_mm` is the reading noise
    /// of the simulated calibrations, else --sigma-mm).
    #[arg(long)]
    pub sensors: std::path::PathBuf,
    /// Number of poses to plan.
    #[arg(long, default_value_t = 16)]
    pub n: usize,
    /// Half-range of the tilt about x and about y around the centre [deg].
    #[arg(long, default_value_t = 5.0)]
    pub tilt_max: f64,
    /// Centre orientation θ1,θ2 [deg] (the plane's tilt the robot presents
    /// at the middle of its reach).
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.0], allow_negative_numbers = true)]
    pub center_tilt: Vec<f64>,
    /// Standoff range MIN,MAX [mm]: where the plane crosses the spindle axis.
    #[arg(long, value_delimiter = ',', required = true)]
    pub standoff: Vec<f64>,
    /// Reading noise (1σ) [mm] when sensors.csv has no sigma_mm.
    #[arg(long, default_value_t = 0.01)]
    pub sigma_mm: f64,
    /// Tracker point noise ξ (1σ per coordinate) [mm], 20 points on 150 mm.
    #[arg(long, default_value_t = 0.02)]
    pub xi_mm: f64,
    /// Simulated calibrations behind the expected figures.
    #[arg(long, default_value_t = 20)]
    pub draws: usize,
    /// The plan as CSV (pose, tilts, standoff, plane a,b,c,d_mm).
    #[arg(long, default_value = "plan.csv")]
    pub out: std::path::PathBuf,
    /// Print the plan and its expected figures as JSON.
    #[arg(long)]
    pub json: bool,
    /// Joint angles about the spindle axis per pose (1: none; 4: every
    /// pose also at 90/180/270°), so that a calibration can separate a
    /// tilted tracker from the head: the CSV gets N·n rows and a joint_deg
    /// column; the expected figures are those of the n planned poses
    /// (docs/frames.md).
    #[arg(long, default_value_t = 1)]
    pub reversal: usize,
}

/// Schema of `perpend plan --json` (docs/json.md).
pub const PLAN_SCHEMA: &str = "perpend.plan/1";

/// `perpend plan --json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlanJson {
    /// `perpend.plan/<version>`.
    pub schema: &'static str,
    /// The poses, in the order to visit them.
    pub poses: Vec<PlannedPose>,
    /// Expected figures from simulated calibrations.
    pub expected: Expected,
    /// Where the CSV went.
    pub out: String,
}

/// Runs `perpend plan`.
///
/// # Errors
/// Unreadable or malformed head, impossible reach, fewer poses than the
/// head needs, a simulated calibration that fails, I/O. Nothing is written
/// then.
pub fn run(a: &Args) -> Result<()> {
    let table = perpend_formats::exchange::read_sensors(&a.sensors)?;
    let nominal = table
        .sensors()
        .map_err(|e| anyhow!("{}: {e}", a.sensors.display()))?;
    let reach = reach_of(a)?;
    let declared = table
        .rows
        .iter()
        .filter_map(|r| r.sigma_mm)
        .fold(0.0, f64::max);
    let (zeta, source) = if declared > 0.0 {
        (declared, format!("sigma_mm of {}", a.sensors.display()))
    } else {
        (a.sigma_mm, "--sigma-mm".to_string())
    };
    if let Some(w) = sigma_warning(zeta, &source) {
        eprintln!("warning: {w}");
    }
    let (min, cond) = min_poses(&nominal, &reach, MIN_POSES_CAP.max(a.n))?;
    if a.n < min {
        bail!(
            "{} poses cannot calibrate this head: the model has {DOF} parameters per sensor \
             ({} for {} sensors), one reading per sensor and pose, and the fit needs one reading \
             more than its unknowns; in this reach the planned design identifies every sensor \
             from {min} poses (worst condition {cond:.1e}, limit {:.0e}): use --n {min} or more \
             ({} or more for figures near the floor, `perpend bench plan`)",
            a.n,
            DOF * nominal.len(),
            nominal.len(),
            Thresholds::<f64>::default().max_condition,
            min.max(8)
        );
    }
    let poses = plan(&nominal, &reach, a.n)?;
    let planes: Vec<Plane<f64>> = poses.iter().map(PlannedPose::plane).collect();
    let (head, cfg, test) = simulation(nominal, &reach, zeta, a.xi_mm);
    let lsq = LsqConfig::default();
    let expected = evaluate(&head, &cfg, &planes, &test, a.draws, (1, 2), &lsq)?;
    if expected.ok < expected.draws || expected.draws == 0 {
        bail!(
            "{} of {} simulated calibrations of this plan failed (ζ = {zeta} mm, tracker ξ = {} mm): \
             the {} poses do not identify the head under this noise (the noise-free minimum \
             here is {min}); plan more poses (--n) or a wider reach. Nothing written",
            expected.draws - expected.ok,
            expected.draws,
            a.xi_mm,
            a.n,
        );
    }
    match a.reversal {
        1 => write_csv(&a.out, &poses)?,
        n => crate::frames::plan::write_reversal(&a.out, &poses, n)?,
    }
    if a.json {
        let j = PlanJson {
            schema: PLAN_SCHEMA,
            poses,
            expected,
            out: a.out.display().to_string(),
        };
        println!("{}", serde_json::to_string_pretty(&j)?);
        return Ok(());
    }
    print_report(&poses, &expected, zeta, a, &reach);
    Ok(())
}

/// Largest pose count [`min_poses`] tries when `--n` asks for fewer.
const MIN_POSES_CAP: usize = 40;

/// The reach of `perpend plan`'s arguments.
fn reach_of(a: &Args) -> Result<Reach> {
    let (&[s0, s1], &[cx, cy]) = (a.standoff.as_slice(), a.center_tilt.as_slice()) else {
        bail!("--standoff takes MIN,MAX and --center-tilt θ1,θ2: two numbers each");
    };
    let (lo, hi) = (s0.min(s1), s0.max(s1));
    if !(a.tilt_max >= 0.0 && a.tilt_max < 45.0 && hi > lo) {
        bail!(
            "--tilt-max must be in [0, 45) degrees and --standoff MIN,MAX a range with MAX > MIN"
        );
    }
    Ok(Reach {
        center_deg: (cx, cy),
        tilt_max_deg: a.tilt_max,
        standoff_mm: (lo, hi),
    })
}

/// The simulated truth (the nominal head), the noise and the test spread
/// behind a plan's expected figures.
fn simulation(
    nominal: Vec<Sensor<f64>>,
    reach: &Reach,
    zeta_mm: f64,
    xi_mm: f64,
) -> (SimHead, SimConfig, PoseSpread) {
    let (lo, hi) = reach.standoff_mm;
    let head = SimHead {
        name: "nominal".into(),
        nominal: nominal.clone(),
        truth: nominal,
        sigma_mm: None,
        standoff_mm: 0.5 * (lo + hi),
    };
    let mut cfg = SimConfig::paper();
    cfg.zeta_mm = zeta_mm;
    cfg.tracker = Some(crate::sim::Tracker {
        xi_mm,
        ..crate::sim::Tracker::paper()
    });
    let test = PoseSpread {
        center_tilt_x_deg: reach.center_deg.0,
        center_tilt_y_deg: reach.center_deg.1,
        tilt_x_range_deg: 2.0 * reach.tilt_max_deg,
        tilt_y_range_deg: 2.0 * reach.tilt_max_deg,
        standoff_mm: 0.5 * (lo + hi),
        standoff_range_mm: hi - lo,
    };
    (head, cfg, test)
}

fn write_csv(path: &std::path::Path, poses: &[PlannedPose]) -> Result<()> {
    let mut s = String::from(
        "# perpend plan: D-optimal datum-plane poses, in the TCS (+z along the feed)\n",
    );
    s.push_str("pose,tilt_x_deg,tilt_y_deg,standoff_mm,a,b,c,d_mm\n");
    for (k, p) in poses.iter().enumerate() {
        let pl = p.plane();
        s.push_str(&format!(
            "{},{:.4},{:.4},{:.4},{:.9},{:.9},{:.9},{:.6}\n",
            k + 1,
            p.tilt_x_deg,
            p.tilt_y_deg,
            p.standoff_mm,
            pl.n.x,
            pl.n.y,
            pl.n.z,
            pl.d
        ));
    }
    std::fs::write(path, s).map_err(|e| anyhow!("{}: {e}", path.display()))
}

fn print_report(poses: &[PlannedPose], e: &Expected, zeta: f64, a: &Args, r: &Reach) {
    println!(
        "plan: {} poses, tilt ±{}° about x and y around ({}, {})°, standoff {}-{} mm → {}",
        poses.len(),
        r.tilt_max_deg,
        r.center_deg.0,
        r.center_deg.1,
        r.standoff_mm.0,
        r.standoff_mm.1,
        a.out.display()
    );
    println!("  pose  tilt x [°]  tilt y [°]  standoff [mm]");
    for (k, p) in poses.iter().enumerate() {
        println!(
            "  {:>4}  {:>10.2}  {:>10.2}  {:>13.2}",
            k + 1,
            p.tilt_x_deg,
            p.tilt_y_deg,
            p.standoff_mm
        );
    }
    println!(
        "expected after calibration ({} of {} simulated calibrations at ζ = {} mm, tracker ξ = {} mm):",
        e.ok, e.draws, zeta, a.xi_mm
    );
    for (i, (z, d)) in e.sigma_zero_mm.iter().zip(&e.sigma_dir_mrad).enumerate() {
        println!(
            "  sensor {}: zero point 1σ {:.4} / {:.4} / {:.4} mm (x/y/z), beam direction 1σ {:.3} mrad",
            i + 1,
            z[0],
            z[1],
            z[2],
            d
        );
    }
    println!(
        "  normal error on planes of the same reach: mean {:.4}°, p95 {:.4}° (perfect calibration: {:.4}°)",
        e.lsq_mean_deg, e.lsq_p95_deg, e.floor_mean_deg
    );
}

/// Arguments of `perpend bench plan`.
#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// Seeds per pose count.
    #[arg(long, default_value_t = 100)]
    pub seeds: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// Runs `perpend bench plan`.
///
/// # Errors
/// Those of [`bench`].
pub fn run_bench(a: &BenchArgs) -> Result<()> {
    let b = bench(a.seeds.max(1))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&b)?);
        return Ok(());
    }
    println!("poses   planned [°]   random [°]   floor [°]   (mean normal error, {} seeds × 20 test planes)", a.seeds);
    for (p, r) in b.planned.iter().zip(&b.random) {
        println!(
            "{:>5}   {:>11.4}   {:>10.4}   {:>9.4}{}",
            p.poses,
            p.lsq_mean_deg,
            r.lsq_mean_deg,
            p.floor_mean_deg,
            if r.failed > 0 {
                format!("   (random: {} failed to identify)", r.failed)
            } else {
                String::new()
            }
        );
    }
    match b.planned_poses_to_goal {
        Some(n) => println!("planned poses reach 1.10× the 100-random-pose floor with {n} poses"),
        None => {
            println!("planned poses do not reach 1.10× the 100-random-pose floor within 100 poses")
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use rand::Rng;

    fn paper() -> (SimHead, Reach) {
        let h = crate::sim::paper_head().unwrap();
        (h, Reach::of(&PoseSpread::paper()))
    }

    #[test]
    fn a_plan_is_distinct_reachable_and_beats_random_sets() {
        let (h, reach) = paper();
        let p = plan(&h.nominal, &reach, 12).unwrap();
        assert_eq!(p.len(), 12);
        for (j, a) in p.iter().enumerate() {
            assert!(p[..j].iter().all(|b| b != a), "pose {j} repeated");
            assert!((a.tilt_x_deg - reach.center_deg.0).abs() <= reach.tilt_max_deg + 1e-9);
            assert!(a.standoff_mm >= reach.standoff_mm.0 - 1e-9);
        }
        let ns = h.nominal.len();
        let crit = |ps: &[PlannedPose]| {
            let infos: Vec<Vec<Info>> = ps.iter().map(|x| info(&h.nominal, x).unwrap()).collect();
            criterion(&sum(&infos, &(0..infos.len()).collect::<Vec<_>>(), ns, 0.0))
        };
        let planned = crit(&p);
        let grid = reach.grid(&h.nominal);
        let mut rng = StdRng::seed_from_u64(5);
        for _ in 0..50 {
            let r: Vec<PlannedPose> = (0..12)
                .map(|_| grid[rng.gen_range(0..grid.len())])
                .collect();
            assert!(planned > crit(&r), "a random set beat the plan");
        }
    }

    #[test]
    fn impossible_requests_are_errors() {
        let (h, reach) = paper();
        assert!(plan(&h.nominal, &reach, 2).is_err());
        assert!(plan(&h.nominal, &reach, 10_000)
            .unwrap_err()
            .to_string()
            .contains("reachable"));
    }

    /// The minimum is where the estimator starts to accept the planned
    /// design: its plan calibrates every simulated draw, and the same plan
    /// without its last pose calibrates none.
    #[test]
    fn the_minimum_calibrates_and_one_pose_less_does_not() {
        let (h, reach) = paper();
        let (n, cond) = min_poses(&h.nominal, &reach, 40).unwrap();
        assert!(n > DOF, "minimum {n} not above the {DOF} parameters");
        assert!(cond <= Thresholds::<f64>::default().max_condition, "{cond}");
        let planes: Vec<Plane<f64>> = plan(&h.nominal, &reach, n)
            .unwrap()
            .iter()
            .map(PlannedPose::plane)
            .collect();
        let (cfg, spread, lsq) = (
            SimConfig::paper(),
            PoseSpread::paper(),
            LsqConfig::default(),
        );
        let e = evaluate(&h, &cfg, &planes, &spread, 4, (3, 4), &lsq).unwrap();
        assert_eq!(e.ok, 4, "the minimum's plan failed a calibration");
        let fewer = evaluate(&h, &cfg, &planes[..n - 1], &spread, 4, (3, 4), &lsq).unwrap();
        assert_eq!(
            fewer.ok,
            0,
            "{} poses calibrated: the minimum is not tight",
            n - 1
        );
    }

    #[test]
    fn a_reach_without_tilt_has_no_minimum() {
        let (h, mut reach) = paper();
        reach.tilt_max_deg = 0.0;
        let e = min_poses(&h.nominal, &reach, 40).unwrap_err().to_string();
        assert!(e.contains("widen --tilt-max"), "{e}");
    }

    #[test]
    fn a_sigma_in_micrometres_is_a_warning_with_the_conversion() {
        let w = sigma_warning(10.0, "sigma_mm").unwrap();
        assert!(w.contains("10 µm = 0.01 mm"), "{w}");
        assert!(sigma_warning(0.01, "sigma_mm").is_none());
        assert!(sigma_warning(1e-6, "--sigma-mm").is_some());
    }

    /// Paired on the same test planes: 12 planned poses calibrate better
    /// than 12 random poses of the same spread, and within 1.2× the floor.
    #[test]
    fn twelve_planned_poses_beat_twelve_random_ones() {
        let (h, reach) = paper();
        let cfg = SimConfig::paper();
        let spread = PoseSpread::paper();
        let lsq = LsqConfig::default();
        let planes: Vec<Plane<f64>> = plan(&h.nominal, &reach, 12)
            .unwrap()
            .iter()
            .map(PlannedPose::plane)
            .collect();
        let (mut p, mut r, mut f) = (0.0, 0.0, 0.0);
        for s in 0..20u64 {
            let e = evaluate(&h, &cfg, &planes, &spread, 1, (s, s), &lsq).unwrap();
            let mut rng = StdRng::seed_from_u64(99 + s);
            let rand: Vec<Plane<f64>> = (0..12).map(|_| spread.draw(&mut rng)).collect();
            let q = evaluate(&h, &cfg, &rand, &spread, 1, (s, s), &lsq).unwrap();
            if e.ok == 1 && q.ok == 1 {
                p += e.lsq_mean_deg;
                r += q.lsq_mean_deg;
                f += e.floor_mean_deg;
            }
        }
        assert!(p < r, "planned {p} random {r}");
        assert!(p < 1.2 * f, "planned {p} floor {f}");
    }
}
