//! The verification pass of a cell run (before and after the push) and of
//! an interim check (`perpend cell check`): at each fresh pose the robot
//! presents the datum plane, the tracker measures it, and the board's own
//! normal (θ1/θ2 of the TPDO mapping 0x2002 sub 1 and 2, one frame per
//! SYNC; Tian eq. 1-3 inverted) is sampled over `samples` SYNCs.
//!
//! Per pose (issue 45): the sample normals are averaged (their sum,
//! normalised), the **error** is the angle between that mean normal and
//! the tracker's plane normal, and the **readings' standard uncertainty**
//! per axis is the scatter of the sample normals about their mean (in the
//! mean's tangent plane) over √samples: what
//! [`perpend_formats::conformity`] decides with. Averaging before the angle
//! keeps the reading noise out of the error's expectation (the mean of
//! per-sample angles is biased by about 1.25σ however many samples).
//!
//! The **floor** is the same statistic for a perfectly calibrated board:
//! the true head (or the calibrated one) reading the true planes with the
//! captures' reading noise, fitted like the board fits them, averaged over
//! the same sample count and compared with the same tracker planes.
//!
//! Every pose's figures go to `verify.csv` (the tracker's and the true
//! plane, the mean normal, its error and uncertainty), hashed into the
//! record, so that the decision can be recomputed from the record alone.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use anyhow::{anyhow, bail, Context as _, Result};
use nalgebra::Vector3;
use perpend_calib::plan::PlannedPose;
use perpend_calib::sim::gauss;
use perpend_core::ext::Context;
use perpend_core::geometry::tangent_basis;
use perpend_core::head::{Head4, Sensor};
use perpend_core::model::distance;
use perpend_core::normal::{plane as fit_plane, Method as FitMethod};
use perpend_formats::conformity::{Decision, Measured, Verdict};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::robot::{abcd, check_cancel, normal_error, Presented, Robot};
use crate::canopen::Nmt;
use crate::node::Node;

/// The board's normal from θ1/θ2 [deg] (Tian eq. 1-3 inverted).
pub fn normal_from_angles(th1: f64, th2: f64) -> nalgebra::Vector3<f64> {
    nalgebra::Vector3::new(-th2.to_radians().tan(), th1.to_radians().tan(), -1.0).normalize()
}

/// The synchronous TPDOs carrying θ1 and θ2 (0x2002 sub 1, 2, together)
/// and the status word (0x2005).
pub fn angle_pdos(node: &mut Node) -> Result<[crate::canopen::pdo::Tpdo; 2]> {
    let tpdos = node.client.read_tpdos(node.id, 4)?;
    let find = |subs: &[(u16, u8)]| {
        tpdos
            .iter()
            .find(|t| {
                let has = |i: u16, s: u8| t.mapped.iter().any(|m| m.index == i && m.sub == s);
                t.valid && t.synchronous() && subs.iter().all(|&(i, s)| has(i, s))
            })
            .cloned()
    };
    match (find(&[(0x2002, 1), (0x2002, 2)]), find(&[(0x2005, 0)])) {
        (Some(a), Some(s)) => Ok([a, s]),
        _ => bail!(
            "{}: no synchronous TPDOs with θ1 and θ2 (0x2002 sub 1, 2, in one) and the status \
             (0x2005); the default TPDOs 1 and 2 have them",
            node.name()
        ),
    }
}

/// The board's normal at one SYNC (θ1/θ2 from one frame); `None` when its
/// status says it has no plane.
fn board_normal(
    node: &mut Node,
    pdos: &[crate::canopen::pdo::Tpdo; 2],
) -> Result<Option<nalgebra::Vector3<f64>>> {
    node.client.sync()?;
    let mut values = std::collections::BTreeMap::new();
    for _ in 0..2 {
        let f = node
            .client
            .wait_for(Duration::from_secs(1), |f| {
                pdos.iter().any(|p| p.cob_id == f.id)
            })?
            .ok_or_else(|| anyhow!("{}: no TPDO after SYNC within 1 s", node.name()))?;
        for p in pdos.iter().filter(|p| p.cob_id == f.id) {
            for (m, v) in p.decode(f.payload()) {
                values.insert((m.index, m.sub), v.as_f64());
            }
        }
    }
    let get = |i, s| values.get(&(i, s)).copied();
    match (get(0x2002, 1), get(0x2002, 2), get(0x2005, 0)) {
        (Some(a), Some(b), Some(st)) if st as u32 & perpend_can::status::NO_PLANE == 0 => {
            Ok(Some(normal_from_angles(a, b)))
        }
        _ => Ok(None),
    }
}

/// Takes every frame waiting from the bus; `true` when a boot-up
/// message of the node was among them (it reset since the last look).
pub fn drain_saw_bootup(node: &mut Node) -> Result<bool> {
    let id = 0x700 + node.id as u16;
    let mut boot = false;
    while let Some((_, f)) = node.client.recv(Duration::ZERO)? {
        boot |= f.id == id && f.len == 1 && f.data[0] == 0 && !f.rtr;
    }
    Ok(boot)
}

/// The error for a node that reset itself (boot-up message) during `what`.
pub fn reset_error(node: &Node, what: &str) -> anyhow::Error {
    anyhow!(
        "{} reset itself during {what} (boot-up message): power or firmware trouble; its \
         readings from before the reset are not trusted, the run stops",
        node.name()
    )
}

/// The board's normals at one pose over `n` SYNCs, and how many SYNCs had
/// no plane.
fn board_normals(
    node: &mut Node,
    pdos: &[crate::canopen::pdo::Tpdo; 2],
    n: usize,
    what: &str,
) -> Result<(Vec<nalgebra::Vector3<f64>>, usize)> {
    let mut out = Vec::with_capacity(n);
    if drain_saw_bootup(node)? {
        return Err(reset_error(node, what));
    }
    for _ in 0..n {
        if let Some(v) = board_normal(node, pdos)? {
            out.push(v);
        }
        // Spread the samples over the board's noise, not one sample twice.
        std::thread::sleep(Duration::from_millis(3));
    }
    let missing = n - out.len();
    Ok((out, missing))
}

/// Default maximum permissible normal error [deg] without `--tolerance-deg`
/// or a cell configuration.
pub const TOLERANCE_DEG: f64 = 0.05;

/// What a verification is decided against: the tolerance and the
/// reference standard (the tracker) with its uncertainty.
#[derive(Debug, Clone)]
pub struct Reference {
    /// Maximum permissible normal error [deg].
    pub tolerance_deg: f64,
    /// The tracker as the record states it.
    pub tracker: perpend_calib::record::Tracker,
    /// Its standard uncertainty per axis of a plane normal [deg].
    pub tracker_u_deg: f64,
    /// Where that figure comes from, in words.
    pub source: String,
    /// The cell configuration read, with its hash.
    pub config: Option<(
        perpend_calib::cellconfig::CellConfig,
        perpend_calib::record::FileHash,
    )>,
}

impl Reference {
    /// From `--config` and `--tolerance-deg` (which wins over the
    /// configuration's); `simulated`: the robot is the virtual board's,
    /// whose tracker then simulates the configured one (else Chen §5's).
    ///
    /// # Errors
    /// A configuration or tolerance refused by physics.
    pub fn new(config: Option<&Path>, tolerance: Option<f64>, simulated: bool) -> Result<Self> {
        use perpend_calib::cellconfig::{self as cc, CellConfig};
        let config = config.map(CellConfig::read).transpose()?;
        let tolerance_deg = tolerance
            .or(config.as_ref().map(|c| c.0.tolerance_deg))
            .unwrap_or(TOLERANCE_DEG);
        cc::check_tolerance(tolerance_deg).context("--tolerance-deg")?;
        let (tracker, source) = match (&config, simulated) {
            (Some((c, f)), _) => (
                c.tracker.clone(),
                format!(
                    "tracker {} (serial {}) as {} states it",
                    c.tracker.model, c.tracker.serial, f.path
                ),
            ),
            (None, true) => (
                cc::paper_tracker("simulated tracker (Chen 2018 §5)"),
                "the simulated tracker's figures (Chen 2018 §5: 20 points, ξ 0.02 mm, 150 mm)"
                    .into(),
            ),
            (None, false) => (
                cc::paper_tracker("not given (no --config)"),
                "assumed, no --config: a tracker like Chen 2018 §5's (20 points, ξ 0.02 mm, \
                 150 mm patch)"
                    .into(),
            ),
        };
        let u = perpend_formats::conformity::tracker_u_rad(
            tracker.xi_mm,
            tracker.points,
            tracker.patch_mm,
        )
        .ok_or_else(|| anyhow!("the tracker's figures give no uncertainty"))?;
        // At zero error a pose passes only when its U (at least the
        // tracker's 2u) is inside the tolerance: below that no run decides.
        if 2.0 * u.to_degrees() >= tolerance_deg {
            bail!(
                "the tolerance {tolerance_deg}° is within the tracker's own expanded uncertainty \
                 U = {:.4}° (k = 2; {source}): no verification can decide it. Nothing was \
                 changed; choose a wider tolerance, or a tracker with more points, a larger \
                 patch or less point noise",
                2.0 * u.to_degrees()
            );
        }
        Ok(Self {
            tolerance_deg,
            tracker_u_deg: u.to_degrees(),
            tracker,
            source,
            config,
        })
    }

    /// The simulated tracker that measures like this one.
    pub fn sim_tracker(&self) -> perpend_calib::sim::Tracker {
        perpend_calib::sim::Tracker {
            xi_mm: self.tracker.xi_mm,
            points: self.tracker.points,
            patch_mm: self.tracker.patch_mm,
        }
    }

    /// The decision of `v` against this reference.
    pub fn decide(&self, v: &Verified) -> perpend_formats::conformity::Decision {
        perpend_formats::conformity::decide(
            &v.measured(),
            self.tolerance_deg,
            self.tracker_u_deg,
            &self.source,
        )
    }
}

/// One verified pose.
#[derive(Debug, Clone)]
pub struct PoseResult {
    /// Pose number (1-based, in the order verified).
    pub pose: i64,
    /// The pose as planned.
    pub planned: PlannedPose,
    /// The planes as presented.
    pub presented: Presented,
    /// The board's mean normal (`None`: no sample had a plane).
    pub mean: Option<Vector3<f64>>,
    /// Samples with a plane.
    pub samples: usize,
    /// Samples whose status said "no plane".
    pub missing: usize,
    /// Angle between the mean normal and the tracker's [deg].
    pub error_deg: Option<f64>,
    /// The readings' standard uncertainty per axis of the mean [deg].
    pub readings_u_deg: Option<f64>,
}

/// What one verification pass measured.
#[derive(Debug, Clone, Default)]
pub struct Verified {
    /// Per pose, in the order verified.
    pub poses: Vec<PoseResult>,
}

impl Verified {
    /// Mean over the poses with a plane of their error [deg].
    pub fn mean_deg(&self) -> f64 {
        let e: Vec<f64> = self.poses.iter().filter_map(|p| p.error_deg).collect();
        e.iter().sum::<f64>() / e.len().max(1) as f64
    }

    /// The poses with a plane, as [`perpend_formats::conformity`] takes them.
    pub fn measured(&self) -> Vec<Measured> {
        self.poses
            .iter()
            .filter_map(|p| {
                Some(Measured {
                    pose: p.pose,
                    error_deg: p.error_deg?,
                    readings_u_deg: p.readings_u_deg?,
                    samples: p.samples,
                })
            })
            .collect()
    }

    /// The planes as presented.
    pub fn seen(&self) -> Vec<Presented> {
        self.poses.iter().map(|p| p.presented).collect()
    }
}

/// The mean of `normals` (oriented like `reference`, summed, normalised)
/// and the standard uncertainty per axis of that mean [rad]: the sample
/// scatter in its tangent plane over √n (`None` for fewer than 2).
pub fn average(
    normals: &[Vector3<f64>],
    reference: &Vector3<f64>,
) -> Option<(Vector3<f64>, Option<f64>)> {
    let sum: Vector3<f64> = normals
        .iter()
        .map(|n| if n.dot(reference) < 0.0 { -n } else { *n })
        .sum();
    let mean = sum.try_normalize(1e-12)?;
    let n = normals.len();
    if n < 2 {
        return Some((mean, None));
    }
    let (e1, e2) = tangent_basis(&mean);
    let var = |e: &Vector3<f64>| {
        let c: Vec<f64> = normals.iter().map(|v| v.dot(e)).collect();
        let m = c.iter().sum::<f64>() / n as f64;
        c.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1) as f64
    };
    let per_axis = ((var(&e1) + var(&e2)) / 2.0).sqrt();
    Some((mean, Some(per_axis / (n as f64).sqrt())))
}

/// One pose's figures from its sample normals.
fn pose_result(
    pose: i64,
    planned: PlannedPose,
    presented: Presented,
    normals: &[Vector3<f64>],
    missing: usize,
) -> PoseResult {
    let avg = average(normals, &presented.tracker.n);
    PoseResult {
        pose,
        planned,
        presented,
        mean: avg.map(|a| a.0),
        samples: normals.len(),
        missing,
        error_deg: avg.map(|a| normal_error(&a.0, &presented.tracker.n)),
        readings_u_deg: avg.and_then(|a| a.1).map(f64::to_degrees),
    }
}

/// The options `cell run` and `cell check` share: the robot, how each
/// fresh pose is measured, and what it is decided against.
#[derive(clap::Args, Debug, Clone)]
pub struct MeasureArgs {
    /// `sim:HOST:PORT` (the virtual board's world channel) or `manual`.
    #[arg(long)]
    pub robot: String,
    /// SYNCs (board samples) per verification pose (at least 2: their
    /// scatter is the readings' share of the uncertainty).
    #[arg(long, default_value_t = 20)]
    pub verify_samples: usize,
    /// How long the robot settles after a move before measuring [ms].
    #[arg(long, default_value_t = 300)]
    pub settle_ms: u64,
    /// Maximum permissible normal error at every fresh pose [deg]
    /// (default: `cell check`: the record's; then the --config file's,
    /// else 0.05).
    #[arg(long)]
    pub tolerance_deg: Option<f64>,
    /// The cell configuration (JSON, docs/record.md): laboratory, site,
    /// operator, approver, tolerance, the tracker (model, serial,
    /// calibration due date, traceability, point noise), for the record
    /// and certificate.
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
}

impl MeasureArgs {
    /// The sampling of a verification pass.
    pub fn sampling(&self) -> Sampling {
        Sampling {
            samples: self.verify_samples,
            settle_ms: self.settle_ms,
        }
    }

    /// Whether the robot is the simulated one.
    pub fn simulated(&self) -> bool {
        self.robot.starts_with("sim:")
    }
}

/// Sampling of one verification pass: SYNCs per pose and settling time.
#[derive(Debug, Clone, Copy)]
pub struct Sampling {
    /// SYNCs (board samples) per pose.
    pub samples: usize,
    /// How long the robot settles after a move [ms].
    pub settle_ms: u64,
}

/// One verification pass over `poses`. The node runs operational during
/// it; the caller's restore returns it to the state found if it stops.
///
/// # Errors
/// Bus, robot, Ctrl-C, a reset of the node, no plane at any pose.
pub fn verify(
    node: &mut Node,
    robot: &mut Robot,
    poses: &[PlannedPose],
    s: Sampling,
    what: &str,
    cancel: &AtomicBool,
) -> Result<Verified> {
    let pdos = angle_pdos(node)?;
    node.client.nmt(node.id, Nmt::Start)?;
    let mut out = Verified::default();
    for (k, pose) in poses.iter().enumerate() {
        check_cancel(cancel, what)?;
        let label = format!("{what}: verification pose {}", k + 1);
        let p = robot.present(&label, pose, cancel)?;
        std::thread::sleep(Duration::from_millis(s.settle_ms));
        let (normals, miss) = board_normals(node, &pdos, s.samples, &label)?;
        out.poses
            .push(pose_result(k as i64 + 1, *pose, p, &normals, miss));
    }
    node.client.nmt(node.id, Nmt::Preop)?;
    let (have, missing): (usize, usize) = out
        .poses
        .iter()
        .fold((0, 0), |(h, m), p| (h + p.samples, m + p.missing));
    if have == 0 {
        bail!(
            "{what}: {} reported no plane at any verification pose",
            node.name()
        );
    }
    if missing > 0 {
        eprintln!(
            "warning: {what}: {missing} of {} samples without a plane, left out",
            have + missing
        );
    }
    Ok(out)
}

/// Appends the pass `pass` of `v` to `verify.csv` at `path` (header
/// first when new).
///
/// # Errors
/// I/O, naming the file.
pub fn write_csv(path: &Path, pass: &str, v: &Verified) -> Result<()> {
    use std::io::Write as _;
    let new = !path.exists();
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("{}: cannot write", path.display()))?;
    let mut text = String::new();
    if new {
        text.push_str(
            "pass,pose,tilt_x_deg,tilt_y_deg,standoff_mm,tracker_a,tracker_b,tracker_c,\
             tracker_d_mm,true_a,true_b,true_c,true_d_mm,mean_nx,mean_ny,mean_nz,samples,\
             missing,error_deg,readings_u_deg\n",
        );
    }
    let opt = |x: Option<f64>| x.map_or(String::new(), |x| format!("{x:.9}"));
    for p in &v.poses {
        let m = p.mean;
        text.push_str(&format!(
            "{pass},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            p.pose,
            p.planned.tilt_x_deg,
            p.planned.tilt_y_deg,
            p.planned.standoff_mm,
            abcd(&p.presented.tracker),
            abcd(&p.presented.truth),
            opt(m.map(|m| m.x)),
            opt(m.map(|m| m.y)),
            opt(m.map(|m| m.z)),
            p.samples,
            p.missing,
            opt(p.error_deg),
            opt(p.readings_u_deg),
        ));
    }
    f.write_all(text.as_bytes())
        .with_context(|| format!("{}: cannot write", path.display()))
}

/// Reads plan.csv (`pose, tilt_x_deg, tilt_y_deg, standoff_mm`, …).
///
/// # Errors
/// Unreadable file, a missing column, a row that is not numbers, fewer
/// than 6 poses.
pub fn read_plan(path: &Path) -> Result<Vec<(i64, PlannedPose)>> {
    let name = path.display().to_string();
    let mut rd = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .from_path(path)
        .with_context(|| format!("{name}: cannot read"))?;
    let header: Vec<String> = rd.headers()?.iter().map(|h| h.trim().into()).collect();
    let col = |c: &str| {
        header
            .iter()
            .position(|h| h == c)
            .ok_or_else(|| anyhow!("{name}: no column '{c}' (write it with `perpend plan`)"))
    };
    let cols = [
        col("pose")?,
        col("tilt_x_deg")?,
        col("tilt_y_deg")?,
        col("standoff_mm")?,
    ];
    let mut out = Vec::new();
    for rec in rd.records() {
        let rec = rec.with_context(|| format!("{name}: unreadable row"))?;
        let line = rec.position().map_or(0, |p| p.line());
        let v: Vec<f64> = cols
            .iter()
            .map(|&c| rec.get(c).and_then(|t| t.trim().parse::<f64>().ok()))
            .collect::<Option<_>>()
            .ok_or_else(|| anyhow!("{name}, line {line}: expected numbers"))?;
        let pose = PlannedPose {
            tilt_x_deg: v[1],
            tilt_y_deg: v[2],
            standoff_mm: v[3],
        };
        out.push((v[0] as i64, pose));
    }
    if out.len() < 6 {
        bail!(
            "{name}: {} poses; a calibration needs at least 6",
            out.len()
        );
    }
    Ok(out)
}

/// `count` random poses inside the bounding box of the plan.
pub fn fresh_poses(plan: &[(i64, PlannedPose)], count: usize, seed: u64) -> Vec<PlannedPose> {
    let range = |f: fn(&PlannedPose) -> f64| {
        plan.iter()
            .map(|(_, p)| f(p))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
                (lo.min(x), hi.max(x))
            })
    };
    let (tx, ty, s) = (
        range(|p| p.tilt_x_deg),
        range(|p| p.tilt_y_deg),
        range(|p| p.standoff_mm),
    );
    let mut rng = StdRng::seed_from_u64(seed);
    let mut draw = |(lo, hi): (f64, f64)| lo + (hi - lo) * rng.gen_range(0.0..=1.0);
    (0..count)
        .map(|_| PlannedPose {
            tilt_x_deg: draw(tx),
            tilt_y_deg: draw(ty),
            standoff_mm: draw(s),
        })
        .collect()
}

/// The decision in one sentence whose figures are the decision's.
pub fn decision_words(d: &Decision) -> String {
    let worst = d
        .poses
        .iter()
        .max_by(|a, b| (a.error_deg + a.expanded_deg).total_cmp(&(b.error_deg + b.expanded_deg)));
    let Some(w) = worst else {
        return format!("{}: no pose verified", d.verdict.word());
    };
    match d.verdict {
        Verdict::Pass => format!(
            "PASS: at every one of {} fresh poses the normal error plus its expanded uncertainty \
             is within the tolerance {}° (largest: pose {}, {:.4}° + {:.4}°, k = {:.2})",
            d.poses.len(),
            d.tolerance_deg,
            w.pose,
            w.error_deg,
            w.expanded_deg,
            w.k
        ),
        Verdict::Fail => {
            let f = d
                .poses
                .iter()
                .find(|p| p.verdict == Verdict::Fail)
                .unwrap_or(w);
            format!(
                "FAIL: at pose {} the normal error {:.4}° minus its expanded uncertainty {:.4}° \
                 (k = {:.2}) exceeds the tolerance {}°",
                f.pose, f.error_deg, f.expanded_deg, f.k, d.tolerance_deg
            )
        }
        Verdict::Inconclusive => format!(
            "INCONCLUSIVE against the tolerance {}°: {}",
            d.tolerance_deg,
            d.decide_by.as_deref().unwrap_or("undecided")
        ),
    }
}

/// A head of four sensors.
///
/// # Errors
/// Another sensor count.
pub fn head4(v: Vec<Sensor<f64>>, what: &str) -> Result<Head4<f64>> {
    let n = v.len();
    let arr: [Sensor<f64>; 4] = v
        .try_into()
        .map_err(|_| anyhow!("{what}: 4 sensors expected, {n} found"))?;
    Ok(Head4::new(arr))
}

/// The floor: the mean over `seen` of the error of `head`'s normal,
/// averaged over `n` samples of the true planes read with noise `sigma`,
/// against the tracker's planes (the statistic of [`verify`]).
///
/// # Errors
/// A beam that misses a plane, a fit that fails.
pub fn floor(
    head: &Head4<f64>,
    seen: &[Presented],
    sigma: f64,
    n: usize,
    seed: u64,
) -> Result<f64> {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x666c_6f6f);
    let mut sum = 0.0;
    for p in seen {
        let mut normals = Vec::with_capacity(n);
        for _ in 0..n {
            let mut r = [None; 4];
            for (i, x) in r.iter_mut().enumerate() {
                let d = distance(&head.sensors[i], &p.truth, i)
                    .map_err(|e| anyhow!("floor: sensor {} misses the plane: {e}", i + 1))?;
                *x = Some(d + sigma * gauss(&mut rng));
            }
            let fit = fit_plane(head, &r, &Context::default(), FitMethod::LeastSquares)
                .map_err(|e| anyhow!("floor: {e}"))?;
            normals.push(fit.normal);
        }
        let (mean, _) =
            average(&normals, &p.tracker.n).ok_or_else(|| anyhow!("floor: no normal"))?;
        sum += normal_error(&mean, &p.tracker.n);
    }
    Ok(sum / seen.len().max(1) as f64)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn angles_give_back_the_normal() {
        let pose = PlannedPose {
            tilt_x_deg: 3.0,
            tilt_y_deg: -2.0,
            standoff_mm: 28.0,
        };
        let n = normal_from_angles(3.0, -2.0);
        assert!(normal_error(&n, &pose.plane().n) < 1e-9);
        assert!(normal_error(&-n, &pose.plane().n) < 1e-9);
    }

    /// The mean of noisy normals converges on the true one, and the
    /// stated uncertainty is the scatter of such means.
    #[test]
    fn the_average_and_its_uncertainty_follow_the_sample_scatter() {
        use rand::Rng;
        let truth = Vector3::new(0.05, -0.02, 1.0).normalize();
        let (e1, e2) = tangent_basis(&truth);
        let sd = 1e-3; // rad per axis
        let mut rng = StdRng::seed_from_u64(7);
        let (mut errs, mut us) = (Vec::new(), Vec::new());
        for _ in 0..400 {
            let normals: Vec<Vector3<f64>> = (0..20)
                .map(|_| {
                    let flip = if rng.gen_bool(0.5) { -1.0 } else { 1.0 };
                    flip * (truth + e1 * sd * gauss(&mut rng) + e2 * sd * gauss(&mut rng))
                        .normalize()
                })
                .collect();
            let (m, u) = average(&normals, &truth).unwrap();
            errs.push((m - truth).dot(&e1));
            us.push(u.unwrap());
        }
        let rms = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
        let u_mean = us.iter().sum::<f64>() / us.len() as f64;
        let expect = sd / 20f64.sqrt();
        assert!((rms / expect - 1.0).abs() < 0.12, "{rms} vs {expect}");
        assert!((u_mean / expect - 1.0).abs() < 0.05, "{u_mean} vs {expect}");
        assert_eq!(average(&[truth], &truth).unwrap().1, None);
        assert!(average(&[], &truth).is_none());
    }

    #[test]
    fn fresh_poses_stay_in_the_plan_box() {
        let p = |x, y, s| PlannedPose {
            tilt_x_deg: x,
            tilt_y_deg: y,
            standoff_mm: s,
        };
        let plan = vec![(1, p(-5.0, -4.0, 26.0)), (2, p(5.0, 4.0, 30.0))];
        for q in fresh_poses(&plan, 50, 3) {
            assert!((-5.0..=5.0).contains(&q.tilt_x_deg));
            assert!((-4.0..=4.0).contains(&q.tilt_y_deg));
            assert!((26.0..=30.0).contains(&q.standoff_mm));
        }
        assert!(Robot::open("robot", 1, perpend_calib::sim::Tracker::paper()).is_err());
    }
}
