//! `perpend cell run --reversal` (issue 36): the head and the cell's frame
//! errors estimated together from a run whose plan turns the head about the
//! spindle axis (`perpend plan --reversal N`, column `joint_deg`).
//!
//! From the run's `poses.csv` (the tracker's planes in the taught TCS and
//! the readings) and the plan's joint angles (by pose number) it runs
//! [`perpend_calib::frames::estimate`], writes the joint head's geometry into
//! `params.json` (what the board gets), and reports each identifiable frame
//! error as estimate ± 1σ in µrad / µm whatever its precision, whether it
//! is significant (beyond 2σ) and resolved (1σ ≤ half the calibration's
//! expected normal error), and the warnings of
//! [`perpend_calib::frames::report`] against that error; the head is
//! corrected for what is significant or resolved; the estimates go into
//! the record (`frames`).
//!
//! Limits: the paper's reading model (no extensions); the verification
//! poses are compared with the tracker's planes corrected by the estimated
//! tracker tilt only through [`corrected`].

use std::collections::HashMap;
use std::path::Path;

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_calib::frames::report::{summarise, FrameEstimates};
use perpend_calib::frames::{estimate, true_plane, FrameFit, FramePose, Frames, Tolerance};
use perpend_core::geometry::Plane;

/// Arguments of `perpend frames`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The nominal head (sensors.csv).
    #[arg(long)]
    pub sensors: std::path::PathBuf,
    /// The run: the tracker's planes and the readings (poses.csv).
    #[arg(long)]
    pub poses: std::path::PathBuf,
    /// The plan with the joint angle of every pose (`perpend plan
    /// --reversal N`: columns pose, joint_deg).
    #[arg(long)]
    pub plan: std::path::PathBuf,
    /// The calibration's expected normal error [deg] (`perpend calibrate`
    /// prints it); a significant frame error larger than it is a warning,
    /// and a 1σ up to half of it counts as resolved. Without it only the
    /// unresolved tracker tilt is warned about, resolved at 1σ ≤ 30 µrad.
    #[arg(long)]
    pub expected_deg: Option<f64>,
    /// One JSON object (`perpend.frames/1`) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `perpend frames`: the joint estimate of a reversal run from its files,
/// offline (what `cell run --reversal` does after its capture).
///
/// # Errors
/// Those of [`read_joints`] and [`estimate_run`].
pub fn run(a: &Args) -> Result<()> {
    let joints = read_joints(&a.plan)?;
    let expected = a.expected_deg.unwrap_or(f64::INFINITY);
    let (fit, summary) = estimate_run(&a.sensors, &a.poses, &joints, expected)?;
    if a.json {
        let mut v = serde_json::to_value(&summary)?;
        v["residual_rms_mm"] = serde_json::json!(fit.rms_mm);
        println!(
            "{}",
            crate::schema::tagged_pretty(crate::schema::FRAMES, &v)
        );
        return Ok(());
    }
    for l in perpend_calib::frames::report::lines(&summary) {
        println!("{l}");
    }
    println!("residual RMS of the joint fit: {:.4} mm", fit.rms_mm);
    if a.expected_deg.is_none() {
        println!(
            "(no --expected-deg: significant frame errors are not weighed against the calibration)"
        );
    }
    Ok(())
}

/// The joint angle [deg] of every pose of `plan` (column `joint_deg` of
/// `perpend plan --reversal`), by pose number.
///
/// # Errors
/// Unreadable plan, no `joint_deg` column (a plan without reversal), a
/// non-number.
pub fn read_joints(plan: &Path) -> Result<HashMap<i64, f64>> {
    let name = plan.display().to_string();
    let mut rd = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .from_path(plan)
        .with_context(|| format!("{name}: cannot read"))?;
    let header: Vec<String> = rd.headers()?.iter().map(|h| h.trim().into()).collect();
    let col = |c: &str| header.iter().position(|h| h == c);
    let (Some(pose), Some(joint)) = (col("pose"), col("joint_deg")) else {
        bail!("{name}: no joint_deg column: --reversal needs a plan that turns the head about the spindle axis (perpend plan --reversal 4)");
    };
    let mut out = HashMap::new();
    for rec in rd.records() {
        let rec = rec.with_context(|| format!("{name}: unreadable row"))?;
        let num = |c: usize| rec.get(c).and_then(|t| t.trim().parse::<f64>().ok());
        let (Some(p), Some(j)) = (num(pose), num(joint)) else {
            let line = rec.position().map_or(0, |p| p.line());
            bail!("{name}, line {line}: pose and joint_deg must be numbers");
        };
        out.insert(p as i64, j);
    }
    Ok(out)
}

/// The joint estimate of a run: `sensors` (nominal), `poses` (poses.csv),
/// the plan's joint angles, against `expected_deg`.
///
/// # Errors
/// Unreadable files, a pose without a joint angle, the estimate's.
pub fn estimate_run(
    sensors: &Path,
    poses: &Path,
    joints: &HashMap<i64, f64>,
    expected_deg: f64,
) -> Result<(FrameFit, FrameEstimates)> {
    let nominal = perpend_formats::exchange::read_sensors(sensors)?
        .sensors()
        .map_err(|e| anyhow!("{}: {e}", sensors.display()))?;
    let table = perpend_formats::exchange::read_poses(poses, Some(nominal.len()))?;
    let mut fp = Vec::new();
    let mut readings = Vec::new();
    let mut used = Vec::new();
    for r in &table.rows {
        let j = joints.get(&r.pose).copied().ok_or_else(|| {
            anyhow!(
                "pose {} of {} is not in the plan: capture and plan must match",
                r.pose,
                poses.display()
            )
        })?;
        fp.push(FramePose::seen(&r.plane, j.to_radians()));
        readings.push(r.readings.clone());
        used.push(j);
    }
    let tol = Tolerance::expected(expected_deg);
    let fit = estimate(&nominal, &fp, &readings, Some(tol)).context("the frame estimate")?;
    let summary = summarise(&fit, &used, expected_deg);
    Ok((fit, summary))
}

/// Writes the joint head's geometry into the parameter file `params`
/// (other fields as the calibration wrote them).
///
/// # Errors
/// Unreadable parameter file, a sensor count that differs, I/O.
pub fn apply_head(params: &Path, fit: &FrameFit) -> Result<()> {
    let mut f = perpend_formats::paramfile::ParamFile::read(params)?;
    if f.sensors.len() != fit.head.len() {
        bail!(
            "{}: {} sensors, the frame estimate has {}",
            params.display(),
            f.sensors.len(),
            fit.head.len()
        );
    }
    for (p, s) in f.sensors.iter_mut().zip(&fit.head) {
        p.zero_mm = [s.zero.x, s.zero.y, s.zero.z];
        p.dir = [s.dir.x, s.dir.y, s.dir.z];
    }
    f.write(params)
}

/// The tracker's plane `tracker` (taught TCS, last joint at `joint_deg`)
/// corrected by the estimated frame errors: what the head really saw.
pub fn corrected(tracker: &Plane<f64>, joint_deg: f64, frames: &Frames) -> Plane<f64> {
    true_plane(&FramePose::seen(tracker, joint_deg.to_radians()), frames)
}

/// The simulated robot's last joint during a `--reversal` run: the plan's
/// joint angles, the one of the pose being presented, and the frame errors
/// estimated so far (the verification compares with corrected planes).
#[derive(Debug, Clone, Default)]
pub struct Turns {
    joints: HashMap<i64, f64>,
    current_deg: f64,
    frames: Frames,
}

impl Turns {
    /// The plan's joint angles ([`read_joints`]).
    pub fn new(joints: HashMap<i64, f64>) -> Self {
        Self {
            joints,
            ..Self::default()
        }
    }

    /// Whether the run turns the head (`--reversal`).
    pub fn active(&self) -> bool {
        !self.joints.is_empty()
    }

    /// The plan's joint angles.
    pub fn joints(&self) -> &HashMap<i64, f64> {
        &self.joints
    }

    /// Selects the joint angle of plan pose `pose` (`None`: 0°, the
    /// verification poses).
    pub fn select(&mut self, pose: Option<i64>) {
        self.current_deg = pose
            .and_then(|k| self.joints.get(&k).copied())
            .unwrap_or(0.0);
    }

    /// The world-channel line presenting `seen` (the plane in the TCS after
    /// the turn): `move BASE J` when turned, else `plane A,B,C,D`.
    pub fn command(&self, seen: &Plane<f64>) -> String {
        let abcd = |p: &Plane<f64>| format!("{:.12},{:.12},{:.12},{:.9}", p.n.x, p.n.y, p.n.z, p.d);
        if self.current_deg == 0.0 {
            return format!("plane {}\n", abcd(seen));
        }
        let rz = nalgebra::Rotation3::from_axis_angle(
            &nalgebra::Vector3::z_axis(),
            self.current_deg.to_radians(),
        );
        let base = seen.transformed(rz.matrix(), &nalgebra::Vector3::zeros());
        format!("move {} {}\n", abcd(&base), self.current_deg)
    }

    /// Sets the estimated frame errors (after the calibration).
    pub fn set_frames(&mut self, f: Frames) {
        self.frames = f;
    }

    /// The tracker's plane corrected by the estimated frame errors.
    pub fn correct(&self, tracker: &Plane<f64>) -> Plane<f64> {
        corrected(tracker, self.current_deg, &self.frames)
    }
}

/// After the calibration of a `--reversal` run: the joint estimate from
/// `DIR/poses.csv`, its head written into `DIR/params.json`, the report
/// printed and written to `DIR/frames.json`, the frame errors the head was
/// corrected for handed to `turns` for the verification.
///
/// # Errors
/// Those of [`estimate_run`] and [`apply_head`], I/O.
pub fn after_calibration(
    sensors: &Path,
    out: &Path,
    turns: &mut Turns,
    expected_deg: f64,
) -> Result<FrameEstimates> {
    let (fit, summary) = estimate_run(
        sensors,
        &out.join("poses.csv"),
        turns.joints(),
        expected_deg,
    )?;
    apply_head(&out.join("params.json"), &fit)?;
    for l in perpend_calib::frames::report::lines(&summary) {
        println!("cell: {l}");
    }
    let path = out.join("frames.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("{}: cannot write", path.display()))?;
    turns.set_frames(fit.correction);
    Ok(summary)
}

/// The record of a `--reversal` run: the frame estimates of
/// `DIR/frames.json` and the parameters the joint estimate left in
/// `params` (unchanged when the run had no reversal).
///
/// # Errors
/// Unreadable files.
pub fn into_record(
    r: perpend_calib::record::Record,
    out: &Path,
    params: &Path,
) -> Result<perpend_calib::record::Record> {
    let path = out.join("frames.json");
    if !path.exists() {
        return Ok(r);
    }
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let f: FrameEstimates = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a frame report", path.display()))?;
    let mut r = r.with_frames(f);
    r.parameters = perpend_formats::paramfile::ParamFile::read(params)?.sensors;
    r.output = Some(perpend_calib::record::FileHash::of(params)?);
    Ok(r)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_calib::frames::plan::write_reversal;
    use perpend_calib::frames::{add_noise, frames_deg, readings};
    use perpend_calib::plan::PlannedPose;
    use perpend_formats::exchange::{write_poses, write_sensors, PoseRow, PoseTable, SensorTable};
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// A run on disk: nominal head, plan with reversal, captured poses of
    /// the true head under `frames`, 4 µm noise.
    fn run_files(dir: &Path, frames: &Frames, seed: u64) -> (HashMap<i64, f64>, FrameFit) {
        let mut rng = StdRng::seed_from_u64(seed);
        let head = perpend_calib::sim::random_head(&mut rng, 1.0, 0.03).unwrap();
        let base: Vec<PlannedPose> = (0..24)
            .map(|_| PlannedPose {
                tilt_x_deg: rng.gen_range(-10.0..10.0),
                tilt_y_deg: rng.gen_range(-10.0..10.0),
                standoff_mm: rng.gen_range(30.0..40.0),
            })
            .collect();
        let plan = dir.join("plan.csv");
        write_reversal(&plan, &base, 4).unwrap();
        let joints = read_joints(&plan).unwrap();
        let turned = perpend_calib::frames::plan::turned(&base, 4).unwrap();
        let fp: Vec<FramePose> = turned
            .iter()
            .map(|t| FramePose::seen(&t.pose.plane(), t.joint_deg.to_radians()))
            .collect();
        let clean = readings(&head.truth, &fp, frames);
        let meas = add_noise(&clean, 0.004, &mut rng);
        let rows = fp
            .iter()
            .zip(meas)
            .enumerate()
            .map(|(k, (p, r))| PoseRow {
                line: 0,
                pose: k as i64 + 1,
                abcd: [p.plane.n.x, p.plane.n.y, p.plane.n.z, p.plane.d],
                plane: p.plane,
                readings: r,
                t_s: None,
                temp_c: None,
                noise: Default::default(),
            })
            .collect();
        let table = PoseTable { n_sensors: 4, rows };
        let f = std::fs::File::create(dir.join("poses.csv")).unwrap();
        write_poses(f, &table, &[]).unwrap();
        let s = std::fs::File::create(dir.join("nominal.csv")).unwrap();
        write_sensors(s, &SensorTable::from_sensors(&head.nominal, None), &[]).unwrap();
        let (fit, _) = estimate_run(
            &dir.join("nominal.csv"),
            &dir.join("poses.csv"),
            &joints,
            0.003,
        )
        .unwrap();
        (joints, fit)
    }

    #[test]
    fn a_tilted_tracker_is_found_from_the_run_files_and_warned_about() {
        let dir = tempfile::tempdir().unwrap();
        let f = frames_deg([0.05, 0.0], [0.0; 2], [0.0; 2]);
        let (joints, fit) = run_files(dir.path(), &f, 5);
        assert_eq!(joints.len(), 96);
        let est = fit.frames[0].to_degrees();
        assert!((est - 0.05).abs() < 0.005, "{est}");
        let s = summarise(&fit, &[0.0, 90.0], 0.003);
        assert!(s.errors[0].significant && s.errors[0].unit == "µrad");
        assert!(
            s.warnings
                .iter()
                .any(|w| w.contains("re-register the tracker")),
            "{:?}",
            s.warnings
        );
        // the corrected tracker plane is what the head saw
        let tracker = Plane::from_abcd(0.0, 0.1, -1.0, 35.0).unwrap();
        let c = corrected(&tracker, 90.0, &fit.frames);
        let truth = corrected(&tracker, 90.0, &f);
        assert!(perpend_calib::calibrate::angle_deg(&c.n, &truth.n) < 0.005);
    }

    #[test]
    fn no_tilt_no_warning_and_a_plan_without_joints_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (_, fit) = run_files(dir.path(), &Frames::zeros(), 6);
        let s = summarise(&fit, &[0.0], 0.003);
        assert!(s.errors.iter().all(|e| !e.significant), "{:?}", s.errors);
        assert!(s.warnings.is_empty(), "{:?}", s.warnings);
        let plain = dir.path().join("plain.csv");
        std::fs::write(&plain, "pose,tilt_x_deg,tilt_y_deg,standoff_mm\n1,0,0,35\n").unwrap();
        let e = read_joints(&plain).unwrap_err().to_string();
        assert!(e.contains("perpend plan --reversal 4"), "{e}");
    }
}
